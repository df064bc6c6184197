"""The tick path: a frame in, a duty out, and what stops the motors when that goes wrong.

``policy`` (load an ONNX model, prepare a frame, infer) -> ``actions`` (mu to duties) ->
``loop`` (the fixed-rate tick) with ``safety`` (the stop latch, the guarded drive, the
watchdog) around it. Everything here is safety-critical, runs on the robot's Python 3.8 and
imports only ``config``, ``errors`` and ``hal`` below it.
"""
