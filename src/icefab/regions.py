"""Scaffold regions: what the scaffold material fills in every layer (thesis 3.3, 3.7).

Algorithm (thesis 3.3, RPSCAF):

1. A *merged* region ``M_k`` for every layer ``k``: the union of the part regions of all
   layers at and above ``k``. It is a scan from the top with one Boolean union per layer,
   ``M_k = M_{k+1} u P_k`` (sequential, like the thesis).
2. ``surround`` mode: the scaffold of layer ``k`` is ``expand(M_k, buffer) - P_k``
   (thesis: BUFFERF on the merged region, then a Boolean subtraction), independently per
   layer, so it runs on a process pool over chunks of layers (``job.cell.cpus``).
   ``buffer = 0`` gives classic support: only what is above. With a buffer:

   * the outer wall ``E_k = expand(M_k, buffer)`` is smoothed within ``smoothing_mm``
     and grown back over ``E_k`` (:func:`smoothed_wall`: the scaffold only gets wider, by
     up to about twice the smoothing). Why: the buffer's offset keeps every wiggle of a
     scanned part's slices, and the outermost scaffold paths at 125 mm/s crawl along them
     under the jerk bound (issue 15: within 0.1 mm, -1.8 % of the MTTS time on 5 bunny
     layers; more widens the band between part and wall past what its two boundary paths
     cover, and leaves slivers unfilled);
   * then ``O_k = W_k u shrink(O_{k+1}, d_k)`` from the top, ``d_k`` being layer
     ``k + 1``'s thickness times tan(``overhang_angle_deg``), so no wall leans out over
     the one below by more than the limiting angle (:func:`leaning_walls`). Mitred
     offsets are not nested: the sharp tip of a bunny's ear mitres up to twice the buffer
     out, the blunter tip of the layer below less, and the exact walls leaned out by over
     1 mm per layer there.
3. ``overhang`` mode (Ossino 4: compare adjacent layers, limiting angle 0-45 deg): the
   area of the layer above ``U_{k+1} = P_{k+1} u S_{k+1}`` not carried by the part within
   the limiting angle, ``N_k = U_{k+1} - expand(P_k, t * tan(angle))``, needs support;
   the scaffold is that area grown back to the part, ``S_k = (expand(N_k, t * tan(angle))
   n U_{k+1}) - P_k``, so no empty band separates them. A sequential scan from the top.
4. Subset: layers whose height fraction lies outside ``job.scaffold.subset`` get no
   scaffold (control-file entry "scaffolding subset").
5. Thin scaffold pieces: the part of the scaffold removed by an opening of radius
   ``min_width / 2`` is dropped, except where it lies under part of the layers above
   (there it is kept: merged with the scaffold around it, never leaving a part unsupported).
   Surround narrower than ``min_width`` (a slot between two walls, or a buffer below
   ``min_width``) is removed too; ``min_width_mm = 0`` keeps everything.
6. Thin part features (narrower than the part path width) are reported in
   ``Stack.warnings`` with their layer and location, not silently lost.
7. Ice hook wall (thesis 3.7, Fig. 3-8): on layers 0-19 that keep scaffold (inside the
   subset, and with some scaffold at all) the scaffold is grown outward by the band the
   two-ring wall takes (:func:`hook_band_mm` ``(2)``), so the wall does not eat into
   the surround, cannot merge with the part, and the outline does not step out at layer
   10; the rings themselves are made by ``icefab.paths``. The wall anchors scaffold: a
   layer without scaffold gets none.

The full surround is whole up to twice the point filter: ``expand`` filters the merged
region's rings before growing them and the grown rings after, and each filter moves an
edge inward by at most ``max_filter_deviation_mm`` (its chords cut across convex bends),
so the scaffold's outer edge lies at least ``buffer - 2 * filter`` from the part.

Degenerate cases: empty layers (no part) take the merged region of the layers above
unchanged (scaffold columns pass through them); an empty stack returns unchanged. Slicer
coordinates are rounded to Clipper's 1e-4 mm grid, so part and scaffold may overlap by
up to that grid along their shared edges.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from typing import Callable, Sequence

import numpy as np

from icefab import geometry as geo
from icefab.config import Job, MaterialSettings
from icefab.errors import GeometryError
from icefab.core import Region, Stack
from icefab.geometry import signed_area
from icefab.stages import adopt_layers, check_layer_thickness, check_layers_agree
from icefab.workload import check_paths
from icefab.parallel import n_workers, parallel_map  # noqa: F401  (n_workers: old home)

log = logging.getLogger(__name__)

#: Thin features smaller than this area (mm^2) are not reported.
THIN_REPORT_AREA_MM2 = 0.5


# --------------------------------------------------------------------------- scans


def merged_regions(parts: Sequence[Region]) -> list[Region]:
    """``M_k``: union of the part regions at and above layer k (one union per layer)."""
    out: list[Region] = [Region()] * len(parts)
    above = Region()
    for k in range(len(parts) - 1, -1, -1):
        if parts[k].is_empty:
            cur = above
        elif above.is_empty:
            cur = parts[k]
        else:
            cur = geo.union(above, parts[k])
        out[k] = cur
        above = cur
    return out


def _in_subset(stack: Stack, job: Job) -> np.ndarray:
    """(n,) bool: layers whose height fraction lies inside ``job.scaffold.subset``."""
    n = len(stack.layers)
    if n == 0:
        return np.zeros(0, dtype=bool)
    lo, hi = job.scaffold.subset
    if (lo, hi) == (0.0, 1.0):
        return np.ones(n, dtype=bool)
    frac = (np.arange(n) + 0.5) / n
    return (frac >= lo) & (frac <= hi)


#: Window of the outer wall's smoothing (``scaffold.smoothing_mm``): the standard deviation
#: (mm) of :func:`icefab.geometry.smooth_rings`' window, as the fill rings'
#: (``paths.FILL_SMOOTH_SIGMA_MM``): a scan's wiggles span a few millimetres. On 5 bunny
#: layers, smoothing within 0.5 mm (its first form), 3 / 5 / 8 mm took 2.2 / 2.9 / 2.0 % off
#: the MTTS time (BENCHMARKS.md, issue 15).
WALL_SMOOTH_SIGMA_MM = 5.0


def smoothed_wall(outer: Region, tol_mm: float, filt: float) -> Region:
    """``outer`` with its rings smoothed within ``tol_mm`` (corners over 60 degrees kept,
    :func:`icefab.geometry.smooth_rings`), chord-filtered within ``filt`` (the smoothing
    leaves a point every 0.01 mm of deviation, for the robot; a region's edge needs the
    slices' filter only: 17 % more scaffold points on the bunny without it) and grown by as
    far as ``outer`` reached outside the smoothed rings plus ``filt``, united with
    ``outer``: it holds ``outer`` and lies within about ``2 tol_mm + filt`` of it. (The
    union is for the rare point the smoothing's reach misses: on teeth 0.25 mm high every
    2 mm, 0.07 mm^2 of a 20 mm disk stayed out.) ``tol_mm`` <= 0 or an empty region:
    ``outer`` itself."""
    if not tol_mm > 0 or outer.is_empty:
        return outer
    rings, reach = geo.smooth_rings(list(outer.rings), tol_mm, WALL_SMOOTH_SIGMA_MM)
    if reach <= 0:
        return geo.union(outer, rings)
    smooth = geo.region_from_rings(geo.simplify(rings, filt))
    return geo.union(outer, geo.expand(smooth, reach + filt, 0.0))


def _wall_task(args: tuple[Region, Region, float, float, float, float]
               ) -> tuple[Region, list[tuple[np.ndarray, float]]]:
    """The outer wall of one layer's surround, ``expand(M_k, buffer)`` smoothed within
    ``smoothing`` (:func:`smoothed_wall`), and the layer's thin part features (one task,
    so the layer crosses to a worker process once)."""
    merged, part, buffer, smoothing, filt, width = args
    thin = _thin_part_task((part, width, filt))
    if merged.is_empty:
        return Region(), thin
    if buffer <= 0:
        return merged, thin
    return smoothed_wall(geo.expand(merged, buffer, filt), smoothing, filt), thin


def leaning_walls(walls: Sequence[Region], leans: Sequence[float]) -> list[Region]:
    """``O_k = W_k u shrink(O_{k+1}, leans[k])`` from the top: every wall holds the one
    above it shrunk by ``leans[k]`` mm, so no wall leans out over the one below it by more
    than that (``leans[-1]``, the top's, is not used). Sequential, one shrink and one union
    per layer (0.45 s for the 1 200 bunny layers)."""
    out: list[Region] = [Region()] * len(walls)
    above = Region()
    for k in range(len(walls) - 1, -1, -1):
        cur = walls[k]
        if not above.is_empty:
            inner = geo.shrink(above, leans[k], 0.0) if leans[k] > 0 else above
            if cur.is_empty:
                cur = inner
            elif not inner.is_empty:
                cur = geo.union(cur, inner)
        out[k] = cur
        above = cur
    return out


def _surround_task(args: tuple[Region, Region, Region, float, float]) -> Region:
    """Scaffold of one layer (surround mode): its outer wall less the part, thin pieces
    dropped (:func:`_drop_thin`)."""
    outer, part, part_above, min_width, filt = args
    if outer.is_empty:
        return Region()
    scaffold = geo.difference(outer, part) if not part.is_empty else outer
    return _drop_thin(scaffold, part_above, min_width, filt)


def _drop_thin(scaffold: Region, part_above: Region, min_width: float, filt: float) -> Region:
    """Remove scaffold pieces narrower than ``min_width`` unless they carry part above."""
    if min_width <= 0 or scaffold.is_empty:
        return scaffold
    # What is kept is grown by twice the point filter so the filter's chords along curved
    # edges do not count as thin pieces.
    kept = geo.opening(scaffold, min_width / 2.0, filt, margin=2.0 * filt + 1e-3)
    thin = geo.difference(scaffold, kept)
    if thin.is_empty or thin.area < 1e-9:
        return scaffold
    needed = geo.intersection(thin, part_above) if not part_above.is_empty else Region()
    # Drop thin slivers: scaffold minus (thin minus needed). Clipping the original keeps
    # its exact edges against the part.
    dropped = geo.difference(thin, needed) if not needed.is_empty else thin
    if dropped.area < 1e-9:
        return scaffold
    return geo.difference(scaffold, dropped)


def _thin_part_task(args: tuple[Region, float, float]) -> list[tuple[np.ndarray, float]]:
    part, width, filt = args
    if part.is_empty or width <= 0:
        return []
    # Use a slightly smaller radius so features exactly one path wide are not reported.
    kept = geo.opening(part, 0.5 * width * 0.98, filt, margin=2.0 * filt + 1e-3)
    thin = geo.difference(part, kept)
    out = []
    for poly in thin.polygons():
        a = sum(signed_area(r) for r in poly)
        if a >= THIN_REPORT_AREA_MM2:
            out.append((poly[0].mean(axis=0), a))
    return out


def check_stack(stack: Stack, job: Job) -> None:
    """What a stage taking a Stack checks first: the job's layer thickness is the stack's
    (:func:`icefab.stages.check_layer_thickness`), each layer's own thickness (NaN: the
    stack's) lies in (0, the thickest the job allows], and every region's rings run as
    icefab orients them: outer rings (even depth) counter-clockwise, holes clockwise. A
    Stack a program built with its outer rings clockwise got no part path and a scaffold
    around nothing; a negative thickness commanded a negative volume (a tester's). Layers
    run bottom first: each ``z`` finite and above the one before. The thickest layer is
    the stack's adaptive settings' (:func:`icefab.stages.adopt_layers`: a job with adaptive
    layers off takes them, one that contradicts them is refused)."""
    check_layer_thickness(stack.layer_thickness, job)
    if stack.job is not None and stack.job is not job:
        check_layers_agree(stack.job, job, "the stack's layers", "icefab slice")
    sl = adopt_layers(stack.job, job).slicing
    thickest = max(sl.layer_thickness_mm, sl.max_layer_thickness_mm)
    below = -math.inf
    for k, layer in enumerate(stack.layers):
        z = float(layer.z)
        # layers go up: the scaffold is merged from the top down, the measured layers and
        # the simulator's surface follow the order (a NaN or descending z went through)
        if not math.isfinite(z) or z <= below:
            raise GeometryError(f"layer {k}: z = {z!r} mm: layers must be given bottom first, "
                                f"each z finite and above the one below ({below:g} mm)")
        below = z
        t = float(layer.thickness)
        if not math.isnan(t) and not 0.0 < t <= thickest * (1 + 1e-9):
            raise GeometryError(f"layer {k}: thickness {t!r} mm: expected NaN (the stack's) "
                                f"or a thickness in (0, {thickest:g}] mm "
                                "(slicing.max_layer_thickness_mm)")
        for what, region in (("part", layer.part), ("scaffold", layer.scaffold)):
            if not len(region.rings):
                continue
            depth = region.depth()
            areas = geo.ring_areas(list(region.rings))
            wrong = np.flatnonzero(np.where(depth % 2 == 0, areas < 0, areas > 0))
            if len(wrong):
                i = int(wrong[0])
                kind = "an outer ring" if depth[i] % 2 == 0 else "a hole"
                raise GeometryError(
                    f"layer {k}: {what} ring {i} is {kind} wound "
                    f"{'clockwise' if areas[i] < 0 else 'counter-clockwise'}: icefab's outer "
                    "rings run counter-clockwise and holes clockwise: reverse the rings "
                    "wound the other way")


def add_scaffold(stack: Stack, job: Job | None = None, *,
                 progress: Callable[[int, int], None] | None = None) -> Stack:
    """The stack with every layer's ``scaffold`` region filled in (thesis 3.3).

    stack: layers bottom first, with their ``part`` regions.
    job: settings (``job.scaffold``, ``job.materials.part.path_width_mm`` for the thin
        part report, ``job.cell.cpus``); default ``stack.job``.
    progress: optional ``progress(done, total)`` callback for the per-layer work.
    Returns a new Stack; ``warnings`` gains one line per thin part feature (layer, x, y,
    area) narrower than the part path width. ConfigError if ``job``'s layer thickness
    contradicts the stack's (the thickness the stack was sliced at travels with it).
    """
    job = job or stack.job
    check_stack(stack, job)
    # the paths' budget, before the walls' work: a program's 4 km square took 52 s and
    # 3.5 GB here for one layer before plan_paths refused it
    check_paths((sum(layer.part.area for layer in stack.layers), 0.0), job)
    s = job.scaffold
    layers = list(stack.layers)
    n = len(layers)
    parts = [layer.part for layer in layers]
    filt = job.slicing.max_filter_deviation_mm
    warnings = list(stack.warnings)

    width = job.materials.part.path_width_mm
    scaffolds: list[Region] = [Region()] * n
    thin: list[list[tuple[np.ndarray, float]]] | None = None
    if s.enabled and n:
        merged = merged_regions(parts)
        part_above = merged[1:] + [Region()]
        if s.mode == "surround":
            half = None if progress is None else (lambda d, t: progress(d, 2 * t))
            rest = None if progress is None else (lambda d, t: progress(t + d, 2 * t))
            done = parallel_map(_wall_task, [(merged[k], parts[k], s.buffer_mm,
                                              s.smoothing_mm, filt, width)
                                             for k in range(n)], job, progress=half)
            walls = [d[0] for d in done]
            thin = [d[1] for d in done]
            if s.buffer_mm > 0 and s.overhang_angle_deg < 90.0:
                walls = leaning_walls(walls, _leans(stack.thicknesses, s.overhang_angle_deg))
            scaffolds = parallel_map(_surround_task, [(walls[k], parts[k], part_above[k],
                                                       s.min_width_mm, filt)
                                                      for k in range(n)], job, progress=rest)
        else:
            scaffolds = _overhang_scan(parts, part_above, stack.thicknesses, job)
        inside = _in_subset(stack, job)
        scaffolds = [sc if inside[k] else Region() for k, sc in enumerate(scaffolds)]
        if s.hook_wall:
            scaffolds = _hook_wall_room(parts, scaffolds, [L.index for L in layers], job)

    if thin is None:
        thin = parallel_map(_thin_part_task, [(p, width, filt) for p in parts], job)
    for layer, found in zip(layers, thin):
        for (x, y), a in found:
            warnings.append(f"layer {layer.index} (z = {layer.z:.3f} mm): part feature "
                            f"narrower than the path width {width} mm near x = {x:.1f}, "
                            f"y = {y:.1f} mm ({a:.1f} mm^2 thinner than a path)")
    new_layers = tuple(dataclasses.replace(layer, scaffold=sc)
                       for layer, sc in zip(layers, scaffolds))
    log.info("scaffold: %d layers, %.0f mm^2 total scaffold area", n,
             sum(sc.area for sc in scaffolds))
    return dataclasses.replace(stack, layers=new_layers, job=job, warnings=tuple(warnings))


def _leans(thickness: np.ndarray, angle_deg: float) -> np.ndarray:
    """(n,) how far (mm) layer ``k + 1`` may overhang layer ``k``: its own thickness times
    tan(``angle_deg``, at most 89 degrees) (adaptive layers: a thin layer less; the top
    layer, with none above it, its own thickness)."""
    t = np.asarray(thickness, dtype=np.float64)
    return np.append(t[1:], t[-1:]) * math.tan(math.radians(min(angle_deg, 89.0)))


def _overhang_scan(parts: list[Region], part_above: list[Region], thickness: np.ndarray,
                   job: Job) -> list[Region]:
    """Overhang-only support (Ossino 4): scan from the top comparing adjacent layers.

    thickness: (n,) every layer's thickness, mm: layer k + 1 may overhang layer k by its
    own thickness times tan(overhang angle) (adaptive layers: a thin layer less)."""
    s = job.scaffold
    filt = job.slicing.max_filter_deviation_mm
    reaches = _leans(thickness, s.overhang_angle_deg).tolist()
    # A finer point filter here: its chords must not eat into the (small) reach.
    carried = parallel_map(_expand_task, [(p, r, min(filt, r / 4.0))
                                          for p, r in zip(parts, reaches)], job)
    n = len(parts)
    out: list[Region] = [Region()] * n
    above = Region()  # P_{k+1} u S_{k+1}
    for k in range(n - 1, -1, -1):
        if above.is_empty:
            sc = Region()
        elif parts[k].is_empty:
            sc = above
        else:
            # Support is needed where the layer above is not carried within the limiting
            # angle; it then reaches back to the part (no empty band between the two).
            needed = geo.difference(above, carried[k])
            if needed.area < 1e-6:
                sc = Region()
            else:
                grown = geo.expand(needed, reaches[k] + 2.0 * filt + 1e-3, filt)
                sc = geo.difference(geo.intersection(grown, above), parts[k])
                sc = _drop_thin(sc, part_above[k], s.min_width_mm, filt)
        out[k] = sc
        if parts[k].is_empty:
            above = sc
        elif sc.is_empty:
            above = parts[k]
        else:
            above = geo.union(parts[k], sc)
    return out


def _expand_task(args: tuple[Region, float, float]) -> Region:
    """The region grown by ``d``, always containing the exact region (the point filter's
    chords may cut inside it when ``d`` is smaller than the filter)."""
    region, d, filt = args
    if d <= 0 or region.is_empty:
        return region
    return geo.union(region, geo.expand(region, d, filt))


def hook_band_mm(count: int, mat: MaterialSettings) -> float:
    """Width of the outer scaffold band the hook wall's ``count`` ice rings take, mm
    (thesis 3.7): the regions grow by it (``count = 2``), ``icefab.paths`` cuts the rings
    from it."""
    if count <= 0:
        return 0.0
    return mat.initial_offset_mm + (count - 0.5) * mat.path_width_mm


def _hook_wall_room(parts: list[Region], scaffolds: list[Region], indices: list[int],
                    job: Job) -> list[Region]:
    """Extra scaffold outside layers 0-19 for the ice hook wall (thesis 3.7).

    Every one of those layers grows by the band of the two-ring wall, so the outline does
    not step outward at layer 10 (no overhang): layers 0-9 get one ice ring at the
    outside, layers 10-19 a second one just inside it, on top of scaffold: the hook.
    """
    filt = job.slicing.max_filter_deviation_mm
    out = list(scaffolds)
    band = hook_band_mm(2, job.materials.scaffold)
    for k, index in enumerate(indices):
        # only where the layer keeps scaffold: not outside the scaffolding subset, not
        # where there is none (classic support on a part without overhang)
        if index >= 20 or scaffolds[k].is_empty:
            continue
        both = geo.union(parts[k], scaffolds[k])
        grown = geo.expand(both, band, filt)
        out[k] = geo.difference(grown, parts[k]) if not parts[k].is_empty else grown
    return out
