"""Reading what a user gives us: ``safe_file`` (open a file without following a trap: size
bounds, regular files only, atomic replace) and ``sections`` (the TOML file and flags to typed
dataclasses, checked). The bottom of the package beside ``errors``: everything may import it, it
imports nothing of the runtime.
"""
