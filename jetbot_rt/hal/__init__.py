"""Hardware abstraction: ``Camera`` and ``Drive`` interfaces, the ``Robot`` that holds them, and
the backend factory."""

from jetbot_rt.hal.base import Camera, Drive, Frame, Robot
from jetbot_rt.hal.registry import BackendOptions, make_backend

__all__ = ["BackendOptions", "Camera", "Drive", "Frame", "Robot", "make_backend"]
