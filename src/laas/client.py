"""A typed client of the laas service: a `GpsMeasurement` in, a `CorrectedPosition` out.

    with Client.from_env() as client:  # LAAS_CLUSTER, LAAS_USERNAME, LAAS_PASSWORD, ...
        position = client.locate(fix)

The client is one LDM participant (`ldm.Participant`): its own connection to the
user-cluster broker, its own session, pseudonyms and end-to-end encryption. It finds the
service as every laas client does (`laas.discovery`): one worker named ``laas``, or the
regional workers of ``laas``, and sends each fix to the worker whose region
holds it (`ldm.RoutedSession`), handing the user over at a border.

While the session keeps quiet after a change of pseudonym (the core's rotation policy),
the client answers a fix itself from its last answer (`laas.deadreckon`), on the lanes
of `hdmap` when it has the map; `Client.silent` counts those answers.

Every failure is a `laas.errors.ClientError` whose message says what to do: an error
reply of the service raises `FixRefused`, never returns.

`AsyncClient` is the same for asyncio.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
from concurrent.futures import Future, InvalidStateError
from concurrent.futures import TimeoutError as FutureTimeout
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from laas.deadreckon import dead_reckon
from laas.discovery import offers, wait_for_service
from laas.errors import (
    ClientError,
    ConfigError,
    FixRefused,
    KeepingQuiet,
    NoAnswer,
    ServiceUnavailable,
    UntrustedService,
)
from laas.map.hdmap import HdMap
from laas.models import CorrectedPosition, ErrorKind, ErrorReply, GpsMeasurement, read_reply
from laas.worker.service import SERVICE_NAME
from ldm import (
    BrokerSettings,
    LdmError,
    Participant,
    RequestRejected,
    RoutedSession,
    SessionSilent,
    TrustError,
)
from ldm.errors import ConfigError as LdmConfigError
from ldm.ops.process import broker_settings

__all__ = ["AsyncClient", "Client"]

_WHAT_TO_DO: dict[ErrorKind, str] = {
    "invalid": "correct the fields named",
    "clock": "send fixes dated by this machine's clock, set right (NTP)",
    "outside": "the position is not on the service's map; is this the deployment of your area?",
    "stale": "send each fix with a later timestamp than the one before",
    "internal": "send the next fix; if this goes on, tell the service's operator",
}


_REJECTED = {
    "rate_limited": "send fewer fixes a second (the user core's rate limit)",
    "clock": "set this machine's clock right (NTP)",
    "unavailable": "the user core cannot reach the service now; send the next fix later",
}
"""What to do when the user core refuses a fix, by the reason of its `ldm.RequestRejected`."""


class Client:
    """One road user's connection to the laas service; use as a context manager.

    `cluster` is the user-cluster broker (a URL, or `ldm.BrokerSettings` with the
    account). Pin the worker's identity (`service_key`, or endorsing `anchors`) and the
    user core's key (`core_key`), as the operator publishes them: then no broker and no
    core can read a fix or answer in the service's name. `hdmap`, the map the service
    serves, puts the client's own answers while it keeps quiet on the right lane.
    Thread-safe.
    """

    def __init__(
        self,
        cluster: BrokerSettings | str,
        *,
        client_id: str | None = None,
        service_key: str | None = None,
        anchors: tuple[str, ...] = (),
        core_key: str | None = None,
        hdmap: HdMap | None = None,
        service: str = SERVICE_NAME,
        timeout: float = 10.0,
    ) -> None:
        try:
            self.participant = Participant.create(
                cluster,
                client_id=client_id,
                service_keys={service: service_key} if service_key else {},
                anchors=list(anchors),
                core_key=core_key,
            )
        except LdmConfigError as exc:
            raise ConfigError(str(exc)) from None
        self.hdmap = hdmap
        self.service = service
        self.timeout = timeout
        self.silent = 0
        """Fixes answered by the client itself while its session kept quiet."""
        self._routed: RoutedSession | None = None
        self._lock = threading.Lock()
        self._last: tuple[CorrectedPosition, GpsMeasurement] | None = None  # answer, its fix
        self._sent: GpsMeasurement | None = None  # the last fix sent (for the motion)

    @classmethod
    def from_env(
        cls, prefix: str = "LAAS", *, hdmap: HdMap | None = None, **settings: Any
    ) -> Client:
        """A client configured as the `laas` commands are: the broker from
        ``{prefix}_CLUSTER``, ``{prefix}_USERNAME``, ``{prefix}_PASSWORD`` and
        ``{prefix}_CA_FILE``; the pins from ``{prefix}_SERVICE_KEY`` and
        ``{prefix}_CORE_KEY``; `settings` as in `Client` override them."""
        url = os.environ.get(f"{prefix}_CLUSTER")
        if not url:
            raise ConfigError(
                f"set {prefix}_CLUSTER to the user-cluster broker, mqtt://HOST:PORT "
                "(mqtts:// with TLS)"
            )
        ca = os.environ.get(f"{prefix}_CA_FILE")
        try:
            broker = broker_settings(
                url,
                Path(ca) if ca else None,
                os.environ.get(f"{prefix}_USERNAME"),
                f"{prefix}_PASSWORD",
            )
        except LdmConfigError as exc:
            raise ConfigError(f"{exc} (from the {prefix}_* environment variables)") from None
        pins = {
            "service_key": os.environ.get(f"{prefix}_SERVICE_KEY") or None,
            "core_key": os.environ.get(f"{prefix}_CORE_KEY") or None,
        }
        return cls(broker, hdmap=hdmap, **{**pins, **settings})

    # --- lifetime -----------------------------------------------------------------------

    def start(self) -> Client:
        """Connect and wait until the cluster lists the service (each within `timeout`);
        the session opens with the first fix, with the worker whose area holds it."""
        try:
            self.participant.start(timeout=self.timeout)
            wait_for_service(self.participant, self.timeout, self.service)
        except TimeoutError as exc:
            self.participant.stop()
            raise self._not_found(exc) from exc
        except LdmError as exc:
            self.participant.stop()
            raise _client_error(exc) from exc
        self._routed = RoutedSession(self.participant, self.service, timeout=self.timeout)
        return self

    def close(self) -> None:
        """Disconnect; a fix still waiting for its answer fails with ServiceUnavailable."""
        self.participant.stop()

    def __enter__(self) -> Client:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def _not_found(self, exc: TimeoutError) -> ClientError:
        """Why no worker was found: an untrusted one, an unsigned list, or none."""
        p = self.participant
        if any(offers(s, self.service) for s in p.untrusted):
            return UntrustedService(
                f"the cluster lists {self.service!r}, but signed by another key than the one "
                "pinned (LAAS_SERVICE_KEY): pin the key the operator publishes"
            )
        if p.ignored and p.config.core_key is not None:
            return UntrustedService(
                "the user core's service lists are not signed by the pinned core key "
                "(LAAS_CORE_KEY): pin the key the operator publishes"
            )
        return ServiceUnavailable(str(exc))

    @property
    def worker(self) -> str | None:
        """The worker the last fix went to (``laas``, or a regional ``laas-KofN``)."""
        return None if self._routed is None else self._routed.current

    # --- fixes --------------------------------------------------------------------------

    def locate(self, fix: GpsMeasurement, timeout: float = 5.0) -> CorrectedPosition:
        """The corrected position of `fix`; a ClientError that says what to do otherwise."""
        future = self.submit(fix)
        try:
            return future.result(timeout)
        except FutureTimeout:
            future.cancel()
            raise NoAnswer(
                f"no answer from {self.service!r} within {timeout:g} s; the service is busy "
                "or gone, or the fix was dropped as too old: send the next one"
            ) from None

    def submit(self, fix: GpsMeasurement) -> Future[CorrectedPosition]:
        """Send `fix` now; the future gets its corrected position or a ClientError."""
        if not isinstance(fix, GpsMeasurement):
            raise TypeError(
                f"give a laas.GpsMeasurement, not {type(fix).__name__} "
                "(from a dict: GpsMeasurement(**fix))"
            )
        routed = self._routed
        if routed is None:
            raise ServiceUnavailable("the client is not started: use `with client:` or start()")
        with self._lock:
            before, self._sent = self._sent, fix
        if before is not None and fix.timestamp > before.timestamp:  # for the rotation policy
            routed.moved(fix.speed * (fix.timestamp - before.timestamp) / 1000.0, fix.speed)
        answer: Future[CorrectedPosition] = Future()
        try:  # to the worker whose region holds the fix (a hand-over opens a session)
            reply = routed.submit(fix.model_dump(exclude_none=True), (fix.longitude, fix.latitude))
        except LdmError as exc:
            answer.set_exception(_client_error(exc))
            return answer
        reply.add_done_callback(lambda r: self._settle(answer, fix, r))
        return answer

    def _settle(
        self, answer: Future[CorrectedPosition], fix: GpsMeasurement, reply: Future[Any]
    ) -> None:
        """Turn the service's reply into `answer`'s outcome (the participant's thread)."""
        error = reply.exception()
        if isinstance(error, SessionSilent):
            with self._lock:
                last = self._last
                if last is not None:
                    self.silent += 1
            if last is None:
                message = f"{error}; with no earlier answer to go on from, send again then"
                _outcome(answer, KeepingQuiet(message))
            else:
                _outcome(answer, dead_reckon(*last, fix, self.hdmap))
            return
        if error is not None:
            _outcome(answer, _client_error(error))
            return
        try:
            got = read_reply(reply.result())
        except ValidationError:
            problem = ServiceUnavailable(
                f"the reply of {self.service!r} is not a laas reply; is the service under "
                "that name a laas worker?"
            )
            _outcome(answer, problem)
            return
        if isinstance(got, ErrorReply):
            e = got.error
            refused = FixRefused(f"{e.message}; {_WHAT_TO_DO[e.kind]}", e.kind, e.fields)
            _outcome(answer, refused)
            return
        got = got.model_copy(update={"handover": None})  # the workers', not the user's
        with self._lock:
            self._last = (got, fix)
        _outcome(answer, got)


def _outcome(future: Future[CorrectedPosition], outcome: CorrectedPosition | ClientError) -> None:
    """Complete `future` unless its caller gave up on it (cancelled at its timeout)."""
    with contextlib.suppress(InvalidStateError):
        if isinstance(outcome, ClientError):
            future.set_exception(outcome)
        else:
            future.set_result(outcome)


def _client_error(exc: BaseException) -> ClientError:
    """The ClientError for an LDM error (its message already says what to check)."""
    if isinstance(exc, ClientError):
        return exc
    if isinstance(exc, TrustError):
        return UntrustedService(str(exc))
    if isinstance(exc, RequestRejected):
        if "ephemeral key" in str(exc):
            return ServiceUnavailable(
                f"{exc}: the user core still holds the session of an earlier client of this "
                "name (a restart within its rekey interval); wait, or connect under another name"
            )
        hint = _REJECTED.get(exc.reason)
        return ServiceUnavailable(str(exc) if hint is None else f"{exc}; {hint}")
    if isinstance(exc, TimeoutError):
        return NoAnswer(f"{exc}; send the next fix")
    return ServiceUnavailable(str(exc))


class AsyncClient:
    """`Client` for asyncio: ``async with AsyncClient(...) as c: await c.locate(fix)``.

    Takes the same arguments as `Client`, or a `Client`; `from_env` too. The connection's
    work runs on its own threads, never on the event loop.
    """

    def __init__(self, cluster: BrokerSettings | str | Client, **settings: Any) -> None:
        self.client = cluster if isinstance(cluster, Client) else Client(cluster, **settings)

    @classmethod
    def from_env(cls, prefix: str = "LAAS", **settings: Any) -> AsyncClient:
        """As `Client.from_env`."""
        return cls(Client.from_env(prefix, **settings))

    async def __aenter__(self) -> AsyncClient:
        await asyncio.to_thread(self.client.start)
        return self

    async def __aexit__(self, *_exc: object) -> None:
        await asyncio.to_thread(self.client.close)

    async def locate(self, fix: GpsMeasurement, timeout: float = 5.0) -> CorrectedPosition:
        """As `Client.locate`."""
        future = await asyncio.to_thread(self.client.submit, fix)  # a hand-over may wait
        try:
            return await asyncio.wait_for(asyncio.wrap_future(future), timeout)
        except TimeoutError as exc:
            if isinstance(exc, ClientError):  # the service's own: no reply in its time
                raise
            raise NoAnswer(
                f"no answer from {self.client.service!r} within {timeout:g} s; the service "
                "is busy or gone, or the fix was dropped as too old: send the next one"
            ) from None
