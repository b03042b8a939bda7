"""Admission: what a core decides about a participant's message on paho's threads,
before the message shares a queue with anyone (`ldm.core.core.Core.sink`).

Each participant client id has three budgets (`ldm.core.budgets.Limits`), token buckets
for its input and for the refusal notices that answer it. `Admission` charges each
message to one of them (`Charge`), as far as it can tell cheaply: what looks like a
session request (`request_like`), its session's input (`SessionKeys`, `tagged`: decoded
once and its tag checked, here), and everything else. The message then travels to the
core's dispatch thread as an `Admitted`, with what admission decided and the envelope it decoded.

`Admission` owns what it decides with: the budgets, what it knows of each session
(told by the dispatch thread after each message that may have changed it, `Admission.know`),
the correlation ids of recent input (replays), and the clearing of retained junk. Its
one lock covers these alone; the dispatch thread reaches them only through its methods.
"""

from __future__ import annotations

import hmac
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Container
from dataclasses import dataclass

from pydantic import ValidationError

from ldm.config import CoreConfig
from ldm.core.budgets import NOTICE_RATE, Bucket, Budget, Charge, Limits
from ldm.core.stats import CoreStats
from ldm.security.crypto import input_tag
from ldm.transport.mqtt import Message
from ldm.wire.messages import Envelope
from ldm.wire.topics import Topic

__all__ = [
    "Admission",
    "Admitted",
    "SessionKeys",
    "envelope_key",
    "request_like",
    "tag_secret",
    "tagged",
]

_CLEAR_RATE = 1000.0  # clearings a second of participant topics that are no session's

_K = b'"k":"'
_K_LEN = 44  # base64 of a 32-byte X25519 key
_TAG_CHECK_MAX = 4096  # bytes: larger input is not checked at intake (charged ``other``)


@dataclass(frozen=True, slots=True)
class SessionKeys:
    """What intake knows of one session: its ephemeral keys with the end of their grace
    (inf: current), and the secrets its input may be tagged with (none yet: empty)."""

    keys: tuple[tuple[bytes, float], ...]
    secrets: tuple[bytes, ...]

    def claims(self, payload: bytes, now: float) -> bool:
        """Whether `payload` may be this session's input (cheap: a find or two): it has
        a tag (a session with a secret) or one of the session's keys (one without)."""
        if self.secrets:
            return b'"m"' in payload
        k = envelope_key(payload)
        return k is not None and any(key == k and until > now for key, until in self.keys)


def envelope_key(payload: bytes) -> bytes | None:
    """The ``k`` of an input envelope as `Envelope.encode` writes it, found without
    parsing (``"k":"`` within the first 256 bytes, then 44 characters and ``"``).

    Only to choose the budget that pays for a message of a session without a secret
    (the message is parsed properly later); anyone who copies the key gets the same.
    """
    at = payload.find(_K, 0, 256)
    if at < 0:
        return None
    start = at + len(_K)
    end = start + _K_LEN
    return payload[start:end] if payload[end : end + 1] == b'"' else None


def request_like(payload: bytes) -> bool:
    """Whether a payload may be a session request (at most 1 KiB, naming a
    ``"service"``), to charge it to the client's ``session`` budget; cheap, and
    validated properly later."""
    return len(payload) <= 1024 and b'"service"' in payload


def tagged(secrets: tuple[bytes, ...], payload: bytes) -> tuple[Envelope, bytes] | None:
    """An input envelope of at most 4 KiB, decoded, that carries a valid tag ``m`` of
    one of the session's secrets (`ldm.security.crypto.input_tag`), with that secret; None for
    anything else. The core decodes and checks it here, once: the dispatch thread takes it as it
    is."""
    if len(payload) > _TAG_CHECK_MAX or b'"m"' not in payload:
        return None
    try:
        env = Envelope.model_validate_json(payload)
    except ValidationError:
        return None
    secret = tag_secret(env, secrets)
    return None if secret is None else (env, secret)


def tag_secret(env: Envelope, secrets: tuple[bytes, ...] | list[bytes]) -> bytes | None:
    """The secret among `secrets` whose tag `env` carries (None: none of them)."""
    if env.k is None or env.m is None:
        return None
    for secret in reversed(secrets):  # the newest first: the participant's usual case
        if hmac.compare_digest(env.m, input_tag(secret, env.c, env.t, env.k, env.d)):
            return secret
    return None


@dataclass(frozen=True, slots=True)
class Admitted(Message):
    """A participant message taken at intake (`Core.sink`), with what intake decided:
    ``parsed``: its topic, parsed once at intake; ``charge``: the budget that paid for
    it; ``refused``: over the rate, only its ``rejected`` notice is left to send (the
    notice bucket already paid); ``envelope``: the input decoded, its tag checked with
    ``secret`` (the session's secret when intake took it), so the dispatch thread
    neither parses the topic, nor decodes nor checks the input again."""

    parsed: Topic
    charge: Charge = "other"
    refused: bool = False
    envelope: Envelope | None = None
    secret: bytes | None = None


class Admission:
    """A core's intake of participant messages (`admit`, on paho's threads), and the
    notice budgets the dispatch thread answers refusals from (`notice`).

    ``clear(topic, qos)`` publishes an empty retained message on a participant topic
    (the cluster transport's); ``offered(service)`` tells whether the cluster offers a
    service (input for one it does not is on no session's topic).
    """

    def __init__(
        self,
        config: CoreConfig,
        stats: CoreStats,
        clear: Callable[[str, int], None],
        offered: Callable[[str], bool],
    ) -> None:
        self._config = config
        self._stats = stats
        self._clear_topic = clear
        self._offered = offered
        self._lock = threading.Lock()
        """Over every table below and the counters admission writes in ``stats``
        (rejected_rate, notices_suppressed, dropped_overload, dropped_retained)."""
        self._limits: dict[str, Limits] = {}
        self._keys: dict[tuple[str, str], SessionKeys] = {}
        """(client, service) -> what admission knows of the session, to charge its
        input to the right budget; the dispatch thread tells it (`know`)."""
        self._recent: OrderedDict[tuple[str, str, str], float] = OrderedDict()
        """(client, service, c) of input charged to its session in the last ``max_age``,
        oldest first: a replay of one is not the session's."""
        self._clears = Bucket(_CLEAR_RATE, time.time())
        self._next_sweep = time.time() + config.retain_sweep

    # --- paho's threads ---------------------------------------------------------------

    def admit(self, msg: Message, topic: Topic) -> Admitted | None:
        """A message on ``ldm/p/{client}/up/...``: the item to queue in its client's
        lane, or None (dropped, or refused with no notice to send).

        Retained (old: cleared on the broker) and empty messages are dropped. The rest
        is charged to one of the client's budgets: what looks like a session request to
        ``session``, its session's input (`owned`) to ``own``, anything else to
        ``other``. Over the rate it is refused here (the item then carries only its
        ``rejected`` notice, if the notice bucket pays). Costs a few finds per message,
        and a JSON parse and an HMAC only for input that claims to be its session's
        while the session's budget can still pay for it.
        """
        if msg.retain or not msg.payload:
            if msg.payload:  # an empty retained publish deletes it on the broker
                self._clear_topic(msg.topic, 1)
            with self._lock:
                self._stats.dropped_retained += 1
            return None
        client = topic.client
        service = topic.service if topic.kind == "participant_input" else ""
        cfg = self._config
        now = time.time()
        if topic.kind == "participant_up" or (service and not self._offered(service)):
            self._clear(msg.topic, now)
        charge: Charge = "other"
        verified = True  # whether `charge` is known to be right
        envelope: Envelope | None = None  # decoded and its tag checked with `secret`
        secret: bytes | None = None
        if topic.kind == "session_request" and request_like(msg.payload):
            charge = "session"
        elif topic.kind == "services_request" and len(msg.payload) <= 1024:
            charge = "session"  # a list request: as cheap to tell, as rare
        elif service:
            with self._lock:
                known = self._keys.get((client, service))
            if known is not None and known.claims(msg.payload, now):
                # The tag is checked (outside the lock) only while the session's budget
                # could pay: a participant over its rate costs no parsing. Unchecked,
                # it is refused, and the refusal is answered from ``other``.
                with self._lock:
                    verified = self._limits_of(client, now).own.input.ready(
                        now, cfg.rate, cfg.burst
                    )
                if verified:
                    own, envelope, secret = self.owned(known, client, service, msg.payload, now)
                else:
                    own = True
                charge = "own" if own else "other"
        notice = False
        with self._lock:
            limits = self._limits_of(client, now)
            budget = limits.budget(charge)
            admitted = verified and budget.input.take(now, cfg.rate, cfg.burst)
            if not admitted:
                self._stats.rejected_rate += 1
                payer = budget if verified else limits.other
                deep = msg.topic.count("/") >= 4  # ldm/p/{client}/up/...: its notice topic
                notice = deep and self._take_notice(payer, now)
        if not (admitted or notice):
            return None
        return Admitted(
            msg.topic,
            msg.payload,
            msg.qos,
            False,
            msg.source,
            parsed=topic,
            charge=charge,
            refused=not admitted,
            envelope=envelope if admitted else None,
            secret=secret,
        )

    def owned(
        self, known: SessionKeys, client: str, service: str, payload: bytes, now: float
    ) -> tuple[bool, Envelope | None, bytes | None]:
        """Whether `payload` is its session's input, and new: tagged with the session's
        secret (under any key: a new key after a rotation is the session's too), fresh
        (``max_age``), and not a copy of one taken in the last ``max_age`` (an
        eavesdropper's replay on a broker without ACL). A session without a secret has
        nothing to check beyond its key (`SessionKeys.claims`). With it, the envelope
        decoded and the secret its tag was checked with (None when there is no secret
        or it is not its own)."""
        if not known.secrets:
            return True, None, None
        found = tagged(known.secrets, payload)
        if found is None:
            return False, None, None
        env, secret = found
        c, t = env.c, env.t
        cfg = self._config
        if not now - cfg.max_age <= t <= now + cfg.max_clock_skew:
            return False, None, None
        with self._lock:
            recent = self._recent
            while recent and next(iter(recent.values())) < now - cfg.max_age:
                recent.popitem(last=False)
            if (client, service, c) in recent:
                return False, None, None
            recent[(client, service, c)] = now
        return True, env, secret

    def _clear(self, topic: str, now: float) -> None:
        """Clear what may be retained on `topic`, a participant's topic that is no
        session's, at once.

        A live message does not show the retain flag, so retained junk on topics of a
        participant's own (one participant made the broker hold 120 MB, which Mosquitto
        never gives back: issue 25) would wait for the next sweep (``retain_sweep``).
        The session topics are few per participant and swept; any other topic is
        cleared as its message arrives, within ``_CLEAR_RATE`` a second, beyond which
        the next sweep comes within a second.
        """
        with self._lock:
            cleared = self._clears.take(now, _CLEAR_RATE, _CLEAR_RATE)
            if not cleared:
                self._next_sweep = min(self._next_sweep, now + 1.0)
        if cleared:
            self._clear_topic(topic, 0)

    def overflowed(self, count: int = 1) -> None:
        """`count` messages found the core's queue full (dropped, ``dropped_overload``)."""
        with self._lock:
            self._stats.dropped_overload += count

    def malformed(self, count: int) -> None:
        """`count` lines of a batch were malformed (``dropped_invalid``)."""
        with self._lock:
            self._stats.dropped_invalid += count

    # --- the dispatch thread ------------------------------------------------------------

    def notice(self, charge: Charge, client: str) -> bool:
        """A token from the notice bucket (10/s) of the client's budget `charge`: False
        when it is empty. A client admission never saw (no budgets) is answered."""
        with self._lock:
            limits = self._limits.get(client)
            if limits is None:
                return True
            return self._take_notice(limits.budget(charge), time.time())

    def know(self, client: str, service: str, keys: SessionKeys | None) -> None:
        """What the session of `client` for `service` now is (None: none, or one with
        neither a key nor a secret yet)."""
        with self._lock:
            if keys is not None:
                self._keys[(client, service)] = keys
            else:
                self._keys.pop((client, service), None)

    def knows(self, client: str, service: str) -> SessionKeys | None:
        """What admission knows of the session now."""
        with self._lock:
            return self._keys.get((client, service))

    def forget(self, now: float, sessions: Container[tuple[str, str]]) -> None:
        """Drop full budgets (the same as none) and what it knows of sessions that are
        no longer in `sessions`."""
        cfg = self._config
        with self._lock:
            for client, limits in list(self._limits.items()):
                if limits.full(now, cfg.rate, cfg.burst):
                    del self._limits[client]
            for gone in [key for key in self._keys if key not in sessions]:
                del self._keys[gone]

    def sweep_due(self, now: float) -> bool:
        """Whether it is time to have the broker send what is retained on participant
        topics again (then the next sweep is ``retain_sweep`` later)."""
        with self._lock:
            if now < self._next_sweep:
                return False
            self._next_sweep = now + self._config.retain_sweep
            return True

    @property
    def clients(self) -> frozenset[str]:
        """Clients with budgets (not full ones)."""
        with self._lock:
            return frozenset(self._limits)

    @property
    def sessions(self) -> frozenset[tuple[str, str]]:
        """(client, service) of the sessions admission knows."""
        with self._lock:
            return frozenset(self._keys)

    def _limits_of(self, client: str, now: float) -> Limits:
        """The client's budgets, new (full) if it has none (hold ``_lock``)."""
        limits = self._limits.get(client)
        if limits is None:
            limits = self._limits[client] = Limits.new(now, self._config.burst)
        return limits

    def _take_notice(self, budget: Budget, now: float) -> bool:
        """A token from the budget's notice bucket (hold ``_lock``)."""
        if budget.notices.take(now, NOTICE_RATE, NOTICE_RATE):
            return True
        self._stats.notices_suppressed += 1
        return False
