"""Every `laas.` and `ldm.` dotted name that the docstrings, comments and docs cite
names something that exists (a module, or an object in one)."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOTTED = re.compile(r"(?<![\w./-])((?:laas|ldm)(?:\.[A-Za-z_]\w*)+)")
NOT_NAMES = {
    "laas.key",  # a key file in `ldm keys new laas.key`
    "laas.request",  # the README's example calls its session `laas`
}


def _resolves(name: str) -> bool:
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return False
            obj = getattr(obj, attr)
        return True
    return False


def test_every_cited_dotted_name_exists() -> None:
    files = [*sorted((ROOT / "src").rglob("*.py")), *sorted((ROOT / "docs").rglob("*.md"))]
    files += [ROOT / "README.md", ROOT / "maps" / "README.md"]
    missing = [
        f"{path.relative_to(ROOT)}:{number}: {name}"
        for path in files
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        for name in (m.group(1).rstrip(".") for m in DOTTED.finditer(line))
        if name not in NOT_NAMES and not _resolves(name)
    ]
    assert missing == []
