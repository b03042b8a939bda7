"""The engine's compiled arithmetic: numba's `njit` behind one typed decorator.

The engine's per-fix arithmetic works on arrays of a handful of elements (a 4 x 4
covariance, a user's few lanes over some dozens of u-cells), where each numpy call costs
more than the arithmetic it does. The functions decorated here are compiled to machine
code on first use and kept in numba's cache: `__pycache__` beside their module, or
`NUMBA_CACHE_DIR` when set (the container image sets it). A process after the first
loads them in milliseconds. Where no cache can be written (a read-only install and no
writable home), they are compiled anew in every process, and a warning says how to give
them a cache. Each stays plain Python that numba also runs as it is: `LAAS_NO_JIT=1` runs
them uncompiled (numba's own `NUMBA_DISABLE_JIT`), slowly, for a debugger or a coverage
run.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba

__all__ = ["COMPILED", "jit"]

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable[..., object])

_DISABLED = os.environ.get("LAAS_NO_JIT", "") not in ("", "0")

COMPILED: list[Any] = []
"""Every function `jit` compiled (numba's dispatchers; `laas.engine.warm` builds them all)."""


def jit(fn: F) -> F:
    """`fn` compiled in nopython mode, cached on disk, dividing by zero as numpy does
    (inf or NaN, no exception); `fn` itself with LAAS_NO_JIT=1."""
    if _DISABLED:
        return fn
    try:
        compiled = numba.njit(cache=True, error_model="numpy")(fn)
    except RuntimeError as exc:  # numba: "cannot cache function ...: no locator available"
        log.warning(
            "%s is compiled anew in every process (%s): set NUMBA_CACHE_DIR to a writable "
            "folder to keep it",
            fn.__qualname__,
            exc,
        )
        compiled = numba.njit(error_model="numpy")(fn)
    COMPILED.append(compiled)
    return cast(F, compiled)
