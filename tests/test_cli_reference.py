"""The README's configuration reference is what the argument parsers say
(scripts/cli_reference.py made it), and names every variable the code reads."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def script() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "cli_reference", ROOT / "scripts" / "cli_reference.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_reference_is_what_the_parsers_say() -> None:
    made = script().reference()
    assert made in (ROOT / "README.md").read_text(), (
        "README.md's configuration reference is out of date: run "
        "`python scripts/cli_reference.py --write`"
    )


def test_every_variable_the_code_reads_is_in_the_reference() -> None:
    reference = script().reference()
    read = re.compile(r"environ(?:\.get)?[(\[]\s*[\"']((?:LAAS|LDM)_[A-Z0-9_]+)")
    names = {n for f in (ROOT / "src").rglob("*.py") for n in read.findall(f.read_text())}
    assert {"LAAS_MAP", "LAAS_LOG_LEVEL", "LDM_MOSQUITTO"} <= names
    assert [n for n in sorted(names) if f"`{n}`" not in reference] == []


def test_every_subcommand_and_flag_is_listed() -> None:
    module = script()
    reference = module.reference()
    for command, parser in module.commands():
        row = next(
            (line for line in reference.splitlines() if line.startswith(f"| `{command}` |")), None
        )
        assert row is not None, command
        for action in parser._actions:
            if action.option_strings and action.option_strings[-1] not in ("--help", "--version"):
                assert f"`{action.option_strings[-1]}`" in row, (command, action.option_strings)
