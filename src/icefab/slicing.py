"""Slicing: a mesh into layers of closed, oriented, nested contours (thesis 3.2, Ossino 2-3).

Pipeline (RPSLICE's FACETSLICE = INTERSECTFACET + SEGMERGE + PATHFILTER, thesis 3.2):

1. **Layer planes.** The sliced height range is ``[z_lo, z_hi]``: the part's z range cut
   down by ``job.parts.part_fraction``. Layer ``k`` spans ``[z_lo + k*t, z_lo + (k+1)*t]``
   with ``t = job.slicing.layer_thickness_mm``; there are ``n = round((z_hi - z_lo) / t)``
   layers (at least one), so a part exactly ``n`` layers tall gives ``n`` layers. The
   cutting plane of layer ``k`` lies at ``z_lo + (k + c)*t`` where ``c =
   job.slicing.cut_fraction`` (0 bottom, 0.5 middle -- the default --, 1 top of the
   layer); for a top layer reaching past the part (rounding) the fraction is taken of the
   part's share ``[bottom, z_hi]`` of the layer, so that no plane misses the part.
   ``Layer.z`` is that height, ``Layer.top_z`` the layer's top surface.

2. **Facet-plane intersection** (INTERSECTFACET, Ossino eq. 1), vectorised over all facets
   and all layers at once: for every facet the range of planes it spans comes from
   ``searchsorted`` on its lowest and highest vertex, the (facet, plane) pairs are
   expanded with ``np.repeat``, and both crossing points are interpolated on the two
   crossed facet edges (the numpy expansion lives in ``tests/_slicing_twins.py``). The production path runs the same
   rules and arithmetic in compiled kernels parallel over facets (:func:`_intersect`,
   bit-identical output, checked by the tests) to use both cores and skip the large
   temporaries.

   *Degenerate cases* (decided here, by symbolic perturbation): a vertex is "above" a
   plane at height ``q`` when ``z >= q``, so a vertex lying exactly on a plane counts as
   above it -- the plane is taken infinitesimally *below* ``q``. To cut inside the layer,
   planes with ``cut_fraction < 1`` are evaluated at ``q = nextafter(z_plane, +inf)`` (a
   vertex on the plane then counts as *below*; the section is the one just above the
   plane, i.e. inside the layer), planes with ``cut_fraction = 1`` at ``q = z_plane``
   (section just below, inside the layer). A plane clamped to the part's bottom always
   takes the section just above it, one clamped to the top the section just below.
   Consequences: every facet with a vertex strictly on each side is cut into exactly one
   segment; horizontal facets are never cut; a facet edge lying in a plane is produced by
   exactly one of its two facets; a vertex on a plane gives zero-length segments that are
   removed when the points are cleaned. So the contours have neither gaps nor duplicate
   segments, and stacked parts or horizontal faces on a plane give the section of the
   layer the plane belongs to.

3. **Topological linking** (SEGMERGE2): each segment end lies on a mesh edge; the segment
   continuing a contour is the one in the facet across that edge, in the same layer. The
   facet adjacency is computed once (half-edges bucketed by their lower vertex, O(facets)),
   after which the partner of every segment end is found in O(1) without any per-layer
   sort; a compiled walker then follows the chains. Exact and O(segments). Segment ends
   whose edge is a boundary edge (open or unwelded mesh) or shared by more than two
   facets (non-manifold) fall back to tolerance matching of their coordinates
   (``job.parts.weld_tolerance_mm``, cKDTree) -- logged, counted in ``SliceReport`` and
   in a warning.

4. **Open chains** that still cannot close (holes in a scan the 3D closing of
   ``icefab.mesh.holes`` left open, or a mesh sliced without it -- the per-layer last resort):
   within the layer, chains are joined end-to-start greedily by the nearest free endpoint
   (a chain may be reversed), preferring to close on itself when its own start is
   nearest; then each chain is closed on itself. Straight chords up to
   ``job.slicing.max_gap_mm`` (the bound, 2 mm by default) are closed, each reported in
   ``Stack.warnings`` with its layer, location and length (and counted in one summary
   line). A longer chord needs the user's consent: with ``open_contours = "refuse"``
   (default) slicing stops with one line naming the layer, the chord and the settings;
   ``"close"`` closes it too (reported); with ``"drop"`` no join or closure may cross more
   than ``max_gap_mm``, and a chain that cannot close is dropped and reported. Areas are
   never silently wrong: every non-trivial closure is reported.

5. **Path filter** (PATHFILTER): points closer than ``min_point_spacing_mm`` to the last
   kept point and (near-)collinear points are removed, per contour in a compiled kernel,
   never moving the contour by more than ``max_filter_deviation_mm`` (every removed point
   lies within that distance of the filtered contour). Rings that collapse are dropped
   and counted: fewer than 3 points, ``|area| < MIN_RING_AREA_MM2``, or thinner than the
   filter bound (``2 |area| / perimeter < max_filter_deviation_mm``: a circle of that
   radius, a sliver of twice that width).

6. **Orientation and nesting** (Ossino 3.1-3.2: hierarchy array q, contour groups A):
   the parent of every ring is the smallest ring (by ``|area|``) containing one of its
   points (even-odd test, compiled); depth parity tells outer rings (even, turned
   counter-clockwise) from holes (odd, clockwise), the icefab convention (the thesis uses
   the opposite one). So the sum of a region's signed ring areas is the cross-section
   area. Every ring also knows its facet orientation (a closed chain is walked along it;
   a chain closed across gaps takes the orientation of most of its points). Where the
   two disagree for some rings of a layer but not all (all: the surface is inside out,
   and the nesting stands), or where rings cross each other (found by the nesting tests)
   or themselves (``icefab.geometry.simple_mask``) -- self-intersecting surfaces,
   overlapping shells, such as a spout or handle pushed into a body, or merged parts that
   overlap -- the layer's region is the non-zero union of the facet-oriented rings (``icefab.geometry``, Clipper on a 1e-4 mm grid); those layers
   are listed in ``SliceReport.union_layers`` and counted in a warning. So every region
   from slicing is simple (valid in the OGC sense) and ``Region.area`` counts an overlap
   once: it is the area of the non-zero union of what the mesh encloses.

The stack file (``save_stack`` / ``load_stack``) is documented in :mod:`icefab.resultfiles`.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Callable

import numba
import numpy as np

from icefab.config import Job
from icefab.adaptive import AdaptiveLayers, plan_layers
from icefab.errors import GeometryError
from icefab.fitting import fit_rings
from icefab.geometry import _in_ring, region_from_rings
from icefab.mesh.topology import edge_buckets, nested_same_way
from icefab.core import (Layer, Mesh, Region, Stack, layer_runs, offsets, signed_area,
                         split_rows)
from icefab.resultfiles import (STACK_FORMAT, STACK_VERSION, load_stack,  # noqa: F401 (old home)
                                save_stack)
from icefab.workload import check_layers

log = logging.getLogger(__name__)

Progress = Callable[[int, int], None]

#: Rings whose area is below this (mm^2) after cleaning are dropped as collapsed.
MIN_RING_AREA_MM2 = 1e-9
#: Points within this distance (mm) of the chord replacing them count as collinear.
COLLINEAR_TOL_MM = 1e-9
#: Longest gap (mm) closed without mention: numerical noise of tolerance matching.
_NOISE_GAP_MM = 1e-6
#: At most this many individual warnings (a bound on memory only: the CLI summarises them
#: by kind and writes them all to warnings.txt, ``icefab.findings``); the rest are counted.
MAX_WARNINGS = 100_000
#: Segments per chunk of layers (bounds the memory of the vectorised intersection).
_CHUNK_SEGMENTS = 3_000_000




@dataclass
class SliceReport:
    """Counts gathered while slicing (logged; the CLI prints them)."""

    segments: int = 0
    rings: int = 0
    tolerance_matched_ends: int = 0
    open_chains: int = 0
    gaps_closed: int = 0
    large_gaps_closed: int = 0
    chains_dropped: int = 0
    rings_collapsed: int = 0
    rings_reoriented: int = 0
    union_layers: list[int] = field(default_factory=list)
    points_before_filter: int = 0
    points_after_filter: int = 0
    empty_layers: list[int] = field(default_factory=list)
    #: adaptive layers: the count uniform slicing needs for the same cusp bound, and the
    #: largest cusp height the layers keep (t_k * max |n_z|), mm
    uniform_layers: int = 0
    max_cusp_mm: float = 0.0


# --------------------------------------------------------------------------- planes


def layer_planes(z_min: float, z_max: float, job: Job, mesh: Mesh | None = None, *,
                 adaptive: AdaptiveLayers | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Layer bottoms, tops, cutting heights and evaluation heights for a part.

    z_min, z_max: the part's z range, mm. mesh: the part, needed for adaptive layers
    (``slicing.cusp_height_mm`` > 0: thicknesses from its facet normals,
    :mod:`icefab.adaptive`); ``adaptive``: those layers when already planned.
    Returns ``(bottom, top, z, q)``, each (n,) float64 mm: layer bottom and top, the
    reported cutting height, and the height ``q`` the vertex classification ``z >= q``
    uses (see the module docstring: ``q`` is ``z`` or the next float above it).
    """
    sl = job.slicing
    t = sl.layer_thickness_mm
    f0, f1 = job.parts.part_fraction
    height = z_max - z_min
    z_lo = z_min + f0 * height
    z_hi = z_min + f1 * height
    if sl.cusp_height_mm > 0:
        if adaptive is None:
            if mesh is None:
                raise ValueError("layer_planes: adaptive layers need the mesh")
            adaptive = adaptive_layers(mesh, z_lo, z_hi, job)
        edges = adaptive.edges
        bottom, top = edges[:-1].copy(), edges[1:].copy()
        n = len(bottom)
    else:
        n = max(1, int(round((z_hi - z_lo) / t)))   # the top layer may reach past the part
        k = np.arange(n, dtype=np.float64)
        bottom = z_lo + k * t
        top = z_lo + (k + 1.0) * t
    c = job.slicing.cut_fraction
    # inside the part's share of the layer (the top layer may reach past the part)
    z = np.clip(bottom + c * (np.minimum(top, z_hi) - bottom), z_lo, z_hi)
    above = np.full(n, c < 1.0)          # take the section just above the plane
    above[z <= z_lo] = True
    above[z >= z_hi] = False
    q = np.where(above, np.nextafter(z, np.inf), z)
    return bottom, top, z, q


def layer_count(mesh: Mesh, job: Job) -> int | None:
    """The number of layers :func:`slice_mesh` makes of the placed ``mesh`` (vertices
    mm) with ``job``, from its z extent, ``parts.part_fraction`` and
    ``slicing.layer_thickness_mm``, without slicing it: what a command's ``--layers`` is
    checked against before the slow work. None when only slicing tells: adaptive layers
    (``slicing.cusp_height_mm`` > 0, planned from the facets), or a mesh
    :func:`slice_mesh` refuses (no finite, positive height). ConfigError as slicing's
    for a part of too many layers (:func:`icefab.workload.check_layers`)."""
    v = np.asarray(mesh.vertices, dtype=np.float64)
    if job.slicing.cusp_height_mm > 0 or v.ndim != 2 or v.shape[1:] != (3,) or not len(v):
        return None
    z_min, z_max = float(v[:, 2].min()), float(v[:, 2].max())
    if not (np.isfinite([z_min, z_max]).all() and z_max > z_min):
        return None
    check_layers(z_min, z_max, job)
    return len(layer_planes(z_min, z_max, job)[0])   # uniform: cheap, no mesh needed


def adaptive_layers(mesh: Mesh, z_lo: float, z_hi: float, job: Job) -> AdaptiveLayers:
    """The cusp-bounded layers of ``mesh`` between ``z_lo`` and ``z_hi`` mm with the job's
    ``slicing`` bound and thickness range (:func:`icefab.adaptive.plan_layers`)."""
    sl = job.slicing
    return plan_layers(mesh, z_lo, z_hi, sl.cusp_height_mm, sl.min_layer_thickness_mm,
                       sl.max_layer_thickness_mm or sl.layer_thickness_mm)


def cusp_warnings(cusp: np.ndarray, job: Job) -> list[str]:
    """The warning (none or one) for adaptive layers whose cusp height (``cusp``, (n,) mm
    per layer, :attr:`icefab.adaptive.AdaptiveLayers.cusp`) is above the job's bound: only
    the minimum thickness keeps a layer thicker than the bound allows (a wall too flat, or
    a flat less than the minimum above a layer's bottom), so the warning names both
    settings (a cone's layers kept 0.0857 mm against a 0.05 mm bound with none)."""
    sl = job.slicing
    over = np.flatnonzero(np.asarray(cusp) > sl.cusp_height_mm * (1.0 + 1e-9))
    if not len(over):
        return []
    return [f"{len(over)} adaptive layers keep a cusp height above slicing.cusp_height_mm = "
            f"{sl.cusp_height_mm:g} (layers {layer_runs(over.tolist())}, "
            f"{float(np.max(cusp)):.4g} mm at the most): slicing.min_layer_thickness_mm = "
            f"{sl.min_layer_thickness_mm:g} allows no thinner layer on their flat walls or "
            "flats; lower it to keep the bound"]


# --------------------------------------------------------------------------- adjacency


@numba.njit(cache=True)
def _adjacency_kernel(faces: np.ndarray, n_vertices: int) -> np.ndarray:  # pragma: no cover
    """Bucket twin of the sorting version in ``tests/_slicing_twins.py``: O(facets), no sort.

    Half-edges bucketed by their lower vertex (:func:`icefab.mesh.edge_buckets`) are
    matched by their upper vertex inside each small bucket.
    """
    m = faces.shape[0]
    n_half = 3 * m
    start, bucket_h, bucket_hi = edge_buckets(faces, n_vertices)
    nbr = np.full(n_half, -1, dtype=np.int64)
    for v in range(n_vertices):
        s = start[v]
        e = start[v + 1]
        for i in range(s, e):
            hi = bucket_hi[i]
            if hi < 0:
                continue
            n_same = 1
            other = -1
            for k in range(i + 1, e):
                if bucket_hi[k] == hi:
                    n_same += 1
                    other = k if other < 0 else other
            if n_same == 2:
                nbr[bucket_h[i]] = bucket_h[other]
                nbr[bucket_h[other]] = bucket_h[i]
                bucket_hi[other] = -1
            elif n_same > 2:
                for k in range(i, e):
                    if bucket_hi[k] == hi:
                        nbr[bucket_h[k]] = -2
                        if k > i:
                            bucket_hi[k] = -1
    return nbr.reshape(m, 3)


def _facet_adjacency(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Neighbour across every facet edge.

    faces: (m, 3) int64. Local edge j of a facet joins its corners j and (j+1) % 3.
    Returns (m, 3) int64: ``3*g + j'`` (facet g, its local edge j') of the facet across
    that edge, -1 for a boundary edge (one facet), -2 for a non-manifold edge (> 2 facets).
    """
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if len(faces) == 0:
        return np.zeros((0, 3), dtype=np.int64)
    return _adjacency_kernel(faces, int(n_vertices))


def _ramp(counts: np.ndarray) -> np.ndarray:
    """0..c-1 for every count c, concatenated: (sum(counts),) int64."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    starts = np.cumsum(counts) - counts
    return np.arange(total, dtype=np.int64) - np.repeat(starts, counts)


# --------------------------------------------------------------------------- intersection


@dataclass
class _Segments:
    """Segments of a chunk of layers; end ``2*s`` is the start, ``2*s+1`` the end."""

    layer: np.ndarray     # (S,) int64 layer index
    facet: np.ndarray     # (S,) int64
    edge: np.ndarray      # (S, 2) int8 local edge of the facet each end lies on
    points: np.ndarray    # (2S, 2) float64 mm, point of every end
    partner: np.ndarray   # (2S,) int64 end on the other side of the edge, -1 none


@numba.njit(cache=True, parallel=True)
def _cut_kernel(vertices: np.ndarray, faces: np.ndarray, q: np.ndarray, fsel: np.ndarray,
                a: np.ndarray, base: np.ndarray, cnt: np.ndarray, layer: np.ndarray,
                edge: np.ndarray, pts: np.ndarray) -> None:  # pragma: no cover
    """Compiled twin of the numpy expansion (``tests/_slicing_twins.py``) (same rules, same
    arithmetic, so bit-identical output), parallel over facets."""
    for ii in numba.prange(fsel.shape[0]):
        f = fsel[ii]
        z0 = vertices[faces[f, 0], 2]
        z1 = vertices[faces[f, 1], 2]
        z2 = vertices[faces[f, 2], 2]
        for jj in range(cnt[ii]):
            k = a[ii] + jj
            s = base[ii] + jj
            qk = q[k]
            b0 = z0 >= qk
            b1 = z1 >= qk
            b2 = z2 >= qk
            na = int(b0) + int(b1) + int(b2)
            if na == 2:
                b0 = not b0
                b1 = not b1
                b2 = not b2
            i = 0 if b0 else (1 if b1 else 2)
            ip = (i + 2) % 3
            if na == 1:
                es, ee = i, ip
            else:
                es, ee = ip, i
            layer[s] = k
            edge[s, 0] = es
            edge[s, 1] = ee
            for end in range(2):
                le = es if end == 0 else ee
                va = faces[f, le]
                vb = faces[f, (le + 1) % 3]
                v0 = min(va, vb)
                v1 = max(va, vb)
                za = vertices[v0, 2]
                t = (qk - za) / (vertices[v1, 2] - za)
                x0 = vertices[v0, 0]
                y0 = vertices[v0, 1]
                pts[2 * s + end, 0] = x0 + t * (vertices[v1, 0] - x0)
                pts[2 * s + end, 1] = y0 + t * (vertices[v1, 1] - y0)


@numba.njit(cache=True, parallel=True)
def _partner_kernel(fsel: np.ndarray, a: np.ndarray, base: np.ndarray, cnt: np.ndarray,
                    slot: np.ndarray, nbr: np.ndarray, edge: np.ndarray,
                    partner: np.ndarray) -> None:  # pragma: no cover
    """Partner end across every end's edge (see the numpy twin in ``tests/_slicing_twins.py``)."""
    for ii in numba.prange(fsel.shape[0]):
        f = fsel[ii]
        for jj in range(cnt[ii]):
            k = a[ii] + jj
            s = base[ii] + jj
            for end in range(2):
                partner[2 * s + end] = -1
                nb = nbr[f, edge[s, end]]
                if nb < 0:
                    continue
                g = nb // 3
                jg = nb % 3
                gi = slot[g]
                if gi < 0 or k < a[gi] or k >= a[gi] + cnt[gi]:
                    continue
                s2 = base[gi] + k - a[gi]
                if edge[s2, 0] == jg:
                    partner[2 * s + end] = 2 * s2
                elif edge[s2, 1] == jg:
                    partner[2 * s + end] = 2 * s2 + 1


def _intersect(vertices: np.ndarray, faces: np.ndarray, fz: np.ndarray, q: np.ndarray,
               lo: np.ndarray, hi: np.ndarray, k0: int, k1: int,
               nbr: np.ndarray) -> _Segments:
    """Compiled, parallel version of the numpy expansion in ``tests/_slicing_twins.py``
    (identical output, tested). ``fz`` is unused (kept for the twin's signature)."""
    a = np.clip(lo, k0, k1)
    cnt = np.clip(hi, k0, k1) - a
    fsel = np.flatnonzero(cnt > 0)
    a = a[fsel]
    cnt = cnt[fsel]
    base = np.cumsum(cnt) - cnt
    n_seg = int(cnt.sum())
    slot = np.full(len(faces), -1, dtype=np.int64)
    slot[fsel] = np.arange(len(fsel))
    layer = np.empty(n_seg, dtype=np.int64)
    edge = np.empty((n_seg, 2), dtype=np.int8)
    pts = np.empty((2 * n_seg, 2), dtype=np.float64)
    partner = np.empty(2 * n_seg, dtype=np.int64)
    _cut_kernel(vertices, faces, q, fsel, a, base, cnt, layer, edge, pts)
    _partner_kernel(fsel, a, base, cnt, slot, nbr, edge, partner)
    return _Segments(layer=layer, facet=np.repeat(fsel, cnt), edge=edge, points=pts,
                     partner=partner)


def _tolerance_match(seg: _Segments, tol: float) -> int:
    """Pair the ends without a topological partner by coordinates (within ``tol`` mm).

    Modifies ``seg.partner`` in place; returns the number of ends paired this way. Ends
    of zero-length segments are left out (they would pair with themselves).
    """
    free = np.flatnonzero(seg.partner < 0)
    if len(free) == 0:
        return 0
    from scipy.spatial import cKDTree

    other = free ^ 1
    zero = np.all(np.abs(seg.points[free] - seg.points[other]) <= tol * 1e-3, axis=1)
    free = free[~zero]
    if len(free) < 2:
        return 0
    lay = seg.layer[free >> 1].astype(np.float64)
    pts = seg.points[free]
    span = float(np.ptp(pts)) + 10.0 * tol + 1.0
    xyz = np.column_stack([pts, lay * span * 4.0])
    tree = cKDTree(xyz)
    dist, j = tree.query(xyz, k=2, distance_upper_bound=tol)
    # with exact ties the point itself need not come first
    me = np.arange(len(free))
    first_is_me = j[:, 0] == me
    cand = np.where(first_is_me, j[:, 1], j[:, 0])
    has = np.isfinite(np.where(first_is_me, dist[:, 1], dist[:, 0])) & (cand < len(free))
    local = np.full(len(free), -1, dtype=np.int64)
    local[has] = cand[has]
    mutual = has.copy()
    mutual[has] = local[local[has]] == np.flatnonzero(has)
    # never pair the two ends of one segment
    mutual &= (free >> 1) != (free[np.where(local >= 0, local, 0)] >> 1)
    e = free[mutual]
    seg.partner[e] = free[local[mutual]]
    return int(mutual.sum())


# --------------------------------------------------------------------------- chaining


@numba.njit(cache=True)
def _walk(partner: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Follow the segment chains (thesis SEGMERGE2 without searching).

    partner: (2S,) int64, end on the other side of each end's edge or -1.
    Returns ``(ends, offsets, closed)``: the end index of every chain point in order
    (a closed chain lists the entry end of each segment; an open chain additionally its
    last exit end), chain offsets (C+1,) into ``ends``, and (C,) bool closed flags.
    """
    n_end = partner.shape[0]
    n_seg = n_end // 2
    visited = np.zeros(n_seg, dtype=np.bool_)
    ends = np.empty(n_end, dtype=np.int64)
    offsets = np.empty(n_seg + 2, dtype=np.int64)
    closed = np.empty(n_seg + 1, dtype=np.bool_)
    pos = 0
    nc = 0
    offsets[0] = 0
    # open chains: start at an end that has no partner
    for e0 in range(n_end):
        if partner[e0] >= 0 or visited[e0 >> 1]:
            continue
        cur = e0
        while True:
            s = cur >> 1
            visited[s] = True
            ends[pos] = cur
            pos += 1
            out = cur ^ 1
            nxt = partner[out]
            if nxt < 0 or visited[nxt >> 1]:
                ends[pos] = out
                pos += 1
                break
            cur = nxt
        closed[nc] = False
        nc += 1
        offsets[nc] = pos
    # closed chains: start at the start end of any unvisited segment
    for s0 in range(n_seg):
        if visited[s0]:
            continue
        cur = 2 * s0
        ok = True
        while True:
            s = cur >> 1
            visited[s] = True
            ends[pos] = cur
            pos += 1
            nxt = partner[cur ^ 1]
            if nxt < 0:
                ok = False
                ends[pos] = cur ^ 1
                pos += 1
                break
            if visited[nxt >> 1]:
                if nxt >> 1 != s0:
                    ok = False   # ran into another chain (inconsistent partners)
                break
            cur = nxt
        closed[nc] = ok
        nc += 1
        offsets[nc] = pos
    return ends[:pos], offsets[:nc + 1], closed[:nc]


@numba.njit(cache=True, parallel=True)
def _gather_rows(src: np.ndarray, idx: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``src[idx]`` for (n, 2) float64 rows, parallel."""
    out = np.empty((idx.shape[0], 2))
    for i in numba.prange(idx.shape[0]):
        out[i, 0] = src[idx[i], 0]
        out[i, 1] = src[idx[i], 1]
    return out


@numba.njit(cache=True)
def _within(pts: np.ndarray, anchor: int, j: int, nxt: int, lim_mid: float,
            lim_j: float) -> bool:  # pragma: no cover
    """True when points anchor+1..j-1 lie within lim_mid, and j within lim_j, of the
    segment from pts[anchor] to pts[nxt]."""
    ax = pts[anchor, 0]
    ay = pts[anchor, 1]
    bx = pts[nxt, 0] - ax
    by = pts[nxt, 1] - ay
    b2 = bx * bx + by * by
    for i in range(anchor + 1, j + 1):
        px = pts[i, 0] - ax
        py = pts[i, 1] - ay
        tt = (px * bx + py * by) / b2 if b2 > 0.0 else 0.0
        if tt < 0.0:
            tt = 0.0
        elif tt > 1.0:
            tt = 1.0
        dx = px - tt * bx
        dy = py - tt * by
        lim = lim_j if i == j else lim_mid
        if dx * dx + dy * dy > lim * lim:
            return False
    return True


@numba.njit(cache=True)
def _filter_ring(pts: np.ndarray, s: int, e: int, keep: np.ndarray, min_spacing: float,
                 max_dev: float) -> None:  # pragma: no cover
    """Path filter of one closed ring pts[s:e]; sets ``keep[s:e]`` (thesis 3.2 PATHFILTER).

    Greedy forward pass (the first point is kept, and dropped at the end if it turns
    out collinear). A point j is removed when, with the chord from the last kept point to
    the point after j replacing it,
      - it is within COLLINEAR_TOL_MM of that chord (repeated or collinear point), or
      - it is closer than ``min_spacing`` to the last kept point (or to the ring's first
        point, where the ring closes) and within ``max_dev`` of the chord,
    and every point removed since the last kept point stays within ``max_dev`` (or
    COLLINEAR_TOL_MM) of it. So no removed point ends up farther than ``max_dev`` from
    the filtered contour. O(points * longest removed run).
    """
    coll = COLLINEAR_TOL_MM
    mid = max(max_dev, coll)
    if e <= s:
        return
    keep[s] = True
    anchor = s
    for j in range(s + 1, e):
        nxt = j + 1 if j + 1 < e else s
        dx = pts[j, 0] - pts[anchor, 0]
        dy = pts[j, 1] - pts[anchor, 1]
        d2 = dx * dx + dy * dy
        # the ring closes on its first point: a point too close to it may go as well
        ex = pts[j, 0] - pts[s, 0]
        ey = pts[j, 1] - pts[s, 1]
        d2 = min(d2, ex * ex + ey * ey) if j > s + 1 else d2
        lim = mid if d2 < min_spacing * min_spacing else coll
        if _within(pts, anchor, j, nxt, mid, lim):
            keep[j] = False
            continue
        keep[j] = True
        anchor = j
    # the first point was kept unconditionally: drop it too when it is collinear
    # with its kept neighbours and every point removed around it stays in bound
    last = anchor
    first = s + 1
    while first < e and not keep[first]:
        first += 1
    if last == s or first >= e or last == first:
        return
    ax = pts[last, 0]
    ay = pts[last, 1]
    bx = pts[first, 0] - ax
    by = pts[first, 1] - ay
    b2 = bx * bx + by * by
    if b2 == 0.0:
        return
    i = last + 1
    while True:
        if i == e:
            i = s
        if i == first:
            break
        px = pts[i, 0] - ax
        py = pts[i, 1] - ay
        tt = min(1.0, max(0.0, (px * bx + py * by) / b2))
        dx = px - tt * bx
        dy = py - tt * by
        lim = coll if i == s else mid
        if dx * dx + dy * dy > lim * lim:
            return
        i += 1
    keep[s] = False


@numba.njit(cache=True, parallel=True)
def _filter_compact(pts: np.ndarray, off: np.ndarray, order: np.ndarray, min_spacing: float,
                    max_dev: float) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Filter every ring (:func:`_filter_ring`, parallel over rings) and gather the kept
    points of the rings in ``order``: returns points (P', 2) and offsets (R+1,)."""
    n = order.shape[0]
    keep = np.empty(pts.shape[0], dtype=np.bool_)
    counts = np.zeros(n, dtype=np.int64)
    for ii in numba.prange(n):
        r = order[ii]
        _filter_ring(pts, off[r], off[r + 1], keep, min_spacing, max_dev)
        c = 0
        for i in range(off[r], off[r + 1]):
            if keep[i]:
                c += 1
        counts[ii] = c
    out_off = np.zeros(n + 1, dtype=np.int64)
    for ii in range(n):
        out_off[ii + 1] = out_off[ii] + counts[ii]
    out = np.empty((out_off[n], 2))
    for ii in numba.prange(n):
        r = order[ii]
        k = out_off[ii]
        for i in range(off[r], off[r + 1]):
            if keep[i]:
                out[k, 0] = pts[i, 0]
                out[k, 1] = pts[i, 1]
                k += 1
    return out, out_off


@numba.njit(cache=True)
def _nesting(pts: np.ndarray, off: np.ndarray, group: np.ndarray,
             abs_area: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Parent ring of every ring (Ossino 3.1 hierarchy array q), -1 for top level.

    pts (P, 2); off (R+1,); group (G+1,) offsets of the rings of each layer (rings sorted
    by layer); abs_area (R,) |signed area|. The parent is the smallest larger ring of the
    same layer containing at least two of three points of the ring (at 0, 1/3 and 2/3 of
    its points): one point touching another ring cannot misplace it.
    Also returns (R,) bool ``overlap``: the ring crosses a larger ring of its layer (only
    one or two of its three points inside it, or -- for a ring outside it whose bounding
    box meets it -- any of its points inside): the layer is not a plain nesting.
    """
    n_ring = off.shape[0] - 1
    parent = np.full(n_ring, -1, dtype=np.int64)
    overlap = np.zeros(n_ring, dtype=np.bool_)
    bb = np.empty((n_ring, 4))
    for r in range(n_ring):
        s = off[r]
        e = off[r + 1]
        bb[r, 0] = pts[s:e, 0].min()
        bb[r, 1] = pts[s:e, 1].min()
        bb[r, 2] = pts[s:e, 0].max()
        bb[r, 3] = pts[s:e, 1].max()
    for g in range(group.shape[0] - 1):
        a = group[g]
        b = group[g + 1]
        if b - a < 2:
            continue
        order = a + np.argsort(abs_area[a:b])
        for ii in range(b - a):
            r = order[ii]
            s = off[r]
            n = off[r + 1] - s
            for jj in range(ii + 1, b - a):
                c = order[jj]
                if (bb[r, 2] < bb[c, 0] or bb[r, 0] > bb[c, 2] or bb[r, 3] < bb[c, 1]
                        or bb[r, 1] > bb[c, 3]):
                    continue        # bounding boxes apart
                votes = 0
                for t in range(3):
                    i = s + (t * n) // 3
                    if _in_ring(pts, off[c], off[c + 1], pts[i, 0], pts[i, 1]):
                        votes += 1
                if votes == 1 or votes == 2:
                    overlap[r] = True
                if votes >= 2:
                    parent[r] = c
                    break
                if votes == 0:
                    for i in range(s, s + n):
                        if _in_ring(pts, off[c], off[c + 1], pts[i, 0], pts[i, 1]):
                            overlap[r] = True
                            break
    return parent, overlap


# --------------------------------------------------------------------------- helpers


@numba.njit(cache=True)
def _ring_measures(pts: np.ndarray,
                   off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """(R,) signed areas (mm^2, shoelace) and (R,) perimeters (mm) of concatenated rings."""
    n = off.shape[0] - 1
    area = np.zeros(n)
    perim = np.zeros(n)
    for r in range(n):
        s = off[r]
        e = off[r + 1]
        if e - s < 2:
            continue
        acc = 0.0
        per = 0.0
        x0 = pts[s, 0]
        y0 = pts[s, 1]
        for i in range(s, e):
            j = i + 1 if i + 1 < e else s
            # relative to the first point: less cancellation for far-off rings
            xi = pts[i, 0] - x0
            yi = pts[i, 1] - y0
            xj = pts[j, 0] - x0
            yj = pts[j, 1] - y0
            acc += xi * yj - xj * yi
            per += np.sqrt((xj - xi) ** 2 + (yj - yi) ** 2)
        area[r] = 0.5 * acc
        perim[r] = per
    return area, perim


@numba.njit(cache=True)
def _count_le(q: np.ndarray, z: float, step: float) -> int:  # pragma: no cover
    """Number of planes with q <= z (``searchsorted(q, z, 'right')``), q sorted and nearly
    uniform with spacing ``step``: a guess, then an exact correction."""
    n = q.shape[0]
    k = int((z - q[0]) / step) + 1 if step > 0.0 else 0
    if k < 0:
        k = 0
    elif k > n:
        k = n
    while k > 0 and q[k - 1] > z:
        k -= 1
    while k < n and q[k] <= z:
        k += 1
    return k


@numba.njit(cache=True)
def _facet_plane_range(vertices: np.ndarray, faces: np.ndarray,
                       q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Planes cutting each facet (Ossino eq. 1 with the rule ``z >= q`` is above): facet f
    is cut by planes lo[f]..hi[f]-1, i.e. those with zmin < q <= zmax. (m,) int64 each."""
    m = faces.shape[0]
    lo = np.empty(m, dtype=np.int64)
    hi = np.empty(m, dtype=np.int64)
    n = q.shape[0]
    step = (q[n - 1] - q[0]) / (n - 1) if n > 1 else 0.0
    for f in range(m):
        a = vertices[faces[f, 0], 2]
        b = vertices[faces[f, 1], 2]
        c = vertices[faces[f, 2], 2]
        lo[f] = _count_le(q, min(a, min(b, c)), step)
        hi[f] = _count_le(q, max(a, max(b, c)), step)
    return lo, hi


def _offsets(counts: np.ndarray) -> np.ndarray:
    return offsets(counts)


def _fmt_pt(p: np.ndarray) -> str:
    return f"({p[0]:.2f}, {p[1]:.2f})"


@dataclass
class _Rings:
    """Concatenated rings: points (P,2), offsets (R+1,), layer (R,); ``oriented`` (R,)
    the ring runs along its facets' orientation (material on the left); ``gap`` (R,) it
    was closed from open chains."""

    points: np.ndarray
    offsets: np.ndarray
    layer: np.ndarray
    oriented: np.ndarray
    gap: np.ndarray

    @staticmethod
    def empty() -> "_Rings":
        return _Rings(np.zeros((0, 2)), np.zeros(1, dtype=np.int64),
                      np.zeros(0, dtype=np.int64), np.zeros(0, dtype=bool),
                      np.zeros(0, dtype=bool))

    @staticmethod
    def concat(parts: list["_Rings"]) -> "_Rings":
        parts = [p for p in parts if len(p.layer)]
        if not parts:
            return _Rings.empty()
        counts = np.concatenate([np.diff(p.offsets) for p in parts])
        return _Rings(np.concatenate([p.points for p in parts]), _offsets(counts),
                      np.concatenate([p.layer for p in parts]),
                      np.concatenate([p.oriented for p in parts]),
                      np.concatenate([p.gap for p in parts]))


class _Warnings:
    def __init__(self) -> None:
        self.items: list[str] = []
        self.suppressed = 0

    def add(self, msg: str) -> None:
        if len(self.items) < MAX_WARNINGS:
            self.items.append(msg)
        else:
            self.suppressed += 1

    def result(self) -> tuple[str, ...]:
        out = list(self.items)
        if self.suppressed:
            out.append(f"... and {self.suppressed} more warnings")
        return tuple(out)


def _close_open_chains(chains_in: list[tuple[np.ndarray, bool]], layer: int, z: float,
                       job: Job, report: SliceReport, warn: _Warnings) -> list[np.ndarray]:
    """Join the open chains of one layer end-to-start greedily, then close them.

    chains_in: (points (k_i, 2) float64, forward) of every open polyline; ``forward``: it
    runs along its facets' orientation. Returns closed rings turned to run along the
    facet orientation of most of their points (material on the left).
    Rule (module docstring, step 4): the chain being grown takes the nearest free endpoint
    of another chain (reversing that chain when its end is nearer) unless its own start
    is at least as near, in which case it closes. Gaps above ``max_gap_mm`` are reported
    and, in "drop" mode, the chain is dropped instead of closed.
    """
    max_gap = job.slicing.max_gap_mm
    drop_mode = job.slicing.open_contours == "drop"
    # in "drop" mode no join may cross more than max_gap_mm
    reach = max_gap if drop_mode else np.inf
    chains = [c for c, _ in chains_in if len(c) >= 1]
    forward = [f for c, f in chains_in if len(c) >= 1]
    n = len(chains)
    starts = np.array([c[0] for c in chains]).reshape(n, 2)
    ends = np.array([c[-1] for c in chains]).reshape(n, 2)
    alive = np.ones(n, dtype=bool)
    rings: list[np.ndarray] = []
    where = f"layer {layer} (z = {z:.3f} mm)"
    for first in range(n):
        if not alive[first]:
            continue
        alive[first] = False
        cur = [chains[first]]
        vote = len(chains[first]) * (1 if forward[first] else -1)
        head = starts[first]
        gaps: list[tuple[float, np.ndarray]] = []
        closed = False
        while True:
            tail = cur[-1][-1]
            d_self = float(np.hypot(*(tail - head)))
            best, rev, i = np.inf, False, -1
            if alive.any():
                idx = np.flatnonzero(alive)
                ds = np.hypot(*(starts[idx] - tail).T)
                de = np.hypot(*(ends[idx] - tail).T)
                i_s, i_e = int(np.argmin(ds)), int(np.argmin(de))
                if ds[i_s] <= de[i_e]:
                    best, rev, i = float(ds[i_s]), False, int(idx[i_s])
                else:
                    best, rev, i = float(de[i_e]), True, int(idx[i_e])
            if d_self <= best or best > reach:
                closed = d_self <= reach
                gaps.append((d_self, 0.5 * (tail + head)))
                break
            alive[i] = False
            nxt = chains[i][::-1] if rev else chains[i]
            vote += len(nxt) * (1 if forward[i] != rev else -1)
            gaps.append((best, 0.5 * (tail + nxt[0])))
            cur.append(nxt)
        if not closed:                  # "drop" mode: cannot close within max_gap_mm
            report.chains_dropped += 1
            g, p = gaps[-1]
            warn.add(f"{where}: open contour dropped: it cannot close within max_gap_mm = "
                     f"{max_gap} (gap {g:.2f} mm at {_fmt_pt(p)})")
            continue
        long = [(g, p) for g, p in gaps if g > max_gap]
        if long and job.slicing.open_contours == "refuse":
            g, p = max(long, key=lambda gp: gp[0])
            raise GeometryError(
                f"{where}: an open contour would be closed across a {g:.2f} mm straight "
                f"chord at {_fmt_pt(p)}, longer than slicing.max_gap_mm = {max_gap:g} (the "
                "hole was not closed in 3D); set slicing.open_contours = \"close\" to build "
                "it anyway, \"drop\" to leave the contour out, or raise slicing.max_gap_mm")
        for g, p in gaps:
            if _NOISE_GAP_MM < g <= max_gap:
                report.gaps_closed += 1
                warn.add(f"{where}: open contour closed across a {g:.2f} mm gap at "
                         f"{_fmt_pt(p)}")
            elif g > max_gap:
                report.large_gaps_closed += 1
                warn.add(f"{where}: open contour closed across a {g:.2f} mm gap at "
                         f"{_fmt_pt(p)} (longer than max_gap_mm = {max_gap}; built as "
                         "slicing.open_contours = \"close\" allows)")
        ring = np.concatenate(cur)
        if len(ring) > 1 and np.array_equal(ring[0], ring[-1]):
            ring = ring[:-1]            # drop a repeated closing point
        rings.append(ring if vote >= 0 else ring[::-1].copy())
    return rings


# --------------------------------------------------------------------------- main entry


def _slice_rings(mesh: Mesh, q: np.ndarray, z_report: np.ndarray, job: Job,
                 report: SliceReport, warn: _Warnings,
                 progress: Progress | None) -> _Rings:
    """Cut, link and close: all rings of all planes ``q`` (unfiltered, unoriented)."""
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    if len(faces):
        good = ((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                & (faces[:, 0] != faces[:, 2]))
        if not good.all():
            log.info("%s: %d facets with a repeated corner ignored", mesh.name,
                     int((~good).sum()))
            faces = faces[good]
    n_planes = len(q)
    if len(faces) == 0:
        return _Rings.empty()
    fz = None  # the compiled cut reads the corner heights itself
    lo, hi = _facet_plane_range(vertices, faces, q)
    nbr = _facet_adjacency(faces, len(vertices))
    n_bad_edges = int((nbr == -2).sum())
    if n_bad_edges:
        log.info("%s: %d facet edges are non-manifold; their segment ends are matched by "
                 "tolerance", mesh.name, n_bad_edges)
    # chunks of layers with a bounded number of segments
    per_plane = np.bincount(lo, minlength=n_planes + 1)[:n_planes] \
        - np.bincount(hi, minlength=n_planes + 1)[:n_planes]
    per_plane = np.cumsum(per_plane)
    cum = np.cumsum(per_plane)
    bounds = [0]
    while bounds[-1] < n_planes:
        k0 = bounds[-1]
        base = cum[k0 - 1] if k0 else 0
        k1 = int(np.searchsorted(cum, base + _CHUNK_SEGMENTS, side="right"))
        bounds.append(min(n_planes, max(k1, k0 + 1)))
    tol = job.parts.weld_tolerance_mm
    parts: list[_Rings] = []
    open_by_layer: dict[int, list[tuple[np.ndarray, bool]]] = {}
    for c in range(len(bounds) - 1):
        k0, k1 = bounds[c], bounds[c + 1]
        seg = _intersect(vertices, faces, fz, q, lo, hi, k0, k1, nbr)
        report.segments += len(seg.layer)
        if len(seg.layer):
            n_tol = _tolerance_match(seg, tol)
            report.tolerance_matched_ends += n_tol
            ends, offs, closed = _walk(seg.partner)
            counts = np.diff(offs)
            ring_layer = seg.layer[ends[offs[:-1]] >> 1]
            pts = _gather_rows(seg.points, ends)
            cl = closed.astype(bool)
            n_open = int(np.argmin(cl)) if not cl.all() else 0
            if cl[n_open:].all():        # the walker lists open chains first
                n_cl = len(cl) - n_open
                parts.append(_Rings(pts[offs[n_open]:], offs[n_open:] - offs[n_open],
                                    ring_layer[n_open:], np.ones(n_cl, dtype=bool),
                                    np.zeros(n_cl, dtype=bool)))
            else:
                ring_mask = np.repeat(cl, counts)
                parts.append(_Rings(pts[ring_mask], _offsets(counts[cl]), ring_layer[cl],
                                    np.ones(int(cl.sum()), dtype=bool),
                                    np.zeros(int(cl.sum()), dtype=bool)))
            for r in np.flatnonzero(~cl):
                # walked from a segment's start end: along the facet orientation
                fwd = bool(ends[offs[r]] & 1 == 0)
                open_by_layer.setdefault(int(ring_layer[r]), []).append(
                    (pts[offs[r]:offs[r + 1]], fwd))
        if progress is not None:
            progress(k1, n_planes)
    if report.tolerance_matched_ends:
        log.warning("%s: %d segment ends linked by tolerance matching (%g mm) instead of "
                    "by mesh edge: the mesh is not welded or not manifold there",
                    mesh.name, report.tolerance_matched_ends, tol)
    # open chains, layer by layer (thesis: a scan's holes; Ossino 2.2)
    extra: list[np.ndarray] = []
    extra_layer: list[int] = []
    for k in sorted(open_by_layer):
        chains = open_by_layer[k]
        report.open_chains += len(chains)
        for ring in _close_open_chains(chains, k, float(z_report[k]), job, report, warn):
            extra.append(ring)
            extra_layer.append(k)
    if extra:
        parts.append(_Rings(np.concatenate(extra), _offsets([len(r) for r in extra]),
                            np.array(extra_layer, dtype=np.int64),
                            np.ones(len(extra), dtype=bool), np.ones(len(extra), dtype=bool)))
    return _Rings.concat(parts)


def _finish_rings(rings: _Rings, job: Job, report: SliceReport
                  ) -> tuple[_Rings, np.ndarray, dict[int, Region]]:
    """Filter, drop collapsed rings, orient and nest.

    Returns the rings sorted by layer, their parents (index within the layer), and the
    regions of the layers that needed a union (layer -> Region, see below)."""
    report.points_before_filter = len(rings.points)
    if len(rings.layer) == 0:
        return rings, np.zeros(0, dtype=np.int64), {}
    # filter, and sort the rings by layer (stable) in the same gather
    order = np.argsort(rings.layer, kind="stable")
    sl = job.slicing
    if sl.fit_contours:  # smooth contours instead of the filter (icefab.fitting)
        pts, off = _filter_compact(rings.points, rings.offsets, order, 0.0, 0.0)
        pts, off = fit_rings(pts, off, float(sl.fit_tolerance_mm), float(sl.corner_angle_deg),
                             float(sl.min_point_spacing_mm) or 0.4)
    else:
        pts, off = _filter_compact(rings.points, rings.offsets, order,
                                   float(sl.min_point_spacing_mm),
                                   float(sl.max_filter_deviation_mm))
    rings = _Rings(pts, off, rings.layer[order], rings.oriented[order], rings.gap[order])
    counts = np.diff(rings.offsets)
    area, perim = _ring_measures(rings.points, rings.offsets)
    # collapsed: < 3 points, (almost) no area, or thinner than the filter's own bound
    # (2|A|/perimeter -- the radius of a circle, half the width of a sliver -- below
    # max_filter_deviation_mm: the filter may move every point of such a ring onto a line)
    # a ring crossing (or touching) itself -- a self-intersecting surface, or two shells
    # walked into one contour -- has no nesting of its own, and its signed area is not its
    # area (a bow tie's is 0): it is never "collapsed", and its layer is united below, so a
    # region from slicing is always simple and counts no overlap twice (issue 11)
    from icefab.geometry import simple_mask

    selfx = ~simple_mask([rings.points[rings.offsets[r]:rings.offsets[r + 1]]
                          for r in range(len(rings.layer))])
    ok = (counts >= 3) & (selfx | ((np.abs(area) >= MIN_RING_AREA_MM2)
                                   & (2.0 * np.abs(area)
                                      >= job.slicing.max_filter_deviation_mm * perim)))
    report.rings_collapsed += int((~ok).sum())
    if not ok.all():
        rings = _Rings(rings.points[np.repeat(ok, counts)], _offsets(counts[ok]),
                       rings.layer[ok], rings.oriented[ok], rings.gap[ok])
        area = area[ok]
        selfx = selfx[ok]
    report.points_after_filter = len(rings.points)
    group = np.searchsorted(rings.layer, np.arange(int(rings.layer.max()) + 2)) \
        if len(rings.layer) else np.zeros(1, dtype=np.int64)
    parent, overlap = _nesting(rings.points, rings.offsets, group.astype(np.int64),
                               np.abs(area))
    # depth parity -> orientation (icefab: outer CCW, holes CW)
    depth = np.zeros(len(parent), dtype=np.int64)
    cur = parent.copy()
    while (cur >= 0).any():
        m = cur >= 0
        depth[m] += 1
        cur[m] = parent[cur[m]]
    want_ccw = depth % 2 == 0
    flip = want_ccw != (area > 0)
    wrong = flip & rings.oriented & ~rings.gap
    n_wrong = int(wrong.sum())
    if n_wrong:
        report.rings_reoriented += n_wrong
        log.info("%d contours ran against the facet orientation (inverted facets or "
                 "overlapping shells)", n_wrong)
    # Layers where nesting cannot be trusted -- rings crossing each other, or some rings
    # (walked, or closed across a gap) whose facet orientation contradicts their nesting
    # while others agree: overlapping shells, e.g. a handle pushed into a body -- get
    # their region as the non-zero union of the facet-oriented
    # rings (material on the left), with icefab.geometry (Clipper, 1e-4 mm grid).
    unions: dict[int, Region] = {}
    # (a layer whose rings all disagree is simply inside out: flipping is enough)
    n_layers = len(group) - 1
    against = np.bincount(rings.layer[flip & rings.oriented], minlength=n_layers)
    along = np.bincount(rings.layer[~flip & rings.oriented], minlength=n_layers)
    crossing = np.bincount(rings.layer[overlap], minlength=n_layers)
    crossing += np.bincount(rings.layer[selfx], minlength=n_layers)
    for k in np.flatnonzero(((against > 0) & (along > 0)) | (crossing > 0)):
        unions[int(k)] = _union_layer(rings, int(group[k]), int(group[k + 1]))
    if flip.any():
        pts = rings.points.copy()
        for r in np.flatnonzero(flip):
            s, e = rings.offsets[r], rings.offsets[r + 1]
            pts[s:e] = pts[s:e][::-1]
        rings = _Rings(pts, rings.offsets, rings.layer, rings.oriented, rings.gap)
    # parent as an index within the layer
    first = group[rings.layer]
    local_parent = np.where(parent >= 0, parent - first, -1)
    return rings, local_parent, unions


def _union_layer(rings: _Rings, a: int, b: int) -> Region:
    """Non-zero union of the facet-oriented rings a..b-1 of one layer (see _finish_rings).

    When the rings' total signed area is negative the facets face inwards (an inside-out
    open surface): the union is then taken of the reversed rings.
    """

    ring_list = [rings.points[rings.offsets[r]:rings.offsets[r + 1]] for r in range(a, b)]
    total = sum(signed_area(r) for r in ring_list)
    if total < 0:
        ring_list = [r[::-1] for r in ring_list]
    return region_from_rings(ring_list, fill="nonzero")


def _checked_mesh(mesh: Mesh) -> Mesh:
    """The mesh with float64 (n, 3) vertices and int64 (m, 3) faces, every coordinate
    finite and every index a vertex's; GeometryError naming what is not. The loaders check
    their files; a Mesh built by a program (from trimesh, say) was sliced as it came: an
    index past the vertices read memory outside them (a tester's segfault, or areas of
    1e8 mm^2), a NaN x or y gave empty layers without a word."""
    name = mesh.name or "mesh"
    try:
        v = np.asarray(mesh.vertices, dtype=np.float64)
        f = np.asarray(mesh.faces)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{name}: vertices and faces must be arrays of numbers "
                            f"({exc})") from None
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise GeometryError(f"{name}: vertices {v.shape} and faces {f.shape}: expected "
                            "(n, 3) coordinates and (m, 3) vertex indices")
    if len(f) and f.dtype.kind not in "iu":
        raise GeometryError(f"{name}: faces of dtype {f.dtype}: expected integer vertex "
                            "indices")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise GeometryError(f"{name}: vertex {k} is {v[k].tolist()}: coordinates must be "
                            "finite")
    if len(f):
        out = (f < 0) | (f >= len(v))
        if out.any():
            k = int(np.argmax(out.any(axis=1)))
            raise GeometryError(f"{name}: face {k} has vertex index {f[k].tolist()} out of "
                                f"range: the mesh has {len(v)} vertices")
    if v is mesh.vertices and f.dtype == np.int64:
        return mesh
    return dataclasses.replace(mesh, vertices=v, faces=f.astype(np.int64))


def slice_mesh(mesh: Mesh, job: Job | None = None, *, progress: Progress | None = None) -> Stack:
    """Slice a mesh into a :class:`Stack` of layers of nested, oriented contours.

    mesh: vertices (n, 3) float64 mm, faces (m, 3) int -- already placed by
        ``icefab.mesh.place_mesh`` or ``prepare_parts`` (the build's z axis is the mesh's
        z axis; they check it against the cell, which slicing does not).
    job: the settings (``job.slicing``, ``job.parts.part_fraction`` and
        ``weld_tolerance_mm``); ``Job()`` when omitted.
    progress: optional ``callable(done, total)`` called as layers are cut.

    Layer ``k`` spans ``[z_lo + k*t, z_lo + (k+1)*t]`` and is cut at ``z_lo + (k +
    cut_fraction)*t``; see the module docstring for the rules (degenerate cases, open
    chains, filter, nesting). Raises GeometryError for a mesh with no height.
    """
    job = Job() if job is None else job
    report = SliceReport()
    warn = _Warnings()
    mesh = _checked_mesh(mesh)
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise GeometryError(f"{mesh.name or 'mesh'}: no facets to slice")
    bounds = mesh.bounds
    z_min, z_max = float(bounds[0, 2]), float(bounds[1, 2])
    if not np.isfinite([z_min, z_max]).all() or z_max <= z_min:
        raise GeometryError(f"{mesh.name or 'mesh'}: height {z_max - z_min!r} mm: a part "
                            "needs a positive, finite height to be sliced")
    check_layers(z_min, z_max, job)  # before any per-layer array (issue 10: z = 1e9)
    # thesis Table 3-1 "number of CPUs": job.cell.cpus threads for the compiled kernels
    prev_threads = numba.get_num_threads()
    numba.set_num_threads(max(1, min(job.cell.cpus or prev_threads,
                                     numba.config.NUMBA_NUM_THREADS)))
    try:
        planned = None
        if job.slicing.cusp_height_mm > 0:
            f0, f1 = job.parts.part_fraction
            planned = adaptive_layers(mesh, z_min + f0 * (z_max - z_min),
                                      z_min + f1 * (z_max - z_min), job)
            report.uniform_layers = planned.uniform_layers
            report.max_cusp_mm = float(planned.cusp.max()) if len(planned.cusp) else 0.0
        bottom, top, z, q = layer_planes(z_min, z_max, job, mesh, adaptive=planned)
        n = len(z)
        adaptive = job.slicing.cusp_height_mm > 0
        own = (top - bottom) if adaptive else np.full(n, np.nan)
        if job.slicing.mode == "2d":
            # thesis slicing option 3: cut once (at the middle layer's plane), copy everywhere
            mid = n // 2
            rings = _slice_rings(mesh, q[mid:mid + 1], z[mid:mid + 1], job, report, warn, None)
            rings.layer[:] = 0
            rings, parent, unions = _finish_rings(rings, job, report)
            region = unions.get(0) or _region_of(rings, parent, 0, len(rings.layer))
            layers = tuple(Layer(index=k, z=float(z[k]), part=region, top_z=float(top[k]),
                                 thickness=float(own[k])) for k in range(n))
            if progress is not None:
                progress(n, n)
        else:
            rings = _slice_rings(mesh, q, z, job, report, warn, progress)
            rings, parent, unions = _finish_rings(rings, job, report)
            starts = np.searchsorted(rings.layer, np.arange(n + 1))
            layers = tuple(Layer(index=k, z=float(z[k]), top_z=float(top[k]),
                                 thickness=float(own[k]),
                                 part=unions[k] if k in unions else
                                 _region_of(rings, parent, int(starts[k]), int(starts[k + 1])))
                           for k in range(n))
        report.rings = sum(len(L.part) for L in layers) if job.slicing.mode == "3d" \
            else len(layers[0].part) if layers else 0
        report.union_layers = sorted(unions)
        empty = [L.index for L in layers if L.part.is_empty]
        report.empty_layers = empty
        for k in empty:
            warn.add(f"layer {k} (z = {z[k]:.3f} mm): empty cross-section")
        summary: list[str] = []
        if report.gaps_closed:
            summary.append(f"{report.gaps_closed} small gaps (<= max_gap_mm = "
                           f"{job.slicing.max_gap_mm} mm) in open contours closed")
        if report.tolerance_matched_ends:
            summary.append(f"{report.tolerance_matched_ends} segment ends linked by tolerance "
                           f"({job.parts.weld_tolerance_mm} mm): mesh not welded or not manifold")
        if report.rings_reoriented:
            summary.append(f"{report.rings_reoriented} contours ran against the facet "
                           "orientation (inverted facets or overlapping shells)")
            # say which shell, when one lies inside another facing the same way: a cavity
            # wound inside out came out solid with only the line above to tell
            from icefab.mesh.repair import point_text

            for n_faces, at in nested_same_way(mesh.vertices, mesh.faces)[:3]:
                summary.append(f"a shell of {n_faces} facets at {point_text(at)} mm lies "
                               "inside another and faces the same way: built solid (a "
                               "cavity whose facets are wound inside out is filled: flip "
                               "them to keep it hollow)")
        if adaptive:
            # the part's height left less than two minimum layers at the top: the last two
            # share it and keep the cusp bound (icefab.adaptive.plan_layers), said here
            # (a tester's spot ended in two 0.08 mm layers under a 0.1 mm minimum, unsaid)
            t_min = job.slicing.min_layer_thickness_mm
            thin = np.flatnonzero(own < t_min * (1.0 - 1e-9))
            if len(thin):
                summary.append(
                    f"{len(thin)} adaptive layers thinner than slicing.min_layer_thickness_mm "
                    f"= {t_min:g} (layers {layer_runs(thin.tolist())}, "
                    f"{float(own[thin].min()):.4g} mm at "
                    "the thinnest): the part's top leaves less than two minimum layers, "
                    "and the last two share it within the cusp bound")
            summary += cusp_warnings(planned.cusp, job)
        if report.union_layers:
            summary.append(f"{len(report.union_layers)} layers made as the union of their "
                           f"contours (overlapping shells or gap closures): "
                           f"{layer_runs(sorted(report.union_layers))}")
        log.info("sliced %s: %d layers, %d segments, %d contours, %d open chains, %d points "
                 "(%d before filter), %d collapsed", mesh.name, n, report.segments, report.rings,
                 report.open_chains, report.points_after_filter, report.points_before_filter,
                 report.rings_collapsed)
        stack = Stack(layers=layers, job=job, layer_thickness=job.slicing.layer_thickness_mm,
                      warnings=tuple(mesh.warnings) + tuple(summary) + warn.result())
    finally:
        numba.set_num_threads(prev_threads)
    object.__setattr__(stack, "_report", report)  # for the CLI and the benchmark
    return stack


def slice_report(stack: Stack) -> SliceReport | None:
    """The :class:`SliceReport` of a stack made by :func:`slice_mesh` in this process."""
    return getattr(stack, "_report", None)


def _region_of(rings: _Rings, parent: np.ndarray, a: int, b: int) -> Region:
    if b <= a:
        return Region()
    s, e = rings.offsets[a], rings.offsets[b]
    pts = rings.points[s:e]
    cuts = rings.offsets[a + 1:b] - s
    return Region(rings=tuple(split_rows(pts, cuts)), parent=parent[a:b].copy())
