"""Hardware abstraction: ``Camera`` and ``Drive`` interfaces and the backend factory."""

from jetbot_rt.hal.base import Backend, Camera, Drive, Frame
from jetbot_rt.hal.registry import BackendOptions, make_backend

__all__ = ["Backend", "BackendOptions", "Camera", "Drive", "Frame", "make_backend"]
