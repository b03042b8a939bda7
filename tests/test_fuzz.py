"""Property tests: every network decoder takes five thousand generated payloads.

The decoders are called in-process (no broker round trip), on a core, a provider, a
participant and a LaaS worker that are built but never connected: their transports only
queue. Promises checked for each payload: the decoder never raises, the message is
accounted for in exactly one counter (core, provider, worker), and another participant's
state is untouched. Times are drawn per example around the clock of the moment, so fresh
input really is forwarded.

Each example is a batch of `BATCH` payloads, so 200 examples make 5,000 payloads per
decoder in a few seconds (hypothesis' own cost is per example, not per payload). That is
twice hypothesis' default number of examples and fifty times its payloads; 10,000 per
decoder cost the test command about 36 s more on the 2-core test machine.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from laas.errors import MapError, TraceError
from laas.map.geojson import read_geojson
from laas.map.hdmap import HdMap
from laas.models import GpsMeasurement
from laas.sim.trace import TraceLine, read_trace
from laas.worker.service import LaasService
from ldm import Core, KeyPair, LdmError, Participant, Provider, Request, ServiceSpec
from ldm.client.participant import Session
from ldm.security.crypto import aad
from ldm.transport import Message
from ldm.wire.messages import (
    Announcement,
    Envelope,
    ServiceDescription,
    SessionGrant,
    SessionRequest,
)

BATCH = 25
FUZZ = settings(
    max_examples=5_000 // BATCH,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much],
)
SMALL = settings(FUZZ, max_examples=300)

UNREACHABLE = "mqtt://127.0.0.1:9"  # never connected: publishes stay in paho's queue
SPEC = ServiceSpec(name="echo", version="1")

# --- payload strategies -------------------------------------------------------------

ODD: list[Any] = [
    None,
    True,
    0,
    -1,
    2**64,
    -(2**70),
    1e308,
    -0.0,
    float("nan"),
    float("inf"),
    float("-inf"),
    "",
    "\u0000",
    "é" * 3,
    "../#",
    "+",
    "ldm/#",
    "A" * 44,
    "AAAA",
    "1.0",
    [],
    [1, "a"],
    {},
    {"c": {"c": None}},
    [[[[[]]]]],
    "x" * 5000,
]
odd_values = st.sampled_from(ODD) | st.integers() | st.floats() | st.text(max_size=8)


def mutations(valid: dict[str, Any]) -> st.SearchStrategy[dict[str, Any]]:
    """A valid object with fields dropped, replaced by odd values, or added."""
    return mutated(st.just(valid), sorted(valid))


def mutated(
    valid: st.SearchStrategy[dict[str, Any]], keys: list[str]
) -> st.SearchStrategy[dict[str, Any]]:
    """`mutations` of a valid object drawn per example (fresh times) with these keys."""
    return st.builds(
        lambda v, drop, replace, extra: {
            **{k: x for k, x in v.items() if k not in drop},
            **replace,
            **extra,
        },
        valid,
        st.sets(st.sampled_from(keys), max_size=3),
        st.dictionaries(st.sampled_from(keys), odd_values, max_size=3),
        st.dictionaries(st.sampled_from(["x", "user", "k2", "c "]), odd_values, max_size=1),
    )


AGES = st.sampled_from([0.0, 0.0, 0.0, 0.5, 3.0, -40.0]) | st.floats(-100, 100)
"""Seconds before now of a drawn ``t``: mostly fresh, some stale, some from the future."""


def now_minus(age: float) -> float:
    return time.time() - age


def encoded(objects: st.SearchStrategy[Any]) -> st.SearchStrategy[bytes]:
    """JSON (with NaN/Infinity literals when floats are odd), and raw bytes."""
    return objects.map(lambda o: json.dumps(o).encode()) | st.binary(max_size=64)


def batches(payloads: st.SearchStrategy[Any]) -> st.SearchStrategy[list[Any]]:
    return st.lists(payloads, min_size=BATCH, max_size=BATCH)


# --- fixtures: one core, provider and worker, never connected -----------------------


PROVIDER_KEY = KeyPair()


@pytest.fixture(scope="module")
def provider_key() -> KeyPair:
    return PROVIDER_KEY


BOB_KEY = KeyPair()  # the fuzzed participant's current ephemeral key


@pytest.fixture(scope="module")
def core(provider_key: KeyPair) -> Iterator[Core]:
    """A single-cluster core that knows `echo` and holds alice's and bob's sessions."""
    c = Core.create(
        "fuzz",
        UNREACHABLE,
        rate=1e9,
        burst=1e9,
        max_payload=4096,
        service_ttl=3600,
        rotation_period=3600,  # a key change stays refused however long the fuzz runs
    )
    description = ServiceDescription(**SPEC.model_dump(), public_key=provider_key.public)
    announcement = Announcement(service=description, t=time.time())  # lives service_ttl
    c.handle(cluster("ldm/svc/echo/announce", announcement.model_dump_json().encode()))
    for who, key in (("alice", KeyPair()), ("bob", BOB_KEY)):
        request = SessionRequest(c="a1", service="echo", t=time.time())
        c.handle(cluster(f"ldm/p/{who}/up/session", request.model_dump_json().encode()))
        env = Envelope(c="a2", t=time.time(), k=key.public, d="AAAA")
        c.handle(cluster(f"ldm/p/{who}/up/data/echo", env.encode()))
    assert c.stats.forwarded_in == 2
    yield c
    c.cluster.stop()


def cluster(topic: str, payload: bytes) -> Message:
    return Message(topic, payload, 1, False, "cluster")


def alice_state(core: Core) -> tuple[object, ...]:
    session = core.sessions.get("alice", "echo")
    assert session is not None
    names = tuple(core.sessions.pseudonyms(session))
    return names, tuple(sorted(n for n in names if core.sessions.of(n) is session))


def core_outcomes(core: Core) -> int:
    s = core.stats
    return (
        s.forwarded_in
        + s.forwarded_out
        + s.dropped_invalid
        + s.dropped_stale
        + s.dropped_unroutable
        + s.rejected_rate
        + s.rejected_size
        + s.rejected_clock
        + s.rejected_rekey
        + s.answered_nosession
        + s.answered_refused
        + s.granted
        + s.control
    )


# bob's input: his session key (forwarded when fresh) or another (a key change refused)
bob_envelopes = st.builds(
    lambda k, age: {"c": "abc", "t": now_minus(age), "k": k, "d": "AAAA"},
    st.sampled_from([BOB_KEY.public] * 3 + [KeyPair().public]),
    AGES,
)


# --- the core: participant input and session requests ------------------------------


@FUZZ
@given(
    batch=batches(
        st.tuples(
            encoded(mutated(bob_envelopes, ["c", "t", "k", "d"])),
            st.sampled_from(["echo", "echo", "nope", "x" * 200, "ec%ho"]),
        )
    )
)
def test_core_participant_input_decoder(core: Core, batch: list[tuple[bytes, str]]) -> None:
    before = alice_state(core)
    for payload, service in batch:
        outcomes = core_outcomes(core)
        core.handle(cluster(f"ldm/p/bob/up/data/{service}", payload))
        assert core_outcomes(core) == outcomes + 1
    assert alice_state(core) == before
    bob = core.sessions.get("bob", "echo")
    assert (
        bob is not None and bob.current is not None and bob.current.key == BOB_KEY.public
    )  # no churn


def test_the_input_fuzz_reaches_forwarding(core: Core) -> None:
    """Guards the fuzz above: fresh input of the session's key is forwarded."""
    forwarded = core.stats.forwarded_in
    env = {"c": "abc", "t": time.time(), "k": BOB_KEY.public, "d": "AAAA"}
    core.handle(cluster("ldm/p/bob/up/data/echo", json.dumps(env).encode()))
    assert core.stats.forwarded_in == forwarded + 1


@FUZZ
@given(
    batch=batches(
        st.tuples(
            encoded(mutations({"c": "r1", "service": "echo", "t": 1.0})),
            st.sampled_from(["mallory", "m2", "m3"]),
        )
    )
)
def test_core_session_request_decoder(core: Core, batch: list[tuple[bytes, str]]) -> None:
    before = alice_state(core)
    for payload, client in batch:
        outcomes = core_outcomes(core)
        core.handle(cluster(f"ldm/p/{client}/up/session", payload))
        assert core_outcomes(core) == outcomes + 1
    assert alice_state(core) == before
    assert all(s.service == "echo" for s in core.sessions)  # only known services
    assert len(core.sessions) <= 5  # alice, bob, plus at most one per client


@FUZZ
@given(
    batch=batches(
        st.tuples(
            encoded(
                mutated(
                    st.builds(
                        lambda age, origin: {
                            "service": {"name": "ghost", "public_key": "A" * 43 + "="},
                            "t": now_minus(age),
                            "origin": origin,
                        },
                        AGES,
                        st.sampled_from(["other", "fuzz", None]),
                    ),
                    ["service", "t", "origin"],
                )
                | mutations({"name": "other", "online": False})
                | mutated(
                    st.builds(lambda age: {"c": "abc", "t": now_minus(age), "d": "AAAA"}, AGES),
                    ["c", "t", "d"],
                )
            )
            | st.just(b""),
            st.sampled_from(
                [
                    ("backbone", "ldm/bb/announce/ghost"),
                    ("backbone", "ldm/bb/core/other"),
                    ("backbone", "ldm/bb/in/fuzz/echo/other/pq"),
                    ("backbone", "ldm/bb/out/fuzz/echo/pq"),
                    ("cluster", "ldm/svc/ghost/announce"),
                    ("cluster", "ldm/svc/echo/out/pq"),
                ]
            ),
        )
    )
)
def test_core_backbone_and_announcement_decoders(
    core: Core, batch: list[tuple[bytes, tuple[str, str]]]
) -> None:
    before = alice_state(core)
    for payload, (source, topic) in batch:
        outcomes = core_outcomes(core)
        core.handle(Message(topic, payload, 1, False, source))
        assert core_outcomes(core) == outcomes + 1, (topic, payload)
    assert alice_state(core) == before
    assert "echo" in {s.name for s in core.services}  # nobody else's service is removed
    entry = core.catalog.get("echo")
    assert entry is not None and entry.origin == "fuzz"


# --- the provider's input decoder --------------------------------------------------


@pytest.fixture(scope="module")
def provider(provider_key: KeyPair) -> Iterator[tuple[Provider, list[Request]]]:
    seen: list[Request] = []

    def handler(request: Request) -> dict[str, Any]:
        seen.append(request)
        return {"ok": True}

    p = Provider.create(UNREACHABLE, SPEC, handler, key=provider_key, max_payload=4096)
    yield p, seen
    p.transport.stop()


PLAINTEXTS = [b"{}", b'{"a": NaN}', b"[]", b"null", b"\xff", b"{" * 3000 + b"}" * 3000, b""]


PARTICIPANT_KEY = KeyPair()
PARTICIPANT_CIPHER = PARTICIPANT_KEY.cipher(PROVIDER_KEY.public, initiator=True)


def sealed(plaintext: bytes, c: str, age: float) -> dict[str, Any]:
    """A valid input envelope, stamped now minus `age` (key agreement done once)."""
    t = now_minus(age)
    d = PARTICIPANT_CIPHER.seal(plaintext, aad(c, t))
    return {"c": c, "t": t, "k": PARTICIPANT_KEY.public, "d": d}


sealed_inputs = st.builds(
    sealed,
    st.sampled_from(PLAINTEXTS),
    st.sampled_from(["abc", "abd"]) | st.from_regex(r"\A[a-z]{8}\Z"),
    AGES,
)


@FUZZ
@given(batch=batches(encoded(mutated(sealed_inputs, ["c", "t", "k", "d"]))))
def test_provider_input_decoder(
    provider: tuple[Provider, list[Request]], batch: list[bytes]
) -> None:
    p, seen = provider
    s = p.stats

    def outcomes() -> int:
        return (
            s.requests
            + s.dropped_invalid
            + s.dropped_stale
            + s.dropped_oversize
            + s.dropped_replay
            + s.answered_again
        )

    for payload in batch:
        before = outcomes()
        handled = len(seen)
        p.handle(Message("ldm/svc/echo/in/pq", payload, 1, False, "provider"))
        assert outcomes() == before + 1
        if len(seen) > handled:  # what reaches the handler is a decrypted JSON object
            assert isinstance(seen[-1].payload, dict)
    assert s.handler_errors == 0


def test_the_provider_fuzz_reaches_the_handler(provider: tuple[Provider, list[Request]]) -> None:
    """Guards the fuzz above: a fresh, well-sealed input is handled."""
    p, seen = provider
    handled = len(seen)
    env = sealed(b'{"x": 1}', "guard1", 0.0)
    p.handle(Message("ldm/svc/echo/in/pq", json.dumps(env).encode(), 1, False, "provider"))
    assert len(seen) == handled + 1 and seen[-1].payload == {"x": 1}


# --- the participant's decoders: service list, session notices, replies -------------


@pytest.fixture(scope="module")
def participant() -> Iterator[tuple[Participant, Session]]:
    """A participant with an open `echo` session (its cipher is PARTICIPANT_KEY's).

    Its test takes three batches per example: about 10,000 payloads for each of the
    three decoders (service list, session notice, reply envelope)."""
    p = Participant.create(UNREACHABLE, client_id="pat", data_qos=1)
    grant = SessionGrant(
        service=ServiceDescription(**SPEC.model_dump(), public_key=PROVIDER_KEY.public),
        session="s1",
        input_topic="ldm/p/pat/up/data/echo",
        reply_topic="ldm/p/pat/down/data/echo",
        rotation_period=120.0,
        grace=5.0,
        idle_timeout=30.0,
        max_age=2.0,
        data_qos=1,
    )
    session = Session(p, grant)
    session._keys.pair = PARTICIPANT_KEY
    session._keys.cipher = PARTICIPANT_KEY.cipher(PROVIDER_KEY.public, initiator=True)
    p._sessions["echo"] = session
    yield p, session
    p.transport.stop()


SERVICE = {"name": "echo", "public_key": PROVIDER_KEY.public, "version": "1"}
REPLY_CIPHER = PROVIDER_KEY.cipher(PARTICIPANT_KEY.public, initiator=False)


def sealed_reply(plaintext: bytes, c: str, age: float) -> dict[str, Any]:
    t = now_minus(age)
    return {"c": c, "t": t, "d": REPLY_CIPHER.seal(plaintext, aad(c, t))}


participant_messages = st.one_of(
    st.tuples(
        st.just("ldm/services"),
        encoded(
            mutations({"t": 1.0, "services": [SERVICE]})
            | mutations({"t": 1.0, "services": [{**SERVICE, "public_key": "B" * 43 + "="}]})
        ),
    ),
    st.tuples(
        st.just("ldm/p/pat/down/session"),
        encoded(
            mutated(
                st.builds(
                    lambda kind: {
                        "kind": kind,
                        "service": "echo",
                        "c": "r1",
                        "reason": "invalid",
                        "error": "e",
                    },
                    st.sampled_from(["grant", "refused", "rotate", "nosession", "rejected", "x"]),
                ),
                ["kind", "service", "c", "reason", "error", "grant"],
            )
        ),
    ),
    st.tuples(
        st.sampled_from(["ldm/p/pat/down/data/echo", "ldm/p/pat/down/data/other"]),
        encoded(
            mutated(
                st.builds(sealed_reply, st.sampled_from(PLAINTEXTS), st.just("r1"), AGES),
                ["c", "t", "d"],
            )
        ),
    ),
)


@FUZZ
@given(batch=st.lists(participant_messages, min_size=BATCH, max_size=BATCH))
def test_participant_decoders(
    participant: tuple[Participant, Session], batch: list[tuple[str, bytes]]
) -> None:
    p, session = participant
    with session._lock:
        session._pending.clear()
    future = session.submit({"q": 1})  # one request waits for a reply, under id "r1"
    with session._lock:
        session._pending["r1"] = session._pending.pop(next(iter(session._pending)))
    for topic, payload in batch:
        p.handle(Message(topic, payload, 1, False, "pat"))  # never raises
    assert all(isinstance(s, ServiceDescription) for s in p.services(timeout=0))
    if future.done() and future.exception() is not None:
        assert isinstance(future.exception(), LdmError)
    elif future.done():
        assert isinstance(future.result(), dict)


# --- the LaaS worker's measurement decoder -----------------------------------------


@pytest.fixture(scope="module")
def worker(hamburg_map: HdMap) -> LaasService:
    return LaasService(hamburg_map)


def fix(t_ms: int, **changes: Any) -> dict[str, Any]:
    base = {
        "timestamp": t_ms,
        "latitude": 53.55876,
        "longitude": 9.97610,
        "altitude": 10.0,
        "heading": 30.8,
        "speed": 5.4,
    }
    return {**base, **changes}


@FUZZ
@given(
    batch=batches(
        st.tuples(
            mutations(fix(0))
            | mutations(fix(int(time.time() * 1000)))
            | st.dictionaries(st.text(max_size=10), odd_values, max_size=6)
            | st.builds(
                lambda dt, lat, lon: fix(int(time.time() * 1000) + dt, latitude=lat, longitude=lon),
                st.integers(-(10**9), 10**9),
                st.floats(-100, 100) | st.floats(53.5, 53.6),
                st.floats(-200, 200) | st.floats(9.9, 10.0),
            ),
            st.sampled_from(["m1", "m2"]),
        )
    )
)
def test_worker_measurement_decoder(
    worker: LaasService, batch: list[tuple[dict[str, Any], str]]
) -> None:
    # alice reports now, so her track is live (the worker expires idle tracks)
    assert "error" not in worker.handle(
        Request("alice", "c", fix(int(time.time() * 1000)), 0.0, True)
    )
    alice = worker.engine._tracks["alice"]
    t_alice, x_alice = alice.t, alice.position.copy()
    s = worker.stats
    for payload, pseudonym in batch:
        outcomes = s.answered + s.invalid + s.refused + s.outside + s.clock + s.failed
        reply = worker.handle(Request(pseudonym, "c", payload, 0.0, False))
        assert s.answered + s.invalid + s.refused + s.outside + s.clock + s.failed == outcomes + 1
        if "error" in reply:
            assert set(reply["error"]) == {"kind", "message", "fields"}
        json.dumps(reply, allow_nan=False)  # every reply can go on the wire
    assert s.failed == 0
    assert worker.engine._tracks["alice"] is alice
    assert alice.t == t_alice and (alice.position == x_alice).all()


# --- files: the trace reader and the map loader ------------------------------------


def measurement_of(text: str) -> tuple[str, GpsMeasurement] | None:
    """What a trace line means on its own: (user, measurement), or None if it is bad."""
    try:
        data = json.loads(text)
    except ValueError:
        return None
    if not isinstance(data, dict):
        return None
    user = data.pop("user", None)
    if not isinstance(user, str) or not user:
        return None
    try:
        return user, GpsMeasurement.model_validate(data)
    except ValidationError:
        return None


@SMALL
@given(
    lines=st.lists(
        encoded(mutations({"user": "car", **fix(1)})).map(lambda b: b.decode("utf-8", "replace"))
        | st.just(json.dumps({"user": "bike", **fix(2)}))  # a good line, every so often
        | st.sampled_from(["", "  ", "\t"]),  # blank lines are skipped, not errors
        max_size=5,
    )
)
def test_trace_reader_reports_every_bad_line(lines: list[str]) -> None:
    results = list(read_trace(lines, source="t.jsonl"))
    expected = [(n, measurement_of(text)) for n, text in enumerate(lines, 1) if text.strip()]
    assert len(results) == len(expected)  # one result per line that is not blank
    for (number, meant), result in zip(expected, results, strict=True):
        if meant is None:
            assert isinstance(result, TraceError), (number, lines[number - 1])
            assert str(result).startswith(f"t.jsonl:{number}: "), str(result)
        else:
            assert isinstance(result, TraceLine), (number, lines[number - 1], result)
            assert (result.line, result.user, result.measurement) == (number, *meant)


@SMALL
@given(doc=odd_values | mutations({"type": "FeatureCollection", "features": []}))
def test_map_loader_raises_only_map_errors(doc: Any) -> None:
    with contextlib.suppress(MapError):
        read_geojson(doc)
