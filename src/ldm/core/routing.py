"""Ciphertext between clusters and back: a core's routing of envelopes it never opens.

Participant input leaves the user cluster under its pseudonym only: to this cluster's
provider, or over the backbone to the service's core. There the service core remembers
which core each pseudonym came from (`Route`), for the replies. A provider's reply goes
to the local participant of its pseudonym (mapped back to its client here, the only
place that knows it), or back over the backbone.

Envelopes to one destination (a provider, another core) wait in the `Outbox` while the
core's dispatch thread handles what waited, then leave as one batch (`ldm.wire.batch`; `flush`).
A core forwards the bytes it received (decoded and checked, not encoded again): the
user core cuts the participant's tag off them (`ldm.wire.messages.untagged`) and
delivers a reply as it came when it holds nothing but ``c``, ``t`` and ``d``
(`ldm.wire.messages.reply_bytes`). Only the core's dispatch thread calls it.
"""

from __future__ import annotations

import time

from ldm.config import CoreConfig
from ldm.core.sessions import Sessions
from ldm.core.state import Route
from ldm.core.stats import CoreStats
from ldm.transport.hops import Hops
from ldm.transport.mqtt import Transport
from ldm.wire import topics
from ldm.wire.batch import Outbox
from ldm.wire.messages import Envelope, reply_bytes, untagged

__all__ = ["Router"]

_UNREACHABLE = 1.0
"""s: a backbone broker unreachable this long fails QoS 1/2 input for other clusters'
services at once (``unavailable``), rather than after its timeout."""


class Router:
    """One core's routing of envelopes (`forward_input`, `remote_input`, `reply`,
    `deliver`), and the routes of other clusters' pseudonyms."""

    def __init__(
        self,
        config: CoreConfig,
        stats: CoreStats,
        sessions: Sessions,
        cluster: Transport,
        backbone: Transport | None,
    ) -> None:
        self._config = config
        self._stats = stats
        self._sessions = sessions
        self._cluster = cluster
        self._backbone = backbone
        self._routes: dict[str, Route] = {}
        """Other clusters' pseudonyms -> the core their input came from."""
        self._outbox = Outbox()
        self.hops: Hops | None = None
        """Set to note when each input passes this core (`ldm.transport.hops`; `laas bench`)."""

    @property
    def route_count(self) -> int:
        return len(self._routes)

    def stale(self, env: Envelope) -> bool:
        """Older than ``max_age`` (counted as ``dropped_stale``)."""
        if time.time() - env.t > self._config.max_age:
            self._stats.dropped_stale += 1
            return True
        return False

    def forward_input(
        self,
        origin: str,
        service: str,
        pseudonym: str,
        env: Envelope,
        received: bytes,
        now: float,
    ) -> str | None:
        """A participant's input, its session checked, under its pseudonym: to this
        cluster's provider or to the service's core (`origin`), as the bytes `received`
        without the tag. Why it cannot leave now, if it cannot (`backbone_problem`),
        else None."""
        cfg = self._config
        payload = untagged(env, received)
        if self.hops is not None:
            self.hops.mark("sent", env.c, env.t)
            self.hops.mark("user_core", env.c, now)
        if origin == cfg.name:
            batch_topic = topics.provider_input_batch(service)
            self._outbox.add(self._cluster, batch_topic, pseudonym, payload, cfg.data_qos)
        elif self._backbone is not None:
            problem = self.backbone_problem(now, service)
            if problem is not None:
                return problem
            batch_topic = topics.bb_input_batch(origin, service, cfg.name)
            self._outbox.add(self._backbone, batch_topic, pseudonym, payload, cfg.data_qos)
        else:
            self._stats.dropped_unroutable += 1
            return None
        self._stats.forwarded_in += 1
        return None

    def backbone_problem(self, now: float, service: str) -> str | None:
        """Why input for `service`, on another cluster, cannot leave now: the backbone
        broker is unreachable (at QoS 0, which the transport does not hold, at once; at
        QoS 1/2, which it holds for the reconnect, after ``_UNREACHABLE`` s). None when
        it can. (A broker that is connected but slow to acknowledge, as NATS while it
        elects leaders, still gets QoS 1/2 input: it is stored and delivered late.)"""
        backbone = self._backbone
        if backbone is None:
            return None
        down = backbone.down_since
        if down is None or (self._config.data_qos > 0 and now - down < _UNREACHABLE):
            return None
        return (
            f"service {service!r} is in another cluster and this core's backbone broker "
            f"has been unreachable for {now - down:.1f} s ({backbone.problem}): nothing "
            "reaches it now; send again later"
        )

    def remote_input(
        self, topic: topics.Topic, pseudonym: str, env: Envelope, payload: bytes, local: bool
    ) -> None:
        """Input from another cluster's participant under `pseudonym`, which came on
        `topic` (a batch's or a single message's; `local`: its service is this
        cluster's), to the provider; its core is remembered for the replies."""
        if self.stale(env):
            return
        if self.hops is not None:
            self.hops.mark("service_core", env.c)
        if not local:
            self._stats.dropped_unroutable += 1
            return
        self._routes[pseudonym] = Route(topic.user_core, time.time())
        batch_topic = topics.provider_input_batch(topic.service)
        self._forward(self._cluster, batch_topic, pseudonym, env, payload)
        self._stats.forwarded_in += 1

    def reply(self, service: str, pseudonym: str, env: Envelope, payload: bytes) -> None:
        """A local provider replied: to a local participant, or back over the backbone
        (`payload`, the envelope's bytes as the provider sent them)."""
        if self.stale(env):
            return
        if self._sessions.of(pseudonym) is not None:
            self.deliver(service, pseudonym, env, payload)
            return
        route = self._routes.get(pseudonym)
        if route is None or self._backbone is None:
            self._stats.dropped_unroutable += 1
            return
        batch_topic = topics.bb_reply_batch(route.user_core, service)
        self._forward(self._backbone, batch_topic, pseudonym, env, payload)
        self._stats.forwarded_out += 1

    def deliver(self, service: str, pseudonym: str, env: Envelope, payload: bytes) -> None:
        """A fresh reply (the caller checked its age) to the participant of a pseudonym:
        `payload`, the bytes `env` was decoded from, when they hold nothing else."""
        session = self._sessions.of(pseudonym)
        if session is None or session.service != service:
            self._stats.dropped_unroutable += 1
            return
        reply = reply_bytes(env, payload)
        topic = topics.participant_reply(session.client, service)
        self._cluster.publish(topic, reply, self._config.data_qos)
        if self.hops is not None:
            self.hops.mark("delivered", env.c)
        self._stats.forwarded_out += 1

    def _forward(
        self, to: Transport, batch_topic: str, pseudonym: str, env: Envelope, payload: bytes
    ) -> None:
        """Forward an envelope as the bytes it came in (decoded, checked, not encoded
        again), unless they hold a newline, which a batch line cannot: then as encoded."""
        if b"\n" in payload:
            payload = env.encode()
        self._outbox.add(to, batch_topic, pseudonym, payload, self._config.data_qos)

    def flush(self) -> None:
        """Send what the outbox holds, one message per destination."""
        self._outbox.flush()
        self._stats.batches_sent = self._outbox.batches
        self._stats.batched = self._outbox.batched

    def expire(self, now: float) -> None:
        """Forget routes idle longer than a session lives (``idle_timeout + grace``)."""
        cfg = self._config
        for pseudonym, route in list(self._routes.items()):
            if now - route.last_seen > cfg.idle_timeout + cfg.grace:
                del self._routes[pseudonym]
