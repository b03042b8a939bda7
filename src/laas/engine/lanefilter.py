"""The lane filter: how the engine places a user on the lanes of its road element.

The engine keeps each user's track and finds its road element; a `LaneFilter` does the
rest. Two implement it: `PaperLaneFilter` (the paper's joint-hypothesis filter, section
IV-D) and `CooperativeLaneFilter` (the default: the common GNSS error and every user's
lane estimated jointly). `laas.engine.engine.make_lane_filter` picks one by
`EngineConfig.mode`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from laas.config import EngineConfig
from laas.engine.common_error import CommonError
from laas.engine.handover import AreaState, LaneState
from laas.engine.tracking import Track
from laas.map.hdmap import Segment

__all__ = ["LaneFilter", "Placement"]


@dataclass(frozen=True, slots=True)
class Placement:
    """A user placed on a lane: the answer before it is turned into WGS84."""

    lane: int
    probability: float  # P(lane)
    point: np.ndarray  # (2,) UTM position on the lane, common error removed
    common_cov: np.ndarray  # (2, 2) covariance of the common error removed, m^2
    cross: float  # 1-sigma across the road, m
    tangent: np.ndarray | None = None  # (2,) the road's direction at the point, if known
    station: float | None = None  # the point's distance along the element, m, if known


class LaneFilter(ABC):
    """Places users on lanes; holds whatever state the method needs between fixes."""

    def __init__(self, config: EngineConfig) -> None:
        self.config = config

    @abstractmethod
    def correction(self, position: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The common error to remove at `position` at time t, and its covariance."""

    @abstractmethod
    def step(self, user: str, track: Track, segment: Segment, t: float) -> Placement:
        """Place `user`, whose track has just taken a fix at time t, in `segment`."""

    def corrections(self, positions: np.ndarray, t: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """`correction` at each of (n, 2) positions, for a batch whose time is t."""
        return [self.correction(p, t) for p in positions]

    def step_many(self, work: Sequence[tuple[str, Track, Segment, float]]) -> list[Placement]:
        """Place a batch of (user, track, segment, t), every user at most once; by default
        `step` of each in turn."""
        return [self.step(user, track, segment, t) for user, track, segment, t in work]

    @abstractmethod
    def leave(self, user: str) -> None:
        """Forget `user`'s lane state (off the map, track restarted, forgotten)."""

    def common_errors(self) -> list[CommonError]:
        """The common-error estimates per area (none unless the method keeps them)."""
        return []

    @abstractmethod
    def segment_groups(self) -> int:
        """Road elements that hold users now."""

    def export_lanes(self, user: str) -> LaneState | None:
        """`user`'s lane table for a hand-over (`laas.engine.handover`); None: none kept."""
        return None

    def import_lanes(self, user: str, state: LaneState, segment: Segment, at: np.ndarray) -> None:
        """Take `user`'s lane table from a hand-over, in `segment`, the user at `at`
        (by default none is kept: the user starts afresh)."""
        return None

    def record_areas(self) -> None:
        """Keep each area's own evidence from now on, for `export_areas` (by default
        there are no areas)."""
        return None

    def export_areas(self, box: tuple[float, float, float, float]) -> list[AreaState]:
        """The own evidence since the last export of the areas whose centre lies in
        (x0, y0, x1, y1)."""
        return []

    def import_areas(
        self,
        source: str,
        states: list[AreaState],
        box: tuple[float, float, float, float] | None = None,
    ) -> int:
        """Fold in a neighbour's own evidence of its areas (from `source`) whose centre
        lies in `box` (None: all); how many."""
        return 0
