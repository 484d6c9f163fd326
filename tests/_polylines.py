"""Test polylines shared by the motion tests."""

from __future__ import annotations

import numpy as np


def zigzag(turn_deg: float, side_mm: float, n: int = 10) -> np.ndarray:
    """A polyline turning by ``turn_deg`` left and right at every vertex, sides in mm."""
    a = np.radians(turn_deg) / 2.0
    ang = np.where(np.arange(n) % 2 == 0, a, -a)
    steps = side_mm * np.c_[np.cos(ang), np.sin(ang)]
    return np.vstack([[300.0, -60.0], [300.0, -60.0] + np.cumsum(steps, axis=0)])
