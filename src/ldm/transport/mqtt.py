"""The MQTT session: the only module that imports paho-mqtt.

One `Transport` is one MQTT 3.1.1 client connection. It sets TCP_NODELAY on every
socket it opens, reconnects with exponential back-off (``reconnect_min`` doubling up
to ``reconnect_max``), re-subscribes every remembered filter after each connect, and
turns paho's messages into the LDM's own `Message`.

Threads: paho's network thread (started by ``loop_start``) runs every callback here.
They never block: each one converts what it got and hands it to ``sink`` (normally
``queue.SimpleQueue.put``); the owner's dispatch thread does the real work. ``publish``
and ``subscribe`` may be called from any thread.

Many connections, one thread: give ``loop=ClientLoop()`` (or call `Transport.attach`
before `start`) and the transport has no network thread of its own; one `ClientLoop`
thread drives the sockets of all its transports with paho's external loop
(``loop_read``/``loop_write``/``loop_misc``) over a ``selectors`` poller (epoll), with
the same reconnect back-off. paho's own thread waits in ``select()``, which fails for a
file descriptor of 1024 or more (paho then reports a lost connection and retries for
ever), and each threaded client holds three descriptors (its socket and a wake-up
socket pair): one process cannot hold more than about 340 threaded connections.
Callbacks then run on the loop's thread, under the same rules.

A clustered broker: with several addresses in ``settings.url`` (``mqtt://h1:p1,h2:p2``)
every connection attempt goes to the next address in the list, starting with the
first, so a lost or refused node is left for the next one at the first retry. The
session is then persistent (``BrokerSettings.clean_session``): the cluster keeps the
subscriptions and the QoS 1/2 messages not yet delivered while the client moves, and
`Transport.stop` discards the session with a second, clean connection.

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
import heapq
import itertools
import logging
import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from ldm.config import BrokerSettings
from ldm.errors import ConnectError

__all__ = ["ClientLoop", "Connected", "Event", "Message", "Transport", "Will"]

log = logging.getLogger(__name__)

_MAX_QUEUED = 10_000  # QoS 1/2 messages held here, and again in paho's queue, at most
_RESUBSCRIBE_AFTER = 1.0  # s: before a subscription the broker refused is asked again


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


def matches(topic_filter: tuple[str, ...], levels: list[str]) -> bool:
    """Whether a topic (cut into `levels`) matches a filter (cut into its levels), by
    MQTT's rules: ``+`` is one level, a final ``#`` any number (none included), and a
    wildcard at the first level never matches a topic that begins with ``$``."""
    if levels[0].startswith("$") and topic_filter[0] in ("+", "#"):
        return False
    n = len(levels)
    for i, level in enumerate(topic_filter):
        if level == "#":
            return True
        if i >= n or (level != "+" and level != levels[i]):
            return False
    return len(topic_filter) == n


def _nodelay(_client: mqtt.Client, _userdata: Any, sock: Any) -> None:
    # Runs on paho's thread for every new socket (plain or TLS) before CONNECT is sent.
    if hasattr(sock, "setsockopt"):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def _client(
    settings: BrokerSettings, client_id: str, clean_session: bool | None = None
) -> mqtt.Client:
    """A paho client for `settings` (credentials, TLS, session), no callbacks yet."""
    client = mqtt.Client(
        CallbackAPIVersion.VERSION2,
        client_id=client_id,
        clean_session=settings.clean_session if clean_session is None else clean_session,
        protocol=mqtt.MQTTv311,
    )
    if settings.username is not None:
        password = settings.password.get_secret_value() if settings.password else None
        client.username_pw_set(settings.username, password)
    if settings.tls:
        client.tls_set(ca_certs=str(settings.ca_file) if settings.ca_file else None)
    return client


def _ignore_socket(_client: mqtt.Client, _userdata: Any, _sock: Any) -> None:
    """paho's register-write callback under a `ClientLoop`, which tracks writes itself."""


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
        loop: ClientLoop | None = None,
    ) -> None:
        self.settings = settings
        self.client_id = client_id
        self.name = name or client_id
        self._sink = sink
        self._subscriptions: dict[str, int] = {}
        self._filters: tuple[tuple[str, ...], ...] = ()
        """Each subscribed filter cut into its levels (replaced whole, never changed in
        place, so paho's thread reads it without the lock)."""
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
        self.dropped_foreign = 0
        """Messages dropped because their topic matches none of our subscriptions: a
        broker's mistake (amqtt, the embedded broker, was seen delivering the retained
        service list to other subscribers), never handed to the owner."""
        self.address = settings.addresses[0]
        """The (host, port) of the node this transport connects to, or did last."""
        self._attempts = 0  # connection attempts so far: the next address is the next one
        self.granted: dict[str, int] = {}
        """Each filter -> the QoS the broker granted (its SUBACK); 128 means refused."""
        self._asked: dict[int, list[tuple[str, int]]] = {}  # SUBSCRIBE mid -> its filters
        self.refusal: str | None = None
        """Why the broker last refused a connection (its CONNACK), if it did."""
        self.down_since: float | None = None
        """When (``time.time()``) the connection was lost, or the first one asked for,
        while none is acknowledged; None while connected (or before `start`)."""
        self.problem = "not connected yet"
        """Why there is no connection, as paho or the broker last said."""
        self._unacked: deque[tuple[mqtt.MQTTMessageInfo, float]] = deque(maxlen=_MAX_QUEUED)
        """QoS 1/2 publishes and when they were sent, oldest first, until the broker
        acknowledged them (`unacked_for`); under ``_lock``."""
        client = _client(settings, client_id)
        if will is not None:
            client.will_set(will.topic, will.payload, qos=will.qos, retain=will.retain)
        client.reconnect_delay_set(settings.reconnect_min, settings.reconnect_max)  # type: ignore[arg-type]
        client.max_queued_messages_set(_MAX_QUEUED)
        client.on_socket_open = _nodelay
        client.on_pre_connect = self._on_pre_connect
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_message = self._on_message
        client.on_subscribe = self._on_subscribe
        self._client = client
        self._loop: ClientLoop | None = None
        if loop is not None:
            self.attach(loop)

    # --- paho callbacks: paho's network thread, never block ---------------------------

    def _on_pre_connect(self, client: mqtt.Client, _u: Any) -> None:
        # Before paho opens a new socket: a publish or subscribe under way on another
        # thread finishes first (on the old socket, or none), and none starts until
        # the CONNACK.
        with self._lock:
            self._connected.clear()
        addresses = self.settings.addresses
        if len(addresses) > 1:
            # paho reads these two right after this callback, to open the socket; its
            # `host`/`port` setters refuse while a connection is being opened.
            self.address = addresses[self._attempts % len(addresses)]
            client._host, client._port = self.address
            log.debug("%s: connecting to %s:%d", self.name, *self.address)
        self._attempts += 1

    def _on_connect(self, client: mqtt.Client, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if reason.is_failure:
            self.refusal = str(reason)
            hint = ""
            if reason == "Client identifier not valid":
                hint = (
                    f"; the broker refused the client id {self.client_id!r} (NATS refuses "
                    "'.', spaces, '*' and '>' in client ids): choose one without them"
                )
            log.warning(
                "%s: %s:%d refused the connection: %s%s", self.name, *self.address, reason, hint
            )
            self.refusal += hint
            self.problem = f"{self.address[0]}:{self.address[1]} refused it: {self.refusal}"
            return
        if self._loop is not None:  # the loop's thread: the back-off starts over
            self._loop._delay[self] = self.settings.reconnect_min
        with self._lock:  # every filter and held message is sent here, or after this
            if self._subscriptions:
                filters = list(self._subscriptions.items())
                _rc, mid = client.subscribe(filters)
                if mid is not None:
                    self._asked[mid] = filters
            held, self._held = self._held, deque()
            for topic, payload, qos, retain in held:
                client.publish(topic, payload, qos=qos, retain=retain)
            self._connected.set()
            self.down_since = None
        self._sink(Connected(self.name))

    def _on_disconnect(self, _c: mqtt.Client, _u: Any, _f: Any, reason: Any, _p: Any) -> None:
        if self._connected.is_set():
            self.disconnects += 1
            self.down_since = time.time()
            self.problem = f"{self.address[0]}:{self.address[1]} disconnected: {reason}"
        elif self.refusal is None:
            self.problem = f"{self.address[0]}:{self.address[1]}: {reason}"
        self._connected.clear()
        if self._started:
            log.info("%s: disconnected (%s), reconnecting with back-off", self.name, reason)

    def _on_subscribe(self, _c: mqtt.Client, _u: Any, mid: int, codes: Any, _p: Any) -> None:
        with self._lock:  # held by whoever sent the SUBSCRIBE until it noted the mid
            filters = self._asked.pop(mid, [])
        for (topic_filter, qos), code in zip(filters, codes, strict=False):
            granted = int(code.value)
            self.granted[topic_filter] = granted
            if granted >= 128:
                log.warning(
                    "%s: %s:%d refused the subscription to %r; asking again in %g s (if it "
                    "never takes it, check the broker's ACL and topic rules: docs/brokers.md)",
                    self.name,
                    *self.address,
                    topic_filter,
                    _RESUBSCRIBE_AFTER,
                )
                retry = threading.Timer(_RESUBSCRIBE_AFTER, self._resubscribe, (topic_filter,))
                retry.daemon = True
                retry.start()
            elif granted < qos:
                log.warning(
                    "%s: %s:%d granted QoS %d for %r (asked %d); messages arrive at QoS %d",
                    self.name,
                    *self.address,
                    granted,
                    topic_filter,
                    qos,
                    granted,
                )

    def _resubscribe(self, topic_filter: str) -> None:
        """A timer's thread: the broker refused `topic_filter` (a clustered broker does
        while it elects new leaders after a node failure); ask again."""
        qos = self._subscriptions.get(topic_filter)
        if self._started and qos is not None:
            self.subscribe(topic_filter, qos)

    def _on_message(self, _c: mqtt.Client, _u: Any, message: mqtt.MQTTMessage) -> None:
        try:
            event = Message._from_paho(message, self.name)
        except UnicodeDecodeError:  # paho decodes the topic lazily; it must not escape here
            self.dropped_topics += 1
            log.debug("%s: dropped a message whose topic is not UTF-8", self.name)
            return
        levels = event.topic.split("/")
        if not any(matches(f, levels) for f in self._filters):
            self.dropped_foreign += 1
            log.debug("%s: dropped a message on a topic it did not subscribe to", self.name)
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
            self._filters = tuple(tuple(f.split("/")) for f in self._subscriptions)
            if self.connected:
                _rc, mid = self._client.subscribe(topic_filter, qos)
                if mid is not None:
                    self._asked[mid] = [(topic_filter, qos)]
                if self._loop is not None:
                    self._loop._flush(self)

    def set_sink(self, sink: Callable[[Event], None]) -> None:
        """Hand events to `sink` from now on (before `start`): under a `ClientLoop`, a
        component may take its events on the loop's thread instead of its own."""
        if self._started:
            raise RuntimeError(f"{self.name}: change the sink before start()")
        self._sink = sink

    def attach(self, loop: ClientLoop) -> None:
        """Have `loop`'s thread drive this connection instead of a paho thread of its own;
        before `start` (for a transport another object builds, such as a participant's)."""
        if self._started:
            raise RuntimeError(f"{self.name}: attach a transport to a loop before start()")
        self._loop = loop
        # With this callback set, paho never writes on the caller's thread: a publish
        # only queues its packet, and `_publish` asks the loop to write it.
        self._client.on_socket_register_write = _ignore_socket
        self._client.on_socket_close = loop._socket_closing
        self._client.user_data_set(self)  # paho hands it to `_socket_closing`

    def start(self, timeout: float | None = None) -> None:
        """Connect in the background; with a timeout, wait for the first connection."""
        self._started = True
        if self.down_since is None and not self.connected:
            self.down_since = time.time()
        self._client.connect_async(self.settings.host, self.settings.port, self.settings.keepalive)
        if self._loop is not None:
            self._loop._add(self)
        else:
            self._client.loop_start()
        if timeout is not None and not self._connected.wait(timeout):
            self.stop()
            why = f" (refused: {self.refusal})" if self.refusal else ""
            raise ConnectError(
                f"{self.name}: no connection to {self.settings.url} within {timeout} s{why}; "
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
                if self._loop is not None:
                    self._loop._flush(self)
                ok = info.rc == mqtt.MQTT_ERR_SUCCESS or (
                    qos > 0 and info.rc == mqtt.MQTT_ERR_NO_CONN  # paho re-sends it
                )
                if info.rc == mqtt.MQTT_ERR_SUCCESS and qos > 0:
                    # (one taken as the connection dropped is re-sent by paho, but its
                    # receipt raises instead of telling; the lost connection is seen anyway)
                    self._unacked.append((info, time.time()))
                    self._drop_acked()
                return info if ok else None
            if qos == 0 or len(self._held) >= _MAX_QUEUED:
                return None
            self._held.append((topic, payload, qos, retain))
            return True

    def _drop_acked(self) -> None:
        """Forget the acknowledged publishes at the head of ``_unacked`` (hold ``_lock``)."""
        unacked = self._unacked
        while unacked and unacked[0][0].is_published():
            unacked.popleft()

    def unacked_for(self, now: float) -> float:
        """How long the oldest QoS 1/2 publish not yet acknowledged by the broker has
        waited (0: none waits). A broker that takes the connection but cannot store
        messages (a NATS cluster without JetStream quorum) shows here first."""
        with self._lock:
            self._drop_acked()
            return now - self._unacked[0][1] if self._unacked else 0.0

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
        """Disconnect cleanly (no last will) and stop the network thread; a persistent
        session is then discarded at the broker."""
        was_started, self._started = self._started, False
        if self._loop is not None:
            self._loop._remove(self, clean=True)
        else:
            self._client.disconnect()
            self._client.loop_stop()
        self._connected.clear()
        if was_started and not self.settings.clean_session:
            self._discard_session()

    def _discard_session(self, timeout: float = 2.0) -> None:
        """Connect once more with a clean session, so the broker drops the old one
        (MQTT 3.1.1 has no other way); else a cluster keeps queueing for it."""
        done = threading.Event()
        client = _client(self.settings, self.client_id, clean_session=True)
        client.on_connect = lambda *_args: done.set()
        host, port = self.address
        try:
            client.connect(host, port, self.settings.keepalive)
            deadline = time.monotonic() + timeout
            while not done.is_set() and time.monotonic() < deadline:
                client.loop(0.05)
            if done.is_set():
                client.disconnect()
                client.loop(0.05)
        except (OSError, ValueError) as exc:
            log.info("%s: could not discard the session at %s:%d: %s", self.name, host, port, exc)
        sock = client.socket()
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.close()
        if not done.is_set():
            log.info("%s: the broker may keep the session of %r", self.name, self.client_id)

    def kill(self) -> None:
        """Drop the connection without DISCONNECT, so the broker sends the last will."""
        self._started = False
        if self._loop is not None:
            self._loop._remove(self, clean=False)
            self._connected.clear()
            return
        sock = self._client.socket()
        if sock is not None:
            with contextlib.suppress(OSError, AttributeError):
                sock.shutdown(socket.SHUT_RDWR)  # type: ignore[attr-defined]
        self._client.loop_stop()
        self._connected.clear()


class ClientLoop:
    """One thread that drives the connections of many transports (paho's external loop).

        loop = ClientLoop().start()
        transports = [Transport(settings, client_id=f"c{i}", sink=..., loop=loop) ...]
        ...                      # start, publish, subscribe and stop as usual
        loop.stop()              # after the transports have stopped

    The thread waits on a ``selectors`` poller (epoll on Linux: no limit of 1024
    descriptors), reads and writes each ready socket with ``loop_read``/``loop_write``,
    runs ``loop_misc`` (keep-alive) once a second, and reconnects a lost connection
    with the transport's back-off (``reconnect_min`` doubling up to ``reconnect_max``,
    reset on each CONNACK). A publish from any thread queues its packet in paho and
    asks the loop, through a wake-up socket pair, to write it. Each connection costs
    one descriptor and no thread; the callbacks of all transports run on this thread,
    one at a time, so a slow sink delays every connection of the loop.
    """

    def __init__(self, name: str = "ldm-client-loop", misc_interval: float = 1.0) -> None:
        self.name = name
        self._misc_interval = misc_interval
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, None)
        self._calls: deque[Callable[[], None]] = deque()
        self._woken = False
        self._transports: dict[Transport, tuple[Any, int] | None] = {}
        """Each transport -> the socket registered for it and its events (None: none)."""
        self._delay: dict[Transport, float] = {}  # the next reconnect back-off
        self._timers: list[tuple[float, int, Transport]] = []  # reconnects due
        self._waiting: set[Transport] = set()  # transports with a reconnect in _timers
        self._jobs: list[tuple[float, int, float, Callable[[], bool]]] = []  # `every`
        self._seq = itertools.count()
        self._running = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def __len__(self) -> int:
        """Transports attached (started and not yet stopped)."""
        return len(self._transports)

    def start(self) -> ClientLoop:
        self._running = True
        self._thread.start()
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the thread; connections still open are dropped without DISCONNECT."""
        if not self._running:
            return
        self._call(self._halt)
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)

    def __enter__(self) -> ClientLoop:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    # --- any thread -------------------------------------------------------------------

    def every(self, interval: float, fn: Callable[[], bool]) -> None:
        """Run `fn` on the loop's thread every `interval` s until it returns False."""

        def schedule() -> None:
            when = time.monotonic() + interval
            heapq.heappush(self._jobs, (when, next(self._seq), interval, fn))

        self._call(schedule)

    def _call(self, fn: Callable[[], None]) -> None:
        """Run `fn` on the loop's thread, soon."""
        self._calls.append(fn)
        if not self._woken:
            self._woken = True
            with contextlib.suppress(BlockingIOError, OSError):
                self._wake_w.send(b"\0")

    def _add(self, transport: Transport) -> None:
        self._call(lambda: self._connect(transport, first=True))

    def _flush(self, transport: Transport) -> None:
        """paho queued a packet for `transport` (any thread): write it from the loop."""
        self._call(lambda: self._write(transport))

    def _remove(self, transport: Transport, *, clean: bool) -> None:
        """Stop driving `transport`: send DISCONNECT first if `clean`; waits up to 5 s
        unless called on the loop's thread."""
        done = threading.Event()

        def remove() -> None:
            try:
                self._close(transport, clean)
            finally:
                done.set()

        if threading.current_thread() is self._thread:
            remove()
        elif self._running and self._thread.is_alive():
            self._call(remove)
            done.wait(5.0)

    # --- the loop's thread ------------------------------------------------------------

    def _socket_closing(self, _client: mqtt.Client, transport: Any, sock: Any) -> None:
        # paho closes a socket only on this thread (reads, writes, keep-alive, reconnect),
        # just before it closes it: unregister while its descriptor is still its own.
        with contextlib.suppress(KeyError, ValueError, OSError):
            self._selector.unregister(sock)
        if self._transports.get(transport) is not None:
            self._transports[transport] = None

    def _halt(self) -> None:
        self._running = False
        for transport in list(self._transports):
            self._close(transport, clean=False)

    def _close(self, transport: Transport, clean: bool) -> None:
        if transport not in self._transports:
            return
        client = transport._client
        if clean and client.socket() is not None and transport.connected:
            client.disconnect()
            with contextlib.suppress(Exception):
                client.loop_write()  # sends DISCONNECT; paho then closes the socket
        sock = client.socket()
        if sock is not None:
            with contextlib.suppress(KeyError, ValueError, OSError):
                self._selector.unregister(sock)
            if not clean:
                with contextlib.suppress(OSError, AttributeError):
                    sock.shutdown(socket.SHUT_RDWR)  # type: ignore[attr-defined]
            with contextlib.suppress(OSError):
                sock.close()
        self._transports.pop(transport, None)
        self._delay.pop(transport, None)
        self._waiting.discard(transport)

    def _connect(self, transport: Transport, first: bool = False) -> None:
        if first:
            self._transports.setdefault(transport, None)
            self._delay[transport] = transport.settings.reconnect_min
        if not transport._started or transport not in self._transports:
            return
        try:
            transport._client.reconnect()
        except (OSError, ValueError) as exc:
            log.debug("%s: could not connect: %s", transport.name, exc)
            self._retry(transport)
            return
        self._write(transport)

    def _retry(self, transport: Transport) -> None:
        if transport in self._waiting:
            return
        self._waiting.add(transport)
        delay = self._delay.get(transport, transport.settings.reconnect_min)
        self._delay[transport] = min(2.0 * delay, transport.settings.reconnect_max)
        heapq.heappush(self._timers, (time.monotonic() + delay, next(self._seq), transport))

    def _write(self, transport: Transport) -> None:
        client = transport._client
        if client.socket() is not None and client.want_write():
            client.loop_write()
        self._sync(transport)

    def _sync(self, transport: Transport) -> None:
        """Register the transport's current socket for the events it needs; a lost
        connection of a started transport is retried after its back-off."""
        if transport not in self._transports:
            return
        client = transport._client
        sock = client.socket()
        slot = self._transports[transport]
        if sock is None:
            if slot is not None:
                with contextlib.suppress(KeyError, ValueError, OSError):
                    self._selector.unregister(slot[0])
                self._transports[transport] = None
            if transport._started:
                self._retry(transport)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.want_write() else 0)
        if slot is None or slot[0] is not sock:
            if slot is not None:
                with contextlib.suppress(KeyError, ValueError, OSError):
                    self._selector.unregister(slot[0])
            self._selector.register(sock, events, transport)
        elif slot[1] != events:
            self._selector.modify(sock, events, transport)
        self._transports[transport] = (sock, events)

    def _run(self) -> None:
        next_misc = time.monotonic() + self._misc_interval
        while self._running:
            now = time.monotonic()
            due = min(next_misc, self._timers[0][0]) if self._timers else next_misc
            if self._jobs:
                due = min(due, self._jobs[0][0])
            try:
                ready = self._selector.select(max(0.0, due - now))
            except OSError:
                log.exception("%s: select failed", self.name)
                ready = []
            for key, mask in ready:
                transport = key.data
                if transport is None:
                    with contextlib.suppress(BlockingIOError, OSError):
                        while self._wake_r.recv(4096):
                            pass
                    continue
                self._ready(transport, mask)
            self._woken = False
            while self._calls:
                try:
                    self._calls.popleft()()
                except Exception:
                    log.exception("%s: error in a loop call", self.name)
            now = time.monotonic()
            while self._timers and self._timers[0][0] <= now:
                _, _, transport = heapq.heappop(self._timers)
                self._waiting.discard(transport)
                if transport._client.socket() is None:
                    self._connect(transport)
            while self._jobs and self._jobs[0][0] <= now:
                _, _, interval, job = heapq.heappop(self._jobs)
                try:
                    again = job()
                except Exception:
                    log.exception("%s: error in a periodic call", self.name)
                    again = True
                if again:
                    heapq.heappush(self._jobs, (now + interval, next(self._seq), interval, job))
            if now >= next_misc:
                next_misc = now + self._misc_interval
                for transport in list(self._transports):
                    if transport._client.socket() is not None:
                        transport._client.loop_misc()
                        self._sync(transport)
        self._selector.close()
        self._wake_r.close()
        self._wake_w.close()

    def _ready(self, transport: Transport, mask: int) -> None:
        client = transport._client
        try:
            if mask & selectors.EVENT_READ:
                client.loop_read()
            if client.socket() is not None and client.want_write():
                client.loop_write()
        except Exception:
            log.exception("%s: error on the connection", transport.name)
        self._sync(transport)
