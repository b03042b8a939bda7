"""Simulated road users as real LDM participants, in real time or sped up.

Each road user of a trace gets its own `ldm.Participant` (its own MQTT connection and
client id), discovers the `laas` service from the retained list, opens a session and
publishes its fixes at their times divided by `speedup`. The fixes' timestamps are
shifted to the wall clock at the start (their spacing is kept), so ages and clocks
stay meaningful. Replies are collected per fix, in trace order.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

from laas.models import CorrectedPosition
from laas.service import SERVICE_NAME
from laas.sim.scenario import Trace
from ldm import BrokerSettings, Participant, Session

__all__ = ["LiveRun", "accounts", "run_participants", "wait_for_service"]


@dataclass
class LiveRun:
    """What the participants received: one answer (or None) per fix, and counters."""

    answers: list[CorrectedPosition | None]
    latencies: list[float] = field(default_factory=list)  # s, publish to reply
    errors: list[str] = field(default_factory=list)

    @property
    def answered(self) -> int:
        return sum(a is not None for a in self.answers)


def wait_for_service(participant: Participant, timeout: float) -> None:
    """Wait until the cluster's service list names the laas service; TimeoutError if not."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any(s.name == SERVICE_NAME for s in participant.services(timeout=0.5)):
            return
        time.sleep(0.1)
    raise TimeoutError(
        f"the {SERVICE_NAME!r} service did not appear in the cluster's service list within "
        f"{timeout:.0f} s; is `laas worker` running and its cores connected?"
    )


def accounts(trace: Trace, prefix: str) -> dict[str, str]:
    """Road user -> the account (and MQTT client id) it connects with: prefix + user."""
    return {u: f"{prefix}{u}" for u in sorted({f.user for f in trace.fixes})}


def run_participants(
    cluster: BrokerSettings | str,
    trace: Trace,
    *,
    account_prefix: str | None = None,
    speedup: float = 1.0,
    reply_timeout: float = 5.0,
    discovery_timeout: float = 20.0,
    progress: Callable[[int, int], None] | None = None,
    **participant_settings: Any,
) -> LiveRun:
    """Drive every user of `trace` through the user-cluster broker at `cluster`.

    Without `account_prefix` all users share the broker settings and get random client
    ids. With it, each user logs in as its own account, `account_prefix` + user, with the
    password of `cluster` and that name as client id: what a broker that confines every
    account to its own topics (`use_username_as_clientid` and a %u ACL) requires.
    """
    base = BrokerSettings.of(cluster)
    if account_prefix is None:
        tag = secrets.token_hex(3)
        logins = {u: (base, f"{u}-{tag}") for u in sorted({f.user for f in trace.fixes})}
    else:
        logins = {
            u: (base.model_copy(update={"username": name}), name)
            for u, name in accounts(trace, account_prefix).items()
        }
    participants = {
        u: Participant.create(settings, client_id=client_id, **participant_settings)
        for u, (settings, client_id) in logins.items()
    }
    sessions: dict[str, Session] = {}
    futures: list[tuple[int, float, Future[dict[str, Any]]]] = []
    run = LiveRun(answers=[None] * len(trace.fixes))
    done_at: dict[int, float] = {}
    try:
        for p in participants.values():
            p.start()
        wait_for_service(next(iter(participants.values())), discovery_timeout)
        for u, p in participants.items():
            sessions[u] = p.open(SERVICE_NAME)
        t0_fix = trace.fixes[0].measurement.timestamp
        shift = int(time.time() * 1000) - t0_fix
        start = time.monotonic()
        for i, fix in enumerate(trace.fixes):
            m = fix.measurement
            due = start + (m.timestamp - t0_fix) / 1000.0 / speedup
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            payload = m.model_copy(update={"timestamp": m.timestamp + shift}).model_dump(
                exclude_none=True
            )
            sent = time.monotonic()
            future = sessions[fix.user].submit(payload)
            future.add_done_callback(_stamp(done_at, i))
            futures.append((i, sent, future))
            if progress is not None:
                progress(i + 1, len(trace.fixes))
        for i, sent, future in futures:
            try:
                reply = future.result(max(0.0, sent + reply_timeout - time.monotonic()))
            except FutureTimeout:
                run.errors.append(f"fix {i}: no reply within {reply_timeout} s")
                continue
            except Exception as exc:  # the session reports a lost request as an error
                run.errors.append(f"fix {i}: {exc}")
                continue
            if "error" in reply:
                run.errors.append(f"fix {i}: {reply['error'].get('message', reply['error'])}")
                continue
            try:
                answer = CorrectedPosition.model_validate(reply)
            except ValidationError as exc:
                run.errors.append(f"fix {i}: malformed reply: {exc}")
                continue
            run.answers[i] = answer.model_copy(update={"timestamp": answer.timestamp - shift})
            run.latencies.append(done_at.get(i, time.monotonic()) - sent)
    finally:
        for p in participants.values():
            p.stop()
    return run


def _stamp(done_at: dict[int, float], i: int) -> Callable[[Future[dict[str, Any]]], None]:
    """A done-callback that records when reply i arrived (on the participant's thread)."""

    def record(_future: Future[dict[str, Any]]) -> None:
        done_at[i] = time.monotonic()

    return record
