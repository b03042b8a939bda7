"""The MQTT session: the only module that imports paho-mqtt.

One `Transport` is one MQTT 3.1.1 client connection. It sets TCP_NODELAY on every
socket it opens, reconnects with exponential back-off (``reconnect_min`` doubling up
to ``reconnect_max``), re-subscribes every remembered filter after each connect, and
turns paho's messages into the LDM's own `Message`.

Threads: paho's network thread (started by ``loop_start``) runs every callback here.
They never block: each one converts what it got and hands it to ``sink`` (normally
``queue.SimpleQueue.put``); the owner's worker thread does the real work. ``publish``
and ``subscribe`` may be called from any thread.

Only a connection the broker has acknowledged (CONNACK) is handed a PUBLISH or a
SUBSCRIBE from another thread. paho alone would not ensure it: on a reconnect it
makes the new socket usable before it queues CONNECT on it, so a publish from
another thread at that moment goes out first, and a broker that takes its first
packet for a CONNECT (amqtt) then waits for more bytes while paho waits for a
CONNACK, until the keep-alive ends the connection. So a QoS 0 message is dropped
while there is no acknowledged connection, and QoS 1/2 messages wait here and are
published on paho's thread right after the CONNACK, behind the re-subscriptions.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from ldm.config import BrokerSettings
from ldm.errors import ConnectError

__all__ = ["Connected", "Event", "Message", "Transport", "Will"]

log = logging.getLogger(__name__)

_MAX_QUEUED = 10_000  # QoS 1/2 messages held here, and again in paho's queue, at most


@dataclass(frozen=True, slots=True)
class Message:
    """One received MQTT message; ``source`` names the transport it came through."""

    topic: str
    payload: bytes
    qos: int
    retain: bool
    source: str

    @classmethod
    def _from_paho(cls, message: mqtt.MQTTMessage, source: str) -> Message:
        return cls(message.topic, bytes(message.payload), message.qos, message.retain, source)


@dataclass(frozen=True, slots=True)
class Connected:
    """The transport (re)connected and has re-sent its subscriptions."""

    source: str


Event = Message | Connected


@dataclass(frozen=True, slots=True)
class Will:
    """The last will the broker publishes if this client vanishes."""

    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = True


def _nodelay(_client: mqtt.Client, _userdata: Any, sock: Any) -> None:
    # Runs on paho's thread for every new socket (plain or TLS) before CONNECT is sent.
    if hasattr(sock, "setsockopt"):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class Transport:
    """A reconnecting MQTT 3.1.1 client that feeds `Message` and `Connected` to a sink."""

    def __init__(
        self,
        settings: BrokerSettings,
        *,
        client_id: str,
        sink: Callable[[Event], None],
        name: str = "",
        will: Will | None = None,
    ) -> None:
        self.settings = settings
        self.client_id = client_id
        self.name = name or client_id
        self._sink = sink
        self._subscriptions: dict[str, int] = {}
        self._held: deque[tuple[str, bytes, int, bool]] = deque()
        """QoS 1/2 messages taken while no connection was acknowledged."""
        self._lock = threading.Lock()
        """Held around every paho call that writes to the socket (publish, subscribe) and
        around every change of ``_connected``: such a call never sees a socket that
        has not been acknowledged. Held only for calls that do not block."""
        self._connected = threading.Event()
        self._started = False
        self.disconnects = 0
        """Connections lost so far (a participant uses it to explain a lost request)."""
        self.dropped_topics = 0
        """Messages dropped because their topic was not valid UTF-8 (paho's thread)."""
        client = mqtt.Client(
            CallbackAPIVersion.VERSION2,
            client_id=client_id,
            clean_session=True,
            protocol=mqtt.MQTTv311,
        )
        if settings.username is not None:
            password = settings.password.get_secret_value() if settings.password else None
            client.username_pw_set(settings.username, password)
        if settings.tls:
            client.tls_set(ca_certs=str(settings.ca_file) if settings.ca_file else None)
        if will is not None:
            client.will_set(will.topic, will.payload, qos=will.qos, retain=will.retain)
        client.reconnect_delay_set(settings.reconnect_min, settings.reconnect_max)  # type: ignore[arg-type]
        client.max_queued_messages_set(_MAX_QUEUED)
        client.on_socket_open = _nodelay
        client.on_pre_connect = self._on_pre_connect
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        self._client = client

    # --- paho callbacks: paho's network thread, never block ---------------------------

    def _on_pre_connect(self, _c: mqtt.Client, _u: Any) -> None:
        # Before paho opens a new socket: a publish or subscribe under way on another
        # thread finishes first (on the old socket, or none), and none starts until
        # the CONNACK.
        with self._lock:
            self._connected.clear()

    def _on_connect(self, client: mqtt.Client, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if reason.is_failure:
            log.warning("%s: broker refused the connection: %s", self.name, reason)
            return
        with self._lock:  # every filter and held message is sent here, or after this
            if self._subscriptions:
                client.subscribe(list(self._subscriptions.items()))
            held, self._held = self._held, deque()
            for topic, payload, qos, retain in held:
                client.publish(topic, payload, qos=qos, retain=retain)
            self._connected.set()
        self._sink(Connected(self.name))

    def _on_disconnect(self, _c: mqtt.Client, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if self._connected.is_set():
            self.disconnects += 1
        self._connected.clear()
        if self._started:
            log.info("%s: disconnected (%s), reconnecting with back-off", self.name, reason)

    def _on_message(self, _c: mqtt.Client, _u: Any, message: mqtt.MQTTMessage) -> None:
        try:
            event = Message._from_paho(message, self.name)
        except UnicodeDecodeError:  # paho decodes the topic lazily; it must not escape here
            self.dropped_topics += 1
            log.debug("%s: dropped a message whose topic is not UTF-8", self.name)
            return
        self._sink(event)

    # --- any thread ---------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    def subscribe(self, topic_filter: str, qos: int = 1) -> None:
        """Subscribe now if connected, and again after every reconnect."""
        with self._lock:
            self._subscriptions[topic_filter] = qos
            if self.connected:
                self._client.subscribe(topic_filter, qos)

    def start(self, timeout: float | None = None) -> None:
        """Connect in the background; with a timeout, wait for the first connection."""
        self._started = True
        self._client.connect_async(self.settings.host, self.settings.port, self.settings.keepalive)
        self._client.loop_start()
        if timeout is not None and not self._connected.wait(timeout):
            self.stop()
            raise ConnectError(
                f"{self.name}: no connection to {self.settings.url} within {timeout} s; "
                "is the broker running and are the URL and credentials right?"
            )

    def publish(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False) -> bool:
        """Queue a message for sending; never waits for the broker.

        False when it was not taken: QoS 0 while no connection is acknowledged (dropped),
        or `_MAX_QUEUED` QoS 1/2 messages already wait. QoS 1/2 messages taken while
        disconnected are sent after the reconnect.
        """
        return self._publish(topic, payload, qos, retain) is not None

    def _publish(
        self, topic: str, payload: bytes, qos: int, retain: bool
    ) -> mqtt.MQTTMessageInfo | bool | None:
        """paho's receipt, True if held for the next connection, None if not taken."""
        with self._lock:
            if self.connected:
                info = self._client.publish(topic, payload, qos=qos, retain=retain)
                ok = info.rc == mqtt.MQTT_ERR_SUCCESS or (
                    qos > 0 and info.rc == mqtt.MQTT_ERR_NO_CONN  # paho re-sends it
                )
                return info if ok else None
            if qos == 0 or len(self._held) >= _MAX_QUEUED:
                return None
            self._held.append((topic, payload, qos, retain))
            return True

    def publish_and_wait(
        self, topic: str, payload: bytes, qos: int = 1, retain: bool = False, timeout: float = 2.0
    ) -> None:
        """Publish and wait until sent; for shutdown paths, never from a paho callback."""
        info = self._publish(topic, payload, qos, retain)
        if isinstance(info, mqtt.MQTTMessageInfo):
            try:
                info.wait_for_publish(timeout)
            except (RuntimeError, ValueError):
                log.info("%s: could not confirm a publish while stopping", self.name)

    def stop(self) -> None:
        """Disconnect cleanly (no last will) and stop the network thread."""
        self._started = False
        self._client.disconnect()
        self._client.loop_stop()
        self._connected.clear()

    def kill(self) -> None:
        """Drop the connection without DISCONNECT, so the broker sends the last will."""
        self._started = False
        sock = self._client.socket()
        if sock is not None:
            with contextlib.suppress(OSError, AttributeError):
                sock.shutdown(socket.SHUT_RDWR)  # type: ignore[attr-defined]
        self._client.loop_stop()
        self._connected.clear()
