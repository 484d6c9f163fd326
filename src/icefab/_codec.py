"""Compiled decoding of a trajectory file's sample counts (numba).

:func:`decode_plane_column` inverts one column of
:func:`icefab.resultfiles.encode_counts` in one pass over its bytes, with the same integer
arithmetic (wrapping int64 sums) and the same final multiplication as the numpy form it
replaces, so the values are identical; reading the bunny's trajectories spent 6.5 s in
the numpy form's transposes and temporaries (issue 17).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy")
def decode_plane_column(planes: np.ndarray, resolution: float, out: np.ndarray) -> None:
    """out[i] = the i-th value of one column: ``planes`` (8, n) uint8 are the byte planes
    (little-endian) of the zig-zag mapped second differences of the counts."""
    n = planes.shape[1]
    acc1 = np.int64(0)
    acc2 = np.int64(0)
    for i in range(n):
        zz = np.uint64(0)
        for b in range(8):
            zz |= np.uint64(planes[b, i]) << np.uint64(8 * b)
        d = np.int64(zz >> np.uint64(1)) ^ -np.int64(zz & np.uint64(1))
        acc1 += d
        acc2 += acc1
        out[i] = acc2 * resolution
