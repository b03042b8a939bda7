"""What a core and a provider do once per message, not once per hop: each topic parsed
on arrival and carried (`ldm.wire.batch.Entry`), the bytes received forwarded as they
came (`ldm.wire.messages.untagged`, `reply_bytes`). No brokers: never-connected
components, fed through their sinks as paho's thread would."""

from __future__ import annotations

import base64
import json
import time
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from ldm import Core, KeyPair, Provider, ServiceSpec
from ldm.security.crypto import aad
from ldm.transport.mqtt import Message
from ldm.wire import batch, topics
from ldm.wire.batch import Entry
from ldm.wire.messages import Envelope, reply_bytes, untagged

UNREACHABLE = "mqtt://127.0.0.1:9"  # never connected: publishes only queue

_B64_32 = st.binary(min_size=32, max_size=32).map(lambda b: base64.b64encode(b).decode())
_TOKENS = st.from_regex(r"\A[A-Za-z0-9_-]{1,64}\Z")
_TIMES = st.floats(min_value=0, max_value=4e9)


@given(
    c=_TOKENS,
    t=_TIMES,
    k=_B64_32,
    d=st.binary(max_size=64).map(lambda b: base64.b64encode(b).decode()),
    m=st.binary(min_size=18, max_size=18).map(lambda b: base64.b64encode(b).decode()),
)
def test_the_user_core_cuts_the_tag_off_the_bytes_it_received(
    c: str, t: float, k: str, d: str, m: str
) -> None:
    env = Envelope(c=c, t=t, k=k, d=d, m=m)
    without = Envelope(c=c, t=t, k=k, d=d).encode()
    assert untagged(env, env.encode()) == without
    # Written some other way (spaces, another order): encoded again, the same envelope.
    spaced = json.dumps({"m": m, "d": d, "k": k, "t": t, "c": c}).encode()
    assert untagged(env, spaced) == without


def test_input_with_fields_the_core_does_not_know_is_encoded_again() -> None:
    k, m = "A" * 43 + "=", "B" * 24
    raw = f'{{"c":"a1","t":1.0,"k":"{k}","d":"AAAA","client_id":"alice","m":"{m}"}}'.encode()
    out = untagged(Envelope.model_validate_json(raw), raw)
    assert b"alice" not in out and b'"m"' not in out
    assert Envelope.model_validate_json(out) == Envelope(c="a1", t=1.0, k=k, d="AAAA")


@given(c=_TOKENS, t=_TIMES)
def test_a_reply_of_c_t_and_d_alone_is_delivered_as_it_came(c: str, t: float) -> None:
    env = Envelope(c=c, t=t, d="AAAA")
    payload = env.encode()
    assert reply_bytes(env, payload) is payload


@pytest.mark.parametrize(
    "raw",
    [
        b'{"c":"a1","t":1.0,"d":"AAAA","client_id":"alice"}',
        b'{"c":"a1","t":1.0,"d":"AAAA","k":"' + b"A" * 43 + b'="}',
        b'{"c":"a1","t":1.0,"d":"AAAA","m":"' + b"B" * 24 + b'"}',
        b'{"c":"a\\u0031","t":1.0,"d":"AAAA"}',
    ],
)
def test_a_reply_with_anything_else_is_encoded_again(raw: bytes) -> None:
    out = reply_bytes(Envelope.model_validate_json(raw), raw)
    assert out == Envelope(c="a1", t=1.0, d="AAAA").encode()


@pytest.fixture
def parses(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """Every topic `topics.parse` is asked to take apart."""
    seen: list[str] = []
    real = topics.parse

    def counting(topic: str) -> topics.Topic:
        seen.append(topic)
        return real(topic)

    monkeypatch.setattr(topics, "parse", counting)
    yield seen


def _envelope(c: str, **fields: Any) -> bytes:
    return Envelope(c=c, t=time.time(), d="AAAA", **fields).encode()


def test_a_core_parses_a_batch_topic_once_and_queues_entries(parses: list[str]) -> None:
    core = Core.create("svc", UNREACHABLE, UNREACHABLE)
    try:
        topic = topics.bb_input_batch("svc", "echo", "user")
        key = KeyPair().public
        lines = [(f"p{i}", _envelope(f"c{i}", k=key)) for i in range(3)]
        core.sink(Message(topic, batch.encode(lines), 1, False, "backbone"))
        items = core._intake.take(10)
        assert [type(item) for item in items] == [Entry] * 3
        assert all(isinstance(i, Entry) and i.topic.kind == "bb_input_batch" for i in items)
        assert [(i.pseudonym, i.payload) for i in items if isinstance(i, Entry)] == lines
        core.handle_many(items)  # type: ignore[arg-type]
        assert core.stats.dropped_unroutable == 3  # echo is not served here
        assert parses == [topic]
    finally:
        core.cluster.stop()


def test_a_core_parses_a_participants_topic_once(parses: list[str]) -> None:
    core = Core.create("edge", UNREACHABLE)
    try:
        topic = topics.participant_input("alice", "echo")
        core.sink(Message(topic, _envelope("c1", k=KeyPair().public), 0, False, "cluster"))
        core.handle_many(core._intake.take(10))  # type: ignore[arg-type]
        assert core.stats.answered_nosession == 1
        assert parses == [topic]
    finally:
        core.cluster.stop()


def test_a_provider_parses_a_batch_topic_once(parses: list[str]) -> None:
    service = KeyPair()
    provider = Provider.create(
        UNREACHABLE, ServiceSpec(name="echo"), lambda r: {"ok": 1}, key=service
    )
    try:
        lines = []
        for i in range(3):
            eph, c, t = KeyPair(), f"c{i}", time.time()
            sealed = eph.cipher(service.public, initiator=True).seal(b"{}", aad(c, t))
            lines.append((f"p{i}", Envelope(c=c, t=t, k=eph.public, d=sealed).encode()))
        topic = topics.provider_input_batch("echo")
        provider.sink(Message(topic, batch.encode(lines), 1, False, "svc"))
        items = provider._queue.take(10)
        assert [i.pseudonym for i in items if isinstance(i, Entry)] == ["p0", "p1", "p2"]
        provider.handle_many(items)  # type: ignore[arg-type]
        assert (provider.stats.requests, provider.stats.replies) == (3, 3)
        assert parses == [topic]
    finally:
        provider.transport.stop()
