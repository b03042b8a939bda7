"""The live map (`laas.worker.dashboard`): its endpoints on a running `laas worker --http 0`,
its event stream under a slow page, and the page itself in a real headless Chromium.

The browser test needs Debian's ``chromium`` and ``chromium-driver`` and the `selenium`
package (the dev extra); without them it skips, unless LAAS_REQUIRE_BROWSER=1, where it
fails.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import threading
import time
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import shapely

from laas.config import EngineConfig
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.run.deployment import LocalDeployment
from laas.run.participants import LiveRun, run_participants
from laas.sim.scenario import Trace, hamburg_scenario, simulate
from laas.worker.dashboard import DashboardServer
from ldm import Core, Participant
from ldm.local.brokers import RunningBroker

from .operations import LAAS, Child, brokers, get, hamburg_fixes, wait_until

CONFIG = EngineConfig(sigma_pos=1.0, sigma_vel=0.25, sigma_heading=0.05)
SVG_NAMESPACE = "http://www.w3.org/2000/svg"


class Events:
    """A page's event stream read on a thread: every event as (name, data)."""

    def __init__(self, base: str, receive_buffer: int | None = None, read: bool = True) -> None:
        host, port = base.removeprefix("http://").rstrip("/").rsplit(":", 1)
        self.sock = socket.socket()
        if receive_buffer is not None:  # before connecting, so the window stays small
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, receive_buffer)
        self.sock.connect((host, int(port)))
        self.sock.sendall(f"GET /api/events HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
        self.events: list[tuple[str, Any]] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        if read:
            self.thread.start()

    def _read(self) -> None:
        stream = self.sock.makefile("rb")
        while stream.readline().strip():  # the status line and headers
            pass
        name = ""
        for raw in stream:
            line = raw.decode().rstrip("\n")
            if line.startswith("event: "):
                name = line.removeprefix("event: ")
            elif line.startswith("data: "):
                self.events.append((name, json.loads(line.removeprefix("data: "))))

    def fixes(self) -> list[dict[str, Any]]:
        """Every answered fix of the ``batch`` events so far."""
        return [fix for name, data in list(self.events) if name == "batch" for fix in data["fixes"]]

    def last(self, name: str) -> Any:
        found = [data for event, data in list(self.events) if event == name]
        return found[-1] if found else None

    def close(self) -> None:
        self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        if self.thread.is_alive():
            self.thread.join(5.0)


# -- `laas worker --http 0` on a service cluster, with two cores -------------------------


@pytest.fixture(scope="module")
def worker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, RunningBroker]]:
    """(the live map's base URL, the user-cluster broker) of a running `laas worker`."""
    with brokers(3) as (user, backbone, service):
        cores = [
            Core.create(name, b.url, backbone.url)
            for name, b in (("user", user), ("service", service))
        ]
        for core in cores:
            core.start()
        log = tmp_path_factory.mktemp("worker") / "worker.log"
        child = Child([*LAAS, "worker", "--cluster", service.url, "--http", "0"], log)
        try:
            line = child.wait_line("live map on http://", timeout=60.0)
            yield line.split("live map on ", 1)[1].split()[0], user
        finally:
            assert child.stop() == 0, child.log()
            for core in cores:
                core.stop()


def test_the_worker_serves_the_page_and_the_lanes_of_its_map(
    worker: tuple[str, RunningBroker], hamburg_map: HdMap
) -> None:
    base, _ = worker
    with urllib.request.urlopen(base, timeout=5) as response:
        assert response.headers["Content-Type"] == "text/html; charset=utf-8"
        assert "default-src 'none'" in response.headers["Content-Security-Policy"]
        page = response.read().decode()
    assert "<svg" in page and "EventSource" in page
    # self-contained: the one absolute URL in the page is the SVG namespace
    assert set(re.findall(r"https?://[^\s\"'<>)`]+", page)) == {SVG_NAMESPACE}

    status, body = get(base + "api/lanes")
    assert status == 200
    lanes = json.loads(body)
    assert lanes["type"] == "FeatureCollection"
    assert len(lanes["features"]) == sum(len(s.lanes) for s in hamburg_map.segments.values())
    for feature in lanes["features"]:
        p = feature["properties"]
        lane = hamburg_map.segments[p["segment"]].lanes[p["lane"]]
        assert (p["type"], p["width"], p["direction"]) == (lane.type, lane.width, lane.direction)
        lonlat = np.array(feature["geometry"]["coordinates"])
        xy = hamburg_map.projection.to_utm_array(lonlat[:, 0], lonlat[:, 1])
        # WGS 84 back to the map's frame: on the lane's own centre line, to 2 cm
        assert shapely.hausdorff_distance(shapely.LineString(xy), lane.centerline) < 0.02
    west, south, east, north = lanes["bbox"]
    assert west < 9.98 < east and south < 53.56 < north  # the Hamburg test road

    status, body = get(base + "nothing-here")
    assert status == 404 and "/api/lanes" in body


def test_the_event_stream_shows_each_answer_under_its_pseudonym(
    worker: tuple[str, RunningBroker], hamburg_map: HdMap
) -> None:
    base, user = worker
    count = 12
    events = Events(base)
    try:
        wait_until(lambda: events.last("hello") is not None)
        sent = hamburg_fixes(hamburg_map, count)
        with Participant.create(user.url, client_id="dashboard-car") as participant:
            wait_until(lambda: any(s.name == "laas" for s in participant.services(timeout=0.1)))
            session = participant.open("laas")
            replies = [session.request(fix.model_dump(), timeout=10.0) for fix in sent]
        wait_until(lambda: len(events.fixes()) == count, timeout=10.0)
        wait_until(lambda: (events.last("stats") or {}).get("answered", 0) >= count, timeout=5.0)
    finally:
        events.close()
    assert events.events[0][0] == "hello"
    seen = events.fixes()
    for fix, reply, shown in zip(sent, replies, seen, strict=True):
        answer = CorrectedPosition.model_validate(reply)
        assert shown["timestamp"] == answer.timestamp == fix.timestamp
        assert (shown["segment"], shown["lane"]) == (answer.segment, answer.lane)
        assert shown["position"] == pytest.approx([answer.longitude, answer.latitude], abs=1e-7)
        assert shown["raw"] == pytest.approx([fix.longitude, fix.latitude], abs=1e-7)
    pseudonyms = {shown["pseudonym"] for shown in seen}
    assert len(pseudonyms) == 1  # one participant, one pseudonym; never its client id
    assert "dashboard-car" not in json.dumps(events.events)
    stats = events.last("stats")
    assert stats["answers_per_s"] > 0 and stats["engine_ms_per_fix"] > 0


@pytest.mark.timeout(90)
def test_laas_demo_prints_the_address_of_its_live_map_and_serves_it(tmp_path: Path) -> None:
    demo = Child(
        [*LAAS, "demo", "--out", str(tmp_path / "out"), "--speedup", "20"], tmp_path / "demo.log"
    )
    try:
        line = demo.wait_line("live map: http://", timeout=60.0)
        base = line.split("live map: ", 1)[1].split()[0]
        status, page = get(base)
        assert status == 200 and "LaaS live map" in page
        wait_until(lambda: len(json.loads(get(base + "api/state")[1])["users"]) > 0, timeout=30.0)
        demo.wait_line("received over MQTT (default mode)", timeout=60.0)
        demo.wait_line("demo-lanes-paper.png", timeout=60.0)  # its last line
        demo.process.wait(30.0)
    finally:
        code = demo.stop()
    assert code == 0, demo.log()
    assert demo.lines[0].startswith("LaaS demo: 3 road users")
    assert demo.lines[2] == line  # at the start: after the deployment, before the road users


# -- a slow page, and the page in a browser: the Hamburg road users, worker in-process ------


def _hamburg_run(
    hdmap: HdMap, deployment: LocalDeployment, speedup: float
) -> tuple[threading.Thread, dict[str, LiveRun], Trace]:
    """The Hamburg scenario's road users as participants, on a thread."""
    scenario = hamburg_scenario()
    trace = simulate(hdmap, scenario, scenario.errors, seed=4)
    result: dict[str, LiveRun] = {}

    def run() -> None:
        result["live"] = run_participants(
            deployment.user_url, trace, speedup=speedup, **deployment.trust
        )

    thread = threading.Thread(target=run, name="hamburg-participants")
    thread.start()
    return thread, result, trace


@pytest.mark.timeout(60)
def test_a_slow_page_loses_old_events_and_slows_nobody(hamburg_map: HdMap) -> None:
    with (
        LocalDeployment(hamburg_map, CONFIG) as deployment,
        DashboardServer(
            deployment.service,  # type: ignore[arg-type]  # in-process worker
            deployment.provider,
            queue=8,
            send_buffer=4096,
        ) as server,
    ):
        slow = Events(server.url, receive_buffer=2048, read=False)  # asks, never reads
        fast = Events(server.url)
        try:
            wait_until(lambda: len(server.feed.clients()) == 2)
            thread, result, _ = _hamburg_run(hamburg_map, deployment, speedup=20.0)
            thread.join(45.0)
            live = result["live"]
            wait_until(lambda: len(fast.fixes()) == live.answered, timeout=5.0)
            clients = server.feed.clients()
        finally:
            slow.close()
            fast.close()
    assert live.errors == [] and live.answered == len(live.answers)
    dropped = sorted(client.dropped for client in clients)
    assert dropped[0] == 0  # the page that reads got every event
    assert dropped[1] > 0  # the one that does not lost old ones, and held up nothing
    answered = {(a.timestamp, a.segment, a.lane) for a in live.answers if a is not None}
    shown = fast.fixes()
    shift = _shift([f["timestamp"] for f in shown], [t for t, _, _ in answered])
    assert {(f["timestamp"] - shift, f["segment"], f["lane"]) for f in shown} == answered


def _browser_or_skip() -> tuple[str, str]:
    """(chromium, chromedriver), or skip (fail with LAAS_REQUIRE_BROWSER=1) saying why."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver") or (
        "/usr/bin/chromedriver" if os.path.exists("/usr/bin/chromedriver") else None
    )
    missing = []
    if chromium is None or driver is None:
        missing.append("chromium and chromedriver (apt-get install -y chromium chromium-driver)")
    try:
        import selenium  # noqa: F401
    except ImportError:
        missing.append("selenium (pip install -e '.[dev]')")
    if missing:
        message = "the browser test needs " + " and ".join(missing)
        if os.environ.get("LAAS_REQUIRE_BROWSER") == "1":
            pytest.fail(f"LAAS_REQUIRE_BROWSER=1 but {message}")
        pytest.skip(message)
    assert chromium is not None and driver is not None
    return chromium, driver


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[Any]:
    """A headless Chromium driven by selenium through Debian's chromedriver."""
    chromium, driver_path = _browser_or_skip()
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    options = Options()
    options.binary_location = chromium
    for flag in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--window-size=1500,900",
        f"--user-data-dir={tmp_path / 'chromium-profile'}",
    ):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    try:
        yield driver
    finally:
        driver.quit()


def _users(driver: Any) -> dict[str, dict[str, str]]:
    """Each road user the page draws: its data attributes, by pseudonym."""
    found: dict[str, dict[str, str]] = driver.execute_script(
        "const out = {};"
        "for (const g of document.querySelectorAll('#users g.user'))"
        "  out[g.dataset.pseudonym] = {...g.dataset};"
        "return out;"
    )
    return found


def _poll(check: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, f"the page did not show {what} in {timeout:g} s"
        time.sleep(0.1)


@pytest.mark.timeout(90)
def test_the_page_shows_the_road_users_moving_on_the_lanes_they_were_given(
    hamburg_map: HdMap, browser: Any, tmp_path: Path
) -> None:
    lanes = sum(len(s.lanes) for s in hamburg_map.segments.values())
    with LocalDeployment(hamburg_map, CONFIG) as deployment:
        assert deployment.service is not None
        with DashboardServer(deployment.service, deployment.provider) as server:
            browser.get(server.url)
            count = "return document.querySelectorAll('path.lane').length"
            _poll(lambda: browser.execute_script(count) == lanes, 15.0, "the map's lanes")
            status = "return document.getElementById('status').dataset.state"
            _poll(lambda: browser.execute_script(status) == "live", 10.0, "the stream live")
            thread, result, trace = _hamburg_run(hamburg_map, deployment, speedup=10.0)
            try:
                _poll(lambda: len(_users(browser)) == 3, 20.0, "three road users")
                before = _users(browser)
                time.sleep(1.5)
                after = _users(browser)
            finally:
                thread.join(45.0)
            live = result["live"]
            last = _last_answers(trace, live)

            def shows_the_last_answers() -> bool:
                times = [int(u["timestamp"]) for u in _users(browser).values()]
                return {t - _shift(times, list(last)) for t in times} == set(last)

            _poll(shows_the_last_answers, 10.0, "each user's last answer")
            shown = _users(browser)
            chosen = browser.execute_script(
                "return [...document.querySelectorAll('#chosen path.chosen')].map((p) => ({"
                "...p.dataset, same: p.getAttribute('d') === document.querySelector("
                '`path.lane[data-segment="${p.dataset.segment}"][data-lane="${p.dataset.lane}"]`'
                ").getAttribute('d')}))"
            )
            answered = "return document.getElementById('answered').textContent"
            _poll(lambda: browser.execute_script(answered) == str(live.answered), 5.0, "stats")
            areas = browser.execute_script(
                "return [...document.querySelectorAll('#areas g.area')]"
                ".map((g) => ({...g.dataset}))"
            )
            estimate = deployment.service.engine.common_errors()
            browser.save_screenshot(str(tmp_path / "live-map.png"))
            errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert live.errors == [] and live.answered == len(live.answers)
    # they appear, and they move: each has a later fix, at another place
    assert set(before) == set(after)
    for p in before:
        assert int(after[p]["fixes"]) > int(before[p]["fixes"])
        assert (after[p]["lat"], after[p]["lon"]) != (before[p]["lat"], before[p]["lon"])
    # what the page shows is what the service answered: lane, place, and the lane drawn
    shift = _shift([int(u["timestamp"]) for u in shown.values()], list(last))
    for user in shown.values():
        answer = last[int(user["timestamp"]) - shift]
        assert (user["segment"], user["lane"]) == (answer.segment, str(answer.lane))
        assert float(user["lat"]) == pytest.approx(answer.latitude, abs=1e-7)
        assert float(user["lon"]) == pytest.approx(answer.longitude, abs=1e-7)
        assert user["laneType"] == answer.lane_type
    assert {(c["pseudonym"], c["segment"], c["lane"]) for c in chosen} == {
        (p, u["segment"], u["lane"]) for p, u in shown.items()
    }
    assert all(c["same"] for c in chosen)  # the chosen lane is drawn on the map's own lane
    # the common error, as the engine holds it (the page's is at most 0.5 s older)
    assert len(areas) == len(estimate) == 1
    assert float(areas[0]["bEast"]) == pytest.approx(float(estimate[0].b[0]), abs=0.5)
    assert float(areas[0]["bNorth"]) == pytest.approx(float(estimate[0].b[1]), abs=0.5)
    assert errors == []
    assert (tmp_path / "live-map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _shift(shown: list[int], answered: list[int]) -> int:
    """How far the worker's timestamps run ahead of the trace's (`run_participants`
    shifts the fixes to the wall clock, and its answers back)."""
    return max(shown) - max(answered) if shown and answered else 0


def _last_answers(trace: Trace, live: LiveRun) -> dict[int, CorrectedPosition]:
    """The answer each road user received to its last fix, by its timestamp."""
    last = {fix.user: a for fix, a in zip(trace.fixes, live.answers, strict=True) if a}
    by_time = {a.timestamp: a for a in last.values()}
    assert len(by_time) == len(last)  # their timestamps tell them apart
    return by_time
