"""PyBullet simulation of the JetBot: ``JetbotWorld`` and the ``sim`` HAL backend.

Importing this package imports pybullet; the runtime core never does (the backend registry
imports ``jetbot_rt.sim.backend`` only when ``--backend sim`` is asked for).
"""

from jetbot_rt.sim.world import JetbotWorld

__all__ = ["JetbotWorld"]
