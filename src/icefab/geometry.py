"""Planar polygon geometry: offsets and Boolean operations on ``Region``s.

This is the only module that imports the polygon library. Everything goes through
Clipper2 (Python binding ``pyclipr``), chosen by ``bench/bench_paths.py`` (Booleans are
the bulk of the scaffold stage and Clipper2 is the fastest there; see BENCHMARKS.md).

Coordinates are converted once, at this module's boundary, to Clipper's exact integer
grid: ``SCALE`` integer units per millimetre (resolution 1e-4 mm). Every result comes back
as float64 millimetres.

Offsets are named by intent: :func:`expand` (outward) and :func:`shrink` (inward). Holes
move the other way, because of the ring orientation (outer rings counter-clockwise, holes
clockwise, ``icefab.types``). Joins are mitred (limit 2, squared beyond): round joins
multiply vertex counts (and time) many-fold. Like the thesis (3.4.2: PATHFILTER after every
BUFFERF call), ring points are filtered after every offset: a vertex closer than
``filter_mm`` to the line through its neighbours is dropped. Results of Booleans are not
filtered, so a region built as a difference keeps the exact shared edges (scaffold and
part touch without overlapping).

Degenerate cases: an empty region in gives an empty region out; offsets by 0 return the
input unchanged; rings with fewer than 3 points or (almost) no area after an offset are
dropped.
"""

from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np
import pyclipr
from numba import njit

from icefab.types import Region


def signed_area(ring: np.ndarray) -> float:
    """Signed area (mm^2) of a ring ``(k, 2)``: positive when counter-clockwise (the
    shoelace formula of ``icefab.types.signed_area`` without temporary arrays)."""
    x = ring[:, 0]
    y = ring[:, 1]
    return 0.5 * float(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])
                       + x[-1] * y[0] - x[0] * y[-1])

#: Clipper integer units per millimetre (the one scale constant: resolution 1e-4 mm).
SCALE = 10_000.0
#: Default point filter after offsets, mm (``job.slicing.max_filter_deviation_mm``).
FILTER_MM = 0.05
#: Miter limit (multiples of the offset distance) before a corner is squared off.
MITER_LIMIT = 2.0
#: Rings with less area than this (mm^2) are dropped after offsets.
MIN_RING_AREA = 1e-6

_NONZERO = pyclipr.FillRule.NonZero
_EVENODD = pyclipr.FillRule.EvenOdd

Rings = list[np.ndarray]


# --------------------------------------------------------------------------- conversion


def rings_of(region: Region | Sequence[np.ndarray]) -> Rings:
    """The rings of a region, a ring list or a single (k, 2) ring as a list of (k, 2)
    float64 arrays, mm."""
    if isinstance(region, Region):
        return list(region.rings)
    if isinstance(region, np.ndarray) and region.ndim == 2:
        return [region]
    return list(region)


def region_from_tree(tree) -> Region:
    """A ``Region`` from a Clipper PolyTree (outer rings CCW, holes CW, parents set).

    Depth-first order: every ring comes after its parent. The ring orientation Clipper
    returns (positive fill: outer rings positive) is trusted; where the tree's nesting
    disagrees with it (Clipper2 can misplace an island inside a hole when rings touch),
    the ring is re-parented by point-in-polygon tests (:func:`_fix_nesting`).
    """
    rings: list[np.ndarray] = []
    parent: list[int] = []
    depths: list[int] = []
    stack = [(child, -1, 0) for child in reversed(tree.children)]
    while stack:
        node, par, depth = stack.pop()
        ring = np.ascontiguousarray(node.polygon, dtype=np.float64)
        if len(ring) < 3:
            continue
        idx = len(rings)
        rings.append(ring)
        parent.append(par)
        depths.append(depth)
        stack.extend((child, idx, depth + 1) for child in reversed(node.children))
    if not rings:
        return Region()
    holes = np.asarray(depths) % 2 == 1
    if np.any((ring_areas(rings) < 0) != holes):
        return _fix_nesting(rings, parent)
    return Region(tuple(rings), np.asarray(parent, dtype=np.int64))


def _fix_nesting(rings: list[np.ndarray], parent: list[int]) -> Region:
    """Repair the nesting of rings whose orientation disagrees with their tree depth: the
    new parent is the smallest ring of the opposite orientation whose bounding box holds
    it and that contains most of its (up to 16 sampled) vertices (none: top level). Rings
    are re-ordered so parents come first."""
    from matplotlib.path import Path as MplPath

    n = len(rings)
    areas = ring_areas(rings)
    par = np.asarray(parent, dtype=np.int64).copy()
    depth = np.zeros(n, dtype=np.int64)
    for i in range(n):  # parents precede children in tree order
        depth[i] = depth[par[i]] + 1 if par[i] >= 0 else 0
    bad = np.flatnonzero((areas < 0) != (depth % 2 == 1))
    lo = np.array([r.min(axis=0) for r in rings])
    hi = np.array([r.max(axis=0) for r in rings])
    for i in bad:
        cand = np.flatnonzero(((areas > 0) == (areas[i] < 0)) & (np.abs(areas) > abs(areas[i]))
                              & np.all(lo <= lo[i], axis=1) & np.all(hi >= hi[i], axis=1))
        cand = cand[np.argsort(np.abs(areas[cand]))]
        sample = rings[i][np.linspace(0, len(rings[i]) - 1, min(16, len(rings[i]))).astype(int)]
        par[i] = -1
        for j in cand:
            if MplPath(rings[j]).contains_points(sample).mean() > 0.5:
                par[i] = int(j)
                break
    kids: dict[int, list[int]] = {}
    for i in range(n):
        kids.setdefault(int(par[i]), []).append(i)
    new_index: dict[int, int] = {}
    out_rings: list[np.ndarray] = []
    out_parent: list[int] = []
    todo = [(i, -1) for i in reversed(kids.get(-1, []))]
    while todo:
        i, p = todo.pop()
        new_index[i] = len(out_rings)
        out_rings.append(rings[i])
        out_parent.append(p)
        todo.extend((c, new_index[i]) for c in reversed(kids.get(i, [])))
    return Region(tuple(out_rings), np.asarray(out_parent, dtype=np.int64))


def region_from_rings(rings: Iterable[np.ndarray], fill: str = "nonzero") -> Region:
    """A ``Region`` (with nesting) from loose rings, resolving overlaps by a union.

    fill: 'nonzero' (orientation matters: CCW adds, CW removes) or 'evenodd'
    (orientation ignored; nesting parity decides).
    """
    rings = [np.asarray(r, dtype=np.float64) for r in rings if len(r) >= 3]
    if not rings:
        return Region()
    c = _clipper()
    c.addPaths(rings, pyclipr.Subject)
    return region_from_tree(c.execute2(pyclipr.Union, _EVENODD if fill == "evenodd"
                                       else _NONZERO))


def _clipper() -> pyclipr.Clipper:
    c = pyclipr.Clipper()
    c.scaleFactor = SCALE
    return c


def _offsetter() -> pyclipr.ClipperOffset:
    o = pyclipr.ClipperOffset()
    o.scaleFactor = SCALE
    o.miterLimit = MITER_LIMIT
    return o


# --------------------------------------------------------------------------- booleans


def _boolean(op, subject: Rings, clip: Rings) -> Region:
    if not subject:
        return Region()
    c = _clipper()
    c.addPaths(subject, pyclipr.Subject)
    if clip:
        c.addPaths(clip, pyclipr.Clip)
    return region_from_tree(c.execute2(op, _NONZERO))


def union(*regions: Region | Sequence[np.ndarray]) -> Region:
    """The union of any number of regions (one Clipper call)."""
    rings: Rings = []
    for r in regions:
        rings.extend(rings_of(r))
    return _boolean(pyclipr.Union, rings, [])


def difference(a: Region | Sequence[np.ndarray], b: Region | Sequence[np.ndarray]) -> Region:
    """``a`` minus ``b``."""
    return _boolean(pyclipr.Difference, rings_of(a), rings_of(b))


def intersection(a: Region | Sequence[np.ndarray], b: Region | Sequence[np.ndarray]) -> Region:
    """The area common to ``a`` and ``b``."""
    ra, rb = rings_of(a), rings_of(b)
    if not ra or not rb:
        return Region()
    return _boolean(pyclipr.Intersection, ra, rb)


def clip_lines(lines: Sequence[np.ndarray], region: Region | Sequence[np.ndarray]
               ) -> list[np.ndarray]:
    """Open polylines cut to the inside of ``region``.

    lines: open polylines, each (k, 2) float64, mm.
    Returns the pieces inside (each (k, 2) float64, mm), in no particular order.
    """
    rings = rings_of(region)
    if not rings or not len(lines):
        return []
    c = _clipper()
    c.addPaths(list(lines), pyclipr.Subject, True)
    c.addPaths(rings, pyclipr.Clip)
    _closed, open_paths = c.execute(pyclipr.Intersection, _NONZERO, returnOpenPaths=True)
    return [np.asarray(p, dtype=np.float64) for p in open_paths if len(p) >= 2]


# --------------------------------------------------------------------------- offsets


@njit(cache=True)
def _filter_mask(pts: np.ndarray, starts: np.ndarray, eps: float, max_span: int
                 ) -> np.ndarray:  # pragma: no cover - compiled
    """Greedy chord filter over concatenated closed rings (thesis PATHFILTER).

    From an anchor, extend the chord to the farthest point such that every skipped point
    lies within ``eps`` of it (at most ``max_span`` points skipped); keep that point and
    repeat. The first point of every ring is kept; the closing edge is included.
    """
    keep = np.zeros(len(pts), dtype=np.bool_)
    eps2 = eps * eps
    for r in range(len(starts) - 1):
        s0 = starts[r]
        n = starts[r + 1] - s0
        keep[s0] = True
        a = 0
        while a < n:
            best = a + 1
            j = a + 2
            while j <= n and j - a <= max_span:
                # chord from a to j (index n is the first point again)
                jx = pts[s0 + (j % n), 0]
                jy = pts[s0 + (j % n), 1]
                ax = pts[s0 + a, 0]
                ay = pts[s0 + a, 1]
                dx = jx - ax
                dy = jy - ay
                L2 = dx * dx + dy * dy
                ok = True
                for i in range(a + 1, j):
                    px = pts[s0 + i, 0] - ax
                    py = pts[s0 + i, 1] - ay
                    if L2 > 0.0:
                        t = (px * dx + py * dy) / L2
                        if t < 0.0:
                            t = 0.0
                        elif t > 1.0:
                            t = 1.0
                        ex = px - t * dx
                        ey = py - t * dy
                    else:
                        ex = px
                        ey = py
                    if ex * ex + ey * ey > eps2:
                        ok = False
                        break
                if not ok:
                    break
                best = j
                j += 1
            if best >= n:
                break
            keep[s0 + best] = True
            a = best
    return keep


def simplify(rings: Rings, filter_mm: float = FILTER_MM) -> Rings:
    """Drop ring vertices so that the ring moves by at most ``filter_mm`` (thesis 3.4.2:
    PATHFILTER after every buffering).

    Rings left with fewer than 3 points or less than MIN_RING_AREA are removed.
    """
    rings = [np.asarray(r, dtype=np.float64) for r in rings if len(r) >= 3]
    if filter_mm > 0 and rings:
        pts = np.concatenate(rings)
        starts = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
        keep = _filter_mask(pts, starts, float(filter_mm), 64)
        rings = [pts[a:b][keep[a:b]] for a, b in zip(starts[:-1], starts[1:])]
    rings = [r for r in rings if len(r) >= 3]
    if not rings:
        return []
    keep = np.abs(ring_areas(rings)) > MIN_RING_AREA
    return [r for r, k in zip(rings, keep) if k]


def offset_rings(rings: Rings, d: float, filter_mm: float = FILTER_MM) -> Rings:
    """Offset closed rings by ``d`` mm (positive outward), flat ring list out.

    The fast form for repeated offsets (fill rings): no nesting tree is built. Output
    orientation follows the icefab convention (outer CCW, holes CW).
    """
    if not rings:
        return []
    if d == 0:
        return list(rings)
    o = _offsetter()
    o.addPaths(rings, pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
    out = o.execute(float(d))
    return simplify(list(out), filter_mm)


def _offset_region(region: Region, d: float, filter_mm: float) -> Region:
    if region.is_empty:
        return Region()
    if d == 0:
        return region
    rings = list(region.rings)
    if d > filter_mm > 0:
        # Growing: filter the input too. Unions (the merged region of the scaffold scan)
        # carry micro-steps that mitred joins would turn into square spikes d long.
        rings = simplify(rings, filter_mm)
    o = _offsetter()
    o.addPaths(rings, pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
    out = simplify(list(o.execute(float(d))), filter_mm)
    if not out:
        return Region()
    # Rebuild the nesting tree (and re-clean after filtering) with one union.
    return region_from_rings(out)


def expand(region: Region, d: float, filter_mm: float = FILTER_MM) -> Region:
    """The region grown outward by ``d`` mm (holes shrink). d >= 0."""
    if d < 0:
        raise ValueError(f"expand distance {d} mm: must be >= 0 (use shrink)")
    return _offset_region(region, d, filter_mm)


def shrink(region: Region, d: float, filter_mm: float = FILTER_MM) -> Region:
    """The region shrunk inward by ``d`` mm (holes grow); parts thinner than 2d vanish."""
    if d < 0:
        raise ValueError(f"shrink distance {d} mm: must be >= 0 (use expand)")
    return _offset_region(region, -d, filter_mm)


def opening(region: Region, r: float, filter_mm: float = FILTER_MM,
            margin: float = 0.0) -> Region:
    """Shrink by ``r`` then expand by ``r + margin``: removes every feature narrower than
    ``2 r`` (and grows what is left by ``margin``, e.g. to absorb the point filter)."""
    if r <= 0 or region.is_empty:
        return region
    inner = offset_rings(list(region.rings), -r, filter_mm)
    if not inner:
        return Region()
    return region_from_rings(offset_rings(inner, r + margin, filter_mm))


def sweep_rings(paths: Sequence[tuple[np.ndarray, bool, float]], grow: float = 0.0) -> Rings:
    """The bands paths sweep with their width (+ ``2 grow``), as flat oriented rings: the
    bands of equal width and kind are united, different ones may overlap (use them as the
    clip side of a NonZero Boolean). Mitred corners, round ends of open paths (the bead
    where the tool stops).

    paths: (points (k, 2) float64 mm, closed, width mm) triples.
    """
    by_width: dict[tuple[float, bool], list[np.ndarray]] = {}
    for pts, closed, width in paths:
        if width > 0 and len(pts) >= 2:
            by_width.setdefault((float(width), bool(closed)), []).append(pts)
    out: Rings = []
    for (width, closed), pts in by_width.items():
        o = _offsetter()
        o.addPaths(pts, pyclipr.JoinType.Miter,
                   pyclipr.EndType.Joined if closed else pyclipr.EndType.Round)
        out.extend(o.execute(width / 2.0 + grow))
    return out


def level_bands(levels: Sequence[tuple[Sequence[np.ndarray], float]]) -> Rings:
    """Bands swept by the rings of offset levels: for each level (oriented rings bounding
    an area D, half-width h) the rings of ``expand(D, h)`` plus the reversed rings of
    ``shrink(D, h)``, whose NonZero winding is 1 exactly in the band. Use them as the clip
    side of a NonZero Boolean (bands of different levels may touch or overlap)."""
    out: Rings = []
    for rings, h in levels:
        if not len(rings):
            continue
        o = _offsetter()
        o.addPaths(list(rings), pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
        out.extend(o.execute(h))
        o = _offsetter()
        o.addPaths(list(rings), pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
        out.extend(np.ascontiguousarray(r[::-1]) for r in o.execute(-h))
    return out


def sweep(paths: Sequence[tuple[np.ndarray, bool, float]]) -> Region:
    """The area covered by paths swept by their width (see :func:`sweep_rings`)."""
    return union(sweep_rings(paths))


def difference_rings(a: Region | Sequence[np.ndarray], b: Region | Sequence[np.ndarray]
                     ) -> Rings:
    """``a`` minus ``b`` as flat oriented rings (outer CCW, holes CW; no nesting tree)."""
    ra = rings_of(a)
    if not ra:
        return []
    rb = rings_of(b)
    if not rb:
        return ra
    c = _clipper()
    c.addPaths(ra, pyclipr.Subject)
    c.addPaths(rb, pyclipr.Clip)
    return [np.asarray(r, dtype=np.float64) for r in c.execute(pyclipr.Difference, _NONZERO)
            if len(r) >= 3]


@njit(cache=True)
def _even_odd(px: np.ndarray, py: np.ndarray, pts: np.ndarray, starts: np.ndarray
              ) -> np.ndarray:  # pragma: no cover - compiled
    """Even-odd crossing test of points against all ring edges."""
    out = np.zeros(len(px), dtype=np.bool_)
    for k in range(len(px)):
        x = px[k]
        y = py[k]
        inside = False
        for r in range(len(starts) - 1):
            s0 = starts[r]
            n = starts[r + 1] - s0
            j = s0 + n - 1
            for i in range(s0, s0 + n):
                yi = pts[i, 1]
                yj = pts[j, 1]
                if (yi > y) != (yj > y):
                    xc = pts[i, 0] + (y - yi) * (pts[j, 0] - pts[i, 0]) / (yj - yi)
                    if x < xc:
                        inside = not inside
                j = i
        out[k] = inside
    return out


def points_inside(points: np.ndarray, region: Region | Sequence[np.ndarray]) -> np.ndarray:
    """(n,) bool: which points (n, 2) mm lie inside the region (even-odd rule over its
    properly nested rings; points on an edge may go either way)."""
    rings = rings_of(region)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not rings or not len(pts):
        return np.zeros(len(pts), dtype=bool)
    allp = np.ascontiguousarray(np.concatenate(rings))
    starts = np.concatenate([[0], np.cumsum([len(r) for r in rings])]).astype(np.int64)
    return _even_odd(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                     allp, starts)


def ring_areas(rings: Sequence[np.ndarray]) -> np.ndarray:
    """(r,) float64 signed areas of rings, mm^2, in one vectorised pass."""
    if not len(rings):
        return np.zeros(0)
    pts = np.concatenate(rings)
    counts = np.array([len(r) for r in rings])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nxt = np.arange(1, len(pts) + 1)
    ends = starts + counts
    nxt[ends - 1] = starts  # wrap each ring to its first point
    cross = pts[:, 0] * pts[nxt, 1] - pts[nxt, 0] * pts[:, 1]
    return 0.5 * np.add.reduceat(cross, starts)


def area(region: Region | Sequence[np.ndarray]) -> float:
    """Area, mm^2 (sum of the signed ring areas)."""
    rings = rings_of(region)
    return float(ring_areas(rings).sum()) if rings else 0.0
