"""What a run leaves behind, and reading it back.

``telemetry`` (one JSON line per tick, written in a thread of its own), ``recorder`` (the
run's side of a recording: hands frames and ticks to the writer process, never waits for it),
``writer_process`` (the child process that encodes and writes them to disk) and ``reader``
(opens a recording for ``replay`` and ``report``, trusting nothing in it). Robot side, Python
3.8; nothing here can hold up a tick or a stop.
"""
