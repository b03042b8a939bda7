"""The `ldm` command line: an embedded broker and a core as child processes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from ldm import Participant, Provider, ServiceSpec
from ldm.local.brokers import wait_for
from ldm.local.embedded import read_line

from .deployment import has_service

LDM = [sys.executable, "-c", "import sys; from ldm.cli import main; sys.exit(main())"]


def spawn(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [*LDM, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, **(env or {})},
    )


def test_ldm_broker_and_ldm_core_serve_a_provider() -> None:
    broker = spawn("broker", "--port", "0")
    core = None
    try:
        assert broker.stdout is not None
        line = read_line(broker.stdout, 10)
        assert line.startswith("ldm broker listening on mqtt://127.0.0.1:"), line
        url = line.split()[-1]
        core = spawn("core", "--name", "solo", "--cluster", url, "--service-ttl", "3")
        assert core.stdout is not None
        assert read_line(core.stdout, 10).startswith("ldm core solo running on")
        spec = ServiceSpec(name="upper")
        with (
            Provider.create(url, spec, lambda r: {"u": str(r.payload["s"]).upper()}) as _,
            Participant.create(url, client_id="cli-car") as p,
        ):
            assert wait_for(has_service(p, "upper"), 5)
            assert p.open("upper").request({"s": "abc"}) == {"u": "ABC"}
        core.send_signal(signal.SIGTERM)
        assert core.wait(10) == 0
    finally:
        for proc in (core, broker):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(10)
            if proc is not None and proc.stdout is not None:
                proc.stdout.close()
    assert broker.returncode == 0


def test_ldm_core_reports_a_missing_password_variable_without_secrets() -> None:
    result = subprocess.run(
        [*LDM, "core", "--name", "x", "--cluster", "mqtt://127.0.0.1:1", "--username", "u"],
        capture_output=True,
        text=True,
        env={k: v for k, v in os.environ.items() if k != "LDM_PASSWORD"},
        timeout=30,
    )
    assert result.returncode == 2
    assert "LDM_PASSWORD is not set" in result.stderr and result.stdout == ""


def test_ldm_core_rejects_a_bad_url() -> None:
    result = subprocess.run(
        [*LDM, "core", "--name", "x", "--cluster", "http://h:1"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 2 and "mqtt://HOST:PORT" in result.stderr  # errors: stderr


@pytest.mark.parametrize("bench", ["flood", "core"])
def test_ldm_bench_without_mosquitto_says_so_on_stderr(bench: str) -> None:
    """`ldm bench flood|core` start Mosquitto brokers of their own (the runs themselves are
    in tests/ldm/test_intake.py and tests/ldm/test_batches.py)."""
    result = subprocess.run(
        [*LDM, "bench", bench],
        capture_output=True,
        text=True,
        env={**os.environ, "LDM_MOSQUITTO": "/nonexistent/mosquitto"},
        timeout=30,
    )
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.startswith("ldm bench: mosquitto is not installed"), result.stderr
