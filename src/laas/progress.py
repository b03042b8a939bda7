"""Progress of long runs, on stderr: rewritten in place on a terminal, about ten lines in a log."""

from __future__ import annotations

import sys
from collections.abc import Callable

__all__ = ["Progress", "progress_printer"]

Progress = Callable[[int, int], None]
"""Called with (done, total) as work completes."""


def progress_printer(label: str, unit: str) -> Progress:
    """A `Progress` that prints ``{label}: {done}/{total} {unit}``."""

    def show(done: int, total: int) -> None:
        tty = sys.stderr.isatty()
        if done == total or tty or done % max(1, total // 10) == 0:
            end = "\n" if done == total or not tty else "\r"
            print(f"{label}: {done}/{total} {unit}", end=end, file=sys.stderr, flush=True)

    return show
