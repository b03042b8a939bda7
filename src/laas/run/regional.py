"""Regional workers live: the same road users through one worker and through N.

`compare_live` starts a local deployment (`LocalDeployment`: three brokers, two cores)
with one worker, drives the trace's users through it as LDM participants
(`run_participants`, which route by region with `ldm.RoutedSession`), then the same
with N regional workers, and scores both against the truth as `laas.evaluation.regional` does
offline (`compare_answers`). ``laas regions --live`` prints it.
"""

from __future__ import annotations

from laas.config import EngineConfig
from laas.evaluation.regional import RegionalComparison, compare_answers
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition
from laas.run.deployment import BrokerChoice, LocalDeployment
from laas.run.participants import run_participants
from laas.sim.scenario import Trace
from laas.worker.regions import split

__all__ = ["compare_live", "live_answers"]


def live_answers(
    hdmap: HdMap,
    trace: Trace,
    config: EngineConfig | None,
    workers: int,
    *,
    speedup: float = 20.0,
    brokers: BrokerChoice = "auto",
) -> list[CorrectedPosition | None]:
    """Every fix's answer (None: none came) through a local deployment of `workers`."""
    with LocalDeployment(hdmap, config, brokers=brokers, regions=workers) as deployment:
        live = run_participants(deployment.user_url, trace, speedup=speedup, **deployment.trust)
    return list(live.answers)


def compare_live(
    hdmap: HdMap,
    trace: Trace,
    config: EngineConfig | None = None,
    workers: int = 2,
    *,
    speedup: float = 20.0,
    brokers: BrokerChoice = "auto",
    after: int = 10,
) -> RegionalComparison:
    """One live worker against `workers` live regional ones (module docstring)."""
    one = live_answers(hdmap, trace, config, 1, speedup=speedup, brokers=brokers)
    many = live_answers(hdmap, trace, config, workers, speedup=speedup, brokers=brokers)
    regions = split(hdmap, workers)  # as LocalDeployment cuts the map
    return compare_answers(hdmap, trace, regions, one, many, handover=True, after=after)
