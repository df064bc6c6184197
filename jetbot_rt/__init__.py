"""jetbot_rt: drive a JetBot (real or simulated) from an ONNX image policy, safely.

Importing this package loads neither torch nor pybullet; those live in ``jetbot_rt.train``
and ``jetbot_rt.sim`` and are imported only when a command needs them.
"""

__version__ = "0.1.0"

import sys as _sys


def _register_envs() -> None:
    from jetbot_rt.train.registration import register_envs

    register_envs()


# gymnasium.make("jetbot_rt:JetbotForward-v0") imports this package to find the id, and an
# import of a package already imported runs nothing: the ids are registered now if gymnasium
# is loaded, else once it is (whatever imports it, and whenever). `import jetbot_rt` itself
# stays light: gymnasium is never imported here (the robot has none).
if "gymnasium" in _sys.modules:
    _register_envs()
else:
    from jetbot_rt._after_import import AfterImport as _AfterImport

    _AfterImport("gymnasium", _register_envs).install()
