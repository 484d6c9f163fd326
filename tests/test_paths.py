"""Deposition paths (thesis 3.4-3.5, 3.7, 5.2.1): invariants checked with shapely, analytic
times and frames, ordering, file round trip."""
from __future__ import annotations

import dataclasses
import math
import os

import numpy as np
import pytest
import shapely
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st
from shapely.geometry import LinearRing, LineString

from icefab import geometry as geo
from icefab import paths as paths_mod
from icefab.config import Job
from icefab.errors import StackFileError
from icefab.resultfiles import POINT_GRID_PER_MM, _point_states, decode_counts
from icefab.paths import (OFF, ON1, ON2, SWEEP_TOL, centre_paths, deposition_state,
                          estimate_build_time, jin_segment_time, layer_point_states,
                          load_toolpaths, order_nearest, plan_layer, plan_paths, point_states,
                          save_toolpaths, to_base_frame)
from icefab.regions import add_scaffold
from icefab.core import (Layer, LayerPaths, Toolpath, Region, Toolpaths, signed_area,
                         tour_members)
from test_geometry import (check_region_structure, polygon_with_holes, rect,
                           to_shapely)
from test_regions import fuzzed_part, make_stack, prism, table

FILT = geo.FILTER_MM + 2e-3


def region_of(layer: Layer, material: str) -> Region:
    return layer.part if material == "part" else layer.scaffold


def _geom(p: Toolpath):
    return LinearRing(p.points) if p.closed else LineString(p.points)


def _variable_sweep(p: Toolpath, grow: float = 0.0):
    """The area a variable-width path sweeps, independently of icefab.geometry: the union
    of the convex hulls of the disks (half its width + ``grow``) at consecutive points."""
    pts, r = p.polyline(), p.polyline_widths() / 2.0 + grow
    disks = shapely.buffer(shapely.points(pts), r, quad_segs=16)
    return shapely.union_all(shapely.convex_hull(shapely.union(disks[:-1], disks[1:])))


def _too_close(p: Toolpath, edge, allowance: float) -> bool:
    """Whether a variable-width path comes nearer ``edge`` than half its width there, less
    ``allowance`` (every segment checked at points 0.05 mm apart)."""
    pts, w = p.polyline(), p.polyline_widths()
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    n = np.maximum(1, np.ceil(seg / 0.05).astype(int))
    i = np.repeat(np.arange(len(seg)), n)
    t = (np.arange(len(i)) - np.repeat(np.cumsum(n) - n, n)) / n[i]
    q = pts[i] + t[:, None] * (pts[i + 1] - pts[i])
    wq = w[i] + t * (w[i + 1] - w[i])
    d = shapely.distance(edge, shapely.points(q))
    return bool(np.any(d < wq / 2.0 - allowance))


def _members(lp: LayerPaths) -> list[Toolpath]:
    """A layer's paths with every continuous tour as the paths it joins."""
    return [m for p in lp.paths for m in tour_members(p)]


def check_layer_paths(layer: Layer, lp: LayerPaths, job: Job, min_cover: float | None = 0.97,
                      hook: bool = False):
    """Must-show invariants of one layer's paths, measured with shapely."""
    for material in ("part", "scaffold"):
        region = region_of(layer, material)
        mat = job.materials[material]
        check_region_structure(region)
        R = to_shapely(region)
        # a continuous tour is checked path by path: its travel deposits nothing
        members = [m for p in lp.paths for m in tour_members(p)]
        deposit = [p for p in members if p.material == material and p.depositing]
        if hook and material == "scaffold":
            # the hook wall's ice rings take the place of outer scaffold paths
            P = to_shapely(layer.part).buffer(1e-6)
            deposit += [p for p in members if p.material == "part" and p.depositing
                        and not P.covers(_geom(p))]
        if region.is_empty:
            assert not deposit
            continue
        if hook and material == "part":
            # hook-wall rings (former scaffold paths) are checked with the scaffold
            Rg = R.buffer(1e-6)
            deposit = [p for p in deposit if Rg.covers(_geom(p))]
        geoms = np.array([_geom(p) for p in deposit], dtype=object)
        widths = np.array([p.width for p in deposit])
        for p, g in zip(deposit, geoms):
            # no self-intersections (GEOS: a ring touching itself is not simple either),
            # and a closed path bounds a valid polygon (no zero-area ring)
            assert g.is_simple, (layer.index, material, p.role, "self-intersecting",
                                 len(p.points))
            assert not p.closed or shapely.Polygon(p.points).is_valid, \
                (layer.index, material, p.role, "invalid ring", len(p.points))
        # inside the region, at least half the path width from the edge, except the
        # calibrated initial offset of boundaries (thesis 3.7) and the point filter
        # (exact distances to the region's edge)
        d = np.array([min(p.width / 2.0, mat.initial_offset_mm) if p.role == "boundary"
                      else p.width / 2.0 for p in deposit])
        shapely.prepare(R)
        edge = R.boundary
        shapely.prepare(edge)
        variable = np.array([p.widths is not None for p in deposit], dtype=bool)
        inside = shapely.covers(R, geoms) & (
            variable | ~shapely.dwithin(edge, geoms, d - FILT - 1e-9))
        for p, ok in zip(deposit, inside):
            assert ok, (layer.index, material, p.role, "too close to the edge", p.width)
            # a variable-width path: half its width there from the edge, at every point
            assert p.widths is None or not _too_close(p, edge, FILT + 1e-9), \
                (layer.index, material, p.role, "too close to the edge", p.widths)
        # room: the area an outer fill ring bounds holds a disk as wide as the path (else
        # the path overlaps itself all along), up to the point filter
        rooms = [(p, shapely.Polygon(p.points)) for p in deposit
                 if p.role == "fill" and p.closed and signed_area(p.points) > 0]
        if rooms:
            shrunk = shapely.buffer([q for _p, q in rooms],
                                    [-(p.width / 2 - FILT) for p, _q in rooms])
            for (p, _q), sh in zip(rooms, shrunk):
                assert not sh.is_empty, (layer.index, material, "fill ring wider than its room",
                                         p.width)
        # swept bead: mitred corners (the robot stops at sharp corners, thesis 4.2
        # PATHSPLIT, and the bead fills the corner), round ends where it stops
        swept = shapely.buffer(geoms, widths / 2.0, join_style="mitre", mitre_limit=2.0)
        grow = SWEEP_TOL + job.slicing.max_filter_deviation_mm
        swept_tol = shapely.buffer(geoms, widths / 2.0 + grow, join_style="mitre",
                                   mitre_limit=2.0)
        for k in np.flatnonzero(variable):     # round joins, the width of each point
            swept[k] = _variable_sweep(deposit[k])
            swept_tol[k] = _variable_sweep(deposit[k], grow)
        if min_cover is not None:
            covered = shapely.union_all(swept)
            nominal = R.buffer(-max(mat.initial_offset_mm - mat.path_width_mm / 2, 0.0),
                               quad_segs=16) if mat.initial_offset_mm > mat.path_width_mm / 2 \
                else R
            # exempt: what is narrower than the path width (part features so thin are
            # reported by add_scaffold; gap fill still covers what it can of them)
            r = 0.49 * mat.path_width_mm
            resolvable = nominal.intersection(R.buffer(-r, quad_segs=16).buffer(r, quad_segs=16))
            if resolvable.area > 0:
                frac = resolvable.intersection(covered).area / resolvable.area
                assert frac >= min_cover, (layer.index, material, "covered", frac)
            # the reported remainder matches the independent measure (gaps narrower than
            # the point filter + SWEEP_TOL on each side are not counted)
            gap = nominal.difference(shapely.union_all(swept_tol)).area
            reported = lp.unfilled_mm2[0 if material == "part" else 1]
            assert reported == pytest.approx(gap, abs=0.02 * nominal.area + 0.5)
    # travel paths connect consecutive paths: in the base frame the end effector never jumps
    prev_end = None
    for p in lp.paths:
        base = to_base_frame(p.points, p.tool_name, job)
        if prev_end is not None:
            assert np.allclose(base[0], prev_end, atol=1e-9), p.role
        prev_end = base[0] if p.closed else base[-1]
        if p.role == "travel":
            assert p.width == 0 and not p.closed and len(p.points) == 2


# ----------------------------------------------------------------------------- analytic


def test_square_boundary_and_concentric_rings_are_where_expected():
    job = Job().replace(**{"feedback.enabled": False})
    layer = Layer(0, 0.125, geo.region_from_rings([rect(0, 0, 30, 30)]))
    lp = plan_layer(layer, job)
    part = [p for p in lp.paths if p.material == "part" and p.depositing]
    b = [p for p in part if p.role == "boundary"]
    assert len(b) == 1
    # boundary: 0.6 mm inside; fill rings at 0.6 + 0.75 + 1.5 = 2.85, then every 3 mm
    assert shapely.Polygon(b[0].points).area == pytest.approx(28.8 ** 2)
    rings = sorted((shapely.Polygon(p.points).area for p in part if p.role == "fill"
                    and p.width == 3.0), reverse=True)
    side = [30 - 2 * (2.85 + 3 * k) for k in range(5)]
    # the fifth ring (0.3 mm square) has no room for a 3 mm path: left to the gap fill
    assert side[-1] == pytest.approx(0.3)
    assert rings == pytest.approx([s * s for s in side if s >= 3.0])
    check_layer_paths(layer, lp, job)


def test_strip_between_the_scaffold_boundaries_is_filled_along_its_centre():
    # surround 4.2 mm: the two scaffold boundaries (1.2 mm in, 1.5 mm wide) take 3.9 mm and
    # leave a 0.3 mm strip (the audit's 92.8 % layers): one centre line 0.3 mm wide
    job = Job().replace(**{"scaffold.buffer_mm": 4.2, "feedback.enabled": False})
    st_ = add_scaffold(make_stack([geo.region_from_rings([rect(0, 0, 20, 20)])] * 2, job))
    layer = st_.layers[0]
    lp = plan_layer(layer, job)
    check_layer_paths(layer, lp, job)
    gap = [p for p in _members(lp) if p.material == "scaffold" and p.role == "fill"]
    assert gap and all(0.25 <= p.width <= 0.3 * 1.3 for p in gap)
    mid = shapely.box(-2.1, -2.1, 22.1, 22.1).exterior  # the strip's centre line
    for p in gap:
        assert shapely.distance(mid, shapely.points(p.points)).max() < 0.05
    assert sum(p.length for p in gap) == pytest.approx(mid.length, rel=0.02)


@pytest.mark.parametrize("buffer, strip", [(4.2, 0.3), (5.0, 1.1)])
def test_no_gap_bead_narrower_than_the_valve_lays(buffer, strip):
    # materials.*.min_bead_width_mm (issue 15: no path narrower than the nozzle can lay):
    # the scaffold's 1.25 mm (one 0.31 mm^3 pulse per mm at 0.25 mm layers). A 0.3 mm
    # strip between the scaffold boundaries gets no path and is reported unfilled; a
    # 1.1 mm one (at least 1.25 / 1.3) gets a bead 1.25 mm wide along its centre line.
    job = Job().replace(**{"scaffold.buffer_mm": buffer, "feedback.enabled": False,
                           "materials.scaffold.min_bead_width_mm": 1.25})
    st_ = add_scaffold(make_stack([geo.region_from_rings([rect(0, 0, 20, 20)])] * 2, job))
    lp = plan_layer(st_.layers[0], job)
    gap = [p for p in _members(lp) if p.material == "scaffold" and p.role == "fill"]
    b = buffer / 2.0    # the strip's centre line: a square buffer / 2 outside the part
    mid = shapely.box(-b, -b, 20.0 + b, 20.0 + b).exterior
    if strip < 1.25 / 1.3:
        assert not gap
        # less the bands' growth by the point filter and SWEEP_TOL on either side
        grown = 2.0 * (job.slicing.max_filter_deviation_mm + SWEEP_TOL)
        assert lp.unfilled_mm2[1] == pytest.approx((strip - grown) * mid.length, rel=0.1)
    else:
        assert gap and all(p.width >= 1.25 - 1e-9 for p in gap)
        for p in gap:
            w = p.widths if p.widths is not None else np.full(len(p.points), p.width)
            assert w.min() >= 1.25 - 1e-9
            # (the centre line cuts the square's corners by up to 0.17 mm)
            assert shapely.distance(mid, shapely.points(p.points)).max() < 0.2
        assert sum(p.length for p in gap) == pytest.approx(mid.length, rel=0.02)
        assert lp.unfilled_mm2[1] < 1.0


@settings(max_examples=25, deadline=None)
@given(st.floats(0.1, 1.2), st.floats(0.0, 0.4), st.floats(0.1, 0.6), st.floats(0, 6.3),
       st.booleans())
def test_centre_lines_keep_the_narrowest_bead(mean, amp, freq, phase, variable):
    # a strip whose half width wanders across the narrowest bead's (w_lay = 1 mm): every
    # path at least w_lay wide everywhere, every open one at least as long as it is wide
    # (a stub shorter than its width would be mostly round ends the valve does not lay),
    # and nothing where the strip is under w_lay / 1.3 all along
    x = np.linspace(0.0, 30.0, 301)
    h = np.maximum(mean + amp * np.sin(freq * x + phase), 0.05)
    w_lay = 1.0
    w_min = w_lay / paths_mod.GAP_RUN_RATIO
    got = centre_paths([_strip(h, x)], w_min, 3.0, 0.05, variable=variable, w_lay=w_lay)
    for pts, closed, w in got:
        w = np.broadcast_to(np.asarray(w, dtype=np.float64), (len(pts),))
        assert w.min() >= w_lay * (1.0 - 1e-9)
        length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
        assert closed or length >= w.max() * paths_mod.GAP_MIN_LENGTH
    if (2.0 * h).max() < w_min:
        assert not got


def _strip(h: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A strip along x between y = -h(x) and h(x), as a counter-clockwise ring."""
    return np.vstack([np.column_stack([x, -h]), np.column_stack([x[::-1], h[::-1]])])


@settings(max_examples=20, deadline=None)
@given(st.floats(0.15, 0.45), st.floats(0.0, 0.25), st.floats(0.1, 0.6), st.floats(0, 6.3))
def test_a_strip_of_changing_width_is_one_path_as_wide_as_it(mean, amp, freq, phase):
    # the centre line of a strip whose half width h(x) wanders (at most 0.7 mm: the
    # widest bead is 1.5 mm here): one variable-width path along it (runs of one width need
    # several), as wide as the strip wherever it goes, covering it but for its ends (the
    # medial axis stops short of the corners)
    x = np.linspace(0.0, 30.0, 301)
    h = np.maximum(mean + amp * np.sin(freq * x + phase), 0.1)
    ring = _strip(h, x)
    var = centre_paths([ring], 0.15, 1.5, 0.05)
    runs = centre_paths([ring], 0.15, 1.5, 0.05, variable=False)
    assert len(var) <= len(runs)
    main = max(var, key=lambda q: float(np.linalg.norm(np.diff(q[0], axis=0), axis=1).sum()))
    pts, closed, w = main
    assert not closed and w.shape == (len(pts),)
    inner = (pts[:, 0] > 2.0) & (pts[:, 0] < 28.0)
    want = 2.0 * np.interp(pts[inner, 0], x, h)
    # twice the clearance (a little less than the strip's width where it slopes), widened
    # by at most twice the 0.05 mm simplification tolerance
    assert np.all(w[inner] <= want + 2 * 0.05 + 1e-9)
    assert np.all(w[inner] >= 0.8 * want)
    strip = shapely.Polygon(ring)
    swept = shapely.union_all([_variable_sweep(Toolpath(points=q, closed=c, widths=ww))
                               for q, c, ww in var])
    core = strip.intersection(shapely.box(1.5, -2, 28.5, 2))
    # 95.5 %, not 97: where the strip narrows to 0.2 mm (the clamp, barely wider than the
    # thinnest 0.15 mm bead) the centre line's simplification within the 0.05 mm filter
    # moves the bead off the middle (widening for it was measured and dropped, issue 15).
    # 600 random strips cover 96.9 % at worst; at the narrowest mean (0.15 mm, half of
    # the strip at the clamp) 400 cover 96.0 % at worst and hypothesis found 95.8 %
    assert core.intersection(swept).area >= 0.955 * core.area


def test_centre_lines_cut_where_too_narrow_beside_whole_ones():
    # a chain cut where it is narrower than the thinnest bead, then a whole open one and
    # a closed one: every part wide enough becomes a path (the bunny's layers mix them)
    from icefab.paths import _chain_paths
    x = np.linspace(0.0, 10.0, 41)
    line = np.c_[x, np.zeros_like(x)]
    neck = np.where(np.abs(x - 5.0) < 1.0, 0.05, 0.4)        # clearance, mm
    t = np.linspace(0.0, 2.0 * np.pi, 60, endpoint=False)
    chains = [(line, neck, False), (line + [0.0, 5.0], np.full(41, 0.4), False),
              (np.c_[20 + 4 * np.cos(t), 4 * np.sin(t)], np.full(60, 0.4), True),
              (line + [0.0, 9.0], neck, False)]
    out = _chain_paths(chains, 0.15, 1.5, 0.05, None)
    assert sorted((round(float(p[:, 0].min()), 1), bool(c)) for p, c, _w in out) == [
        (0.0, False), (0.0, False), (0.0, False), (6.0, False), (6.0, False), (16.0, True)]
    for p, _c, w in out:
        assert w.shape == (len(p),) and np.all(w >= 0.15)


def test_ordering_keeps_each_width_with_its_point():
    rng = np.random.default_rng(5)
    items = []
    for k in range(12):
        pts = rng.uniform(0, 50, (int(rng.integers(2, 9)), 2))
        items.append((pts, bool(k % 3 == 0), pts[:, 0] / 10.0))   # width = x / 10
    ordered, _ = order_nearest(items, np.zeros(2))
    from icefab import _tour
    from icefab.paths import _entry_candidates
    improved, _ = _tour.improve(ordered, np.zeros(2), _entry_candidates(ordered))
    for pts, _c, w in ordered + improved:
        np.testing.assert_array_equal(w, pts[:, 0] / 10.0)
    assert sorted(len(it[0]) for it in improved) == sorted(len(it[0]) for it in items)


def test_gap_paths_never_reach_past_the_region():
    # a fin 0.7-1.0 mm wide: no boundary fits (0.6 mm in from both sides), a centre line
    # of the fin's width does; its bead stays inside (the old gap rings sat 0.45 of their
    # width from the edge: 0.05 mm past it)
    job = Job().replace(**{"feedback.enabled": False})
    for width in (0.7, 1.0):
        fin = geo.union(geo.region_from_rings([rect(0, 0, 20, 20)]),
                        geo.region_from_rings([rect(20, 10 - width / 2, 30, 10 + width / 2)]))
        lp = plan_layer(Layer(0, 0.125, fin), job)
        R = to_shapely(fin)
        in_fin = [p for p in _members(lp) if p.role == "fill" and p.points[:, 0].mean() > 20]
        assert len(in_fin) >= 1
        main = max(in_fin, key=lambda p: p.length)
        # as wide as the fin in its middle (its ends may turn into a corner of each end's
        # fork, where a pruned fork's junction is widened)
        w = main.widths if main.widths is not None else np.full(len(main.points), main.width)
        x = main.points[:, 0]
        assert main.length > 8 and x.min() < 25.0 < x.max()
        k = int(np.flatnonzero((x[:-1] <= 25.0) & (x[1:] > 25.0))[0])
        f = (25.0 - x[k]) / (x[k + 1] - x[k])
        assert w[k] + f * (w[k + 1] - w[k]) == pytest.approx(width, rel=0.05)
        for p in _members(lp):
            if p.role == "fill" and p.widths is not None:   # half its width there
                assert not _too_close(p, R.boundary, 1e-6)
            elif p.role == "fill":
                line = LinearRing(p.points) if p.closed else LineString(p.points)
                d = shapely.distance(R.boundary, shapely.points(line.segmentize(0.01).coords))
                assert d.min() >= p.width / 2 - 1e-6


@pytest.mark.parametrize("size", [1.6, 2.2])
def test_a_pocket_gets_a_variable_width_centre_line_not_a_ring(size):
    """A round gap piece (a rounded triangle, isoperimetric ratio 0.7) gets a ring about as
    wide as its inradius only when the gap fill lays constant-width runs (it turns at every
    corner and the runs fill what it leaves); with variable widths its centre lines alone
    fill it, as wide as the pocket along their axis: nothing of it left (exact disk hulls),
    in under 60 % of the time a jerk-limited robot takes for the ring and its runs."""
    from icefab.paths import gap_fill_paths
    job = Job()
    filt = job.slicing.max_filter_deviation_mm
    th = np.linspace(0.0, 2.0 * np.pi, 3, endpoint=False) + 0.3
    pocket = shapely.Polygon(np.c_[np.cos(th), np.sin(th)] * size).buffer(0.3, quad_segs=8)
    ring = np.asarray(pocket.exterior.coords)[:-1]
    ring = ring if signed_area(ring) > 0 else ring[::-1]
    nominal = geo.region_from_rings([rect(-10, -10, 10, 10)])
    got = {}
    for variable in (False, True):
        mat = dataclasses.replace(job.materials.part, variable_width=variable)
        paths, _left = gap_fill_paths([ring], nominal, mat, filt)
        missed = pocket.difference(_exact_cover({"boundary": [], "fill": paths})).area
        got[variable] = ([c for _p, c, _w in paths], missed,
                         _fill_time({"fill": paths}, job))
    assert any(got[False][0]) and not any(got[True][0])
    assert got[True][1] < 1e-3 < got[False][1]
    assert got[True][2] < 0.6 * got[False][2]


def test_boundary_count_and_fill_none():
    job = Job().replace(**{"materials.part.boundary_count": 3,
                           "materials.part.fill_pattern": "none",
                           "materials.part.gap_fill": False, "feedback.enabled": False})
    layer = Layer(0, 0.125, geo.region_from_rings([rect(0, 0, 30, 30)]))
    lp = plan_layer(layer, job)
    b = [p for p in lp.paths if p.role == "boundary"]
    assert sorted(shapely.Polygon(p.points).area for p in b) == pytest.approx(
        sorted((30 - 2 * (0.6 + 1.5 * k)) ** 2 for k in range(3)))
    assert not [p for p in lp.paths if p.role == "fill"]


@pytest.mark.parametrize("pattern", ["concentric", "zigzag", "raster", "hybrid"])
def test_patterns_on_table_stay_inside_and_cover(pattern):
    job = Job().replace(**{"materials.part.fill_pattern": pattern,
                           "materials.scaffold.fill_pattern": pattern})
    st_ = add_scaffold(make_stack(table(6, 2), job))
    tp = plan_paths(st_, job)
    assert len(tp) == len(st_)
    for layer, lp in zip(st_.layers, tp.layers):
        # line ends keep half the fill width from the edge: less cover on small areas
        check_layer_paths(layer, lp, job, min_cover=0.97 if pattern == "concentric" else 0.75)


def test_tube_with_hole_and_mug_like_rings():
    job = Job()
    st_ = add_scaffold(make_stack(prism(4), job))
    tp = plan_paths(st_, job)
    for layer, lp in zip(st_.layers, tp.layers):
        check_layer_paths(layer, lp, job)


def test_zigzag_links_lines_and_raster_does_not():
    job = Job().replace(**{"materials.part.fill_pattern": "zigzag", "feedback.enabled": False})
    layer = Layer(0, 0.125, geo.region_from_rings([rect(0, 0, 40, 20)]))
    zig = [p for p in _members(plan_layer(layer, job)) if p.role == "fill" and p.width == 3.0]
    assert len(zig) == 1 and len(zig[0].points) > 4  # one linked zigzag
    job2 = job.replace(**{"materials.part.fill_pattern": "raster"})
    lp = plan_layer(layer, job2)
    ras = [p for p in _members(lp) if p.role == "fill" and p.width == 3.0]
    assert len(ras) > 3 and all(len(p.points) == 2 for p in ras)
    # the lines are deposited apart, but the robot runs from one to the next without a
    # stop (a continuous tour)
    assert any(p.off is not None for p in lp.paths if p.role == "fill")
    # lines parallel to x (angle 0) spaced by the fill width
    ys = sorted(p.points[0, 1] for p in ras)
    assert np.allclose(np.diff(ys), 3.0)


def test_hybrid_picks_the_long_direction_by_jin_time():
    # a long thin strip: zigzag along x (0 deg) has fewest turns
    job = Job().replace(**{"materials.part.fill_pattern": "hybrid",
                           "materials.part.hybrid_rings": 1, "feedback.enabled": False})
    from icefab.paths import fill_paths
    region = geo.region_from_rings([rect(0, 0, 120, 24)])
    _paths, angle = fill_paths(region, job.materials.part, job)
    assert angle == 0.0
    region = geo.region_from_rings([rect(0, 0, 24, 120)])
    _paths, angle = fill_paths(region, job.materials.part, job)
    assert angle == 90.0


def test_jin_segment_time_matches_kinematics():
    v, a = 62.5, 500.0
    crit = 3 * v * v / a
    # at the critical length the tool just reaches 2 v in the middle: t = 2 v / a
    assert jin_segment_time(np.array([crit]), v, a)[0] == pytest.approx(2 * v / a)
    # short: accelerate half way and decelerate: L/2 = v t + a t^2 / 2
    L = 0.5 * crit
    t_half = (-v + math.sqrt(v * v + a * L)) / a
    assert jin_segment_time(np.array([L]), v, a)[0] == pytest.approx(2 * t_half)
    # long: ramps (2 v / a, covering crit) plus cruise at 2 v
    L = 10 * crit
    assert jin_segment_time(np.array([L]), v, a)[0] == pytest.approx(2 * v / a + (L - crit) / (2 * v))


def test_measurement_paths_on_every_nth_layer_in_laser_frame():
    job = Job().replace(**{"feedback.interval_layers": 2})
    st_ = add_scaffold(make_stack(prism(4), job))
    tp = plan_paths(st_, job)
    for lp in tp.layers:
        meas = [p for p in lp.paths if p.role == "measure"]
        if (lp.index + 1) % 2 == 0:
            assert {p.material for p in meas} == {"part", "scaffold"}
            assert all(p.tool_name == "laser" and p.width == 0 and not p.depositing
                       for p in meas)
            # measurement comes after all deposition
            roles = [p.role for p in lp.paths if p.role != "travel"]
            assert roles.index("measure") > max(i for i, r in enumerate(roles) if r != "measure")
            # rings 1.5 mm inside (less up to twice their smoothing), then every 3 mm:
            # inside the region
            from icefab.paths import MEASURE_SMOOTHING_MM
            for p in meas:
                R = to_shapely(region_of(st_.layers[lp.index], p.material))
                inset = 1.5 - 2 * MEASURE_SMOOTHING_MM - FILT
                assert R.buffer(-inset).covers(LinearRing(p.points))
        else:
            assert not meas


def test_base_frame_sign_convention():
    job = Job()
    p = np.array([[0.0, 0.0], [10.0, 5.0]])
    # water nozzle at (-0.1, -0.3) in the EE frame: EE at (260.1, -99.7) puts it on (0, 0)
    assert np.allclose(to_base_frame(p, "part", job), [[260.1, -99.7], [270.1, -94.7]])
    assert np.allclose(to_base_frame(p, "scaffold", job)[0], [259.8, -108.2])
    assert np.allclose(to_base_frame(p, "laser", job)[0], [290.0, -119.0])
    # the EE carries the tools: EE position + tool offset (Table 3-1: the tool frame's
    # origin in the EE frame) is the same base point for every tool, ee_origin + p
    for tool in ("part", "scaffold", "laser"):
        off = np.asarray(job.materials[tool].nozzle_offset_mm if tool != "laser"
                         else job.cell.laser_offset_mm)
        assert np.allclose(to_base_frame(p, tool, job) + off, p + [260.0, -100.0])


def test_per_point_states_in_layer_order_and_in_the_file(tmp_path):
    job = Job().replace(**{"feedback.interval_layers": 1})
    st_ = add_scaffold(make_stack(table(2, 1), job))
    tp = plan_paths(st_, job)
    lp = tp.layers[0]
    pts, states = layer_point_states(lp)
    assert pts.shape == (sum(len(p.points) + p.closed for p in lp.paths), 2)
    assert states.dtype == np.int8 and set(states.tolist()) == {OFF, ON1, ON2}
    k = 0
    for p in lp.paths:
        n = len(p.points) + p.closed
        seg = states[k:k + n]
        assert np.array_equal(pts[k:k + len(p.points)], p.points)
        # every path ends on a point whose segment does not deposit (Ossino 6)
        assert seg[-1] == OFF
        expect = np.full(n - 1, {"part": ON1, "scaffold": ON2}[p.material] if p.depositing
                         else OFF, dtype=np.int8)
        if p.off is not None:   # a tour: OFF over its travel curves
            expect[p.off[:n - 1]] = OFF
        assert np.array_equal(seg[:-1], expect)
        if p.closed:  # closed: back to the first point
            assert np.array_equal(pts[k + n - 1], p.points[0])
        k += n
    # the file stores the state of every point, aligned with its points
    f = tmp_path / "tp.npz"
    save_toolpaths(tp, f)
    with np.load(f) as d:
        assert d["state"].shape == (d["point_counts"].shape[2],) and d["state"].dtype == np.int8
        data = {key: d[key] for key in d.files}
        first = d["path_start"][:len(lp.paths) + 1]
    for i, p in enumerate(lp.paths):
        st = data["state"][first[i]:first[i + 1]]
        assert np.array_equal(st, point_states(p))
        assert st[-1] == (deposition_state(p) if p.closed else OFF)
    load_toolpaths(f)
    # a state that disagrees with its path is a corrupt file; version 1 files still load
    bad = dict(data, state=np.where(data["state"] == ON1, ON2, data["state"]).astype(np.int8))
    np.savez(tmp_path / "bad.npz", **bad)
    with pytest.raises(StackFileError, match="states disagree"):
        load_toolpaths(tmp_path / "bad.npz")
    # versions 1 and 4 stored the points as floats (version 5: counts of Clipper's grid)
    pts = decode_counts(data["point_counts"], 1.0) / POINT_GRID_PER_MM
    pts[data["point_exact_index"]] = data["point_exact"]
    floats = {key: v for key, v in data.items()
              if key not in ("point_counts", "point_exact_index", "point_exact")}
    np.savez(tmp_path / "v4.npz", **dict(floats, points=pts, version=np.array(4)))
    v4, v5 = load_toolpaths(tmp_path / "v4.npz"), load_toolpaths(f)
    assert all(a.points.tobytes() == b.points.tobytes()
               for la, lb in zip(v4.layers, v5.layers) for a, b in zip(la.paths, lb.paths))
    # versions 1-3: without tours, per-point widths and states (version 3 refused before)
    for version, drop in ((3, ("point_off",)), (2, ("point_off", "variable", "point_width")),
                          (1, ("point_off", "variable", "point_width", "state"))):
        old = {key: v for key, v in floats.items() if key not in drop}
        if "state" in old:   # without point_off a tour's travel deposits as its members
            old["state"] = _point_states(dict(old, points=pts))
        np.savez(tmp_path / f"v{version}.npz", **dict(old, points=pts, version=np.array(version)))
        assert len(load_toolpaths(tmp_path / f"v{version}.npz")) == len(tp)


def test_deposition_states_and_order():
    job = Job().replace(**{"feedback.enabled": False})
    st_ = add_scaffold(make_stack(table(2, 1), job))
    lp = plan_paths(st_, job).layers[0]
    states = [deposition_state(p) for p in lp.paths]
    assert set(states) == {OFF, ON1, ON2}
    keys = [f"{p.material}:{p.role}" for p in lp.paths if p.role != "travel"]
    # default order: part boundaries, part fill, scaffold boundaries, scaffold fill
    firsts = [keys.index(k) for k in job.materials.order]
    assert firsts == sorted(firsts)
    job2 = job.replace(**{"materials.order": ["scaffold:boundary", "scaffold:fill",
                                              "part:boundary", "part:fill"]})
    lp2 = plan_paths(st_, job2).layers[0]
    assert lp2.paths[0].material == "scaffold"


def test_nearest_neighbour_order_and_start_points():
    sq = [rect(x, 0, x + 2, 2) for x in (20.0, 0.0, 10.0)]
    line = np.array([[40.0, 1.0], [30.0, 1.0]])
    items = [(s, True) for s in sq] + [(line, False)]
    out, end = order_nearest(items, np.array([-1.0, -1.0]))
    starts = [o[0][0] for o in out]
    assert np.allclose(starts[0], [0, 0]) and np.allclose(starts[1], [10, 0])
    assert np.allclose(starts[2], [20, 0])
    # open line entered from its nearer end (30, 1), reversed
    assert np.allclose(out[3][0], [[30.0, 1.0], [40.0, 1.0]]) and np.allclose(end, [40, 1])


def test_estimate_build_time_constant_speeds():
    job = Job()
    sq = rect(0, 0, 10, 10)
    paths = (Toolpath(sq, 0.1, "part", "boundary", True, 1.5, 0),
             Toolpath(np.array([[0.0, 0.0], [0.0, 125.0]]), 0.1, "part", "travel", False, 0.0, 0),
             Toolpath(sq, 0.1, "part", "fill", True, 3.0, 0),
             Toolpath(sq, 0.1, "part", "measure", True, 0.0, 0),
             Toolpath(sq, 0.1, "scaffold", "measure", True, 0.0, 0))
    tp = Toolpaths((LayerPaths(0, 0.1, paths), LayerPaths(1, 0.3, paths[:1])), job)
    per, total = estimate_build_time(tp)
    expected0 = 40 / 25 + 125 / 125 + 40 / 125 + 40 / 50 + 40 / 125
    assert per == pytest.approx([expected0, 40 / 25])
    assert total == pytest.approx(expected0 + 40 / 25)


def test_toolpaths_round_trip_and_corrupt_files(tmp_path):
    job = Job().replace(**{"feedback.interval_layers": 1})
    st_ = add_scaffold(make_stack(table(2, 1), job))
    tp = plan_paths(st_, job)
    f = tmp_path / "tp.npz"
    save_toolpaths(tp, f)
    back = load_toolpaths(f)
    assert back.job == tp.job
    assert len(back) == len(tp)
    for a, b in zip(tp.layers, back.layers):
        assert a.index == b.index and a.z == b.z and a.unfilled_mm2 == b.unfilled_mm2
        assert len(a.paths) == len(b.paths)
        for p, q in zip(a.paths, b.paths):
            assert np.array_equal(p.points, q.points)
            assert (p.z, p.material, p.role, p.closed, p.width, p.layer, p.frame, p.tool) == \
                (q.z, q.material, q.role, q.closed, q.width, q.layer, q.frame, q.tool)
    raw = f.read_bytes()
    (tmp_path / "trunc.npz").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(StackFileError, match="trunc.npz"):
        load_toolpaths(tmp_path / "trunc.npz")
    with pytest.raises(StackFileError, match="not found"):
        load_toolpaths(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(StackFileError, match="not an icefab toolpath"):
        load_toolpaths(tmp_path / "other.npz")
    (tmp_path / "text.npz").write_text("hello")
    with pytest.raises(StackFileError):
        load_toolpaths(tmp_path / "text.npz")


def test_hook_wall_turns_outer_scaffold_rings_to_ice():
    job = Job().replace(**{"scaffold.hook_wall": True, "feedback.enabled": False})
    st_ = add_scaffold(make_stack(prism(22), job))
    tp = plan_paths(st_, job)
    plain = plan_paths(st_, job.replace(**{"scaffold.hook_wall": False}))
    outer = to_shapely(st_.layers[0].part).buffer(3.3, quad_segs=32).exterior
    R = to_shapely(st_.layers[0].part).buffer(1e-6)
    for k, expect in ((0, 1), (12, 2), (21, 0)):
        lp, lp0 = tp.layers[k], plain.layers[k]
        ice = [p for p in _members(lp) if p.material == "part" and p.depositing]
        ice0 = [p for p in _members(lp0) if p.material == "part" and p.depositing]
        hook = [p for p in ice if not R.covers(LinearRing(p.points))]
        assert len(hook) == expect == len(ice) - len(ice0)
        # the ice rings lie in the scaffold, along its outer edge (not in the tube's hole)
        for p in hook:
            assert LinearRing(p.points).distance(outer) < 3.3
            assert to_shapely(st_.layers[k].scaffold).buffer(1e-6).covers(LinearRing(p.points))
        # the calibrated 0.45 mm strip between hook ring and scaffold boundary stays empty
        check_layer_paths(st_.layers[k], lp, job, min_cover=0.8, hook=True)


# ----------------------------------------------------------------------------- property


@settings(max_examples=15)
@given(polygon_with_holes())
def test_property_random_polygons_with_holes(rings):
    job = Job().replace(**{"feedback.enabled": False, "cell.cpus": 1})
    region = geo.region_from_rings(rings)
    st_ = add_scaffold(make_stack([region] * 2, job))
    for layer in st_.layers:
        lp = plan_layer(layer, job)
        # the star shapes have spikes narrower than the paths: coverage is checked elsewhere
        check_layer_paths(layer, lp, job, min_cover=None)


def _gaps_both_ways(region: Region, mat, job: Job):
    """The gaps material_paths measures, level by level (``geo.level_gaps``, what it does)
    and in one Boolean of every band (``geo.level_bands``, what it did): shapely."""
    from icefab.paths import boundary_rings, fill_levels, gap_levels, nominal_area
    filt = job.slicing.max_filter_deviation_mm
    levels = gap_levels(boundary_rings(region, mat, filt), fill_levels(region, mat, job),
                        mat, filt)
    nominal = nominal_area(region, mat, filt)
    return (to_shapely(geo.union(geo.level_gaps(nominal, levels))),
            to_shapely(geo.union(geo.difference_rings(nominal, geo.level_bands(levels)))))


@settings(max_examples=30, deadline=None)
@given(rings=polygon_with_holes(), noisy=st.integers(-1, 5), w=st.floats(0.6, 3.0),
       F=st.floats(1.0, 5.0), smooth=st.floats(0.0, 0.6), count=st.integers(0, 3))
def test_gaps_measured_level_by_level_are_those_of_every_band_at_once(rings, noisy, w, F,
                                                                       smooth, count):
    """Wherever the settings let material_paths measure the gaps level by level
    (``_levels_nest``), they are the gaps one Boolean of every band gives, to Clipper's
    grid: on star shapes with holes and on noisy scanned-like contours."""
    from icefab.paths import _levels_nest
    job = Job()
    mat = dataclasses.replace(job.materials.part, path_width_mm=w, fill_width_mm=F,
                              fill_smoothing_mm=smooth, boundary_count=count)
    assume(_levels_nest(mat, job.slicing.max_filter_deviation_mm))
    region = (geo.region_from_rings(rings) if noisy < 0
              else _noisy_lobed_disk(0.02 * noisy, seed=noisy))
    a, b = _gaps_both_ways(region, mat, job)
    grid = 4.0 / geo.SCALE
    assert a.symmetric_difference(b).area <= grid * (a.length + b.length) + 1e-6


def test_default_settings_measure_gaps_level_by_level():
    """Both materials' defaults take the fast way (the bunny's figures depend on it), a
    fill smoothed by more than the boundary's width can carry does not."""
    from icefab.paths import _levels_nest
    job = Job()
    filt = job.slicing.max_filter_deviation_mm
    assert _levels_nest(job.materials.part, filt) and _levels_nest(job.materials.scaffold, filt)
    assert not _levels_nest(dataclasses.replace(job.materials.part, fill_smoothing_mm=0.5), filt)
    assert _levels_nest(dataclasses.replace(job.materials.part, fill_smoothing_mm=0.5,
                                            boundary_count=0), filt)


def test_cli_paths_from_stack_file(tmp_path, capsys):
    from icefab.cli import main
    from icefab.slicing import save_stack

    job = Job().replace(**{"feedback.interval_layers": 2})
    stack_file = tmp_path / "stack.npz"
    save_stack(make_stack(table(4, 2), job), stack_file)
    out = tmp_path / "out"
    assert main(["paths", str(stack_file), "-o", str(out), "--layers", "0,5"]) == 0
    text = capsys.readouterr().out
    assert "constant-speed estimate" in text and "not a build time" in text
    assert "scaffold boundary" in text
    tp = load_toolpaths(out / "toolpaths.npz")
    assert len(tp) == 6
    assert (out / "paths.png").stat().st_size > 10_000
    # bad layer list: one-line error, exit 2, nothing new written
    assert main(["paths", str(stack_file), "-o", str(tmp_path / "o2"), "--layers", "99"]) == 2
    assert "layer numbers must be between 0 and 5" in capsys.readouterr().err


def _line_angles(lines: list[np.ndarray]) -> np.ndarray:
    """Directions (deg in [0, 180)) of the longest segment of each fill line."""
    out = []
    for ln in lines:
        d = np.diff(ln, axis=0)
        k = int(np.argmax(np.hypot(*d.T)))
        out.append(math.degrees(math.atan2(d[k, 1], d[k, 0])) % 180.0)
    return np.array(out)


def _rotated_rect(cx, cy, length, width, angle_deg):
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    pts = np.array([[-length / 2, -width / 2], [length / 2, -width / 2],
                    [length / 2, width / 2], [-length / 2, width / 2]])
    return pts @ np.array([[c, s], [-s, c]]) + [cx, cy]


def test_zigzag_takes_each_islands_optimal_angle():
    """Two long strips at 30 and 120 degrees in one region: each is zigzagged along its
    length (Jin's model: fewest turns), whatever fill_angle_deg says; 'fixed' uses that."""
    from icefab.paths import fill_levels
    job = Job().replace(**{"materials.part.fill_pattern": "zigzag", "feedback.enabled": False})
    region = geo.region_from_rings([_rotated_rect(0, 0, 120, 24, 30.0),
                                    _rotated_rect(150, 0, 120, 24, 120.0)])
    fill = fill_levels(region, job.materials.part, job)
    lines, angle = fill.lines, fill.angle
    dirs = _line_angles(lines)
    left = np.array([ln[:, 0].mean() < 75 for ln in lines])
    assert left.any() and (~left).any()
    assert np.allclose(dirs[left], 30.0, atol=1e-3)  # the point filter moves ends a little
    assert np.allclose(dirs[~left], 120.0, atol=1e-3)
    assert angle in (30.0, 120.0)  # the larger island's (equal areas: either)
    fixed = job.replace(**{"materials.part.fill_angle_mode": "fixed",
                           "materials.part.fill_angle_deg": 0.0})
    fill = fill_levels(region, fixed.materials.part, fixed)
    lines, angle = fill.lines, fill.angle
    d = _line_angles(lines)
    assert angle == 0.0 and np.allclose(np.minimum(d, 180.0 - d), 0.0, atol=1e-3)


@pytest.mark.parametrize("pattern", ["zigzag", "raster"])
def test_optimal_angle_is_never_slower_than_the_fixed_one_by_jin_time(pattern):
    from icefab.paths import fill_levels, zigzag_time
    job = Job().replace(**{"materials.part.fill_pattern": pattern})
    fixed = job.replace(**{"materials.part.fill_angle_mode": "fixed"})
    rng = np.random.default_rng(3)
    for _ in range(5):
        ring = _rotated_rect(0, 0, rng.uniform(20, 80), rng.uniform(10, 40), rng.uniform(0, 180))
        region = geo.region_from_rings([ring])
        t_opt = zigzag_time(fill_levels(region, job.materials.part, job)[1], job)
        t_fix = zigzag_time(fill_levels(region, fixed.materials.part, fixed)[1], fixed)
        assert t_opt <= t_fix + 1e-9


def test_a_job_file_giving_an_angle_fixes_it(tmp_path):
    from icefab.config import load_job, to_toml
    f = tmp_path / "j.toml"
    f.write_text("[materials.part]\nfill_pattern = \"zigzag\"\nfill_angle_deg = 30.0\n")
    job = load_job(f)
    assert job.materials.part.fill_angle_mode == "fixed"
    assert job.materials.scaffold.fill_angle_mode == "optimal"  # gave no angle
    f.write_text("[materials.part]\nfill_angle_deg = 30.0\nfill_angle_mode = \"optimal\"\n")
    assert load_job(f).materials.part.fill_angle_mode == "optimal"
    f.write_text(to_toml(job))
    assert load_job(f) == job


# ------------------------------------------------------------- smoothed concentric fill


def _noisy_lobed_disk(noise: float = 0.05, seed: int = 3) -> Region:
    """A 120 mm lobed disk whose contour wiggles by ``noise`` mm at every 0.4 mm (a
    scanned mesh's slice)."""
    th = np.linspace(0.0, 2.0 * np.pi, 900, endpoint=False)
    r = 60.0 + 10.0 * np.sin(2.0 * th) + np.random.default_rng(seed).normal(0.0, noise, 900)
    return geo.region_from_rings([np.c_[r * np.cos(th), r * np.sin(th)]])


def _fill_time(sets, job) -> float:
    from icefab.motion import plan_paths_motion
    fills = [Toolpath(points=p + [340.0, 0.0], closed=c, role="fill", frame="base",
                      width=float(np.mean(w)), widths=w if np.ndim(w) else None)
             for p, c, w in sets["fill"]]
    return sum(t.duration for t in plan_paths_motion(fills, job))


def test_smoothed_fill_covers_the_region_and_is_followed_faster():
    """On a noisy contour the smoothed concentric fill (default 0.25 mm) covers the region
    as the plain one does (the unfilled rest stays a few hundredths of a mm^2 of 11 000),
    needs fewer gap paths, and a jerk-limited robot follows it in under half the time;
    the first fill ring keeps to its place within twice the smoothing (plus the filter)."""
    from icefab import paths as paths_mod
    region = _noisy_lobed_disk()
    plain = Job().replace(**{"materials.part.fill_smoothing_mm": 0.0})
    job = Job()
    mat = job.materials.part
    assert mat.fill_smoothing_mm == 0.25
    got = {}
    for name, j in (("plain", plain), ("smooth", job)):
        sets, _, unfilled = paths_mod.material_paths(region, j.materials.part, j)
        got[name] = (sets, unfilled)
    area = geo.area(region)
    assert got["plain"][1] < 1e-5 * area and got["smooth"][1] < 1e-5 * area
    assert len(got["smooth"][0]["fill"]) < len(got["plain"][0]["fill"])
    assert _fill_time(got["smooth"][0], job) < 0.5 * _fill_time(got["plain"][0], job)
    # the first ring: 0.6 + 0.75 + 1.5 mm inside the contour, give or take 2 x 0.25 mm
    # (grown to cover the true edge), its own smoothing and the point filter
    filt = job.slicing.max_filter_deviation_mm
    tol = paths_mod.RING_SMOOTHING * mat.fill_width_mm
    first = max((p for p, c, w in got["smooth"][0]["fill"] if c),
                key=lambda p: abs(signed_area(p)))
    edge = shapely.LinearRing(list(region.rings)[0])
    d = edge.distance(shapely.points(first))
    assert d.min() >= 2.85 - 2 * 0.25 - tol - 2 * filt
    assert d.max() <= 2.85 + 0.25 + tol + 2 * filt


def test_the_first_fill_ring_is_smoothed_like_the_rings_inside_it():
    """The first fill ring is the offset of the smoothed contour: the offset turns what
    the contour's smoothing left of the noise into wiggles, so it is smoothed within
    RING_SMOOTHING x the fill width like every ring inside it. On a noisy contour a
    jerk-limited robot follows it in >= 15 % less time than the offset alone (25 %), its
    bead widened where it moved inward by twice the whole move (F <= w <= F + 2 tol)."""
    from icefab import paths as paths_mod
    region = _noisy_lobed_disk()
    job = Job()
    mat = job.materials.part
    F, filt = mat.fill_width_mm, job.slicing.max_filter_deviation_mm
    tol = paths_mod.RING_SMOOTHING * F
    start = paths_mod._fill_edge(mat) + F / 2.0
    got = {name: paths_mod.concentric_levels(region, start, F, filt, width_mm=F,
                                             smooth_mm=mat.fill_smoothing_mm,
                                             ring_smooth_mm=r,
                                             ring_sigma_mm=paths_mod.RING_SMOOTH_SIGMA_MM)
           for name, r in (("offset", 0.0), ("smoothed", tol))}

    def time(levels):
        (ring,) = levels.levels[0]
        return _fill_time({"fill": [(ring, True, F)]}, job)

    assert time(got["smoothed"]) < 0.85 * time(got["offset"])
    (w,) = got["smoothed"].widths[0]
    assert w is not None and w.min() >= F and w.max() <= F + 2.0 * tol + 1e-9
    assert w.max() > F + 2.0 * filt   # the whole move, not the excess over the filter
    assert got["offset"].widths[0] == [None]


def test_fill_rings_are_smoothed_over_a_window_as_long_as_a_scans_bumps():
    """A scanned part's slices bump by tenths of a millimetre every few centimetres (bunny
    layer 550: the rings' curvature swings by ~0.02 / mm every ~30 mm), and the jerk bound
    holds the robot to ~100 mm/s along them. The rings are smoothed in a window
    (RING_SMOOTH_SIGMA_MM) that reaches such bumps: on a lobed disk bumping by 0.5 mm every
    23.5 mm its first six fill levels are followed in >= 6 % less time than with the 5 mm
    window of the contour's noise (9.7 %), and every ring stays within the smoothing of the
    offset of the ring outside it (so the beads, widened where a ring moved inward, still
    cover: the tests below)."""
    from icefab import paths as paths_mod
    th = np.linspace(0.0, 2.0 * np.pi, 1500, endpoint=False)
    r = 60.0 + 10.0 * np.sin(2.0 * th) + 0.5 * np.sin(16.0 * th)
    region = geo.region_from_rings([np.c_[r * np.cos(th), r * np.sin(th)]])
    job = Job()
    mat = job.materials.part
    F, filt = mat.fill_width_mm, job.slicing.max_filter_deviation_mm
    tol = paths_mod.RING_SMOOTHING * F
    start = paths_mod._fill_edge(mat) + F / 2.0
    assert paths_mod.RING_SMOOTH_SIGMA_MM > paths_mod.FILL_SMOOTH_SIGMA_MM
    got = {}
    for sigma in (paths_mod.FILL_SMOOTH_SIGMA_MM, paths_mod.RING_SMOOTH_SIGMA_MM):
        got[sigma] = paths_mod.concentric_levels(
            region, start, F, filt, width_mm=F, smooth_mm=mat.fill_smoothing_mm,
            ring_smooth_mm=tol, ring_sigma_mm=sigma)

    def time(levels):
        return _fill_time({"fill": [(ring, True, F if w is None else w)
                                    for lv, ws in zip(levels.levels[:6], levels.widths[:6])
                                    for ring, w in zip(lv, ws)]}, job)

    wide = got[paths_mod.RING_SMOOTH_SIGMA_MM]
    assert time(wide) < 0.94 * time(got[paths_mod.FILL_SMOOTH_SIGMA_MM])
    for outer, inner in zip(wide.levels[:6], wide.levels[1:7]):
        offset = shapely.union_all([shapely.LinearRing(x) for x in
                                    geo.offset_rings(outer, -F, filt)])
        for ring in inner:
            assert offset.distance(shapely.points(ring)).max() <= tol + 2 * filt


def _bumpy_disk() -> Region:
    """A 120 mm disk with 12 bumps of 4 mm (6.4 mm radius at their tops): offset inward by
    more than that, every bump becomes a corner."""
    th = np.linspace(0.0, 2.0 * np.pi, 1200, endpoint=False)
    r = 60.0 + 4.0 * np.sin(12.0 * th)
    return geo.region_from_rings([np.c_[r * np.cos(th), r * np.sin(th)]])


def _exact_cover(sets) -> shapely.Geometry:
    """What boundary and fill beads cover, by shapely: a constant bead is the path
    buffered by half its width (round), a variable one the union of the convex hulls of
    consecutive disks (64-gons, outside the disks' polygon: at most 0.1 % of the radius
    short of the disk)."""
    ang = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    circle = np.c_[np.cos(ang), np.sin(ang)] / np.cos(np.pi / 64)
    geoms = []
    for p, c, w in sets["boundary"] + sets["fill"]:
        P = np.vstack([p, p[:1]]) if c else p
        if np.ndim(w):
            W = np.r_[w, w[:1]] if c else w
            disks = P[:, None, :] + (W[:, None, None] / 2.0) * circle[None]
            geoms.extend(shapely.convex_hull(shapely.multipoints(
                np.concatenate([disks[:-1], disks[1:]], axis=1))))
        else:
            geoms.append(shapely.LineString(P).buffer(w / 2.0))
    return shapely.union_all(geoms)


def test_inner_fill_rings_are_smoothed_and_their_beads_widened_where_they_moved_inward(
        monkeypatch):
    """The rings are smoothed within RING_SMOOTHING x the fill width (the corners inward
    offsets make of the bumps rounded off): a jerk-limited robot follows the fill in >= 5 %
    less time. Where a ring moved inward beyond the point filter its bead is widened by
    twice the excess (F <= w <= F + 2 (tol - filter); the first ring, next to the
    boundary, by twice its whole move: <= F + 2 tol), so the beads cover the region as
    well as the unsmoothed rings' within 0.01 % of its area (shapely: exact disk hulls) and
    icefab counts no more unfilled area; the same smoothed rings at the plain width would
    leave > 10 mm^2 more uncovered."""
    from icefab import paths as paths_mod
    region = _bumpy_disk()
    job = Job()
    mat = job.materials.part
    F = mat.fill_width_mm
    tol = paths_mod.RING_SMOOTHING * F
    got = {}
    for name, fraction in (("plain", 0.0), ("smooth", paths_mod.RING_SMOOTHING)):
        monkeypatch.setattr(paths_mod, "RING_SMOOTHING", fraction)
        sets, _, unfilled = paths_mod.material_paths(region, mat, job)
        got[name] = (sets, unfilled)
    sets = got["smooth"][0]
    rings = [(p, w) for p, c, w in sets["fill"] if c]
    widened = [w for _p, w in rings if np.ndim(w)]
    assert len(widened) >= len(rings) // 3
    filt = job.slicing.max_filter_deviation_mm
    first = max(range(len(rings)), key=lambda i: abs(signed_area(rings[i][0])))
    for i, (_p, w) in enumerate(rings):
        if np.ndim(w):
            top = F + 2.0 * (tol if i == first else tol - filt)
            assert w.min() >= F and w.max() <= top + 1e-9
    assert max(w.max() for w in widened) > F + (tol - filt)
    assert not any(np.ndim(w) and c for _p, c, w in got["plain"][0]["fill"])
    assert _fill_time(sets, job) < 0.95 * _fill_time(got["plain"][0], job)
    area = geo.area(region)
    assert got["smooth"][1] <= got["plain"][1] + 1e-6 * area
    target = shapely.Polygon(list(region.rings)[0]).buffer(-mat.initial_offset_mm)
    missed = {name: target.difference(_exact_cover(s)).area for name, (s, _u) in got.items()}
    narrow = {"boundary": sets["boundary"],
              "fill": [(p, c, F if np.ndim(w) and c else w) for p, c, w in sets["fill"]]}
    assert missed["smooth"] <= missed["plain"] + 1e-4 * area
    assert target.difference(_exact_cover(narrow)).area > missed["smooth"] + 10.0


def test_measurement_rings_are_smoothed_all_the_way_in():
    """Every measurement ring is smoothed within MEASURE_SMOOTHING_MM before the next is
    offset from it: on the bumpy disk the laser follows them in >= 5 % less time than
    rings smoothed only at the first (the former rule), and every ring stays inside the
    region."""
    from icefab.motion import plan_paths_motion
    from icefab.paths import (MEASURE_SMOOTHING_MM, concentric_rings, measure_rings)
    region = _bumpy_disk()
    job = Job()
    spacing = job.feedback.measure_spacing_mm

    def time(rings):
        return sum(t.duration for t in plan_paths_motion(
            [Toolpath(points=r + [340.0, 0.0], closed=True, role="measure", frame="base")
             for r in rings], job))

    new = measure_rings(region, spacing, FILT)
    old = [r for lv in concentric_rings(region, spacing / 2.0, spacing, FILT,
                                        smooth_mm=0.25) for r in lv]
    assert abs(len(new) - len(old)) <= 1
    assert time(new) < 0.95 * time(old)
    inset = spacing / 2.0 - 2.0 * MEASURE_SMOOTHING_MM - FILT
    R = shapely.Polygon(list(region.rings)[0]).buffer(-inset)
    assert all(R.covers(LinearRing(r)) for r in new)


def test_measurement_rings_after_the_first_are_smoothed_at_their_turns_too():
    """The fill's smoothing keeps turns over 60 degrees as corners; the measurement rings
    after the first are smoothed there too (MEASURE_CORNER_DEG): on the bumpy disk their
    PATHSPLIT pieces (each a stop) fall by at least 15 % (97 -> 77), every ring still
    near the ring smoothed with its corners kept (Hausdorff, shapely), and the first level
    within the point filter of it."""
    from icefab.motion import pathsplit
    from icefab.paths import MEASURE_SMOOTHING_MM, concentric_rings, measure_levels
    region = _bumpy_disk()
    job = Job()
    spacing = job.feedback.measure_spacing_mm
    kept = concentric_rings(region, spacing / 2.0, spacing, FILT, smooth_mm=0.5,
                            ring_smooth_mm=0.5, corner_deg=60.0)
    got = measure_levels(region, spacing, FILT)

    def pieces(levels):
        return sum(len(pathsplit(Toolpath(points=r, closed=True, role="measure").polyline(),
                                 job)) for lv in levels[1:] for r in lv)
    assert pieces(got) <= 0.85 * pieces(kept)
    # the first ring is smoothed within the point filter only, with or without corners
    assert len(got[0]) == len(kept[0])
    assert all(shapely.hausdorff_distance(LinearRing(a), LinearRing(b)) <= 2.0 * FILT
               for a, b in zip(got[0], kept[0]))
    assert abs(sum(map(len, got)) - sum(map(len, kept))) <= 1
    for a, b in zip(got[1:], kept[1:]):
        for ra, rb in zip(a, b):
            # each level is offset from the one before, so the moves may add up; they
            # stay within the smoothing of every level so far
            assert shapely.hausdorff_distance(LinearRing(ra), LinearRing(rb)) <= \
                MEASURE_SMOOTHING_MM * len(got)


def test_boundaries_keep_within_the_filter_of_the_exact_offset_and_are_followed_faster():
    """A noisy contour's boundary rings are the exact offsets smoothed within the point
    filter: every point stays within it of the exact offset (shapely's), and a
    jerk-limited robot follows the first ring faster than the chord-filtered one."""
    from icefab import paths as paths_mod
    from icefab.motion import plan_motion
    region = _noisy_lobed_disk()
    job = Job()
    mat, filt = job.materials.part, job.slicing.max_filter_deviation_mm
    bounds = paths_mod.boundary_rings(region, mat, filt)
    assert len(bounds) == mat.boundary_count
    poly = shapely.Polygon(list(region.rings)[0])
    depth = mat.initial_offset_mm
    for level in bounds:
        (ring,) = level
        exact = poly.buffer(-depth, join_style="mitre", mitre_limit=2.0).exterior
        assert shapely.distance(exact, shapely.points(ring)).max() <= filt + 1e-4
        depth += mat.path_width_mm
    chord = geo.offset_rings(list(region.rings), -mat.initial_offset_mm, filt)

    def time(ring):
        return plan_motion(Toolpath(points=ring + [340.0, 0.0], closed=True, width=1.5,
                                    frame="base"), job).duration
    assert time(bounds[0][0]) < 0.8 * time(chord[0])      # 12.1 s against 18.7 s


def test_smoothing_leaves_clean_fill_rings_almost_alone():
    """A clean ellipse's rings: the first moves by about the point filter; each ring is
    smoothed within the filter before the next is offset from it, so the rings drift
    inward by ~0.02 mm per ring (the filtered polygon's chords lie inside the curve the
    regression fits), within what the swept bands are grown by (filter + SWEEP_TOL: no
    sliver between them is counted or left). The square's rings stay exactly where they
    were (the analytic test above)."""
    from icefab.paths import concentric_rings
    th = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)
    region = geo.region_from_rings([np.c_[50.0 * np.cos(th), 30.0 * np.sin(th)]])
    plain = concentric_rings(region, 2.85, 3.0, 0.05, width_mm=3.0)
    smooth = concentric_rings(region, 2.85, 3.0, 0.05, width_mm=3.0, smooth_mm=0.25)
    assert len(plain) == len(smooth) == 9
    # the innermost ring is the opening of a thin strip (not compared)
    for k, (a, b) in enumerate(zip(plain[:-1], smooth[:-1])):
        (ra,), (rb,) = a, b
        assert shapely.hausdorff_distance(shapely.LinearRing(ra),
                                          shapely.LinearRing(rb)) < 0.06 + 0.02 * k
    # consecutive smoothed rings lie at most a fill width plus the bands' growth apart
    # (mean spacing: the area between them over their mean length)
    rings = [shapely.Polygon(lv[0]) for lv in smooth[:-1]]
    for a, b in zip(rings[:-1], rings[1:]):
        spacing = (a.area - b.area) / (0.5 * (a.length + b.length))
        assert 3.0 <= spacing <= 3.0 + 2 * (0.05 + SWEEP_TOL)


def test_a_wall_narrower_than_the_measurement_spacing_is_measured_along_its_middle():
    """A ring-shaped wall 2.5 mm wide holds no measurement ring at 3 mm spacing (the
    offset by 1.5 mm is empty): the feedback had no height of it and corrected it with
    the scaffold's. It is measured along its centre line, one closed path near radius
    21.25 mm; a disk gets its concentric rings and nothing more."""
    from icefab.paths import measure_paths, measure_rings
    from test_geometry import circle
    spacing = Job().feedback.measure_spacing_mm
    wall = geo.region_from_rings([circle(22.5), circle(20.0, hole=True)])
    assert measure_rings(wall, spacing, FILT) == []
    (pts, closed), = measure_paths(wall, spacing, FILT)
    assert closed
    assert np.allclose(np.hypot(*pts.T), 21.25, atol=0.05)
    disk = geo.region_from_rings([circle(20.0)])
    got = measure_paths(disk, spacing, FILT)
    assert len(got) == len(measure_rings(disk, spacing, FILT)) and all(c for _p, c in got)


@pytest.mark.parametrize("spacing", [61.0, 100.0])
def test_a_region_that_holds_no_measurement_ring_is_measured_along_its_centre_line(spacing):
    """At a spacing wider than the region it holds no ring, and the piece left (the whole
    region, under spacing^2) was dropped as too small for a path of its own: the 60 mm
    square got no measurement path (a tester's), and SMF corrected the layer from the
    laser along its deposition paths, unsaid. With no ring beside it, it is measured along
    its centre line: the four half-diagonals, none of them a point."""
    from icefab.paths import measure_paths

    square = geo.region_from_rings([np.array([[0.0, 0], [60, 0], [60, 60], [0, 60]])])
    got = measure_paths(square, spacing, FILT)
    lengths = sorted(float(np.hypot(*np.diff(p, axis=0).T).sum()) for p, _c in got)
    assert len(got) == 4 and lengths[0] > 40.0
    ends = np.array([p[[0, -1]] for p, _c in got]).reshape(-1, 2)
    assert np.allclose(np.sort(np.hypot(*(ends - 30.0).T))[:4], 0.0, atol=0.5)


#: hypothesis' wall 2.3 mm thick round a spike: the measurement centre line's smoothing
#: cut the spike's bend to 0.22 mm off the edge (MEASURE_AXIS_MOVE_MM)
_SPIKED_RINGS = [
    np.array([[8.0000, 0.0000], [7.6759, 2.2539], [6.7300, 4.3251], [5.2389, 6.0460],
              [3.3233, 7.2771], [1.1385, 7.9186], [-2.9886, 20.7863], [-3.8556, 8.4425],
              [-6.7123, 7.7464], [-6.7300, 4.3251], [-7.6759, 2.2539], [-8.0000, 0.0000],
              [-7.6759, -2.2539], [-6.7300, -4.3251], [-5.2389, -6.0460], [-3.3233, -7.2771],
              [-1.1385, -7.9186], [1.1385, -7.9186], [3.3233, -7.2771], [5.2389, -6.0460],
              [6.7300, -4.3251], [7.6759, -2.2539]]),
    np.array([[1.5545, 3.6718], [1.4359, 3.3854], [1.2472, 3.1395], [1.0012, 2.9508],
              [0.7148, 2.8322], [0.4075, 2.7917], [0.1001, 2.8322], [-0.1863, 2.9508],
              [-0.4322, 3.1395], [-0.6209, 3.3854], [-0.7396, 3.6718], [-0.7800, 3.9792],
              [-0.7396, 4.2865], [-0.6209, 4.5729], [-0.4322, 4.8189], [-0.1863, 5.0076],
              [0.1001, 5.1262], [0.4075, 5.1667], [0.7148, 5.1262], [1.0012, 5.0076],
              [1.2472, 4.8189], [1.4359, 4.5729], [1.5545, 4.2865], [1.5950, 3.9792]])]


@settings(max_examples=30, deadline=None)
@given(polygon_with_holes(), st.floats(2.0, 8.0), st.one_of(st.none(), st.floats(0.3, 1.5)))
@example(_SPIKED_RINGS, 5.5, 0.421875)
def test_every_piece_of_a_region_the_rings_leave_unmeasured_gets_a_measurement_path(
        rings, spacing, wall):
    """Whatever the measurement rings leave farther than half the spacing (plus their
    smoothing) is measured too: every such piece of at least spacing^2 that holds a disk
    of radius MEASURE_EDGE_MM holds a stretch of a measurement path, which runs inside the
    region. ``wall``: the region is the random
    shape's wall, that many spacings thick (thin walls are what the rings miss)."""
    from icefab.paths import MEASURE_EDGE_MM, MEASURE_SMOOTHING_MM, measure_paths, unmeasured
    region = geo.region_from_rings(rings)
    if wall is not None:
        region = geo.difference(region, geo.shrink(region, wall * spacing))
    if region.is_empty:
        return
    got = measure_paths(region, spacing, FILT)
    rings_only = [p for p, c in got if c and len(p) >= 3]
    # the rings may reach out by their smoothing less half the spacing (as in
    # test_measurement_rings_are_smoothed_all_the_way_in), the centre lines by the filter
    out = max(2.0 * MEASURE_SMOOTHING_MM + FILT - spacing / 2.0, 0.0) + FILT
    R = shapely.union_all([shapely.Polygon(pc[0], pc[1:]) for pc in region.polygons()]
                          ).buffer(out + 1e-3)
    lines = [LineString(np.vstack([p, p[:1]]) if c else p) for p, c in got]
    assert all(R.covers(ln) for ln in lines)
    # the pieces the concentric rings alone leave: neither inside their outermost level
    # nor within reach of it (test_unmeasured_is_what_lies_beyond_the_rings_reach)
    from icefab.paths import measure_levels
    levels = measure_levels(region, spacing, FILT)
    left = unmeasured(region, levels[0] if levels else [], spacing, FILT)
    for piece in left.polygons():
        if geo.area(piece) < spacing * spacing:
            continue
        poly = shapely.Polygon(piece[0], piece[1:])
        # too thin for the laser (a centre line keeps MEASURE_EDGE_MM off the edge), or
        # thick enough only in a spot, e.g. the mitred corner of a 1 mm wall (hypothesis
        # found a pentagon's): a centre line shorter than spacing / 2 is dropped
        eroded = poly.buffer(-MEASURE_EDGE_MM - 0.1)
        if eroded.is_empty or eroded.area < 0.1 * spacing:
            continue
        assert any(poly.intersection(ln).length > 0.0 for ln in lines), \
            f"an unmeasured piece of {poly.area:.1f} mm^2 got no path"
    assert len(rings_only) <= len(got)
    # the centre lines (after the rings) keep off the region's edge, where the surface
    # falls away (less what their smoothing and the point filter move them)
    n_rings = sum(len(lv) for lv in levels)
    edge = shapely.union_all([shapely.Polygon(pc[0], pc[1:])
                              for pc in region.polygons()]).boundary
    for pts, _closed in got[n_rings:]:
        assert shapely.distance(shapely.points(pts), edge).min() >= \
            MEASURE_EDGE_MM - FILT - 0.1


def _measure_time(layer: Layer, job: Job, join: bool, monkeypatch) -> tuple[float, int]:
    """MTTS time (s) of a layer's measurement paths and the travel moves to them, and how
    many measurement paths it has, with the rings joined into spirals or not."""
    from icefab import paths as paths_mod
    from icefab.motion import plan_paths_durations
    with monkeypatch.context() as m:
        if not join:
            m.setattr(paths_mod, "measure_lane_mm", lambda spacing, speed: 0.0)
        lp = paths_mod.plan_layer(layer, job, measured=True)
    t = plan_paths_durations(list(lp.paths), job, layer=lp.index)
    roles = [p.role for p in lp.paths]
    first = roles.index("measure") - 1          # the travel move to the first ring
    return float(t[first:].sum()), roles.count("measure")


@pytest.mark.parametrize("holes", [False, True])
def test_nested_measurement_rings_are_joined_into_spirals(monkeypatch, holes):
    """The laser measures a disk (and a disk with a hole) along one spiral per chain of
    nested rings instead of ring after ring from rest (issue 15's continuous tours for the
    measurement): at least three times fewer paths and >= 10 % less time for the
    measurement and its travel; the spiral stays inside the region, MEASURE_EDGE_MM from
    its edge, and passes within 1.6 spacings of every point of the rings it replaces."""
    from icefab.paths import MEASURE_EDGE_MM, join_measure_rings, measure_levels
    from test_geometry import circle
    job = Job().replace(**{"cell.ee_origin_mm": (340.0, 0.0)})
    spacing = job.feedback.measure_spacing_mm
    rings = [circle(40.0)] + ([circle(12.0, hole=True)] if holes else [])
    region = geo.region_from_rings(rings)
    layer = Layer(index=3, z=1.0, part=region, top_z=1.0)
    t_join, n_join = _measure_time(layer, job, True, monkeypatch)
    t_rings, n_rings = _measure_time(layer, job, False, monkeypatch)
    assert 3 * n_join <= n_rings
    assert t_join < 0.9 * t_rings
    levels = measure_levels(region, spacing, FILT)
    got = join_measure_rings(levels, region, spacing, 12.0)
    spirals = [shapely.LineString(p) for p, closed in got if not closed]
    assert spirals
    poly = shapely.Polygon(rings[0], rings[1:])
    paths = shapely.union_all([shapely.LineString(np.vstack([p, p[:1]]) if c else p)
                               for p, c in got])
    assert poly.buffer(-MEASURE_EDGE_MM + 1e-6).covers(paths)
    every = np.concatenate([r for lv in levels for r in lv])
    assert shapely.distance(shapely.points(every), paths).max() <= 1.6 * spacing


def _check_joined_measurement(region: Region, spacing: float, lane: float,
                              longest: float) -> int:
    """The joined measurement paths of a region lie inside it (the lane changes
    MEASURE_EDGE_MM inside, the rings where they were), every ring point lies within 1.6
    spacings of a path (what a lane change skips lies between the two rings it joins), no
    path is longer than ``longest`` unless it is a single ring (the laser's storage,
    MEASURE_MAX_SAMPLES), and there are never more paths than rings. Returns how many
    rings were joined into others."""
    from icefab.paths import MEASURE_SMOOTHING_MM, join_measure_rings, measure_levels
    levels = measure_levels(region, spacing, FILT)
    n_rings = sum(len(lv) for lv in levels)
    if not n_rings:
        return 0
    got = join_measure_rings(levels, region, spacing, lane, longest)
    assert 1 <= len(got) <= n_rings
    lines = [shapely.LineString(np.vstack([p, p[:1]]) if c else p) for p, c in got]
    out = max(2.0 * MEASURE_SMOOTHING_MM + FILT - spacing / 2.0, 0.0) + FILT
    R = shapely.union_all([shapely.Polygon(pc[0], pc[1:]) for pc in region.polygons()]
                          ).buffer(out + 1e-3)
    assert all(R.covers(ln) for ln in lines)
    every = np.concatenate([r for lv in levels for r in lv])
    assert shapely.distance(shapely.points(every), shapely.union_all(lines)).max() <= \
        1.6 * spacing + 1e-6
    for (pts, closed), ln in zip(got, lines):
        assert closed or ln.length <= longest + 1e-6
        assert np.isfinite(pts).all() and len(pts) >= 3
    return n_rings - len(got)


@settings(max_examples=30, deadline=None)
@given(polygon_with_holes(), st.floats(2.0, 6.0), st.floats(2.0, 8.0),
       st.floats(100.0, 5000.0))
def test_joined_measurement_paths_stay_inside_and_miss_no_ring(rings, spacing, lanes,
                                                                 longest):
    """:func:`_check_joined_measurement` on random star-shaped regions with holes (their
    spiky offsets seldom run side by side: few rings are joined), lane changes ``lanes``
    spacings long."""
    _check_joined_measurement(geo.region_from_rings(rings), spacing, lanes * spacing,
                              longest)


@settings(max_examples=30, deadline=None)
@given(st.floats(15.0, 60.0), st.floats(0.3, 1.0), st.floats(0.0, 0.5), st.floats(-1.0, 1.0),
       st.floats(2.0, 6.0), st.floats(2.0, 8.0), st.floats(100.0, 5000.0))
def test_an_ellipse_is_measured_along_spirals(a, ratio, hole, angle, spacing, lanes,
                                               longest):
    """:func:`_check_joined_measurement` on ellipses (turned, with an off-centre
    elliptic hole or none), whose rings do run side by side: without a hole most of them
    are joined (with one, the rings round the hole and round the edge meet and split
    where the band is narrow, and fewer are); lane changes ``lanes`` spacings long."""
    t = np.linspace(0.0, 2.0 * np.pi, 240, endpoint=False)
    c, s = math.cos(angle), math.sin(angle)
    turn = np.array([[c, -s], [s, c]])
    rings = [np.c_[a * np.cos(t), ratio * a * np.sin(t)] @ turn.T]
    if hole * ratio * a > 2.0:
        rings.append((np.c_[hole * a * np.cos(t) + 0.2 * a,
                            hole * ratio * a * np.sin(t)] @ turn.T)[::-1].copy())
    region = geo.region_from_rings(rings)
    from icefab.paths import measure_levels
    n_rings = sum(len(lv) for lv in measure_levels(region, spacing, FILT))
    joined = _check_joined_measurement(region, spacing, lanes * spacing, longest)
    if len(rings) == 1 and n_rings >= 6 and longest > 2000.0:
        # nested rings with room for a lane change (a third of the next ring's length,
        # two spacings at least) join all but the small innermost ones
        assert joined >= n_rings // 2


def test_unmeasured_is_what_lies_beyond_the_rings_reach():
    """A 40 x 20 mm block with a tab 2 mm wide and 40 mm long: at 3 mm spacing the tab
    holds no ring, and the block's outermost ring (1.5 mm in) measures up to half the
    spacing plus its smoothing and the filter beyond itself (x = 40.55 mm). What is left
    is the rest of the tab, 2 x 39.45 mm; it is measured along its middle."""
    from icefab.paths import MEASURE_SMOOTHING_MM, measure_levels, measure_paths, unmeasured
    spacing = 3.0
    region = geo.union(geo.region_from_rings([rect(0, 0, 40, 20)]),
                       geo.region_from_rings([rect(39, 9, 80, 11)]))
    levels = measure_levels(region, spacing, FILT)
    left = unmeasured(region, levels[0], spacing, FILT)
    reach = spacing / 2.0 + MEASURE_SMOOTHING_MM + FILT
    assert geo.area(left) == pytest.approx(2.0 * (80.0 - (40.0 - spacing / 2.0 + reach)),
                                           abs=0.5)
    lines = [p for p, closed in measure_paths(region, spacing, FILT) if not closed]
    assert len(lines) == 1
    assert np.allclose(lines[0][:, 1], 10.0, atol=0.05)
    assert lines[0][:, 0].min() < 42.0 and lines[0][:, 0].max() > 78.5   # ends: half a width in


@pytest.mark.parametrize("variable", [True, False])
@pytest.mark.parametrize("case", ["spiky-part-101", "spiky-part-456"])
def test_gap_paths_of_a_spiky_part_stay_inside_it(case, variable):
    """Parts found by fuzzing plan_layer (tests/data/regions: a star of random radii at
    random angles with a hole, and a smaller copy of it beside it): centre-line gap paths
    0.2 mm long in the notches crossed the part's edge by 1-10 micrometres, both ends
    0.09 mm inside it, where the edge's spikes came between their points; variable-width
    paths and runs of one width alike. Every layer invariant holds, measured and not."""
    part = fuzzed_part(case)
    job = Job().replace(**{"cell.cpus": 1, "materials.part.variable_width": variable,
                           "materials.scaffold.variable_width": variable})
    layer = add_scaffold(make_stack([part] * 2, job)).layers[0]
    for measured in (True, False):
        check_layer_paths(layer, plan_layer(layer, job, measured), job, min_cover=None)


@pytest.mark.parametrize("count", [0, 1])
def test_the_first_smoothed_fill_ring_keeps_its_bead_inside_without_boundaries(count):
    """With no boundary outside it (``boundary_count = 0``) the first fill band has no
    room to reach outward over its edge, which the smoothing of its edge and of its ring
    would make it do (fuzzing found a first ring's bead 0.5 mm past the part's edge): the
    first level is then left unsmoothed. A wavy disk, scaffold around it."""
    t = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
    r = 25.0 + 0.4 * np.sin(23.0 * t) + 0.2 * np.sin(57.0 * t)
    part = geo.region_from_rings([np.c_[r * np.cos(t), r * np.sin(t)]])
    job = Job().replace(**{"cell.cpus": 1, "materials.part.boundary_count": count,
                           "materials.scaffold.boundary_count": count})
    layer = add_scaffold(make_stack([part] * 2, job)).layers[0]
    check_layer_paths(layer, plan_layer(layer, job, False), job, min_cover=None)


def _random_part(rng: np.random.Generator) -> list[np.ndarray]:
    """A part's rings as the fuzz of plan_layer draws them: a star of random radii at random
    angles, a noisy blob, a thin ellipse or a jittered square, 3-120 mm, sometimes with a
    hole and a smaller copy beside it (tests/data/regions holds the ones that found
    defects)."""
    kind = int(rng.integers(0, 4))
    n = int(rng.integers(5, 400))
    t = (np.sort(rng.uniform(0.0, 2.0 * np.pi, n)) if kind == 1
         else np.linspace(0.0, 2.0 * np.pi, n, endpoint=False))
    scale = float(rng.choice([3.0, 10.0, 40.0, 120.0]))
    if kind == 0:
        r = scale * (1.0 + 0.3 * np.sin(3.0 * t + rng.uniform(0.0, 6.0))) + \
            rng.normal(0.0, 0.05 * scale * rng.uniform(0.0, 0.3), n)
    elif kind == 1:
        r = scale * rng.uniform(0.3, 1.0, n)
    elif kind == 2:
        a, b = scale, scale * rng.uniform(0.02, 0.3)
        r = a * b / np.sqrt((b * np.cos(t)) ** 2 + (a * np.sin(t)) ** 2)
    else:
        r = scale / np.maximum(np.abs(np.cos(t)), np.abs(np.sin(t))) + rng.normal(0.0, 0.02, n)
    r = np.maximum(r, 0.01 * scale)
    outer = np.c_[r * np.cos(t), r * np.sin(t)]
    rings = [outer]
    if rng.random() < 0.3:
        m = int(rng.integers(8, 100))
        tt = np.linspace(0.0, 2.0 * np.pi, m, endpoint=False)[::-1]
        rings.append(rng.uniform(0.05, 0.3) * r.min() * np.c_[np.cos(tt), np.sin(tt)])
    if rng.random() < 0.3:
        rings.append(outer * rng.uniform(0.1, 0.5) + np.array([3.0 * scale, 0.0]))
    return rings


#: Examples of the random parts and settings below; a long fuzz run sets it
#: (``ICEFAB_FUZZ_EXAMPLES=1000 python3 -m pytest tests/test_paths.py -k random_parts``).
FUZZ_EXAMPLES = int(os.environ.get("ICEFAB_FUZZ_EXAMPLES", "4"))


@settings(max_examples=FUZZ_EXAMPLES, deadline=None)
@given(st.integers(0, 2 ** 32 - 1), st.sampled_from(["concentric", "zigzag", "raster",
                                                      "hybrid"]),
       st.booleans(), st.sampled_from([0.0, 90.0, 240.0, 360.0]), st.integers(0, 3),
       st.sampled_from([0.0, 0.25]), st.booleans())
def test_property_random_parts_and_settings(seed, pattern, variable, turn, count, smooth,
                                            optimal):
    """plan_layer on random parts (:func:`_random_part`: spikes, notches, thin walls, holes,
    islands) with random fill settings of both materials, measured and not: every layer
    invariant of :func:`check_layer_paths` holds. (A long run of this found the defects of
    tests/data/regions and the boundary-free first ring. The ice hook wall is left out:
    with hybrid scaffold fill it has a known defect, a strict xfail test below.)"""
    changes: dict = {"cell.cpus": 1}
    for m in ("part", "scaffold"):
        changes |= {f"materials.{m}.fill_pattern": pattern,
                    f"materials.{m}.variable_width": variable,
                    f"materials.{m}.tour_max_turn_deg": turn,
                    f"materials.{m}.boundary_count": count,
                    f"materials.{m}.fill_smoothing_mm": smooth,
                    f"materials.{m}.fill_angle_mode": "optimal" if optimal else "fixed"}
    job = Job().replace(**changes)
    part = geo.region_from_rings(_random_part(np.random.default_rng(seed)))
    assume(not part.is_empty)
    layer = add_scaffold(make_stack([part] * 2, job)).layers[0]
    for measured in (True, False):
        check_layer_paths(layer, plan_layer(layer, job, measured), job, min_cover=None)


def test_the_hook_wall_of_a_spiky_part_goes_round_the_pockets_of_its_outline():
    """A spiky part found by fuzzing (tests/data/regions/hook-part-74.npz) with the ice
    hook wall on: the room made for the wall (``regions._hook_wall_room`` grows part and
    scaffold) joined the scaffolds of the part and of its copy and closed two pockets
    between them (6.2 and 3.7 mm^2, neither scaffold nor part), and a hook ring, an offset
    of the outline alone, ran 2 mm across one. The wall now goes round such pockets."""
    part = fuzzed_part("hook-part-74")
    job = Job().replace(**{"cell.cpus": 1, "scaffold.hook_wall": True})
    layer = add_scaffold(make_stack([part] * 2, job)).layers[0]
    assert sum(geo.ring_areas(list(layer.scaffold.rings)) < 0) == 4   # part, copy, 2 pockets
    check_layer_paths(layer, plan_layer(layer, job, False), job, min_cover=None, hook=True)


def test_hybrid_scaffold_fill_with_the_hook_wall_keeps_off_the_edge():
    """A spiky part found by fuzzing (tests/data/regions/hook-part-550.npz), the ice hook
    wall on and hybrid scaffold fill. The scaffold in the part's hole is an annulus about
    7 mm wide. Its first hybrid level (3.45 mm in) is a sliver: an outer ring of
    470.2 mm^2 and a hole of 467.9 mm^2, 0.03 mm apart, which cross each other after the
    0.05 mm point filter. The next offset of the crossing pair is a ring of 267.7 mm^2 inside
    the hole, 0.42 mm from the scaffold's edge, and as the sliver's "child" it made
    ``_with_room`` keep the sliver too. Without the hook wall the annulus is narrower (its
    hole 467.9 mm^2), no level of it is left, and the invariants held. The filter now drops
    an outer ring and its hole that together are narrower than it can keep apart
    (``geometry._without_slivers``)."""
    part = fuzzed_part("hook-part-550")
    job = Job().replace(**{"cell.cpus": 1, "scaffold.hook_wall": True,
                           "materials.scaffold.fill_pattern": "hybrid"})
    layer = add_scaffold(make_stack([part] * 2, job)).layers[0]
    check_layer_paths(layer, plan_layer(layer, job, False), job, min_cover=None, hook=True)


def test_zigzag_links_do_not_cut_across_a_notch_of_the_fill_area():
    """A part found by the property test above (tests/data/regions/zigzag-part-1011.npz):
    without boundaries, a zigzag link 17 mm long between two raster lines cut across a
    notch of the fill area between the nine points it was checked at, 1.32 mm from the
    part's edge where the fill's 3 mm beads need 1.5 mm."""
    part = fuzzed_part("zigzag-part-1011")
    changes: dict = {"cell.cpus": 1}
    for m in ("part", "scaffold"):
        changes |= {f"materials.{m}.fill_pattern": "zigzag",
                    f"materials.{m}.boundary_count": 0,
                    f"materials.{m}.fill_angle_mode": "optimal"}
    job = Job().replace(**changes)
    layer = add_scaffold(make_stack([part] * 2, job)).layers[0]
    check_layer_paths(layer, plan_layer(layer, job, False), job, min_cover=None)


def test_a_part_left_without_paths_is_said(tmp_path, capsys):
    # an initial offset of 50 mm: no part path at all, "unfilled area: part 0 mm²" and no
    # warning (the strip the offset leaves is not unfilled area, on purpose: now said)
    from icefab.cli import main
    from icefab.slicing import save_stack

    job = Job().replace(**{"materials.part.initial_offset_mm": 50.0})
    stack_file = tmp_path / "stack.npz"
    save_stack(make_stack(table(4, 2), job), stack_file)
    (tmp_path / "job.toml").write_text("[materials.part]\ninitial_offset_mm = 50.0\n")
    assert main(["paths", str(stack_file), "-c", str(tmp_path / "job.toml"), "-o",
                 str(tmp_path / "out")]) == 0
    text = capsys.readouterr().out
    assert "no part path in any layer:" in text
    assert "materials.part.initial_offset_mm = 50 leaves a 49.2 mm strip" in text
    said = (tmp_path / "out" / "paths-warnings.txt").read_text()
    assert "no part path in any layer" in said
    save_stack(make_stack(table(4, 2), Job()), tmp_path / "default.npz")
    assert main(["paths", str(tmp_path / "default.npz"), "-o", str(tmp_path / "ok")]) == 0
    text = capsys.readouterr().out
    assert "no part path" not in text and "strip inside" not in text


@pytest.mark.parametrize("wall", [1.49, 1.5, 1.51])
def test_a_strip_exactly_one_path_width_wide_gets_one_centre_path(wall):
    """The gap fill's rings half a path width inside a gap (room for two beads) left, on
    a tube wall exactly one path width wide, the slivers of the offset: 134 rings of 1e-5
    mm^2, the 51 oriented as holes kept as closed paths, 94 paths where one was due (a
    hunt's). Boundaries off, so the whole wall is the gap fill's."""
    from shapely.geometry import Point

    ring = Point(0, 0).buffer(15, 128).difference(Point(0, 0).buffer(15 - wall, 128))
    outer = np.asarray(ring.exterior.coords)[:-1]
    inner = np.asarray(ring.interiors[0].coords)[:-1]
    rings = [outer if signed_area(outer) > 0 else outer[::-1],
             inner if signed_area(inner) < 0 else inner[::-1]]
    job = Job().replace(**{"feedback.enabled": False, "scaffold.enabled": False,
                           "materials.part.boundary_count": 0})
    lp = plan_layer(Layer(0, 0.125, geo.region_from_rings(rings)), job)
    deposits = [p for p in _members(lp) if p.role in ("fill", "boundary")]
    assert len(deposits) == 1 and deposits[0].closed
    assert deposits[0].length == pytest.approx(2 * math.pi * (15 - wall / 2), rel=0.02)
