"""The subcommands of ``jetbot-rt``, one module each with ``add_arguments(parser)`` and
``run(args) -> exit code``; ``jetbot_rt.cli`` imports only the one that runs, so ``stop`` (what
systemd runs after a crash) loads neither onnxruntime nor the camera code.

- ``run``: drive the robot or the simulation (``Runtime``, its start-up phases);
  ``shutdown``: the run's stop phase and its summary.
- ``stop``: the hardware stop, and every runtime asked to latch its safe stop.
- ``check``: the self-test of a newly assembled robot.
- ``install_service``: the systemd unit and a default config.
- ``replay`` and ``report``: a recording looked at offline.

The parts they assemble are the core (``jetbot_rt/*.py``: config, policy, actions, loop,
safety, telemetry, ...), the hardware (``jetbot_rt/hal``) and the simulation (``jetbot_rt/sim``).
"""
