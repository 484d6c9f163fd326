"""The first run's numba compiling is said plainly on stderr, and nothing when cached."""
from __future__ import annotations

import io

import numba
import numpy as np

from icefab.cli.compiling import FIRST_LINE, compile_notice


def test_compiling_is_announced_once_and_summarised():
    @numba.njit  # a fresh function: compiled on its first call, never cached
    def twice(a):
        return a * 2

    @numba.njit
    def thrice(a):
        return a * 3

    err = io.StringIO()
    with compile_notice(err, interval_s=1e9) as notice:
        twice(np.arange(3))
        thrice(np.arange(3.0))
        twice(np.arange(3))  # already compiled: not counted
    lines = err.getvalue().splitlines()
    assert lines[0] == FIRST_LINE
    assert notice.kernels == 2
    assert lines[-1].startswith("compiled 2 numba kernels in ") and "cached" in lines[-1]
    assert len(lines) == 2


def test_nothing_is_said_when_nothing_compiles():
    @numba.njit
    def once(a):
        return a + 1

    once(1)
    err = io.StringIO()
    with compile_notice(err) as notice:
        assert once(2) == 3
    assert err.getvalue() == "" and notice.kernels == 0
