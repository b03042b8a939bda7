"""The participant library: a small client that uses LDM services.

    with Participant.create("mqtt://localhost:1883", client_id="car-17") as p:
        print([s.name for s in p.services()])
        echo = p.open("echo")
        print(echo.request({"hello": "world"}))

No topic is spelled by the user. Payloads are JSON objects, encrypted end to end for
the service; the core only routes them. There is no log-off: stop sending and the core
drops the session after its idle timeout. If the core lost the session (idle, restart)
the library asks for it again and re-sends the requests still waiting for a reply.
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections.abc import Mapping
from concurrent.futures import Future, InvalidStateError
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any

from pydantic import ValidationError

from ldm.client.rotation import Rotator
from ldm.config import BrokerSettings, ParticipantConfig, build
from ldm.errors import (
    ConnectError,
    CryptoError,
    RequestRejected,
    RequestTimeout,
    ServiceNotFound,
    SessionError,
    SessionSilent,
    TrustError,
)
from ldm.security.crypto import KeyPair, SessionCipher, aad, input_tag
from ldm.security.identity import verify
from ldm.security.trust import Trust
from ldm.transport.dispatch import Dispatcher
from ldm.transport.mqtt import ClientLoop, Connected, Event, Message, Transport
from ldm.wire import topics
from ldm.wire.messages import (
    LIST_REFRESH,
    Envelope,
    ServiceDescription,
    ServiceList,
    ServicesRequest,
    SessionGrant,
    SessionNotice,
    SessionRequest,
    canonical,
)
from ldm.wire.rotation import RotationPolicy

__all__ = ["Participant", "Session"]

Payload = dict[str, Any]


_FIRST_ASK_RETRY = 1.0  # s: an unanswered list request is sent again after this, doubling
_MAX_REQUESTS = 64  # session requests awaiting their grant, remembered at once


def _token() -> str:
    return secrets.token_urlsafe(9)


def _signed(key: str, payload: bytes) -> bool:
    """Whether a service list's JSON carries `key`'s signature, checked on the parsed
    JSON before any validation: the core signs ``canonical("ldm-list/1", fields)`` of
    the same fields it publishes (`ServiceList.signed_text`)."""
    try:
        body = json.loads(payload)
    except (ValueError, RecursionError):
        return False
    if not isinstance(body, dict):
        return False
    sig = body.pop("sig", None)
    try:
        return isinstance(sig, str) and verify(key, canonical("ldm-list/1", body), sig)
    except ValueError:  # NaN or infinities: never signed
        return False


def _settle(future: Future[Any], result: Any = None, error: BaseException | None = None) -> None:
    """Complete a future unless it is done already (cancelled by its caller, or answered)."""
    try:
        if error is not None:
            future.set_exception(error)
        else:
            future.set_result(result)
    except InvalidStateError:
        pass


@dataclass(slots=True)
class _Keys:
    """One ephemeral key and its cipher with the service: one pseudonym at the core."""

    pair: KeyPair
    cipher: SessionCipher

    @classmethod
    def new(cls, service: ServiceDescription) -> _Keys:
        pair = KeyPair()
        return cls(pair, pair.cipher(service.public_key, initiator=True))


@dataclass(slots=True)
class _Pending:
    future: Future[Payload]
    keys: _Keys
    plaintext: bytes
    sent: float  # the send time of its envelope: a re-send after a new grant renews it
    submitted: float = 0.0  # when the application submitted it: its timeout counts from here
    disconnects: int = 0  # the transport's count when sent
    envelope: Envelope | None = None  # as sent: a retry sends it again unchanged
    tried: float = 0.0  # when it was last sent (or sent again)
    retries: int = 0  # how often it was sent again


class Session:
    """An open session with one service: send input, get replies (thread-safe)."""

    def __init__(
        self,
        participant: Participant,
        grant: SessionGrant,
        keys: _Keys | None = None,
        secret: bytes | None = None,
    ) -> None:
        self._participant = participant
        self.grant = grant
        self._keys = keys or _Keys.new(grant.service)
        self._pending: dict[str, _Pending] = {}
        self._lock = threading.Lock()
        self._secret = secret  # shared with the core by the grant; tags every input
        self._rotator = Rotator(
            grant.rotation or RotationPolicy(), grant.rekey_interval, time.time()
        )
        self.rotations = 0
        """How many times this session changed its ephemeral key (and pseudonym)."""
        self.retries = 0
        """Inputs sent again unanswered (`retry`; ``ParticipantConfig.retry_after``)."""

    @property
    def service(self) -> ServiceDescription:
        return self.grant.service

    @property
    def keys(self) -> _Keys:
        """The current ephemeral key pair and its cipher with the service."""
        return self._keys

    @property
    def silent(self) -> bool:
        """Keeping quiet after a change of pseudonym (the core's policy): input is not
        sent now (`submit` fails with SessionSilent); answer the application yourself."""
        return self._rotator.silent(time.time())

    def moved(self, metres: float, speed: float) -> bool:
        """Tell the library how far the participant moved since the last report and its
        speed now (m, m/s): under the ``distance`` and ``stop`` strategies it changes the
        key (and pseudonym) itself when they say so. True if it did. Nothing is sent."""
        now = time.time()
        return self._rotator.moved(metres, speed, now) and self.rotate(now)

    def submit(self, payload: Mapping[str, Any]) -> Future[Payload]:
        """Send one input now; the future gets the service's reply (or SessionSilent at
        once, unsent, while the session keeps quiet after a change of pseudonym)."""
        if self.silent:
            future: Future[Payload] = Future()
            until = self._rotator.silent_until - time.time()
            future.set_exception(
                SessionSilent(
                    f"not sent: the session with {self.service.name!r} keeps quiet for "
                    f"{until:.1f} s more after its change of pseudonym; answer locally"
                )
            )
            return future
        c = _token()
        plaintext = json.dumps(payload, separators=(",", ":")).encode()
        pending = _Pending(Future(), self._keys, plaintext, 0.0, submitted=time.time())
        with self._lock:
            self._pending[c] = pending
        self._send(c, pending)
        return pending.future

    def request(self, payload: Mapping[str, Any], timeout: float = 2.0) -> Payload:
        """Send one input and wait for the reply; RequestTimeout if none comes in time."""
        future = self.submit(payload)
        try:
            return future.result(timeout)
        except FutureTimeout:
            self._forget(future)
            raise RequestTimeout(
                f"no reply from {self.service.name!r} within {timeout} s "
                "(dropped as stale, or the service is busy or gone)"
            ) from None

    def send(self, payload: Mapping[str, Any]) -> None:
        """Send one input without waiting for (or keeping) a reply."""
        self._forget(self.submit(payload))

    def _forget(self, future: Future[Payload]) -> None:
        with self._lock:
            for c, p in list(self._pending.items()):
                if p.future is future:
                    del self._pending[c]

    def _send(self, c: str, pending: _Pending) -> None:
        keys = pending.keys
        pending.sent = time.time()
        unreachable = self._participant.unreachable(pending.sent)
        if unreachable is not None:
            self.fail(c, unreachable)
            return
        pending.disconnects = self._participant.disconnects
        sealed = keys.cipher.seal(pending.plaintext, aad(c, pending.sent))
        k, secret = keys.pair.public, self._secret
        tag = None if secret is None else input_tag(secret, c, pending.sent, k, sealed)
        env = Envelope(c=c, t=pending.sent, k=k, d=sealed, m=tag)
        pending.envelope, pending.tried = env, pending.sent
        if keys is self._keys:
            self._rotator.used(pending.sent)
        if not self._participant.publish_input(self, env):
            self.fail(
                c,
                ConnectError(
                    f"input for {self.service.name!r} not sent: no connection to the broker "
                    "(QoS 0 is not queued) or the send queue is full"
                ),
            )

    # --- called by its participant (the participant's dispatch thread) --------------------

    def rotate(self, now: float, quiet: bool = True) -> bool:
        """Start a new ephemeral key, at most once per ``rekey_interval`` (else False),
        then keep quiet for the policy's silence (unless not `quiet`).

        The core refuses a session's new key sooner than that, so a rotation more often,
        asked by a replayed or forged notice, would only lock the session out. Both
        count from the first input under the current key (`Rotator.used`), the core from
        its arrival (counted from the rotation instead, the participant ran ahead of the
        core by the time until its next input, and the core refused the new key: issue 25).
        """
        if not self._rotator.may_change(now):
            return False
        self._keys = _Keys.new(self.grant.service)
        self._rotator.changed(now, quiet)
        self.rotations += 1
        return True

    def regrant(self, grant: SessionGrant, secret: bytes | None) -> bool:
        """The core granted the session again: new key, re-send what is still waiting.

        Each re-sent input gets a new correlation id: the old one travelled under the
        old pseudonym, and the same id under the new one would link the two. The key
        stays if it changed within the last ``rekey_interval`` and the service's key is
        the same (the core would refuse a new one). A grant of the same service
        identity with an older description (``issued``) changes nothing (False): the
        session never goes back to an older key.
        """
        held = self.grant.service
        if grant.service.identity == held.identity and grant.service.issued < held.issued:
            return False
        changed = grant.service.public_key != self.grant.service.public_key
        self.grant = grant
        self._secret = secret
        self._rotator.policy = grant.rotation or RotationPolicy()
        self._rotator.rekey_interval = grant.rekey_interval
        if changed:
            self._keys = _Keys.new(grant.service)
            self._rotator.changed(time.time(), quiet=False)
            self.rotations += 1
        else:
            self.rotate(time.time(), quiet=False)
        with self._lock:
            waiting, self._pending = list(self._pending.values()), {}
            resend = [(_token(), p) for p in waiting]
            self._pending.update(resend)
        for c, pending in resend:
            pending.keys = self._keys
            self._send(c, pending)
        return True

    def settle(self, env: Envelope) -> bool:
        """Settle the request ``env`` answers; False (and nothing changes) if it is not
        authentic, so a forged reply never uses up a request."""
        with self._lock:
            pending = self._pending.get(env.c)
        if pending is None:
            return True
        try:
            payload = json.loads(pending.keys.cipher.open(env.d, aad(env.c, env.t)))
        except CryptoError:
            return False
        except (ValueError, RecursionError) as exc:
            # Authentic but not JSON: the service itself answered this badly.
            payload = CryptoError(f"reply from {self.service.name!r} is not JSON: {exc}")
        if not isinstance(payload, dict | CryptoError):
            payload = CryptoError(f"reply from {self.service.name!r} is not a JSON object")
        with self._lock:
            if self._pending.get(env.c) is not pending:
                return True  # answered meanwhile (a duplicate at QoS 1)
            del self._pending[env.c]
        if isinstance(payload, CryptoError):
            _settle(pending.future, error=payload)
        else:
            _settle(pending.future, payload)
        return True

    def fail(self, c: str | None, error: Exception) -> None:
        """Fail the request `c` (if it still waits) with `error`."""
        with self._lock:
            pending = self._pending.pop(c, None) if c is not None else None
        if pending is not None:
            _settle(pending.future, error=error)

    def fail_all(self, error: Exception) -> None:
        """Fail every request still waiting with `error`."""
        with self._lock:
            pending, self._pending = list(self._pending.values()), {}
        for p in pending:
            _settle(p.future, error=error)

    def retry(self, now: float, after: float, max_age: float) -> None:
        """Send again, unchanged (same correlation id, time, key and tag), each input
        unanswered `after` s after it was sent, then after twice as long each time
        (`after`, 2 `after`, 4 `after`, ...: a long outage costs a few retries per
        input, not one every `after`), while every hop would still take it (younger
        than `max_age`). The provider answers a correlation id it answered already with
        the same reply (`ProviderStats.answered_again`), so an input or reply lost on the
        way (a broker node that died with it, data at QoS 0) costs a retry, not the
        request."""
        with self._lock:
            due = [
                (p, p.envelope)
                for p in self._pending.values()
                if p.envelope is not None
                and now - p.tried >= after * 2**p.retries
                and now - p.sent < max_age
            ]
            for p, _ in due:
                p.tried = now
                p.retries += 1
        for _, envelope in due:
            if self._participant.publish_input(self, envelope):
                self.retries += 1

    def expire(self, now: float, limit: float, disconnects: int) -> None:
        """Fail the requests submitted more than `limit` s ago (RequestTimeout), and ask
        the participant to open the session again: the core may have lost it.

        The limit counts from the submission, not from the last send: a re-send after a
        new grant does not give an input a second lifetime."""
        with self._lock:
            old = [(c, p) for c, p in self._pending.items() if now - p.submitted > limit]
            for c, _ in old:
                del self._pending[c]
        if old:  # the core may have lost or replaced the session without a word: ask again
            self._participant.reopen(self)
        for _, p in old:
            why = "the input or its reply was lost or dropped as stale"
            if disconnects != p.disconnects:
                why = "the connection to the broker dropped meanwhile; " + why
            error = RequestTimeout(f"no reply from {self.service.name!r} within {limit:g} s: {why}")
            _settle(p.future, error=error)


class Participant(Dispatcher[Event]):
    """A participant client of one user-cluster broker. Use as a context manager."""

    def __init__(self, config: ParticipantConfig) -> None:
        super().__init__("ldm-participant", 0.25)
        self.config = config
        # With credentials the client id defaults to the user name: a broker that sets
        # use_username_as_clientid (docs/security.md) forces the same.
        self.client_id = (
            config.client_id or config.broker.username or f"ldm-p-{secrets.token_hex(6)}"
        )
        self._services: list[ServiceDescription] = []
        self._list_t = 0.0  # time of the newest signed service list taken
        self._next_ask = float("inf")  # when to ask the core for the list again
        self._ask_wait = _FIRST_ASK_RETRY  # s until then, while the core has not answered
        self._list_answered = False  # a list came on this client's own topic since the ask
        self._have_list = threading.Event()
        self.trust = Trust(config.service_keys, config.anchors)
        self._distrusted: dict[str, str] = {}  # service -> why its last grant was refused
        self.ignored = 0
        """Notices, lists and replies ignored as unauthentic (forged, replayed, unsigned)."""
        self.untrusted: list[ServiceDescription] = []
        """The services of the latest list left out: neither pinned nor endorsed."""
        self._opening: dict[str, Future[tuple[SessionGrant, bytes | None]]] = {}
        self._requests: dict[str, KeyPair] = {}
        """Request correlation id -> the key sent with it, until its grant (or a newer
        request) comes: with the grant's ``auth_key`` it gives the session's secret."""
        self._sessions: dict[str, Session] = {}
        self._reopening: dict[str, tuple[str, float]] = {}
        """Service -> the correlation id and time of the request that re-opens its
        session, until the grant (or a refusal) comes."""
        self._lock = threading.Lock()
        self.transport = Transport(
            config.broker, client_id=self.client_id, sink=self.put, name=self.client_id
        )
        self.transport.subscribe(topics.SERVICES, 1)
        self.transport.subscribe(topics.participant_down(self.client_id), 1)

    @classmethod
    def create(
        cls, broker: BrokerSettings | str, client_id: str | None = None, **settings: Any
    ) -> Participant:
        """Build a participant from a URL or settings plus any ParticipantConfig field."""
        config = build(
            ParticipantConfig, broker=BrokerSettings.of(broker), client_id=client_id, **settings
        )
        return cls(config)

    def start(self, timeout: float | None = 10.0) -> Participant:
        self.start_dispatch()
        self.transport.start(timeout)
        return self

    def start_on(self, loop: ClientLoop) -> Participant:
        """Start without threads of its own, for a load generator holding hundreds of
        participants in one process: the connection joins `loop` (`ClientLoop`), each
        message is handled on the loop's thread as it arrives (instead of queued for a
        dispatch thread), and the dispatcher's ``tick`` runs from the loop at its interval.
        Returns at once; `transport.connected` says when the broker acknowledged."""
        self.transport.attach(loop)
        self.transport.set_sink(self._handle_inline)
        self._stopping.clear()

        def tick() -> bool:
            if self._stopping.is_set():
                return False
            self.tick(time.time())
            return True

        loop.every(self._interval, tick)
        self.transport.start(None)
        return self

    def _handle_inline(self, item: Event) -> None:
        # As the dispatch thread would: an error is logged, never raised into paho.
        try:
            self.handle(item)
        except Exception:
            logging.getLogger(__name__).exception("%s: error while handling", self.client_id)

    def stop(self) -> None:
        """Disconnect and fail every request still waiting (ConnectError).

        No log-off is sent: the core drops idle sessions by itself.
        """
        self.stop_dispatch()
        self.transport.stop()
        error = ConnectError(f"participant {self.client_id!r} stopped before the answer came")
        with self._lock:
            opening, self._opening = list(self._opening.values()), {}
            sessions = list(self._sessions.values())
        for future in opening:
            _settle(future, error=error)
        for session in sessions:
            session.fail_all(error)

    def __enter__(self) -> Participant:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def services(self, timeout: float = 5.0) -> list[ServiceDescription]:
        """The cluster's current service list (waits for the retained list once)."""
        self._have_list.wait(timeout)
        return list(self._services)

    def open(self, service: str, timeout: float = 5.0) -> Session:
        """Request a session with a service and wait for the core's grant.

        One session per service: opening the same service again replaces the session.
        Raises ServiceNotFound if the core does not know the service, SessionError if
        the core does not answer in time.
        """
        c = _token()
        future: Future[tuple[SessionGrant, bytes | None]] = Future()
        with self._lock:
            self._opening[c] = future
        self._request_session(c, service)
        try:
            grant, secret = future.result(timeout)
        except FutureTimeout:
            problem = self._distrusted.get(service)
            if problem is not None:
                raise TrustError(f"{problem}; not opening a session with it") from None
            raise SessionError(
                f"no answer to the session request for {service!r} within {timeout} s; "
                "is the cluster's LDM core running?"
            ) from None
        finally:
            with self._lock:
                self._opening.pop(c, None)
        with self._lock:
            old = self._sessions.get(service)
            # The same service key: keep the ephemeral key (and so the pseudonym), as a
            # new key so soon would be refused by the core (rekey_interval).
            same = old is not None and old.service.public_key == grant.service.public_key
            keys = old.keys if old is not None and same else None
            session = Session(self, grant, keys, secret)
            self._sessions[service] = session
        if old is not None:
            old.fail_all(SessionError(f"the session with {service!r} was opened again"))
        return session

    def _request_session(self, c: str, service: str) -> None:
        key = KeyPair()
        with self._lock:
            if len(self._requests) >= _MAX_REQUESTS:  # unanswered ones: forget the oldest
                del self._requests[next(iter(self._requests))]
            self._requests[c] = key
        request = SessionRequest(c=c, service=service, t=time.time(), k=key.public)
        self.transport.publish(
            topics.session_request(self.client_id), request.model_dump_json().encode(), qos=1
        )

    @property
    def disconnects(self) -> int:
        """Connections to the broker lost so far."""
        return self.transport.disconnects

    def publish_input(self, session: Session, env: Envelope) -> bool:
        """Publish a session's sealed input on its topic (any thread); False if it was
        not taken (no connection for QoS 0, or the send queue is full)."""
        qos = self.config.data_qos if self.config.data_qos is not None else session.grant.data_qos
        topic = topics.participant_input(self.client_id, session.service.name)
        return self.transport.publish(topic, env.encode(), qos)

    def reopen(self, session: Session) -> None:
        """Ask the core for `session` again (any thread): the core lost it, or the
        service has a new key. The grant renews the session in place (`Session.regrant`)."""
        now = time.time()
        name = session.service.name
        with self._lock:
            asked = self._reopening.get(name)
            if asked is not None and now - asked[1] < 1.0:
                return  # asked already; ask again only if no grant came within a second
            c = _token()
            self._reopening[name] = (c, now)
        self._request_session(c, name)

    def _reopened(self, service: str, c: str | None) -> bool:
        """Whether `c` answers the request that re-opens `service`'s session (it is
        then answered: no longer waited for)."""
        with self._lock:
            asked = self._reopening.get(service)
            if asked is None or asked[0] != c:
                return False
            del self._reopening[service]
            return True

    # --- dispatch thread ----------------------------------------------------------------

    def handle(self, item: Event) -> None:
        if isinstance(item, Connected):
            self._ask_services(time.time())
            return
        try:
            self._message(item)
        except ValidationError:
            return

    def _message(self, msg: Message) -> None:
        if msg.topic == topics.SERVICES:
            self._service_list(msg.payload)
            return
        topic = topics.parse(msg.topic)
        if topic.kind == "services_reply":
            self._list_answered = True
            self._ask_wait = _FIRST_ASK_RETRY
            self._next_ask = time.time() + LIST_REFRESH
            self._service_list(msg.payload)
        elif topic.kind == "session_notice":
            notice = SessionNotice.model_validate_json(msg.payload)
            if self._authentic(notice):
                self._notice(notice)
            else:
                self.ignored += 1
        elif topic.kind == "participant_reply":
            session = self._sessions.get(topic.service)
            env = Envelope.model_validate_json(msg.payload)
            fresh = time.time() - env.t <= self.config.max_age
            if session is not None and fresh and not session.settle(env):
                self.ignored += 1

    def _authentic(self, notice: SessionNotice) -> bool:
        """With a pinned core key: signed by it, for this client, and recent."""
        key = self.config.core_key
        if key is None:
            return True
        return (
            notice.to == self.client_id
            and notice.t is not None
            and abs(time.time() - notice.t) <= self.config.notice_window
            and verify(key, notice.signed_text(), notice.sig)
        )

    def _ask_services(self, now: float) -> None:
        """Ask the core for the service list on this client's own topics (at each
        connect, and every `LIST_REFRESH` s): where the broker's ACL lets a participant
        read only its own topics, that is how the list comes (also as it changes).
        Unanswered (no core yet), it asks again after 1 s, then twice as long each
        time, up to `LIST_REFRESH`."""
        self._next_ask = now + (LIST_REFRESH if self._list_answered else self._ask_wait)
        if not self._list_answered:
            self._ask_wait = min(LIST_REFRESH, 2 * self._ask_wait)
        self._list_answered = False
        request = ServicesRequest(t=now).model_dump_json().encode()
        self.transport.publish(topics.services_request(self.client_id), request, qos=1)

    def _service_list(self, payload: bytes) -> None:
        """Take a service list: at most ``max_list`` bytes, signed by the pinned core
        (if any; checked on the JSON before the list is validated), never older than
        the last one, and only the services the participant trusts.

        An empty payload is the core clearing its list (it stopped): no services, and
        no session is touched.
        """
        if not payload:
            self._services = []
            self._have_list.set()
            return
        key = self.config.core_key
        if len(payload) > self.config.max_list or (key is not None and not _signed(key, payload)):
            self.ignored += 1  # checked before the list is validated: a forgery costs little
            return
        listing = ServiceList.model_validate_json(payload)
        if key is not None:
            if listing.t < self._list_t:
                self.ignored += 1
                return
            self._list_t = listing.t
        services = [s for s in listing.services if self.trust.trusts(s)]
        self.untrusted = [s for s in listing.services if not self.trust.trusts(s)]
        self._services = services
        self._have_list.set()
        self._check_keys(services)

    def _notice(self, notice: SessionNotice) -> None:
        session = self._sessions.get(notice.service)
        if notice.kind == "grant" and notice.grant is not None:
            problem = self.trust.problem(notice.grant.service)
            if problem is not None:
                self._distrusted[notice.service] = problem
                self.ignored += 1
                return
            with self._lock:
                opening = self._opening.get(notice.c or "")
                key = self._requests.pop(notice.c or "", None)
            secret = None
            if key is not None and notice.grant.auth_key is not None:
                secret = key.session_secret(notice.grant.auth_key)
            if opening is not None:
                _settle(opening, (notice.grant, secret))  # a duplicate (QoS 1) finds it done
            elif (
                session is not None
                and self._reopened(notice.service, notice.c)
                and not session.regrant(notice.grant, secret)
            ):
                self.ignored += 1  # an older description: the session keeps its key
        elif notice.kind == "refused":
            error = ServiceNotFound(notice.error or f"service {notice.service!r} refused")
            with self._lock:
                opening = self._opening.get(notice.c or "")
            if opening is not None:
                _settle(opening, error=error)
            elif session is not None and self._reopened(notice.service, notice.c):
                session.fail_all(error)  # the session cannot be re-opened
            elif session is not None:
                session.fail(notice.c, error)
        elif notice.kind == "rejected":
            rejected = RequestRejected(
                notice.reason or "invalid", f"the core refused the input: {notice.error}"
            )
            with self._lock:
                opening = self._opening.get(notice.c or "")
            if opening is not None:
                _settle(opening, error=rejected)
            elif session is not None:
                session.fail(notice.c, rejected)
        elif notice.kind == "rotate" and session is not None:
            session.rotate(time.time())
        elif notice.kind == "nosession" and session is not None:
            self.reopen(session)

    def _check_keys(self, services: list[ServiceDescription]) -> None:
        """A service that restarted with a new key needs its sessions opened again.

        Only for a newer key (``issued``): a replayed older description changes nothing.
        """
        latest = {s.name: s for s in services}
        for session in list(self._sessions.values()):
            desc = latest.get(session.service.name)
            if (
                desc is not None
                and desc.public_key != session.service.public_key
                and desc.issued >= session.service.issued
            ):
                self.reopen(session)

    def unreachable(self, now: float) -> ConnectError | None:
        """The error for every request while no broker node has taken the connection,
        or acknowledged a QoS 1 message, for ``unreachable_after`` seconds (None while
        it is not so)."""
        limit = self.config.unreachable_after
        down = self.transport.down_since
        if down is not None and now - down >= limit:
            return ConnectError(
                f"no broker node reachable for {now - down:.1f} s ({self.transport.problem}; "
                f"tried {self.config.broker.url}): nothing can be sent or answered now, so "
                "the request failed rather than wait (it may or may not have reached the "
                "service). A cluster that lost its quorum refuses every connection: send "
                "again once `transport.connected` is true"
            )
        waited = self.transport.unacked_for(now)
        if waited >= limit:
            return ConnectError(
                f"the broker at {self.transport.address[0]}:{self.transport.address[1]} has "
                f"not acknowledged a message for {waited:.1f} s: it takes the connection but "
                "cannot store input (a NATS cluster that lost its JetStream quorum does "
                "this), so the request failed rather than wait. Send again once the broker "
                "acknowledges again"
            )
        return None

    def tick(self, now: float) -> None:
        if now >= self._next_ask:
            self._ask_services(now)
        limit = 2 * self.config.max_age + 1.0
        unreachable = self.unreachable(now)
        if unreachable is not None:
            for session in list(self._sessions.values()):
                session.fail_all(unreachable)
        retry_after = self.config.retry_after
        for session in list(self._sessions.values()):
            if retry_after is not None:
                session.retry(now, retry_after, self.config.max_age)
            session.expire(now, limit, self.transport.disconnects)
            if session.service.name in self._reopening:
                self.reopen(session)
