"""Every `laas.` and `ldm.` dotted name that the docstrings, comments, docs and the
deployment files cite names something that exists (a module, or an object in one), and
the docs' maps of the tree name every module of each package they show."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOTTED = re.compile(r"(?<![\w./-])((?:laas|ldm)(?:\.[A-Za-z_]\w*)+)")
NOT_NAMES = {
    "laas.key",  # a key file in `ldm keys new laas.key`
    "laas.request",  # the README's example calls its session `laas`
    "laas.example.org",  # a host name in the examples of docs/operations.md
}
MAPS = ("docs/design.md", "docs/ldm.md")  # each has a map of src/ in a code block


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


def _cited_files() -> list[Path]:
    files = [*sorted((ROOT / "src").rglob("*.py")), *sorted((ROOT / "docs").rglob("*.md"))]
    files += [ROOT / "README.md", ROOT / "maps" / "README.md", ROOT / "Dockerfile"]
    files += sorted(ROOT.glob("docker-compose*.yml"))
    files += sorted(p for p in (ROOT / "deploy").rglob("*") if p.is_file())
    return files


def test_every_cited_dotted_name_exists() -> None:
    missing = [
        f"{path.relative_to(ROOT)}:{number}: {name}"
        for path in _cited_files()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        for name in (m.group(1).rstrip(".") for m in DOTTED.finditer(line))
        if name not in NOT_NAMES and not _resolves(name)
    ]
    assert missing == []


def _map_entries(doc: str) -> dict[Path, str]:
    """Each package a map shows (``src/ldm/``, then ``  wire/`` ...) -> the text of its
    entry: its line and the lines under it, up to the next package at its depth."""
    entries: dict[Path, str] = {}
    in_map = False
    stack: list[tuple[int, Path]] = []
    for line in (ROOT / doc).read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            in_map, stack = False, []
            continue
        if not stack and line.startswith("src/"):
            in_map = True
        if not in_map or not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        first, _, rest = line.strip().partition(" ")
        while len(stack) > 1 and stack[-1][0] >= indent:
            stack.pop()  # a package or module beside the last package, not in it
        if first.endswith("/"):
            if stack and stack[-1][0] >= indent:
                stack.pop()
            path = ROOT / first if not stack else stack[-1][1] / first
            stack.append((indent, path))
            entries[path] = rest
        else:
            entries[stack[-1][1]] += " " + line
    return entries


@pytest.mark.parametrize("doc", MAPS)
def test_the_docs_maps_name_every_module_of_the_packages_they_show(doc: str) -> None:
    entries = _map_entries(doc)
    assert entries, f"{doc} has no map of src/"
    unnamed = []
    for package, text in entries.items():
        assert package.is_dir(), f"{doc} maps {package.relative_to(ROOT)}, which is not there"
        while "(" in text:  # what a module holds, in parentheses, does not name a module
            text, n = re.subn(r"\([^()]*\)", " ", text)
            if not n:
                break
        words = set(re.findall(r"\w+", text)) | {p.name for p in entries if p.parent == package}
        modules = [p.stem for p in package.glob("*.py") if not p.stem.startswith("__")]
        modules += [p.name for p in package.iterdir() if (p / "__init__.py").is_file()]
        unnamed += [f"{package.relative_to(ROOT)}/{m}" for m in sorted(modules) if m not in words]
    assert unnamed == []
