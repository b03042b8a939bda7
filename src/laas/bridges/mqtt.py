"""The common part of the bridges that read devices from MQTT (OwnTracks, CAM).

A bridge holds one MQTT connection of its own (its account on the user-cluster broker)
for the devices' topics, and a `DevicePool` for the devices' LDM participants. paho's
thread only queues each message (`ldm.transport`); the bridge's own thread decodes it
and hands the fix to the pool, and once a second forgets the silent devices. A message
the bridge cannot read is the device's problem: `handle` counts it and goes on.

A broker's ACL that does not let the bridge read its devices' topics (or the devices
write them) drops their messages without a word: Mosquitto grants the subscription and
delivers nothing. So a bridge that has heard nothing `quiet_after` seconds after it
connected says so, once, naming its account and topics.
"""

from __future__ import annotations

import logging
import queue
import secrets
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Sequence

from laas.bridges.pool import DevicePool
from ldm import BrokerSettings
from ldm.transport import Message, Transport

__all__ = ["MqttBridge"]

log = logging.getLogger(__name__)

_EXPIRE_EVERY = 1.0  # s between sweeps for silent devices
_NOTHING = object()  # the inbox stayed empty for a sweep's interval


class MqttBridge(ABC):
    """Subscribes `subscriptions` on `broker` and feeds each message to `handle`."""

    def __init__(
        self,
        broker: BrokerSettings,
        pool: DevicePool,
        subscriptions: Sequence[str],
        *,
        name: str,
        client_id: str | None = None,
        quiet_after: float = 60.0,
    ) -> None:
        self.pool = pool
        self.name = name
        self.quiet_after = quiet_after
        self.received = 0  # device messages taken from the broker
        self._account = broker.username
        self._inbox: queue.SimpleQueue[object] = queue.SimpleQueue()
        client_id = client_id or broker.username or f"{name}-{secrets.token_hex(4)}"
        self.transport = Transport(broker, client_id=client_id, sink=self._inbox.put, name=name)
        self._filters = list(subscriptions)
        for topic_filter in self._filters:
            self.transport.subscribe(topic_filter, 1)
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self, timeout: float | None = 10.0) -> MqttBridge:
        """Start the bridge's thread, then connect and wait until the broker has taken
        its subscriptions (up to `timeout` s each), so no device message sent after
        this returns is missed."""
        self._thread.start()
        self.transport.start(timeout)
        deadline = time.monotonic() + (10.0 if timeout is None else timeout)
        while any(f not in self.transport.granted for f in self._filters):
            if time.monotonic() > deadline:
                log.warning("%s: the broker has not confirmed its subscriptions yet", self.name)
                break
            time.sleep(0.01)
        return self

    @property
    def alive(self) -> bool:
        """Whether the bridge's thread runs (started and not stopped)."""
        return self._thread.is_alive()

    def stop(self) -> None:
        """Disconnect, stop the thread and close every device's participant."""
        self.transport.stop()
        self._inbox.put(None)
        if self._thread.is_alive():
            self._thread.join(10.0)
        self.pool.close()

    def __enter__(self) -> MqttBridge:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def publish(self, topic: str, payload: bytes, *, retain: bool = False, qos: int = 1) -> None:
        """Send a message on the bridge's own connection (from any thread)."""
        if not self.transport.publish(topic, payload, qos, retain):
            log.warning("%s: an answer on %s was not sent: no connection", self.name, topic)

    @abstractmethod
    def handle(self, message: Message) -> None:
        """Decode one device message and submit its fix; runs on the bridge's thread."""

    def forgotten(self, names: list[str]) -> None:  # noqa: B027 - optional hook
        """Devices the pool just forgot (after `track_timeout` of silence)."""

    def _quiet(self) -> None:
        """Nothing arrived since the bridge connected: say what to check."""
        log.warning(
            "%s: no message on %s in %g s since it connected; check that the devices "
            "publish there and that the broker's ACL lets account %s read it and the "
            "devices write it (deploy/security/acl-user-cluster, docs/bridges.md)",
            self.name,
            " ".join(self._filters),
            self.quiet_after,
            self._account or "(anonymous)",
        )

    def _run(self) -> None:
        next_sweep = time.monotonic() + _EXPIRE_EVERY
        quiet_at: float | None = time.monotonic() + self.quiet_after
        while True:
            try:
                item = self._inbox.get(timeout=_EXPIRE_EVERY)
            except queue.Empty:
                item = _NOTHING
            if item is None:
                return
            if isinstance(item, Message):
                self.received += 1
                quiet_at = None
                try:
                    self.handle(item)
                except Exception:  # a bug for one message must not stop the bridge
                    log.exception("%s: failed on a message on %s", self.name, item.topic)
            if quiet_at is not None and time.monotonic() >= quiet_at:
                quiet_at = None
                self._quiet()
            if time.monotonic() >= next_sweep:
                next_sweep = time.monotonic() + _EXPIRE_EVERY
                names = self.pool.expire()
                if names:
                    self.forgotten(names)
