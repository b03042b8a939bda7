"""What several `laas` commands share: flag groups, and how a command reads them."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

from laas.config import EngineConfig
from laas.errors import ConfigError
from ldm import BrokerSettings
from ldm.ops.help import Parser
from ldm.ops.process import broker_settings

if TYPE_CHECKING:
    from laas.map.hdmap import HdMap
    from laas.sim.scenario import Scenario

__all__ = [
    "Subcommands",
    "chosen_scenario",
    "cluster_broker",
    "connection_args",
    "engine_args",
    "engine_config",
    "http_args",
    "max_age_arg",
    "pinned_key_args",
    "scenario_args",
    "write_plots",
]

Subcommands: TypeAlias = "argparse._SubParsersAction[Parser]"
"""What `laas`'s parser adds its subcommands to (each module's ``add_*`` takes it)."""


def engine_args(p: argparse.ArgumentParser) -> None:
    """The engine's flags: --mode, --no-kalman and the receiver's noise."""
    p.add_argument("--mode", choices=["default", "paper"], default="default", help="lane filter")
    p.add_argument("--no-kalman", action="store_true", help="use the raw fixes, unsmoothed")
    p.add_argument("--sigma-pos", type=float, default=1.0, help="receiver position noise, m")
    p.add_argument("--sigma-vel", type=float, default=0.25, help="receiver speed noise, m/s")
    p.add_argument("--sigma-heading", type=float, default=0.5, help="heading noise, degrees")


def engine_config(a: argparse.Namespace) -> EngineConfig:
    """The EngineConfig the flags of `engine_args` give (ConfigError names a bad one)."""
    return EngineConfig(
        mode=a.mode,
        kalman=not a.no_kalman,
        sigma_pos=a.sigma_pos,
        sigma_vel=a.sigma_vel,
        sigma_heading=a.sigma_heading,
    )


def connection_args(p: argparse.ArgumentParser, env_prefix: str) -> None:
    """The broker to connect to and its account: --cluster, --username, --password-env,
    --ca-file, each with its default from ``{env_prefix}_...``."""
    p.add_argument(
        "--cluster",
        default=os.environ.get(f"{env_prefix}_CLUSTER"),
        help=f"cluster broker, mqtt[s]://HOST:PORT (env {env_prefix}_CLUSTER)",
    )
    p.add_argument(
        "--username",
        default=os.environ.get(f"{env_prefix}_USERNAME"),
        help=f"user name on the broker (env {env_prefix}_USERNAME)",
    )
    p.add_argument(
        "--password-env",
        default=f"{env_prefix}_PASSWORD",
        help=f"environment variable holding the password (default {env_prefix}_PASSWORD)",
    )
    p.add_argument(
        "--ca-file",
        type=Path,
        default=os.environ.get(f"{env_prefix}_CA_FILE"),
        help=f"CA certificates for an mqtts:// broker (env {env_prefix}_CA_FILE)",
    )


def pinned_key_args(p: argparse.ArgumentParser, *, anchors: bool = False) -> None:
    """`--service-key` and `--core-key` (and, with `anchors`, `--trust-anchor`): the keys
    a participant pins (docs/security.md)."""
    p.add_argument(
        "--service-key",
        default=os.environ.get("LAAS_SERVICE_KEY"),
        help="pin the laas worker's identity (its public key; env LAAS_SERVICE_KEY)",
    )
    if anchors:
        p.add_argument(
            "--trust-anchor",
            action="append",
            default=[],
            metavar="KEY",
            help="trust a laas identity this anchor endorsed (repeatable)",
        )
    p.add_argument(
        "--core-key",
        default=os.environ.get("LAAS_CORE_KEY"),
        help="pin the user core's key: act only on notices it signed (env LAAS_CORE_KEY)",
    )


def max_age_arg(p: argparse.ArgumentParser, what: str) -> None:
    """`--max-age`: every hop drops what is older than its max_age (docs/brokers.md)."""
    p.add_argument(
        "--max-age",
        type=float,
        default=float(os.environ.get("LAAS_MAX_AGE", "2")),
        metavar="SECONDS",
        help=f"{what} (env LAAS_MAX_AGE; default 2 s). Give every hop the same: the "
        "cores' `ldm core --max-age`; on a NATS cluster about 10 s, the time it takes "
        "to elect new leaders after a node fails (docs/brokers.md)",
    )


def http_args(p: argparse.ArgumentParser, default: int | None) -> None:
    """--http and --http-host: the live map (`laas.worker.dashboard`)."""
    p.add_argument(
        "--http",
        type=int,
        metavar="PORT",
        default=os.environ.get("LAAS_HTTP_PORT", default),  # argparse converts a string
        help="serve the live map on this port; 0 picks a free one (env LAAS_HTTP_PORT; "
        + ("default: no live map)" if default is None else f"default {default})"),
    )
    p.add_argument(
        "--http-host",
        metavar="HOST",
        default=os.environ.get("LAAS_HTTP_HOST", "127.0.0.1"),
        help="address of the live map (env LAAS_HTTP_HOST; default 127.0.0.1)",
    )


def scenario_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="messe-hamburg", help="built-in scenario")
    p.add_argument(
        "--map",
        help="instead: road users roaming this lane map (GeoJSON, e.g. from laas map import)",
    )
    p.add_argument("--users", type=int, default=10, help="with --map: road users (default 10)")
    p.add_argument(
        "--duration", type=float, default=120.0, help="with --map: seconds (default 120)"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the GNSS errors (and of --map's users)"
    )
    p.add_argument("--sigma-pos", type=float, default=1.0, help="receiver position noise, m")
    p.add_argument("--sigma-vel", type=float, default=0.25, help="receiver speed noise, m/s")


def chosen_scenario(a: argparse.Namespace) -> tuple[Scenario, HdMap]:
    """The built-in scenario `--scenario`, or with `--map` users roaming that map (the
    flags of `scenario_args`)."""
    from laas.sim.roam import scenario_or_roam

    return scenario_or_roam(a.scenario, a.map, a.seed, users=a.users, duration=a.duration)


def write_plots(
    scenario: Scenario,
    hdmap: HdMap,
    out: Path,
    seed: int,
    sigma_pos: float,
    sigma_vel: float,
) -> list[Path]:
    """Fig. 3 and Fig. 4 of one seeded run into `out`; each file written is printed."""
    from laas.evaluation.plots import scenario_plots

    paths = scenario_plots(scenario, hdmap, out, seed, sigma_pos, sigma_vel)
    for p in paths:
        print(f"wrote {p}")
    return paths


def cluster_broker(a: argparse.Namespace) -> BrokerSettings:
    """The broker the flags of `connection_args` name; ConfigError without --cluster."""
    if not a.cluster:
        raise ConfigError("give the cluster broker: --cluster mqtt://HOST:PORT (or LAAS_CLUSTER)")
    return broker_settings(a.cluster, a.ca_file, a.username, a.password_env)
