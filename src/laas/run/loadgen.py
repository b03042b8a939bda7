"""Many participants from one process: a paced ramp over one shared client loop.

Each road user is still its own `ldm.Participant` (its own MQTT connection, client id,
session and pseudonym), but no participant has a thread of its own: one
`ldm.transport.ClientLoop` thread drives all their sockets with paho's external loop
over epoll, and handles each participant's messages and periodic tick as they come
(`Participant.start_on`), instead of a paho network thread and a dispatch thread per
participant (500 participants were 1,000 threads, and the GIL hand-offs between them
cost more CPU than the LDM cores themselves).

paho's threaded loop waits in ``select()``, which fails for descriptors of 1024 and up,
and a threaded client holds three (its socket and a wake-up pair), so a process could
not hold more than about 340 threaded participants: the reason
`laas bench` did not start at 800 (docs in `laas.run.bench`).

The connections are opened at a paced rate (`connect_rate` per second), then the
sessions, each with a progress report, so a thousand clients do not hit the broker and
the user core in one burst.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

from laas.run.participants import Login, wait_for_service
from laas.worker.service import SERVICE_NAME
from ldm import Participant, RoutedSession, Session
from ldm.errors import ConnectError
from ldm.transport import ClientLoop

__all__ = ["RampProgress", "paced_sessions"]

RampProgress = Callable[[str, int, int], None]
"""progress(stage, done, total): stage "connect" (connections acknowledged) or
"session" (sessions open), called about once a second and at the end of each stage."""

_SESSION_THREADS = 16  # session requests in flight at once (each waits for its grant)


@contextmanager
def paced_sessions(
    logins: Mapping[str, Login],
    *,
    connect_rate: float = 200.0,
    connect_timeout: float = 30.0,
    discovery_timeout: float = 30.0,
    session_timeout: float = 10.0,
    progress: RampProgress | None = None,
    where: Mapping[str, tuple[float, float]] | None = None,
    **participant_settings: Any,
) -> Iterator[dict[str, Session] | dict[str, RoutedSession]]:
    """Start one participant per road user on a shared `ClientLoop`, `connect_rate`
    connections a second, wait until all are connected (`connect_timeout` s after the
    last one started; ConnectError if not), wait for the laas service, open a session
    each; everything stops when the block ends. With `where` (each user's first
    position, lon/lat), each gets a `RoutedSession` instead, opened with the worker of
    that position's region."""
    if connect_rate <= 0.0:
        raise ValueError("connect_rate must be positive")
    report = progress or (lambda _stage, _done, _total: None)
    total = len(logins)
    participants: dict[str, Participant] = {}
    loop = ClientLoop(name="laas-loadgen-loop").start()
    try:
        t0 = time.monotonic()
        next_report = t0 + 1.0
        for i, (user, (settings, client_id)) in enumerate(logins.items()):
            delay = t0 + i / connect_rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            participant = Participant.create(settings, client_id=client_id, **participant_settings)
            participants[user] = participant
            participant.start_on(loop)  # no thread of its own: see the module's doc
            if time.monotonic() >= next_report:
                next_report += 1.0
                report("connect", _connected(participants), total)
        deadline = time.monotonic() + connect_timeout
        while (connected := _connected(participants)) < total:
            if time.monotonic() > deadline:
                raise ConnectError(
                    f"{connected} of {total} participants connected within "
                    f"{connect_timeout:g} s of the last start"
                )
            if time.monotonic() >= next_report:
                next_report += 1.0
                report("connect", connected, total)
            time.sleep(0.05)
        report("connect", total, total)
        wait_for_service(next(iter(participants.values())), discovery_timeout)
        yield _open_all(participants, session_timeout, report, where)
    finally:
        for participant in participants.values():
            participant.stop()
        loop.stop()


def _connected(participants: Mapping[str, Participant]) -> int:
    return sum(p.transport.connected for p in participants.values())


def _open_all(
    participants: Mapping[str, Participant],
    timeout: float,
    report: RampProgress,
    where: Mapping[str, tuple[float, float]] | None = None,
) -> dict[str, Session] | dict[str, RoutedSession]:
    """A session for each participant (routed by `where`, if given), `_SESSION_THREADS`
    requests in flight."""
    if where is not None:
        routed = {u: RoutedSession(p, SERVICE_NAME, timeout) for u, p in participants.items()}
        with ThreadPoolExecutor(_SESSION_THREADS, thread_name_prefix="laas-open") as pool:
            prepared = [pool.submit(r.prepare, where[u]) for u, r in routed.items()]
            for done in prepared:
                done.result()  # raises the first failure
        report("session", len(routed), len(routed))
        return routed
    total = len(participants)
    sessions: dict[str, Session] = {}
    next_report = time.monotonic() + 1.0
    with ThreadPoolExecutor(_SESSION_THREADS, thread_name_prefix="laas-open") as pool:
        futures = {u: pool.submit(p.open, SERVICE_NAME, timeout) for u, p in participants.items()}
        for user, future in futures.items():
            sessions[user] = future.result()  # raises the first failure
            if time.monotonic() >= next_report:
                next_report += 1.0
                report("session", len(sessions), total)
    report("session", total, total)
    return sessions
