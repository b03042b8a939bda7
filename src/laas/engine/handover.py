"""What one worker hands another: a user's state at a region's border, and the common
error of the areas two regions share. Pure data (no MQTT, no keys): the worker seals
and moves it (`laas.worker.service`).

A road user who crosses into the next worker's region takes its history along, so the
next worker goes on as one worker would have:

    UserState   its Kalman track (x = [e, n, v_e, v_n], P, the last fix and its dt) and,
                in default mode, its lane table alpha(u, l) = P(lane l | u = n . b) for
                its road element and normal n. The table is conditioned on u, not on any
                worker's posterior of b, so it holds in the next worker's area as well;
                only its u-cells that the old area's posterior holds (`CommonError.span`)
                travel, the others take the table's marginal lane probabilities.

    AreaState   one area's common error as its worker alone estimated it (its own
                users' evidence, `CommonError.shared`): the neighbour multiplies it into
                its own area at that place (`CommonError.take_shared`), so both sides of a
                border pool the evidence of every user near it, as one worker does.

`user_to_bytes` / `user_from_bytes` (and the same for areas) give a compact form (JSON,
arrays as base64 float32, zlib-compressed) and refuse a malformed one with
`HandoverError`.
"""

from __future__ import annotations

import base64
import json
import math
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from laas.errors import LaasError

__all__ = [
    "AreaState",
    "HandoverError",
    "LaneState",
    "UserState",
    "areas_from_bytes",
    "areas_to_bytes",
    "user_from_bytes",
    "user_to_bytes",
]

_VERSION = 1
_MAX_BYTES = 4 << 20  # a hand-over unpacks to this at most


class HandoverError(LaasError):
    """A hand-over that cannot be read; the message names the part."""


@dataclass(frozen=True)
class LaneState:
    """A user's lane table: alpha's u-cells [lo, lo + rows) of a u-grid of `cells`."""

    segment: str
    normal: np.ndarray  # (2,)
    cells: int
    lo: int
    alpha: np.ndarray  # (rows, L)


@dataclass(frozen=True)
class UserState:
    """A user's Kalman track and lane table (`Track.state`, `LaneState`)."""

    x: np.ndarray  # (4,) e, n, v_e, v_n
    p: np.ndarray  # (4, 4)
    fix: tuple[float, float, float, float, float, float | None]  # t, e, n, speed, heading, acc
    dt: float
    lanes: LaneState | None


@dataclass(frozen=True)
class AreaState:
    """One area's own common-error estimate (`CommonError.shared`): its centre (UTM, m),
    the size of its u-grid (`cells`: the same prior gives the same grids), log p over
    the window (i0, i1, j0, j1) of its grid of b, and the time (s) its evidence is faded
    to (None: not faded, or unknown)."""

    centre: tuple[float, float]
    cells: int
    window: tuple[int, int, int, int]
    log: np.ndarray  # (i1 - i0, j1 - j0)
    t: float | None = None


def _array(a: np.ndarray) -> dict[str, Any]:
    a32 = np.ascontiguousarray(a, dtype=np.float32)
    return {"shape": list(a32.shape), "data": base64.b64encode(a32.tobytes()).decode()}


def _unarray(d: Any, what: str) -> np.ndarray:
    try:
        shape = tuple(int(n) for n in d["shape"])
        raw = base64.b64decode(d["data"], validate=True)
        out = np.frombuffer(raw, dtype=np.float32).reshape(shape).astype(np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise HandoverError(f"hand-over: {what} is not an array ({exc})") from None
    if not np.all(np.isfinite(out) | (out == -np.inf)):
        raise HandoverError(f"hand-over: {what} holds NaN or +inf")
    return out


def user_to_bytes(state: UserState) -> bytes:
    """The compact form of a user's state."""
    body: dict[str, Any] = {
        "v": _VERSION,
        "x": _array(state.x),
        "p": _array(state.p),
        "fix": list(state.fix),
        "dt": state.dt,
    }
    if state.lanes is not None:
        ln = state.lanes
        body["lanes"] = {
            "segment": ln.segment,
            "normal": [float(ln.normal[0]), float(ln.normal[1])],
            "cells": ln.cells,
            "lo": ln.lo,
            "alpha": _array(ln.alpha),
        }
    return _pack(body)


def user_from_bytes(data: bytes) -> UserState:
    """A user's state from `user_to_bytes`; `HandoverError` names what is wrong."""
    body = _body(data)
    try:
        x, p = _unarray(body["x"], "x"), _unarray(body["p"], "P")
        t, e, n, speed, heading, acc = body["fix"]
        fix = (float(t), float(e), float(n), float(speed), float(heading))
        accuracy = None if acc is None else float(acc)
        dt = float(body["dt"])
        lanes = None
        if body.get("lanes") is not None:
            ln = body["lanes"]
            lanes = LaneState(
                str(ln["segment"]),
                np.array([float(ln["normal"][0]), float(ln["normal"][1])]),
                int(ln["cells"]),
                int(ln["lo"]),
                _unarray(ln["alpha"], "alpha"),
            )
    except (KeyError, TypeError, ValueError) as exc:
        raise HandoverError(f"hand-over: a user's state is malformed ({exc!r})") from None
    if x.shape != (4,) or p.shape != (4, 4) or not np.isfinite(x).all():
        raise HandoverError("hand-over: the track needs x of 4 and P of 4 x 4 finite values")
    if lanes is not None and (
        lanes.alpha.ndim != 2 or not 0 <= lanes.lo <= lanes.lo + len(lanes.alpha) <= lanes.cells
    ):
        raise HandoverError("hand-over: the lane table does not fit its u-grid")
    return UserState(x, p, (*fix, accuracy), dt, lanes)


def areas_to_bytes(states: list[AreaState]) -> bytes:
    """The compact form of a worker's shared areas."""
    return _pack(
        {
            "v": _VERSION,
            "areas": [
                {
                    "centre": list(a.centre),
                    "cells": a.cells,
                    "window": list(a.window),
                    "log": _array(a.log),
                    "t": a.t,
                }
                for a in states
            ],
        }
    )


def areas_from_bytes(data: bytes) -> list[AreaState]:
    """Shared areas from `areas_to_bytes`; `HandoverError` names what is wrong."""
    body = _body(data)
    out = []
    try:
        for a in body["areas"]:
            i0, i1, j0, j1 = (int(k) for k in a["window"])
            log = _unarray(a["log"], "an area's log p")
            if log.shape != (i1 - i0, j1 - j0):
                raise HandoverError("hand-over: an area's log p does not fit its window")
            t = a.get("t")
            if t is not None and not math.isfinite(float(t)):
                raise HandoverError("hand-over: an area's time is not a finite number")
            out.append(
                AreaState(
                    (float(a["centre"][0]), float(a["centre"][1])),
                    int(a["cells"]),
                    (i0, i1, j0, j1),
                    log,
                    None if t is None else float(t),
                )
            )
    except (KeyError, TypeError, ValueError) as exc:
        raise HandoverError(f"hand-over: shared areas are malformed ({exc!r})") from None
    return out


def _pack(body: dict[str, Any]) -> bytes:
    return zlib.compress(json.dumps(body, separators=(",", ":")).encode())


def _body(data: bytes) -> dict[str, Any]:
    try:
        unpacker = zlib.decompressobj()
        text = unpacker.decompress(data, _MAX_BYTES)
        if unpacker.unconsumed_tail:
            raise HandoverError(f"hand-over: unpacks to more than {_MAX_BYTES} bytes")
        body = json.loads(text)
    except (zlib.error, ValueError):
        raise HandoverError("hand-over: not compressed JSON") from None
    if not isinstance(body, dict) or body.get("v") != _VERSION:
        raise HandoverError(f"hand-over: give a version {_VERSION} object")
    return body
