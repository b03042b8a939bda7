"""The engine's compiled arithmetic: numba's `njit` behind one typed decorator.

The engine's per-fix arithmetic works on arrays of a handful of elements (a 4 x 4
covariance, a user's few lanes over some dozens of u-cells), where each numpy call costs
more than the arithmetic it does. The functions decorated here are compiled to machine
code on first use and kept in `__pycache__` beside their module (numba's cache), so a
process after the first loads them in milliseconds. Each stays plain Python that numba
also runs as it is: `LAAS_NO_JIT=1` runs them uncompiled (numba's own
`NUMBA_DISABLE_JIT`), slowly, for a debugger or a coverage run.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba

__all__ = ["COMPILED", "jit"]

F = TypeVar("F", bound=Callable[..., object])

_DISABLED = os.environ.get("LAAS_NO_JIT", "") not in ("", "0")

COMPILED: list[Any] = []
"""Every function `jit` compiled (numba's dispatchers; `laas.engine.warm` builds them all)."""


def jit(fn: F) -> F:
    """`fn` compiled in nopython mode, cached on disk, dividing by zero as numpy does
    (inf or NaN, no exception); `fn` itself with LAAS_NO_JIT=1."""
    if _DISABLED:
        return fn
    compiled = numba.njit(cache=True, error_model="numpy")(fn)
    COMPILED.append(compiled)
    return cast(F, compiled)
