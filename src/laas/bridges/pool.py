"""The devices a bridge serves, each one its own LDM participant.

A bridge (OwnTracks, gpsd, CAM) translates a device's messages into `GpsMeasurement`s
and hands them to a `DevicePool` under the device's name. The pool gives every device
its own `ldm.Participant` (its own MQTT connection and client id, so its own session,
pseudonyms and keys at the user core) the first time it is heard of, and forgets it,
closing the participant, once it has been silent for `track_timeout` seconds.

A device finds the service as every laas client does (`laas.discovery`): the worker
named `laas`, or the regional workers of `laas`. Each fix goes to the worker
whose region holds it (`ldm.RoutedSession`), so a device that drives across a border is
handed over to the next worker.

A device's fixes go on in the order they came, each once. A fix not newer than the
newest one the service accepted from the device, or dated as one still on its way (a
QoS 1 message the broker delivered twice, an OwnTracks phone's second fix within one
second of ``tst``, a receiver that repeats an epoch), is dropped here, logged at debug
level and counted (`PoolStats.stale`): the service would refuse it as stale. Only what
the service accepted moves a device's newest time on: a fix the service refuses (one
dated minutes ahead by a phone's wrong clock, say) is logged with the service's reason
and locks none of the device's later fixes out. The fixes that come while the session
opens wait in the device's queue and are sent, in order, by the thread that opened it,
before any later fix; a fix that comes once it is open is sent at once by the bridge's
thread. One lock per device keeps the two from overtaking each other (`_Device.lock`).

Threads: `submit`, `malformed` and `expire` may be called from any one thread (the
bridge's). Sessions are opened on a small thread pool, so a device whose session is
slow to open never holds up another. Answers are handed to the bridge's callback on
the device participant's thread; the callback must not block.

Nothing here logs a position, a password or a key: problems are logged by device name
and field, at most once per device per `log_interval`.
"""

from __future__ import annotations

import contextlib
import logging
import re
import threading
import time
from collections.abc import Callable
from concurrent.futures import CancelledError, Future, InvalidStateError, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from laas.deadreckon import dead_reckon
from laas.discovery import wait_for_service
from laas.errors import LaasError
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition, ErrorReply, GpsMeasurement, read_reply
from laas.worker.service import SERVICE_NAME
from ldm import (
    BrokerSettings,
    Participant,
    RequestRejected,
    RoutedSession,
    ServiceNotFound,
    SessionSilent,
)
from ldm.wire.topics import NAME_PATTERN

__all__ = [
    "Answer",
    "DevicePool",
    "LogLimiter",
    "Malformed",
    "PoolConfig",
    "PoolStats",
    "device_name",
]

log = logging.getLogger(__name__)

Answer = CorrectedPosition | ErrorReply
OnAnswer = Callable[[Answer], None]

_PART = re.compile(r"^[A-Za-z0-9_-]{1,60}$")


class Malformed(LaasError, ValueError):
    """A device message that is not a fix; the text says why, never with the values."""


def device_name(prefix: str, *parts: str) -> str:
    """The client id of a device: ``prefix`` + parts joined by ".", e.g. ``ot.alice.phone``.

    Parts may hold letters, digits, ``_`` and ``-`` only (no ".", so two devices never
    share a name); ValueError names the part otherwise.
    """
    for part in parts:
        if not _PART.match(part):
            raise ValueError(f"{part!r} cannot name a device: use 1-60 letters, digits, '_' or '-'")
    name = prefix + ".".join(parts)
    if not NAME_PATTERN.match(name):
        raise ValueError(f"{name!r} is not a valid MQTT client id; shorten the names")
    return name


class PoolConfig(BaseModel):
    """How a bridge's device participants connect and how long they are kept."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    cluster: BrokerSettings
    """The user-cluster broker the device participants connect to."""
    device_accounts: bool = False
    """Each device logs in as its own broker account, named as its client id, with the
    password of `cluster` (for a broker with ``use_username_as_clientid``, such as the
    compose deployment's). False: every device uses `cluster`'s account as it is."""
    service_keys: dict[str, str] = Field(default_factory=dict)
    anchors: list[str] = Field(default_factory=list)
    core_key: str | None = None
    track_timeout: float = Field(default=60.0, gt=0)
    """A device silent for this long (s) is forgotten: its participant is closed."""
    open_timeout: float = Field(default=10.0, gt=0)
    """How long (s) to wait for the broker, the service list and the session grant."""
    retry_after: float = Field(default=5.0, ge=0)
    """After a failed open, a device's fixes are dropped for this long (s), then retried."""
    log_interval: float = Field(default=60.0, ge=0)
    """At most one log line per device and kind of problem per this many seconds."""
    max_devices: int = Field(default=10_000, ge=1)


@dataclass
class PoolStats:
    """Counters of one pool (read them from any thread; they only grow, but `devices`)."""

    devices: int = 0  # devices held now
    opened: int = 0  # sessions opened
    forgotten: int = 0  # devices dropped after track_timeout of silence
    fixes: int = 0  # fixes submitted
    stale: int = 0  # fixes not newer than their device's last, dropped (not in `fixes`)
    answered: int = 0  # corrected positions received, or made while the session kept quiet
    silent: int = 0  # of them, dead-reckoned by the bridge (`laas.deadreckon`)
    refused: int = 0  # error replies from the service
    lost: int = 0  # fixes with no reply (no session, timeout, connection)
    malformed: int = 0  # device messages that were not a fix
    malformed_by_device: dict[str, int] = field(default_factory=dict)


class LogLimiter:
    """Logs a warning per key at most once per `interval` s, with how many were held back."""

    def __init__(self, interval: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.interval = interval
        self._clock = clock
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def warn(self, key: str, message: str, *args: object) -> bool:
        """Log `message % args` unless `key` was logged within the interval; True if logged."""
        now = self._clock()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self.interval:
                self._held[key] = self._held.get(key, 0) + 1
                return False
            held = self._held.pop(key, 0)
            if len(self._last) >= 100_000:  # bounded: forget the oldest keys
                for old in list(self._last)[:1000]:
                    del self._last[old]
            self._last[key] = now
        suffix = f" ({held} more like it since the last report)" if held else ""
        log.warning(message + suffix, *args)
        return True

    def forget(self, prefix: str) -> None:
        """Drop the keys that start with `prefix` (a device that was forgotten)."""
        with self._lock:
            for key in [k for k in self._last if k.startswith(prefix)]:
                del self._last[key]
                self._held.pop(key, None)


@dataclass
class _Device:
    name: str
    last_seen: float
    opened_at: float
    where: tuple[float, float]  # (longitude, latitude) of its first fix: its first worker
    session: Future[RoutedSession] = field(default_factory=Future)
    participant: Participant | None = None
    last: tuple[CorrectedPosition, GpsMeasurement] | None = None  # its last answer, and fix
    last_fix: GpsMeasurement | None = None  # its last fix sent on (for its motion)
    accepted: int | None = None  # the timestamp of its newest fix the service answered, ms
    pending: set[int] = field(default_factory=set)  # timestamps of its fixes on their way
    waiting: list[tuple[GpsMeasurement, OnAnswer]] = field(default_factory=list)
    ready: bool = False  # the session's outcome is known and `waiting` was sent on
    lock: threading.Lock = field(default_factory=threading.Lock)  # orders its sends


class DevicePool:
    """One LDM participant per device name; use as a context manager."""

    def __init__(
        self,
        config: PoolConfig,
        *,
        clock: Callable[[], float] = time.monotonic,
        service: str = SERVICE_NAME,
        hdmap: HdMap | None = None,
    ) -> None:
        self.config = config
        self.hdmap = hdmap
        """The lane map a silent device's own answer is placed on (`laas.deadreckon`);
        None: its last answered lane."""
        self.stats = PoolStats()
        self.service = service
        self._clock = clock
        self._devices: dict[str, _Device] = {}
        self._lock = threading.Lock()
        self._executor = ThreadPoolExecutor(max_workers=4, thread_name_prefix="bridge-open")
        self.limiter = LogLimiter(config.log_interval, clock)

    # --- the bridge's thread ------------------------------------------------------------

    def submit(self, name: str, fix: GpsMeasurement, on_answer: OnAnswer) -> None:
        """Send `fix` as device `name` (opened on first use); `on_answer` gets the reply."""
        now = self._clock()
        with self._lock:
            device = self._devices.get(name)
            failed = (
                device is not None
                and device.session.done()
                and (device.session.cancelled() or device.session.exception() is not None)
            )
            if failed and device is not None and now - device.opened_at >= self.config.retry_after:
                self._close(device)
                del self._devices[name]
                device = None
            if device is None:
                if len(self._devices) >= self.config.max_devices:
                    self.stats.lost += 1
                    self.limiter.warn(
                        f"{name}|full",
                        "device %s: not served, the bridge already serves %d devices (max_devices)",
                        name,
                        len(self._devices),
                    )
                    return
                device = _Device(name, now, now, (fix.longitude, fix.latitude))
                self._devices[name] = device
                self.stats.devices = len(self._devices)
                device.session.add_done_callback(lambda _f: self._flush(device))
                self._executor.submit(self._open, device)
            device.last_seen = now
            if fix.timestamp in device.pending or (
                device.accepted is not None and fix.timestamp <= device.accepted
            ):
                self.stats.stale += 1
                log.debug(
                    "device %s: a fix not newer than its last accepted or pending one, dropped",
                    name,
                )
                return
            device.pending.add(fix.timestamp)
            self.stats.fixes += 1
        with device.lock:
            if not device.ready:
                device.waiting.append((fix, on_answer))
                return
            self._send(device, device.session, fix, on_answer)

    def malformed(self, name: str, problem: str) -> None:
        """Count a message of device `name` that was not a fix, and log it (rate-limited)."""
        self.stats.malformed += 1
        by_device = self.stats.malformed_by_device
        if name in by_device or len(by_device) < self.config.max_devices:
            by_device[name] = by_device.get(name, 0) + 1
        self.limiter.warn(f"{name}|malformed", "device %s: malformed message: %s", name, problem)

    def expire(self) -> list[str]:
        """Forget every device silent for `track_timeout`; the names forgotten."""
        now = self._clock()
        with self._lock:
            old = [
                d for d in self._devices.values() if now - d.last_seen > self.config.track_timeout
            ]
            for d in old:
                del self._devices[d.name]
            self.stats.devices = len(self._devices)
            self.stats.forgotten += len(old)
        for d in old:
            self._close(d)
            self.limiter.forget(f"{d.name}|")
            self.stats.malformed_by_device.pop(d.name, None)
            log.info("device %s: silent for %.0f s, forgotten", d.name, now - d.last_seen)
        return [d.name for d in old]

    def drain(self, timeout: float) -> bool:
        """Wait up to `timeout` s until every fix submitted has its outcome; True if so."""
        deadline = time.monotonic() + timeout
        while True:
            s = self.stats
            if s.answered + s.refused + s.lost >= s.fixes:
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)

    def names(self) -> list[str]:
        """The devices held now."""
        with self._lock:
            return list(self._devices)

    def participant(self, name: str) -> Participant | None:
        """Device `name`'s participant, once its session is open (for tests and tools)."""
        with self._lock:
            device = self._devices.get(name)
        if device is None or not device.session.done() or device.session.exception():
            return None
        return device.participant

    def close(self) -> None:
        """Close every device's participant."""
        with self._lock:
            devices, self._devices = list(self._devices.values()), {}
            self.stats.devices = 0
        self._executor.shutdown(wait=True, cancel_futures=True)
        for d in devices:
            self._close(d)

    def __enter__(self) -> DevicePool:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    # --- the opening threads and the participants' threads ------------------------------

    def _open(self, device: _Device) -> None:
        c = self.config
        broker = c.cluster
        if c.device_accounts:
            broker = broker.model_copy(update={"username": device.name})
        try:
            participant = Participant.create(
                broker,
                client_id=device.name,
                service_keys=c.service_keys,
                anchors=c.anchors,
                core_key=c.core_key,
            )
            device.participant = participant
            participant.start(timeout=c.open_timeout)
            wait_for_service(participant, c.open_timeout, self.service)
            session = RoutedSession(participant, self.service, timeout=c.open_timeout)
            session.prepare(device.where)  # opened now, with the worker of its first fix
        except Exception as exc:  # any failure fails this device only
            if device.participant is not None:
                device.participant.stop()
            with contextlib.suppress(InvalidStateError):
                device.session.set_exception(exc)
            return
        try:
            device.session.set_result(session)
        except InvalidStateError:  # forgotten (cancelled) while it opened
            participant.stop()
            return
        self.stats.opened += 1

    def _flush(self, device: _Device) -> None:
        """The session's outcome is known (opened, failed or cancelled): send the fixes
        that waited for it, in order, before any later one."""
        with device.lock:
            waiting, device.waiting = device.waiting, []
            for fix, on in waiting:
                self._send(device, device.session, fix, on)
            device.ready = True

    def _send(
        self,
        device: _Device,
        opened: Future[RoutedSession],
        fix: GpsMeasurement,
        on: OnAnswer,
    ) -> None:
        error = CancelledError() if opened.cancelled() else opened.exception()
        if error is not None:
            self._settle(device, fix, accepted=False)
            self.stats.lost += 1
            self.limiter.warn(
                f"{device.name}|open",
                "device %s: no session with %r, its fixes are dropped: %s",
                device.name,
                self.service,
                error,
            )
            return
        payload = fix.model_dump(exclude_none=True)
        where = (fix.longitude, fix.latitude)
        session = opened.result()
        before, device.last_fix = device.last_fix, fix
        if before is not None and fix.timestamp > before.timestamp:  # for the rotation policy
            session.moved(fix.speed * (fix.timestamp - before.timestamp) / 1000.0, fix.speed)
        try:  # to the worker whose region holds the fix (a hand-over opens a session)
            reply = session.submit(payload, where)
        except ServiceNotFound:  # its message holds the position: not logged
            self._settle(device, fix, accepted=False)
            self.stats.lost += 1
            self.limiter.warn(
                f"{device.name}|route",
                "device %s: a fix was not sent: no worker of %r covers its position",
                device.name,
                self.service,
            )
            return
        except Exception as exc:  # the hand-over's new session failed
            self._settle(device, fix, accepted=False)
            self.stats.lost += 1
            self.limiter.warn(
                f"{device.name}|route", "device %s: a fix was not sent: %s", device.name, exc
            )
            return
        reply.add_done_callback(lambda r: self._reply(device, fix, r, on))

    def _reply(
        self, device: _Device, fix: GpsMeasurement, reply: Future[dict[str, Any]], on: OnAnswer
    ) -> None:
        error = reply.exception()
        answer = None
        if error is None:
            with contextlib.suppress(ValidationError):
                answer = read_reply(reply.result())
        # Only a fix the service answered moves the device's newest time on; a silent
        # session's dead-reckoned answer and a refusal do not.
        self._settle(device, fix, accepted=isinstance(answer, CorrectedPosition))
        if isinstance(error, SessionSilent) and device.last is not None:
            # The session keeps quiet after a change of pseudonym: answer as the device would.
            self.stats.answered += 1
            self.stats.silent += 1
            self._pass_on(device, dead_reckon(*device.last, fix, self.hdmap), on)
            return
        if error is not None:
            self.stats.lost += 1
            if isinstance(error, RequestRejected) and "ephemeral key" in str(error):
                self.limiter.warn(
                    f"{device.name}|rekey",
                    "device %s: the user core still holds the session of an earlier "
                    "participant of this name (a restart within its rekey interval) and "
                    "refuses the new one's fixes until that passes: %s; wait, or restart "
                    "under another name",
                    device.name,
                    error,
                )
                return
            self.limiter.warn(
                f"{device.name}|lost", "device %s: a fix got no answer: %s", device.name, error
            )
            return
        if answer is None:
            self.stats.lost += 1
            self.limiter.warn(
                f"{device.name}|reply", "device %s: the service's reply is not one", device.name
            )
            return
        if isinstance(answer, ErrorReply):
            self.stats.refused += 1
            self.limiter.warn(
                f"{device.name}|refused",
                "device %s: fix refused (%s): %s",
                device.name,
                answer.error.kind,
                answer.error.message,
            )
        else:
            self.stats.answered += 1
            device.last = (answer, fix)
        self._pass_on(device, answer, on)

    def _settle(self, device: _Device, fix: GpsMeasurement, *, accepted: bool) -> None:
        """`fix` has its outcome: no longer on its way; if accepted, the device's newest."""
        with self._lock:
            device.pending.discard(fix.timestamp)
            if accepted and (device.accepted is None or fix.timestamp > device.accepted):
                device.accepted = fix.timestamp

    def _pass_on(
        self, device: _Device, answer: CorrectedPosition | ErrorReply, on: OnAnswer
    ) -> None:
        try:
            on(answer)
        except Exception:
            log.exception("device %s: the bridge failed to pass an answer on", device.name)

    def _close(self, device: _Device) -> None:
        if not device.session.done():
            device.session.cancel()
        if device.participant is not None:
            device.participant.stop()
