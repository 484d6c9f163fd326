"""Planar polygon geometry: offsets and Boolean operations on ``Region``s.

This is the only module that imports the polygon library. Everything goes through
Clipper2 (Python binding ``pyclipr``), chosen by ``bench/bench_paths.py`` (Booleans are
the bulk of the scaffold stage and Clipper2 is the fastest there; see BENCHMARKS.md).

Coordinates are converted once, at this module's boundary, to Clipper's exact integer
grid: ``SCALE`` integer units per millimetre (resolution 1e-4 mm). Every result comes back
as float64 millimetres.

Offsets are named by intent: :func:`expand` (outward) and :func:`shrink` (inward). Holes
move the other way, because of the ring orientation (outer rings counter-clockwise, holes
clockwise, ``icefab.core``). Joins are mitred (limit 2, squared beyond): round joins
multiply vertex counts (and time) many-fold. Like the thesis (3.4.2: PATHFILTER after every
BUFFERF call), ring points are filtered after every offset: a vertex closer than
``filter_mm`` to the line through its neighbours is dropped. The filter never makes a ring
cross or touch itself (the thesis' RPSLICE was written to end the previous code's
self-intersecting paths): a ring whose filtered form is not simple keeps its points, and
rings Clipper returns touching themselves at a vertex are cut into loops there
(:func:`simplify`). Results of Booleans are not filtered, so a region built as a
difference keeps the exact shared edges (scaffold and part touch without overlapping).

Thin areas (gaps the paths leave) are described by their centre lines, the medial axis
(:func:`medial_axis`, from scipy's Delaunay triangulation of the sampled rings), with the
clearance (half the local width) at every point (:func:`width_runs`).

Degenerate cases: an empty region in gives an empty region out; offsets by 0 return the
input unchanged; rings with fewer than 3 points or (almost) no area after an offset are
dropped.
"""

from __future__ import annotations

import itertools
import math
from typing import Callable, Iterable, Sequence

import numpy as np
import pyclipr
from numba import njit

from icefab import _smooth
from icefab.core import (MITER_LIMIT, Region, arc_lengths, closed_polyline,  # noqa: F401
                         offsets, signed_area, split_rows,
                         subdivide_segments)  # (re-exported)

#: Clipper integer units per millimetre (the one scale constant: resolution 1e-4 mm).
SCALE = 10_000.0
#: Default point filter after offsets, mm (``job.slicing.max_filter_deviation_mm``).
FILTER_MM = 0.05
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
    areas = ring_areas(rings)
    rings, parent, areas, depths = _without_needles(rings, parent, areas, depths)
    if not rings:
        return Region()
    holes = np.asarray(depths) % 2 == 1
    if np.any((areas < 0) != holes):
        return _fix_nesting(rings, parent)
    return Region(tuple(rings), np.asarray(parent, dtype=np.int64))


#: Rings of a Clipper result with more area than this (mm^2) are never needles
#: (:func:`_without_needles`): one 1 m long and one grid unit wide holds 0.05 mm^2.
NEEDLE_MAX_AREA_MM2 = 0.05


def _without_needles(rings: list[np.ndarray], parent: list[int], areas: np.ndarray,
                     depths: list[int]) -> tuple[list[np.ndarray], list[int], np.ndarray,
                                                 list[int]]:
    """The rings of a Clipper result less its needles: rings narrower on average than one
    grid unit (``2 |area| / perimeter < 1 / SCALE``) that hold no other ring. Clipper2
    may return such a spike as a ring of its own: a fuzzed scaffold had a 3-point "hole"
    8.5 mm long and 3.5e-5 mm wide inside another hole, which under the nonzero rule
    made a sliver of scaffold inside the part's hole and the polygon invalid. Parents
    come before their children (tree order) and stay so."""
    # only small rings can be needles (a needle 1 m long holds 0.05 mm^2): their
    # perimeters alone are measured
    small = np.flatnonzero(np.abs(areas) < NEEDLE_MAX_AREA_MM2)
    if not len(small):
        return rings, parent, areas, depths
    needle = np.zeros(len(rings), dtype=bool)
    needle[small] = 2.0 * np.abs(areas[small]) * SCALE < ring_perimeters(
        [rings[i] for i in small])
    if not needle.any():
        return rings, parent, areas, depths
    par = np.asarray(parent, dtype=np.int64)
    needle[par[par >= 0]] = False          # a ring holding another is no needle
    if not needle.any():
        return rings, parent, areas, depths
    keep = np.flatnonzero(~needle)
    new = np.full(len(rings), -1, dtype=np.int64)
    new[keep] = np.arange(len(keep))
    return ([rings[i] for i in keep], [int(new[par[i]]) if par[i] >= 0 else -1 for i in keep],
            areas[keep], [depths[i] for i in keep])


def _fix_nesting(rings: list[np.ndarray], parent: list[int]) -> Region:
    """Repair the nesting of rings whose orientation disagrees with their tree depth: the
    new parent is the smallest ring of the opposite orientation whose bounding box holds
    it and that contains most of its (up to 16 sampled) vertices (none: top level). Rings
    are re-ordered so parents come first."""
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
            if points_inside(sample, [rings[j]]).mean() > 0.5:
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
def _seg_dist2(px: float, py: float, dx: float, dy: float
               ) -> float:  # pragma: no cover - compiled
    """Squared distance of the point (px, py) from the segment (0, 0)-(dx, dy)."""
    L2 = dx * dx + dy * dy
    t = (px * dx + py * dy) / L2 if L2 > 0.0 else 0.0
    t = min(1.0, max(0.0, t))
    ex = px - t * dx
    ey = py - t * dy
    return ex * ex + ey * ey


@njit(cache=True)
def _filter_mask(pts: np.ndarray, starts: np.ndarray, eps: np.ndarray, max_span: int,
                 closed: bool) -> np.ndarray:  # pragma: no cover - compiled
    """Greedy chord filter over concatenated rings or polylines (thesis PATHFILTER).

    From an anchor, extend the chord to the farthest point such that every skipped point
    lies within ``eps[r]`` of it (at most ``max_span`` points skipped); keep that point and
    repeat. The first point of every ring / polyline is kept; closed: the closing edge is
    filtered too (chord end index n is the first point again); open: the last point is
    kept.
    """
    keep = np.zeros(len(pts), dtype=np.bool_)
    for r in range(len(starts) - 1):
        eps2 = eps[r] * eps[r]
        s0 = starts[r]
        n = starts[r + 1] - s0
        if n == 0:
            continue
        last = n if closed else n - 1  # the final chord end
        keep[s0] = True
        keep[s0 + last % n] = True
        a = 0
        while a < last:
            best = a + 1
            j = a + 2
            while j <= last and j - a <= max_span:
                ax = pts[s0 + a, 0]
                ay = pts[s0 + a, 1]
                dx = pts[s0 + j % n, 0] - ax
                dy = pts[s0 + j % n, 1] - ay
                ok = True
                for i in range(a + 1, j):
                    if _seg_dist2(pts[s0 + i, 0] - ax, pts[s0 + i, 1] - ay, dx, dy) > eps2:
                        ok = False
                        break
                if not ok:
                    break
                best = j
                j += 1
            if best >= last:
                break
            keep[s0 + best] = True
            a = best
    return keep


def _chord_keep(pts: np.ndarray, starts: np.ndarray, eps: float | np.ndarray,
                closed: bool, max_span: int = 64) -> np.ndarray:
    """:func:`_filter_mask` with ``eps`` one value or one per ring / polyline."""
    eps = np.ascontiguousarray(np.broadcast_to(np.asarray(eps, dtype=np.float64),
                                               (len(starts) - 1,)))
    return _filter_mask(pts, starts, eps, max_span, closed)


@njit(cache=True)
def _segments_touch(ax, ay, bx, by, cx, cy, dx, dy) -> bool:  # pragma: no cover - compiled
    """True when the closed segments ab and cd share a point (crossing or touching)."""
    d1 = (dx - cx) * (ay - cy) - (dy - cy) * (ax - cx)
    d2 = (dx - cx) * (by - cy) - (dy - cy) * (bx - cx)
    d3 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    d4 = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax)
    if ((d1 > 0 and d2 < 0) or (d1 < 0 and d2 > 0)) and \
            ((d3 > 0 and d4 < 0) or (d3 < 0 and d4 > 0)):
        return True
    # touching: an end point on the other segment (collinear cases included)
    if d1 == 0 and min(cx, dx) <= ax <= max(cx, dx) and min(cy, dy) <= ay <= max(cy, dy):
        return True
    if d2 == 0 and min(cx, dx) <= bx <= max(cx, dx) and min(cy, dy) <= by <= max(cy, dy):
        return True
    if d3 == 0 and min(ax, bx) <= cx <= max(ax, bx) and min(ay, by) <= cy <= max(ay, by):
        return True
    if d4 == 0 and min(ax, bx) <= dx <= max(ax, bx) and min(ay, by) <= dy <= max(ay, by):
        return True
    return False


@njit(cache=True)
def _simple_mask(pts: np.ndarray, starts: np.ndarray, closed: bool
                 ) -> np.ndarray:  # pragma: no cover - compiled
    """(r,) bool: which of the concatenated rings (or open polylines) are simple.

    A ring is simple when no two of its edges share a point except consecutive edges at
    their common vertex (and those do not fold back onto each other): the definition of
    GEOS' ``is_simple``, so a ring touching itself at a vertex is not simple. Edges are
    swept in order of their smallest x, so each edge is only tested against the edges
    whose x-range overlaps its own.
    """
    nr = len(starts) - 1
    out = np.ones(nr, dtype=np.bool_)
    for r in range(nr):
        s0 = starts[r]
        n = starts[r + 1] - s0
        m = n if closed else n - 1  # number of edges
        if m < 2:
            continue
        x0 = np.empty(m)
        x1 = np.empty(m)
        for i in range(m):
            a = s0 + i
            b = s0 + (i + 1) % n
            x0[i] = min(pts[a, 0], pts[b, 0])
            x1[i] = max(pts[a, 0], pts[b, 0])
        order = np.argsort(x0)
        ok = True
        for oi in range(m):
            i = order[oi]
            ai = s0 + i
            bi = s0 + (i + 1) % n
            ax, ay, bx, by = pts[ai, 0], pts[ai, 1], pts[bi, 0], pts[bi, 1]
            if ax == bx and ay == by:
                ok = False  # zero-length edge: a repeated point
                break
            ylo = min(ay, by)
            yhi = max(ay, by)
            for oj in range(oi + 1, m):
                j = order[oj]
                if x0[j] > x1[i]:
                    break
                cj = s0 + j
                dj = s0 + (j + 1) % n
                cx, cy, dx, dy = pts[cj, 0], pts[cj, 1], pts[dj, 0], pts[dj, 1]
                if max(cy, dy) < ylo or min(cy, dy) > yhi:
                    continue
                lo = min(i, j)
                hi = max(i, j)
                if hi == lo + 1 or (closed and lo == 0 and hi == m - 1 and m > 2):
                    # consecutive edges share one vertex: not simple only if they fold back
                    if hi == lo + 1:
                        px, py = pts[s0 + lo, 0], pts[s0 + lo, 1]
                        qx, qy = pts[s0 + hi, 0], pts[s0 + hi, 1]
                        tx, ty = pts[s0 + (hi + 1) % n, 0], pts[s0 + (hi + 1) % n, 1]
                    else:
                        px, py = pts[s0 + m - 1, 0], pts[s0 + m - 1, 1]
                        qx, qy = pts[s0, 0], pts[s0, 1]
                        tx, ty = pts[s0 + 1, 0], pts[s0 + 1, 1]
                    cr = (qx - px) * (ty - qy) - (qy - py) * (tx - qx)
                    dot = (qx - px) * (tx - qx) + (qy - py) * (ty - qy)
                    if cr == 0 and dot < 0:
                        ok = False
                        break
                    continue
                if _segments_touch(ax, ay, bx, by, cx, cy, dx, dy):
                    ok = False
                    break
            if not ok:
                break
        out[r] = ok
    return out


def _pack(rings: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Rings or polylines as the compiled kernels take them: all points (v, 2) float64,
    contiguous, and each one's first row (r + 1,) int64, the last entry v."""
    pts = np.ascontiguousarray(np.concatenate(rings), dtype=np.float64)
    return pts, offsets([len(r) for r in rings])


def simple_mask(rings: Sequence[np.ndarray], closed: bool = True) -> np.ndarray:
    """(r,) bool: which rings (closed) or open polylines have no self-intersection and do
    not touch themselves (GEOS' ``is_simple``)."""
    rings = [np.asarray(r, dtype=np.float64) for r in rings]
    if not rings:
        return np.zeros(0, dtype=bool)
    return _simple_mask(*_pack(rings), closed)


def _split_touching(ring: np.ndarray) -> Rings:
    """A ring that passes through one vertex more than once (Clipper output may touch
    itself at a vertex) cut there into loops, each a ring of its own."""
    _u, inv, counts = np.unique(ring, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    if counts.max() < 2:
        return [ring]
    # walk the ring; when a point repeats, the loop since its previous visit is closed off
    out: Rings = []
    stack: list[int] = []
    seen: dict[int, int] = {}
    for i, key in enumerate(inv):
        key = int(key)
        if key in seen:
            j = seen[key]
            loop = stack[j:]
            if len(loop) >= 3:
                out.append(ring[loop])
            for k in stack[j + 1:]:
                seen.pop(int(inv[k]), None)
            del stack[j + 1:]
            continue
        seen[key] = len(stack)
        stack.append(i)
    if len(stack) >= 3:
        out.append(ring[stack])
    return out


def simplify(rings: Rings, filter_mm: float = FILTER_MM, slivers: bool = False) -> Rings:
    """Drop ring vertices so that the ring moves by at most ``filter_mm`` (thesis 3.4.2:
    PATHFILTER after every buffering), never making a ring cross or touch itself.

    The chord filter only looks along the ring, so where a ring comes back within
    ``2 filter_mm`` of itself (a sliver left by an offset, a narrow neck) its chords may
    cross: such rings keep all their points. Rings that touch themselves at a vertex
    (Clipper's offsets and Booleans may return those) are first cut there into separate
    rings. Rings left with fewer than 3 points or less than MIN_RING_AREA are removed.

    slivers: True also drops an outer ring and its hole that together are narrower than
    the filter keeps apart (:func:`_slivers`), as :func:`offset_rings` (the paths stage's
    levels) does. A region keeps them: a scaffold may be an annulus 0.1 mm wide where
    ``scaffold.min_width_mm`` allows it.
    """
    rings = [np.asarray(r, dtype=np.float64) for r in rings if len(r) >= 3]
    if filter_mm > 0 and rings:
        pts, starts = _pack(rings)
        # one compiled pass filters, tests and measures the filtered rings (three packings
        # of the same rings cost as much as the filter: some 150 offsets a layer)
        sliver = (_slivers(rings, _packed_areas(pts, starts), float(filter_mm)) if slivers
                  else np.zeros(len(rings), dtype=bool))
        if sliver.any():
            rings = [r for r, k in zip(rings, sliver) if not k]
            if not rings:
                return []
            pts, starts = _pack(rings)
        kept, cut, ok, areas, _keep = _filtered_rings(pts, starts, float(filter_mm))
        if ok.all():
            big = np.abs(areas) > MIN_RING_AREA
            return [kept[a:b] for a, b, k in zip(cut[:-1], cut[1:], big) if k]
        rings = [r for a, b, k, ring in zip(cut[:-1], cut[1:], ok, rings)
                 for r in ([kept[a:b]] if k else _simplify_slow(ring, filter_mm))]
    rings = [r for r in rings if len(r) >= 3]
    if not rings:
        return []
    keep = np.abs(ring_areas(rings)) > MIN_RING_AREA
    return [r for r, k in zip(rings, keep) if k]


def _slivers(rings: list[np.ndarray], areas: np.ndarray, filter_mm: float) -> np.ndarray:
    """(r,) bool: the outer rings and holes in them that together are a sliver, narrower
    on average than twice the filter (``2 (A_outer - |A_hole|) / (P_outer + P_hole) <
    2 filter_mm``): below what the chord filter, which moves each ring by up to
    ``filter_mm`` on its own, can keep apart. A fuzzed part's fill level was such a pair,
    0.03 mm apart on average: filtered, the two crossed, and the next offset inward of the
    crossed pair was a ring inside the hole, 0.42 mm from the region's edge
    (``tests/data/regions/hook-part-550.npz``). areas: the rings' signed areas, mm^2."""
    sliver = np.zeros(len(rings), dtype=bool)
    if len(rings) < 2:
        return sliver
    holes = np.flatnonzero(areas < 0)
    outers = np.flatnonzero(areas > 0)
    if not len(holes) or not len(outers):
        return sliver
    # the pairs measured: a hole of at least half its outer's area (a smaller one leaves a
    # sliver only in an outer ring that is nearly one itself); then whether it is in it
    gap = areas[outers][:, None] + areas[holes][None, :]
    oi, hj = np.nonzero((gap > 0) & (gap < 0.5 * areas[outers][:, None]))
    if not len(oi):
        return sliver
    o, h = outers[oi], holes[hj]
    per = np.zeros(len(rings))
    both = np.unique(np.concatenate([o, h]))
    per[both] = ring_perimeters([rings[i] for i in both])
    thin = 2.0 * gap[oi, hj] < 2.0 * filter_mm * (per[o] + per[h])
    for i, j in zip(o[thin].tolist(), h[thin].tolist()):
        if rings_holding([rings[i]], rings[j][:1])[0] == 0:    # the hole is in that outer
            sliver[i] = sliver[j] = True
    return sliver


@njit(cache=True)
def _filtered_rings(pts: np.ndarray, starts: np.ndarray, eps: float
                    ) -> tuple:  # pragma: no cover - compiled
    """:func:`simplify`'s fast path: the rings packed in ``pts, starts`` filtered by the
    chord filter within ``eps``, packed the same way, which of them are simple with at
    least 3 points, their signed areas, and the filter's keep-mask over ``pts``."""
    keep = _filter_mask(pts, starts, np.full(len(starts) - 1, eps), 64, True)
    nr = len(starts) - 1
    cut = np.zeros(nr + 1, dtype=np.int64)
    for r in range(nr):
        c = 0
        for i in range(starts[r], starts[r + 1]):
            if keep[i]:
                c += 1
        cut[r + 1] = cut[r] + c
    kept = np.empty((cut[nr], 2))
    k = 0
    for i in range(len(pts)):
        if keep[i]:
            kept[k, 0] = pts[i, 0]
            kept[k, 1] = pts[i, 1]
            k += 1
    ok = _simple_mask(kept, cut, True)
    for r in range(nr):
        if cut[r + 1] - cut[r] < 3:
            ok[r] = False
    return kept, cut, ok, _packed_areas(kept, cut), keep


#: Grid spacing of :func:`smooth_rings` (mm): a tenth of its usual window.
SMOOTH_SPACING_MM = 0.5


def smooth_rings(rings: Rings, tol_mm: float, sigma_mm: float, max_turn_deg: float = 60.0
                 ) -> tuple[Rings, float]:
    """Closed rings smoothed within ``tol_mm``: the scan noise of a sliced mesh taken off
    the paths that follow them, corners kept.

    The ring is resampled every ~``SMOOTH_SPACING_MM`` and fitted by the same local
    quadratic regression as the motion stage's smoothing (:func:`icefab._smooth.smooth_pieces`,
    thesis 4.1.1), with a window of half-width ``3 sigma_mm`` that runs round the ring
    (no fixed start point) and narrows where the ring turns by more than ``max_turn_deg``
    within it (a corner stays a corner). Every displacement is scaled down to at most
    ``tol_mm``, smoothly along the ring. The result is the ring's own vertices and the grid
    points, moved, put on Clipper's grid (``1 / SCALE``) and filtered by
    ``min(tol_mm / 5, 0.01)`` (the smoothing itself gets the rest of the tolerance): every
    point of the result is within ``tol_mm`` of the input ring, and so is every chord (the
    points of one chord lie on one input segment).

    Why: a jerk-limited robot slows down for noise, not for length. A ring of a 300 mm
    scan with 0.05 mm vertex noise changes curvature every few millimetres, which caps the
    speed at ~40 mm/s under a 4 000 mm/s^3 jerk bound (BENCHMARKS.md, issue 15).

    Orientation is kept. Rings shorter than 8 grid steps, and rings whose smoothed form is
    not simple (a neck narrower than twice the tolerance), come back unchanged; so does
    every ring when ``tol_mm`` is at most two grid steps.

    Returns (the rings, ``reach`` mm): how far the area the input rings bound reaches
    outside the area the smoothed ones bound, i.e. the largest move of a point into that
    area (icefab's orientation: the area lies left of every ring), plus the filter's and
    the grid's part; 0 when nothing moved inward. Growing the smoothed area by ``reach``
    covers the input's.
    """
    out, reach, _inward = smooth_rings_moved(rings, tol_mm, sigma_mm, max_turn_deg)
    return out, reach


def smooth_rings_moved(rings: Rings, tol_mm: float, sigma_mm: float,
                       max_turn_deg: float = 60.0) -> tuple[Rings, float, list[np.ndarray]]:
    """:func:`smooth_rings`, and how far each point of each ring moved into the area
    (mm, (k,) per ring: the whole length of its move if it moved into it, else 0; zeros
    for a ring that came back unchanged). "Into" is judged against the input segments
    the point lay on: a point that slid along the ring past a vertex may end up inside
    with no move counted (in tests: 1 point in 100 at most, by up to 0.06 x ``tol_mm``
    over 300 random rings, 0.29 x on one jagged by 0.16 mm at every vertex)."""
    rings = [np.asarray(r, dtype=np.float64) for r in rings]
    still = [np.zeros(len(r)) for r in rings]
    if not tol_mm > 2.0 / SCALE or not rings:
        # within the grid nothing can move (the cap below would be negative: it turned
        # rings inside out)
        return list(rings), 0.0, still
    eps = min(tol_mm / 5.0, 0.01)
    work = [i for i, r in enumerate(rings) if len(r) >= 3]
    if not work:
        return list(rings), 0.0, still
    pts, starts = _pack([rings[i] for i in work])
    # rings shorter than 8 grid steps get no grid (empty pieces) and stay as they are
    gstart, graw, h, fstart, fu, fraw, own = _smooth.periodic_pieces(
        pts, starts, SMOOTH_SPACING_MM, 3.0 * sigma_mm, 8, 8.0 * SMOOTH_SPACING_MM)
    moved = _smooth.smooth_pieces(gstart, graw, h, fstart, fu, fraw,
                                  sigma_mm / SMOOTH_SPACING_MM, tol_mm - eps - 1.0 / SCALE,
                                  np.radians(max_turn_deg))
    moved, cut, reach_of, inward = _smooth.collect_rings(moved, fraw, fstart, own)
    # on Clipper's grid, as every other ring: coordinates that are whole multiples of
    # 1 / SCALE compress (a toolpath file of smoothed rings took twice the bytes)
    moved = np.round(moved * SCALE) / SCALE
    thinned, tcut, used, _areas, keep = _filtered_rings(moved, cut, float(eps))
    inward = inward[keep]
    out = list(rings)
    for k in np.flatnonzero(used):
        a, b = tcut[k], tcut[k + 1]
        out[work[k]] = thinned[a:b]
        still[work[k]] = inward[a:b]
    reach = float(reach_of[used].max()) if used.any() else 0.0
    return out, (reach + eps + 1.0 / SCALE if reach > 1e-6 else 0.0), still


def _simplify_slow(ring: np.ndarray, filter_mm: float) -> Rings:
    """The rings one ring becomes when its filtered form is not simple: it is cut at the
    vertices where it touches itself, each loop is filtered, and loops whose filtered form
    still crosses itself keep all their points."""
    out: Rings = []
    for loop in _split_touching(ring):
        if abs(signed_area(loop)) <= MIN_RING_AREA:
            continue
        loop, starts = _pack([loop])
        kept = loop[_chord_keep(loop, starts, float(filter_mm), closed=True)]
        if len(kept) >= 3 and simple_mask([kept])[0]:
            out.append(kept)
        else:
            out.append(loop)
    return out


def offset_rings(rings: Rings, d: float, filter_mm: float = FILTER_MM) -> Rings:
    """Offset closed rings by ``d`` mm (positive outward), flat ring list out.

    The fast form for repeated offsets (fill rings): no nesting tree is built. Output
    orientation follows the icefab convention (outer CCW, holes CW). Filtered within
    ``filter_mm``, less the slivers the filter cannot keep apart (:func:`simplify`).
    """
    if not rings:
        return []
    if d == 0:
        return list(rings)
    o = _offsetter()
    o.addPaths(without_orphan_holes(rings), pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
    out = o.execute(float(d))
    return simplify(list(out), filter_mm, slivers=True)


def without_orphan_holes(rings: Rings) -> Rings:
    """The rings less the holes (clockwise rings) that no outer ring of the list holds.

    Why: Clipper's offset takes the orientation of a whole set from the ring with its
    lowest point. A stray clockwise sliver lowest of all (a bunny layer's fill level had
    one of 0.02 mm^2, left by the offset of the level before) turns the set inside out, and
    the next fill level came back empty: 730 mm^2 of the layer went unfilled."""
    rings = list(rings)
    if len(rings) < 2:
        # a lone clockwise ring is an orphan too: offset, Clipper made it a square
        # 1.8e15 mm wide (a fill level smoothed within less than the grid was one)
        return [r for r in rings if signed_area(r) >= 0]
    areas = ring_areas(rings)
    holes = np.flatnonzero(areas < 0)
    outers = np.flatnonzero(areas > 0)
    if not len(holes):
        return rings
    held = np.zeros(len(holes), dtype=bool)
    if len(outers):
        held = rings_holding([rings[i] for i in outers],
                             np.array([rings[i][0] for i in holes])) >= 0
    if held.all():
        return rings
    drop = set(holes[~held].tolist())
    return [r for i, r in enumerate(rings) if i not in drop]


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


def sweep_rings(paths: Sequence[tuple[np.ndarray, bool, float | np.ndarray]],
                grow: float = 0.0) -> Rings:
    """The bands paths sweep with their width (+ ``2 grow``), as flat oriented rings: the
    bands of equal width and kind are united, different ones may overlap (use them as the
    clip side of a NonZero Boolean). Mitred corners, round ends of open paths (the bead
    where the tool stops); a variable-width path (:func:`variable_sweep_rings`) has round
    joins.

    paths: (points (k, 2) float64 mm, closed, width mm or (k,) one per point) triples.
    """
    by_width: dict[tuple[float, bool], list[np.ndarray]] = {}
    variable = []
    for pts, closed, width in paths:
        if np.ndim(width):
            variable.append((pts, closed, width))
        elif width > 0 and len(pts) >= 2:
            by_width.setdefault((float(width), bool(closed)), []).append(pts)
    out: Rings = variable_sweep_rings(variable, grow) if variable else []
    for (width, closed), pts in by_width.items():
        o = _offsetter()
        o.addPaths(pts, pyclipr.JoinType.Miter,
                   pyclipr.EndType.Joined if closed else pyclipr.EndType.Round)
        out.extend(o.execute(width / 2.0 + grow))
    return out


#: Sides of the polygon inscribed in the disk a variable-width path sweeps at each of its
#: points (its area is 0.6 % short of the disk's: the sweep is never overestimated).
DISK_SIDES = 32
#: Pieces of a disk (:func:`_disk_pieces`) smaller than this are left out, mm^2.
_MIN_PIECE_MM2 = 1e-6
#: How far a piece of a disk reaches into the quadrilaterals beside it, mm (ten of
#: Clipper's grid units; the piece stays inside its disk).
_PIECE_OVERLAP_MM = 1e-3


def variable_sweep_rings(paths: Sequence[tuple[np.ndarray, bool, np.ndarray]],
                         grow: float = 0.0) -> Rings:
    """The bands variable-width paths sweep (+ ``2 grow``), as flat counter-clockwise
    rings that overlap (the clip side of a NonZero Boolean): the convex hull of the disks
    of consecutive points (radius half the width), as per segment the quadrilateral
    between the disks' outer common tangents and, at every point, what of its disk
    (inscribed ``DISK_SIDES``-gon) those quadrilaterals leave (:func:`_disk_pieces`).

    Where one disk holds the other a segment has no quadrilateral and both disks stay
    whole on its side. A full disk at every point gives the same union, but each overlaps
    its neighbours' in dozens of crossings: on the bunny the Boolean that subtracts the
    sweep of the gap fill's centre lines took twice as long (BENCHMARKS.md, issue 17).

    paths: (points (k, 2) float64 mm, closed, widths (k,) mm) triples.
    """
    polys, radii = [], []
    for pts, closed, w in paths:
        if len(pts) == 0:
            continue
        polys.append(closed_polyline(np.asarray(pts, np.float64), closed))
        radii.append(closed_polyline(np.asarray(w, np.float64), closed) / 2.0 + grow)
    if not polys:
        return []
    P, starts = _pack(polys)
    r = np.concatenate(radii)
    inner = np.ones(len(P) - 1, dtype=bool)
    inner[starts[1:-1] - 1] = False               # from one path to the next
    d = P[1:] - P[:-1]
    L = np.hypot(d[:, 0], d[:, 1])
    use = inner & (L > np.abs(r[:-1] - r[1:])) & (r[:-1] > 0) & (r[1:] > 0)
    t = np.zeros_like(d)
    t[use] = d[use] / L[use, None]
    sin_b = np.zeros(len(L))
    sin_b[use] = (r[:-1] - r[1:])[use] / L[use]
    ang = 2.0 * np.pi * np.arange(DISK_SIDES) / DISK_SIDES
    circle = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    verts, vstarts = _disk_pieces(P, r, t, sin_b, use, circle)
    pieces = split_rows(verts, vstarts[1:-1])
    # the quadrilaterals between the disks' outer common tangents
    a, b, ra, rb = P[:-1][use], P[1:][use], r[:-1][use, None], r[1:][use, None]
    t, sb = t[use], sin_b[use][:, None]
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)     # left of a -> b
    cos_b = np.sqrt(1.0 - sb ** 2)
    left, right = n * cos_b + t * sb, -n * cos_b + t * sb   # unit, to the tangents
    quads = np.stack([a + right * ra, b + right * rb, b + left * rb, a + left * ra], axis=1)
    return [q for q in pieces if len(q) >= 3] + list(quads)


@njit(cache=True)
def _disk_pieces(P: np.ndarray, r: np.ndarray, t: np.ndarray, sin_b: np.ndarray,
                 use: np.ndarray, circle: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """What of the disk at every point the tangent quadrilaterals of its two segments
    leave: the inscribed polygon (``circle`` scaled by r) clipped to the half-planes
    beyond the chord where the incoming segment's quadrilateral ends, ``(p - b) . t_in
    >= r sin_in``, and behind the chord where the outgoing one's starts, ``(p - b) .
    t_out <= r sin_out`` (the chords between a disk's tangent points are perpendicular
    to the segment). A side without a quadrilateral (path end, one disk holding the
    other) clips nothing. Returns the pieces' vertices (counter-clockwise) and their
    start indices (n + 1,); an empty piece (or one under ``_MIN_PIECE_MM2``) has none."""
    n = P.shape[0]
    ns = circle.shape[0]
    out = np.empty((n * (ns + 4), 2))
    starts = np.zeros(n + 1, dtype=np.int64)
    buf = np.empty((ns + 4, 2))
    nxt = np.empty((ns + 4, 2))
    k = 0
    for i in range(n):
        bx, by, rr = P[i, 0], P[i, 1], r[i]
        m = 0
        if rr > 0.0:
            for j in range(ns):
                buf[m, 0] = bx + rr * circle[j, 0]
                buf[m, 1] = by + rr * circle[j, 1]
                m += 1
        for side in range(2):
            if m < 3:
                break
            # each piece reaches _PIECE_OVERLAP_MM into the quadrilateral it abuts: on
            # Clipper's grid, edges that only meet leave hairline slivers
            if side == 0:
                if i == 0 or not use[i - 1]:
                    continue
                ux, uy, c = t[i - 1, 0], t[i - 1, 1], rr * sin_b[i - 1] - _PIECE_OVERLAP_MM
            else:
                if i == n - 1 or not use[i]:
                    continue
                # behind the outgoing chord: -(p - b) . t_out >= -r sin_out
                ux, uy, c = -t[i, 0], -t[i, 1], -rr * sin_b[i] - _PIECE_OVERLAP_MM
            q = 0
            for j in range(m):
                jn = j + 1 if j + 1 < m else 0
                da = (buf[j, 0] - bx) * ux + (buf[j, 1] - by) * uy - c
                db = (buf[jn, 0] - bx) * ux + (buf[jn, 1] - by) * uy - c
                if da >= 0.0:
                    nxt[q, 0] = buf[j, 0]
                    nxt[q, 1] = buf[j, 1]
                    q += 1
                if (da > 0.0 and db < 0.0) or (da < 0.0 and db > 0.0):
                    f = da / (da - db)
                    nxt[q, 0] = buf[j, 0] + f * (buf[jn, 0] - buf[j, 0])
                    nxt[q, 1] = buf[j, 1] + f * (buf[jn, 1] - buf[j, 1])
                    q += 1
            for j in range(q):
                buf[j, 0] = nxt[j, 0]
                buf[j, 1] = nxt[j, 1]
            m = q
        area = 0.0
        for j in range(m):
            jn = j + 1 if j + 1 < m else 0
            area += buf[j, 0] * buf[jn, 1] - buf[jn, 0] * buf[j, 1]
        # slivers where the two chords nearly meet add nothing and only upset Booleans
        if m >= 3 and area > 2.0 * _MIN_PIECE_MM2:
            for j in range(m):
                out[k, 0] = buf[j, 0]
                out[k, 1] = buf[j, 1]
                k += 1
        starts[i + 1] = k
    return out[:k], starts


def level_bands(levels: Sequence[tuple[Sequence[np.ndarray], float]
                                | tuple[Sequence[np.ndarray], float, Sequence[np.ndarray]]]
                ) -> Rings:
    """Bands swept by the rings of offset levels: for each level (oriented rings bounding
    an area D, half-width h, optionally rings bounding an area E the band's outer edge
    holds too: widened beads) the rings of ``expand(D + E, h)`` plus the reversed rings
    of ``shrink(D, h)``, whose NonZero winding is 1 exactly in the band. Use them as the
    clip side of a NonZero Boolean (bands of different levels may touch or overlap)."""
    out: Rings = []
    for outer, inner in _level_edges(levels):
        out.extend(outer)
        out.extend(np.ascontiguousarray(r[::-1]) for r in inner)
    return out


def _level_edges(levels: Sequence[tuple]) -> list[tuple[list[np.ndarray], list[np.ndarray]]]:
    """Per non-empty level of :func:`level_bands`: the rings of ``expand(D + E, h)`` and
    of ``shrink(D, h)``, as Clipper orients them."""
    out = []
    for level in levels:
        rings, h = level[0], level[1]
        if not len(rings):
            continue
        rings = without_orphan_holes(rings)
        also = without_orphan_holes(level[2]) if len(level) > 2 else []
        o = _offsetter()
        # one offset of both sets: Clipper unites what it offsets (D and E overlap)
        o.addPaths(rings + also, pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
        grown = list(o.execute(h))
        o = _offsetter()
        o.addPaths(rings, pyclipr.JoinType.Miter, pyclipr.EndType.Polygon)
        out.append((grown, list(o.execute(-h))))
    return out


def level_gaps(area: Region | Sequence[np.ndarray],
               levels: Sequence[tuple[Sequence[np.ndarray], float]
                                | tuple[Sequence[np.ndarray], float, Sequence[np.ndarray]]]
               ) -> Rings:
    """``area`` less the bands of nested ring levels (:func:`level_bands`' levels, outermost
    first), level by level: what of ``area`` lies outside the first band's outer edge, what
    lies between each band's inner edge and the next band's outer edge, and what lies
    inside the last band. Flat oriented rings, as :func:`difference_rings`.

    Equal to ``difference_rings(area, level_bands(levels))`` when the levels nest: every
    level's outer edge ``expand(D + E, h)`` lies within the one before's, and so does its
    inner edge ``shrink(D, h)`` (then no band reaches between two others). Offset rings
    do; :func:`icefab.paths.material_paths` checks the settings under which its levels
    do (``_levels_nest``). Why: one Boolean of every band at once keeps the edges of all
    levels in its sweep line together (a bunny layer has 20-50 levels); level by level,
    offsets included, it takes 37 % less CPU on 120 bunny layers (6 % of ``plan_layer``),
    the same unfilled area to 2e-5 mm^2 a layer (BENCHMARKS.md, issue 15)."""
    edges = _level_edges(levels)
    if not edges:
        return [np.asarray(r, dtype=np.float64) for r in rings_of(area)]
    out = difference_rings(area, edges[0][0])
    for (_outer, inner), (outer, _inner) in zip(edges[:-1], edges[1:]):
        out += difference_rings(inner, outer)
    return out + [np.asarray(r, dtype=np.float64) for r in edges[-1][1] if len(r) >= 3]


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
def _in_ring(pts: np.ndarray, s0: int, e0: int, x: float, y: float
             ) -> bool:  # pragma: no cover - compiled
    """Even-odd crossing test of the point (x, y) against the ring pts[s0:e0]."""
    inside = False
    j = e0 - 1
    for i in range(s0, e0):
        yi = pts[i, 1]
        yj = pts[j, 1]
        if (yi > y) != (yj > y):
            xc = pts[i, 0] + (y - yi) * (pts[j, 0] - pts[i, 0]) / (yj - yi)
            if x < xc:
                inside = not inside
        j = i
    return inside


def points_inside(points: np.ndarray, region: Region | Sequence[np.ndarray]) -> np.ndarray:
    """(n,) bool: which points (n, 2) mm lie inside the region (even-odd rule over its
    properly nested rings; points on an edge may go either way)."""
    rings = rings_of(region)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not rings or not len(pts):
        return np.zeros(len(pts), dtype=bool)
    return _even_odd_rows(np.ascontiguousarray(pts[:, 0]), np.ascontiguousarray(pts[:, 1]),
                          *_pack(rings))


@njit(cache=True)
def _even_odd_rows(px: np.ndarray, py: np.ndarray, pts: np.ndarray, starts: np.ndarray
                   ) -> np.ndarray:  # pragma: no cover - compiled
    """Even-odd crossing test of points (px, py) against all ring edges, the edges
    bucketed into horizontal rows so each point is only tested against the edges whose
    y-range may hold it."""
    ne = len(pts)
    out = np.zeros(len(px), dtype=np.bool_)
    if ne == 0:
        return out
    y0 = pts[:, 1].min()
    y1 = pts[:, 1].max()
    nrow = max(1, int(np.sqrt(ne)))
    h = (y1 - y0) / nrow if y1 > y0 else 1.0
    ea = np.empty(ne, dtype=np.int64)  # edge i runs from point ea[i] to point eb[i]
    eb = np.empty(ne, dtype=np.int64)
    k = 0
    for r in range(len(starts) - 1):
        s0 = starts[r]
        n = starts[r + 1] - s0
        for i in range(n):
            ea[k] = s0 + i
            eb[k] = s0 + (i + 1) % n
            k += 1
    r0 = np.empty(ne, dtype=np.int64)
    r1 = np.empty(ne, dtype=np.int64)
    count = np.zeros(nrow + 1, dtype=np.int64)
    for i in range(ne):
        lo = min(pts[ea[i], 1], pts[eb[i], 1])
        hi = max(pts[ea[i], 1], pts[eb[i], 1])
        r0[i] = min(nrow - 1, max(0, int((lo - y0) / h)))
        r1[i] = min(nrow - 1, max(0, int((hi - y0) / h)))
        for r in range(r0[i], r1[i] + 1):
            count[r + 1] += 1
    for r in range(nrow):
        count[r + 1] += count[r]
    fill = count[:-1].copy()
    bucket = np.empty(count[nrow], dtype=np.int64)
    for i in range(ne):
        for r in range(r0[i], r1[i] + 1):
            bucket[fill[r]] = i
            fill[r] += 1
    for k in range(len(px)):
        x = px[k]
        y = py[k]
        if y < y0 or y > y1:
            continue
        r = min(nrow - 1, max(0, int((y - y0) / h)))
        inside = False
        for q in range(count[r], count[r + 1]):
            i = bucket[q]
            yi = pts[ea[i], 1]
            yj = pts[eb[i], 1]
            if (yi > y) != (yj > y):
                xc = pts[ea[i], 0] + (y - yi) * (pts[eb[i], 0] - pts[ea[i], 0]) / (yj - yi)
                if x < xc:
                    inside = not inside
        out[k] = inside
    return out


def simplify_open(lines: Sequence[np.ndarray], filter_mm: float | np.ndarray = FILTER_MM
                  ) -> list[np.ndarray]:
    """Open polylines with the points dropped that lie within ``filter_mm`` (one value,
    or one per polyline) of the chord kept over them (the end points stay); a polyline
    whose filtered form would cross itself keeps all its points."""
    lines = [np.asarray(ln, dtype=np.float64) for ln in lines]
    return [ln[k] for ln, k in zip(lines, simplify_masks(lines, filter_mm))]


def simplify_masks(lines: Sequence[np.ndarray], filter_mm: float | np.ndarray = FILTER_MM,
                   closed: bool = False) -> list[np.ndarray]:
    """The points :func:`simplify_open` keeps, as one (k,) bool mask per polyline (to
    carry values the points hold, e.g. widths, along); ``closed``: the lines are rings
    (first point not repeated), their closing edge filtered too and their filtered form
    checked as a ring."""
    lines = [np.asarray(ln, dtype=np.float64) for ln in lines]
    if not lines:
        return []
    pts, starts = _pack(lines)
    keep = _chord_keep(pts, starts, filter_mm, closed=closed)
    masks = [keep[a:b] for a, b in zip(starts[:-1], starts[1:])]
    ok = simple_mask([ln[m] for ln, m in zip(lines, masks)], closed=closed)
    return [m if k else np.ones(len(m), dtype=bool) for m, k in zip(masks, ok)]


# --------------------------------------------------------------------------- medial axis


@njit(cache=True)
def _chains(n: int, ea: np.ndarray, eb: np.ndarray):  # pragma: no cover - compiled
    """Split a graph (vertices 0..n-1, edges ea[i]-eb[i]) into chains: maximal paths
    whose inner vertices have degree 2, and cycles of degree-2 vertices.

    Returns (vertex indices concatenated, chain starts (c+1,), closed flags (c,)); a
    closed chain does not repeat its first vertex.
    """
    m = len(ea)
    deg = np.zeros(n, dtype=np.int64)
    for i in range(m):
        deg[ea[i]] += 1
        deg[eb[i]] += 1
    off = np.zeros(n + 1, dtype=np.int64)
    for v in range(n):
        off[v + 1] = off[v] + deg[v]
    fill = off[:-1].copy()
    nbr = np.empty(2 * m, dtype=np.int64)
    eid = np.empty(2 * m, dtype=np.int64)
    for i in range(m):
        a, b = ea[i], eb[i]
        nbr[fill[a]] = b
        eid[fill[a]] = i
        fill[a] += 1
        nbr[fill[b]] = a
        eid[fill[b]] = i
        fill[b] += 1
    used = np.zeros(m, dtype=np.bool_)
    verts = np.empty(2 * m + 1, dtype=np.int64)
    starts = np.zeros(m + 1, dtype=np.int64)
    closed = np.zeros(m, dtype=np.bool_)
    nv = 0
    nc = 0
    for phase in range(2):
        for v0 in range(n):
            if deg[v0] == 0 or (phase == 0 and deg[v0] == 2):
                continue
            for q0 in range(off[v0], off[v0 + 1]):
                if used[eid[q0]]:
                    continue
                starts[nc] = nv
                verts[nv] = v0
                nv += 1
                q = q0
                while True:
                    used[eid[q]] = True
                    v = nbr[q]
                    if phase == 1 and v == v0:
                        break
                    verts[nv] = v
                    nv += 1
                    if deg[v] != 2:
                        break
                    nxt = -1
                    for q2 in range(off[v], off[v + 1]):
                        if not used[eid[q2]]:
                            nxt = q2
                            break
                    if nxt < 0:
                        break
                    q = nxt
                closed[nc] = phase == 1
                nc += 1
                starts[nc] = nv
    return verts[:nv], starts[:nc + 1], closed[:nc]


@njit(cache=True)
def _record_run(ints: np.ndarray, floats: np.ndarray, whole: np.ndarray, k: int, c: int,
                first: int, last: int, lo: float, mean: float, hi: float, is_whole: bool
                ) -> int:  # pragma: no cover - compiled
    """Store run k of :func:`_width_runs` (chain, first and last vertex; smallest, mean
    and largest width; whole closed chain) and return k + 1."""
    ints[k, 0] = c
    ints[k, 1] = first
    ints[k, 2] = last
    floats[k, 0] = lo
    floats[k, 1] = mean
    floats[k, 2] = hi
    whole[k] = is_whole
    return k + 1


@njit(cache=True)
def _width_runs(pts: np.ndarray, w: np.ndarray, starts: np.ndarray, closed: np.ndarray,
                ratio: float, min_length: float):  # pragma: no cover - compiled
    """Cut chains into runs of similar width (see :func:`width_runs`).

    Returns per run: (chain index, first and last vertex) (r, 3) int64 (vertices local to
    the chain; for a cut closed chain the last may be n, meaning its first vertex again),
    (smallest, length-weighted mean, largest width) (r, 3) float64, and whether the run is
    a whole closed chain (r,) bool.
    """
    cap = len(w) + len(starts)
    ints = np.empty((cap, 3), dtype=np.int64)
    floats = np.empty((cap, 3))
    whole = np.zeros(cap, dtype=np.bool_)
    k = 0
    for c in range(len(starts) - 1):
        s0 = starts[c]
        n = starts[c + 1] - s0
        if n < 2:
            continue
        m = n + 1 if closed[c] else n
        if closed[c]:  # a closed chain whose widths all agree stays whole
            lo = w[s0]
            hi = w[s0]
            sw = 0.0
            sl = 0.0
            for i in range(1, m):
                p = s0 + ((i - 1) % n)
                q = s0 + (i % n)
                d = np.sqrt((pts[q, 0] - pts[p, 0]) ** 2 + (pts[q, 1] - pts[p, 1]) ** 2)
                sw += 0.5 * (w[p] + w[q]) * d
                sl += d
                lo = min(lo, w[q])
                hi = max(hi, w[q])
            if hi <= ratio * lo:
                k = _record_run(ints, floats, whole, k, c, 0, n - 1, lo,
                                sw / sl if sl > 0 else lo, hi, True)
                continue
        # a run takes vertices while its widths stay within the ratio, but is never cut
        # shorter than ``min_length`` (a tapering corner would give many tiny runs); the
        # vertex a run shares with the previous one counts for its smallest width (a
        # bead ends there) but not for the ratio
        a = 0
        lo = w[s0]
        hi = w[s0]
        shared = w[s0]
        sw = 0.0
        sl = 0.0
        for i in range(1, m):
            p = s0 + ((i - 1) % n)
            q = s0 + (i % n)
            wi = w[q]
            if max(hi, wi) > ratio * min(lo, wi) and sl >= min_length:
                k = _record_run(ints, floats, whole, k, c, a, i - 1, min(lo, shared),
                                sw / sl if sl > 0 else lo, hi, False)
                a = i - 1
                shared = w[p]
                lo = np.inf
                hi = 0.0
                sw = 0.0
                sl = 0.0
            d = np.sqrt((pts[q, 0] - pts[p, 0]) ** 2 + (pts[q, 1] - pts[p, 1]) ** 2)
            sw += 0.5 * (w[p] + wi) * d
            sl += d
            lo = min(lo, wi)
            hi = max(hi, wi)
        k = _record_run(ints, floats, whole, k, c, a, m - 1, min(lo, shared),
                        sw / sl if sl > 0 else lo, hi, False)
    return ints[:k], floats[:k], whole[:k]


def width_runs(chains: Sequence[tuple[np.ndarray, np.ndarray, bool]], ratio: float,
               min_length: float = 0.0
               ) -> list[tuple[np.ndarray, tuple[float, float, float], bool]]:
    """Cut width-carrying polylines into runs of similar width.

    chains: ``(points (k, 2) mm, width (k,) mm, closed)``, e.g. :func:`medial_axis` chains
        with twice the clearance as width.
    ratio: within a run the largest width is at most ``ratio`` (> 1) times the smallest,
        unless the run is not yet ``min_length`` (mm) long (a run is never cut shorter).
    Returns ``(points, (smallest, length-weighted mean, largest width), closed)`` runs:
    consecutive runs of a chain share their end vertex (it counts for the smallest width
    of both, for the ratio and the largest of the first only); a closed chain whose widths all
    agree stays closed, any other closed chain is cut into open runs, the last of which
    comes back to its first vertex.
    """
    chains = [c for c in chains if len(c[0]) >= 2]
    if not chains:
        return []
    w = np.concatenate([np.asarray(c[1], dtype=np.float64) for c in chains])
    closed = np.array([bool(c[2]) for c in chains])
    pts, starts = _pack([c[0] for c in chains])
    ints, floats, whole_chain = _width_runs(pts, w, starts, closed, float(ratio),
                                            float(min_length))
    out = []
    for (c, a, b), (lo, mean, hi), whole in zip(ints, floats, whole_chain):
        pts = chains[c][0]
        widths = (float(lo), float(mean), float(hi))
        if whole:
            out.append((pts, widths, True))
        elif b < len(pts):
            out.append((pts[a:b + 1], widths, False))
        else:
            out.append((np.vstack([pts[a:], pts[:1]]), widths, False))
    return out


class RingEdges:
    """The edges of flat rings for nearest-edge queries: sampled every ``spacing`` mm
    (:func:`_sample_rings`) and the samples indexed (``scipy.spatial.cKDTree``) once per
    spacing, for the many queries of one region (:func:`segment_clearances`,
    :func:`distance_to_rings`, :func:`segments_to_rings_distance` take it in place of the
    rings; each built both anew on every call: 6 % of the paths stage on bunny layers)."""

    def __init__(self, rings: Sequence[np.ndarray]) -> None:
        self.rings = [np.asarray(r, dtype=np.float64) for r in rings if len(r) >= 2]
        self._sampled: dict[float, tuple] = {}

    def sampled(self, spacing: float) -> tuple[tuple, object]:
        """(the samples as :func:`_sample_rings` returns them, their KD-tree)."""
        got = self._sampled.get(spacing)
        if got is None:
            from scipy.spatial import cKDTree

            samples = _sample_rings(self.rings, spacing)
            got = self._sampled[spacing] = (samples, cKDTree(samples[0]))
        return got


def ring_edges(rings: Sequence[np.ndarray] | RingEdges) -> RingEdges:
    """``rings`` as :class:`RingEdges` (itself when it is one)."""
    return rings if isinstance(rings, RingEdges) else RingEdges(rings)


def segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n,) distances of points p (n, 2) to segments a-b (n, 2 each), mm."""
    d = b - a
    L2 = np.einsum("ij,ij->i", d, d)
    t = np.einsum("ij,ij->i", p - a, d) / np.where(L2 > 0, L2, 1.0)
    t = np.clip(t, 0.0, 1.0)
    e = p - (a + t[:, None] * d)
    return np.sqrt(np.einsum("ij,ij->i", e, e))


@njit(cache=True)
def _pair_distances(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray
                    ) -> np.ndarray:  # pragma: no cover - compiled
    """(n,) distances between the segments ``a[i]-b[i]`` and ``c[i]-d[i]`` ((n, 2) each,
    mm): 0 where they cross or touch, else the least distance of an end of one to the
    other (where a segment-to-segment distance lies when they do not cross)."""
    out = np.empty(len(a))
    for i in range(len(a)):
        ax, ay, bx, by = a[i, 0], a[i, 1], b[i, 0], b[i, 1]
        cx, cy, dx, dy = c[i, 0], c[i, 1], d[i, 0], d[i, 1]
        ux, uy, vx, vy = bx - ax, by - ay, dx - cx, dy - cy
        o1 = ux * (cy - ay) - uy * (cx - ax)
        o2 = ux * (dy - ay) - uy * (dx - ax)
        o3 = vx * (ay - cy) - vy * (ax - cx)
        o4 = vx * (by - cy) - vy * (bx - cx)
        if (o1 * o2 <= 0.0 and o3 * o4 <= 0.0 and (o1 != 0.0 or o2 != 0.0)
                and (o3 != 0.0 or o4 != 0.0)):
            out[i] = 0.0
            continue
        best = min(_seg_dist2(cx - ax, cy - ay, ux, uy), _seg_dist2(dx - ax, dy - ay, ux, uy),
                   _seg_dist2(ax - cx, ay - cy, vx, vy), _seg_dist2(bx - cx, by - cy, vx, vy))
        out[i] = math.sqrt(best)
    return out


def segments_to_rings_distance(a: np.ndarray, b: np.ndarray,
                               rings: Sequence[np.ndarray] | RingEdges,
                               upper: float | np.ndarray, spacing: float = 1.0
                               ) -> np.ndarray:
    """(n,) float64: the exact distance (mm) of the segments ``a[i] -> b[i]`` ((n, 2) each)
    to the edges of ``rings``, 0 where an edge crosses one; ``inf`` where no edge comes
    within ``upper`` (mm, one for all or (n,) one per segment: the less, the cheaper).
    The edges are sampled every ``spacing`` mm to find the ones near each segment (any
    edge within ``upper`` of a segment has a sample within ``upper + spacing / 2`` of the
    segment, so within that plus half its length of its middle)."""
    a = np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 2)
    b = np.ascontiguousarray(b, dtype=np.float64).reshape(-1, 2)
    upper = np.broadcast_to(np.asarray(upper, dtype=np.float64), (len(a),))
    out = np.full(len(a), np.inf)
    edges = ring_edges(rings)
    if not edges.rings or not len(a):
        return out
    (P, edge, ea, eb, prv, _ring, _arc, _len), tree = edges.sampled(spacing)
    near = tree.query_ball_point(
        (a + b) / 2.0, np.hypot(*(b - a).T) / 2.0 + upper + spacing / 2.0)
    counts = np.fromiter((len(c) for c in near), np.int64, len(near))
    if not counts.any():
        return out
    which = np.repeat(np.arange(len(a)), counts)
    ids = np.fromiter(itertools.chain.from_iterable(near), np.int64, int(counts.sum()))
    e = edge[ids]
    # a vertex is a sample of the edge it starts and the end of the one before: that
    # edge's last stretch lies nearer it than to its own last sample (a hypothesis case:
    # a segment crossing a ring's closing edge 0.2 mm from its end, found 0.03 mm away)
    at_vertex = np.flatnonzero((P[ids] == ea[e]).all(axis=1))
    which = np.concatenate([which, which[at_vertex]])
    e = np.concatenate([e, prv[e[at_vertex]]])
    # each (segment, edge) pair once (the samples of one edge come in a row)
    pair = np.unique(which * len(ea) + e)
    which, e = pair // len(ea), pair % len(ea)
    dist = _pair_distances(a[which], b[which], np.ascontiguousarray(ea[e]),
                           np.ascontiguousarray(eb[e]))
    np.minimum.at(out, which, dist)
    out[out > upper] = np.inf
    return out


def segment_clearances(a: np.ndarray, b: np.ndarray, rings: Sequence[np.ndarray] | RingEdges,
                       upper: float) -> np.ndarray:
    """(n,) float64: how far (mm) each segment ``a[i] -> b[i]`` ((n, 2) each) keeps from
    the edges of ``rings``: the least distance of its points a quarter millimetre apart
    (:func:`distance_to_rings`), or its exact distance
    (:func:`segments_to_rings_distance`, 0 where an edge crosses it) where that is less
    by more than rounding; ``inf`` where no edge comes within ``upper``. Why both: a
    segment that cuts across a spike or a concave corner of the edge passes nearer to it
    than any of its points (fuzzing found 0.2 mm gap paths crossing a spiky part's edge
    by 1-10 um with both ends 0.09 mm inside it), and the points' distance alone is what
    the paths were planned with before."""
    a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
    rings = ring_edges(rings)
    dense, i, _ = _subdivided(a, b, 0.25)
    # the dense points hold every segment's start; its end is added
    d = distance_to_rings(np.concatenate([dense, b]), rings, upper=upper)
    out = d[len(dense):].copy()
    np.minimum.at(out, i, d[:len(dense)])
    # the exact distance is less only where an edge comes nearer than that
    exact = segments_to_rings_distance(a, b, rings, np.minimum(out, upper))
    # the same distances computed in another order differ in their last bits
    return np.where(exact < out - 1e-9, exact, out)


def _subdivided(a: np.ndarray, b: np.ndarray, step: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`icefab.core.subdivide_segments` (points along the segments ``a[i] -> b[i]``,
    (n, 2) mm each, at most ``step`` mm apart), compiled: the same values to the last bit,
    in a tenth of the time (its dozen numpy calls, some 10 a bunny layer, cost 0.7 ms
    there; BENCHMARKS.md, issue 15)."""
    return _subdivide(np.ascontiguousarray(a, dtype=np.float64),
                      np.ascontiguousarray(b, dtype=np.float64), float(step))


@njit(cache=True)
def _subdivide(a: np.ndarray, b: np.ndarray, step: float
               ) -> tuple:  # pragma: no cover - compiled
    """:func:`_subdivided`'s kernel, in numpy's order of operations: each segment's length
    ``sqrt(dx^2 + dy^2)``, ``max(1, ceil(length / step))`` points at fractions ``q / n``,
    each ``a + f (b - a)``."""
    m = len(a)
    n = np.empty(m, np.int64)
    total = 0
    for s in range(m):
        dx = b[s, 0] - a[s, 0]
        dy = b[s, 1] - a[s, 1]
        k = int(math.ceil(math.sqrt(dx * dx + dy * dy) / step))
        n[s] = k if k > 1 else 1
        total += n[s]
    pts = np.empty((total, 2))
    seg = np.empty(total, np.int64)
    frac = np.empty(total)
    j = 0
    for s in range(m):
        dx = b[s, 0] - a[s, 0]
        dy = b[s, 1] - a[s, 1]
        for q in range(n[s]):
            f = q / n[s]
            pts[j, 0] = a[s, 0] + f * dx
            pts[j, 1] = a[s, 1] + f * dy
            seg[j] = s
            frac[j] = f
            j += 1
    return pts, seg, frac


def _sample_rings(rings: Sequence[np.ndarray], spacing: float):
    """Points along flat rings at most ``spacing`` apart (every vertex among them).

    Returns (samples (s, 2), edge of each sample (s,), ring vertices concatenated (v, 2),
    the end of each vertex's edge (v, 2), the previous edge of each vertex (v,), ring of
    each sample (s,), arc position of each sample on its ring (s,), ring lengths (r,)).
    """
    a, first, nxt = _wrapped(rings)
    a = np.ascontiguousarray(a)
    prv = np.empty_like(nxt)
    prv[nxt] = np.arange(len(nxt))
    b = a[nxt]
    seg = np.linalg.norm(b - a, axis=1)
    P, edge, t = _subdivided(a, b, spacing)
    ring, arc = _sample_arcs(edge, t, seg, np.ascontiguousarray(first, dtype=np.int64))
    ring_len = np.add.reduceat(seg, first)
    return P, edge, a, b, prv, ring, arc, ring_len


@njit(cache=True)
def _sample_arcs(edge: np.ndarray, t: np.ndarray, seg: np.ndarray, first: np.ndarray
                 ) -> tuple:  # pragma: no cover - compiled
    """:func:`_sample_rings`' ring (s,) int64 and arc position (s,) mm of each sample, from
    its edge and fraction along it, the edges' lengths ``seg`` (v,) mm and each ring's
    first edge ``first`` (r,): ``cum[e] - cum[first] + t seg[e]`` with ``cum`` the running
    sum of ``seg`` (numpy's order of operations, so the same values to the last bit)."""
    nv = len(seg)
    cum = np.empty(nv + 1)
    cum[0] = 0.0
    for i in range(nv):
        cum[i + 1] = cum[i] + seg[i]
    ring_of_edge = np.empty(nv, np.int64)
    for r in range(len(first)):
        end = first[r + 1] if r + 1 < len(first) else nv
        for i in range(first[r], end):
            ring_of_edge[i] = r
    ring = np.empty(len(edge), np.int64)
    arc = np.empty(len(edge))
    for j in range(len(edge)):
        e = edge[j]
        r = ring_of_edge[e]
        ring[j] = r
        arc[j] = cum[e] - cum[first[r]] + t[j] * seg[e]
    return ring, arc


def _nearest_edge_distance(q: np.ndarray, P: np.ndarray, edge: np.ndarray, a: np.ndarray,
                           b: np.ndarray, prv: np.ndarray,
                           upper: float = np.inf, tree=None) -> np.ndarray:
    """(n,) distance of points q (n, 2) to the ring edges, through the edges of their
    ``NEAR_SAMPLES`` nearest samples (exact when the samples are dense enough that the
    nearest edge point lies near one of them); points with no sample within ``upper``
    get ``inf`` (their distance exceeds ``upper`` less half the sampling). ``tree``: a
    ``cKDTree`` of ``P`` when one is at hand."""
    from scipy.spatial import cKDTree

    tree = cKDTree(P) if tree is None else tree
    k = min(NEAR_SAMPLES, len(P))
    dist, near = tree.query(q, k=k, distance_upper_bound=upper)
    near = near.reshape(len(q), -1)
    found = np.isfinite(dist.reshape(len(q), -1)[:, 0])
    out = np.full(len(q), np.inf)
    if not found.any():
        return out
    out[found] = _near_edges_distance(np.ascontiguousarray(q[found]),
                                      np.ascontiguousarray(near[found]), len(P), edge, prv,
                                      np.ascontiguousarray(a), np.ascontiguousarray(b))
    return out


@njit(cache=True)
def _near_edges_distance(q: np.ndarray, near: np.ndarray, n_samples: int, edge: np.ndarray,
                         prv: np.ndarray, a: np.ndarray, b: np.ndarray
                         ) -> np.ndarray:  # pragma: no cover - compiled
    """(n,) distance of each point q (n, 2) to the edges leaving and arriving at its
    samples ``near`` (n, k) (``n_samples``: a missing neighbour), rounded as
    :func:`segment_distance` computes it: ``_seg_dist2``'s order of operations gave other
    last bits, and some bunny paths moved."""
    out = np.full(len(q), np.inf)
    for i in range(len(q)):
        best = np.inf
        for col in range(near.shape[1]):
            s = near[i, col]
            if s >= n_samples:
                continue
            e = edge[s]
            for ed in (e, prv[e]):
                dx = b[ed, 0] - a[ed, 0]
                dy = b[ed, 1] - a[ed, 1]
                L2 = dx * dx + dy * dy
                t = ((q[i, 0] - a[ed, 0]) * dx + (q[i, 1] - a[ed, 1]) * dy) / \
                    (L2 if L2 > 0 else 1.0)
                t = min(max(t, 0.0), 1.0)
                ex = q[i, 0] - (a[ed, 0] + t * dx)
                ey = q[i, 1] - (a[ed, 1] + t * dy)
                d = math.sqrt(ex * ex + ey * ey)
                if d < best:
                    best = d
        out[i] = best
    return out


def distance_to_rings(points: np.ndarray, rings: Sequence[np.ndarray] | RingEdges,
                      spacing: float = 0.25, upper: float = np.inf) -> np.ndarray:
    """(n,) float64: distance (mm) of points (n, 2) to the nearest edge of ``rings``
    (edges are sampled every ``spacing`` mm to find the candidates); with ``upper``,
    points farther than ``upper + spacing`` from every sample get ``inf`` (cheaper)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    edges = ring_edges(rings)
    if not edges.rings or not len(pts):
        return np.full(len(pts), np.inf)
    (P, edge, a, b, prv, _ring, _arc, _len), tree = edges.sampled(spacing)
    return _nearest_edge_distance(pts, P, edge, a, b, prv, upper=upper + spacing, tree=tree)


def ring_nearest(points: np.ndarray, ring: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For points (n, 2) and one closed ring (k, 2): the arc length along the ring (from
    its first point) of the ring's point nearest each, and that distance, mm, (n,) each.
    Every pair of point and edge, compiled: for a few points, where
    :func:`distance_to_rings`' sampling of the ring would cost more than it saves."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    r = np.ascontiguousarray(ring, dtype=np.float64).reshape(-1, 2)
    if not len(r):
        return np.zeros(len(pts)), np.full(len(pts), np.inf)
    return _ring_nearest(pts, r)


@njit(cache=True)
def _ring_nearest(pts: np.ndarray, ring: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    n = len(ring)
    arc = np.empty(n + 1)
    arc[0] = 0.0
    for j in range(n):
        k = j + 1 if j + 1 < n else 0
        arc[j + 1] = arc[j] + np.hypot(ring[k, 0] - ring[j, 0], ring[k, 1] - ring[j, 1])
    at = np.empty(len(pts))
    dist = np.empty(len(pts))
    for i in range(len(pts)):
        best = np.inf
        best_at = 0.0
        for j in range(n):
            k = j + 1 if j + 1 < n else 0
            dx = ring[k, 0] - ring[j, 0]
            dy = ring[k, 1] - ring[j, 1]
            px = pts[i, 0] - ring[j, 0]
            py = pts[i, 1] - ring[j, 1]
            L2 = dx * dx + dy * dy
            t = (px * dx + py * dy) / L2 if L2 > 0.0 else 0.0
            t = min(1.0, max(0.0, t))
            ex = px - t * dx
            ey = py - t * dy
            d2 = ex * ex + ey * ey
            if d2 < best:
                best = d2
                best_at = arc[j] + t * (arc[j + 1] - arc[j])
        at[i] = best_at
        dist[i] = np.sqrt(best)
    return at, dist


def nearest_on_rings(points: np.ndarray, rings: Sequence[np.ndarray], spacing: float = 0.25
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The nearest point on ``rings``' edges to each of ``points`` (n, 2), mm: exact.

    The edges are sampled every ``spacing`` mm (every vertex among the samples). If the
    nearest sample is d0 away, the nearest edge point f is at most d0 away and a sample of
    its edge lies within ``spacing / 2`` of f, so within ``d0 + spacing / 2`` of the point:
    the edges (leaving and arriving) of every sample in that ball hold the answer. The ball
    is gathered by k-nearest queries, k doubled until it is covered.
    Returns (distance (n,), foot (n, 2), index of the foot's ring (n,)); with no rings the
    distances are ``inf``, feet NaN and rings -1.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    keep = [i for i, r in enumerate(rings) if len(r) >= 2]
    dist = np.full(len(pts), np.inf)
    foot = np.full((len(pts), 2), np.nan)
    ring = np.full(len(pts), -1, dtype=np.int64)
    if not keep or not len(pts):
        return dist, foot, ring
    from scipy.spatial import cKDTree

    P, edge, a, b, prv, _r, _arc, _len = _sample_rings(
        [np.asarray(rings[i], dtype=np.float64) for i in keep], spacing)
    ring_of_edge = np.repeat(np.asarray(keep), [len(rings[i]) for i in keep])
    tree = cKDTree(P)
    k = min(8, len(P))
    while True:
        dd, near = tree.query(pts, k=k)
        dd, near = dd.reshape(len(pts), -1), near.reshape(len(pts), -1)
        if k == len(P) or np.all(dd[:, -1] > dd[:, 0] + 0.5 * spacing + 1e-12):
            break
        k = min(2 * k, len(P))
    radius = dd[:, :1] + 0.5 * spacing + 1e-12
    for col in range(near.shape[1]):
        inside = dd[:, col] <= radius[:, 0]
        if not inside.any():
            break
        e = edge[near[:, col]]
        for ed in (e, prv[e]):
            d = b[ed] - a[ed]
            L2 = np.einsum("ij,ij->i", d, d)
            t = np.clip(np.einsum("ij,ij->i", pts - a[ed], d) / np.where(L2 > 0, L2, 1.0),
                        0.0, 1.0)
            f = a[ed] + t[:, None] * d
            fd = np.hypot(*(pts - f).T)
            better = inside & (fd < dist)
            dist[better] = fd[better]
            foot[better] = f[better]
            ring[better] = ring_of_edge[ed[better]]
    return dist, foot, ring


#: Jitter of the samples given to qhull by :func:`medial_axis`, mm.
JITTER_MM = 5e-5
#: Samples nearest a medial-axis vertex whose edges give its clearance.
NEAR_SAMPLES = 6
#: Two samples are on different sides of the area (their Voronoi edge is medial) when
#: they are this many times farther apart along their ring than across: 1.2 keeps the
#: branches into corners up to 113 degrees (1 / sin(angle / 2)).
FAR_RATIO = 1.2


#: A branch of the medial axis ending in a corner is pruned when it is shorter than this
#: many times its junction's width (twice the clearance) and the junction's disk, grown to
#: hold every disk of the branch, stays within ``max_radius`` and ``room``
#: (:func:`medial_axis`). The tips of the strips the concentric rings leave fork into a Y
#: whose arms are about as long as the strip is wide: each arm was a gap path of its own,
#: a rest stop pair for ~1 mm of bead whose round ends the valve does not lay. The whole
#: bunny: 93 226 -> 50 379 paths, MTTS 83.34 -> 80.86 h (-3.0 %), unfilled 1 023.5 ->
#: 1 019.2 mm^2, the same lowest coverage (BENCHMARKS.md, issue 15); pruned without
#: widening the junction, five times the unfilled area on 30 of its layers.
BRANCH_PRUNE_WIDTHS = 1.0


def medial_axis(rings: Sequence[np.ndarray], spacing: float, min_radius: float = 0.0,
                max_radius: float | None = None,
                room: Callable[[np.ndarray], np.ndarray] | None = None, slack: float = 0.0
                ) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """Centre lines (medial axis) of the area bounded by flat oriented rings.

    The ring edges are sampled every ``spacing`` mm at most; the Voronoi vertices of the
    samples (circumcentres of their Delaunay triangles, ``scipy.spatial.Delaunay``) that
    lie inside the area, linked where the two samples they separate lie on different
    rings or far apart along their ring (more than ``FAR_RATIO`` times their distance:
    the two sides of a strip, not neighbours on one side), form the medial axis. Each vertex
    carries its clearance: the distance to the nearest ring edge (the edges of its
    ``NEAR_SAMPLES`` nearest samples, and the empty circle's radius). Vertices with less
    clearance than ``min_radius`` are dropped; a branch ending in a corner is pruned when
    the disks of its clearance lie inside the disk at its branch point (it covers
    nothing more: branches the sampling makes, not the shape), and, given
    ``max_radius``, when it is shorter than ``BRANCH_PRUNE_WIDTHS`` times the branch
    point's width and the branch point's disk, grown to hold every disk of the branch,
    stays within ``max_radius`` and within ``room(points)`` ((k,) mm, when given: how far a
    bead may reach from each branch point, e.g. to the edge of the area the beads must
    stay in): the branch point then takes the grown clearance (a bead following it is
    widened there to lay what the branch would have), plus ``slack`` (mm: what a later
    simplification of the widths may take off). Every branch point keeps two branches
    (the longest), so a pocket keeps its axis.

    Returns chains ``(points (k, 2) float64 mm, clearance (k,) float64 mm, closed)``:
    open chains end at branch points or where the clearance falls below ``min_radius``;
    closed ones (around a hole) do not repeat their first point.
    """
    from scipy.spatial import Delaunay, QhullError

    rings = [np.asarray(r, dtype=np.float64) for r in rings if len(r) >= 3]
    if not rings or spacing <= 0:
        return []
    # -- sample the edges; every sample remembers its edge, ring and arc position
    P, edge, a, b, prv, ring, arc, ring_len = _sample_rings(rings, spacing)
    counts = np.array([len(r) for r in rings])
    if len(P) < 4:
        return []
    # a fixed sub-micrometre jitter keeps qhull away from the co-circular and collinear
    # samples (offset arcs, straight edges) where its facet merging is slow or fails
    rng = np.random.default_rng(len(P))
    Pj = P + rng.uniform(-JITTER_MM, JITTER_MM, P.shape)
    try:
        tri = Delaunay(Pj)
    except (QhullError, ValueError):
        return []
    S = tri.simplices
    N = tri.neighbors
    # -- circumcentres and their clearance
    pa, pb, pc = P[S[:, 0]], P[S[:, 1]], P[S[:, 2]]
    ba, ca = pb - pa, pc - pa
    den = 2.0 * (ba[:, 0] * ca[:, 1] - ba[:, 1] * ca[:, 0])
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    b2 = np.einsum("ij,ij->i", ba, ba)
    c2 = np.einsum("ij,ij->i", ca, ca)
    C = pa + np.c_[(ca[:, 1] * b2 - ba[:, 1] * c2) / den, (ba[:, 0] * c2 - ca[:, 0] * b2) / den]
    R = np.linalg.norm(C - pa, axis=1)
    starts = offsets(counts)
    inside = ok & _even_odd_rows(np.ascontiguousarray(C[:, 0]), np.ascontiguousarray(C[:, 1]),
                                 np.ascontiguousarray(a), starts)
    idx = np.flatnonzero(inside & (R >= min_radius))  # R bounds the clearance from above
    if not len(idx):
        return []
    # exact clearance: distance to the ring edges of the samples nearest the centre (the
    # nearest edge point lies within spacing / 2 of a sample, so among the nearest ones)
    clear = R.copy()
    clear[idx] = np.minimum(R[idx], _nearest_edge_distance(C[idx], P, edge, a, b, prv))
    good = np.zeros(len(S), dtype=bool)
    good[idx] = clear[idx] >= min_radius
    # -- Voronoi edges between good circumcentres separating far-apart samples
    tt = np.repeat(np.arange(len(S)), 3)
    col = np.tile(np.arange(3), len(S))
    uu = N.reshape(-1)
    sel = (uu > tt) & good[tt] & good[np.maximum(uu, 0)]
    tt, col, uu = tt[sel], col[sel], uu[sel]
    p1 = S[tt, (col + 1) % 3]
    p2 = S[tt, (col + 2) % 3]
    chord = np.linalg.norm(P[p1] - P[p2], axis=1)
    d = np.abs(arc[p1] - arc[p2])
    d = np.minimum(d, ring_len[ring[p1]] - d)
    far = (ring[p1] != ring[p2]) | (d > FAR_RATIO * chord + 1e-9)
    tt, uu = tt[far], uu[far]
    if not len(tt):
        return []
    verts, cstarts, cclosed = _chains(len(S), tt, uu)
    # -- prune short branches that end in a corner (a leaf) off a branch point; a branch
    # point keeps two branches at least (the longest), so a pocket keeps its axis
    deg = np.bincount(np.concatenate([tt, uu]), minlength=len(S))
    pruned = False
    prunable: dict[int, list[tuple[float, np.ndarray]]] = {}
    # every chain at once (thousands per layer): the branches with one leaf end
    first, last = verts[cstarts[:-1]], verts[cstarts[1:] - 1]
    branch = ~cclosed & ((deg[first] == 1) != (deg[last] == 1))
    hub = np.where(deg[first] == 1, last, first)
    leaf = np.where(deg[first] == 1, first, last)
    step = np.r_[np.linalg.norm(np.diff(C[verts], axis=0), axis=1), 0.0]
    step[cstarts[1:] - 1] = 0.0  # no step from one chain's end to the next's start
    length = np.add.reduceat(step, cstarts[:-1])
    # its disks lie in the junction's disk: it covers nothing more; or it is short and
    # the junction's disk can grow to hold them (reach: how far the grown disk must go)
    inside = length + clear[leaf] < clear[hub]
    short = branch & ~inside & (length < BRANCH_PRUNE_WIDTHS * 2.0 * clear[hub]) \
        if max_radius is not None else np.zeros(len(length), dtype=bool)
    reach = np.zeros(len(length))
    if short.any():   # every chain's farthest disk from its hub, all at once
        far = np.linalg.norm(C[verts] - C[np.repeat(hub, np.diff(cstarts))], axis=1) \
            + clear[verts]
        reach = np.where(short, np.maximum.reduceat(far, cstarts[:-1]), 0.0)
    limit = np.full(len(length), max_radius if max_radius is not None else 0.0)
    if room is not None and short.any():
        limit[short] = np.minimum(limit[short], room(C[hub[short]]))
    for i in np.flatnonzero(branch & (inside | (short & (reach + slack <= limit)))):
        prunable.setdefault(int(hub[i]), []).append(
            (float(length[i]), verts[cstarts[i]:cstarts[i + 1]], float(reach[i])))
    gone = np.zeros(len(S), dtype=bool)   # the pruned branches' vertices (not junctions)
    by_x = xs = None                      # the centres in order of x, to find twins
    for junction, branches in prunable.items():
        branches.sort(key=lambda b: b[0])
        for _length, ch, grown in branches[:max(0, int(deg[junction]) - 2)]:
            gone[ch[ch != junction]] = True
            pruned = True
            if grown > 0.0:   # a branch the junction's disk grows to hold
                grown += slack
            if grown > clear[junction]:
                # and its twins: co-circular samples give several triangles one centre,
                # and the chain may keep a twin of the junction (_no_backtrack_mask drops
                # repeated points); candidates by x (a margin for the rounding), then
                # within 1e-9 mm in both
                if by_x is None:
                    by_x = np.argsort(C[:, 0], kind="stable")
                    xs = C[by_x, 0]
                x = C[junction, 0]
                near = by_x[np.searchsorted(xs, x - 2e-9):np.searchsorted(xs, x + 2e-9, "right")]
                twins = near[np.abs(C[near] - C[junction]).max(axis=1) <= 1e-9]
                clear[twins] = np.maximum(clear[twins], grown)
    if pruned:
        drop = gone[tt] | gone[uu]
        tt, uu = tt[~drop], uu[~drop]
        if not len(tt):
            return []
        verts, cstarts, cclosed = _chains(len(S), tt, uu)
    # circumcentres of neighbouring triangles may step back a little along a strip whose
    # two sides are sampled at different spacings: a line doubling back is not simple
    keep = _no_backtrack_mask(C, verts, cstarts, cclosed)
    out = []
    for s, e, c in zip(cstarts[:-1], cstarts[1:], cclosed):
        v = verts[s:e][keep[s:e]]
        if len(v) >= (3 if c else 2):
            out.append((C[v], clear[v], bool(c)))
    return out


@njit(cache=True)
def _no_backtrack_mask(C: np.ndarray, verts: np.ndarray, starts: np.ndarray,
                       closed: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Keep-mask over the concatenated chain vertices: repeated points and points where
    the chain turns back by more than 120 degrees are dropped (see :func:`medial_axis`);
    ends of open chains stay. Passes repeat until none is left, dropping at most every
    other vertex of a run of flagged ones per pass."""
    keep = np.ones(len(verts), dtype=np.bool_)
    for c in range(len(starts) - 1):
        s0 = starts[c]
        n = starts[c + 1] - s0
        for _ in range(64):
            idx = np.empty(n, dtype=np.int64)
            m = 0
            for i in range(n):
                if keep[s0 + i]:
                    idx[m] = s0 + i
                    m += 1
            if m < 3:
                break
            changed = False
            last = -2
            for j in range(m):
                if not closed[c] and (j == 0 or j == m - 1):
                    continue
                p = C[verts[idx[j]]]
                q = C[verts[idx[(j - 1) % m]]]
                r = C[verts[idx[(j + 1) % m]]]
                ax = p[0] - q[0]
                ay = p[1] - q[1]
                bx = r[0] - p[0]
                by = r[1] - p[1]
                la = np.sqrt(ax * ax + ay * ay)
                lb = np.sqrt(bx * bx + by * by)
                bad = la == 0.0 or ax * bx + ay * by < -0.5 * la * lb
                if bad and j != last + 1:
                    keep[idx[j]] = False
                    last = j
                    changed = True
            if not changed:
                break
    return keep



@njit(cache=True)
def _rings_holding(pts: np.ndarray, starts: np.ndarray, px: np.ndarray, py: np.ndarray
                   ) -> np.ndarray:  # pragma: no cover - compiled
    """(p,) int64: for every point, the ring (alone, even-odd) of least absolute area
    that holds it, or -1."""
    nr = len(starts) - 1
    lo = np.empty((nr, 2))
    hi = np.empty((nr, 2))
    area = np.empty(nr)
    for r in range(nr):
        s0 = starts[r]
        n = starts[r + 1] - s0
        lo[r, 0] = pts[s0:s0 + n, 0].min()
        lo[r, 1] = pts[s0:s0 + n, 1].min()
        hi[r, 0] = pts[s0:s0 + n, 0].max()
        hi[r, 1] = pts[s0:s0 + n, 1].max()
        a2 = 0.0
        for i in range(n):
            j = (i + 1) % n
            a2 += pts[s0 + i, 0] * pts[s0 + j, 1] - pts[s0 + j, 0] * pts[s0 + i, 1]
        area[r] = abs(a2) / 2.0
    out = np.full(len(px), -1, dtype=np.int64)
    for k in range(len(px)):
        x = px[k]
        y = py[k]
        best = np.inf
        for r in range(nr):
            if x < lo[r, 0] or x > hi[r, 0] or y < lo[r, 1] or y > hi[r, 1]:
                continue
            if area[r] >= best:
                continue
            if _in_ring(pts, starts[r], starts[r + 1], x, y):
                best = area[r]
                out[k] = r
    return out


def rings_holding(rings: Sequence[np.ndarray], points: np.ndarray) -> np.ndarray:
    """(p,) int64: for every point (p, 2) mm, the index of the smallest of ``rings`` (each
    taken alone) that holds it, -1 for none (points on an edge may go either way)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if not len(rings) or not len(pts):
        return np.full(len(pts), -1, dtype=np.int64)
    return _rings_holding(*_pack(rings), np.ascontiguousarray(pts[:, 0]),
                          np.ascontiguousarray(pts[:, 1]))


def _wrapped(rings: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenated ring points (v, 2), each ring's first index (r,), and the index of
    every point's successor along its ring (v,), the last wrapping to the first."""
    pts = np.concatenate(rings)
    counts = np.array([len(r) for r in rings])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    nxt = np.arange(1, len(pts) + 1)
    nxt[starts + counts - 1] = starts
    return pts, starts, nxt


def ring_areas(rings: Sequence[np.ndarray]) -> np.ndarray:
    """(r,) float64 signed areas of rings, mm^2, in one compiled pass (the paths stage
    asks for them some 300 times per layer, mostly of one to a few rings)."""
    if not len(rings):
        return np.zeros(0)
    return _packed_areas(*_pack(rings))


@njit(cache=True)
def _packed_areas(pts: np.ndarray, starts: np.ndarray) -> np.ndarray:  # pragma: no cover
    """Shoelace areas of the rings packed as :func:`_pack` gives them (empty ring: 0)."""
    nr = len(starts) - 1
    out = np.zeros(nr)
    for r in range(nr):
        a = starts[r]
        b = starts[r + 1]
        acc = 0.0
        for i in range(a, b):
            j = i + 1 if i + 1 < b else a
            acc += pts[i, 0] * pts[j, 1] - pts[j, 0] * pts[i, 1]
        out[r] = 0.5 * acc
    return out


def corner_vertices(ring: np.ndarray, angle_deg: float) -> np.ndarray:
    """(c,) int64: the vertices of a closed ring (k, 2) where it turns by more than
    ``angle_deg`` (0-180; the closing segment counts; repeated points do not turn)."""
    pts = np.ascontiguousarray(ring, dtype=np.float64)
    if len(pts) < 3:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(_turn_mask(pts, math.cos(math.radians(angle_deg))))


@njit(cache=True)
def _turn_mask(pts: np.ndarray, cos_limit: float) -> np.ndarray:  # pragma: no cover
    """Vertices of a closed ring whose arriving and leaving segments make an angle whose
    cosine is below ``cos_limit`` (a turn over the angle)."""
    n = len(pts)
    out = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        p = i - 1 if i > 0 else n - 1
        q = i + 1 if i + 1 < n else 0
        fx = pts[i, 0] - pts[p, 0]
        fy = pts[i, 1] - pts[p, 1]
        ex = pts[q, 0] - pts[i, 0]
        ey = pts[q, 1] - pts[i, 1]
        nf = math.sqrt(fx * fx + fy * fy)
        ne = math.sqrt(ex * ex + ey * ey)
        if nf > 0.0 and ne > 0.0:
            out[i] = fx * ex + fy * ey < cos_limit * nf * ne
    return out


def ring_perimeters(rings: Sequence[np.ndarray]) -> np.ndarray:
    """(r,) float64 perimeters of rings (closing edge included), mm, in one pass."""
    if not len(rings):
        return np.zeros(0)
    pts, starts, nxt = _wrapped(rings)
    return np.add.reduceat(np.hypot(*(pts[nxt] - pts).T), starts)


def area(region: Region | Sequence[np.ndarray]) -> float:
    """Area, mm^2 (sum of the signed ring areas)."""
    rings = rings_of(region)
    return float(ring_areas(rings).sum()) if rings else 0.0
