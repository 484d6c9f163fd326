"""The laser of the virtual cell (thesis 5.2.1): sample positions along measurement paths or
trajectories, noise and the latency a build leaves uncompensated, readings of a height map.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy import ndimage

from icefab.core import HeightMap, arc_lengths, closed_polyline

from icefab.sim.deposition import _at

log = logging.getLogger(__name__)


def uncompensated_latency_s(job) -> float:
    """What of the laser's latency a build leaves, s: the sensor's own
    (``simulation.laser_latency_s``, the virtual cell's laser) less what the build takes
    off (``cell.laser_latency_s``, the calibrated value: ``icefab.build`` reads the
    trajectory that much earlier). The simulator reads its laser with this, so that it
    measures as a build on the virtual cell does; negative when the calibration overstates
    the latency (the samples then read ahead of their tags)."""
    return float(job.simulation.laser_latency_s - job.cell.laser_latency_s)


def sample_surface(surface: HeightMap, xy: np.ndarray) -> np.ndarray:
    """Bilinear height of ``surface`` at (n, 2) points (mm); edge values beyond the map."""
    g = surface.spacing
    coords = np.stack([(xy[:, 1] - surface.origin[1]) / g, (xy[:, 0] - surface.origin[0]) / g])
    return ndimage.map_coordinates(surface.z, coords, order=1, mode="nearest")


def _resample(points: np.ndarray, closed: bool, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` mm along a polyline: (k, 2) points and (k,) arc length."""
    poly = closed_polyline(points, closed)
    if len(poly) < 2:
        return poly.copy(), np.zeros(len(poly))
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = arc_lengths(seg)
    total = s[-1]
    if total <= 0:
        return poly[:1].copy(), np.zeros(1)
    k = max(1, int(math.ceil(total / spacing - 1e-9)))
    t = np.linspace(0.0, total, k + 1)
    return _at(poly, s, t), t


def _refine(points: np.ndarray, closed: bool, max_step: float) -> np.ndarray:
    """The polyline of a path (closed: first point repeated at the end) with every edge
    longer than ``max_step`` split into equal parts, repeated points dropped."""
    poly = closed_polyline(points, closed)
    if len(poly) < 2:
        return poly
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    poly = poly[keep]
    seg = seg[keep[1:]]
    if len(poly) < 2:
        return poly
    parts = np.maximum(1, np.ceil(seg / max_step - 1e-9).astype(np.int64))
    start = np.repeat(poly[:-1], parts, axis=0)
    step = np.repeat(np.diff(poly, axis=0) / parts[:, None], parts, axis=0)
    k = np.arange(parts.sum()) - np.repeat(np.cumsum(parts) - parts, parts)
    return np.vstack([start + k[:, None] * step, poly[-1:]])


def laser_positions(points: np.ndarray, closed: bool, *, speed_mm_s: float, rate_hz: float,
                    latency_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the laser samples along one measurement path (thesis 5.2.1).

    points: (k, 2) float64, mm, the measurement path in part coordinates (laser frame
        offset already applied).
    Returns (tagged, true): (m, 2) positions the samples are reported at (every
    ``speed / rate`` mm) and where the surface was actually read: ``speed * latency`` mm
    earlier along the path (clamped at the path start).
    """
    spacing = speed_mm_s / rate_hz
    poly = closed_polyline(points, closed)
    tagged, t = _resample(points, closed, spacing)
    if len(poly) < 2 or latency_s == 0:
        return tagged, tagged.copy()
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = arc_lengths(seg)
    true = _at(poly, s, np.maximum(t - speed_mm_s * latency_s, 0.0))
    return tagged, true


def laser_measure(surface: HeightMap, tagged: np.ndarray, true: np.ndarray, *,
                  noise_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Simulated laser samples: (m, 3) float64 x, y (tagged position), z (mm).

    ``z`` is the surface height at the ``true`` positions plus Gaussian noise of std
    ``noise_mm``. Use :func:`laser_positions` for the positions along a path.
    """
    z = sample_surface(surface, true)
    if noise_mm > 0:
        z = z + rng.normal(0.0, noise_mm, size=len(z))
    return np.column_stack([tagged, z])
