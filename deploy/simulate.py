"""The compose simulator: a scenario's road users as live participants, one account each.

    python deploy/simulate.py --cluster mqtt://broker-user:1883 --account-prefix sim-

Like `laas simulate`, but for a locked-down user-cluster broker: there every participant
is an account (`use_username_as_clientid`, and the ACL confines it to
ldm/p/{its user name}/...), so each road user connects with its own account,
ACCOUNT_PREFIX + road user (`sim-car`, `sim-cyclist-1`, `sim-cyclist-2` for the Hamburg
scenario), all with the password in $LAAS_PASSWORD. `python deploy/simulate.py
--accounts` prints those names (deploy/security/compose-accounts.sh creates them).

Answers go to stdout as JSON Lines, the summary ("N/M answered; lane accuracy ...") to
stderr, as with `laas simulate`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from laas.evaluate import score
from laas.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.scenario import Trace, get_scenario, simulate
from laas.service import SERVICE_NAME
from laas.trace import format_answer
from ldm import BrokerSettings, LdmError, Participant, Session


def accounts(scenario: str, prefix: str) -> dict[str, str]:
    """Road user -> the account it connects with."""
    return {u.user: f"{prefix}{u.user}" for u in get_scenario(scenario).users}


def drive(
    settings: dict[str, BrokerSettings], trace: Trace, speedup: float, reply_timeout: float = 5.0
) -> tuple[list[CorrectedPosition | None], list[str]]:
    """Send every fix on time through its user's participant; one answer (or None) each."""
    participants = {u: Participant.create(s) for u, s in settings.items()}  # client id = user
    answers: list[CorrectedPosition | None] = [None] * len(trace.fixes)
    errors: list[str] = []
    futures: list[tuple[int, float, Future[dict[str, Any]]]] = []
    try:
        for p in participants.values():
            p.start(timeout=10)
        first = next(iter(participants.values()))
        deadline = time.monotonic() + 20
        while not any(s.name == SERVICE_NAME for s in first.services(timeout=0.5)):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no {SERVICE_NAME!r} service in the service list in 20 s")
            time.sleep(0.1)
        sessions: dict[str, Session] = {u: p.open(SERVICE_NAME) for u, p in participants.items()}
        t0 = trace.fixes[0].measurement.timestamp
        shift = int(time.time() * 1000) - t0
        start = time.monotonic()
        for i, fix in enumerate(trace.fixes):
            m = fix.measurement
            delay = start + (m.timestamp - t0) / 1000.0 / speedup - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            payload = m.model_copy(update={"timestamp": m.timestamp + shift}).model_dump()
            futures.append((i, time.monotonic(), sessions[fix.user].submit(payload)))
        for i, sent, future in futures:
            try:
                reply = future.result(max(0.0, sent + reply_timeout - time.monotonic()))
                answer = CorrectedPosition.model_validate(reply)
            except FutureTimeout:
                errors.append(f"fix {i}: no reply within {reply_timeout} s")
                continue
            except (LdmError, ValidationError) as exc:
                errors.append(f"fix {i}: {exc}")
                continue
            answers[i] = answer.model_copy(update={"timestamp": answer.timestamp - shift})
    finally:
        for p in participants.values():
            p.stop()
    return answers, errors


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cluster", default=os.environ.get("LAAS_CLUSTER"))
    parser.add_argument("--account-prefix", default="sim-", help="account = prefix + road user")
    parser.add_argument("--password-env", default="LAAS_PASSWORD")
    parser.add_argument("--ca-file", type=Path, default=os.environ.get("LAAS_CA_FILE"))
    parser.add_argument("--scenario", default="messe-hamburg")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--speedup", type=float, default=1.0, help="faster than real time by")
    parser.add_argument("--accounts", action="store_true", help="print the account names")
    a = parser.parse_args(argv)
    names = accounts(a.scenario, a.account_prefix)
    if a.accounts:
        print("\n".join(names.values()))
        return 0
    if not a.cluster:
        parser.error("--cluster (or LAAS_CLUSTER) is required")
    settings = {
        u: BrokerSettings(url=a.cluster, username=n, password_env=a.password_env, ca_file=a.ca_file)
        for u, n in names.items()
    }
    scenario = get_scenario(a.scenario)
    hdmap = HdMap.load(scenario.map)
    trace = simulate(hdmap, scenario, scenario.errors, a.seed)
    print(
        f"simulate: {len(trace.fixes)} fixes of {len(names)} road users at {a.speedup:g}x "
        f"real time, accounts {', '.join(names.values())}",
        file=sys.stderr,
    )
    try:
        answers, errors = drive(settings, trace, a.speedup)
    except (LdmError, TimeoutError) as exc:
        print(f"simulate: {exc}", file=sys.stderr)
        return 1
    for fix, answer in zip(trace.fixes, answers, strict=True):
        if answer is not None:
            print(format_answer(fix.user, answer))
    for error in errors[:10]:
        print(f"simulate: {error}", file=sys.stderr)
    answered = sum(a is not None for a in answers)
    if not answered:
        print("simulate: no fix was answered", file=sys.stderr)
        return 1
    r = score(hdmap, trace, answers)
    print(
        f"simulate: {answered}/{len(trace.fixes)} answered; lane accuracy {r.accuracy:.3f}, "
        f"AED {r.aed:.2f} m (raw fixes {r.raw_aed:.2f} m)",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
