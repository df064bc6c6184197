"""The argument parser both command lines use (``jetbot-rt`` and ``jetbot-train``): a usage
error is one line and exit code 2, and each option's default is shown. It sits below both CLIs
so neither imports the other for it."""

from __future__ import annotations

import argparse
from typing import Any

from jetbot_rt.errors import EXIT_USAGE


class HelpFormatter(argparse.HelpFormatter):
    """Shows each option's default where it has one and the help does not already say it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            action.option_strings
            and default not in (None, False, argparse.SUPPRESS)
            and "default" not in text
        ):
            text += " (default: %(default)s)"
        return text


def plain(text: str) -> str:
    """A docstring line for ``--help``: without reStructuredText's double backquotes."""
    return text.replace("``", "")


class OneLineParser(argparse.ArgumentParser):
    """argparse, but a usage error is one line and exit code 2, and defaults are shown."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}\n")
