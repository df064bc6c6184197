"""jetbot_rt: drive a JetBot (real or simulated) from an ONNX image policy, safely.

Importing this package loads neither torch nor pybullet; those live in ``jetbot_rt.train``
and ``jetbot_rt.sim`` and are imported only when a command needs them.
"""

__version__ = "0.1.0"

import sys as _sys

if "gymnasium" in _sys.modules:
    # gymnasium.make("jetbot_rt:JetbotForward-v0") imports this package to find the id;
    # registering only when gymnasium is already loaded keeps `import jetbot_rt` light.
    from jetbot_rt.train.registration import register_envs as _register_envs

    _register_envs()
