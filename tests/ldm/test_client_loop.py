"""`ClientLoop`: many connections on one thread (paho's external loop), on real brokers."""

from __future__ import annotations

import threading

from ldm.config import BrokerSettings
from ldm.local.brokers import RunningBroker, wait_for
from ldm.transport.mqtt import ClientLoop, Connected, Event, Message, Transport


def _messages(events: list[Event]) -> list[Message]:
    return [e for e in list(events) if isinstance(e, Message)]


def test_one_loop_thread_carries_many_connections_both_ways(mqtt_broker: RunningBroker) -> None:
    settings = BrokerSettings(url=mqtt_broker.url)
    threads_before = threading.active_count()
    got: dict[int, list[Event]] = {}
    with ClientLoop() as loop:
        transports = []
        for k in range(60):
            got[k] = []
            t = Transport(settings, client_id=f"loop-{k}", sink=got[k].append, loop=loop)
            t.subscribe(f"loop/{k}", 1)
            transports.append(t)
        for t in transports:
            t.start()
        assert wait_for(lambda: all(t.connected for t in transports), 15)
        # the loop's one thread, no paho thread per connection
        assert threading.active_count() <= threads_before + 1
        assert len(loop) == 60
        # publishes from another thread than the loop's, to every other connection
        for k, t in enumerate(transports):
            assert t.publish(f"loop/{(k + 1) % 60}", f"from {k}".encode(), 1)
        assert wait_for(lambda: all(len(_messages(got[k])) == 1 for k in got), 15)
        for k in got:
            assert _messages(got[k])[0].payload == f"from {(k - 1) % 60}".encode()
        for t in transports:
            t.stop()
        assert wait_for(lambda: len(loop) == 0, 5)


def test_a_loop_connection_comes_back_after_the_broker_restarts(
    mqtt_broker: RunningBroker,
) -> None:
    settings = BrokerSettings(url=mqtt_broker.url, reconnect_min=0.1, reconnect_max=0.5)
    events: list[Event] = []
    with ClientLoop() as loop:
        receiver = Transport(settings, client_id="loop-rx", sink=events.append, loop=loop)
        receiver.subscribe("restart/#", 1)
        sender = Transport(settings, client_id="loop-tx", sink=lambda _e: None, loop=loop)
        receiver.start(timeout=5)
        sender.start(timeout=5)
        try:
            mqtt_broker.stop()
            assert wait_for(lambda: not sender.connected and not receiver.connected, 10)
            mqtt_broker.start()
            assert wait_for(lambda: sender.connected and receiver.connected, 10)
            assert wait_for(lambda: sum(isinstance(e, Connected) for e in events) == 2, 5)
            # the subscription is made again on the new connection (sent until it arrives:
            # the receiver's SUBSCRIBE may reach the broker after the first publish)

            def delivered() -> bool:
                sender.publish("restart/x", b"again", 1)
                return any(m.payload == b"again" for m in _messages(events))

            assert wait_for(delivered, 10)
        finally:
            sender.stop()
            receiver.stop()


def test_a_transport_joins_a_loop_only_before_it_starts(mqtt_broker: RunningBroker) -> None:
    settings = BrokerSettings(url=mqtt_broker.url)
    t = Transport(settings, client_id="late", sink=lambda _e: None)
    t.start(timeout=5)
    try:
        with ClientLoop() as loop:
            try:
                t.attach(loop)
            except RuntimeError as exc:
                assert "before start()" in str(exc)
            else:
                raise AssertionError("attach after start was accepted")
    finally:
        t.stop()
