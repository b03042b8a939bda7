"""`laas worker --processes N`: one worker node using all its cores.

The map is cut into N regions (`laas.worker.regions`) and each is served by a `laas worker
--region K/N` child process, so each process owns the common-error areas and the road
elements of its strip, and participants route their fixes to it by position
(`ldm.client.routing.RoutedSession`). All children serve under one identity (participants pin
`laas` to it): the key file given with ``--identity``, or one made for this
run. Ports given for metrics or the live map are numbered on: child K gets port + K - 1
(0 stays 0, a free port each). The supervisor ends every child when it is told to stop
or when one of them exits.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from laas.errors import ConfigError
from ldm.security.identity import SigningKey

__all__ = ["child_argv", "serve_processes"]

_PORTS = ("--metrics-port", "--http")
_DROP = ("--processes", "--region", "--identity", *_PORTS)


def child_argv(argv: Sequence[str], k: int, count: int, identity: Path) -> list[str]:
    """The `laas worker` arguments of child `k` (0-based) of `count`: `argv` without
    the options the supervisor sets, then its region, identity and ports."""
    out: list[str] = []
    ports: dict[str, int] = {}
    items = list(argv)
    i = 0
    while i < len(items):
        item = items[i]
        name, eq, value = item.partition("=")
        if name in _DROP:
            if not eq:
                i += 1
                value = items[i] if i < len(items) else ""
            if name in _PORTS:
                try:
                    ports[name] = int(value)
                except ValueError:
                    raise ConfigError(f"{name} {value!r}: give a port number") from None
        else:
            out.append(item)
        i += 1
    out += ["--region", f"{k + 1}/{count}", "--identity", str(identity)]
    for name, port in ports.items():
        out += [name, str(port + k if port else 0)]
    return out


def serve_processes(argv: Sequence[str], count: int, identity: Path | None) -> int:
    """Run `count` regional workers until SIGINT or SIGTERM, or until one exits."""
    with tempfile.TemporaryDirectory(prefix="laas-workers-") as tmp:
        if identity is None:
            identity = Path(tmp) / "identity.pem"
        key = SigningKey.load_or_create(identity)
        print(
            f"laas worker: {count} regional workers, identity (participants pin it for "
            f"'laas'): {key.public}",
            flush=True,
        )
        children = [
            subprocess.Popen(
                [sys.executable, "-m", "laas.cli", "worker", *child_argv(argv, k, count, identity)]
            )
            for k in range(count)
        ]
        stopping = False

        def stop(_signum: int, _frame: object) -> None:
            nonlocal stopping
            stopping = True

        previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            while not stopping and all(c.poll() is None for c in children):
                time.sleep(0.2)
        finally:
            for s, handler in previous.items():
                signal.signal(s, handler)
            for child in children:
                if child.poll() is None:
                    child.send_signal(signal.SIGTERM)
            for child in children:
                try:
                    child.wait(15)
                except subprocess.TimeoutExpired:
                    child.kill()
                    child.wait(5)
        failed = [c.returncode for c in children if c.returncode not in (0, -signal.SIGTERM)]
        return 1 if failed and not stopping else 0
