"""The architecture's rules, checked on the source: what may import what, and the public API."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import laas
from laas import ConfigError, EngineConfig
from laas.worker.service import WorkerConfig

SRC = Path(__file__).resolve().parent.parent / "src"

# The engine and the map are pure: no MQTT, no LDM, no pictures, no command line.
PURE = ("laas/engine", "laas/map")
FORBIDDEN_IN_PURE = (
    "ldm",
    "paho",
    "amqtt",
    "matplotlib",
    "laas.cli",
    "laas.worker",
    "laas.run",
)


def _imports(path: Path) -> set[str]:
    """Every module a file imports, lazily or not."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return found


def _offending(folder: str, forbidden: tuple[str, ...]) -> list[str]:
    bad = []
    for path in sorted((SRC / folder).rglob("*.py")):
        for name in sorted(_imports(path)):
            if any(name == f or name.startswith(f + ".") for f in forbidden):
                bad.append(f"{path.relative_to(SRC)} imports {name}")
    return bad


@pytest.mark.parametrize("folder", PURE)
def test_the_engine_and_the_map_import_no_transport_pictures_or_cli(folder: str) -> None:
    assert _offending(folder, FORBIDDEN_IN_PURE) == []


def test_the_ldm_never_imports_laas() -> None:
    assert _offending("ldm", ("laas",)) == []


def test_what_makes_traces_never_imports_what_judges_answers() -> None:
    """`laas.sim` makes traces and replays them; `laas.evaluation` judges the answers,
    and builds on `laas.sim`, never the other way."""
    assert _offending("laas/sim", ("laas.evaluation",)) == []


def test_no_library_module_imports_a_command_line() -> None:
    """The command lines are thin faces: what both need lives in library modules. Only
    the `laas.cli` package's own modules and ``python -m ldm`` import them."""

    def in_a_command_line(path: Path) -> bool:
        name = path.relative_to(SRC).as_posix()
        return name.startswith("laas/cli/") or name == "ldm/__main__.py"

    users = [
        f"{p.relative_to(SRC)} imports {n}"
        for p in sorted(SRC.rglob("*.py"))
        for n in sorted(_imports(p))
        if any(n == cli or n.startswith(cli + ".") for cli in ("ldm.cli", "laas.cli"))
        and not in_a_command_line(p)
    ]
    assert users == []


def _module(path: Path) -> str:
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_no_modules_import_each_other() -> None:
    """No import circle, lazy imports included: a module that needs another's reader or
    subclasses is not needed by it (an import inside a function hides a circle, it does
    not open it)."""
    modules = {_module(p): p for p in SRC.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        found = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                for alias in node.names:
                    full = f"{node.module}.{alias.name}"
                    found.add(full if full in modules else node.module)
            elif isinstance(node, ast.Import):
                found.update(alias.name for alias in node.names)
        graph[name] = {m for m in found if m in modules and m != name}

    def reaches(start: str, goal: str) -> bool:
        seen, todo = set(), [start]
        while todo:
            here = todo.pop()
            if here == goal:
                return True
            if here not in seen:
                seen.add(here)
                todo.extend(graph[here])
        return False

    circles = sorted(f"{a} <-> {b}" for a in graph for b in graph[a] if a < b and reaches(b, a))
    assert circles == []


def test_paho_lives_in_the_transport_package_only() -> None:
    users = [
        str(p.relative_to(SRC))
        for p in sorted(SRC.rglob("*.py"))
        if any(n == "paho" or n.startswith("paho.") for n in _imports(p))
    ]
    assert users == ["ldm/transport/mqtt.py"]


# What each of the LDM's subpackages may import from the rest of the LDM: the wire and
# the keys at the bottom, the transport beside them, the three roles (client, core,
# provider) on top of those and never of each other, then operations and local brokers.
LDM_LAYERS = {
    "wire": ("errors",),
    "security": ("errors", "wire"),
    "transport": ("config", "errors"),
    "client": ("config", "errors", "security", "transport", "wire"),
    "core": ("config", "errors", "security", "transport", "wire"),
    "provider": ("config", "errors", "security", "transport", "wire"),
    "ops": ("config", "core", "errors", "provider", "transport"),
    "local": ("client", "config", "core", "errors", "provider", "transport", "wire"),
}


@pytest.mark.parametrize("package", sorted(LDM_LAYERS))
def test_each_ldm_package_imports_only_the_layers_below_it(package: str) -> None:
    allowed = tuple(f"ldm.{name}" for name in (package, *LDM_LAYERS[package]))
    bad = [
        f"{path.relative_to(SRC)} imports {name}"
        for path in sorted((SRC / "ldm" / package).rglob("*.py"))
        for name in sorted(_imports(path))
        if name.startswith("ldm.")
        and not any(name == a or name.startswith(a + ".") for a in allowed)
    ]
    assert bad == []


def test_the_ldm_tree_is_its_architecture() -> None:
    top = sorted(p.name for p in (SRC / "ldm").iterdir() if not p.name.startswith("__"))
    assert top == [*sorted(["cli.py", "config.py", "errors.py", "py.typed", *LDM_LAYERS])]


def test_importing_the_engine_loads_no_transport() -> None:
    code = (
        "import sys, laas, laas.engine, laas.map, laas.map.geojson, laas.map.mapgen;"
        "print(' '.join(sorted(m for m in sys.modules if m.split('.')[0] in "
        "('ldm', 'paho', 'amqtt', 'matplotlib'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_the_public_api_is_pinned() -> None:
    assert sorted(laas.__all__) == [
        "AsyncClient",
        "Client",
        "ClientError",
        "ConfigError",
        "CorrectedPosition",
        "Engine",
        "EngineConfig",
        "EngineStats",
        "ErrorReply",
        "FixRefused",
        "GpsMeasurement",
        "HdMap",
        "KeepingQuiet",
        "LaasError",
        "Lane",
        "LaneType",
        "MapError",
        "Mode",
        "NoAnswer",
        "Segment",
        "ServiceUnavailable",
        "TraceError",
        "UntrustedService",
        "__version__",
        "load_map",
        "read_reply",
    ]
    for name in laas.__all__:
        assert getattr(laas, name) is not None


@pytest.mark.parametrize(
    ("make", "setting"), [(EngineConfig, "sigma_pos"), (WorkerConfig, "max_past")]
)
def test_a_bad_setting_is_a_config_error_that_names_it(make: type, setting: str) -> None:
    with pytest.raises(ConfigError, match=f"invalid {make.__name__}: {setting}: ") as info:
        make(**{setting: -1.0})
    assert isinstance(info.value, laas.LaasError)
    with pytest.raises(ConfigError, match="colour: Extra inputs are not permitted"):
        make(colour="red")
