"""PyBullet simulation of the JetBot: ``world.JetbotWorld``, the ``sim`` HAL backend, the tasks
and the domain randomization.

The modules that import pybullet are imported by name (the backend registry imports
``jetbot_rt.sim.backend`` only when ``--backend sim`` is asked for); this package itself imports
nothing, so that ``Config`` can read the ``[sim]`` schema (``sim.config``) on the robot.
"""
