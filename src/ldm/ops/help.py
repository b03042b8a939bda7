"""Command-line help in one style for `ldm` and `laas`: every option shows its default.

`Parser` is an `argparse.ArgumentParser` whose help (and its subcommands' help, which
argparse builds with the same class) uses `DefaultsHelpFormatter`: an option's help ends
with ``(default: VALUE)`` unless it already says what its default is, or has none (no
value, a flag that is off, a list that starts empty). An option whose default comes from
an environment variable names it in its help itself (``env LAAS_CLUSTER``);
``tests/test_cli_conventions.py`` checks both for every option of both commands.
"""

from __future__ import annotations

import argparse
from importlib.metadata import PackageNotFoundError, version
from typing import Any

__all__ = ["DefaultsHelpFormatter", "Parser", "add_version", "no_default", "package_version"]


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Appends ``(default: %(default)s)`` to an option's help that does not name its default."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        default = action.default
        if (
            action.option_strings
            and "default" not in text.lower()
            and not no_default(default)
            and action.nargs != 0
        ):
            text += " (default: %(default)s)"
        return text


def no_default(default: object) -> bool:
    """True for a default that is no value: None, a flag's False, an empty list."""
    return default is None or default is False or default == [] or default == argparse.SUPPRESS


class Parser(argparse.ArgumentParser):
    """An ArgumentParser with `DefaultsHelpFormatter` (its subparsers too)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", DefaultsHelpFormatter)
        super().__init__(*args, **kwargs)


def package_version() -> str:
    """The installed version of the laas distribution (which holds ldm and laas)."""
    try:
        return version("laas")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def add_version(parser: argparse.ArgumentParser, program: str) -> None:
    """``--version``: print ``PROGRAM VERSION`` and exit."""
    parser.add_argument(
        "--version",
        action="version",
        version=f"{program} {package_version()}",
        help="print the version and exit",
    )
