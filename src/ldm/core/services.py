"""The services a core knows, and the service list it keeps on ``ldm/services``.

`Catalog` learns local providers' announcements (``ldm/svc/{name}/announce``), forwards
them to the backbone and learns every other core's; it drops a service on its
withdrawal, on its core's last will, or after ``service_ttl``. With ``service_keys`` or
``anchors`` it takes only announcements and withdrawals signed by a trusted identity
(`ldm.security.trust.Trust`); an announcement is bound to the cluster it was made for,
and never older than the last one taken for its service (replays). It signs the
cluster's service list and puts it back if anyone else changes it.

Only the core's dispatch thread calls it, except `get` and `descriptions` (a dict read).
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict

from pydantic import TypeAdapter

from ldm.config import CoreConfig
from ldm.core.budgets import Bucket
from ldm.core.state import ServiceEntry
from ldm.core.stats import CoreStats
from ldm.security.identity import SigningKey, verify
from ldm.security.trust import Trust
from ldm.transport.mqtt import Transport
from ldm.wire import topics
from ldm.wire.messages import (
    LIST_REFRESH,
    Announcement,
    CoreStatus,
    ServiceDescription,
    ServiceList,
    Withdrawal,
)

__all__ = ["Catalog"]

log = logging.getLogger(__name__)

_ANNOUNCE_OR_WITHDRAW: TypeAdapter[Announcement | Withdrawal] = TypeAdapter(
    Announcement | Withdrawal
)
_REPAIR_RATE = 5.0  # service-list repairs per second: a second core on the broker cannot loop us
_MAX_ASKERS = 100_000  # clients sent each change of the list; the longest silent is dropped


class Catalog:
    """The services of every cluster, as one core knows them (`ServiceEntry`: its
    description, the core it is served by, when it expires)."""

    def __init__(
        self,
        config: CoreConfig,
        stats: CoreStats,
        identity: SigningKey,
        trust: Trust,
        cluster: Transport,
        backbone: Transport | None,
    ) -> None:
        self._config = config
        self._name = config.name
        self._stats = stats
        self._identity = identity
        self._trust = trust
        self._cluster = cluster
        self._backbone = backbone
        self._services: dict[str, ServiceEntry] = {}
        self._latest: dict[str, tuple[str | None, float, float]] = {}
        """Service -> (identity, issued, t) of the last announcement taken, also for a
        while after it is gone: an older one is refused (`_forward_only`)."""
        self._left: dict[str, float] = {}
        """Local service -> when it was withdrawn, for ``service_ttl`` s (`served_here`)."""
        self._published_list: list[ServiceDescription] | None = None
        self._list_payload = b""  # the retained list as this core last published it
        self._repairs = Bucket(_REPAIR_RATE, 0.0)
        self._repair_owed = False  # a foreign list was seen and not yet replaced (`repair`)
        self._askers: OrderedDict[str, float] = OrderedDict()
        """Client -> when it last asked for the list (`send_to`), the longest ago first."""

    def get(self, service: str) -> ServiceEntry | None:
        return self._services.get(service)

    def served_here(self, service: str, now: float) -> bool:
        """Whether input for `service` from another cluster goes to this cluster's
        provider: the service is this core's, or was until a withdrawal less than
        ``service_ttl`` s ago.

        A withdrawal can be a last will that a broker sent while the provider was only
        moving to another node (a NATS node refusing its reconnect during a leader
        election): its persistent session keeps what is sent to it meanwhile. Input
        already on its way from another core is therefore forwarded, not dropped
        unanswered (it then failed only by the participant's `RequestTimeout`, after
        2 x max_age + 1 s: 41 s in tests/ldm/test_nats.py). The other core stops sending
        once it has the withdrawal; a provider that really left answers nothing, as
        before, and one that is back announces again."""
        svc = self._services.get(service)
        if svc is not None:
            return svc.origin == self._name
        left = self._left.get(service)
        return left is not None and now - left < self._config.service_ttl

    def __contains__(self, service: object) -> bool:
        return service in self._services

    def entries(self) -> list[ServiceEntry]:
        """A snapshot of the services this core knows (read from any thread)."""
        return list(self._services.values())

    def descriptions(self) -> list[ServiceDescription]:
        """A snapshot of the services' descriptions (read from any thread)."""
        return [s.description for s in list(self._services.values())]

    @property
    def list_payload(self) -> bytes:
        """The retained service list as this core last published it."""
        return self._list_payload

    def own(self) -> list[str]:
        """The services this core's own providers offer."""
        return [n for n, s in list(self._services.items()) if s.origin == self._name]

    def send_to(self, client: str, now: float) -> None:
        """A participant asked for the list (``ServicesRequest``): send it on the
        client's own topic, now and at each change for ``3 * LIST_REFRESH`` s (the
        participant asks again within ``LIST_REFRESH``). Where the broker's ACL lets a
        participant read only its own topics, this is how it gets the list."""
        self._stats.control += 1
        self._askers.pop(client, None)
        self._askers[client] = now
        if len(self._askers) > _MAX_ASKERS:
            self._askers.popitem(last=False)
        if self._list_payload:
            self._cluster.publish(topics.services_reply(client), self._list_payload, qos=1)

    def clear_askers(self) -> None:
        """The core stops: an empty list to each client that asked (as on ``ldm/services``)."""
        for client in self._askers:
            self._cluster.publish(topics.services_reply(client), b"", qos=1)

    def connected(self) -> None:
        """The cluster broker (re)connected: publish the list again."""
        self._published_list = None
        self.publish_list()

    def announce_own(self) -> None:
        """The backbone broker (re)connected: announce this core's services there."""
        for name, svc in self._services.items():
            if svc.origin == self._name:
                self._announce(name, svc)

    def core_status(self, payload: bytes) -> None:
        """A core's status on the backbone: an offline one takes its services along."""
        if payload:
            status = CoreStatus.model_validate_json(payload)
            if not status.online and status.name != self._name:
                self.drop_origin(status.name)
        self._stats.control += 1

    def local(self, service: str, payload: bytes) -> None:
        ann = _ANNOUNCE_OR_WITHDRAW.validate_json(payload) if payload else None
        if not isinstance(ann, Announcement):
            svc = self._services.get(service)
            if svc is not None and svc.origin == self._name and self._withdrawn(svc, ann):
                self._remove_service(service)
            self._stats.control += 1
            return
        if ann.service.name != service:
            self._stats.dropped_invalid += 1
            return
        if not self._bound(ann, self._name) or not self._acceptable(ann):
            return
        if not self._forward_only(ann):
            return
        self._stats.control += 1
        expires = ann.t + self._config.service_ttl
        svc = ServiceEntry(ann.service, self._name, expires, ann.sig, ann.cluster)
        self._services[service] = svc
        self._announce(service, svc)
        self.publish_list()

    def _withdrawn(self, svc: ServiceEntry, goodbye: Withdrawal | None) -> bool:
        """Whether a withdrawal (None: an empty payload) ends ``svc``.

        With trust set, only the service's own signed withdrawal of its current key
        does: anyone could clear a retained topic on a broker without ACL.
        """
        if self._trust.open:
            return True
        desc = svc.description
        return (
            goodbye is not None
            and goodbye.identity is not None
            and goodbye.identity == desc.identity
            and goodbye.issued == desc.issued
            and verify(goodbye.identity, goodbye.signed_text(), goodbye.sig)
        )

    def _bound(self, ann: Announcement, cluster: str) -> bool:
        """Whether `ann` was announced in `cluster` (this core's name for a local
        announcement, its ``origin`` for a backbone copy), as its signed ``cluster``
        says (else counted). An announcement signed for another cluster is a replay:
        taken here, the service would look local and every input would go to a topic
        no one serves. With trust set, an unbound announcement is refused as well."""
        if ann.cluster == cluster:
            return True
        if ann.cluster is not None:
            self._stats.dropped_elsewhere += 1
            log.warning(
                "%s: announcement of %s made for cluster %s, not %s, dropped (a replay)",
                self._name,
                ann.service.name,
                ann.cluster,
                cluster,
                extra={"event": "announcement_elsewhere"},
            )
            return False
        if self._trust.open:
            return True
        self._stats.dropped_untrusted += 1
        log.warning(
            "%s: announcement of %s names no cluster, dropped: the provider has not read "
            "this cluster's service list (let it read ldm/services, or set "
            "ProviderConfig.cluster to %r)",
            self._name,
            ann.service.name,
            cluster,
            extra={"event": "announcement_unbound"},
        )
        return False

    def _forward_only(self, ann: Announcement) -> bool:
        """Whether `ann` is not older than the last announcement taken for its service
        under the same identity (else counted as stale).

        Order: (``issued``, ``t``). A replayed announcement of a withdrawn or replaced
        key is genuine and fresh (within ``service_ttl``), so only its order gives it
        away: taken, it put a dead provider's key back in the list (issue 25). The same
        announcement again is taken while its service is listed (a redelivery), never
        once it is gone. What was last taken is kept ``service_ttl`` after it was made,
        after which a replay of it is stale anyway (`expire`).
        """
        desc = ann.service
        last = self._latest.get(desc.name)
        if last is not None and last[0] == desc.identity:
            new, old = (desc.issued, ann.t), (last[1], last[2])
            if new < old or (new == old and desc.name not in self._services):
                self._stats.dropped_stale += 1
                log.info(
                    "%s: an older announcement of %s dropped (a replay)",
                    self._name,
                    desc.name,
                    extra={"event": "announcement_older"},
                )
                return False
        self._latest[desc.name] = (desc.identity, desc.issued, ann.t)
        return True

    def _acceptable(self, ann: Announcement) -> bool:
        """Fresh, not from the future, and signed by a trusted identity (else counted).

        A time ahead of the clock would make a retained announcement outlive its
        provider; ``max_clock_skew`` is the same limit participants' input has.
        """
        now = time.time()
        if ann.t > now + self._config.max_clock_skew:
            self._stats.dropped_invalid += 1
            log.warning(
                "%s: announcement of %s from the future dropped",
                self._name,
                ann.service.name,
                extra={"event": "announcement_from_future"},
            )
            return False
        if ann.t + self._config.service_ttl <= now:
            self._stats.dropped_stale += 1  # a retained announcement of a provider that is gone
            return False
        if not self._trust.announcement(ann):
            self._stats.dropped_untrusted += 1
            log.warning(
                "%s: announcement of %s dropped: %s",
                self._name,
                ann.service.name,
                self._trust.problem(ann.service) or "its time is not signed by its identity",
                extra={"event": "announcement_untrusted"},
            )
            return False
        return True

    def _announce(self, service: str, svc: ServiceEntry) -> None:
        if self._backbone is None:
            return
        stamp = svc.expires - self._config.service_ttl
        ann = Announcement(
            service=svc.description, t=stamp, origin=self._name, sig=svc.sig, cluster=svc.cluster
        )
        self._backbone.publish(
            topics.bb_announce(service), ann.model_dump_json().encode(), qos=1, retain=True
        )

    def remote(self, service: str, payload: bytes) -> None:
        if not payload:
            svc = self._services.get(service)
            if svc is not None and svc.origin != self._name:
                self._remove_service(service)
            self._stats.control += 1
            return
        ann = Announcement.model_validate_json(payload)
        if ann.origin is None or ann.service.name != service:
            self._stats.dropped_invalid += 1
            return
        if not self._bound(ann, ann.origin) or not self._acceptable(ann):
            return
        if not self._forward_only(ann):
            return
        self._stats.control += 1
        current = self._services.get(service)
        if ann.origin == self._name or (current is not None and current.origin == self._name):
            return  # our own, back from the backbone; or a local provider wins over a remote one
        expires = ann.t + self._config.service_ttl
        entry = ServiceEntry(ann.service, ann.origin, expires, ann.sig, ann.cluster)
        self._services[service] = entry
        self.publish_list()

    def _remove_service(self, service: str) -> None:
        svc = self._services.pop(service, None)
        if svc is None:
            return
        log.info("%s: service %s is gone", self._name, service, extra={"event": "service_gone"})
        if svc.origin == self._name:
            self._left[service] = time.time()
        if svc.origin == self._name and self._backbone is not None:
            self._backbone.publish(topics.bb_announce(service), b"", qos=1, retain=True)
        self.publish_list()

    def drop_origin(self, origin: str) -> None:
        for name in [n for n, s in self._services.items() if s.origin == origin]:
            self._remove_service(name)

    def expire(self, now: float) -> None:
        for name in [n for n, s in self._services.items() if s.expires <= now]:
            self._remove_service(name)
        ttl = self._config.service_ttl
        for name in [n for n, left in self._left.items() if left + ttl <= now]:
            del self._left[name]
        for name in [n for n, last in self._latest.items() if last[2] + ttl <= now]:
            if name not in self._services:
                del self._latest[name]
        askers = self._askers
        while askers and next(iter(askers.values())) < now - 3 * LIST_REFRESH:
            askers.popitem(last=False)

    def publish_list(self) -> None:
        services = sorted((s.description for s in self._services.values()), key=lambda d: d.name)
        if services == self._published_list:
            return
        self._published_list = services
        listing = ServiceList(
            t=time.time(), services=services, core=self._identity.public, cluster=self._name
        )
        listing = listing.model_copy(update={"sig": self._identity.sign(listing.signed_text())})
        self._list_payload = listing.model_dump_json().encode()
        self._cluster.publish(topics.SERVICES, self._list_payload, qos=1, retain=True)
        for client in self._askers:
            self._cluster.publish(topics.services_reply(client), self._list_payload, qos=1)

    def check_list(self, payload: bytes) -> None:
        """The retained list on the cluster must be this core's: if not, publish it again.

        Anyone who can write ``ldm/services`` (a broker without ACL) could replace it;
        the core sees the change one broker round trip later and puts its own back.
        Repairs are bounded (``_REPAIR_RATE`` a second, so two cores on one broker
        cannot loop fast), and one the bucket cannot pay for now is owed, not skipped:
        `_repair` pays it from ``tick`` as soon as the bucket allows, so the last list
        of any burst is repaired within 1 / ``_REPAIR_RATE`` s plus a tick.
        """
        if payload == self._list_payload or self._published_list is None:
            if payload == self._list_payload:
                self._repair_owed = False  # ours is back: nothing after it is owed
            self._stats.control += 1  # our own, or before we published (it follows)
            return
        self._stats.repaired_list += 1
        self._repair_owed = True
        self.repair(time.time())

    def repair(self, now: float) -> None:
        """Publish this core's list again if a repair is owed and the bucket pays."""
        if self._repair_owed and self._repairs.take(now, _REPAIR_RATE, _REPAIR_RATE):
            self._repair_owed = False
            log.warning(
                "%s: the service list on the cluster was not ours; repaired",
                self._name,
                extra={"event": "service_list_repaired"},
            )
            self._cluster.publish(topics.SERVICES, self._list_payload, qos=1, retain=True)
