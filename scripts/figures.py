"""Re-run the quick figure commands and print each quoted figure beside its value now.

Every figure the README and docs/ quote comes from a command named beside it. This
script runs the quick ones (each a test that prints its figure, `pytest -s`), reads the
figure from the output, and prints, per figure: where it is quoted, what is quoted
there, what the command prints now, and the command. A drift shows as a difference
between the two columns (nothing here fails on a difference: a figure measured on a
loaded machine moves). A quote no longer found in its document is marked, so that the
table here follows the docs.

    .venv/bin/python scripts/figures.py             # the quick figures (about a minute)
    .venv/bin/python scripts/figures.py --list      # what it knows, nothing run
    .venv/bin/python scripts/figures.py --only karlsruhe-import   # one (the fastest)

Slower figures (the NATS failover runs, `laas evaluate`, `laas bench`) are listed with
`--list` and run only when named with `--only`.
"""

from __future__ import annotations

import argparse
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PYTEST = [sys.executable, "-m", "pytest", "-q", "-s", "-p", "no:cacheprovider", "-n", "0"]


@dataclass(frozen=True)
class Figure:
    name: str
    doc: str  # the file that quotes it, from the repository root
    quoted: str  # the text quoted there (found verbatim, or the figure is marked)
    command: tuple[str, ...]  # run from the repository root
    pattern: str  # a regular expression on the output; its groups are the figure now
    quick: bool = True  # run by default (else only with --only)

    def shown_command(self) -> str:
        args = list(self.command)
        if args[: len(PYTEST)] == PYTEST:
            args = [".venv/bin/pytest", "-q", "-s", *args[len(PYTEST) :]]
        return shlex.join(args)


FIGURES = (
    Figure(
        "karlsruhe-import",
        "docs/maps/lanelet2.md",
        "It imports in about 1.3 s on one core",
        (*PYTEST, "tests/test_import_lanelet2.py", "-k", "karlsruhe_imports"),
        r"Karlsruhe imported in ([\d.]+ s)",
    ),
    Figure(
        "opendrive-curves-import",
        "docs/maps/opendrive.md",
        "| 4 border lanes | 0.13 s |",
        (*PYTEST, "tests/test_import_opendrive.py", "-k", "samples_import and curves"),
        r"curves: imported in ([\d.]+ s)",
    ),
    Figure(
        "standby-takeover",
        "README.md",
        "answers resume 0.21–0.22 s after the kill",
        (*PYTEST, "tests/test_regions.py", "-k", "standby"),
        r"answers resumed ([\d.]+ s) after the worker died",
    ),
    Figure(
        "border-accuracy",
        "README.md",
        "lane accuracy 0.993 with two regional workers against 0.993 with one",
        (*PYTEST, "tests/test_regions.py", "-k", "across_the_border"),
        r"lane accuracy ([\d.]+) with two workers .*?, ([\d.]+) with one",
    ),
    Figure(
        "quorum-loss-error",
        "docs/brokers.md",
        "failed so within 1.5-1.6 s of the loss",
        (*PYTEST, "tests/ldm/test_nats.py", "-k", "quorum"),
        r"longest wait ([\d.]+ s)",
    ),
    Figure(
        "nats-failover-qos1",
        "docs/brokers.md",
        "| slowest reply of an input sent around the failure | 5.2–11.9 s",
        (*PYTEST, "tests/ldm/test_nats.py", "-k", "killing_a_node_while_qos1"),
        r"lost (\d+), refused by the user core (\d+).*?slowest reply ([\d.]+ s)",
        quick=False,
    ),
)


def quoted_in_doc(figure: Figure) -> bool:
    path = ROOT / figure.doc
    return path.exists() and figure.quoted in path.read_text()


def measure(figure: Figure) -> str:
    """Run the figure's command; its figure now, or why there is none."""
    try:
        out = subprocess.run(
            figure.command, cwd=ROOT, capture_output=True, text=True, timeout=600, check=False
        )
    except subprocess.TimeoutExpired:
        return "(no figure: the command ran over 600 s)"
    found = re.search(figure.pattern, out.stdout)
    if found is None:
        tail = (out.stdout + out.stderr).strip().splitlines()[-1:] or ["no output"]
        return f"(no figure: exit {out.returncode}, {tail[0][:120]})"
    return ", ".join(found.groups())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", metavar="NAME", help="run these (repeat)")
    parser.add_argument("--list", action="store_true", help="list the figures, run nothing")
    a = parser.parse_args(argv)
    known = {f.name: f for f in FIGURES}
    unknown = sorted(set(a.only or ()) - set(known))
    if unknown:
        parser.error(f"no figure named {', '.join(unknown)}; known: {', '.join(known)}")
    chosen = [known[n] for n in a.only] if a.only else [f for f in FIGURES if f.quick]
    for f in FIGURES if a.list else chosen:
        where = f.doc if quoted_in_doc(f) else f"{f.doc} (QUOTE NOT FOUND)"
        now = "-" if a.list else measure(f)
        print(f"{f.name}\n  quoted  {f.quoted!r} in {where}\n  now     {now}")
        print(f"  command {f.shown_command()}" + ("" if f.quick else "  (slow: --only)"))
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
