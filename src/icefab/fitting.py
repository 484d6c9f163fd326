"""Smooth slice contours: local cubic B-spline interpolation of the exact section (Zhang &
Liou, section III; Piegl & Tiller, The NURBS Book, 9.3.4), within a deviation bound.

A faceted mesh cuts into polygons whose vertices turn by a few degrees each; MTTS must
slow down for every turn (curvature-limited speed). This module replaces such a ring by a
C1 curve through its points (Q_k), sampled finely, that stays within ``tolerance`` of the
exact section everywhere, and keeps the corners that are real.

The curve (per ring, closed):

* **Tangents** T_k by the five-point rule (their eq. 3-4, Akima's): V_k = (1 - a_k) q_k +
  a_k q_{k+1}, a_k = |q_{k-1} x q_k| / (|q_{k-1} x q_k| + |q_{k+1} x q_{k+2}|), with the
  chords q_k = Q_k - Q_{k-1} taken as unit vectors (so a dense stretch beside a sparse one
  does not outweigh it); a vanishing denominator (two straight runs) gives a_k = 1/2.
  Straight runs stay straight: three collinear points give a tangent along them.
* **Corners**: where the contour turns by more than ``corner_deg`` at one point, the point
  is a corner of the model (a CAD edge), not faceting: the curve keeps it, arriving along
  the incoming chord and leaving along the outgoing one (their a_k = 1 case). A coarsely
  faceted cylinder (16 facets turn 22.5 degrees each) is smoothed at the default 40;
  the fandisk's and a box's edges (60-90 degrees) stay sharp.
* **Segments**: one cubic Bezier per chord, Q_k to Q_{k+1}, with inner control points on
  the tangents at Renner's distance (their eq. 5-9): equal speed at both ends and the
  middle, so the pieces join C1 into a cubic B-spline with double inner knots (eq. 10-11).
* **Deviation bound**: a Bezier segment's distance from its chord's line is a cubic in
  its parameter, maximised exactly (``_deviation``; the convex-hull bound where the
  control points do not project onto the chord). Where that exceeds the bound, the
  chord's midpoint (a point of the
  exact section) is added and the neighbouring tangents are recomputed (their
  densification, eq. 12-13, done only where needed), until every segment is within.
  Since every segment starts and ends on its chord and stays within the band around it,
  the curve and the section are within ``tolerance`` of each other both ways.
* **Sampling**: each segment is sampled at most ``spacing`` mm apart and densely enough
  that the samples' chords stay within a quarter of the tolerance of the curve (|C''| h^2
  / 8), the curve itself being fitted to three quarters: the sampled ring is within
  ``tolerance`` of the exact section.
* **Simple stays simple**: the bound is per segment, so in a sliver narrower than twice
  the tolerance the curves of its two sides may cross (a sinusoidal ring 0.04 mm wide at
  0.02 mm, a review's: 1 in 300 random slivers). A fitted ring that crosses or touches
  itself where the ring did not is fitted again at half the tolerance, twice at most
  (:data:`SIMPLE_RETRIES`: a tighter curve hugs its chords), else the ring itself is kept:
  the slicer unites a self-crossing ring's layer downstream, where the sliver's two
  sides crossing would have lost or doubled the area between them.

Why not scipy's splines: ``scipy.interpolate.splprep``/``make_splprep`` fit a global
smoothing spline whose bound is on the sum of squared residuals at the points, not on the
distance between the curve and the section everywhere; and a global fit moves every point
when one corner is kept. The paper's local interpolation (each segment from its own four
points, corners as tangent breaks) gives both the pointwise bound and the corners, at the
cost of these ~100 lines of numpy (vectorised per ring).

May import: ``icefab.core``, ``icefab.geometry``.
"""

from __future__ import annotations

import math

import numpy as np

from icefab.core import offsets
from icefab.geometry import segment_distance, simple_mask

#: Densification rounds before a ring is given up as already the polygon (a round halves
#: the failing chords: 30 rounds take a 100 mm chord to 1e-7 mm).
MAX_ROUNDS = 30
#: Points closer than this to their predecessor are dropped before fitting, mm.
MIN_CHORD_MM = 1e-6
#: Fits at half the tolerance tried, each, before a simple ring whose fit crosses itself
#: is kept as it is (:func:`fit_ring`): the review's sliver (0.04 mm wide) was simple at
#: half of 0.02 mm; the ring itself is within any tolerance, only less smooth.
SIMPLE_RETRIES = 2


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.hypot(v[:, 0], v[:, 1])
    return v / np.where(n > 0, n, 1.0)[:, None]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _controls(q: np.ndarray, corner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inner control points (P1, P2), each (k, 2), of the Bezier segments Q_k -> Q_{k+1} of
    a closed ring ``q`` (k, 2); ``corner`` (k,) bool marks the points kept as corners."""
    nxt = np.roll(q, -1, axis=0)
    chord = nxt - q                        # chord k: Q_k -> Q_{k+1}
    u = _unit(chord)
    u_in = np.roll(u, 1, axis=0)           # chord arriving at Q_k
    c_prev = np.abs(_cross(np.roll(u_in, 1, axis=0), u_in))   # |q_{k-1} x q_k|
    c_next = np.abs(_cross(u, np.roll(u, -1, axis=0)))        # |q_{k+1} x q_{k+2}|
    den = c_prev + c_next
    a = np.where(den > 1e-12, c_prev / np.where(den > 1e-12, den, 1.0), 0.5)
    t = _unit((1.0 - a)[:, None] * u_in + a[:, None] * u)
    t_out = np.where(corner[:, None], u, t)                    # leaving Q_k
    t_in = np.where(corner[:, None], u_in, t)                  # arriving at Q_k
    t0, t3 = t_out, np.roll(t_in, -1, axis=0)                  # segment k's end tangents
    # Renner: |C'(0)| = |C'(1/2)| = |C'(1)| = alpha solves a alpha^2 + b alpha + c = 0
    s = t0 + t3
    qa = 16.0 - np.einsum("ij,ij->i", s, s)
    qb = 12.0 * np.einsum("ij,ij->i", chord, s)
    qc = -36.0 * np.einsum("ij,ij->i", chord, chord)
    alpha = (-qb + np.sqrt(qb * qb - 4.0 * qa * qc)) / (2.0 * qa)
    return q + (alpha / 3.0)[:, None] * t0, nxt - (alpha / 3.0)[:, None] * t3


def _deviation(q: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """(k,) the largest distance of each Bezier segment from its chord, mm.

    With signed distances d1, d2 of P1, P2 from the chord's line, the curve's distance is
    the cubic d(u) = 3 d1 u (1-u)^2 + 3 d2 u^2 (1-u), whose maximum is at an end or a root
    of its derivative (exact). That is the distance from the chord itself when P1 and P2
    project onto the chord (the curve, inside their convex hull, then does too); otherwise
    the convex-hull bound, the larger distance of P1 or P2 from the chord, is used.
    """
    nxt = np.roll(q, -1, axis=0)
    d = nxt - q
    L = np.hypot(d[:, 0], d[:, 1])
    u = d / np.where(L > 0, L, 1.0)[:, None]
    d1, d2 = _cross(u, p1 - q), _cross(u, p2 - q)
    a1, a2 = np.einsum("ij,ij->i", p1 - q, u), np.einsum("ij,ij->i", p2 - q, u)
    # d'(u)/3 = d1 + (2 d2 - 4 d1) u + 3 (d1 - d2) u^2
    A, B, C = 3.0 * (d1 - d2), 2.0 * d2 - 4.0 * d1, d1
    disc = np.maximum(B * B - 4.0 * A * C, 0.0)
    quad = np.abs(A) > 1e-15 * (np.abs(B) + np.abs(C) + 1e-300)
    sq = np.sqrt(disc)
    r1 = np.where(quad, (-B + sq) / np.where(quad, 2.0 * A, 1.0),
                  -C / np.where(np.abs(B) > 0, B, 1.0))
    r2 = np.where(quad, (-B - sq) / np.where(quad, 2.0 * A, 1.0), r1)
    best = np.zeros(len(q))
    for r in (r1, r2, np.full(len(q), 0.5)):
        t = np.clip(r, 0.0, 1.0)
        best = np.maximum(best, np.abs(3 * d1 * t * (1 - t) ** 2 + 3 * d2 * t * t * (1 - t)))
    inside = (a1 >= 0) & (a1 <= L) & (a2 >= 0) & (a2 <= L)
    hull = np.maximum(segment_distance(p1, q, nxt), segment_distance(p2, q, nxt))
    return np.where(inside, best, hull)


def _turns(q: np.ndarray) -> np.ndarray:
    """(k,) direction change at every point of a closed ring, radians in [0, pi]."""
    u = _unit(np.roll(q, -1, axis=0) - q)
    u_in = np.roll(u, 1, axis=0)
    return np.abs(np.arctan2(_cross(u_in, u), np.einsum("ij,ij->i", u_in, u)))


def fit_ring(ring: np.ndarray, tolerance: float, corner_deg: float = 40.0,
             spacing: float = 0.4) -> np.ndarray:
    """A closed ring (k, 2) mm replaced by samples of its local cubic interpolant (the
    module docstring): within ``tolerance`` mm of the ring everywhere, corners turning
    more than ``corner_deg`` kept, samples at most ``spacing`` mm apart.

    Returns (s, 2) float64, first point not repeated; the ring's own points are among the
    samples (and its corners), in the same orientation. A simple ring (no crossing or
    touching of its own) gives a simple one: where the fit is not, a fit at a smaller
    tolerance or, failing that, the ring itself (:func:`_keep_simple`).
    """
    _check_settings(tolerance, corner_deg, spacing)
    out = _fit(ring, tolerance, corner_deg, spacing)
    if len(out) >= 3 and not simple_mask([out])[0]:
        return _keep_simple(ring, out, tolerance, corner_deg, spacing)
    return out


def _check_settings(tolerance: float, corner_deg: float, spacing: float) -> None:
    """ValueError unless tolerance (mm) and spacing (mm) are > 0 and corner_deg in
    (0, 180) degrees."""
    if not (tolerance > 0.0 and spacing > 0.0 and 0.0 < corner_deg < 180.0):
        raise ValueError(f"fit_ring: tolerance {tolerance!r} and spacing {spacing!r} must be "
                         f"> 0 and corner_deg {corner_deg!r} in (0, 180)")


def _keep_simple(ring: np.ndarray, fitted: np.ndarray, tolerance: float, corner_deg: float,
                 spacing: float) -> np.ndarray:
    """What :func:`fit_ring` gives for ``ring`` (k, 2) mm whose fit ``fitted`` crosses or
    touches itself: ``fitted`` when the ring does too (nothing to keep); else the first
    fit at half, a quarter ... of ``tolerance`` mm (``SIMPLE_RETRIES`` of them) that is
    simple, or the ring itself (points within ``MIN_CHORD_MM`` of the one before merged):
    within any tolerance of itself and simple, only not smoothed."""
    q = _distinct(np.asarray(ring, dtype=np.float64))
    if len(q) < 3 or not simple_mask([q])[0]:
        return fitted
    tol = tolerance
    for _ in range(SIMPLE_RETRIES):
        tol *= 0.5
        out = _fit(q, tol, corner_deg, spacing)
        if simple_mask([out])[0]:
            return out
    return q.copy()


def _distinct(q: np.ndarray) -> np.ndarray:
    """The ring (k, 2) without its points within ``MIN_CHORD_MM`` of the one before (the
    first point kept when all are)."""
    keep = np.hypot(*(q - np.roll(q, 1, axis=0)).T) > MIN_CHORD_MM
    return q[keep] if keep.any() else q[:1]


def _fit(ring: np.ndarray, tolerance: float, corner_deg: float, spacing: float
         ) -> np.ndarray:
    """The fit proper of :func:`fit_ring` (the module docstring), without its settings'
    check or its keeping a simple ring simple."""
    q = _distinct(np.asarray(ring, dtype=np.float64))
    if len(q) < 3:
        return q.copy()
    corner = _turns(q) > math.radians(corner_deg)
    fit_tol = 0.75 * tolerance
    for _ in range(MAX_ROUNDS):
        p1, p2 = _controls(q, corner)
        bad = _deviation(q, p1, p2) > fit_tol
        if not bad.any():
            break
        # add the midpoints of the failing chords (points of the exact section)
        mid = 0.5 * (q[bad] + np.roll(q, -1, axis=0)[bad])
        at = np.flatnonzero(bad) + 1
        q = np.insert(q, at, mid, axis=0)
        corner = np.insert(corner, at, False)
    else:  # pragma: no cover - a ring this stubborn is returned as its polygon
        return q.copy()
    return _sample(q, p1, p2, tolerance - fit_tol, spacing)


def _sample(q: np.ndarray, p1: np.ndarray, p2: np.ndarray, chord_tol: float,
            spacing: float) -> np.ndarray:
    """Samples of the closed piecewise Bezier curve: per segment n points (its start and
    n - 1 inner ones), n so that samples are at most ``spacing`` apart along the control
    polygon (longer than the curve) and each sample chord within ``chord_tol`` of the
    curve (|C''| <= the larger of its end values, a linear function; chord error
    <= max|C''| / (8 n^2))."""
    p3 = np.roll(q, -1, axis=0)
    length = (np.hypot(*(p1 - q).T) + np.hypot(*(p2 - p1).T) + np.hypot(*(p3 - p2).T))
    c2 = 6.0 * np.maximum(np.hypot(*(p2 - 2 * p1 + q).T), np.hypot(*(p3 - 2 * p2 + p1).T))
    n = np.maximum(np.ceil(length / spacing), np.ceil(np.sqrt(c2 / (8.0 * chord_tol))))
    n = np.maximum(n, 1).astype(np.int64)
    seg = np.repeat(np.arange(len(q)), n)
    u = (np.arange(len(seg)) - np.repeat(np.cumsum(n) - n, n)) / n[seg]
    v = 1.0 - u
    b0, b1, b2, b3 = v ** 3, 3 * u * v * v, 3 * u * u * v, u ** 3
    return (b0[:, None] * q[seg] + b1[:, None] * p1[seg] + b2[:, None] * p2[seg]
            + b3[:, None] * p3[seg])


def fit_rings(points: np.ndarray, ring_offsets: np.ndarray, tolerance: float,
              corner_deg: float = 40.0, spacing: float = 0.4
              ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_ring` over rings stored as concatenated points (P, 2) with (R + 1,)
    offsets; returns the fitted rings the same way."""
    _check_settings(tolerance, corner_deg, spacing)
    rings = [points[a:b] for a, b in zip(ring_offsets[:-1], ring_offsets[1:])]
    out = [_fit(r, tolerance, corner_deg, spacing) for r in rings]
    # one pass of the simplicity check over all rings (a call per ring cost a quarter
    # of the fit's time on 2000 rings of 200 points)
    big = [k for k, r in enumerate(out) if len(r) >= 3]
    simple = simple_mask([out[k] for k in big])
    for k in np.asarray(big, dtype=np.int64)[~simple]:
        out[k] = _keep_simple(rings[k], out[k], tolerance, corner_deg, spacing)
    counts = np.array([len(r) for r in out], dtype=np.int64)
    pts = np.concatenate(out) if out else np.zeros((0, 2))
    return pts, offsets(counts)
