"""Valve pulse instants of many trajectories in one compiled call (numba).

:func:`pulse_instants_many` is :func:`icefab.flow.pulse_instants` (thesis eqs. 6.5-6.6)
for every trajectory of a layer at once, with the same floating-point operations in the
same order, so its instants are bit-identical to the per-path function's (tested): the
cumulative pulse count by the trapezoidal rule as ``scipy.integrate.cumulative_trapezoid``
forms it (``dt * (nu[k + 1] + nu[k]) / 2`` summed in sequence, as ``numpy.cumsum`` does),
pulse j where the count reaches ``j + 1/2``, by linear interpolation of t. Issue 17: the
per-path Python work made ``icefab valves`` take two minutes on a 1 M-facet part.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def _cumulative(t: np.ndarray, nu: np.ndarray, a: int, b: int, cum: np.ndarray) -> float:
    """cum[a:b] = the cumulative trapezoidal integral of nu over t on rows a..b-1 (from 0);
    returns its last value."""
    acc = 0.0
    cum[a] = 0.0
    for k in range(a, b - 1):
        acc += (t[k + 1] - t[k]) * (nu[k + 1] + nu[k]) / 2.0
        cum[k + 1] = acc
    return acc


@njit(cache=True, error_model="numpy")
def _count(total: float) -> int:
    """Pulses of a path whose cumulative count ends at ``total``: the targets j + 1/2 for
    j < floor(total + 1/2) that do not exceed ``total``."""
    p = int(np.floor(total + 0.5))
    n = 0
    for j in range(max(p, 0)):
        if j + 0.5 <= total:
            n += 1
    return n


@njit(cache=True, error_model="numpy")
def pulse_instants_many(t: np.ndarray, nu: np.ndarray, starts: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Pulse instants (s, from each trajectory's start) of trajectories whose samples are
    rows ``starts[i]:starts[i+1]`` of ``t`` (n,) s and ``nu`` (n,) Hz.

    Returns (instants (P,) float64, offsets (m + 1,) int64): trajectory i's are
    ``instants[offsets[i]:offsets[i+1]]``. A trajectory of fewer than two samples has none.
    """
    m = len(starts) - 1
    cum = np.empty(len(t))
    counts = np.zeros(m + 1, np.int64)
    for i in range(m):
        a, b = starts[i], starts[i + 1]
        if b - a < 2:
            continue
        counts[i + 1] = _count(_cumulative(t, nu, a, b, cum))
    offsets = np.cumsum(counts)
    out = np.empty(offsets[m])
    for i in range(m):
        a, b = starts[i], starts[i + 1]
        o = offsets[i]
        n = offsets[i + 1] - o
        if n == 0:
            continue
        k = a + 1  # searchsorted(cum[a:b], target, "left"), clipped to [1, len - 1]
        for j in range(n):
            target = j + 0.5
            while k < b - 1 and cum[k] < target:
                k += 1
            c0, c1 = cum[k - 1], cum[k]
            frac = (target - c0) / (c1 - c0 if c1 > c0 else 1.0)
            out[o + j] = t[k - 1] + frac * (t[k] - t[k - 1])
    return out, offsets


@njit(cache=True, error_model="numpy")
def pwm_widths_us(want_us: np.ndarray, lo_us: float, hi_us: float) -> np.ndarray:
    """PWM pulse widths, whole microseconds, period by period, with what each period misses
    carried into the next (:func:`icefab.flow._pwm_widths_us`, which states the rule): a
    period asking (with the carry) under ``lo_us / 2`` gets none, under ``lo_us`` the
    shortest pulse, over ``hi_us`` the longest, its own excess over ``hi_us`` not carried."""
    out = np.zeros(len(want_us))
    carry = 0.0
    for k in range(len(want_us)):
        w = want_us[k]
        want = w + carry
        if want < 0.5 * lo_us:
            got = 0.0
        elif want < lo_us:
            got = lo_us
        else:
            got = min(np.floor(want + 0.5), hi_us)
        out[k] = got
        carry = want - got - max(w - hi_us, 0.0)
    return out


@njit(cache=True, error_model="numpy")
def sigma_delta_power(want_s: np.ndarray, playable: np.ndarray, shortest_s: float,
                      s_min: int, s_max: int) -> np.ndarray:
    """(n,) int64 cutter power S per G-code move, from the power ``want_s`` (n,) float64 in
    S units (255 x duty) asked per move, with what each move misses carried into the next
    (:func:`icefab.export.step_power`, which states the rule): a move that may not open
    (``playable`` False) or asks for nothing gets S0 and passes on what it asked; otherwise
    a move asking (with the carry) under ``shortest_s / 2`` gets S0, under ``s_min``
    S``s_min``, else the nearest integer up to ``s_max``."""
    out = np.zeros(len(want_s), np.int64)
    carry = 0.0
    for k in range(len(want_s)):
        x = want_s[k]
        if not playable[k] or x <= 1e-6:   # float dust from spreading a pulse opens nothing
            carry += x
            continue
        want = x + carry
        if want < 0.5 * shortest_s - 1e-6:   # 1e-6: one shortest pulse asked is not under
            got = 0
        elif want < s_min:
            got = s_min
        else:
            got = int(min(np.floor(want + 0.5), s_max))
        out[k] = got
        carry = want - got
    return out
