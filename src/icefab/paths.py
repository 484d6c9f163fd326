"""Deposition, measurement and travel paths of every layer (thesis 3.4-3.5, 3.7, 5.2.1).

From a ``Stack`` with part and scaffold regions to ordered ``Path``s per layer:

* Boundary paths (thesis 3.4, 3.7): boundary ``i`` (0-based) of a material is its region
  shrunk by ``initial_offset + i * path_width`` (defaults 0.6 mm water, 1.2 mm scaffold,
  path width 1.5 mm). The initial offset is the material-specific calibration of the
  thesis, so a boundary of width ``w`` may reach ``w/2 - initial_offset`` beyond the region
  edge (0.15 mm for water with the defaults): that is intended, the material spreads less.
* Fill (thesis 3.5, Jin et al. 3-4) inside the *fill edge* ``e = initial_offset + (n -
  1/2) * path_width`` (the inner edge of the last of ``n`` boundaries; with no boundary,
  ``max(initial_offset - path_width/2, 0)``):

  - ``concentric``: rings at ``e + F/2``, then every ``F`` (fill width) inward until
    nothing is left (iterative Clipper offsets, points filtered after each); a ring
    never gets a path wider than its room: the innermost rings are cut to the part of
    their area at least ``F`` wide (:func:`_with_room`), the rest goes to the gap fill.
    With ``fill_smoothing_mm`` > 0 the first ring follows the smoothed contour and every
    ring, the first too, is smoothed within ``RING_SMOOTHING * F`` (in a wider window,
    ``RING_SMOOTH_SIGMA_MM``), its bead widened where it moved inward (a width per point,
    :func:`concentric_levels`);
  - ``zigzag``: parallel lines spaced ``F``, clipped to the region shrunk by ``e + F/2``,
    consecutive lines linked where the link stays inside; each island of the region at
    the angle (in steps of ``hybrid_angle_step_deg`` over [0, 180)) with the least time
    by Jin's model (eqs. 8-18, :func:`jin_segment_time`), or at ``fill_angle_deg`` with
    ``fill_angle_mode = "fixed"``;
  - ``raster``: the same lines unlinked, each its own path (the thesis' ZZFILL);
  - ``hybrid``: ``hybrid_rings`` concentric rings, then zigzag inside at each island's
    optimal angle;
  - ``none``.

  Gap fill (``gap_fill``, on by default; not in the thesis; :func:`gap_fill_paths`): what
  the paths leave of the region gets rings of the boundary width where it has room for
  two, one ring in each pocket (constant-width gap fill only), and paths along the centre
  line of the remaining strips and pockets, as wide as the strip (less width, less flow;
  e.g. between the two scaffold boundaries where the surround is a little wider than they
  take, or the middle of a thin wall). Strips narrower than ``THIN_GAP_MIN`` path widths
  get nothing. The rest of the *nominal* area (the region shrunk by ``max(initial_offset -
  path_width/2, 0)``: the calibrated edge strip of the scaffold is empty on purpose) that
  no path sweeps is reported in ``LayerPaths.unfilled_mm2`` (paths swept with mitred
  corners and round ends; gaps narrower than twice the point filter + ``SWEEP_TOL`` are
  not counted). What the paths cover: at least 97 % of the nominal area, not counting the
  parts of the region narrower than the path width (part features so thin are reported by
  ``add_scaffold``; tested on every layer of the real meshes).
* No deposition path crosses or touches itself (the point filter keeps rings simple,
  :func:`icefab.geometry.simplify`; centre lines never double back).
* Measurement paths (thesis 5.2.1): on layers with ``(index + 1) % interval_layers == 0``,
  concentric rings over each material's region (shrunk by half the measurement spacing,
  then every spacing), joined into spirals where they nest (:func:`join_measure_rings`:
  the laser runs from one ring into the next without a stop), and the centre lines of
  what they leave unmeasured (a wall narrower than the spacing: :func:`measure_paths`),
  role "measure", one material per path, given for the laser tool.
* Order within a layer: ``job.materials.order`` (default part boundaries, part fill,
  scaffold boundaries, scaffold fill), measurement paths last; inside each set nearest
  neighbour from the current position (the layer starts at the part-frame origin), with the
  start point of every closed path chosen as its point nearest to the current position and
  either end of an open path, then shortened by 2-opt and a better start vertex for each
  closed path (:func:`icefab._tour.improve`: never longer than nearest neighbour);
  continuous tours (:func:`join_tours`, issue 15): consecutive boundary or fill paths of
  one material joined through a travel curve the robot does not stop for, the valve off
  over it (``Toolpath.off``), where the heading turns by at most
  ``materials.*.tour_max_turn_deg``; explicit travel paths (role "travel", width 0)
  between consecutive paths. Measurement paths and tours stay within what the robot
  controller stores of one path (:func:`path_store_s`).
* Reference frames (thesis Table 3-1): points are in the part (building) frame of the tool
  that follows them (``Path.tool_name``). See :func:`to_base_frame`. A travel path is given
  for the tool of the path that follows it; when the tool changes, its first point is the
  previous end point shifted by the difference of the two tool offsets, so the end effector
  moves continuously in the base frame.
* Deposition state per point (Ossino 6): ON1 (part), ON2 (scaffold) or OFF, the state
  of the segment leaving the point: :func:`point_states` (one path),
  :func:`layer_point_states` (a layer's points in order, with states), stored per point
  in the toolpath file (``state``).
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Iterator, NamedTuple, Sequence

import numpy as np

from icefab import _tour
from icefab import geometry as geo
from icefab.config import Job, MaterialSettings
from icefab.frames import FRAME_TOOLS as TOOLS, tool_offset, to_base_frame  # noqa: F401 (old home)
from icefab.parallel import parallel_imap
from icefab.stages import measured_layers
from icefab.regions import check_stack, hook_band_mm
from icefab.robots import CONTROLLER_PATH_POINTS
from icefab.resultfiles import (TOOLPATHS_FORMAT as FORMAT, TOOLPATHS_VERSION as VERSION,  # noqa: F401
                                LayerHead, PackedToolpaths, load_toolpaths, pack_layer_paths,
                                packed_lengths, save_toolpaths, unpack_layer_paths)
from icefab.geometry import signed_area
from icefab.core import (MATERIALS, OFF, ON1, ON2, ROLES, Layer, LayerPaths,  # noqa: F401
                         Region, Stack, Toolpath, Toolpaths, arc_lengths, area_text,
                         closed_polyline, deposition_state, mean_width, offsets, path_lengths,
                         point_states, split_rows)
from icefab.workload import check_paths

log = logging.getLogger(__name__)


def layer_point_states(layer: LayerPaths) -> tuple[np.ndarray, np.ndarray]:
    """A layer's points in the order the tools visit them, with Ossino's state of each.

    Returns (points (N, 2) float64 mm, states (N,) int8): the points of every path in
    order (travel paths included), a closed path followed by its first point again;
    ``states[i]`` is the state of the segment from point i to point i + 1 (ON1 part,
    ON2 scaffold, OFF), so the end point of every path marks the start of a segment that
    does not deposit (Ossino 6: "the end-point of every closed contour must mark the
    start of a non-depositing segment"). Points are in the part frame of the tool that
    follows their path (``Path.tool_name``; :func:`to_base_frame`).
    """
    pts: list[np.ndarray] = []
    states: list[np.ndarray] = []
    for p in layer.paths:
        st = point_states(p)
        if p.closed and len(p.points):
            pts.append(closed_polyline(p.points))
            states.append(np.append(st, np.int8(OFF)))
        else:
            pts.append(p.points)
            states.append(st)
    if not pts:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int8)
    return np.concatenate(pts).astype(np.float64), np.concatenate(states).astype(np.int8)


# --------------------------------------------------------------------------- fill pieces


def _fill_edge(mat: MaterialSettings) -> float:
    n = mat.boundary_count
    if n == 0:
        return max(mat.initial_offset_mm - mat.path_width_mm / 2.0, 0.0)
    return mat.initial_offset_mm + (n - 0.5) * mat.path_width_mm


#: Window of the boundaries' smoothing within the point filter: the standard deviation
#: (mm) of :func:`icefab.geometry.smooth_rings`' window. On 10 bunny layers boundary MTTS
#: time fell by 15 / 18.5 / 18 % with 5 / 2 / 1 mm (BENCHMARKS.md, issue 15).
BOUNDARY_SMOOTH_SIGMA_MM = 2.0


def boundary_rings(region: Region, mat: MaterialSettings, filt: float) -> list[list[np.ndarray]]:
    """Boundary path rings of a region, outermost first (thesis 3.4, 3.7).

    Each is the exact offset smoothed within the point filter ``filt``
    (:func:`icefab.geometry.smooth_rings`, corners over 60 degrees kept) instead of
    chord-filtered within it: as close to the exact offset as the filter keeps it, without
    the wiggles of a scanned contour that hold a jerk-limited robot to a crawl (issue 15).
    Returns one list of (k, 2) float64 rings (mm) per boundary.
    """
    out: list[list[np.ndarray]] = []
    rings = list(region.rings)
    for i in range(mat.boundary_count):
        d = mat.initial_offset_mm if i == 0 else mat.path_width_mm
        rings = geo.offset_rings(rings, -d, 0.0)
        if rings and filt > 0:
            rings = geo.smooth_rings(rings, filt, BOUNDARY_SMOOTH_SIGMA_MM)[0]
        if not rings:
            break
        out.append(rings)
    return out


#: Window of the fill rings' smoothing (``materials.*.fill_smoothing_mm``): the standard
#: deviation (mm) of :func:`icefab.geometry.smooth_rings`' regression window (half-width 3x).
#: The wiggles of a scanned mesh's slices span a few millimetres; 5 and 8 mm gave the same
#: MTTS time on bunny layers, 2 mm a third of the gain (BENCHMARKS.md, issue 15).
FILL_SMOOTH_SIGMA_MM = 5.0


def concentric_rings(region: Region, start_mm: float, step_mm: float, filt: float,
                     max_rings: int = 100_000, width_mm: float = 0.0,
                     smooth_mm: float = 0.0, ring_smooth_mm: float = 0.0,
                     corner_deg: float = 60.0) -> list[list[np.ndarray]]:
    """Rings of ``region`` shrunk by ``start_mm``, then every ``step_mm`` until empty
    (:func:`concentric_levels` without the bead widths)."""
    return concentric_levels(region, start_mm, step_mm, filt, max_rings, width_mm,
                             smooth_mm, ring_smooth_mm, corner_deg).levels


def concentric_levels(region: Region, start_mm: float, step_mm: float, filt: float,
                      max_rings: int = 100_000, width_mm: float = 0.0,
                      smooth_mm: float = 0.0, ring_smooth_mm: float = 0.0,
                      corner_deg: float = 60.0,
                      ring_sigma_mm: float = FILL_SMOOTH_SIGMA_MM) -> "FillLevels":
    """Rings of ``region`` shrunk by ``start_mm``, then every ``step_mm`` until empty, and
    the width of the bead along each.

    width_mm: the width of the paths along the rings; when > 0 every ring is given room
        for it (:func:`_with_room`): a ring whose area is narrower than the path would
        overlap itself.
    smooth_mm: when > 0 the rings follow a smoothed contour (issue 15: the robot's jerk
        and acceleration bounds make it crawl along the wiggles of a scanned mesh and
        round every corner of an offset slowly):

        * the edge of the first ring's band (``region`` shrunk by ``start_mm - step_mm /
          2``) is smoothed within ``smooth_mm`` (:func:`icefab.geometry.smooth_rings`)
          and grown by as much as the true edge reaches outside it (at most ``smooth_mm``;
          nothing on a clean contour), so it lies outside the true edge everywhere: the
          first band overlaps what is outside it by up to ``2 smooth_mm`` and leaves no
          sliver. The first ring is ``step_mm / 2`` inside it. Where that and the first
          ring's smoothing would reach past the region's edge (less room than that
          outside the first band: no boundaries), the first level is not smoothed.
        * every ring, the first (the offset of the smoothed edge) too when ``width_mm``
          > 0, is smoothed within ``ring_smooth_mm`` in a window of ``ring_sigma_mm``
          (corners turning by over ``corner_deg`` kept; the edge's smoothing keeps those
          over 60 degrees; the first measurement ring stays put, so the laser keeps off
          the edge), and the next is offset from the smoothed ring, so the moves never
          add up. Offsetting inward turns the bumps of a contour into corners (where the
          offset swallows a bump narrower than the offset), and what the edge's smoothing
          left of the noise into wiggles; rounded, they no longer stop or slow the robot (the first
          ring of the bunny's middle layer: 8.72 -> 7.42 s for 633 mm). Where a ring
          moved inward, away from the band outside it, by more than the point filter
          (which the sweeps allow for), its bead is widened by twice the excess (when
          ``width_mm`` > 0): the valve lays ``w(s) dh c(s)`` and the band outside stays
          covered; where it moved outward the beads overlap. The first ring's bead is
          widened by twice its whole inward move: with the filter's allowance it left
          slivers against the boundaries' band (exact disk hulls, shapely:
          ``tests/test_paths.py``).
        * with ``ring_smooth_mm`` <= ``filt`` the rings are smoothed within ``filt`` (as
          far as the point filter moves them anyway).
    Returns a :class:`FillLevels` without lines: one list of (k, 2) float64 rings (mm)
    per offset level, outermost first; the same lists of bead widths (None for a ring
    ``width_mm`` wide all along, else (k,) float64 mm, one per point, >= ``width_mm``);
    per level, the rings whose area the widened beads' outer edge also holds.
    """
    out: list[list[np.ndarray]] = []
    widths: list[list[np.ndarray | None]] = []
    held_by: list[list[np.ndarray]] = []
    # the first band may reach outward over its edge by up to twice smooth_mm and the
    # first ring's own smoothing: with less room than that between the band's edge and
    # the region's (no boundary outside it: boundary_count = 0), the first level is not
    # smoothed (fuzzing found a first fill ring's bead 0.5 mm past the part's edge)
    room = start_mm - step_mm / 2.0
    tight = width_mm > 0 and smooth_mm > 0 and \
        2.0 * smooth_mm + max(ring_smooth_mm, filt) > room + filt
    if smooth_mm > 0 and not tight:
        edge = geo.offset_rings(list(region.rings), -room, filt)
        smooth, reach = geo.smooth_rings(edge, smooth_mm, FILL_SMOOTH_SIGMA_MM)
        rings = geo.offset_rings(smooth, -(step_mm / 2.0 - reach), filt)
    else:
        rings = geo.offset_rings(list(region.rings), -start_mm, filt)
    while rings and len(out) < max_rings:
        raw = None
        first = not out
        if smooth_mm > 0 and not (tight and first):
            # the first ring too when it lays a bead (widened, it leaves no sliver); a
            # measurement ring (no width) stays where the edge's smoothing put it, else
            # it could come within the laser's reach of the region's edge
            tol = max(ring_smooth_mm, filt) if (out or width_mm > 0) else filt
            if tol > filt:
                raw = rings
            rings, _reach, inward = geo.smooth_rings_moved(rings, tol, ring_sigma_mm,
                                                           corner_deg)
        nxt = geo.offset_rings(rings, -step_mm, filt)
        smoothed = rings
        if width_mm > 0:
            rings = _with_room(rings, nxt, width_mm, filt)
        if rings:
            out.append(rings)
            ws: list[np.ndarray | None] = [None] * len(rings)
            held: list[np.ndarray] = []
            if raw is not None and width_mm > 0:
                ws, held = _widened_beads(rings, smoothed, inward, raw, width_mm,
                                          0.0 if first else filt)
            widths.append(ws)
            held_by.append(held)
        rings = nxt
    return FillLevels(out, [], math.nan, widths, held_by)


def _widened_beads(rings: list[np.ndarray], smoothed: list[np.ndarray],
                   inward: list[np.ndarray], raw: list[np.ndarray], width: float,
                   filt: float) -> tuple[list[np.ndarray | None], list[np.ndarray]]:
    """Bead widths of one level of smoothed rings (:func:`concentric_levels`) and the
    rings whose area the widened beads' outer edge holds besides the smoothed rings'.

    rings: the level as :func:`_with_room` left it; smoothed: the level before that, with
    how far each point moved into the ring's area (``inward``,
    :func:`icefab.geometry.smooth_rings_moved`); raw: the level before smoothing (ring
    ``i`` of ``smoothed`` is ring ``i`` of ``raw`` smoothed). A ring's bead is ``width``
    plus twice how far its point moved inward beyond the point filter ``filt`` (which the
    swept bands are grown by), so its outer edge stays within the filter of where the raw
    ring's would be: widening by the whole move laid 0.5 % more fill on bunny layers for
    no less unfilled area, and raised the demo mug's open-loop height error from 1.868 to
    1.883 mm. None where the widening adds at most ``WIDEN_MIN_MM`` and for the rings
    ``_with_room`` replaced. ``filt`` is that allowance: the point filter, 0 for the
    first level (:func:`concentric_levels`). The outer edge of the widened beads is that
    of the smoothed rings' band or of the raw rings' shrunk by ``filt``, whichever lies
    farther out:
    the level's band is ``expand(smoothed + held, width / 2) - shrink(smoothed, width / 2)``
    (:func:`icefab.geometry.level_bands`) with ``held`` the raw rings of the level (those
    ``_with_room`` kept: whole outers with their holes) shrunk by ``filt``; none when no
    bead was widened."""
    out: list[np.ndarray | None] = [None] * len(rings)
    pos = {id(r): i for i, r in enumerate(smoothed)}
    kept = []   # the rings _with_room left: whole outers with their holes
    for i, r in enumerate(rings):
        j = pos.get(id(r))
        if j is None:
            continue
        kept.append(j)
        extra = 2.0 * np.maximum(inward[j] - filt, 0.0)
        if extra.max(initial=0.0) > WIDEN_MIN_MM:
            out[i] = width + extra
    if all(w is None for w in out):
        return out, []
    return out, geo.offset_rings([raw[j] for j in kept], -filt, 0.0)


#: Concentric fill (with ``fill_smoothing_mm`` > 0): every ring is smoothed within this
#: fraction of the fill width, its bead widened where it moved inward
#: (:func:`concentric_levels`), in a window of ``RING_SMOOTH_SIGMA_MM``. On 10 bunny
#: layers 0.1 / 0.15 / 0.25 / 0.3 mm of the 3 mm width (5 mm window) took 9.2 / 11.5 /
#: 12.9 / 13.1 % off the fill's MTTS time, the unfilled area +1.7 / 0 / +6.1 / +8.4 %
#: (BENCHMARKS.md, issue 15; the rings after the first then); the first ring too, 2 % off
#: 7 measured layers. The bumps that then still slow the robot are long: on bunny layer 550
#: the outer rings' curvature swings by ~0.02 / mm every ~30 mm, which the jerk bound
#: holds to ~100 mm/s, and a 5 mm window barely reaches them. 0.3 mm in a 7.5 mm window
#: (0.15 mm in 5 mm before): the whole bunny 87.89 -> 86.21 h (-1.9 %), unfilled 1 014 ->
#: 1 023 mm^2; the rounded box +0.7 % (one more gap path per layer where the rings of its
#: annulus meet), the demo mug's height errors unchanged; the rings' bead area +0.4 %. A
#: 10 mm window: -1.8 %, 1 038 mm^2, the box +1.3 %; 0.15 mm in 10 mm: slower than
#: before; 0.45-1.5 mm in 10-20 mm windows gained nothing more on 5 layers: what is left
#: of the rings' time is their ends and the corners inward offsets make (BENCHMARKS.md).
RING_SMOOTHING = 0.1
#: Window of every fill ring's smoothing (mm, the standard deviation as
#: ``FILL_SMOOTH_SIGMA_MM``, which stays the window of the first ring's band edge and of
#: the measurement rings).
RING_SMOOTH_SIGMA_MM = 7.5
#: A smoothed ring's bead is widened only where it would grow by more than this (mm).
WIDEN_MIN_MM = 0.01


def _has_room(ring: np.ndarray, width: float) -> bool:
    """Whether an outer ring holds a disk of diameter ``width`` (less 2 %, so a strip
    exactly as wide as the path counts), i.e. a path of that width fits inside it."""
    return bool(geo.offset_rings([ring], -0.49 * width, 0.0))


def _with_room(rings: list[np.ndarray], inner: list[np.ndarray], width: float, filt: float
               ) -> list[np.ndarray]:
    """The rings of one offset level, with room for a path of ``width`` along them.

    A ring's path reaches ``width / 2`` into the area the ring bounds; where that area is
    narrower than ``width``, the path from one side overlaps the path from the other
    (twice the material on a strip: issue 3's "no ring wider than its room"). The
    innermost polygons of the level (outer rings holding no ring of the next level
    ``inner``, with their holes) are replaced by their opening by ``width / 2``: what is
    narrower than ``width`` is cut away (the gap fill takes it, with paths of its own
    width), what is left holds a disk of diameter ``width`` under every point of its
    path. Polygons holding a next-level ring are at least ``2 step`` wide somewhere and
    keep their ring as it is (a neck narrower than the path between two wide parts of
    one ring is not detected).
    """
    areas = geo.ring_areas(rings)
    outer = np.flatnonzero(areas > 0)
    if not len(outer):
        # only holes: the slivers an offset leaves of a strip exactly twice the offset
        # wide (a 1.5 mm gap shrunk by 0.75 mm: 134 rings of 1e-5 mm^2, 51 of them holes,
        # each laid as a closed path: 94 paths on one tube where 1 was due, a hunt's)
        return []
    outer_rings = [rings[i] for i in outer]
    has_child = np.zeros(len(outer), dtype=bool)
    if inner:
        holder = geo.rings_holding(outer_rings, np.array([r[0] for r in inner]))
        has_child[holder[holder >= 0]] = True
    holes = np.flatnonzero(areas < 0)
    hole_holder = (geo.rings_holding(outer_rings, np.array([rings[h][0] for h in holes]))
                   if len(holes) else np.zeros(0, np.int64))
    orphans = {int(h) for h, o in zip(holes, hole_holder) if o < 0}   # slivers, as above
    if has_child.all():
        return [r for i, r in enumerate(rings) if i not in orphans]
    narrow = set(outer[~has_child].tolist())
    narrow.update(int(h) for h, o in zip(holes, hole_holder) if o >= 0 and not has_child[o])
    group = [rings[i] for i in sorted(narrow)]
    h = width / 2.0
    opened = geo.offset_rings(geo.offset_rings(group, -h, filt), h, filt)
    if opened:
        # clipped to what it was cut from: the mitred growth back re-sharpens corners the
        # offsets had squared off (beyond the miter limit), which stick out; slivers the
        # clipping leaves (no room) are dropped
        opened = [r for r in geo.intersection(opened, group).rings
                  if signed_area(r) < -geo.MIN_RING_AREA
                  or (signed_area(r) > geo.MIN_RING_AREA
                      and _has_room(r, width))]
    return [r for i, r in enumerate(rings) if i not in narrow and i not in orphans] + opened


def _rotate(pts: np.ndarray, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return pts @ np.array([[c, s], [-s, c]])


def raster_lines(area: Region, spacing: float, angle_deg: float) -> list[np.ndarray]:
    """Parallel lines at ``angle_deg`` spaced ``spacing`` clipped to ``area``.

    Returns open 2-point segments (mm) sorted by line then along the line direction; the
    lines are centred in the extent of ``area`` across them.
    """
    if area.is_empty:
        return []
    a = math.radians(angle_deg)
    pts = np.concatenate(area.rings)
    rot = _rotate(pts, -a)  # frame where the lines are horizontal
    (x0, y0), (x1, y1) = rot.min(axis=0), rot.max(axis=0)
    n = int(math.floor((y1 - y0) / spacing)) + 1
    ys = y0 + (y1 - y0 - (n - 1) * spacing) / 2.0 + spacing * np.arange(n)
    ys = ys[(ys > y0) & (ys < y1)] if n > 1 else np.array([(y0 + y1) / 2.0])
    if len(ys) == 0:
        return []
    lines = np.empty((len(ys), 2, 2))
    lines[:, 0, 0], lines[:, 1, 0] = x0 - 1.0, x1 + 1.0
    lines[:, :, 1] = ys[:, None]
    world = [_rotate(ln, a) for ln in lines]
    pieces = geo.clip_lines(world, area)
    if not pieces:
        return []
    segs = np.array([[p[0], p[-1]] for p in pieces])  # straight lines: keep the ends
    r = _rotate(segs.reshape(-1, 2), -a).reshape(-1, 2, 2)
    flip = r[:, 0, 0] > r[:, 1, 0]
    segs[flip] = segs[flip, ::-1]
    r[flip] = r[flip, ::-1]
    level = np.rint((r[:, 0, 1] - ys[0]) / spacing).astype(np.int64)
    order = np.lexsort((r[:, 0, 0], level))
    return [segs[i] for i in order]


#: Zigzag links may run this far outside the fill area (mm): the raster lines end on its
#: edge, so the area a link must stay in is the fill area grown by this (ten grid units).
LINK_MARGIN_MM = 1e-3


def link_zigzag(segs: list[np.ndarray], spacing: float, inside: Region, angle_deg: float
                ) -> list[np.ndarray]:
    """Link raster segments into zigzag polylines (Jin's Type I lines joined by Type II).

    segs: from :func:`raster_lines` (sorted by line, left to right in the line frame).
    inside: region every link must stay in (links leaving it are not made).
    Returns open polylines, (k, 2) float64, mm.
    """
    if not segs:
        return []
    a = math.radians(angle_deg)
    S = np.array(segs)  # (m, 2, 2)
    r = _rotate(S.reshape(-1, 2), -a).reshape(-1, 2, 2)
    level = np.rint((r[:, 0, 1] - r[:, 0, 1].min()) / spacing).astype(np.int64)
    m = len(S)
    # Candidate link from each end of segment i to the same end of the nearest segment on
    # the next line: right end -> right end, left end -> left end (alternating direction).
    cand = np.full((m, 2), -1, dtype=np.int64)
    for side in (0, 1):
        ends = r[:, side, :]
        for lv in np.unique(level):
            cur = np.flatnonzero(level == lv)
            nxt = np.flatnonzero(level == lv + 1)
            if len(nxt) == 0:
                continue
            d = np.linalg.norm(ends[cur][:, None, :] - ends[nxt][None, :, :], axis=2)
            j = np.argmin(d, axis=1)
            # links along a boundary at a shallow angle to the lines are long; the
            # inside check below is the real guard, this only stops absurd ones
            ok = d[np.arange(len(cur)), j] <= 12.0 * spacing
            cand[cur[ok], side] = nxt[j[ok]]
    # Validate all candidate links in one clipping call.
    ii, ss = np.nonzero(cand >= 0)
    valid = np.zeros((m, 2), dtype=bool)
    if len(ii):
        # sample every link at 9 interior points (at most 0.5 mm apart would be finer; the
        # links are short chords near the boundary) and test them all at once
        a = S[ii, ss]
        b = S[cand[ii, ss], ss]
        t = np.linspace(0.1, 0.9, 9)
        samples = a[:, None, :] + t[None, :, None] * (b - a)[:, None, :]
        ok = geo.points_inside(samples.reshape(-1, 2), inside).reshape(len(ii), -1).all(axis=1)
        # and no edge of ``inside`` crosses the link between its samples (a link up to
        # 12 spacings long cut across a notch of a fuzzed part's fill area, 0.13 mm
        # nearer the part's edge than the fill allows); its ends lie ``LINK_MARGIN_MM``
        # inside ``inside`` (_zigzag_at), more than the distance that counts as a crossing
        ok[ok] = np.isinf(geo.segments_to_rings_distance(a[ok], b[ok], list(inside.rings),
                                                         LINK_MARGIN_MM / 10.0))
        valid[ii, ss] = ok
    used = np.zeros(m, dtype=bool)
    out: list[np.ndarray] = []
    for start in range(m):
        if used[start]:
            continue
        chain = [S[start, 0], S[start, 1]]
        used[start] = True
        cur, side = start, 1  # we are at the right end of segment `start`
        while True:
            j = cand[cur, side]
            if j < 0 or used[j] or not valid[cur, side]:
                break
            used[j] = True
            chain.extend([S[j, side], S[j, 1 - side]])
            cur, side = j, 1 - side
        out.append(np.array(chain))
    return out


def jin_segment_time(length: np.ndarray, v_min: float, accel: float) -> np.ndarray:
    """Time to traverse straight segments starting and ending at ``v_min`` (Jin eq. 18).

    The tool accelerates at ``accel`` from ``v_min`` up to ``v_max = 2 v_min`` (eq. 13)
    and decelerates symmetrically; it reaches ``v_max`` only on segments longer than
    ``3 v_min^2 / accel`` (eq. 17 times two).
    length: (m,) float64, mm. Returns (m,) float64, s.
    """
    L = np.asarray(length, dtype=np.float64)
    crit = 3.0 * v_min ** 2 / accel
    short = (-2.0 * v_min + np.sqrt(4.0 * v_min ** 2 + 4.0 * accel * L)) / accel
    long_ = 2.0 * v_min / accel + (L - crit) / (2.0 * v_min)
    return np.where(L <= crit, short, long_)


def zigzag_time(polylines: Sequence[np.ndarray], job: Job) -> float:
    """Build time of zigzag paths by Jin's model (eqs. 8-12, 18), s.

    Every straight segment (Type I line or Type II link) starts and ends at
    ``v_min = fill_speed / 2`` (eq. 13 with ``v_max`` = the fill speed) and accelerates at
    ``job.motion.accel_mm_s2``.
    """
    if not polylines:
        return 0.0
    # Unlinked pieces cost a travel move each (timed the same way) from the end of one to
    # the start of the next, in the order they come.
    moves = [np.linalg.norm(np.diff(p, axis=0), axis=1) for p in polylines]
    moves += [np.array([np.linalg.norm(b[0] - a[-1])]) for a, b in zip(polylines[:-1],
                                                                       polylines[1:])]
    lengths = np.concatenate(moves)
    lengths = lengths[lengths > 0]
    v_min = job.motion.fill_speed_mm_s / 2.0
    return float(jin_segment_time(lengths, v_min, job.motion.accel_mm_s2).sum())


def _zigzag_at(inner: Region, spacing: float, angle: float, filt: float,
               linked: bool) -> list[np.ndarray]:
    segs = raster_lines(inner, spacing, angle)
    if not linked:
        return segs
    return link_zigzag(segs, spacing, geo.expand(inner, LINK_MARGIN_MM, 0.0), angle)


def fill_paths(region: Region, mat: MaterialSettings, job: Job
               ) -> tuple[list[tuple[np.ndarray, bool, float | np.ndarray]], float]:
    """Fill paths of one material's region: ``[(points, closed, width), ...]`` (width: mm,
    or (k,) mm per point for a widened smoothed ring) and the raster angle used (deg; NaN
    for concentric or none)."""
    fill = fill_levels(region, mat, job)
    F = mat.fill_width_mm
    return fill.paths(F), fill.angle


class FillLevels(NamedTuple):
    """Fill of one material's region (:func:`fill_levels`)."""

    levels: list[list[np.ndarray]]          # concentric rings, one list per offset level
    lines: list[np.ndarray]                 # open raster/zigzag lines
    angle: float                            # raster angle, deg (NaN: concentric or none)
    widths: list[list[np.ndarray | None]]   # per ring as ``levels``: None or (k,) mm
    held: list[list[np.ndarray]]            # per level: rings whose area the widened
                                            # beads' outer edge holds too (or none)

    def paths(self, width: float) -> list[tuple[np.ndarray, bool, float | np.ndarray]]:
        """``(points, closed, width)`` of every ring and line (``width`` unless widened)."""
        return ([(r, True, width if w is None else w)
                 for lv, ws in zip(self.levels, self.widths) for r, w in zip(lv, ws)]
                + [(ln, False, width) for ln in self.lines])


def fill_levels(region: Region, mat: MaterialSettings, job: Job) -> FillLevels:
    """Fill of one material's region as concentric ring levels (each a list of oriented
    rings at one offset) with their bead widths, open raster/zigzag lines, and the raster
    angle (deg; NaN for concentric or none)."""
    filt = job.slicing.max_filter_deviation_mm
    pattern = mat.fill_pattern
    F = mat.fill_width_mm
    e = _fill_edge(mat)
    if pattern == "none" or region.is_empty:
        return FillLevels([], [], math.nan, [], [])
    if pattern == "concentric":
        return concentric_levels(region, e + F / 2.0, F, filt, width_mm=F,
                                 smooth_mm=mat.fill_smoothing_mm,
                                 ring_smooth_mm=RING_SMOOTHING * F,
                                 ring_sigma_mm=RING_SMOOTH_SIGMA_MM)
    levels: list[list[np.ndarray]] = []
    start = e + F / 2.0
    if pattern == "hybrid" and mat.hybrid_rings > 0:
        levels = concentric_rings(region, start, F, filt, max_rings=mat.hybrid_rings,
                                  width_mm=F)
        start += mat.hybrid_rings * F
    plain = [[None] * len(lv) for lv in levels]   # no ring smoothed, none widened
    held: list[list[np.ndarray]] = [[] for _ in levels]
    inner = geo.shrink(region, start, filt)
    if inner.is_empty:
        return FillLevels(levels, [], math.nan, plain, held)
    linked = pattern != "raster"
    if pattern == "hybrid" or mat.fill_angle_mode == "optimal":
        # each island at its own angle: the least time by Jin's model (Jin et al. 3-4)
        lines, angle, area = [], math.nan, -1.0
        for island in _islands(inner):
            best = _best_angle(island, F, filt, linked, mat.hybrid_angle_step_deg, job)
            lines += best[1]
            a = geo.area(list(island.rings))
            if a > area:  # the angle reported: the largest island's
                angle, area = best[0], a
    else:
        angle = mat.fill_angle_deg
        lines = _zigzag_at(inner, F, angle, filt, linked)
    return FillLevels(levels, lines, angle, plain, held)


def _best_angle(area: Region, spacing: float, filt: float, linked: bool, step_deg: float,
                job: Job) -> tuple[float, list[np.ndarray]]:
    """The raster angle over [0, 180) in steps of ``step_deg`` whose zigzag (or raster)
    lines take the least time by Jin's model (:func:`zigzag_time`), and the lines."""
    best: tuple[float, float, list[np.ndarray]] | None = None
    for ang in np.arange(0.0, 180.0 - 1e-9, step_deg):
        lines = _zigzag_at(area, spacing, float(ang), filt, linked)
        t = zigzag_time(lines, job)
        if best is None or t < best[0] - 1e-9:
            best = (t, float(ang), lines)
    assert best is not None
    return best[1], best[2]


def _islands(region: Region) -> list[Region]:
    """The connected pieces of a region: each outer ring with its holes."""
    polygons = region.polygons()
    return [region] if len(polygons) <= 1 else [geo.region_from_rings(p) for p in polygons]


#: Measurement rings follow the region's contour smoothed within this (mm), each ring
#: within it again before the next is offset from it (:func:`concentric_levels`): the
#: laser's heights are placed where it was (the trajectory's samples), so the rings need
#: not hug the contour. On bunny layers the first ring's smoothing at 0.25 mm took 22 % off
#: the time at the laser's speed, every ring's at 0.5 mm another 6 % (BENCHMARKS.md, issue
#: 15)...
MEASURE_SMOOTHING_MM = 0.5
#: ... and every ring after the first is smoothed so at its turns too: the fill's
#: smoothing keeps turns over 60 degrees as corners (its window narrows there), but the
#: laser deposits nothing, and each corner left is a stop. The inward offsets make corners
#: of a scan's bumps: on bunny layer 400 the part's measurement rings after the first split
#: into 44 pieces instead of 76, and on layers 100/400/700/1000 the measurement with its
#: travel took 838 s instead of 852 s (-1.6 %); the demo mug's SMF error is unchanged (20
#: seeds: -0.08 +- 0.33 um, lower under 11, Wilcoxon p = 0.28). A clean polygon's corner
#: stays a corner (the smoothing moves no point farther than ``MEASURE_SMOOTHING_MM``).
#: The first ring is left as it is: smoothing the edge it is offset from at its corners
#: would let the ring grow back by the smoothing's reach, up to ``MEASURE_SMOOTHING_MM``
#: nearer the region's edge everywhere (BENCHMARKS.md, issue 15).
MEASURE_CORNER_DEG = 180.0


def measure_levels(region: Region, spacing: float, filt: float) -> list[list[np.ndarray]]:
    """Concentric measurement rings over a region (thesis 5.2.1), level by level,
    outermost first: shrunk by spacing/2, then every spacing, smoothed
    (``MEASURE_SMOOTHING_MM``; all but the first at their turns too:
    ``MEASURE_CORNER_DEG``)."""
    return concentric_rings(region, spacing / 2.0, spacing, filt,
                            smooth_mm=MEASURE_SMOOTHING_MM,
                            ring_smooth_mm=MEASURE_SMOOTHING_MM,
                            corner_deg=MEASURE_CORNER_DEG)


def measure_rings(region: Region, spacing: float, filt: float) -> list[np.ndarray]:
    """The rings of :func:`measure_levels`, all levels in one list."""
    return [r for lv in measure_levels(region, spacing, filt) for r in lv]


#: Centre-line measurement paths keep this far (mm) inside what they measure: a chain of
#: the medial axis runs out into the corners, to the region's edge, where the surface
#: falls away with the last bead (and beyond it lies the layer below or nothing). On the
#: demo mug at 4.5 mm spacing the laser, at rest at such an end, read 3-5 mm below the
#: surface on every measured layer, and the feedback raised the flow around it.
MEASURE_EDGE_MM = 0.5
#: ... within this (mm): a measurement centre line's smoothing moves no point farther; in a
#: spike's tip the smoothing cut a bend by 0.28 mm towards the edge (hypothesis' wall of
#: 2.3 mm round a spike: 0.22 mm off the edge), where the laser reads the surface falling
#: away.
MEASURE_AXIS_MOVE_MM = 0.1


def measure_paths(region: Region, spacing: float, filt: float, lane_mm: float = 0.0,
                  max_length_mm: float = math.inf) -> list[tuple[np.ndarray, bool]]:
    """Measurement paths over a region, ``(points (k, 2) mm, closed)``: the concentric
    rings of :func:`measure_rings`, then a path along the centre line of every piece of
    the region they leave unmeasured (:func:`unmeasured`) of at least ``spacing^2`` (any
    size when the region holds no ring), kept
    ``MEASURE_EDGE_MM`` from the piece's edge (a piece thinner than twice that gets none): a
    wall or a strip narrower than ``spacing`` holds no ring (the offset by ``spacing / 2``
    is empty), and the feedback would correct it with the heights of whatever was measured
    nearest (issue 15; on the demo mug at 4.5 mm the wall went unmeasured from 6 mm up and
    the SMF height error grew as in open loop, 1.18 mm instead of 0.05 mm).

    With ``lane_mm`` > 0 the rings that nest are joined into spirals
    (:func:`join_measure_rings`, lane changes ``lane_mm`` long, each spiral at most
    ``max_length_mm``): the rings come first, joined or not, then the centre lines."""
    levels = measure_levels(region, spacing, filt)
    out: list[tuple[np.ndarray, bool]] = (
        join_measure_rings(levels, region, spacing, lane_mm, max_length_mm) if lane_mm > 0
        else [(r, True) for lv in levels for r in lv])
    # a piece under spacing^2 is left to the measurements beside it; with no ring at all
    # nothing is beside it (at a 61 mm spacing a 60 mm square got no measurement path,
    # and SMF corrected the layer from the laser along its deposition paths, unsaid)
    least = spacing * spacing if out else 0.0
    left = [p for p in unmeasured(region, levels[0] if levels else [], spacing,
                                  filt).polygons()
            if geo.area(p) >= least]
    if not left:
        return out
    rings_left = [r for p in left for r in p]
    perim = float(geo.ring_perimeters(rings_left).sum())
    typical = 2.0 * max(geo.area(rings_left), 0.0) / max(perim, 1e-12)   # a strip's width
    chains = geo.medial_axis(rings_left, float(np.clip(typical / 3.0, 0.05, 0.5)),
                             MEASURE_EDGE_MM)
    if not chains:
        return out
    # a chain ends at a branch point (where it meets others) or in a corner (a leaf, an
    # end no other chain shares): leaves shorter than half the spacing reach into
    # corners the rest measures anyway
    ends = np.array([[p[0], p[-1]] if not closed else [[np.nan] * 2] * 2
                     for p, _c, closed in chains]).reshape(-1, 2)
    _u, inv, count = np.unique(np.round(ends, 9), axis=0, return_inverse=True,
                               return_counts=True)
    leaf = (count[inv.reshape(-1)] == 1).reshape(-1, 2).any(axis=1) & \
        ~np.array([closed for _p, _c, closed in chains])
    chains = _smoothed_axis([(p, 2.0 * c, closed) for p, c, closed in chains],
                            MEASURE_AXIS_MOVE_MM)
    lengths = np.array([np.hypot(*np.diff(pts, axis=0).T).sum() for pts, _w, _c in chains])
    tiny = lengths < filt
    short = (leaf & (lengths < spacing / 2.0)) | tiny
    if short.all() and not out:
        short = tiny                  # nothing else measures the region: keep them all
    for (pts, _w, closed), skip in zip(chains, short):
        if skip:
            continue
        keep = geo.simplify_masks([pts], np.array([float(filt)]), closed=closed)[0]
        if closed and keep.sum() >= 3:
            out.append((np.ascontiguousarray(pts[keep]), True))
        elif not closed and keep.sum() >= 2:
            out.append((np.ascontiguousarray(pts[keep]), False))
    return out


#: A measurement spiral changes from one ring to the next in at least this many spacings
#: of length, and in at least ``MEASURE_LANE_S`` at its speed (:func:`measure_lane_mm`):
#: a quintic blend across one spacing over ``L`` turns at most ``5.8 spacing / L^2``
#: (1/mm), i.e. 0.12 /mm (300 mm/s^2 at the part's 50 mm/s) over 12 mm at the default 3 mm
#: spacing, and 0.028 /mm (430 mm/s^2 at 125 mm/s) over 25 mm for the scaffold: the robot
#: does not slow down for it under the 500 mm/s^2 bound.
MEASURE_LANE_SPACINGS = 4.0
MEASURE_LANE_S = 0.2
#: A joined measurement path holds at most this many laser samples: the LK-G3001P stores
#: 65 536 values (``icefab.cell.lkg.STORAGE_CAPACITY``) and the cell reads them after each
#: measurement path (thesis 5.2.1); half of it leaves room for the path's speed-ups.
MEASURE_MAX_SAMPLES = 32_768
#: ... and lasts at most this fraction of what the robot controller stores of one path
#: (:func:`path_store_s`: 65 s at the defaults, 3.3 m of ice), leaving room for its
#: slow-downs: the bunny's longest spirals took 9 640-14 318 samples, more than the
#: 8 192 the controller takes, and ``icefab build`` refused the part before it started.
MEASURE_STORE_FRACTION = 0.5


def path_store_s(job: Job) -> float:
    """Seconds of motion the robot controller stores of one path, s:
    :data:`icefab.robots.CONTROLLER_PATH_POINTS` samples of ``motion.dt_s``."""
    return CONTROLLER_PATH_POINTS * job.motion.dt_s


def measure_lane_mm(spacing: float, speed_mm_s: float) -> float:
    """Length (mm) of a measurement spiral's lane change from one ring to the next."""
    return max(MEASURE_LANE_SPACINGS * spacing, MEASURE_LANE_S * speed_mm_s)


def join_measure_rings(levels: Sequence[Sequence[np.ndarray]], region: Region,
                       spacing: float, lane_mm: float, max_length_mm: float = math.inf
                       ) -> list[tuple[np.ndarray, bool]]:
    """Concentric measurement rings (:func:`measure_levels`, outermost level first)
    joined into spirals where they nest: issue 15's continuous tours for the laser, which
    deposits nothing, so a path may run from one ring into the next without a stop (the
    thesis' BUFFERF rings, 5.2.1, each started and ended at rest; on bunny layers joining
    took 5 % off the measurement's time, most of it the travel moves between rings).

    A ring is followed by the ring of the next level that lies within 1.5 spacings of it
    (the same orientation: an island's rings, or a hole's), the largest if several do;
    each spiral leaves a ring ``lane_mm`` before it closes, along a quintic blend
    (continuous in curvature at both ends) from it onto the stretch of the next ring
    beside it (:func:`_lane_change`), and goes on round that one. A lane change is made
    only where the rings
    run side by side (at most 1.6 spacings apart along it) and the blend stays inside the
    region at least ``MEASURE_EDGE_MM`` from its edge; elsewhere, and past
    ``max_length_mm``, the spiral ends and the next ring starts a path of its own. The
    first ring of a spiral is left where the next lies nearest.

    Returns ``(points (k, 2) mm, closed)``: a spiral is open, a ring not joined is closed.
    What a lane change leaves out of the two rings (the stretches it runs beside) lies
    within 1.6 spacings of the blend."""
    areas = [geo.ring_areas(list(lv)) for lv in levels]
    boxes = [[(r.min(axis=0), r.max(axis=0)) for r in lv] for lv in levels]
    child: dict[tuple[int, int], int] = {}
    for k in range(len(levels) - 1):
        taken: set[int] = set()
        for j in np.argsort(-np.abs(areas[k + 1])):
            ring = levels[k + 1][j]
            lo, hi = boxes[k + 1][j]
            probe = ring[::max(1, len(ring) // 64)]
            best: tuple[int, float] | None = None
            for i, parent in enumerate(levels[k]):
                plo, phi = boxes[k][i]
                if i in taken or np.sign(areas[k][i]) != np.sign(areas[k + 1][j]) or \
                        np.any(lo < plo - 2.0 * spacing) or np.any(hi > phi + 2.0 * spacing):
                    continue
                d = float(geo.ring_nearest(probe, parent)[1].min())
                if d < 1.5 * spacing and (best is None or d < best[1]):
                    best = (i, d)
            if best is not None:
                child[(k, best[0])] = int(j)
                taken.add(best[0])
    followed = {(k + 1, j) for (k, _i), j in child.items()}
    if not child:
        return [(r, True) for lv in levels for r in lv]
    inner = geo.shrink(region, MEASURE_EDGE_MM, 0.0)   # where a lane change may run
    out: list[tuple[np.ndarray, bool]] = []
    for k, lv in enumerate(levels):
        for i in range(len(lv)):
            if (k, i) in followed:
                continue
            chain = [lv[i]]
            kk, ii = k, i
            while (kk, ii) in child:
                kk, ii = kk + 1, child[(kk, ii)]
                chain.append(levels[kk][ii])
            out += _spirals(chain, inner, spacing, lane_mm, max_length_mm)
    return out


def _ring_arc(ring: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A ring closed (k + 1, 2) and the arc length at each of its points (k + 1,), mm."""
    closed = closed_polyline(ring)
    return closed, arc_lengths(np.hypot(*np.diff(closed, axis=0).T))


def _ring_at(closed: np.ndarray, arc: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points (n, 2) of a ring (:func:`_ring_arc`) at arc lengths ``t`` (n,), mm, taken
    round the ring."""
    t = np.mod(t, arc[-1])
    return np.column_stack([np.interp(t, arc, closed[:, 0]), np.interp(t, arc, closed[:, 1])])


def _lap(ring: tuple[np.ndarray, np.ndarray], start: float, frm: float, to: float
         ) -> np.ndarray:
    """The stretch of a ring (:func:`_ring_arc`) from arc ``start + frm`` to ``start +
    to`` (0 <= frm < to <= its length), with every vertex between: points (k, 2) mm."""
    rel = np.mod(ring[1][:-1] - start, ring[1][-1])
    between = np.sort(rel[(rel > frm) & (rel < to)])
    return _ring_at(*ring, start + np.concatenate([[frm], between, [to]]))


def _lane_change(ring: tuple[np.ndarray, np.ndarray], leave: float,
                 nxt: tuple[np.ndarray, np.ndarray], length: float, spacing: float,
                 inner: Region) -> tuple[float, float, np.ndarray] | None:
    """The blend from ``ring`` at arc ``leave`` onto the ring ``nxt`` over ``length`` mm
    of ``ring`` (:func:`join_measure_rings`), side by side with the part of ``nxt`` nearest
    it (rings of different curvature run at different rates: the inner ring of a bend is
    shorter). Returns (arc of ``nxt`` where the blend starts beside it, the length of
    ``nxt`` it runs beside, its points (n, 2)), or None where the rings do not run side by
    side (over 1.6 spacings apart, or the nearest point running back along ``nxt``) or the
    blend leaves ``inner`` (the region shrunk by ``MEASURE_EDGE_MM``)."""
    u = np.linspace(0.0, 1.0, max(int(math.ceil(length / 0.5)), 4) + 1)
    a = _ring_at(*ring, leave + u * length)
    total = nxt[1][-1]
    at, gap = geo.ring_nearest(a, nxt[0][:-1])
    run = np.unwrap(at, period=total)
    step = np.diff(run)
    # the nearest point may stay put for a while (a corner of the inner ring faces a bend
    # of the outer one) but not run back
    if gap.max() > 1.6 * spacing or np.any(step < -1e-9) or \
            not 0.0 < run[-1] - run[0] < 0.5 * total:
        return None
    b = _ring_at(*nxt, run)
    w = (u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u))[:, None]
    blend = (1.0 - w) * a + w * b
    if not geo.points_inside(blend, inner).all():
        return None
    return float(run[0]), float(run[-1] - run[0]), blend


def _spirals(chain: list[np.ndarray], inner: Region, spacing: float, lane_mm: float,
             max_length_mm: float) -> list[tuple[np.ndarray, bool]]:
    """A chain of nested rings (outermost first) as spirals and single rings; ``inner``:
    where a lane change may run (:func:`_lane_change`)."""
    out: list[tuple[np.ndarray, bool]] = []
    while chain:
        ring = _ring_arc(chain[0])
        pieces: list[np.ndarray] = []
        start = done = 0.0      # where the current ring's lap starts; what a lane took
        length = 0.0
        joined = 0
        for nxt_ring in chain[1:]:
            nxt = _ring_arc(nxt_ring)
            total = ring[1][-1]
            lane = min(lane_mm, 0.5 * (total - done), nxt[1][-1] / 3.0)
            if lane < 2.0 * spacing or length + total + nxt[1][-1] > max_length_mm:
                break
            if not joined:   # leave the first ring where the next lies nearest
                every = max(1, (len(ring[0]) - 1) // 256)
                near = geo.ring_nearest(ring[0][:-1:every], nxt_ring)[1]
                start = ring[1][:-1:every][int(np.argmin(near))] + lane
            found = _lane_change(ring, start + total - lane, nxt, lane, spacing, inner)
            if found is None:
                break
            nxt_start, beside, blend = found
            pieces += [_lap(ring, start, done, total - lane), blend[1:]]
            length += total
            ring, start, done = nxt, nxt_start, beside
            joined += 1
        if not joined:
            out.append((chain[0], True))
            chain = chain[1:]
            continue
        pieces.append(_lap(ring, start, done, ring[1][-1]))
        # on Clipper's grid, as the rings were: the interpolated vertices differ from it
        # by rounding only, and grid coordinates compress (the toolpath file, issue 17)
        pts = np.round(np.concatenate(pieces) * geo.SCALE) / geo.SCALE
        keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
        out.append((np.ascontiguousarray(pts[keep]), False))
        chain = chain[joined + 1:]
    return out


def unmeasured(region: Region, first: Sequence[np.ndarray], spacing: float, filt: float
               ) -> Region:
    """What of ``region`` the measurement rings leave unmeasured, given their outermost
    level ``first`` (:func:`measure_rings`): what lies neither inside that level (where
    the deeper rings are, and the heights are interpolated between rings, thesis 5.2.1)
    nor within ``spacing / 2`` of it (plus its smoothing, ``MEASURE_SMOOTHING_MM``, and
    the point filter ``filt``). The surface there would only be extrapolated."""
    if not len(first):
        return region
    reach = spacing / 2.0 + MEASURE_SMOOTHING_MM + filt
    return geo.difference(region, geo.offset_rings(list(first), reach, 0.0))


# --------------------------------------------------------------------------- ordering


#: Vertices of a closed path considered as its start point by the nearest-neighbour order.
MAX_START_CANDIDATES = 64


def _start_candidates(pts: np.ndarray, corner_deg: float | None = None) -> np.ndarray:
    """Indices of the vertices of a closed path ``pts`` (k, 2) that may become its start:
    its corners (turns over ``corner_deg``) when it has any, else all vertices; at most
    ``MAX_START_CANDIDATES`` of them, evenly spread (:func:`_entry_candidates` of one
    closed path).

    Why corners: the robot stops at every turn over the PATHSPLIT angle and at a path's
    start and end (thesis 4.1.1); a closed path that starts at one of its corners pays
    for both with one stop. On bunny layers 38 % of the rings with a corner started
    elsewhere (BENCHMARKS.md, issue 15)."""
    return _entry_candidates([(pts, True)], corner_deg)[0]


def _entry_candidates(items: Sequence[tuple], corner_deg: float | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The vertices each of ``items`` (``(points (k, 2), closed, ...)``) may be entered
    at, all in one compiled pass: a closed path's :func:`_start_candidates`, an open
    path's first and last point. Returns (vertex index within its path (m,) int64, the
    rows of each item (n + 1,) int64)."""
    if not items:
        return np.zeros(0, dtype=np.int64), np.zeros(1, dtype=np.int64)
    pts = np.ascontiguousarray(np.concatenate([it[0] for it in items]), dtype=np.float64)
    starts = offsets([len(it[0]) for it in items])
    closed = np.array([bool(it[1]) for it in items])
    cos_limit = math.cos(math.radians(corner_deg)) if corner_deg is not None else 0.0
    return _tour.entry_candidates(pts, starts, closed, cos_limit, corner_deg is not None,
                                  MAX_START_CANDIDATES)


def order_nearest(items: Sequence[tuple], start: np.ndarray,
                  corner_deg: float | None = None) -> tuple[list[tuple], np.ndarray]:
    """Order paths by nearest neighbour from ``start``, choosing start points.

    items: tuples ``(points (k, 2) float64 mm, closed, ...)``; further fields are kept.
    A closed path may start at any of up to ``MAX_START_CANDIDATES`` evenly spread vertices
    (its corners over ``corner_deg`` only, when given and it has any:
    :func:`_start_candidates`; it is rotated to start there); an open path at either end
    (it is reversed when entered from its last point).
    Returns the re-ordered items and the final position (2,) mm.
    """
    if not items:
        return [], np.asarray(start, dtype=np.float64)
    index, bounds = _entry_candidates(items, corner_deg)
    owner = np.repeat(np.arange(len(items)), np.diff(bounds))
    P = _tour.entry_points(items, index, bounds)
    closed = np.array([bool(item[1]) for item in items])
    cur = np.asarray(start, dtype=np.float64)
    out: list[tuple] = []
    for k in _tour.nearest_order(P, owner, bounds, closed, float(cur[0]), float(cur[1])):
        i = int(owner[k])
        j = int(index[k])
        # a closed path rotated to start at vertex j, an open one reversed when entered
        # from its last point (j > 0)
        item = _tour.moved(items[i], roll=j) if items[i][1] else \
            _tour.moved(items[i], flip=j > 0)
        out.append(item)
        cur = item[0][0] if item[1] else item[0][-1]
    return out, cur


# --------------------------------------------------------------------------- tours

#: A tour's travel curve (:func:`tour_connectors`): a cubic Bezier whose handles are this
#: fraction of the gap long (at least ``TOUR_HANDLE_MIN_MM``), sampled about every
#: ``TOUR_STEP_MM`` (8 to ``TOUR_MAX_POINTS`` points).
TOUR_HANDLE = 0.3
TOUR_HANDLE_MIN_MM = 0.5
TOUR_STEP_MM = 0.1
TOUR_MAX_POINTS = 400
#: From a closed path to a closed one (concentric rings) a join turning more than this
#: loses time: the rings start at corners, where the robot stops anyway (degrees;
#: BENCHMARKS.md, issue 15).
RING_TO_RING_MAX_TURN_DEG = 120.0
#: A path shorter than this ends a tour (mm): between two travel curves the robot passes
#: it within one sample (16 ms is 2 mm at 125 mm/s), and a valve that followed the samples
#: would miss it. On 5 bunny layers none is missed and the tours save 3.8 %. (The valve now
#: switches at the exact instants, ``Trajectory.on_spans``; the rule is kept as measured.)
TOUR_MIN_MEMBER_MM = 0.5
#: A tour is at most this fraction of what the robot controller stores of one path
#: (:func:`path_store_s`) long at the speed bound (MTTS takes about twice that on the
#: bunny's fill: 83 h against a 44 h floor), so that it fits the store.
TOUR_STORE_FRACTION = 0.25
#: Paths whose ends are closer than this are not joined (mm): no travel curve would
#: separate them in the tour.
TOUR_SAME_POINT_MM = 1e-6


def _heading(poly: np.ndarray, at_end: bool) -> np.ndarray | None:
    """Unit direction of a polyline's last (or first) segment of any length (repeated
    points skipped): where a tour's travel curve meets the path it is tangent to it (G1),
    so MTTS does not stop there (PATHSPLIT, thesis 4.1.1). None when it has no length."""
    p = poly[::-1] if at_end else poly
    x0, y0 = float(p[0, 0]), float(p[0, 1])
    for k in range(1, len(p)):
        dx, dy = float(p[k, 0]) - x0, float(p[k, 1]) - y0
        n = math.hypot(dx, dy)
        if n > TOUR_SAME_POINT_MM:
            return np.array([-dx / n, -dy / n] if at_end else [dx / n, dy / n])
    return None


def tour_turn_deg(a: np.ndarray, ta: np.ndarray, b: np.ndarray, tb: np.ndarray
                  ) -> np.ndarray:
    """How far the heading turns from a path leaving ``a`` along ``ta`` to the next one
    entering at ``b`` along ``tb`` (unit vectors; (2,) or (j, 2) each), degrees in
    [0, 360]: to the gap's direction and from it to ``tb`` (with no gap, from ``ta`` to
    ``tb``). 0 for paths in line, 180 for a sideways step between parallel paths, 360 for
    a U-turn on the spot."""
    d = np.asarray(b, np.float64) - a
    gap = np.hypot(d[..., 0], d[..., 1])[..., None]
    u = np.where(gap > TOUR_SAME_POINT_MM, d / np.where(gap > 0, gap, 1.0), ta)
    return np.degrees(np.arccos(np.clip(np.sum(ta * u, axis=-1), -1.0, 1.0))
                      + np.arccos(np.clip(np.sum(u * tb, axis=-1), -1.0, 1.0)))


def tour_connectors(a: np.ndarray, ta: np.ndarray, b: np.ndarray, tb: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The inner points of the travel curves of many joins, each argument (j, 2): from
    ``a`` (leaving along the unit ``ta``) to ``b`` (arriving along ``tb``), a cubic Bezier
    tangent to both ends (G1: no corner where it meets the paths, so MTTS need not stop
    there, thesis 4.1.1). Returns the points concatenated (M, 2) mm and how many each
    curve has (j,) int64."""
    gap = np.hypot(*(b - a).T)
    h = np.maximum(TOUR_HANDLE * gap, TOUR_HANDLE_MIN_MM)[:, None]
    n = np.clip(np.ceil((gap + 2.0 * h[:, 0]) / TOUR_STEP_MM), 8, TOUR_MAX_POINTS
                ).astype(np.int64)
    counts = n - 2
    owner = np.repeat(np.arange(len(n)), counts)
    s = ((np.arange(counts.sum()) - np.repeat(offsets(counts)[:-1], counts) + 1)
         / (n[owner] - 1))[:, None]
    c0, c1, c2, c3 = a[owner], (a + ta * h)[owner], (b - tb * h)[owner], b[owner]
    pts = ((1 - s) ** 3 * c0 + 3 * (1 - s) ** 2 * s * c1 + 3 * (1 - s) * s * s * c2
           + s ** 3 * c3)
    # on Clipper's grid, as every other point of the paths: arbitrary floats took the
    # demo mug's toolpath file from 6.1 to 9.9 MB of compressed points
    return np.round(pts * geo.SCALE) / geo.SCALE, counts


def _tour_parts(path: Toolpath) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A path as a piece of a tour: its polyline, the width at every polyline point and
    whether the segment leaving each point is off (a closed path's closing segment
    deposits; the last point's entry is set by the caller)."""
    poly = path.polyline()
    off = np.zeros(len(poly), dtype=bool)
    if path.off is not None:
        off[:len(path.points)] = np.asarray(path.off, dtype=bool)
    return poly, path.polyline_widths(), off


def join_tours(paths: Sequence[Toolpath], max_turn_deg: float,
               max_length_mm: float = math.inf) -> list[Toolpath]:
    """Continuous tours (issue 15): consecutive deposition paths (one material, role and
    tool, in deposition order) joined into one open path through a travel curve
    (:func:`tour_connectors`) whose segments are ``off``, wherever the heading turns by at
    most ``max_turn_deg`` (:func:`tour_turn_deg`; ``RING_TO_RING_MAX_TURN_DEG`` at most
    from one closed path to the next; 0: no joins), while the tour stays within
    ``max_length_mm`` (its paths and the straight gaps between them). Not joined: paths
    that meet end to end, and anything after a path shorter than ``TOUR_MIN_MEMBER_MM``.

    Why: every path starts and ends at rest (thesis 4.1.1), and on the bunny a rest stop
    pair with its travel costs 0.3-0.35 s; a join between paths in line saves 0.22-0.42
    s of MTTS time, a sideways step between parallel paths 0.03-0.09 s, a U-turn nothing,
    and joined concentric rings lose time (they start at corners where they stop anyway;
    ``bench/bench_tour_joins.py``, BENCHMARKS.md). The robot still stops where MTTS must:
    at PATHSPLIT corners of the paths, material and tool changes, the measurement.

    A tour's widths are per point when its paths' widths differ (the points of its travel
    curves are 0 wide; their segments are off), its ``width`` the mean over what it
    deposits; :func:`icefab.core.tour_members` gives its paths back. The valve follows the
    trajectory's samples (:func:`icefab.motion._sample_widths`: 0 wide on a travel curve),
    so it switches within one sample (16 ms) of where a path ends or starts.
    """
    if max_turn_deg <= 0 or len(paths) < 2:
        return list(paths)
    join, (a, ta, b, tb), lengths = _joins(paths, max_turn_deg)
    if np.isfinite(max_length_mm):   # a tour ends where it would grow too long
        gap = np.hypot(*(b - a).T)
        run = float(lengths[0])
        for i in range(1, len(paths)):
            run = run + float(gap[i - 1] + lengths[i]) if join[i - 1] else float(lengths[i])
            if join[i - 1] and run > max_length_mm:
                join[i - 1] = False
                run = float(lengths[i])
    pts, counts = tour_connectors(a[join], ta[join], b[join], tb[join])
    curves = iter(split_rows(pts, np.cumsum(counts)[:-1]) if len(counts) else [])
    out: list[Toolpath] = []
    first = 0
    for i in range(1, len(paths) + 1):
        if i == len(paths) or not join[i - 1]:
            out.append(_tour_path(paths[first:i], [next(curves) for _ in range(i - first - 1)]))
            first = i
    return out


def _joins(paths: Sequence[Toolpath], max_turn_deg: float
           ) -> tuple[np.ndarray, tuple[np.ndarray, ...], np.ndarray]:
    """(n - 1,) bool: whether :func:`join_tours` joins path i to path i + 1 (every rule
    looks at the two alone), for all pairs at once; each pair's (n - 1, 2) arrays
    ``a, ta, b, tb`` (:func:`tour_connectors`: where and along what path i ends, path
    i + 1 starts); the paths' lengths (n,) mm."""
    polys = [p.polyline() for p in paths]
    ends = np.array([q[-1] for q in polys], dtype=np.float64)
    starts = np.array([q[0] for q in polys], dtype=np.float64)
    t_end = np.array([_heading(q, True) if len(q) > 1 else (np.nan, np.nan) for q in polys],
                     dtype=np.float64)
    t_start = np.array([_heading(q, False) if len(q) > 1 else (np.nan, np.nan)
                        for q in polys], dtype=np.float64)
    kind = [(p.depositing, p.material, p.role, p.tool_name) for p in paths]
    closed = np.array([p.closed for p in paths], dtype=bool)
    lengths = path_lengths(paths)
    same = np.array([k[0] and k == n for k, n in zip(kind[:-1], kind[1:])], dtype=bool)
    a, b, ta, tb = ends[:-1], starts[1:], t_end[:-1], t_start[1:]
    gap = np.hypot(*(b - a).T)
    turn = tour_turn_deg(a, ta, b, tb)
    limit = np.where(closed[:-1] & closed[1:],
                     min(max_turn_deg, RING_TO_RING_MAX_TURN_DEG), max_turn_deg)
    # (a NaN heading, a path of no length, compares False)
    join = (same & (lengths[:-1] >= TOUR_MIN_MEMBER_MM) & (gap > TOUR_SAME_POINT_MM)
            & (turn <= limit))
    return join, (a, ta, b, tb), lengths


def _tour_path(members: Sequence[Toolpath], curves: Sequence[np.ndarray]) -> Toolpath:
    """One open path through ``members`` (consecutive, checked by :func:`join_tours`),
    ``curves[i]`` between members i and i + 1, off; a single member as it is."""
    if len(members) == 1:
        return members[0]
    pts, widths, off = [], [], []
    for i, m in enumerate(members):
        poly, w, o = _tour_parts(m)
        if i:
            c = curves[i - 1]
            off[-1][-1] = True                   # leaving the path onto the travel curve
            pts.append(c)
            widths.append(np.zeros(len(c)))
            off.append(np.ones(len(c), dtype=bool))
        pts.append(poly)
        widths.append(w)
        off.append(o)
    P, W, O = np.concatenate(pts), np.concatenate(widths), np.concatenate(off)
    O[-1] = False                                # an open path's last point leaves nothing
    first = members[0]
    same = all(m.widths is None and m.width == first.width for m in members)
    return Toolpath(np.ascontiguousarray(P), first.z, first.material, first.role, False,
                    float(first.width) if same else mean_width(P, W, ~O[:-1]),
                    first.layer, first.frame, first.tool, None if same else W, O)


# --------------------------------------------------------------------------- one layer


def _hook_wall_count(index: int) -> int:
    """Outer scaffold paths turned into ice for the hook wall (thesis 3.7): the outermost
    one on layers 0-9, the two outermost on layers 10-19."""
    if index < 10:
        return 1
    if index < 20:
        return 2
    return 0


def hook_wall(scaffold: Region, part: Region, count: int, mat: MaterialSettings, filt: float
              ) -> tuple[list[np.ndarray], Region]:
    """Split the ice hook wall off a layer's scaffold (thesis 3.7, Fig. 3-8).

    The outline of the build is the scaffold's counter-clockwise rings that do not lie in
    the part's footprint (the part's outer rings filled; scaffold in a hole of the part is
    not outside). The hook wall is ``count`` rings at the scaffold's boundary offsets from
    that outline (``initial_offset + i * path_width``); the band they take,
    :func:`hook_band_mm` wide, is removed from the scaffold, whose own paths are then planned
    on what is left. Returns (ice rings, remaining scaffold region).
    """
    if count <= 0 or scaffold.is_empty:
        return [], scaffold
    depth = part.depth()
    footprint = geo.region_from_rings([r for r, d in zip(part.rings, depth) if d == 0])
    outline = []
    pockets = []
    for r, d in zip(scaffold.rings, scaffold.depth()):
        a = signed_area(r)
        outside = footprint.is_empty or \
            geo.area(geo.intersection([r[::-1] if d % 2 else r], footprint)) < 0.99 * abs(a)
        if outside:
            # a hole of the scaffold outside the part's footprint is a pocket of the build's
            # outline (regions._hook_wall_room's growth closes such pockets between two
            # scaffolds; a fuzzed spiky part's hook ring ran 2 mm across one): the wall
            # goes round it
            (pockets if d % 2 else outline).append(r)
    if not outline:
        return [], scaffold
    outer = geo.region_from_rings(outline + pockets)
    rings: list[np.ndarray] = []
    for i in range(count):
        rings.extend(geo.offset_rings(list(outer.rings),
                                      -(mat.initial_offset_mm + i * mat.path_width_mm), filt))
    # the band of the rings taken; with one ring (layers 0-9) the scaffold keeps the rest
    band = geo.difference(outer, geo.shrink(outer, hook_band_mm(count, mat), filt))
    return rings, geo.difference(scaffold, band)


def nominal_area(region: Region, mat: MaterialSettings, filt: float) -> Region:
    """The area a material's paths are meant to cover: the region shrunk by
    ``max(initial_offset - path_width/2, 0)`` (the calibrated edge strip of a material
    whose initial offset exceeds half the path width is left empty on purpose)."""
    d = max(mat.initial_offset_mm - mat.path_width_mm / 2.0, 0.0)
    return geo.shrink(region, d, filt) if d > 0 else region


def material_paths(region: Region, mat: MaterialSettings, job: Job, hook_levels: int = 0,
                   part: Region | None = None
                   ) -> tuple[dict[str, list[tuple[np.ndarray, bool, float]]],
                              list[np.ndarray], float]:
    """Boundary and fill paths of one material's region.

    Returns ``({"boundary": [...], "fill": [...]}, hook_rings, unfilled_mm2)`` where each
    path is ``(points (k, 2) float64 mm, closed, width mm)``; ``hook_rings`` are the
    rings of the ice hook wall (:func:`hook_wall`, ``hook_levels`` rings, given the layer's
    ``part``) taken out of the scaffold (thesis 3.7); ``unfilled_mm2`` the nominal area
    (:func:`nominal_area`) that no path sweeps. With ``mat.gap_fill`` the gaps get extra
    fill paths (:func:`gap_fill_paths`: rings with room, pocket rings with constant
    widths, centre lines of the strips left; none narrower than
    ``mat.min_bead_width_mm``) before the remainder is measured.
    """
    filt = job.slicing.max_filter_deviation_mm
    w = mat.path_width_mm
    out: dict[str, list[tuple[np.ndarray, bool, float]]] = {"boundary": [], "fill": []}
    if region.is_empty:
        return out, [], 0.0
    whole = region
    hook: list[np.ndarray] = []
    if hook_levels and part is not None:
        hook, region = hook_wall(region, part, hook_levels, mat, filt)
    bounds = boundary_rings(region, mat, filt)
    fill = fill_levels(region, mat, job)
    F = mat.fill_width_mm
    out["boundary"] = [(r, True, w) for lv in bounds for r in lv]
    out["fill"] = fill.paths(F)
    nominal = nominal_area(whole, mat, filt)
    # Flat Booleans (no nesting tree): the bands only clip. Ring levels sweep as
    # expand(level) - shrink(level) (two polygon offsets, much cheaper than sweeping each
    # ring as a line); bands are grown by the point filter (whose chords move one level
    # against the next) plus SWEEP_TOL, so touching bands leave no slivers.
    tol = filt + SWEEP_TOL
    levels = gap_levels(bounds, fill, mat, filt)
    swept = geo.sweep_rings([(ln, False, F) for ln in fill.lines]
                            + [(r, True, w) for r in hook], tol)
    if _levels_nest(mat, filt):   # the same gaps, at a fraction of the cost
        gaps = geo.difference_rings(geo.level_gaps(nominal, levels), swept)
    else:
        gaps = geo.difference_rings(nominal, geo.level_bands(levels) + swept)
    if mat.gap_fill and gaps:
        extra, gaps = gap_fill_paths(gaps, nominal, mat, filt, whole)
        out["fill"] += extra
    return out, hook, max(geo.area(gaps), 0.0)


def gap_levels(bounds: list[list[np.ndarray]], fill: FillLevels, mat: MaterialSettings,
               filt: float) -> list[tuple]:
    """The ring levels whose bands :func:`material_paths` takes out of the nominal area
    (:func:`icefab.geometry.level_bands`' levels): the boundaries (half-width ``w / 2``)
    and the fill levels (``F / 2``, with the rings their widened beads hold), each grown
    by the point filter and ``SWEEP_TOL``, outermost first."""
    tol = filt + SWEEP_TOL
    return ([(lv, mat.path_width_mm / 2.0 + tol) for lv in bounds]
            + [(lv, mat.fill_width_mm / 2.0 + tol, held)
               for lv, held in zip(fill.levels, fill.held)])


def _levels_nest(mat: MaterialSettings, filt: float) -> bool:
    """Whether the boundary and fill ring levels of :func:`material_paths` nest as
    :func:`icefab.geometry.level_gaps` needs: each band's outer and inner edges within the
    band's before. Offsets of offsets do; what moves a level outward is smoothing. The
    first fill band reaches outward over the last boundary's band by up to twice
    ``fill_smoothing_mm`` plus the sweeps' growth and the filter, which must stay within
    the boundary's width; a fill ring moves by up to ``RING_SMOOTHING`` of the fill width
    either way, which must stay within the rest of the fill's half-width; each with a
    margin of 2."""
    tol = filt + SWEEP_TOL
    w, F = mat.path_width_mm, mat.fill_width_mm
    smooth = mat.fill_smoothing_mm if mat.fill_pattern == "concentric" else 0.0
    ring = max(RING_SMOOTHING * F, filt) if smooth > 0 else 0.0
    fill_ok = 2.0 * (tol + ring + 2.0 * filt) < F / 2.0
    bound_ok = 2.0 * (tol + 2.0 * filt) < w / 2.0
    first_ok = mat.boundary_count == 0 or 2.0 * (2.0 * smooth + 2.0 * tol + filt) < w
    return fill_ok and bound_ok and first_ok


#: Growth of swept bands when measuring gaps, mm, on top of the point filter (closes
#: slivers between touching bands; gaps narrower than twice the total are not counted).
SWEEP_TOL = 0.005
#: Gaps narrower than this fraction of the path width get no path (and are reported).
THIN_GAP_MIN = 0.1
#: Gap paths along a centre line: a run's widest point is at most this many times its
#: narrowest (unless the run is short, ``GAP_MIN_RUN_MM``), and its width is its widest,
#: at most this many times its length-weighted mean width: a run covers its strip and
#: deposits at most 30 % more than the strip holds (where the strip narrows, the bead
#: overlaps its neighbours, as slicers' gap fill does; never beyond the region).
GAP_RUN_RATIO = 1.3
#: Runs are not cut shorter than this (mm): a strip whose width wobbles would give many
#: tiny paths, each a stop of the robot.
GAP_MIN_RUN_MM = 1.0
#: With ``materials.*.min_bead_width_mm`` (w_lay) set, a strip down to w_lay / this wide
#: gets a bead w_lay wide (:func:`gap_fill_paths`); a narrower one is left unfilled.
GAP_WIDEN_RATIO = 1.3
#: Open gap paths sweeping less than this area (mm^2) are left out.
GAP_MIN_AREA_MM2 = 0.05
#: ... and, with ``materials.*.min_bead_width_mm`` set, so are open gap paths shorter
#: than this many times their (widest) width: the sweep credits a path with round ends,
#: but the valve lays ``w dh`` per mm of path only (eq. 6.2), so a path shorter than its
#: width is mostly ends it does not lay; on the demo mug 465 such paths got no pulse at
#: all (their volume under half a pulse).
GAP_MIN_LENGTH = 1.0
#: Gap pieces at least this round (isoperimetric ratio ``4 pi A / P^2``: 1 for a disk,
#: 0.6 for an equilateral triangle, 0.35 for a 6:1 rectangle) are pockets, filled with one
#: ring rather than along their centre line when the gap fill lays constant-width runs.
GAP_BLOB_ROUNDNESS = 0.35
#: Pocket ring widths are floored to a multiple of this (mm), so that the pockets of one
#: width are offset at once (a tenth of the thinnest path the defaults lay, 0.15 mm).
POCKET_WIDTH_STEP_MM = 0.05


def gap_fill_paths(gaps: list[np.ndarray], nominal: Region, mat: MaterialSettings,
                   filt: float, region: Region | None = None
                   ) -> tuple[list[tuple[np.ndarray, bool, float]], list[np.ndarray]]:
    """Paths for the gaps the boundaries and the fill leave (not in the thesis).

    1. Where a gap has room for two beads of the path width ``w``: one ring ``w / 2``
       inside its edge, with room (:func:`_with_room`: nowhere narrower than ``w``).
    2. Pockets (round gap pieces, ``GAP_BLOB_ROUNDNESS``), without ``mat.variable_width``
       only: one ring about as wide as the pocket's inradius (``0.8 * 2 A / P``), half
       that inside its edge, with room. A pocket is at most twice the path width wide
       (step 1 took the rest), so a variable-width centre line, as wide as the pocket
       along its axis, fills it: the ring turned at every corner of the pocket (a small
       one 4-7 rest stops for 2-10 mm of bead), and on 7 bunny layers the centre lines
       took 6.7 % off the MTTS time and left less unfilled area (1.34 / 6.0 -> 1.21 / 5.0
       mm^2, part / scaffold; BENCHMARKS.md, issue 15).
    3. What is left (strips: between two boundaries a little apart, in the middle of the
       last fill ring, along the tips of the fill) is filled along its centre line
       (medial axis, :func:`icefab.geometry.medial_axis`), the path width following the
       local width of the strip (twice the clearance, at most ``max(w, fill width)``;
       less width, less flow): with ``mat.variable_width`` one path per centre line, its
       width given at every point (issue 15: the valve follows it), else in runs of
       similar width (``GAP_RUN_RATIO``, ``GAP_MIN_RUN_MM``); never nearer the edge of
       ``region`` than half its width (less the point filter). No ring doubles back on
       itself: the strips that offset rings would cover twice get one centre line.

    No gap path is narrower than ``mat.min_bead_width_mm`` (``w_lay``), the narrowest bead
    the valve lays as a line (one drop per mm, thesis 6.1: see the setting): a strip
    down to ``w_lay / GAP_WIDEN_RATIO`` wide gets a bead ``w_lay`` wide (at most 30 % more
    than it holds, as a run of constant width does), unless the bead would then reach
    beyond ``region``. Gaps (or parts of gaps) narrower than that, or than
    ``THIN_GAP_MIN * w``, get no path and are returned, with every other bit no path
    sweeps, as the unfilled remainder.

    gaps: flat oriented rings (mm), the nominal area minus the bands already swept grown
        by ``filt + SWEEP_TOL`` (so touching bands leave no slivers).
    nominal: the nominal area (the paths stay in it).
    Returns (paths ``(points, closed, width)``, the width one number or, for a
    variable-width path, (k,) one per point; remaining gaps as flat oriented rings).
    """
    w = mat.path_width_mm
    tol = filt + SWEEP_TOL
    w_max = max(w, mat.fill_width_mm)
    w_lay = min(mat.min_bead_width_mm, w_max)
    w_min = max(THIN_GAP_MIN * w, w_lay / GAP_WIDEN_RATIO)
    paths: list[tuple[np.ndarray, bool, float]] = []

    def take(new: list[tuple[np.ndarray, bool, float]]) -> None:
        nonlocal gaps
        if new:
            paths.extend(new)
            gaps = geo.difference_rings(gaps, geo.sweep_rings(new, tol))

    rings = geo.offset_rings(gaps, -w / 2.0, filt)
    take([(r, True, w) for r in _with_room(rings, [], w, filt)] if rings else [])
    if gaps and not mat.variable_width:
        take(_pocket_rings(gaps, w_min, w, filt, w_lay))
    if gaps and geo.area(gaps) >= w_min * w_min:
        # the gap before the bands' growth by tol: where the paths may go
        room = geo.intersection(geo.offset_rings(gaps, tol, 0.0), nominal)
        take(centre_paths(list(room.rings), w_min, w_max, filt, region, mat.variable_width,
                          w_lay))
    return paths, gaps


def _pocket_rings(gaps: list[np.ndarray], w_min: float, w_max: float, filt: float,
                  w_lay: float = 0.0) -> list[tuple[np.ndarray, bool, float]]:
    """One ring in every round gap piece (see :func:`gap_fill_paths`, step 2); slivers
    narrower than ``w_min`` (no path goes there) do not join pockets into one piece."""
    pieces = geo.region_from_rings(gaps)
    core = geo.intersection(geo.opening(pieces, w_min / 2.0, 0.0), pieces)
    if core.is_empty:
        return []
    rings = list(core.rings)
    areas = geo.ring_areas(rings)
    perims = geo.ring_perimeters(rings)
    depth = core.depth()
    # every hole (odd depth) counts for the outer ring it belongs to
    owner = np.where(depth % 2 == 1, core.parent, np.arange(len(rings)))
    A = np.bincount(owner, weights=areas, minlength=len(rings))
    P = np.bincount(owner, weights=perims, minlength=len(rings))
    # pockets of about one width are offset and given room at once (they are disjoint,
    # so the offsets and openings of all equal those of each); the width is floored to a
    # multiple of POCKET_WIDTH_STEP_MM (never wider than its estimate)
    by_width: dict[float, list[np.ndarray]] = {}
    for i in np.flatnonzero((depth % 2 == 0) & (A > 0)):
        if 4.0 * math.pi * A[i] / P[i] ** 2 < GAP_BLOB_ROUNDNESS:
            continue
        # 2 A / P is the inradius of a polygon with an incircle and overestimates it
        # for others (by 22 % for a half disk): the ring's room is checked anyway
        wb = min(0.8 * 2.0 * A[i] / P[i], w_max)
        if wb < w_min:
            continue
        wq = max(math.floor(wb / POCKET_WIDTH_STEP_MM + 1e-9) * POCKET_WIDTH_STEP_MM, w_min,
                 w_lay)
        by_width.setdefault(wq, []).extend(
            [rings[i]] + [rings[j] for j in np.flatnonzero((owner == i) & (depth % 2 == 1))])
    out: list[tuple[np.ndarray, bool, float]] = []
    for wb, poly in sorted(by_width.items()):
        found = geo.offset_rings(poly, -wb / 2.0, filt)
        if found:
            out += [(r, True, wb) for r in _with_room(found, [], wb, filt)]
    return out


def centre_paths(rings: list[np.ndarray], w_min: float, w_max: float, filt: float,
                 region: Region | None = None, variable: bool = True, w_lay: float = 0.0
                 ) -> list[tuple[np.ndarray, bool, float | np.ndarray]]:
    """Paths along the centre line of a thin area, about as wide as the area (see
    :func:`gap_fill_paths`, step 3): ``(points (k, 2) mm, closed, width)``.

    rings: flat oriented rings bounding the area. Parts narrower than ``w_min`` get no
    path; widths are capped at ``w_max``, and at twice the distance to the edge of
    ``region`` (the paths' region; less the filter's deviation) when given.
    variable: one path per centre-line chain with a width per point (``width`` (k,) mm,
    twice the clearance: :func:`_chain_paths`); else runs of one width each
    (:func:`_run_paths`). w_lay: no path is narrower (mm): where the area is narrower (but
    at least ``w_min``) the bead is widened to it, and where the edge of ``region`` leaves
    it less room the path is cut.
    """
    if not rings:
        return []
    perim = float(geo.ring_perimeters(rings).sum())
    typical = 2.0 * max(geo.area(rings), 0.0) / max(perim, 1e-12)  # a strip's width
    spacing = float(np.clip(typical / 3.0, w_min / 3.0, w_max / 4.0))
    # the region's edges, sampled once for the branches' room and the beads' cap
    edges = (geo.RingEdges(region.rings)
             if region is not None and not region.is_empty else None)
    room = _room_to_edge(edges, w_max / 2.0, spacing) if edges is not None else None
    # (slack: _simplified keeps the widths within the point filter of their profile)
    chains = geo.medial_axis(rings, spacing, w_min / 2.0, w_max / 2.0, room, filt / 2.0)
    w_lay = min(w_lay, w_max)
    if w_lay > 0.0:   # clearances (half-widths) from w_min / 2 up are raised to w_lay / 2
        chains = [(p, np.where(r >= 0.5 * w_min, np.maximum(r, 0.5 * w_lay), r), c)
                  for p, r, c in chains]
    # cut where narrower than the valve lays (the edge cap can make it so), a hair below
    # it for the rounding of the widths' interpolation
    w_cut = max(w_min, w_lay * (1.0 - 1e-9))
    # with a narrowest bead, no stubs shorter than their width either (GAP_MIN_LENGTH)
    min_length = GAP_MIN_LENGTH if w_lay > 0.0 else 0.0
    if variable:
        return _chain_paths(chains, w_cut, w_max, filt, edges, min_length)
    return _run_paths(chains, w_cut, w_max, filt, edges, min_length)


def _room_to_edge(edges: geo.RingEdges, upper: float, step: float
                  ) -> Callable[[np.ndarray], np.ndarray]:
    """How far a bead may reach from each of some points (k, 2) mm: to the region's edge
    ``edges`` (as :func:`_edge_capped` will cap it; at most ``upper``), less ``step``, a
    step of the centre line, whose segments reach nearer the edge than their points."""
    return lambda pts: geo.segment_clearances(pts, pts, edges, upper) - step


def _chain_paths(chains: list[tuple[np.ndarray, np.ndarray, bool]], w_min: float,
                 w_max: float, filt: float, edges: geo.RingEdges | None,
                 min_length: float = 0.0) -> list[tuple[np.ndarray, bool, np.ndarray]]:
    """Variable-width centre-line paths (issue 15): each medial-axis chain is one path
    whose width at every point is twice its clearance, smoothed (:func:`_smoothed_axis`),
    simplified within the point filter ``filt``, the width profile too
    (:func:`_simplified`), at most ``w_max``, capped at twice the distance to the paths'
    region's edge ``edges`` (when given), and cut where it is narrower than ``w_min``; open
    pieces shorter than ``min_length`` times their widest width are left out
    (``GAP_MIN_LENGTH``)."""
    chains = [(np.asarray(p, np.float64), np.minimum(2.0 * np.asarray(r, np.float64), w_max),
               bool(c)) for p, r, c in chains if len(p) >= 2]
    if not chains:
        return []
    chains = _smoothed_axis(chains)
    # closed chains as polylines back to their first point (the widths' profile, the
    # edge cap and the areas work on polylines)
    lines = [closed_polyline(p, c) for p, _w, c in chains]
    widths = [closed_polyline(w, c) for _p, w, c in chains]
    # within the point filter, as every ring is: a tighter tolerance (15 % of the bead's
    # width) kept the axis' zigzag (10 bunny layers: 25 % less gap time with the whole
    # filter)
    eps = np.full(len(lines), float(filt))
    # a closed chain is filtered as a ring (as a polyline back to its first point it
    # would touch itself there and keep every point)
    closed = np.array([c for _p, _w, c in chains], dtype=bool)
    masks: list[np.ndarray] = [np.zeros(0, bool)] * len(lines)
    for flag in (False, True):
        idx = np.flatnonzero(closed == flag)
        if len(idx):
            got = geo.simplify_masks([lines[i][:-1] if flag else lines[i] for i in idx],
                                     eps[idx], closed=flag)
            for i, m in zip(idx, got):
                masks[i] = np.append(m, True) if flag else m
    lines, widths = _simplified(lines, widths, masks, eps)
    widths = [np.minimum(w, w_max) for w in widths]
    if edges is not None:
        widths = _edge_capped(lines, widths, edges, w_max)
    # length and swept area of every whole line at once (most are open and wide enough)
    length, band = _length_and_band(lines, widths)
    W = np.concatenate(widths)
    n = np.array([len(ln) for ln in lines])
    first = np.cumsum(n) - n
    last = first + n - 1
    swept = band + math.pi / 8.0 * (W[first] ** 2 + W[last] ** 2)   # round ends
    wide = np.minimum.reduceat(W, first) >= w_min
    out: list[tuple[np.ndarray, bool, np.ndarray]] = []
    for k, ((_p, _w, closed), ln, w) in enumerate(zip(chains, lines, widths)):
        if wide[k] and not closed:
            if length[k] >= min_length * float(w.max()) and length[k] > 1e-3 \
                    and swept[k] >= GAP_MIN_AREA_MM2:
                out.append((ln, False, w))
            continue
        ok = w >= w_min
        if closed and ok.all() and len(ln) > 3:
            pts, wr = ln[:-1], w[:-1]
            # a centre line around a hole narrower than the path would overlap itself
            if signed_area(pts) > 0 and not _has_room(pts, float(wr.max())):
                continue
            out.append((pts, True, wr))
            continue
        if closed and not ok.all():   # start the polyline where it is too narrow
            j = int(np.flatnonzero(~ok)[0])
            ln = np.concatenate([ln[j:-1], ln[:j + 1]])
            w, ok = np.concatenate([w[j:-1], w[:j + 1]]), np.concatenate([ok[j:-1], ok[:j + 1]])
        # the runs of consecutive points wide enough, each a path
        edges = np.flatnonzero(np.diff(np.concatenate([[0], ok.astype(np.int8), [0]])))
        for a, b in zip(edges[::2], edges[1::2]):
            if b - a < 2:
                continue
            pts, wr = ln[a:b], w[a:b]
            (piece,), (area,) = _length_and_band([pts], [wr])
            if piece > 1e-3 and piece >= min_length * float(wr.max()) \
                    and area + math.pi / 8.0 * (wr[0] ** 2 + wr[-1] ** 2) >= GAP_MIN_AREA_MM2:
                out.append((pts, False, wr))
    return out


#: Passes of the binomial (1, 2, 1) / 4 filter over a medial-axis chain's points
#: (:func:`_smoothed_axis`): two take out the axis' zigzag of about a tenth of a
#: millimetre (the Voronoi vertices of the sampled edges), whose turns over 30 degrees
#: each stop the robot: 15 % less gap time on 10 bunny layers, four or eight no more.
AXIS_SMOOTHING_PASSES = 2


def _smoothed_axis(chains: list[tuple[np.ndarray, np.ndarray, bool]],
                   max_move: float = math.inf) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """Medial-axis chains ``(points, widths, closed)`` with their points smoothed by
    ``AXIS_SMOOTHING_PASSES`` passes of the (1, 2, 1) / 4 filter along each chain (an open
    chain's ends stay: they meet other chains at branch points), every width widened by
    twice its point's distance to the smoothed line, so that the bead still covers the disk
    it stood for. ``max_move``: no point moves farther (mm; its move is shortened)."""
    n = np.array([len(p) for p, _w, _c in chains])
    P = np.concatenate([p for p, _w, _c in chains])
    W = np.concatenate([w for _p, w, _c in chains])
    closed = np.repeat(np.array([c for _p, _w, c in chains], dtype=bool), n)
    first = np.repeat(np.cumsum(n) - n, n)
    last = first + np.repeat(n, n) - 1
    i = np.arange(len(P))
    prev = np.where(i == first, last, i - 1)          # a closed chain wraps round
    nxt = np.where(i == last, first, i + 1)
    fixed = ~closed & ((i == first) | (i == last))
    Q = P
    for _ in range(AXIS_SMOOTHING_PASSES):
        Q = np.where(fixed[:, None], Q, 0.25 * Q[prev] + 0.5 * Q + 0.25 * Q[nxt])
    if math.isfinite(max_move):
        move = np.hypot(*(Q - P).T)
        Q = P + (Q - P) * np.minimum(1.0, max_move / np.maximum(move, 1e-300))[:, None]
    # how far each point is from the smoothed line (its segments on either side; a move
    # along the line needs no widening)
    before = np.where(~closed & (i == first), i, prev)
    after = np.where(~closed & (i == last), i, nxt)
    off = np.minimum(geo.segment_distance(P, Q[before], Q), geo.segment_distance(P, Q, Q[after]))
    W = W + 2.0 * off
    return [(q, w, c) for q, w, (_p, _w, c) in zip(_split(Q, n), _split(W, n), chains)]


def _simplified(lines: list[np.ndarray], widths: list[np.ndarray], masks: list[np.ndarray],
                tol: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Width-carrying polylines reduced to the points of ``masks`` (a simplification within
    ``tol``, one per polyline) and the points needed for the width: where a dropped
    point's width lies more than ``tol`` from the profile interpolated linearly along the
    arc between the points kept around it, a point is added back (each round for the worst
    of every span), on the simplified line at its arc position: the width's breakpoints
    add no turns (a medial axis zigzags by a tenth of a millimetre, and every turn over
    ``motion.smooth_angle_deg`` would stop the robot). The widths are not widened for what
    the line moves (at most ``tol``): the bead shifts by that much, as every filtered ring
    does; widening it had laid 6 % more gap bead on 10 bunny layers for 5 % less unfilled
    area, and the demo mug's open-loop height error rose from 1.868 to 1.987 mm."""
    P = np.concatenate(lines)
    W = np.concatenate(widths)
    G = np.concatenate(masks)
    K = G.copy()
    n = np.array([len(ln) for ln in lines])
    T = np.repeat(np.asarray(tol, np.float64), n)
    s = arc_lengths(np.linalg.norm(np.diff(P, axis=0), axis=1))
    idx = np.arange(len(P))

    def around(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The kept points before and after each point (a line's first and last are
        kept) and its arc fraction between them."""
        prev = np.maximum.accumulate(np.where(mask, idx, 0))
        nxt = np.minimum.accumulate(np.where(mask, idx, len(P) - 1)[::-1])[::-1]
        span = s[nxt] - s[prev]
        return prev, nxt, np.divide(s - s[prev], span, out=np.zeros(len(P)), where=span > 0)

    gp, gn, fg = around(G)
    on_line = P[gp] + fg[:, None] * (P[gn] - P[gp])     # every point's place on the line
    while True:
        prev, nxt, f = around(K)
        w_lin = W[prev] + f * (W[nxt] - W[prev])
        bad = np.flatnonzero(~K & (np.abs(W - w_lin) > T))
        if not len(bad):
            break
        o = bad[np.lexsort((-np.abs(W - w_lin)[bad], prev[bad]))]
        K[o[np.concatenate([[True], prev[o][1:] != prev[o][:-1]])]] = True
    pos = np.where(G[:, None], P, on_line)
    keep = _split(K, n)
    return ([q[k] for q, k in zip(_split(pos, n), keep)],
            [w[k] for w, k in zip(_split(W, n), keep)])


def _edge_capped(lines: list[np.ndarray], widths: list[np.ndarray], edges: geo.RingEdges,
                 w_max: float) -> list[np.ndarray]:
    """Widths no more than twice the distance of the path to the region's edge: per
    segment its clearance (:func:`icefab.geometry.segment_clearances`; a segment crossing
    a spike of the edge has none, and a width of 0 cuts the path there), per point the
    lesser of its two segments'."""
    polys = [np.asarray(ln, np.float64) for ln in lines]
    n = np.array([len(p) for p in polys])
    allp = np.concatenate(polys)
    owner = np.repeat(np.arange(len(polys)), n)
    seg = np.flatnonzero(owner[:-1] == owner[1:])
    d_seg = geo.segment_clearances(allp[seg], allp[seg + 1], edges, w_max / 2.0)
    cap = np.full(len(allp), np.inf)
    np.minimum.at(cap, seg, d_seg)
    np.minimum.at(cap, seg + 1, d_seg)
    W = np.minimum(np.concatenate(widths), 2.0 * cap)
    return _split(W, n)


def _split(a: np.ndarray, counts) -> list[np.ndarray]:
    """``a`` cut into consecutive pieces of ``counts`` rows each (views; rows after the
    last piece are left out)."""
    return split_rows(a, np.cumsum(counts, dtype=np.int64))[:-1]


def _run_paths(chains: list[tuple[np.ndarray, np.ndarray, bool]], w_min: float,
               w_max: float, filt: float, edges: geo.RingEdges | None,
               min_length: float = 0.0) -> list[tuple[np.ndarray, bool, float]]:
    """Constant-width centre-line paths: each chain cut into runs of similar width
    (``GAP_RUN_RATIO``, ``GAP_MIN_RUN_MM``), each run as wide as its widest point (at most
    ``GAP_RUN_RATIO`` times its mean), at most twice its distance to the region's edge
    ``edges`` (when given); open runs shorter than ``min_length`` times their width are
    left out."""
    runs = geo.width_runs([(p, np.minimum(2.0 * r, w_max), c) for p, r, c in chains],
                          GAP_RUN_RATIO, GAP_MIN_RUN_MM)
    if not runs:
        return []
    lo, mean, hi = np.array([r[1] for r in runs]).T
    widths = np.minimum(hi, GAP_RUN_RATIO * mean)
    # simplified within the point filter, as every ring is (the swept bands are grown by
    # it, so no gap is left uncounted), a thin bead by at most 15 % of its width: the
    # medial axis zigzags a little, and each turn over motion.smooth_angle_deg is a
    # stop of the robot (half the filter here left 25 % more corners on bunny layers)
    eps = np.minimum(filt, 0.15 * widths)
    keep = widths >= w_min
    pts = [r[0] for r in runs]
    closed = np.array([r[2] for r in runs])
    idx = np.flatnonzero(keep & ~closed)
    if len(idx):
        for i, ln in zip(idx, geo.simplify_open([pts[i] for i in idx], eps[idx])):
            pts[i] = ln
    for i in np.flatnonzero(keep & closed):
        f = geo.simplify([pts[i]], float(eps[i]))
        pts[i] = f[0] if len(f) == 1 else pts[i]
    if edges is not None and keep.any():
        # never nearer the region's edge than half the width: the least clearance of the
        # paths' segments as filtered (geometry.segment_clearances)
        idx = np.flatnonzero(keep)
        polys = [closed_polyline(pts[i], bool(closed[i])) for i in idx]
        n = np.array([len(q) for q in polys])
        allp = np.concatenate(polys)
        owner = np.repeat(np.arange(len(idx)), n)
        seg = np.flatnonzero(owner[:-1] == owner[1:])
        d = geo.segment_clearances(allp[seg], allp[seg + 1], edges, float(widths.max()) / 2.0)
        dmin = np.full(len(idx), np.inf)
        np.minimum.at(dmin, owner[seg], d)
        widths[idx] = np.minimum(widths[idx], 2.0 * dmin)
        keep = widths >= w_min
    out: list[tuple[np.ndarray, bool, float]] = []
    for i in np.flatnonzero(keep):
        p = pts[i]
        if closed[i]:
            # a centre line around a hole narrower than the path would overlap itself
            if signed_area(p) > 0 and not _has_room(p, widths[i]):
                continue
            out.append((p, True, float(widths[i])))
            continue
        length = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
        if length >= widths[i] * min_length and length > 1e-3 \
                and length * widths[i] + math.pi / 4.0 * widths[i] ** 2 >= GAP_MIN_AREA_MM2:
            out.append((p, False, float(widths[i])))
    return out


def _length_and_band(lines: Sequence[np.ndarray], widths: Sequence[np.ndarray]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Per polyline (its width (k,) at each point, linear between): its length (mm) and
    the area its band covers without the ends (mm^2, the trapezoids of its segments), all
    at once."""
    n = np.array([len(ln) for ln in lines])
    P, W = np.concatenate(lines), np.concatenate(widths)
    owner = np.repeat(np.arange(len(lines)), n)[1:]
    inside = np.ones(len(P) - 1, dtype=bool)
    inside[np.cumsum(n)[:-1] - 1] = False        # from one polyline to the next
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)[inside]
    return (np.bincount(owner[inside], weights=seg, minlength=len(lines)),
            np.bincount(owner[inside], weights=seg * 0.5 * (W[:-1] + W[1:])[inside],
                        minlength=len(lines)))


def _mean_widths(items: Sequence[tuple]) -> np.ndarray:
    """Per ordering item ``(points, closed, width)``: the length-weighted mean of a
    variable width ((k,) array; mm; the first point's on a path of no length), the path's
    nominal ``width``; NaN for a constant width."""
    out = np.full(len(items), np.nan)
    var = [i for i, it in enumerate(items) if isinstance(it[2], np.ndarray)]
    if not var:
        return out
    ws = [closed_polyline(np.asarray(items[i][2], np.float64), items[i][1]) for i in var]
    total, area = _length_and_band([closed_polyline(items[i][0], items[i][1]) for i in var],
                                   ws)
    first = np.array([w[0] for w in ws])
    out[var] = np.where(total > 0, area / np.where(total > 0, total, 1.0), first)
    return out


def plan_layer(layer: Layer, job: Job, measured: bool | None = None) -> LayerPaths:
    """Ordered paths of one layer (see the module docstring). ``measured``: whether the
    layer carries measurement paths (None: every ``feedback.interval_layers``-th layer by
    index; :func:`plan_paths` decides by height for adaptive layers,
    :func:`icefab.stages.measured_layers`)."""
    filt = job.slicing.max_filter_deviation_mm
    z = layer.z
    groups: dict[str, list[tuple[np.ndarray, bool, float]]] = {}
    unfilled = []
    hook: list[np.ndarray] = []
    for material in ("part", "scaffold"):
        mat = job.materials[material]
        region = layer.part if material == "part" else layer.scaffold
        n_hook = (_hook_wall_count(layer.index)
                  if material == "scaffold" and job.scaffold.hook_wall else 0)
        sets, taken, gap = material_paths(region, mat, job, n_hook, layer.part)
        if taken:
            hook = taken
        groups[f"{material}:boundary"] = sets["boundary"]
        groups[f"{material}:fill"] = sets["fill"]
        unfilled.append(gap)
    if hook:
        # Hook wall: the outermost scaffold rings are deposited in ice (thesis 3.7).
        w = job.materials.part.path_width_mm
        groups["part:boundary"] = groups["part:boundary"] + [(r, True, w) for r in hook]

    if measured is None:
        measured = job.feedback.enabled and \
            (layer.index + 1) % job.feedback.interval_layers == 0
    order = list(job.materials.order)
    if measured:
        for material in ("part", "scaffold"):
            region = layer.part if material == "part" else layer.scaffold
            spacing = job.feedback.measure_spacing_mm
            speed = laser_speed(material, job)
            longest = speed * min(MEASURE_MAX_SAMPLES / job.simulation.laser_rate_hz,
                                  MEASURE_STORE_FRACTION * path_store_s(job))
            groups[f"{material}:measure"] = [
                (pts, closed, 0.0)
                for pts, closed in measure_paths(region, spacing, filt,
                                                 measure_lane_mm(spacing, speed), longest)]
            order.append(f"{material}:measure")

    paths: list[Toolpath] = []
    cur = np.zeros(2)
    cur_tool: str | None = None
    corner = job.motion.smooth_angle_deg
    # a tour's travel moves at the deposition's speed bound: not when travel is slower
    tours = job.motion.travel_speed_mm_s >= job.motion.speed_mm_s
    for key in order:
        material, role = key.split(":")
        tool = "laser" if role == "measure" else material
        ordered, _end = order_nearest(groups.get(key, []), cur, corner)
        ordered, _end = _tour.improve(ordered, cur, _entry_candidates(ordered, corner))
        means = _mean_widths(ordered)
        group = []
        for (pts, closed, width), mean in zip(ordered, means):
            widths = None
            if isinstance(width, np.ndarray):   # a variable-width path: its mean width
                widths = np.ascontiguousarray(width, dtype=np.float64)
                width = mean
            group.append(Toolpath(np.ascontiguousarray(pts), z, material, role, closed,
                                  float(width), layer.index, "part", tool, widths))
        if role != "measure" and tours:
            group = join_tours(group, job.materials[material].tour_max_turn_deg,
                               TOUR_STORE_FRACTION * path_store_s(job) * job.motion.speed_mm_s)
        for p in group:
            pts = p.points
            if cur_tool is not None:
                a = cur if cur_tool == tool else (
                    cur - tool_offset(cur_tool, job) + tool_offset(tool, job))
                if float(np.hypot(*(pts[0] - a))) > 1e-9:
                    paths.append(Toolpath(np.array([a, pts[0]]), z, material, "travel", False,
                                      0.0, layer.index, "part", tool))
            paths.append(p)
            cur = pts[0] if p.closed else pts[-1]
            cur_tool = tool
    return LayerPaths(layer.index, z, tuple(paths), (float(unfilled[0]), float(unfilled[1])),
                      layer.thickness, layer.top_z)


def plan_paths(stack: Stack, job: Job | None = None, *,
               progress: Callable[[int, int], None] | None = None) -> Toolpaths:
    """Ordered deposition, measurement and travel paths of every layer.

    stack: layers with part and (after ``add_scaffold``) scaffold regions.
    job: settings (``job.materials``, ``job.feedback``, ``job.scaffold.hook_wall``,
        ``job.cell.cpus``); default ``stack.job``.
    progress: optional ``progress(done, total)`` callback (layers planned).
    Layers are planned independently on a process pool. Returns ``Toolpaths`` whose
    warnings carry the stack's warnings plus a summary of unfilled area. ConfigError if
    ``job``'s layer thickness contradicts the stack's.
    """
    job = job or stack.job
    # unpacked as the workers hand the layers back, not after the last one
    layers = [unpack_layer_paths(p)
              for p in iter_plan_paths_packed(stack, job, progress=progress)]
    return Toolpaths(tuple(layers), job, paths_warnings(stack, layers))


def iter_plan_paths_packed(stack: Stack, job: Job | None = None, *,
                           progress: Callable[[int, int], None] | None = None
                           ) -> Iterator[tuple]:
    """:func:`plan_paths` layer by layer, in order, as the pool hands the layers back and
    as the workers send them (:func:`icefab.resultfiles.pack_layer_paths`;
    ``unpack_layer_paths`` makes one a LayerPaths): ``icefab paths`` checks, tallies and
    writes them (:func:`icefab.resultfiles.save_toolpath_layers`) while the workers plan
    the next, without making their Toolpaths (issue 17). The settings are checked before
    any layer is planned."""
    job = job or stack.job
    check_stack(stack, job)
    check_paths((sum(layer.part.area for layer in stack.layers),
                 sum(layer.scaffold.area for layer in stack.layers)), job)
    if np.isfinite([L.thickness for L in stack.layers]).any():  # adaptive: by height
        flags = measured_layers([L.thickness for L in stack.layers], job)
    else:
        flags = [None] * len(stack.layers)
    return parallel_imap(_plan_task, [(layer, job, m) for layer, m in zip(stack.layers, flags)],
                         job, min_items=8, progress=progress)


def paths_warnings(stack: Stack, layers: Sequence[LayerPaths | LayerHead]) -> tuple[str, ...]:
    """The warnings of a stack's planned layers (LayerPaths, or the heads ``icefab paths``
    keeps): the stack's, and a summary of the area no path sweeps."""
    warnings = list(stack.warnings)
    total = np.array([lp.unfilled_mm2 for lp in layers]).reshape(-1, 2).sum(axis=0)
    if total.sum() >= GAP_MIN_AREA_MM2:    # less than the smallest gap path is no finding
        warnings.append(f"unfilled area (gaps the paths cannot fill): part "
                        f"{area_text(total[0])} mm^2, scaffold {area_text(total[1])} mm^2 "
                        f"over {len(layers)} layers")
    return tuple(warnings)


def _plan_task(args: tuple[Layer, Job, bool | None]) -> tuple:
    """Plan one layer in a worker; the result travels back packed in a few arrays (one
    pickled object per path would cost more than the planning of small layers)."""
    layer, job, measured = args
    return pack_layer_paths(plan_layer(layer, job, measured))


# --------------------------------------------------------------------------- estimate


def path_speed(path: Toolpath, job: Job) -> float:
    """Constant speed used for a path in the estimate, mm/s: boundary 25, fill 125,
    travel ``travel_speed_mm_s``, part measurement ``measure_speed_mm_s`` (50: the
    reflective ice, thesis 4.2), scaffold measurement ``speed_mm_s`` (125)."""
    return float(_speed_table(job)[ROLES.index(path.role),
                                   MATERIALS.index(path.material)])


def laser_speed(material: str, job: Job) -> float:
    """Speed along a measurement path of ``material``, mm/s, as the motion stage bounds it
    (:func:`icefab.motion.path_limits`): ``measure_speed_mm_s`` over the ice (50: its
    reflective surface, thesis 4.2), ``speed_mm_s`` over the scaffold (125)."""
    m = job.motion
    return float(m.measure_speed_mm_s if material == "part" else m.speed_mm_s)


def _speed_table(job: Job) -> np.ndarray:
    """(roles, materials) float64 mm/s: :func:`path_speed` of every role and material
    (indexed as ``icefab.core.ROLES`` and ``MATERIALS``: the packed paths' codes)."""
    m = job.motion
    table = np.empty((len(ROLES), len(MATERIALS)))
    for r, role in enumerate(ROLES):
        for k, material in enumerate(MATERIALS):
            if role == "boundary":
                v = m.boundary_speed_mm_s
            elif role == "fill":
                v = m.fill_speed_mm_s
            elif role == "travel":
                v = m.travel_speed_mm_s
            else:
                v = laser_speed(material, job)
            table[r, k] = v
    return table


def estimate_build_time(toolpaths: Toolpaths | PackedToolpaths, job: Job | None = None
                        ) -> tuple[np.ndarray, float]:
    """Build time at constant speeds (thesis 4.2), to compare with trajectory planning.

    Returns (per-layer times (n,) float64 s, total s). Accelerations are ignored.
    """
    job = job or toolpaths.job
    if isinstance(toolpaths, PackedToolpaths):   # as its arrays (icefab plan), the same
        per = np.array([packed_estimate(d, job, packed_lengths(d))
                        for d in toolpaths.layers], dtype=np.float64)
    else:
        per = np.array([layer_estimate(lp, job) for lp in toolpaths.layers],
                       dtype=np.float64)
    return per, float(per.sum())


def layer_estimate(lp: LayerPaths, job: Job) -> float:
    """One layer's :func:`estimate_build_time`, s."""
    if not lp.paths:
        return 0.0
    speeds = _speed_table(job)[[ROLES.index(p.role) for p in lp.paths],
                               [MATERIALS.index(p.material) for p in lp.paths]]
    return float((path_lengths(lp.paths) / speeds).sum())


def packed_estimate(packed: dict[str, np.ndarray], job: Job, lengths: np.ndarray) -> float:
    """:func:`layer_estimate` of a layer as :func:`icefab.resultfiles.pack_paths` packed
    its paths (``lengths``: theirs, mm), the same value."""
    if not len(lengths):
        return 0.0
    speeds = _speed_table(job)[packed["role"].astype(np.int64),
                               packed["material"].astype(np.int64)]
    return float((lengths / speeds).sum())


# --------------------------------------------------------------------------- files

#: Format of ``save_toolpaths`` files.
