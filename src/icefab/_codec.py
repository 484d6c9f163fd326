"""Compiled encoding and decoding of a trajectory file's sample counts (numba).

:func:`encode_plane_column` makes one column of :func:`icefab.resultfiles.encode_counts`
and :func:`decode_plane_column` inverts it, each in one pass over the values, with the
same integer arithmetic (wrapping int64 sums) and the same final multiplication as the
numpy forms they replace, so the values are identical; reading the bunny's trajectories
spent 6.5 s in the numpy form's transposes and temporaries (issue 17).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def decode_plane_column(planes: np.ndarray, resolution: float, out: np.ndarray) -> None:
    """out[i] = the i-th value of one column: ``planes`` (k, n) uint8, k <= 8, are the
    low byte planes (little-endian) of the zig-zag mapped second differences of the counts
    (the planes above k are zeros)."""
    k, n = planes.shape
    acc1 = np.int64(0)
    acc2 = np.int64(0)
    for i in range(n):
        zz = np.uint64(0)
        for b in range(k):
            zz |= np.uint64(planes[b, i]) << np.uint64(8 * b)
        d = np.int64(zz >> np.uint64(1)) ^ -np.int64(zz & np.uint64(1))
        acc1 += d
        acc2 += acc1
        out[i] = acc2 * resolution


@njit(cache=True, error_model="numpy")
def encode_plane_column(values: np.ndarray, resolution: float, out: np.ndarray) -> int:
    """out[:, i] = the 8 little-endian bytes of the zig-zag mapped second difference of
    the counts ``rint(values / resolution)`` (the first ones against zeros); returns how
    many of the planes hold a non-zero byte (at least 1): the planes above are zeros that
    the file leaves out. The numpy form it replaces computed the same integers. ``out``
    (k, n) with k < 8 gets the low k planes only; with k = 0 the call only counts them (a
    writer that holds the whole column need not hold eight bytes per value)."""
    n = len(values)
    prev_q = np.int64(0)
    prev_d1 = np.int64(0)
    used = np.uint64(0)
    for i in range(n):
        q = np.int64(np.rint(values[i] / resolution))
        d1 = q - prev_q
        d = d1 - prev_d1
        prev_q, prev_d1 = q, d1
        zz = np.uint64((d << 1) ^ (d >> 63))
        used |= zz
        for b in range(min(8, out.shape[0])):
            out[b, i] = np.uint8((zz >> np.uint64(8 * b)) & np.uint64(0xFF))
    k = 1
    while k < 8 and (used >> np.uint64(8 * k)) != np.uint64(0):
        k += 1
    return k
