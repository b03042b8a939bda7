"""The engine's compiled functions (`laas.engine.jit`) give what their own Python gives:
each is run compiled and as the plain Python it was written as (numba keeps it as
`py_func`, what `LAAS_NO_JIT=1` runs), on the same inputs."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from laas.engine import common_error, stacked, tracking


def _both(kernel: Callable[..., Any], *args: Any) -> tuple[Any, Any]:
    """(compiled result, plain Python result), each on its own copy of the arguments
    (some kernels work in place)."""
    plain = getattr(kernel, "py_func", None)
    assert plain is not None, f"{kernel.__name__} is not compiled (LAAS_NO_JIT set?)"
    copies = [[a.copy() if isinstance(a, np.ndarray) else a for a in args] for _ in range(2)]
    return (kernel(*copies[0]), copies[0]), (plain(*copies[1]), copies[1])


def _close(a: Any, b: Any) -> None:
    if isinstance(a, tuple | list):
        assert len(a) == len(b)
        for x, y in zip(a, b, strict=True):
            _close(x, y)
    elif isinstance(a, np.ndarray | float | int):
        np.testing.assert_allclose(
            np.asarray(a, float), np.asarray(b, float), rtol=1e-12, atol=1e-12
        )
    else:
        assert a == b


def test_the_kalman_step() -> None:
    rng = np.random.default_rng(1)
    n = 5
    x = rng.normal(0.0, 10.0, (n, 4))
    p = np.array([np.diag(rng.uniform(0.5, 3.0, 4)) for _ in range(n)])
    rows = np.column_stack(
        [
            np.full(n, 10.0),  # t
            rng.uniform(0.1, 2.0, n),  # dt
            rng.normal(0.0, 10.0, n),  # e
            rng.normal(0.0, 10.0, n),  # n
            rng.uniform(0.0, 15.0, n),  # speed
            rng.uniform(0.0, 2 * math.pi, n),  # heading
            rng.uniform(0.5, 4.0, n),  # sigma_pos^2
            [math.nan, 8.5, 7.0, math.nan, 9.9],  # when a disagreement began
        ]
    )
    compiled, plain = _both(tracking._kalman, x, p, rows, 0.49, 0.0525, 0.1, 0.05)
    _close(compiled[1], plain[1])  # x, P and the rows, changed in place alike


def test_the_multipath_weight() -> None:
    compiled, plain = _both(tracking.multipath_weight, 2.0, 0.3, 1.5, 2.5, -1.0, 0.05)
    _close(compiled[0], plain[0])
    assert 0.0 < compiled[0] < 1.0


@pytest.fixture
def area() -> common_error.CommonError:
    """An area with some evidence in it and a shrunk window."""
    a = common_error.CommonError(np.zeros(2), 3.0, 0.05, 0.3)
    rng = np.random.default_rng(2)
    a.update(np.array([0.6, 0.8]), rng.normal(0.0, 2.0, a.u.size))
    a.update(np.array([1.0, 0.0]), -0.5 * ((a.u.values - 0.4) / 0.8) ** 2)
    return a


def test_the_window_arithmetic(area: common_error.CommonError) -> None:
    i0, i1, j0, j1 = area._win
    assert (i0, j0) != (0, 0)  # a window inside the grid
    ae, an = area._axis[i0:i1], area._axis[j0:j1]
    w = np.exp(area._log[i0:i1, j0:j1])
    compiled, plain = _both(common_error._window_moments, w, ae, an)
    _close(compiled, plain)
    compiled, plain = _both(common_error._held, area._log, i0, i1, j0, j1, -40.0)
    _close(compiled[0], plain[0])
    u = area.u
    compiled, plain = _both(common_error._u_cells, ae, an, 0.6, 0.8, u.lo, u.step, u.size)
    _close(compiled[0], plain[0])
    cells = compiled[0][0]
    compiled, plain = _both(common_error._u_moments, area._w, ae, an, cells, u.size)
    _close(compiled[0], plain[0])
    prior = area._log.copy() * 0.5
    for whole in (False, True):  # the window shifted to its maximum, or (not whole) left
        compiled, plain = _both(
            common_error._fade_window, area._log, prior, i0, i1, j0, j1, 0.97, 40.0, whole
        )
        _close(compiled, plain)


def test_the_stacked_kernels() -> None:
    rng = np.random.default_rng(3)
    n, h, lanes, cells = 2, 30, 3, 80
    alpha = rng.random((n, h, lanes))
    args = (
        alpha,
        rng.random((n, lanes, lanes)),
        rng.random((n, lanes)),
        rng.normal(0.0, 3.0, n),
        np.linspace(-4.0, 4.0, cells),
        np.array([10, 70]),
        np.sort(rng.uniform(-5.0, 5.0, (n, lanes)), axis=1),
        np.array([1.5, 2.5]),
        np.array([0.3, 1.0]),
        1e-3,
        0.05,
        3.0,
    )
    compiled, plain = _both(stacked._evidence_cells, *args)
    _close(compiled[0], plain[0])
    moments = rng.random((2, cells, 6))
    compiled, plain = _both(
        stacked.lanes_and_conditionals, moments, np.array([1, 0]), np.array([10, 70]), alpha, 0.01
    )
    _close(compiled[0], plain[0])


@pytest.mark.parametrize("mode", ["default", "paper"])
def test_the_warm_up_builds_every_compiled_function(mode: str) -> None:
    """`warm_up` leaves nothing to compile on a worker's first fix, whatever its mode
    (in a fresh interpreter: in this one other tests have built them already)."""
    import subprocess
    import sys

    script = (
        "from laas.config import EngineConfig\n"
        "from laas.engine.jit import COMPILED\n"
        "from laas.engine.warm import warm_up\n"
        f"warm_up(config=EngineConfig(mode={mode!r}))\n"
        "print(len(COMPILED), [f.__name__ for f in COMPILED if not f.signatures])\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True
    )
    count, missing = out.stdout.split(" ", 1)
    assert int(count) >= 10
    assert missing.strip() == "[]", out.stderr


def test_the_prediction() -> None:
    from laas.engine.transition import _prediction

    rng = np.random.default_rng(4)
    n, lanes = 4, 3
    compiled, plain = _both(
        _prediction,
        np.array([1.0, -1.0, 0.0]),
        np.array([math.inf, 5.0, 12.0]),
        np.array([1.0, 0.8, 1.5]),
        np.array([1.0, 0.05, 0.02]),
        np.array([8.0, -8.0, 0.5, 3.0]),  # along: forward, backward, standing, forward
        rng.uniform(0.0, 15.0, n),
        rng.normal(0.0, 0.5, n),
        rng.uniform(0.1, 2.0, n),
        rng.uniform(0.1, 1.0, n),
        np.sort(rng.uniform(-5.0, 5.0, (n, lanes)), axis=1),
        0.01,
        0.45,
        0.05,
    )
    _close(compiled[0], plain[0])
    fit, transition = compiled[0]
    np.testing.assert_allclose(transition.sum(axis=2), 1.0)  # each row a distribution
    assert fit[1, 0] < fit[0, 0]  # a forward lane fits a user moving backward less


def test_the_carry_of_a_lane_table(area: common_error.CommonError) -> None:
    from laas.engine.cooperative import _carry

    old, new = np.array([0.6, 0.8]), np.array([0.8, 0.6])
    w, idx_old = area.weights_and_cells(old)
    _, idx_new = area.weights_and_cells(new)
    lo, hi = area.taken(new)
    alpha = np.random.default_rng(5).random((area.u.size, 3))
    compiled, plain = _both(_carry, alpha, w, idx_old, idx_new, lo, hi)
    _close(compiled[0], plain[0])
    num, den = compiled[0]
    np.testing.assert_allclose(den.sum(), 1.0)  # every window cell's weight, once
    np.testing.assert_allclose(num.sum(), (alpha[idx_old] * w[..., None]).sum())


def test_a_function_whose_cache_cannot_be_written_is_compiled_all_the_same(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """Numba finds no place for the cache of a function without a source file (as of a
    read-only install without a writable home): it is compiled uncached, with a warning."""
    from laas.engine import jit

    space: dict[str, Any] = {}
    exec(compile("def twice(x):\n    return 2.0 * x\n", "<no file>", "exec"), space)
    with caplog.at_level("WARNING", logger="laas.engine.jit"):
        twice = jit.jit(space["twice"])
    assert twice(2.5) == 5.0
    assert twice.signatures  # compiled, not the plain function
    assert "NUMBA_CACHE_DIR" in caplog.text
    jit.COMPILED.remove(twice)  # not one of the engine's
