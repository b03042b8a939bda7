"""Helpers for the operations tests: `ldm core` and `laas worker` as child processes,
their metrics endpoints, and fixes on the Hamburg map sent by a real participant."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from prometheus_client.parser import text_string_to_metric_families

from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from ldm.local.brokers import RunningBroker, find_mosquitto, start_broker, wait_for
from ldm.local.embedded import read_line

from .helpers import fix_on

LDM = [sys.executable, "-m", "ldm"]
LAAS = [sys.executable, "-m", "laas.cli"]


class Child:
    """A child process whose stdout we read line by line; its stderr (the log) goes to a
    file, read once it has stopped."""

    def __init__(self, argv: list[str], log: Path, env: dict[str, str] | None = None) -> None:
        clean = {k: v for k, v in os.environ.items() if not k.startswith(("LDM_", "LAAS_"))}
        self.log_path = log
        with open(log, "wb") as stderr:
            self.process = subprocess.Popen(
                argv,
                stdout=subprocess.PIPE,
                stderr=stderr,
                text=True,
                env={**clean, **(env or {}), "PYTHONUNBUFFERED": "1"},
            )
        self.lines: list[str] = []

    def wait_line(self, prefix: str, timeout: float = 30.0) -> str:
        """The first stdout line (from now on) containing `prefix`."""
        assert self.process.stdout is not None
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            line = read_line(self.process.stdout, max(0.1, deadline - time.monotonic()))
            if line:
                self.lines.append(line)
                if prefix in line:
                    return line
            elif self.process.poll() is not None:
                break
        raise AssertionError(f"no line with {prefix!r}; saw {self.lines}\n{self.log()}")

    def metrics_base(self) -> str:
        """http://HOST:PORT of the metrics server the child announced."""
        line = self.wait_line("metrics on http://")
        url = line.split("metrics on ", 1)[1].split()[0]
        assert url.endswith("/metrics"), line
        return url.removesuffix("/metrics")

    def stop(self) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(15)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)
        if self.process.stdout is not None:
            self.process.stdout.close()
        return self.process.returncode

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


def get(url: str) -> tuple[int, str]:
    """(HTTP status, body) of a GET, errors included."""
    try:
        with urllib.request.urlopen(url, timeout=5) as response:
            return response.status, response.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.read().decode()


def checks(base: str, path: str) -> tuple[int, dict[str, Any]]:
    """(status, JSON body) of /healthz or /readyz."""
    status, body = get(base + path)
    return status, json.loads(body)


def ready(base: str) -> bool:
    return checks(base, "/readyz")[0] == 200


class Scrape:
    """One scrape of /metrics, parsed with prometheus_client's own parser."""

    def __init__(self, base: str) -> None:
        status, self.text = get(base + "/metrics")
        assert status == 200, self.text
        self.samples = [
            sample
            for family in text_string_to_metric_families(self.text)
            for sample in family.samples
        ]

    def value(self, metric: str, /, **labels: str) -> float:
        """The sum of the samples called `metric` whose labels include `labels`."""
        found = [
            s.value
            for s in self.samples
            if s.name == metric and all(s.labels.get(k) == v for k, v in labels.items())
        ]
        assert found, f"no sample {metric}{labels}"
        return float(sum(found))

    def labels(self) -> set[tuple[str, str]]:
        return {(k, v) for s in self.samples for k, v in s.labels.items()}


def broker_kind() -> str:
    return "mosquitto" if find_mosquitto() else "embedded"


@contextmanager
def brokers(count: int) -> Iterator[list[RunningBroker]]:
    running = [start_broker(broker_kind()) for _ in range(count)]  # type: ignore[arg-type]
    try:
        yield running
    finally:
        for broker in running:
            broker.stop()


def hamburg_fixes(hdmap: HdMap, count: int) -> list[GpsMeasurement]:
    """`count` fixes of one car driving lane 0 of the map's longest element, from now on
    at 5 Hz (5 m/s)."""
    segment = max(hdmap.segments.values(), key=lambda seg: seg.length)
    now_ms = int(time.time() * 1000)
    return [fix_on(hdmap, segment, 20.0 + i, 0, now_ms + 200 * i) for i in range(count)]


def wait_until(condition: Any, timeout: float = 15.0) -> None:
    assert wait_for(condition, timeout, interval=0.1), "timed out"
