"""jetbot_rt: drive a JetBot (real or simulated) from an ONNX image policy, safely.

Importing this package loads neither torch nor pybullet; those live in ``jetbot_rt.train``
and ``jetbot_rt.sim`` and are imported only when a command needs them.
"""

__version__ = "0.1.0"
