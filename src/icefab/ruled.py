"""Ruled layer edges for multi-axis cells (Zhang & Liou, sections IV-V; de Jager's ruled
slices).

A planar cell builds each layer as an extrusion of its contour (the "zero order"
approximation: a staircase on every slanted wall). A cell that can tilt its nozzle (or a
machining head that trims each layer) can instead give each layer a ruled side surface: a
straight generator from every point of the layer's contour to the matching point of the
next layer's contour. This module finds those generators; planar cells ignore it.

Matching (their section V):

* **Correspondence of contours.** A contour of layer k is joined to the contours of layer
  k+1 whose material overlaps its own: polygons (an outer ring with its holes) of the two
  layers correspond when their areas intersect (Clipper), outer rings match outer rings and
  holes match holes of corresponding polygons. This handles branching (one contour below,
  two above: each point takes the nearer branch) and the correspondence problem (several
  contours in both layers) without the facet bookkeeping of their direct test.
* **Matching points.** Each contour point is matched to the nearest point of the
  corresponding contours above. For a ruled (or any smooth) wall the nearest point lies
  along the wall's steepest direction, so the generator's horizontal length over the layer
  height is the tangent of the wall's inclination from vertical: on a cone it is the
  cone's half angle, on a twisted extrusion ``atan(omega * s)`` (twist rate omega rad/mm,
  s the distance from the side's middle), the tilts the tests check.
* **Ledges.** A generator flatter than ``max_tilt`` from vertical is no wall: the contour
  above steps in or out there (a horizontal ledge, a contour that ends), and the point gets
  no match (NaN) rather than a generator that would cut through the part.

Sign convention: ``tilt`` (radians) is positive when the generator leans out of the
material (an overhang: the layer above reaches beyond this one) and negative when it leans
in (the part narrows upwards), measured against the contour's outward normal.

May import: ``icefab.core``, ``icefab.geometry``.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from icefab import geometry
from icefab.core import Region, RuledEdges, Stack

#: Generators flatter than this from vertical are ledges (no match), degrees.
MAX_TILT_DEG = 80.0


def _polygon_of_ring(region: Region) -> np.ndarray:
    """(r,) int64: the index of the outer ring of the polygon each ring belongs to."""
    depth = region.depth()
    return np.where(depth % 2 == 0, np.arange(len(region)), region.parent).astype(np.int64)


def _bounds(rings: Sequence[np.ndarray]) -> np.ndarray:
    return np.array([[r[:, 0].min(), r[:, 1].min(), r[:, 0].max(), r[:, 1].max()]
                     for r in rings]).reshape(-1, 4)


def corresponding(lower: Region, upper: Region) -> list[np.ndarray]:
    """For every ring of ``lower``, the (m,) int64 indices of the rings of ``upper`` it is
    joined to: rings of the same kind (outer or hole) whose polygons overlap its polygon."""
    out = [np.zeros(0, dtype=np.int64) for _ in range(len(lower))]
    if lower.is_empty or upper.is_empty:
        return out
    poly_lo, poly_up = _polygon_of_ring(lower), _polygon_of_ring(upper)
    outer_lo = np.flatnonzero(poly_lo == np.arange(len(lower)))
    outer_up = np.flatnonzero(poly_up == np.arange(len(upper)))
    blo, bup = _bounds([lower.rings[i] for i in outer_lo]), _bounds([upper.rings[j]
                                                                      for j in outer_up])
    overlap: dict[int, list[int]] = {int(i): [] for i in outer_lo}
    for a, i in enumerate(outer_lo):
        near = np.flatnonzero((bup[:, 0] <= blo[a, 2]) & (bup[:, 2] >= blo[a, 0])
                              & (bup[:, 1] <= blo[a, 3]) & (bup[:, 3] >= blo[a, 1]))
        if not len(near):
            continue
        mine = [lower.rings[k] for k in np.flatnonzero(poly_lo == i)]
        for b in near:
            j = int(outer_up[b])
            theirs = [upper.rings[k] for k in np.flatnonzero(poly_up == j)]
            if geometry.area(geometry.intersection(mine, theirs)) > 0.0:
                overlap[int(i)].append(j)
    is_hole_up = poly_up != np.arange(len(upper))
    for r in range(len(lower)):
        polys = overlap[int(poly_lo[r])]
        hole = poly_lo[r] != r
        out[r] = np.flatnonzero(np.isin(poly_up, polys) & (is_hole_up == hole)).astype(np.int64)
    return out


def _outward_normals(ring: np.ndarray) -> np.ndarray:
    """(k, 2) unit normals at the ring's vertices pointing out of the material (the mean of
    the two edges' normals; icefab rings: outer CCW, holes CW, so (dy, -dx) points out for
    both)."""
    d = np.roll(ring, -1, axis=0) - ring
    n = np.stack([d[:, 1], -d[:, 0]], axis=1)
    n /= np.maximum(np.hypot(n[:, 0], n[:, 1]), 1e-300)[:, None]
    v = n + np.roll(n, 1, axis=0)
    return v / np.maximum(np.hypot(v[:, 0], v[:, 1]), 1e-300)[:, None]


def layer_generators(lower: Region, upper: Region, dz: float,
                     max_tilt_deg: float = MAX_TILT_DEG, spacing: float = 0.05
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Generators from every point of ``lower``'s rings to ``upper`` (dz mm above).

    ``spacing``: sampling of the upper rings for the nearest-point search, mm (exact up to a
    few samples away; the result is the exact nearest point of the candidate edges).
    Returns (match (n, 2) mm, match_ring (n,) int64, tilt (n,) rad) over the concatenated
    points of ``lower.rings``; NaN / -1 where there is no generator (see the module
    docstring).
    """
    if not dz > 0.0:
        raise ValueError(f"layer height {dz!r} mm: expected > 0")
    n = lower.n_points
    match = np.full((n, 2), np.nan)
    match_ring = np.full(n, -1, dtype=np.int64)
    tilt = np.full(n, np.nan)
    limit = dz * math.tan(math.radians(max_tilt_deg))
    cands = corresponding(lower, upper)
    start = 0
    for r, ring in enumerate(lower.rings):
        stop = start + len(ring)
        cand = cands[r]
        if len(cand):
            dist, foot, which = geometry.nearest_on_rings(
                ring, [upper.rings[j] for j in cand], spacing=spacing)
            ok = dist <= limit
            sl = slice(start, stop)
            match[sl][ok] = foot[ok]
            match_ring[sl][ok] = cand[which[ok]]
            off = foot - ring
            side = np.sign(np.einsum("ij,ij->i", off, _outward_normals(ring)))
            tilt[sl][ok] = (side * np.arctan2(dist, dz))[ok]
        start = stop
    return match, match_ring, tilt


def ruled_edges(stack: Stack, max_tilt_deg: float = MAX_TILT_DEG,
                progress=None) -> RuledEdges:
    """The ruled side surfaces of every layer's part contours (the module docstring).

    ``max_tilt_deg``: generators flatter than this from vertical are ledges (no match), in
    (0, 90) degrees. ``progress(done, total)`` is called after every layer.
    """
    if not 0.0 < max_tilt_deg < 90.0:
        raise ValueError(f"max_tilt_deg {max_tilt_deg!r}: expected between 0 and 90 degrees")
    cols: dict[str, list[np.ndarray]] = {k: [] for k in
                                         ("layer", "ring", "point", "z", "match",
                                          "match_ring", "dz", "tilt")}
    layers = stack.layers
    for k, L in enumerate(layers):
        n = L.part.n_points
        if n:
            cols["layer"].append(np.full(n, k, dtype=np.int64))
            cols["ring"].append(np.repeat(np.arange(len(L.part)),
                                          [len(r) for r in L.part.rings]))
            cols["point"].append(np.concatenate(L.part.rings))
            cols["z"].append(np.full(n, L.z))
            if k + 1 < len(layers) and not layers[k + 1].part.is_empty:
                dz = float(layers[k + 1].z - L.z)
                m, mr, t = layer_generators(L.part, layers[k + 1].part, dz, max_tilt_deg)
            else:
                m, mr, t = (np.full((n, 2), np.nan), np.full(n, -1, np.int64),
                            np.full(n, np.nan))
                dz = np.nan
            cols["dz"].append(np.where(mr >= 0, dz, np.nan))
            cols["match"].append(m)
            cols["match_ring"].append(mr)
            cols["tilt"].append(t)
        if progress is not None:
            progress(k + 1, len(layers))
    empty = {"point": (0, 2), "match": (0, 2)}
    arrays = {k: (np.concatenate(v) if v else
                  np.zeros(empty.get(k, (0,)),
                           dtype=np.int64 if k in ("layer", "ring", "match_ring")
                           else np.float64))
              for k, v in cols.items()}
    return RuledEdges(**arrays)
