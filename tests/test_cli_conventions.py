"""The conventions of both command lines, `laas` and `ldm`: `--version`; help for every
argument and subcommand; every option's default shown, and the environment variable a
default comes from named; errors on stderr; one spelling for per-device accounts."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from laas.cli import build_parser as laas_parser
from laas.cli import main as laas_main
from ldm.cli import _parser as ldm_parser
from ldm.cli import main as ldm_main
from ldm.ops.help import no_default, package_version

SRC = Path(__file__).resolve().parent.parent / "src"


def parsers() -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """Every parser of both commands, subcommands and theirs included, by its name."""
    todo = [laas_parser(), ldm_parser()]
    while todo:
        parser = todo.pop()
        yield parser.prog, parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                todo += list(action.choices.values())


def options(parser: argparse.ArgumentParser) -> Iterator[argparse.Action]:
    for action in parser._actions:
        if not isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            yield action


def test_both_commands_print_their_version(capsys: pytest.CaptureFixture[str]) -> None:
    for main, name in ((laas_main, "laas"), (ldm_main, "ldm")):
        with pytest.raises(SystemExit) as exited:
            main(["--version"])
        assert exited.value.code == 0
        assert capsys.readouterr().out.strip() == f"{name} {package_version()}"
    assert re.fullmatch(r"\d+\.\d+\.\d+.*", package_version())


def test_every_argument_and_subcommand_has_help() -> None:
    missing = []
    for prog, parser in parsers():
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                missing += [f"{prog} {c.dest}" for c in action._choices_actions if not c.help]
            elif not action.help or action.help == argparse.SUPPRESS:
                missing.append(f"{prog} {'/'.join(action.option_strings) or action.dest}")
    assert missing == []


def test_every_option_shows_its_default() -> None:
    hidden = []
    for prog, parser in parsers():
        formatter = parser._get_formatter()
        for action in options(parser):
            if action.option_strings and not no_default(action.default) and action.nargs != 0:
                text = formatter._expand_help(action)
                if "default" not in text.lower():
                    hidden.append(f"{prog} {action.option_strings[0]}: {text}")
    assert hidden == []
    # the formatter says it where the help does not
    worker = dict(parsers())["laas worker"].format_help()
    assert re.search(r"--sigma-pos SIGMA_POS\s+receiver position noise, m \(default: 1.0\)", worker)
    # a default of 0 is a default
    simulate = dict(parsers())["laas simulate"].format_help()
    assert re.search(r"--seed SEED\s+seed of the GNSS errors .*\s*\(default: 0\)", simulate)


def environment_variables() -> set[str]:
    names: set[str] = set()
    for path in [*SRC.glob("laas/**/*.py"), *SRC.glob("ldm/**/*.py")]:
        text = path.read_text()
        names |= set(re.findall(r"\b(?:LAAS|LDM)_[A-Z0-9_]+\b", text))
        for suffix in re.findall(r"\{\w*prefix\w*\}_([A-Z0-9_]+)", text):  # f"{prefix}_X"
            names |= {f"LAAS_{suffix}", f"LDM_{suffix}"}
    return names


def defaults() -> dict[tuple[str, str], object]:
    return {
        (prog, action.dest): action.default
        for prog, parser in parsers()
        for action in options(parser)
    }


def test_every_default_read_from_the_environment_names_its_variable(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    names = environment_variables()
    assert {"LAAS_CLUSTER", "LAAS_MAP", "LDM_METRICS_PORT"} <= names
    for name in names:
        monkeypatch.delenv(name, raising=False)
    baseline = defaults()
    helps = {(prog, a.dest): a.help or "" for prog, p in parsers() for a in options(p)}
    undocumented = []
    for name in sorted(names):
        monkeypatch.setenv(name, "7")
        for key, default in defaults().items():
            if default != baseline[key] and name not in helps[key]:
                undocumented.append(f"{key[0]} {key[1]}: {name}")
        monkeypatch.delenv(name)
    assert undocumented == []


def test_errors_go_to_stderr(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("LAAS_CLUSTER", raising=False)
    assert laas_main(["owntracks"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("laas owntracks: give the user-cluster broker")
    assert ldm_main(["core", "--name", "x", "--cluster", "ftp://nowhere:1"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith("ldm core: ")
    with pytest.raises(SystemExit):
        laas_main(["worker", "--no-such-flag"])
    out, err = capsys.readouterr()
    assert out == "" and "unrecognized arguments: --no-such-flag" in err


def test_one_spelling_for_per_device_accounts() -> None:
    """simulate, gpsd, owntracks and cam: --device-accounts, the password in the variable
    --device-password-env names (default LAAS_DEVICE_PASSWORD); no other spelling."""
    by_name = dict(parsers())
    for command in ("simulate", "gpsd", "owntracks", "cam"):
        parser = by_name[f"laas {command}"]
        flags = {s: a for a in options(parser) for s in a.option_strings}
        assert isinstance(flags["--device-accounts"], argparse._StoreTrueAction), command
        assert flags["--device-password-env"].default == "LAAS_DEVICE_PASSWORD", command
        accounts = {s for s in flags if "account" in s} - {"--list-accounts"}
        assert accounts == {"--device-accounts"}, command


def test_simulate_names_its_device_accounts_with_the_prefix(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert laas_main(["simulate", "--list-accounts", "--prefix", "sim-"]) == 0
    assert capsys.readouterr().out.split() == ["sim-car", "sim-cyclist-1", "sim-cyclist-2"]
