"""The configuration reference of `laas` and `ldm`, made from their argument parsers.

    python scripts/cli_reference.py           # print the README's reference
    python scripts/cli_reference.py --write   # put it in README.md between its markers

The README holds every flag of every subcommand and every environment variable, each
variable with the flags it sets; `laas CMD --help` gives each flag's meaning and default.
tests/test_cli_reference.py fails while the README differs from what this prints.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

__all__ = ["OTHER_VARIABLES", "README", "commands", "reference", "variables"]

README = Path(__file__).resolve().parents[1] / "README.md"
START = "<!-- cli-reference: made by scripts/cli_reference.py; do not edit -->"
END = "<!-- cli-reference: end -->"
_VARIABLE = re.compile(r"\b(?:LAAS|LDM)_[A-Z0-9_]+\b")

OTHER_VARIABLES = {
    "LAAS_MAPS": "the folder of the bundled maps (`laas.load_map`, the default `--map`)",
    "LAAS_NO_JIT": "`1`: the engine's arithmetic runs uncompiled (slowly; for a debugger)",
    "LDM_MOSQUITTO": "the mosquitto binary the local deployments and tests start",
    "LDM_NATS_SERVER": "the nats-server binary (`ldm nats-cluster`, tests)",
    "LDM_REQUIRE_MOSQUITTO": "`1`: a test that needs Mosquitto fails instead of skipping",
    "LDM_REQUIRE_NATS": "`1`: a test that needs nats-server fails instead of skipping",
}
"""Variables no flag names: what each sets."""


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def commands() -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """("laas worker", its parser), ... for every subcommand, nested ones too."""
    from laas import cli as laas_cli
    from ldm import cli as ldm_cli

    def walk(prefix: str, parser: argparse.ArgumentParser) -> Iterator[tuple[str, Any]]:
        subs = _subcommands(parser)
        if not subs:
            yield prefix, parser
        for name, sub in subs.items():
            yield from walk(f"{prefix} {name}", sub)

    for tool, module in (("laas", laas_cli), ("ldm", ldm_cli)):
        build = getattr(module, "build_parser", None) or module._parser
        yield from walk(tool, build())


def _flags(parser: argparse.ArgumentParser) -> list[argparse.Action]:
    return [
        a
        for a in parser._actions
        if a.option_strings and not isinstance(a, argparse._HelpAction | argparse._VersionAction)
    ]


def _defaults() -> dict[str, object]:
    """``laas CMD --flag`` -> its default, for every flag, as the parsers build it now."""
    return {
        f"{command} {a.option_strings[-1]}": a.default
        for command, parser in commands()
        for a in _flags(parser)
    }


def variables() -> dict[str, list[str]]:
    """Each variable -> the flags it gives, ``laas CMD --flag``: those whose default changes
    when it is set (every ``os.environ`` read in src/), and those whose help or default
    names it (``--password-env``)."""
    src = Path(__file__).resolve().parents[1] / "src"
    read = re.compile(r"environ(?:\.get)?[(\[]\s*[\"']((?:LAAS|LDM)_[A-Z0-9_]+)")
    names = {n for f in src.rglob("*.py") for n in read.findall(f.read_text())}
    found: dict[str, list[str]] = {}
    for command, parser in commands():
        for action in _flags(parser):
            text = (
                f"{action.help or ''} {action.default if isinstance(action.default, str) else ''}"
            )
            for name in sorted(set(_VARIABLE.findall(text))):
                found.setdefault(name, []).append(f"{command} {action.option_strings[-1]}")
    base = _defaults()
    for name in sorted(names - set(found) - set(OTHER_VARIABLES)):
        os.environ[name] = "7"  # a valid int, float and text alike
        try:
            changed = [flag for flag, value in _defaults().items() if value != base[flag]]
        finally:
            del os.environ[name]
        if changed:
            found[name] = changed
    return dict(sorted(found.items()))


def _flag_list(parser: argparse.ArgumentParser) -> str:
    return " ".join(f"`{a.option_strings[-1]}`" for a in _flags(parser)) or "none"


def _positionals(parser: argparse.ArgumentParser) -> str:
    names = [a.metavar or a.dest for a in parser._actions if not a.option_strings]
    return " ".join(str(n).upper() for n in names if not isinstance(n, tuple))


def _sets(flags: list[str]) -> str:
    """ "`--cluster` of `laas` worker, simulate; ...": the flags, each with its commands."""
    by_flag: dict[str, dict[str, list[str]]] = {}
    for flag in flags:
        tool, command, option = flag.split(" ", 1)[0], *flag.split(" ", 1)[1].rsplit(" ", 1)
        by_flag.setdefault(option, {}).setdefault(tool, []).append(command)
    return "; ".join(
        f"`{option}` of " + ", ".join(f"`{tool}` {', '.join(cs)}" for tool, cs in tools.items())
        for option, tools in by_flag.items()
    )


@contextlib.contextmanager
def _no_variables() -> Iterator[None]:
    """No LAAS_ or LDM_ variable set while the block runs, so that defaults are the
    parsers' own; restored after."""
    saved = {n: v for n, v in os.environ.items() if n.startswith(("LAAS_", "LDM_"))}
    for name in saved:
        del os.environ[name]
    try:
        yield
    finally:
        os.environ.update(saved)


def reference() -> str:
    """The README's reference: the flags of each command, then every variable."""
    with _no_variables():
        return _reference()


def _reference() -> str:
    lines = [
        START,
        "| command | arguments | flags |",
        "|---|---|---|",
    ]
    for command, parser in commands():
        lines.append(f"| `{command}` | {_positionals(parser)} | {_flag_list(parser)} |")
    lines += [
        "",
        "| environment variable | the flag whose value it gives |",
        "|---|---|",
    ]
    named = variables()
    for name, flags in named.items():
        lines.append(f"| `{name}` | {_sets(flags)} |")
    for name, what in OTHER_VARIABLES.items():
        if name not in named:
            lines.append(f"| `{name}` | {what} |")
    lines.append(END)
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    text = reference()
    if argv[1:] != ["--write"]:
        sys.stdout.write(text)
        return 0
    readme = README.read_text()
    if START not in readme or END not in readme:
        print(f"{README}: no {START!r} ... {END!r} markers", file=sys.stderr)
        return 1
    head, rest = readme.split(START, 1)
    README.write_text(head + text.rstrip("\n") + rest.split(END, 1)[1])
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
