"""A small LDM deployment for tests: brokers, cores, an echo provider, sniffers."""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ldm import Core, Participant, Provider, Request, ServiceSpec
from ldm.config import BrokerSettings
from ldm.local.brokers import RunningBroker, wait_for
from ldm.transport.mqtt import Event, Message, Transport

FAST = {
    "rotation_period": 0.5,
    "grace": 0.5,
    "idle_timeout": 1.0,
    "service_ttl": 1.5,
    "max_age": 2.0,
}

ECHO = ServiceSpec(
    name="echo",
    version="1.0",
    description="Replies with what it was sent.",
    input_schema={"type": "object"},
    output_schema={"type": "object", "properties": {"echo": {"type": "object"}}},
)


class Sniffer:
    """Subscribes to ``#`` on a broker and keeps everything it sees."""

    def __init__(self, url: str, name: str) -> None:
        self.messages: list[Message] = []
        self._lock = threading.Lock()
        self.transport = Transport(
            BrokerSettings(url=url), client_id=f"sniffer-{name}", sink=self._sink, name=name
        )
        self.transport.subscribe("#", 1)
        self.transport.start(timeout=5)

    def _sink(self, event: Event) -> None:
        if isinstance(event, Message):
            with self._lock:
                self.messages.append(event)

    def snapshot(self) -> list[Message]:
        with self._lock:
            return list(self.messages)

    def stop(self) -> None:
        self.transport.stop()


@dataclass
class EchoService:
    """An echo handler that records what the service side could observe."""

    requests: list[Request] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, request: Request) -> dict[str, Any]:
        with self.lock:
            self.requests.append(request)
        return {"echo": request.payload}

    def pseudonyms(self) -> set[str]:
        with self.lock:
            return {r.pseudonym for r in self.requests}

    def pseudonyms_of(self, who: str) -> set[str]:
        """The pseudonyms of the requests whose payload says ``"who": who``."""
        with self.lock:
            return {r.pseudonym for r in self.requests if r.payload.get("who") == who}


def echo_provider(url: str, service: EchoService, **settings: Any) -> Provider:
    settings.setdefault("announce_interval", 0.3)
    return Provider.create(url, ECHO, service, **settings).start(timeout=5)


def has_service(participant: Participant, name: str) -> Callable[[], bool]:
    return lambda: any(s.name == name for s in participant.services(timeout=0.05))


def lacks_service(participant: Participant, name: str) -> Callable[[], bool]:
    return lambda: not has_service(participant, name)()


@dataclass
class Deployment:
    """User cluster + inter-cluster broker + service cluster, with an echo service."""

    user: RunningBroker
    backbone: RunningBroker
    service: RunningBroker
    user_core: Core
    service_core: Core
    echo: EchoService
    provider: Provider
    sniffers: list[Sniffer]
    participants: list[Participant] = field(default_factory=list)

    def participant(
        self, client_id: str, username: str | None = None, **options: Any
    ) -> Participant:
        """A started participant on the user broker (``ParticipantConfig`` `options`)."""
        settings = BrokerSettings(url=self.user.url, username=username)
        options.setdefault("max_age", FAST["max_age"])
        p = Participant.create(settings, client_id=client_id, **options)
        p.start(timeout=5)
        self.participants.append(p)
        return p

    def wait_listed(self, participant: Participant, timeout: float = 5.0) -> None:
        assert wait_for(has_service(participant, "echo"), timeout), "echo never listed"

    def close(self) -> None:
        for p in self.participants:
            p.stop()
        for s in self.sniffers:
            s.stop()
        self.provider.stop()
        self.user_core.stop()
        self.service_core.stop()


def deploy(
    factory: Callable[[], RunningBroker],
    *,
    backbone_is_service_broker: bool = False,
    **core_options: Any,
) -> Deployment:
    """Three brokers (or two, when the service broker doubles as the backbone); both
    cores take ``FAST`` and `core_options` (``CoreConfig`` fields)."""
    user = factory()
    service = factory()
    backbone = service if backbone_is_service_broker else factory()
    sniffers = [Sniffer(backbone.url, "backbone")]
    if backbone is not service:
        sniffers.append(Sniffer(service.url, "service"))
    options = {**FAST, **core_options}
    user_core = Core.create("user-edge", user.url, backbone.url, **options).start(timeout=5)
    service_core = Core.create("svc-cluster", service.url, backbone.url, **options)
    service_core.start(timeout=5)
    echo = EchoService()
    provider = echo_provider(service.url, echo, max_age=FAST["max_age"])
    return Deployment(user, backbone, service, user_core, service_core, echo, provider, sniffers)
