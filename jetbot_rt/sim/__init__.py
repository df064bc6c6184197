"""PyBullet simulation of the JetBot: ``world.JetbotWorld`` (which builds a task's scene,
``jetbot_rt.tasks``), the ``sim`` HAL backend and the domain randomization.

The modules that import pybullet are imported by name (the backend registry imports
``jetbot_rt.sim.backend`` only when ``--backend sim`` is asked for); this package itself imports
nothing, so that ``Config`` can read the ``[sim]`` schema (``sim.config``) on the robot.
"""
