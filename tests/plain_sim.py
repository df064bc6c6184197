"""The simulator without its default fisheye lens and appearance families, for the tests of
plumbing that never look at what the frames show: the trainer's workers, checkpoints, Ctrl-C,
Ray, the CLI's errors. ``[sim] lens = "pinhole"`` renders the frame at its size instead of a
wider one remapped; ``[randomize] appearance = false`` builds no textures, clutter or lamps at a
reset. Measured on the 2-core VM, a randomized seek env at 56x56: a step 4.4 -> 2.2 ms, a reset
27 -> 8 ms. The looks, the lens and the bundled policies' quality keep the defaults in their own
tests (test_appearance_families.py, test_lens.py, test_seek.py, test_task_follow_avoid.py)."""

from __future__ import annotations

from pathlib import Path

PLAIN_SIM = '[sim]\nlens = "pinhole"\n\n[randomize]\nappearance = false\n'
"""The two tables as a config file's text."""


def plain_config():  # -> jetbot_rt.config.sections.Config
    from jetbot_rt.config.sections import from_dict

    return from_dict({"sim": {"lens": "pinhole"}, "randomize": {"appearance": False}})


def plain_sim_file(directory: Path, extra: str = "") -> Path:
    """``PLAIN_SIM`` (and ``extra``, more tables) as ``directory/plain.toml``."""
    path = Path(directory) / "plain.toml"
    path.write_text(PLAIN_SIM + extra)
    return path
