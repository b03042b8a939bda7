"""The LaaS worker: the positioning engine offered as an LDM service named `laas`.

It takes every participant's `GpsMeasurement` through the provider's one wildcard
subscription, keeps a Kalman track per pseudonym (a rotated pseudonym simply starts a
new track; the common-error estimate, which is not per user, carries the group over),
and answers each accepted fix with a `CorrectedPosition`. A fix it cannot use gets an
error reply that names the field and the problem. The handler runs on the provider's
one dispatch thread, so the engine needs no lock; it takes the fixes that waited together
as one batch (`handle_many`), and the engine gives each the answer it would have given
alone.

What the worker refuses, each with an error reply ``{"error": {"kind", "message",
"fields"}}`` and a counter in `WorkerStats`, touching no other pseudonym's state:

- ``invalid``: not a `GpsMeasurement` (wrong types, missing or unknown fields, NaN,
  infinities, latitude/longitude out of range);
- ``outside``: a fix farther than ``max_distance`` metres from the map's bounds (the
  service area; it would also pull the shared common-error estimate);
- ``clock``: a timestamp more than ``max_past`` seconds behind the worker's wall clock,
  or more than ``max_future`` seconds ahead of where the pseudonym's first fix puts it:

      t <= t0 + max_speedup * (now - wall0) + max_future      (t0 at wall clock wall0)

  ``max_speedup`` is 1 for live participants, so a phone's fix dated 5 minutes ahead is
  refused instead of locking its later fixes out as stale. A worker that serves a
  simulator sped up by a factor s (which sends timestamps running ahead by (1 - 1/s) of
  the scenario time) is started with ``max_speedup`` >= s (`laas worker --max-speedup`,
  and `LocalDeployment`, which serves simulations);
- ``stale``: a duplicate, or older than the pseudonym's last fix;
- ``internal``: the engine failed on this fix (logged; a bug to report).

A regional worker (`laas.worker.regions`) hands its users over at its border: while a
fix lies past the border (outside its ``strip``), the answer carries the user's state
(`Engine.export_user`) sealed with the key the regional workers share
(`ldm.Provider.seal_shared`) as ``handover``; a fix that brings one (the first to this
worker, `ldm.RoutedSession`) has it opened (`ldm.Provider.open_shared`) and taken
(`Engine.import_user`) before the engine answers it. One that cannot be opened or read
is counted (``handover_refused``) and the fix answered as a new track's. Every
``share_every`` seconds the worker sends its users' evidence about the common error of
its areas to the other regional workers (`Provider.note`), and takes what the others
send for the areas its coverage holds (`Engine.import_areas`); a region of one has no
neighbour, and neither records its evidence nor sends notes.

A pseudonym's state (its track, its clock anchor) is forgotten ``track_timeout``
seconds of the worker's wall clock after its last accepted fix, whatever its timestamps
say, and the worker holds at most ``max_pseudonyms`` of them (the least recently heard
goes first), so neither a participant's clock nor a flood of pseudonyms grows its memory.
"""

from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import version
from typing import Any, Protocol

from pydantic import Field, ValidationError

from laas.config import EngineConfig, Settings
from laas.engine.engine import Engine
from laas.engine.handover import (
    HandoverError,
    areas_from_bytes,
    areas_to_bytes,
    user_from_bytes,
    user_to_bytes,
)
from laas.engine.warm import warm_up
from laas.map.hdmap import HdMap
from laas.models import HANDOVER_MAX, CorrectedPosition, ErrorReply, GpsMeasurement, problems
from laas.worker.regions import Region
from ldm import BrokerSettings, Provider, Request, ServiceSpec
from ldm.errors import CryptoError
from ldm.security.identity import SigningKey

__all__ = [
    "SERVICE_NAME",
    "LaasService",
    "Observation",
    "WorkerConfig",
    "WorkerStats",
    "service_spec",
    "start_worker",
]

SERVICE_NAME = "laas"
_HANDOVER_AAD = "laas-handover/1"

log = logging.getLogger(__name__)


class SharedKey(Protocol):
    """Seals and opens what only the regional workers may read (`ldm.Provider`)."""

    def seal_shared(self, plaintext: bytes, context: str) -> str: ...

    def open_shared(self, sealed: str, context: str) -> bytes: ...


def service_spec(region: Region | None = None) -> ServiceSpec:
    """What the worker announces: name, version and the two wire schemas; a regional
    worker, its own name among the regions of `laas` and its coverage
    (`laas.worker.regions`)."""
    return ServiceSpec(
        name=SERVICE_NAME if region is None else region.name,
        version=version("laas"),
        description="Lane-level cooperative positioning: send GNSS fixes, get lane positions back.",
        input_schema=GpsMeasurement.model_json_schema(),
        output_schema=CorrectedPosition.model_json_schema(),
        family=None if region is None else SERVICE_NAME,
        coverage=None if region is None else region.coverage,
    )


class WorkerConfig(Settings):
    """The worker's limits on its input, validated once at start."""

    max_future: float = Field(
        default=120.0, ge=0, description="a session's first fix may lead the clock by, s"
    )
    max_past: float = Field(default=600.0, gt=0, description="a fix may lag the clock by, s")
    max_speedup: float = Field(
        default=1.0,
        ge=1,
        description="later fixes may run this much faster than real time (simulators only)",
    )
    max_distance: float = Field(
        default=10_000.0, ge=0, description="fixes this far outside the map are refused, m"
    )
    max_pseudonyms: int = Field(
        default=100_000, ge=1, description="pseudonyms held at once; the stalest go first"
    )
    expire_every: float = Field(default=1.0, gt=0, description="housekeeping interval, s")
    share_every: float = Field(
        default=1.0,
        gt=0,
        description="a regional worker sends its area evidence this often (fix time), s",
    )


@dataclass
class _Session:
    """What the worker remembers of a pseudonym besides its track (wall clock, seconds)."""

    t0: float  # timestamp of its first accepted fix
    wall0: float  # wall clock then
    last: float  # wall clock at its last accepted fix


@dataclass(frozen=True, slots=True)
class Observation:
    """One answered fix as the worker saw it: pseudonym, the fix and the answer."""

    pseudonym: str
    fix: GpsMeasurement
    answer: CorrectedPosition


@dataclass
class WorkerStats:
    """What the worker did with its input."""

    answered: int = 0
    invalid: int = 0
    refused: int = 0  # duplicates and fixes older than the track's last
    outside: int = 0
    clock: int = 0
    failed: int = 0
    expired: int = 0  # pseudonyms forgotten after track_timeout of silence
    evicted: int = 0  # pseudonyms forgotten because max_pseudonyms were held
    engine_seconds: float = 0.0  # time spent in the engine (perf_counter)
    handed_out: int = 0  # answers that carried the user's state for the next worker
    handed_in: int = 0  # fixes whose hand-over was taken
    handover_refused: int = 0  # hand-overs that could not be opened or read
    handover_skipped: int = 0  # states too large to hand over (models.HANDOVER_MAX)

    @property
    def refusals(self) -> dict[str, int]:
        """The fixes refused, by the kind of their error reply."""
        return {
            "invalid": self.invalid,
            "clock": self.clock,
            "outside": self.outside,
            "stale": self.refused,
            "internal": self.failed,
        }

    def summary(self) -> str:
        """One line: answered, and every refusal by kind.

        >>> WorkerStats(answered=5, clock=2, outside=1).summary()
        '5 answered, 3 refused (2 clock, 1 outside)'
        """
        kinds = {k: n for k, n in self.refusals.items() if n}
        detail = ", ".join(f"{n} {k}" for k, n in kinds.items())
        return f"{self.answered} answered, {sum(kinds.values())} refused" + (
            f" ({detail})" if detail else ""
        )


class LaasService:
    """Decode, correct, answer. `handle` is the provider's handler."""

    def __init__(
        self,
        hdmap: HdMap,
        config: EngineConfig | None = None,
        worker: WorkerConfig | None = None,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        region: Region | None = None,
        shared: SharedKey | None = None,
    ) -> None:
        self.engine = Engine(hdmap, config)
        self.region = region
        self.shared = shared if region is not None else None
        """Seals and opens hand-overs (the worker's `ldm.Provider`, which `start_worker`
        sets); None: no hand-over (one worker for the map)."""
        self.notes: Callable[[bytes], None] | None = None
        """Sends the area evidence to the other regional workers (`Provider.note`); None:
        not shared."""
        if region is not None and self._neighbours():
            self.engine.record_areas()
        self.config = worker or WorkerConfig()
        self.stats = WorkerStats()
        self._map = hdmap
        # The service area in degrees, computed once: the map's UTM bounds grown by
        # max_distance, so the per-fix check needs no projection (the engine does that).
        x0, y0, x1, y1 = hdmap.bounds
        d = self.config.max_distance
        corners = [
            hdmap.projection.to_wgs84(x, y) for x in (x0 - d, x1 + d) for y in (y0 - d, y1 + d)
        ]
        self._area = (
            min(c[0] for c in corners),
            min(c[1] for c in corners),
            max(c[0] for c in corners),
            max(c[1] for c in corners),
        )
        self._clock = clock
        self._wall = wall_clock
        self._next_expiry = clock() + self.config.expire_every
        self._next_share = -math.inf  # fix time (s) of the next share of area evidence
        self._sessions: OrderedDict[str, _Session] = OrderedDict()  # least recent first
        self.observer: Callable[[Sequence[Observation]], None] | None = None
        """Shown every batch of answered fixes, on the dispatch thread (a live map);
        None: nobody watches. It must be quick, and it learns only what the worker
        knows: pseudonyms, fixes and answers."""
        self.timer: Callable[[str, float], None] | None = None
        """Told ("engine", seconds) for each batch the engine answers; None: not timed
        (`laas.worker.metrics.watch_worker` sets it)."""

    @property
    def sessions(self) -> int:
        """Pseudonyms the worker holds state for (tracks and clock anchors)."""
        return len(self._sessions)

    def handle(self, request: Request) -> Mapping[str, Any]:
        """One fix of one pseudonym -> its corrected position, or an error reply."""
        return self.handle_many([request])[0]

    def handle_many(self, requests: Sequence[Request]) -> list[Mapping[str, Any]]:
        """Fixes that waited together -> one reply each, in order: each is checked, the
        engine takes the accepted ones as one batch (`Engine.process_many`, which answers
        as it would one at a time), and silent pseudonyms are forgotten after."""
        replies: list[Mapping[str, Any]] = [{} for _ in requests]
        work: list[tuple[int, str, GpsMeasurement]] = []
        now = self._wall()
        for i, request in enumerate(requests):
            checked = self._check(request, now)
            if isinstance(checked, ErrorReply):
                replies[i] = checked.model_dump()
            else:
                work.append((i, request.pseudonym, checked))
        if work:
            started = time.perf_counter()
            self._hand_in(work)
            try:
                answers = self.engine.process_many([(u, m) for _, u, m in work])
            except Exception:
                self.stats.failed += len(work)
                log.exception("the engine failed on a batch of %d fixes", len(work))
                failed = ErrorReply.of(
                    "internal", "the service failed on this fix; it has been logged"
                ).model_dump()
                for i, _, _ in work:
                    replies[i] = failed
                return replies
            spent = time.perf_counter() - started
            self.stats.engine_seconds += spent
            if self.timer is not None:
                self.timer("engine", spent)
            for (i, _, m), answer in zip(work, answers, strict=True):
                replies[i] = self._reply(m, answer)
            if self.shared is not None:
                self._hand_out(work, answers, replies)
            if self.observer is not None:
                seen = [
                    Observation(u, m, a)
                    for (_, u, m), a in zip(work, answers, strict=True)
                    if a is not None
                ]
                try:
                    self.observer(seen)
                except Exception:
                    log.exception("the observer failed; the answers went out as usual")
        self._housekeep(now)
        if work:
            self._share(max(m.timestamp for _, _, m in work) / 1000.0)
        return replies

    # -- regions: hand-over and shared areas (module docstring) ----------------------------

    def _hand_in(self, work: Sequence[tuple[int, str, GpsMeasurement]]) -> None:
        """Take the hand-overs the fixes bring, before the engine answers them."""
        for _, pseudonym, m in work:
            if m.handover is None:
                continue
            try:
                if self.shared is None:
                    raise CryptoError("this worker serves no region: it takes no hand-over")
                state = user_from_bytes(self.shared.open_shared(m.handover, _HANDOVER_AAD))
                if self.engine.import_user(pseudonym, state):
                    self.stats.handed_in += 1
            except (CryptoError, HandoverError) as exc:
                self.stats.handover_refused += 1
                # the first said loudly (workers under different identity keys refuse
                # every one), the rest counted (laas_handovers_total{way="refused"})
                log.log(
                    logging.WARNING if self.stats.handover_refused == 1 else logging.DEBUG,
                    "a hand-over was refused, the fix taken as a new track's (%s); do all "
                    "regional workers serve under one identity key (--identity)?",
                    exc,
                )

    def _hand_out(
        self,
        work: Sequence[tuple[int, str, GpsMeasurement]],
        answers: Sequence[CorrectedPosition | None],
        replies: list[Mapping[str, Any]],
    ) -> None:
        """Add the user's sealed state to each answer to a fix past the border."""
        assert self.region is not None and self.region.strip is not None
        assert self.shared is not None
        x0, y0, x1, y1 = self.region.strip
        xy = self._map.projection.to_utm_array(
            [m.longitude for _, _, m in work], [m.latitude for _, _, m in work]
        )
        for (i, pseudonym, _), answer, (x, y) in zip(work, answers, xy, strict=True):
            if answer is None or (x0 <= x <= x1 and y0 <= y <= y1):
                continue
            state = self.engine.export_user(pseudonym)
            if state is not None:
                token = self.shared.seal_shared(user_to_bytes(state), _HANDOVER_AAD)
                if len(token) > HANDOVER_MAX:  # a wide lane table: the user starts afresh
                    self.stats.handover_skipped += 1
                    continue
                replies[i] = {**replies[i], "handover": token}
                self.stats.handed_out += 1

    def _share(self, t: float) -> None:
        """Every share_every s of the fixes' time (a simulation sped up shares as
        often as live): this worker's own area evidence to the other regional workers."""
        if self.notes is None or not self._neighbours() or t < self._next_share:
            return
        self._next_share = t + self.config.share_every
        states = self.engine.export_areas(self._reach())
        if states:
            try:
                self.notes(areas_to_bytes(states))
            except Exception:
                log.exception("the area evidence was not sent; it is lost to the neighbours")

    def _neighbours(self) -> bool:
        """Whether this worker's region has neighbours to share area evidence with."""
        return self.region is not None and self.region.count > 1

    def take_note(self, sender: str, payload: bytes) -> None:
        """A sibling's area evidence (`Provider`'s ``on_note``, the dispatch thread)."""
        try:
            self.engine.import_areas(sender, areas_from_bytes(payload), self._reach())
        except HandoverError as exc:
            log.warning("area evidence from %s refused: %s", sender, exc)

    def _reach(self) -> tuple[float, float, float, float]:
        """The areas this worker shares and takes: centres in its box grown by half an
        area (an area reaches that far)."""
        assert self.region is not None
        x0, y0, x1, y1 = self.region.box
        m = self.engine.config.bias_area / 2.0
        return (x0 - m, y0 - m, x1 + m, y1 + m)

    def _check(self, request: Request, now: float) -> GpsMeasurement | ErrorReply:
        """The request's fix, or why it is refused; an accepted fix's session is noted."""
        try:
            measurement = GpsMeasurement.model_validate(request.payload)
        except ValidationError as exc:
            self.stats.invalid += 1
            found = problems(exc)
            summary = "; ".join(f"{field}: {problem}" for field, problem in found)
            return ErrorReply.of("invalid", f"measurement refused: {summary}", *found)
        t = measurement.timestamp / 1000.0
        refusal = self._check_clock(request.pseudonym, t, now)
        if refusal is None:
            refusal = self._check_area(measurement)
        if refusal is not None:
            return refusal
        session = self._sessions.get(request.pseudonym)
        if session is None:
            self._sessions[request.pseudonym] = _Session(t, now, now)
        else:
            session.last = now
            self._sessions.move_to_end(request.pseudonym)
        return measurement

    def _reply(self, m: GpsMeasurement, answer: CorrectedPosition | None) -> Mapping[str, Any]:
        if answer is None:
            self.stats.refused += 1
            return ErrorReply.of(
                "stale",
                f"timestamp {m.timestamp} is not newer than this session's last fix",
                ("timestamp", "not newer than the last fix"),
            ).model_dump()
        self.stats.answered += 1
        return answer.model_dump()

    def _housekeep(self, now: float) -> None:
        """Forget the pseudonyms silent for track_timeout (checked every expire_every s)
        and, past max_pseudonyms, the stalest."""
        tick = self._clock()
        if tick >= self._next_expiry:
            self._next_expiry = tick + self.config.expire_every
            timeout = self.engine.config.track_timeout
            while self._sessions:
                oldest, stalest = next(iter(self._sessions.items()))
                if now - stalest.last <= timeout:
                    break
                del self._sessions[oldest]
                self.engine.forget(oldest, expired=True)
                self.stats.expired += 1
        while len(self._sessions) > self.config.max_pseudonyms:
            gone, _ = self._sessions.popitem(last=False)
            self.engine.forget(gone)
            self.stats.evicted += 1

    def _check_clock(self, pseudonym: str, t: float, now: float) -> ErrorReply | None:
        """Refuse a timestamp too far behind the wall clock, or too far ahead of it."""
        c = self.config
        problem = None
        if t < now - c.max_past:
            problem = f"{now - t:.0f} s behind the service's clock (limit {c.max_past:g} s)"
        else:
            session = self._sessions.get(pseudonym)
            if session is None and t > now + c.max_future:
                problem = (
                    f"{t - now:.0f} s ahead of the service's clock "
                    f"(limit {c.max_future:g} s for a session's first fix)"
                )
            elif session is not None:
                limit = session.t0 + c.max_speedup * max(0.0, now - session.wall0) + c.max_future
                if t > limit:
                    problem = (
                        f"runs ahead of the service's clock more than {c.max_speedup:g} "
                        "times faster than real time since this session's first fix"
                    )
        if problem is None:
            return None
        self.stats.clock += 1
        return ErrorReply.of(
            "clock",
            f"measurement refused: timestamp: {problem}; synchronise the clock",
            ("timestamp", problem),
        )

    def _check_area(self, m: GpsMeasurement) -> ErrorReply | None:
        """Refuse a fix outside the map's area (plus ``max_distance``)."""
        lon0, lat0, lon1, lat1 = self._area
        if lon0 <= m.longitude <= lon1 and lat0 <= m.latitude <= lat1:
            return None
        self.stats.outside += 1
        d = self.config.max_distance
        problem = f"more than {d / 1000:g} km outside the service area of map {self._map.source}"
        return ErrorReply.of(
            "outside",
            f"measurement refused: latitude/longitude: {problem}",
            ("latitude", problem),
            ("longitude", problem),
        )


def start_worker(
    cluster: BrokerSettings | str,
    hdmap: HdMap,
    config: EngineConfig | None = None,
    worker: WorkerConfig | None = None,
    *,
    region: Region | None = None,
    **provider_settings: Any,
) -> tuple[Provider, LaasService]:
    """Connect to a service-cluster broker, announce `laas` (or, for a region, its
    regional worker of `laas`) and serve until stopped.

    ``provider_settings`` go to `ldm.ProviderConfig` (``max_queue``, ``max_age``,
    ``data_qos``, ...).
    """
    identity = provider_settings.pop("identity", None)
    if identity is None and region is not None:
        path = provider_settings.get("identity_file")
        identity = SigningKey.load_or_create(path) if path else SigningKey.generate()
    service = LaasService(hdmap, config, worker, region=region)
    # the engine's arithmetic compiled (or loaded from numba's cache) before the first fix
    log.info("laas worker: the engine's arithmetic ready in %.1f s", warm_up(hdmap, config))
    provider = Provider.create(
        cluster,
        service_spec(region),
        service.handle,
        batch_handler=service.handle_many,
        identity=identity,
        on_note=None if region is None else service.take_note,
        **provider_settings,
    )
    if region is not None:
        service.shared = provider
        service.notes = provider.note
    provider.start()
    log.info("laas worker serving map %s on %s", hdmap.source, BrokerSettings.of(cluster).url)
    if region is not None:
        log.info("laas worker serving region %s", region.name)
    return provider, service
