"""`laas simulate`: a scenario's road users as live LDM participants
(`laas.run.participants`), their answers scored against the truth."""

from __future__ import annotations

import argparse
import sys

from laas.cli.bridges import device_account_args
from laas.cli.common import (
    Subcommands,
    chosen_scenario,
    cluster_broker,
    connection_args,
    max_age_arg,
    pinned_key_args,
    scenario_args,
)
from laas.progress import progress_printer
from ldm.ops.process import broker_settings

__all__ = ["add_simulate"]


def _cmd_simulate(a: argparse.Namespace) -> int:
    from laas.evaluation.score import score
    from laas.run.participants import accounts, run_participants
    from laas.sim.scenario import simulate_with
    from laas.sim.trace import format_answer

    scenario, hdmap = chosen_scenario(a)
    trace = simulate_with(hdmap, scenario, a.seed, sigma_pos=a.sigma_pos, sigma_vel=a.sigma_vel)
    if a.list_accounts:
        print("\n".join(accounts(trace, a.prefix).values()))
        return 0
    cluster = cluster_broker(a)
    if a.device_accounts:  # one account per road user, one password for all
        cluster = broker_settings(cluster.url, a.ca_file, "device", a.device_password_env)
    print(
        f"laas simulate: {len(trace.fixes)} fixes of {len(scenario.users)} road users "
        f"at {a.speedup:g}x real time",
        file=sys.stderr,
    )
    live = run_participants(
        cluster,
        trace,
        account_prefix=a.prefix if a.device_accounts else None,
        speedup=a.speedup,
        reply_timeout=max(5.0, 2 * a.max_age + 1.0),  # the participant's own limit, and more
        max_age=a.max_age,
        progress=progress_printer("  sent", "fixes"),
        hdmap=hdmap,  # a silent user's own answer goes on the map's lanes
        service_keys={"laas": a.service_key} if a.service_key else {},
        anchors=a.trust_anchor,
        core_key=a.core_key,
    )
    out = sys.stdout if a.out is None else open(a.out, "w", encoding="utf-8")  # noqa: SIM115
    try:
        for fix, answer in zip(trace.fixes, live.answers, strict=True):
            if answer is not None:
                out.write(format_answer(fix.user, answer) + "\n")
    finally:
        if out is not sys.stdout:
            out.close()
    for error in live.errors[:10]:
        print(f"laas simulate: {error}", file=sys.stderr)
    if not live.answered:
        print("laas simulate: no fix was answered", file=sys.stderr)
        return 1
    r = score(hdmap, trace, live.answers)
    print(
        f"laas simulate: {live.answered}/{len(trace.fixes)} answered; lane accuracy "
        f"{r.accuracy:.3f}, AED {r.aed:.2f} m (raw fixes {r.raw_aed:.2f} m)",
        file=sys.stderr,
    )
    return 0


def add_simulate(sub: Subcommands) -> None:
    """`laas simulate`."""
    p = sub.add_parser("simulate", help="run a scenario's road users as live LDM participants")
    connection_args(p, "LAAS")
    scenario_args(p)
    p.add_argument("--speedup", type=float, default=1.0, help="faster than real time by")
    max_age_arg(p, "drop replies older than this, and fail a request after 2x this + 1 s")
    p.add_argument("--out", help="write the answers (JSON Lines) here; default stdout")
    device_account_args(p, "road user")
    p.add_argument(
        "--prefix",
        default="sim-",
        help="the road users' client ids (and accounts) with --device-accounts: PREFIX + user",
    )
    p.add_argument(
        "--list-accounts",
        action="store_true",
        help="print the accounts the users need with --device-accounts, and exit",
    )
    pinned_key_args(p, anchors=True)
    p.set_defaults(func=_cmd_simulate)
