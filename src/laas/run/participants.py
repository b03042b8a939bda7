"""Simulated road users as real LDM participants, in real time or sped up.

Each road user of a trace gets its own `ldm.Participant` (its own MQTT connection and
client id), discovers the `laas` service from the retained list, opens a session and
publishes its fixes at their times divided by `speedup`. The fixes' timestamps are
shifted to the wall clock at the start (their spacing is kept), so ages and clocks
stay meaningful. Replies are collected per fix, in trace order.

A road user whose region has no worker (a regional worker missing) is not answered, and
only it: its fixes are reported as errors, every other user runs on.

`run_participants` does all of that in this process. Its parts serve `laas bench` too,
whose participant processes each drive a share of the users: `open_sessions` (connect
and discover), `submit_on_time` (the sending loop) and `collect_replies`.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

from laas.deadreckon import dead_reckon
from laas.discovery import wait_for_service
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition, ErrorReply, GpsMeasurement, read_reply
from laas.sim.scenario import Trace
from laas.worker.service import SERVICE_NAME
from ldm import (
    BrokerSettings,
    Participant,
    RoutedSession,
    ServiceNotFound,
    Session,
    SessionSilent,
)

__all__ = [
    "LiveRun",
    "Reply",
    "Request",
    "Sent",
    "accounts",
    "collect_replies",
    "open_sessions",
    "run_participants",
    "submit_on_time",
    "wait_for_service",
]

Login = tuple[BrokerSettings, str]  # the broker settings and client id of one road user


@dataclass
class LiveRun:
    """What the participants received: one answer (or None) per fix, and counters."""

    answers: list[CorrectedPosition | None]
    latencies: list[float] = field(default_factory=list)  # s, publish to reply
    errors: list[str] = field(default_factory=list)
    silent: int = 0  # fixes answered by the participant itself (silence after a change)

    @property
    def answered(self) -> int:
        return sum(a is not None for a in self.answers)


@dataclass
class Request:
    """One submitted fix: when it left and when its reply arrived (`time.perf_counter`)."""

    index: int
    sent: float
    future: Future[dict[str, Any]]
    arrived: float | None = None

    def stamp(self, _future: Future[dict[str, Any]]) -> None:
        """The future's done-callback: runs on the participant's thread, records the time."""
        self.arrived = time.perf_counter()


@dataclass
class Sent:
    """What `submit_on_time` sent: the requests, in schedule order, and its clock."""

    requests: list[Request]
    start: float  # perf_counter at the schedule's zero
    end: float  # perf_counter after the last submit
    shift: int  # ms added to every fix's timestamp


@dataclass(frozen=True)
class Reply:
    """The outcome of one request: a corrected position, or why there is none."""

    index: int
    answer: CorrectedPosition | None
    latency: float | None  # s from just before the submit to the reply, for an answer
    error: str | None
    lost: bool = False  # no reply at all (a timeout, or the session gave it up)
    silent: bool = False  # not sent: the session kept quiet after a change of pseudonym


def accounts(trace: Trace, prefix: str) -> dict[str, str]:
    """Road user -> the account (and MQTT client id) it connects with: prefix + user."""
    return {u: f"{prefix}{u}" for u in sorted({f.user for f in trace.fixes})}


@contextmanager
def open_sessions(
    logins: Mapping[str, Login],
    discovery_timeout: float,
    where: Mapping[str, tuple[float, float]],
    **participant_settings: Any,
) -> Iterator[dict[str, RoutedSession]]:
    """Start one participant per road user, wait for the service, route each (a session
    with the worker whose region holds the user's first position `where`, opened now;
    where no worker serves, at its first fix that one does); the participants stop when
    the block ends."""
    participants = {
        u: Participant.create(settings, client_id=client_id, **participant_settings)
        for u, (settings, client_id) in logins.items()
    }
    try:
        for p in participants.values():
            p.start()
        wait_for_service(next(iter(participants.values())), discovery_timeout)
        routed = {u: RoutedSession(p, SERVICE_NAME) for u, p in participants.items()}
        for user, session in routed.items():  # opened now, not with the first fix
            with suppress(ServiceNotFound):  # its region's worker is missing: its fixes fail
                session.prepare(where[user])
        yield routed
    finally:
        for p in participants.values():
            p.stop()


def submit_on_time(
    sessions: Mapping[str, Session] | Mapping[str, RoutedSession],
    sends: Sequence[tuple[str, dict[str, Any]]],
    *,
    t0_ms: int,
    start: float,
    speedup: float = 1.0,
    on_submit: Callable[[int, Sequence[Request]], None] | None = None,
) -> Sent:
    """Submit each (user, measurement) when its time comes, then return.

    Time `t0_ms` of the fixes falls at wall-clock time `start` (`time.time()`); a fix is
    due `(timestamp - t0_ms) / speedup` ms later and leaves with its timestamp shifted by
    `start - t0_ms`. `on_submit(i, requests so far)` runs after each submit.
    """
    shift = round(start * 1000.0) - t0_ms
    mono0 = time.perf_counter() + (start - time.time())
    requests: list[Request] = []
    last: dict[str, int] = {}  # user -> the timestamp of its last fix
    for i, (user, measurement) in enumerate(sends):
        timestamp = int(measurement["timestamp"])
        before = last.get(user)
        last[user] = timestamp
        if before is not None:  # the motion the receiver reports, for the rotation policy
            speed = float(measurement["speed"])
            sessions[user].moved(speed * (timestamp - before) / 1000.0, speed)
        delay = mono0 + (timestamp - t0_ms) / 1000.0 / speedup - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        payload = dict(measurement, timestamp=timestamp + shift)
        sent = time.perf_counter()
        session = sessions[user]
        try:
            if isinstance(session, RoutedSession):  # to the worker of the fix's region
                future = session.submit(payload, (payload["longitude"], payload["latitude"]))
            else:
                future = session.submit(payload)
        except ServiceNotFound as exc:  # no worker serves the fix's region: this fix fails
            future = Future()
            future.set_exception(exc)
        request = Request(i, sent, future)
        request.future.add_done_callback(request.stamp)
        requests.append(request)
        if on_submit is not None:
            on_submit(i, requests)
    return Sent(requests, mono0, time.perf_counter(), shift)


def collect_replies(sent: Sent, reply_timeout: float) -> Iterator[Reply]:
    """Each request's outcome in order, waiting up to `reply_timeout` s from its submit."""
    for r in sent.requests:
        try:
            reply = r.future.result(max(0.0, r.sent + reply_timeout - time.perf_counter()))
        except FutureTimeout:
            yield Reply(
                r.index, None, None, f"fix {r.index}: no reply within {reply_timeout:g} s", True
            )
            continue
        except SessionSilent as exc:  # kept quiet: the participant answers itself
            yield Reply(r.index, None, None, f"fix {r.index}: {exc}", silent=True)
            continue
        except Exception as exc:  # the session reports a lost request as an error
            yield Reply(
                r.index, None, None, f"fix {r.index}: no reply ({type(exc).__name__}: {exc})", True
            )
            continue
        try:
            answer = read_reply(reply)
        except ValidationError as exc:
            yield Reply(r.index, None, None, f"fix {r.index}: malformed reply: {exc}")
            continue
        if isinstance(answer, ErrorReply):
            yield Reply(r.index, None, None, f"fix {r.index}: {answer.error.message}")
            continue
        arrived = r.arrived if r.arrived is not None else time.perf_counter()
        yield Reply(r.index, answer, arrived - r.sent, None)


def run_participants(
    cluster: BrokerSettings | str,
    trace: Trace,
    *,
    account_prefix: str | None = None,
    speedup: float = 1.0,
    reply_timeout: float = 5.0,
    discovery_timeout: float = 20.0,
    progress: Callable[[int, int], None] | None = None,
    hdmap: HdMap | None = None,
    **participant_settings: Any,
) -> LiveRun:
    """Drive every user of `trace` through the user-cluster broker at `cluster`.

    Without `account_prefix` all users share the broker settings and get random client
    ids. With it, each user logs in as its own account, `account_prefix` + user, with the
    password of `cluster` and that name as client id: what a broker that confines every
    account to its own topics (`use_username_as_clientid` and a %u ACL) requires.

    A fix the session keeps quiet about (the rotation policy's silence) gets the user's own
    answer (`laas.deadreckon`), on `hdmap`'s lanes when it is given.
    """
    base = BrokerSettings.of(cluster)
    logins: dict[str, Login]
    if account_prefix is None:
        tag = secrets.token_hex(3)
        logins = {u: (base, f"{u}-{tag}") for u in sorted({f.user for f in trace.fixes})}
    else:
        logins = {
            u: (base.model_copy(update={"username": name}), name)
            for u, name in accounts(trace, account_prefix).items()
        }
    sends = [(f.user, f.measurement.model_dump(exclude_none=True)) for f in trace.fixes]
    total = len(sends)

    def report(i: int, _requests: Sequence[Request]) -> None:
        if progress is not None:
            progress(i + 1, total)

    run = LiveRun(answers=[None] * total)
    first: dict[str, tuple[float, float]] = {}
    for fix in trace.fixes:
        first.setdefault(fix.user, (fix.measurement.longitude, fix.measurement.latitude))
    with open_sessions(logins, discovery_timeout, first, **participant_settings) as sessions:
        sent = submit_on_time(
            sessions,
            sends,
            t0_ms=trace.fixes[0].measurement.timestamp,
            start=time.time(),
            speedup=speedup,
            on_submit=report,
        )
        last: dict[str, tuple[CorrectedPosition, GpsMeasurement]] = {}
        for reply in collect_replies(sent, reply_timeout):
            fix = trace.fixes[reply.index]
            held = last.get(fix.user)
            if reply.silent and held is not None:  # as the device would: dead-reckoned
                run.answers[reply.index] = dead_reckon(held[0], held[1], fix.measurement, hdmap)
                run.silent += 1
                continue
            if reply.answer is None:
                run.errors.append(reply.error or f"fix {reply.index}: no answer")
                continue
            answer = reply.answer.model_copy(
                update={"timestamp": reply.answer.timestamp - sent.shift}
            )
            run.answers[reply.index] = answer
            last[fix.user] = (answer, fix.measurement)
            if reply.latency is not None:
                run.latencies.append(reply.latency)
    return run
