"""`scripts/figures.py`: the quoted figures beside their values now (the fastest one is
run here; the whole table is a command, `python scripts/figures.py`)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scripts" / "figures.py"


def test_the_fastest_figure_is_measured_beside_its_quote() -> None:
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--only", "karlsruhe-import"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    ).stdout
    assert "quoted  'It imports in about 1.3 s on one core' in docs/maps/lanelet2.md\n" in out
    now = re.search(r"\n  now     ([\d.]+) s\n", out)
    assert now is not None, out  # a figure, not "(no figure: ...)"
    assert "command .venv/bin/pytest -q -s tests/test_import_lanelet2.py" in out


def test_every_figure_quoted_in_docs_is_still_there() -> None:
    """The quotes the script compares are in docs/ verbatim (README's are marked by the
    script when they are gone, not failed here: the README is rewritten elsewhere)."""
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--list"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    ).stdout
    missing = [line for line in out.splitlines() if "docs/" in line and "QUOTE NOT FOUND" in line]
    assert missing == [], missing
    assert out.count("\n  command ") >= 6
