"""Where each process spends its CPU: py-spy sampling profiles, recorded and summed up.

`laas bench --profile DIR` attaches one ``py-spy record`` to every process of the system
under test but the brokers (the cores, which share the bench's own process, the worker
and the participant processes) for the seconds of the load, and writes each raw profile
to DIR as ``KIND-PID.txt`` in py-spy's collapsed-stack format (one line per distinct
stack, ``frame;frame;...;frame COUNT``, frames as ``function (file)``): the input of
flame-graph tools, or of `summarise` here. Idle threads are not sampled, so the shares
are of the process's active time (on all its threads together).

Per process, the entries are
    own     the share of samples where the function is the innermost frame
    total   the share of samples where it is on the stack at all (once per sample)
and `format_profiles` prints the top entries by own time, with their total beside, then
the project's own functions (``laas``, ``ldm``) by total time: where the time goes
inclusive of what they call.

py-spy reads the target's memory from outside (no code change, no slowdown of the
target beyond the reading); it needs the right to trace the process (root, or
``kernel.yama.ptrace_scope`` 0, or CAP_SYS_PTRACE in a container).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from laas.errors import ConfigError

__all__ = [
    "Entry",
    "Profile",
    "Recorder",
    "find_py_spy",
    "format_profiles",
    "read_profile",
    "summarise",
]

_RATE = 100  # samples per second


def find_py_spy() -> str:
    """The py-spy executable: beside this Python (a venv's bin), else on PATH."""
    beside = Path(sys.executable).parent / "py-spy"
    if beside.exists():
        return str(beside)
    found = shutil.which("py-spy")
    if found is None:
        raise ConfigError("--profile needs py-spy: pip install py-spy (in the dev extra)")
    return found


@dataclass(frozen=True)
class Entry:
    """A function and its share of the process's samples: innermost, and on the stack."""

    function: str
    own: float
    total: float


@dataclass(frozen=True)
class Profile:
    """One process's profile: its label (``KIND-PID``), samples, the top entries by own
    time, and the project's own functions (``laas``, ``ldm``) by total time."""

    label: str
    samples: int
    entries: list[Entry]
    inclusive: list[Entry]


class Recorder:
    """One ``py-spy record`` per process, all for `seconds`, raw profiles into `folder`."""

    def __init__(self, folder: Path, seconds: float) -> None:
        self.folder = folder
        self.seconds = seconds
        self._spies: list[tuple[str, subprocess.Popen[bytes]]] = []
        folder.mkdir(parents=True, exist_ok=True)
        self._exe = find_py_spy()

    def start(self, processes: Mapping[int, str]) -> None:
        """Attach to each pid -> kind (a kind of ``brokers`` is skipped)."""
        for pid, kind in processes.items():
            if kind == "brokers":
                continue
            label = f"{kind}-{pid}"
            log = (self.folder / f"{label}.log").open("wb")
            spy = subprocess.Popen(
                [
                    self._exe,
                    "record",
                    "--pid",
                    str(pid),
                    "--duration",
                    str(max(1, round(self.seconds))),
                    "--rate",
                    str(_RATE),
                    "--format",
                    "raw",
                    "--nolineno",
                    "--nonblocking",
                    "--output",
                    str(self.folder / f"{label}.txt"),
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
            )
            log.close()
            self._spies.append((label, spy))

    def stop(self, timeout: float = 30.0) -> list[str]:
        """Wait for every recorder to write its file (stopping those that overrun);
        the labels whose profile is missing."""
        missing = []
        for label, spy in self._spies:
            try:
                spy.wait(timeout)
            except subprocess.TimeoutExpired:
                spy.terminate()
                spy.wait(5.0)
            if not (self.folder / f"{label}.txt").exists():
                missing.append(label)
        return missing


def read_profile(path: Path) -> Counter[tuple[str, ...]]:
    """A raw (collapsed-stack) profile: samples by stack, outermost frame first."""
    stacks: Counter[tuple[str, ...]] = Counter()
    for line in path.read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if stack and count.isdigit():
            stacks[tuple(stack.split(";"))] += int(count)
    return stacks


def _short(frame: str) -> str:
    """``function (path/to/module.py)`` shortened to the package path from ``laas/``,
    ``ldm/`` or ``site-packages/`` on."""
    name, _, where = frame.partition(" (")
    where = where.rstrip(")")
    for root in ("site-packages/", "/laas/", "/ldm/", "/lib/python"):
        at = where.rfind(root)
        if at >= 0:
            where = where[at + 1 :] if root.startswith("/") else where[at + len(root) :]
            break
    return f"{name} ({where})" if where else name


def summarise(stacks: Counter[tuple[str, ...]], label: str, top: int = 10) -> Profile:
    """The top entries by own time, the first stacks' process and thread frames aside."""
    samples = sum(stacks.values())
    own: Counter[str] = Counter()
    total: Counter[str] = Counter()
    for stack, count in stacks.items():
        frames = [_short(f) for f in stack if not f.startswith(("process ", "thread "))]
        if not frames:
            continue
        own[frames[-1]] += count
        for frame in dict.fromkeys(frames):  # once per sample, in stack order
            total[frame] += count
    n = max(samples, 1)
    entries = [Entry(f, c / n, total[f] / n) for f, c in _top(own, top)]
    ours = Counter({f: c for f, c in total.items() if f.endswith(".py)") and _ours(f)})
    inclusive = [Entry(f, own[f] / n, c / n) for f, c in _top(ours, top)]
    return Profile(label, samples, entries, inclusive)


def _top(counts: Counter[str], top: int) -> list[tuple[str, int]]:
    """The `top` largest counts, ties by name (the same order every run)."""
    return sorted(counts.items(), key=lambda item: (-item[1], item[0]))[:top]


def _ours(frame: str) -> bool:
    """Whether a shortened frame is the project's: in ``laas/`` or ``ldm/``."""
    return " (laas/" in frame or " (ldm/" in frame


def profiles(folder: Path, top: int = 10) -> list[Profile]:
    """Every raw profile in `folder`, summed up, in the order cores, worker, participants."""
    order = {"cores": 0, "worker": 1, "participants": 2}
    found = []
    for path in sorted(folder.glob("*.txt")):
        found.append(summarise(read_profile(path), path.stem, top))
    return sorted(found, key=lambda p: (order.get(p.label.split("-")[0], 9), p.label))


def format_profiles(found: Sequence[Profile], folder: Path | None = None) -> str:
    """Per process, its top entries: own share, total share, function (module)."""
    lines = [
        f"profiles (py-spy, {_RATE} Hz, active time only"
        + (f"; raw in {folder})" if folder else ")")
    ]
    for p in found:
        lines.append(f"  {p.label}: {p.samples} samples")
        lines.append("     own  total  function")
        for e in p.entries:
            lines.append(f"    {e.own:4.0%}  {e.total:5.0%}  {e.function}")
        if p.inclusive:
            lines.append("     own  total  the project's own functions, by total")
            for e in p.inclusive:
                lines.append(f"    {e.own:4.0%}  {e.total:5.0%}  {e.function}")
    return "\n".join(lines)
