"""Adaptive layer thickness by cusp height (Zhang & Liou IV, eq. 17; Dolenc & Makela).

A layer of thickness t built as an extrusion of one contour leaves a staircase on a
slanted wall; its cusp height (the staircase's distance from the surface, measured along
the normal) is C = t |cos theta| = t |n_z| for a wall whose unit normal n makes the angle
theta with the build direction. Given a bound C_max, each layer is as thick as the
steepest-flat facet it holds allows: t_k = C_max / max |n_z| over the facets that reach
into the layer, within [min, max] thickness. Horizontal facets (|n_z| = 1) inside a layer
make it end at their height when that leaves at least the minimum thickness (the flat is
then a layer boundary and costs no staircase), else they count like any facet: that layer
is at most max(min, C_max) thick. A flat less than the minimum above a layer's top makes
that layer end the minimum below the flat when it keeps the minimum itself, so the next
layer ends on the flat. Where the minimum is above C_max, a flat it keeps inside a layer
(or a wall too flat for a minimum layer) leaves a cusp above the bound: ``cusp`` says so
per layer, and the slicer warns (``icefab.slicing.slice_mesh``).

The thesis (4.1) argues the water cell keeps one thickness: a layer above 0.25 mm spreads,
and the valve and SMF tune for it. So the bound is off by default
(``slicing.cusp_height_mm = 0``) and the largest thickness defaults to
``slicing.layer_thickness_mm``: cells depositing paste or semi-solid materials, whose bead
aspect ratio allows thick layers on vertical walls, turn it on.

Downstream, each layer's thickness travels with it (``Layer.thickness``,
``LayerPaths.thickness``, ``LayerMotion.thickness``, the ``layer_height`` member of the
result files) and is used where one thickness was assumed: the overhang scaffold's reach
(``icefab.regions``), the measurement schedule, by height (``icefab.stages.measured_layers``),
the valve flow q = w dh_k c (eq. 6.2; ``icefab valves``, the simulator's valve programs, the
SMF headroom check), the simulator's nominal heights and SMF's measurement interval
(``icefab.sim``). Path widths stay the nozzle's (``materials.*.path_width_mm``): a thinner
layer gets less flow along the same paths, not narrower ones. The build runner refuses
adaptive trajectories for now (its journal and virtual cell count in uniform layers).

The layer planner works on a fine grid of heights (bins of a quarter of the minimum
thickness): each bin holds the largest |n_z| of the facets reaching into it, and a sparse
table answers "the largest |n_z| in this slab" in O(1) per query (conservative by up to a
bin at each end: a layer may come out thinner than it needs to, never with a larger cusp).

May import: ``icefab.core``, ``icefab.config``, ``icefab.errors``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icefab.core import Mesh, offsets

#: Facets whose |n_z| is at least this are horizontal (flats).
FLAT = 1.0 - 1e-9


@dataclass(frozen=True)
class AdaptiveLayers:
    """Layer bottoms and tops (n + 1,) float64 mm of a cusp-bounded slicing, with
    figures: ``cusp`` (n,) the bound each layer keeps (t_k * max |n_z| in it, mm),
    ``uniform_layers`` the count uniform slicing needs for the same bound (one thickness
    for the whole part, thin enough for its flattest wall: C_max / max |n_z|, within the
    thickness range)."""

    edges: np.ndarray
    cusp: np.ndarray
    uniform_layers: int


def _normals_z(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(facet z min, facet z max, |n_z|) of every facet with an area."""
    v = mesh.vertices[mesh.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 0
    return v[ok, :, 2].min(axis=1), v[ok, :, 2].max(axis=1), np.abs(n[ok, 2]) / norm[ok]


class _RangeMax:
    """Largest value over bins [i, j) in O(1) after an O(n log n) sparse table."""

    def __init__(self, values: np.ndarray) -> None:
        self.levels = [values]
        k = 1
        while 2 * k <= len(values):
            prev = self.levels[-1]
            self.levels.append(np.maximum(prev[:-k], prev[k:]))
            k *= 2

    def __call__(self, i: int, j: int) -> float:
        if j <= i:
            return 0.0
        lev = (j - i).bit_length() - 1
        a = self.levels[lev]
        return float(max(a[i], a[j - (1 << lev)]))


def _flats_inside(flats: np.ndarray, z0: float, t: float, t_min: float, cap: float,
                  eps: float) -> float:
    """The thickness (mm) of the layer from ``z0`` (mm) that its slanted facets allow to
    be ``t``, once the flats (sorted heights, mm) inside it count. The first flat at least
    ``t_min`` above ``z0`` ends the layer (a boundary costs no staircase). One nearer
    ``z0`` cannot end it and counts like any facet (|n_z| = 1): the layer is at most
    ``cap`` = max(t_min, cusp) thick, and a flat from ``t_min`` up ends that one again.
    Without the cap such a layer took the slanted facets' thickness (a 0.15 mm step
    under a 2 mm layer was cut through its middle and lost)."""
    i = int(np.searchsorted(flats, z0 + eps, side="right"))   # the first flat above z0
    if i == len(flats) or flats[i] >= z0 + t - eps:
        return t
    if flats[i] >= z0 + t_min - eps:
        return float(flats[i] - z0)
    t = min(t, cap)
    k = int(np.searchsorted(flats, z0 + t_min - eps))
    return float(flats[k] - z0) if k < len(flats) and flats[k] < z0 + t - eps else t


def _before_flat(flats: np.ndarray, z0: float, t: float, t_min: float, eps: float
                 ) -> float:
    """The thickness (mm) of the layer ``[z0, z0 + t]`` (mm) shortened so the next layer
    ends on a flat (sorted heights, mm) that lies less than ``t_min`` above its top: the
    next layer could not end on that flat and would hold it (a cusp of its whole
    thickness); ended ``t_min`` below the flat it gets a layer of ``t_min`` that ends
    there. Only when this layer keeps ``t_min`` and no flat comes to lie in the next."""
    k = int(np.searchsorted(flats, z0 + t + eps, side="right"))  # the first flat above
    if k == len(flats) or flats[k] >= z0 + t + t_min - eps:
        return t
    shorter = float(flats[k] - t_min - z0)
    passed = k > 0 and flats[k - 1] > z0 + shorter - eps   # a flat it would move above
    return shorter if shorter >= t_min - eps and not passed else t


def plan_layers(mesh: Mesh, z_lo: float, z_hi: float, cusp_mm: float, t_min: float,
                t_max: float) -> AdaptiveLayers:
    """Layer edges from ``z_lo`` to ``z_hi`` (mm) keeping every layer's cusp height under
    ``cusp_mm`` within thicknesses ``[t_min, t_max]`` (the module docstring).

    The last layer ends at ``z_hi``; when what a layer would leave is thinner than
    ``t_min``, the last two layers share the rest equally (each no thicker than the bound
    allows, either may be under ``t_min``).
    """
    if not (cusp_mm > 0 and 0 < t_min <= t_max):
        raise ValueError(f"plan_layers: cusp {cusp_mm!r} must be > 0 and 0 < t_min "
                         f"{t_min!r} <= t_max {t_max!r}")
    fz0, fz1, nz = _normals_z(mesh)
    slanted = nz < FLAT
    b = t_min / 4.0
    nbins = max(1, int(np.ceil((z_hi - z_lo) / b)))
    lo = np.clip(np.floor((fz0[slanted] - z_lo) / b).astype(np.int64), 0, nbins - 1)
    hi = np.clip(np.floor((fz1[slanted] - z_lo) / b).astype(np.int64), 0, nbins - 1)
    # every facet marks the bins it reaches into (facets are short: a few bins each)
    count = hi - lo + 1
    idx = np.repeat(lo - offsets(count)[:-1], count) + np.arange(int(count.sum()))
    bins = np.zeros(nbins)
    np.maximum.at(bins, idx, np.repeat(nz[slanted], count))
    rmq = _RangeMax(bins)
    flats = np.unique(fz0[~slanted])
    flats = flats[(flats > z_lo) & (flats < z_hi)]
    steepest = float(bins.max()) if len(bins) else 0.0
    if len(flats):
        steepest = 1.0

    def need(z0: float, t: float) -> float:
        """Largest |n_z| of the slanted facets reaching into [z0, z0 + t]."""
        i = int(np.floor((z0 - z_lo) / b + 1e-9))
        j = int(np.ceil((z0 + t - z_lo) / b - 1e-9))
        return rmq(max(i, 0), min(max(j, i + 1), nbins))

    edges = [z_lo]
    cusps = []
    z0 = z_lo
    eps = 1e-9 * max(1.0, abs(z_hi))
    while z_hi - z0 > eps:
        t = t_max
        for _ in range(64):  # shrinking the slab can only lower the need: converges
            m = need(z0, t)
            t_new = t_max if m <= 0 else min(t_max, max(t_min, cusp_mm / m))
            if t_new >= t:
                break
            t = t_new
        t = _flats_inside(flats, z0, t, t_min, max(t_min, cusp_mm), eps)
        t = _before_flat(flats, z0, t, t_min, eps)
        rest = z_hi - z0
        if rest <= t + eps:
            t = rest                      # the last layer
        elif rest - t < t_min - eps:
            t = 0.5 * rest                # the last two share what is left (each <= t)
        z0 = z_hi if abs(z_hi - (z0 + t)) <= eps else z0 + t
        edges.append(z0)
        bottom = edges[-2]
        inside = bool(np.any((flats > bottom + eps) & (flats < z0 - eps)))
        cusps.append((z0 - bottom) * (1.0 if inside else need(bottom, z0 - bottom)))
    t_uniform = t_max if steepest <= 0 else min(t_max, max(t_min, cusp_mm / steepest))
    uniform = max(1, int(round((z_hi - z_lo) / t_uniform)))
    return AdaptiveLayers(edges=np.asarray(edges), cusp=np.asarray(cusps),
                          uniform_layers=uniform)
