"""The run as an operating-system service: signals, the control socket ``jetbot-rt stop`` talks
to, the runtime directory that socket lives in, systemd's notify protocol, and stdout and
stderr that never block. Robot side, Python 3.8; what an outside process or the OS can do to a
run arrives through here.
"""
