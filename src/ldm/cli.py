"""The `ldm` command line."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

__all__ = ["main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the `ldm` command line and return its exit status."""
    parser = argparse.ArgumentParser(prog="ldm", description=__doc__)
    parser.parse_args(argv)
    parser.print_help()
    return 0
