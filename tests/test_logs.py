"""Structured logs: one JSON object per line with component and event, from a real core
and worker; never a password, a key or a position."""

from __future__ import annotations

import base64
import io
import json
import logging
import subprocess
from pathlib import Path

import pytest

from laas.map.hdmap import HdMap
from ldm import Participant
from ldm.ops.logs import JsonFormatter, configure, event_of

from .operations import LAAS, LDM, Child, brokers, hamburg_fixes, ready, wait_until

PASSWORD = "pw-" + base64.b32encode(b"never-in-a-log").decode()


@pytest.mark.timeout(60)
def test_json_logs_of_a_core_and_a_worker_hold_no_secret_or_position(
    tmp_path: Path, hamburg_map: HdMap
) -> None:
    key = tmp_path / "worker.key"
    with brokers(1) as (broker,):
        core = Child(
            [*LDM, "-v", "core", "--name", "solo", "--cluster", broker.url],
            tmp_path / "core.log",
            env={"LDM_LOG_FORMAT": "json"},  # the variable, where compose sets it
        )
        worker = Child(
            [
                *(*LAAS, "worker", "--cluster", broker.url, "--log-format", "json"),
                *("--log-level", "debug", "--identity", str(key), "--metrics-port", "0"),
            ],
            tmp_path / "worker.log",
            env={"LAAS_USERNAME": "laas-worker", "LAAS_PASSWORD": PASSWORD},
        )
        try:
            core.wait_line("running on")
            base = worker.metrics_base()
            wait_until(lambda: ready(base), timeout=40.0)
            fixes = hamburg_fixes(hamburg_map, 6)
            with Participant.create(broker.url, client_id="log-car") as participant:
                wait_until(lambda: any(s.name == "laas" for s in participant.services(0.1)))
                session = participant.open("laas")
                for fix in fixes:
                    assert "error" not in session.request(fix.model_dump(), timeout=10.0)
                assert "error" in session.request({"latitude": "north"}, timeout=10.0)
            assert worker.stop() == 0  # withdraws laas: the core logs that it is gone
            wait_until(lambda: "service_gone" in core.log())
        finally:
            worker.stop()
            assert core.stop() == 0, core.log()
    lines = {"ldm-core-solo": core.log(), "laas-worker": worker.log()}
    events = set()
    for component, text in lines.items():
        assert text.strip(), f"{component} logged nothing"
        for line in text.splitlines():
            record = json.loads(line)  # every line is one JSON object
            assert record["component"] == component
            assert record["event"] and record["level"] and "message" in record
            events.add(record["event"])
            assert PASSWORD not in line
            assert key.read_text().splitlines()[1] not in line  # the private key's body
            for fix in fixes:
                for value in (fix.latitude, fix.longitude):
                    assert f"{value:.4f}" not in line and repr(value) not in line
    assert {"service_gone", "laas_worker_serving_map_on"} <= events


def test_an_exception_is_logged_by_type_and_frames_never_its_text() -> None:
    out = io.StringIO()
    handler = logging.StreamHandler(out)
    handler.setFormatter(JsonFormatter("laas-worker"))
    log = logging.getLogger("tests.logs.exception")
    log.addHandler(handler)
    log.propagate = False
    try:
        try:
            raise ValueError("input_value=53.55878 is not a valid latitude")
        except ValueError:
            log.exception("the engine failed on a fix")
        log.warning("%s: service %s is gone", "core", "laas", extra={"event": "service_gone"})
    finally:
        log.removeHandler(handler)
    failed, gone = (json.loads(line) for line in out.getvalue().splitlines())
    assert failed["event"] == "the_engine_failed_on_a_fix"
    assert failed["error"] == "ValueError" and failed["level"] == "error"
    assert any("test_an_exception_is_logged" in frame for frame in failed["stack"])
    assert "53.55878" not in out.getvalue()
    assert gone["event"] == "service_gone" and gone["message"] == "core: service laas is gone"


def test_events_are_named_from_the_template_without_its_values() -> None:
    record = logging.LogRecord(
        "ldm.transport",
        logging.INFO,
        __file__,
        1,
        "%s: disconnected (%s), reconnecting",
        ("a", 7),
        None,
    )
    assert event_of(record) == "disconnected_reconnecting"


def test_a_bad_log_format_is_a_clear_error() -> None:
    result = subprocess.run(
        [*LDM, "core", "--name", "x", "--cluster", "mqtt://127.0.0.1:1"],
        capture_output=True,
        text=True,
        env={"LDM_LOG_FORMAT": "xml", "PATH": "/usr/bin:/bin"},
        timeout=30,
    )
    assert result.returncode == 2
    assert "log format 'xml': use text or json" in result.stderr
    with pytest.raises(Exception, match="use text or json"):
        configure("yaml", component="test")
