"""Integrity: whether an answer's stated confidence holds against the truth.

An answer is used to decide things, so its lane probability and its accuracies are scored
like its position. Per run, counts that add up over runs (so a suite pools its answers):

- **reliability**: the answers binned by their lane probability p (`BINS` bins of width
  0.1); per bin the count, the sum of p and the number right. The expected calibration
  error is  ECE = sum_b (n_b / N) |mean p_b - right_b / n_b|;
- **confident and wrong** (hazardously misleading information): answers that say
  p >= 0.9 (and p >= 0.99) and whose lane is wrong, as a share of all answers;
- **how sure that share is**: a suite's runs are a sample of the roads and crowds it
  stands for, and confident-and-wrong answers come in runs (a group one lane over for a
  minute), not one by one. `run_interval` therefore resamples whole runs (a bootstrap
  over runs, `RESAMPLES` times, with a fixed seed) and gives the 5th and 95th
  percentile of the pooled share: a 90 % interval for the share on unseen runs of
  the same families;
- **consistency of the accuracies**: the share of answers whose error across the road is
  within once and twice the reported ``accuracy_cross`` (and along the road,
  ``accuracy_along``). For an honest Gaussian 1-sigma these are 68 % and 95 %.

A lane is right by geometry (`lane_holds`): the true position lies inside the answered
lane, its centre line +- half its width, at that place; or the answered lane, continued
across the seams of its road's elements, is the truth's lane (`same_lane`). So the same
physical lane counts wherever a map cuts its road into elements, and an answer on the
right lane of the next element (its position off along the road, where the common error
cannot be seen) is scored for its lane by this and for its position by the AED.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from laas.map.hdmap import HdMap, Segment

__all__ = [
    "BINS",
    "CHAIN_REACH",
    "END_TOLERANCE",
    "Integrity",
    "IntegrityTally",
    "lane_holds",
    "lane_right",
    "run_interval",
    "same_lane",
]

BINS = 10
"""Reliability bins of the lane probability, each 0.1 wide."""

END_TOLERANCE = 1.0
"""m: a true position this far past either end of the answered element still counts as in
it (elements meet end to end; the true position of a user on the seam may lie on either)."""


RESAMPLES = 2000
"""Bootstrap resamples of the runs behind `run_interval`."""

CHAIN_REACH = 30.0
"""m of road between the answered element and the truth's (the elements wholly between
them) within which a lane continued across seams still counts as the same lane: twice
the largest common error along the road of the scenario families (15 m)."""


def lane_holds(hdmap: HdMap, segment: str, lane: int, x: float, y: float) -> bool:
    """True if (x, y) lies inside lane `lane` of `segment`: |d - o_l(s)| <= w_l / 2 at the
    station s of the point, within `END_TOLERANCE` of the element's ends."""
    seg = hdmap.segments.get(segment)
    if seg is None or not 0 <= lane < len(seg.lanes):
        return False
    s, d = seg.frame(x, y)
    if not -END_TOLERANCE <= s <= seg.length + END_TOLERANCE:
        return False
    centre = float(seg.lane_offsets(s)[lane])
    return abs(d - centre) <= seg.lanes[lane].width / 2.0


def same_lane(hdmap: HdMap, answered: tuple[str, int], truth: tuple[str, int]) -> bool:
    """True if lane `answered` (segment, lane), followed across the seams of its road
    (successors and predecessors, each lane into the lane of the next element that holds
    its end point), reaches lane `truth` within `CHAIN_REACH` m of road between them."""
    if answered == truth:
        return True
    seen = {answered}
    frontier = [(answered, 0.0)]
    while frontier:
        (seg_id, lane), far = frontier.pop()
        seg = hdmap.segments[seg_id]
        crossed = 0.0 if (seg_id, lane) == answered else seg.length
        if far + crossed > CHAIN_REACH:
            continue
        for nxt, at_end in _neighbours(hdmap, seg_id):
            other = _continued(hdmap, seg, lane, hdmap.segments[nxt], at_end)
            if other is None or (nxt, other) in seen:
                continue
            if (nxt, other) == truth:
                return True
            seen.add((nxt, other))
            frontier.append(((nxt, other), far + crossed))
    return False


def lane_right(
    hdmap: HdMap,
    answered: tuple[str | None, int | None],
    truth: tuple[str, int],
    x: float,
    y: float,
) -> bool:
    """Whether an answered (segment, lane) is right for a truth at (x, y) on lane `truth`:
    it holds the true position (`lane_holds`) or continues into the truth's lane
    (`same_lane`)."""
    segment, lane = answered
    if segment is None or lane is None or segment not in hdmap.segments:
        return False
    return lane_holds(hdmap, segment, lane, x, y) or same_lane(hdmap, (segment, lane), truth)


def _neighbours(hdmap: HdMap, segment: str) -> list[tuple[str, bool]]:
    """The elements that join `segment`: (id, True) after its end, (id, False) before its
    start."""
    after = [(s, True) for s in hdmap.segments[segment].successors]
    return after + [(s, False) for s in hdmap.predecessors(segment)]


def _continued(hdmap: HdMap, seg: Segment, lane: int, nxt: Segment, at_end: bool) -> int | None:
    """The lane of `nxt` that holds the end (or start) point of `lane` of `seg`, if any."""
    s = seg.length if at_end else 0.0
    x, y = seg.point(s, float(seg.lane_offsets(s)[lane]))
    t, d = nxt.frame(x, y)
    offsets = nxt.lane_offsets(t)
    k = int(np.argmin(np.abs(offsets - d)))
    return k if abs(d - float(offsets[k])) <= nxt.lanes[k].width / 2.0 else None


@dataclass
class IntegrityTally:
    """Counts of one run (or many, added up): see the module docstring."""

    answers: int = 0  # answers with a lane probability (placed on a lane or not)
    count: list[int] = field(default_factory=lambda: [0] * BINS)
    prob: list[float] = field(default_factory=lambda: [0.0] * BINS)
    right: list[int] = field(default_factory=lambda: [0] * BINS)
    wrong_90: int = 0  # said p >= 0.9 and wrong
    wrong_99: int = 0  # said p >= 0.99 and wrong
    said_90: int = 0  # said p >= 0.9
    sigma: int = 0  # answers with both accuracies
    cross_1: int = 0  # |error across| <= accuracy_cross
    cross_2: int = 0  # <= 2 accuracy_cross
    along_1: int = 0
    along_2: int = 0

    def add_answer(self, probability: float, right: bool) -> None:
        """One answer's lane probability and whether its lane was right."""
        k = min(int(probability * BINS), BINS - 1)
        self.answers += 1
        self.count[k] += 1
        self.prob[k] += probability
        self.right[k] += int(right)
        if probability >= 0.9:
            self.said_90 += 1
            self.wrong_90 += int(not right)
            self.wrong_99 += int(probability >= 0.99 and not right)

    def add_errors(
        self, cross: np.ndarray, along: np.ndarray, sigma_cross: np.ndarray, sigma_along: np.ndarray
    ) -> None:
        """|errors| across and along the road against their reported 1-sigma."""
        self.sigma += int(cross.size)
        self.cross_1 += int(np.sum(cross <= sigma_cross))
        self.cross_2 += int(np.sum(cross <= 2.0 * sigma_cross))
        self.along_1 += int(np.sum(along <= sigma_along))
        self.along_2 += int(np.sum(along <= 2.0 * sigma_along))

    def __add__(self, other: IntegrityTally) -> IntegrityTally:
        out = IntegrityTally()
        for name, mine in asdict(self).items():
            theirs = getattr(other, name)
            if isinstance(mine, list):
                setattr(out, name, [a + b for a, b in zip(mine, theirs, strict=True)])
            else:
                setattr(out, name, mine + theirs)
        return out

    @classmethod
    def total(cls, tallies: Iterable[IntegrityTally]) -> IntegrityTally:
        out = cls()
        for t in tallies:
            out = out + t
        return out

    def summary(self) -> Integrity:
        """The figures of these counts."""
        n = max(self.answers, 1)
        ece = sum(
            abs(p - r) for p, r in zip(self.prob, self.right, strict=True)
        )  # sum_b n_b |mean p_b - acc_b| = sum_b |sum p - right|
        s = max(self.sigma, 1)
        return Integrity(
            answers=self.answers,
            ece=ece / n if self.answers else math.nan,
            wrong_90=self.wrong_90 / n if self.answers else math.nan,
            wrong_99=self.wrong_99 / n if self.answers else math.nan,
            said_90=self.said_90 / n if self.answers else math.nan,
            said=[p / c if c else math.nan for p, c in zip(self.prob, self.count, strict=True)],
            right=[r / c if c else math.nan for r, c in zip(self.right, self.count, strict=True)],
            count=list(self.count),
            cross_1=self.cross_1 / s if self.sigma else math.nan,
            cross_2=self.cross_2 / s if self.sigma else math.nan,
            along_1=self.along_1 / s if self.sigma else math.nan,
            along_2=self.along_2 / s if self.sigma else math.nan,
        )


@dataclass(frozen=True)
class Integrity:
    """The integrity figures of a tally (shares of all answers; nan where none)."""

    answers: int
    ece: float  # expected calibration error of the lane probability
    wrong_90: float  # share of answers that said >= 0.9 and were wrong
    wrong_99: float  # ... >= 0.99 and wrong
    said_90: float  # share of answers that said >= 0.9
    said: list[float]  # per bin: mean stated probability
    right: list[float]  # per bin: share right
    count: list[int]  # per bin: answers
    cross_1: float  # share of errors across the road within 1 accuracy_cross
    cross_2: float  # within 2
    along_1: float
    along_2: float

    def as_dict(self) -> dict[str, object]:
        return asdict(self)

    def reliability(self) -> str:
        """The reliability table as two lines: the mean said and the share right per bin."""
        cells = [(s, r, c) for s, r, c in zip(self.said, self.right, self.count, strict=True) if c]
        said = " ".join(f"{s:5.2f}" for s, _, _ in cells)
        right = " ".join(f"{r:5.2f}" for _, r, _ in cells)
        count = " ".join(f"{c:5d}" if c < 100_000 else f"{c / 1000:4.0f}k" for _, _, c in cells)
        return f"said  {said}\nright {right}\nn     {count}"


def run_interval(
    tallies: Sequence[IntegrityTally], level: float = 0.9, resamples: int = RESAMPLES
) -> tuple[float, float]:
    """A `level` interval of the pooled confident-and-wrong share (said p >= 0.9 and
    wrong, over all answers) by resampling whole runs with replacement: with w_r and n_r
    run r's counts and R a resample, the share is sum_R w_r / sum_R n_r. (nan, nan)
    without answers.

    >>> run_interval([IntegrityTally(answers=100, wrong_90=5)] * 4)
    (0.05, 0.05)
    """
    wrong = np.array([t.wrong_90 for t in tallies], dtype=float)
    answers = np.array([t.answers for t in tallies], dtype=float)
    if answers.sum() <= 0.0:
        return math.nan, math.nan
    pick = np.random.default_rng(0).integers(0, len(tallies), (resamples, len(tallies)))
    total = answers[pick].sum(axis=1)
    share = np.divide(wrong[pick].sum(axis=1), total, out=np.zeros(resamples), where=total > 0)
    tail = (1.0 - level) / 2.0 * 100.0
    lo, hi = np.percentile(share, [tail, 100.0 - tail])
    return float(lo), float(hi)
