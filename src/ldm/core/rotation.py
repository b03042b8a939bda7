"""The core's side of rotation (`ldm.wire.rotation`): when it tells a session to change key."""

from __future__ import annotations

import math

from ldm.wire.rotation import Strategy

__all__ = ["next_rotation"]


def next_rotation(strategy: Strategy, period: float, now: float) -> float:
    """When the core next tells a session to change key, after a change (or a notice)
    at `now`: ``period`` later, or with ``epoch`` the next multiple of ``period`` on
    the Unix clock (strictly after `now`)."""
    if strategy == "epoch":
        return (math.floor(now / period) + 1.0) * period
    return now + period
