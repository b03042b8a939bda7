"""Batches: many envelopes in one MQTT message, and the outbox that makes them.

Between the cores, and between a service core and its provider, the envelopes that
wait together for one destination travel as one message on that destination's batch
topic (`ldm.wire.topics`: the single topic without its pseudonym level). The payload
is one line per envelope, joined by ``\\n``::

    {pseudonym} {envelope}

``envelope`` is the envelope's compact JSON exactly as a single message carries it
(`ldm.wire.messages.Envelope.encode`, which never writes a raw newline). A batch is cut
apart without parsing an envelope, so a core forwards ciphertext as the bytes it
received; each envelope is then checked by whoever reads it, and a malformed line
costs only itself.

`Outbox` is the sending side: a dispatch thread adds each envelope as it handles what waited,
and flushes once it has handled all of it, so under light load nothing waits. What it
sends to one destination always goes on the destination's batch topic, one envelope or
many: MQTT keeps the order of the messages on one topic, not across topics, so a
participant's envelope sent alone on its own topic could overtake the one before it in
a batch (the embedded broker did, under load).
"""

from __future__ import annotations

from typing import Final, NamedTuple, Protocol

from ldm.wire.topics import PSEUDONYM_PATTERN, Topic

__all__ = ["MAX_BATCH_BYTES", "Entry", "Outbox", "Publisher", "cut", "decode", "encode"]

MAX_BATCH_BYTES: Final = 64 * 1024
"""A batch is sent once it holds this many bytes, and a new one begun."""

_SEP: Final = b" "
_EOL: Final = b"\n"


def encode(entries: list[tuple[str, bytes]]) -> bytes:
    """``(pseudonym, envelope)`` pairs as one batch payload."""
    return _EOL.join(p.encode() + _SEP + envelope for p, envelope in entries)


def decode(payload: bytes) -> tuple[list[tuple[str, bytes]], int]:
    """A batch payload -> its ``(pseudonym, envelope)`` pairs in order, and the number
    of lines that were malformed (no pseudonym that can be a topic level, or no
    envelope); a malformed line is skipped, the rest are kept."""
    entries: list[tuple[str, bytes]] = []
    bad = 0
    match = PSEUDONYM_PATTERN.match
    for line in payload.split(_EOL):
        name, sep, envelope = line.partition(_SEP)
        try:
            pseudonym = name.decode("ascii")
        except UnicodeDecodeError:
            bad += 1
            continue
        if not sep or not envelope or match(pseudonym) is None:
            bad += 1
            continue
        entries.append((pseudonym, envelope))
    return entries, bad


class Entry(NamedTuple):
    """One envelope as a core or a provider queues it: the topic it came on, parsed
    once on arrival (a batch's topic, or a single message's), the pseudonym it travels
    under (a batch line's, or the single topic's), its bytes as received, and the QoS
    and transport (``source``) of the message that carried it. A message on a topic
    without a pseudonym (a core's control messages) is one too, its ``pseudonym`` empty."""

    topic: Topic
    pseudonym: str
    payload: bytes
    qos: int
    source: str


def cut(payload: bytes, topic: Topic, qos: int, source: str) -> tuple[list[Entry], int]:
    """A batch that came on `topic` (parsed) -> its entries in order, and the number of
    malformed lines (`decode`)."""
    pairs, bad = decode(payload)
    return [Entry(topic, pseudonym, envelope, qos, source) for pseudonym, envelope in pairs], bad


class Publisher(Protocol):
    """What an `Outbox` sends through (an `ldm.transport.Transport`)."""

    def publish(self, topic: str, payload: bytes, qos: int = 0, retain: bool = False) -> object:
        """Publish one message."""


class Outbox:
    """Envelopes held by one dispatch thread while it handles what waited (not thread
    safe: one dispatch thread adds and flushes). Each destination is a publisher and a batch
    topic; `flush` sends each destination's envelopes in the order they were added."""

    def __init__(self) -> None:
        self._groups: dict[tuple[int, str], _Group] = {}
        self.batches = 0
        """Batches sent so far (messages that carried more than one envelope)."""
        self.batched = 0
        """Envelopes sent in those batches."""

    def add(
        self,
        publisher: Publisher,
        batch_topic: str,
        pseudonym: str,
        envelope: bytes,
        qos: int,
    ) -> None:
        """Hold `envelope` for `pseudonym`, to be sent in a batch on `batch_topic` (of
        one, if it is alone at the next `flush`: never on its own single topic, see the
        module docstring). `envelope` must hold no newline."""
        key = (id(publisher), batch_topic)
        group = self._groups.get(key)
        if group is None:
            group = self._groups[key] = _Group(publisher, batch_topic)
        group.add(pseudonym, envelope, qos)
        if group.size >= MAX_BATCH_BYTES:
            self._sent(group.send())

    def flush(self) -> None:
        """Send everything held: one message per destination."""
        groups, self._groups = self._groups, {}
        for group in groups.values():
            self._sent(group.send())

    def _sent(self, batched: int) -> None:
        if batched:
            self.batches += 1
            self.batched += batched

    def __len__(self) -> int:
        """Envelopes held now."""
        return sum(len(g.entries) for g in self._groups.values())


class _Group:
    """One destination's envelopes, in order."""

    __slots__ = ("batch_topic", "entries", "publisher", "qos", "size")

    def __init__(self, publisher: Publisher, batch_topic: str) -> None:
        self.publisher = publisher
        self.batch_topic = batch_topic
        self.entries: list[tuple[str, bytes]] = []
        self.qos = 0
        self.size = 0

    def add(self, pseudonym: str, envelope: bytes, qos: int) -> None:
        self.entries.append((pseudonym, envelope))
        self.qos = max(self.qos, qos)
        self.size += len(envelope) + len(pseudonym) + 2

    def send(self) -> int:
        """Publish what is held on the batch topic; the number of envelopes sent in a
        batch of more than one (0: none, or one alone)."""
        entries = self.entries
        batched = 0
        if entries:
            self.publisher.publish(self.batch_topic, encode(entries), self.qos)
            batched = len(entries) if len(entries) > 1 else 0
        self.entries = []
        self.size = 0
        self.qos = 0
        return batched
