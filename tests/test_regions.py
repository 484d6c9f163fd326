"""Scaffold regions (thesis 3.3): invariants checked with shapely, thesis-style parts."""
from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import given, settings, strategies as st

from icefab import geometry as geo
from icefab.config import Job
from icefab.motion import plan_motion
from icefab.paths import boundary_rings
from icefab.regions import _leans, add_scaffold, leaning_walls, merged_regions, smoothed_wall
from icefab.core import Layer, Region, Stack
from test_geometry import circle, check_region_structure, rect, to_shapely

T = 0.25
#: How far inside the buffer the scaffold's outer edge may lie, mm: twice the point
#: filter (on the input and the output of the grow) plus Clipper's grid.
SURROUND_TOL = 2 * geo.FILTER_MM + 1.0 / geo.SCALE


def make_stack(regions: list[Region], job: Job | None = None) -> Stack:
    job = job or Job()
    layers = tuple(Layer(k, (k + 0.5) * T, r, top_z=(k + 1) * T) for k, r in enumerate(regions))
    return Stack(layers, job, T)


def fuzzed_part(name: str) -> Region:
    """A part region found by fuzzing (``tests/data/regions/NAME.npz``: its rings in order,
    ``ring0``, ``ring1``, ...; the folder's README says what each found)."""
    from pathlib import Path
    data = np.load(Path(__file__).parent / "data" / "regions" / f"{name}.npz")
    return geo.region_from_rings([data[f"ring{k}"] for k in range(len(data.files))])


def table(leg_layers=20, slab_layers=6):
    """A 40 x 40 mm slab on one 10 x 10 mm leg (off centre)."""
    leg = geo.region_from_rings([rect(-15, -15, -5, -5)])
    slab = geo.region_from_rings([rect(-20, -20, 20, 20)])
    return [leg] * leg_layers + [slab] * slab_layers


def prism(n=12):
    """A tube: no overhang anywhere."""
    r = geo.region_from_rings([circle(15, 180), circle(8, 120, hole=True)])
    return [r] * n


def cone_down(n=24):
    """An inverted cone: radius grows by 0.1 mm per 0.25 mm layer (overhang 21.8 deg from
    vertical)."""
    return [geo.region_from_rings([circle(5 + 0.1 * k, 180)]) for k in range(n)]


def check_invariants(stack: Stack, surround: float | None):
    """The must-show invariants, measured with shapely. In surround mode with a buffer
    also: no layer leans out over the one below by more than its thickness times
    tan(``overhang_angle_deg``), and a smoothed outer wall (``scaffold.smoothing_mm``)
    lies within twice the smoothing (and the filters) of the exact buffer."""
    layers = stack.layers
    s = stack.job.scaffold
    filt = stack.job.slicing.max_filter_deviation_mm
    smoothed = bool(surround) and s.smoothing_mm > 0
    tan = math.tan(math.radians(min(s.overhang_angle_deg, 89.0)))
    thickness = stack.thicknesses
    merged = merged_regions([layer.part for layer in layers]) if smoothed else []
    above = shapely.Polygon()
    both_above = far_above = None
    for k in range(len(layers) - 1, -1, -1):
        part = to_shapely(layers[k].part)
        scaf = to_shapely(layers[k].scaffold)
        check_region_structure(layers[k].scaffold)
        # Clipper works on a 1e-4 mm grid: slicer coordinates are rounded by up to half that
        tol_area = 1e-3 + 1.0 / geo.SCALE * (part.length + scaf.length)
        # scaffold and part never overlap
        assert part.intersection(scaf).area < tol_area, f"layer {k}"
        both = part.union(scaf)
        # every part of the layers above, projected down, is carried
        assert above.difference(both).area < tol_area, f"layer {k}"
        if surround is not None and not part.is_empty:
            # the part offset by the buffer (round, the strictest) lies inside part u
            # scaffold, less SURROUND_TOL: expand() filters the merged region's rings
            # before growing them and the grown rings after, and each chord filter moves
            # an edge inward by at most the filter (chords cut across convex bends)
            grown = part.buffer(surround - SURROUND_TOL, quad_segs=16)
            assert grown.difference(both).area < tol_area, f"layer {k}"
        if smoothed and not both.is_empty:
            # the smoothed wall moves out from the exact one (the merged region mitred by
            # the buffer, as expand() makes it) by up to twice the smoothing and its
            # growth's two filters, mitred at the corners it keeps. A wall also holds the
            # walls above it (shrunk by the lean), and mitred walls are not nested: a
            # sharp corner above may reach farther out than the rounder merged region
            # below mitres to.
            exact = to_shapely(geo.expand(merged[k], surround, filt))
            far = exact.buffer(geo.MITER_LIMIT * (2 * s.smoothing_mm + 2 * filt) + 1e-3,
                               quad_segs=16)
            far_above = far if far_above is None else far_above.union(far)
            assert both.difference(far_above).area < tol_area, f"layer {k}"
        if surround and not both.is_empty and both_above is not None:
            # the layer above shrunk by the lean lies on this one: no part of the wall
            # above wider than twice the lean overhangs by more than the lean (a thinner
            # sliver of it holds no bead: the paths keep initial_offset - path_width / 2
            # = 0.45 mm inside the region)
            lean = thickness[k + 1] * tan
            out = both_above.buffer(-lean, quad_segs=16).difference(both)
            assert out.area < tol_area, f"layer {k + 1} leans out over layer {k}"
        above = above.union(part)
        both_above = both


def check_overhang_invariants(stack: Stack, angle_deg: float):
    """Overhang mode: each layer (part and scaffold) overhangs the one below by at most
    t * tan(angle); scaffold and part never overlap."""
    reach = T * math.tan(math.radians(angle_deg)) + geo.FILTER_MM + 1e-3
    below = None
    for layer in stack.layers:
        part = to_shapely(layer.part)
        scaf = to_shapely(layer.scaffold)
        tol_area = 1e-3 + 1.0 / geo.SCALE * (part.length + scaf.length)  # Clipper's grid
        assert part.intersection(scaf).area < tol_area
        both = part.union(scaf)
        if below is not None:
            assert both.difference(below.buffer(reach, quad_segs=16)).area < tol_area, \
                layer.index
        below = both


def test_merged_regions_is_union_of_everything_above():
    parts = table(4, 2)
    m = merged_regions(parts)
    assert [round(x.area, 6) for x in m] == [1600.0] * 6
    assert merged_regions([Region(), parts[0]])[0].area == pytest.approx(100)


def test_table_gets_scaffold_under_the_whole_slab():
    st_ = add_scaffold(make_stack(table()))
    check_invariants(st_, 3.3)
    slab = to_shapely(st_.layers[-1].part)
    for layer in st_.layers[:20]:
        both = to_shapely(layer.part).union(to_shapely(layer.scaffold))
        assert slab.difference(both).area < 1e-6
        # the merged slab buffered by 3.3 mm (mitred: a 46.6 mm square) minus the leg
        assert layer.scaffold.area == pytest.approx(46.6 ** 2 - 100, abs=1e-6)


def rippled_disk(r=40.0, n=1000, amp=0.1, wavelength=5.0, noise=0.02, seed=0,
                 centre=(0.0, 0.0)):
    """A disk whose edge wiggles like a scanned part's slice: a 0.1 mm ripple every 5 mm
    and 0.02 mm of noise at every point (0.25 mm apart)."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rad = r + amp * np.sin(max(round(2.0 * np.pi * r / wavelength), 1) * t) \
        + noise * rng.standard_normal(n)
    return geo.region_from_rings([np.c_[centre[0] + rad * np.cos(t),
                                        centre[1] + rad * np.sin(t)]])


def test_smoothed_outer_wall_lets_the_robot_follow_the_outer_scaffold_path():
    """What scaffold.smoothing_mm is for: the buffer's offset keeps a scan's wiggles, the
    outermost scaffold boundary crawls along them under the jerk bound."""
    part = rippled_disk()
    times, areas = [], []
    for smoothing in (0.0, Job().scaffold.smoothing_mm):
        job = Job().replace(**{"scaffold.smoothing_mm": smoothing, "cell.cpus": 1})
        stack = add_scaffold(make_stack([part] * 3, job))
        check_invariants(stack, 3.3)
        scaffold = stack.layers[0].scaffold
        rings = boundary_rings(scaffold, job.materials.scaffold,
                               job.slicing.max_filter_deviation_mm)[0]
        outer = max(rings, key=lambda r: geo.signed_area(r))
        closed = np.vstack([outer, outer[:1]]) + [340.0, 0.0]   # in the Cobra's reach
        times.append(plan_motion(closed, job).duration)
        areas.append(scaffold.area)
    assert times[1] < 0.6 * times[0]          # measured: 6.9 -> 3.3 s (0.1 mm)
    # the wall only moved outward, by at most twice the smoothing and the filters
    assert areas[0] < areas[1] < areas[0] + (2 * 0.1 + 0.1) * 2.0 * np.pi * 43.3


@settings(max_examples=30, deadline=None)
@given(st.floats(0.05, 0.3), st.floats(2.0, 12.0), st.floats(0.0, 0.04),
       st.integers(0, 10_000), st.sampled_from([0.25, 0.5, 1.0]))
def test_smoothed_wall_holds_the_wall_and_stays_near_it(amp, wavelength, noise, seed, tol):
    outer = rippled_disk(20.0, 500, amp, wavelength, noise, seed)
    filt = geo.FILTER_MM
    wall = smoothed_wall(outer, tol, filt)
    check_region_structure(wall)
    a, w = to_shapely(outer), to_shapely(wall)
    assert a.difference(w).area < 1e-3                               # holds it
    far = a.buffer(2 * tol + 4 * filt + 1e-3, quad_segs=16)
    assert w.difference(far).area < 1e-3                             # stays near it
    assert smoothed_wall(outer, 0.0, filt) is outer


def test_a_sharp_tip_above_a_blunt_one_does_not_overhang():
    """Mitred offsets are not nested: a 70-degree tip above mitres 5.75 mm out, the same
    tip blunted by a square below only 4.3 mm; without the lean the wall above overhangs
    the one below by 1.4 mm."""
    tip = geo.region_from_rings([np.array([[0.0, -7.0], [10.0, 0.0], [0.0, 7.0]])])
    blunt = geo.union(tip, [rect(8.0, -1.0, 11.0, 1.0)])
    for angle, overhangs in ((45.0, False), (90.0, True)):
        job = Job().replace(**{"scaffold.overhang_angle_deg": angle, "cell.cpus": 1,
                               "scaffold.smoothing_mm": 0.0})
        stack = add_scaffold(make_stack([blunt, tip, tip], job))
        if not overhangs:
            check_invariants(stack, 3.3)
        both = [to_shapely(L.part).union(to_shapely(L.scaffold)) for L in stack.layers]
        out = both[1].buffer(-T, quad_segs=16).difference(both[0]).area
        assert (out > 0.5) == overhangs, (angle, out)


def test_walls_lean_out_by_at_most_the_limiting_angle():
    """A wide top on a narrow stem: each wall must hold the one above shrunk by the lean,
    so the smoothed walls step in by at most the lean going up (at 90 degrees add_scaffold
    skips the pass: test_a_sharp_tip_above_a_blunt_one_does_not_overhang)."""
    big = geo.region_from_rings([circle(20.0, 180)])
    small = geo.region_from_rings([circle(10.0, 180)])
    walls = [small, small, big]
    out = leaning_walls(walls, [0.25, 0.25, 0.25])
    assert out[2] is big
    assert out[1].area == pytest.approx(math.pi * 19.75 ** 2, rel=2e-3)
    assert out[0].area == pytest.approx(math.pi * 19.5 ** 2, rel=2e-3)
    assert _leans(np.array([0.25, 0.1, 0.25]), 45.0) == pytest.approx([0.1, 0.25, 0.25])
    assert _leans(np.array([0.25, 0.25]), 90.0) == pytest.approx([0.25 * math.tan(
        math.radians(89.0))] * 2)
    assert len(_leans(np.zeros(0), 45.0)) == 0


def test_classic_support_buffer_zero():
    job = Job().replace(**{"scaffold.buffer_mm": 0.0})
    st_ = add_scaffold(make_stack(table(), job))
    check_invariants(st_, None)
    for layer in st_.layers[:20]:
        assert layer.scaffold.area == pytest.approx(1600 - 100, abs=1e-6)
    assert all(layer.scaffold.is_empty for layer in st_.layers[20:])


def test_no_overhang_gets_only_the_surround():
    st_ = add_scaffold(make_stack(prism()))
    check_invariants(st_, 3.3)
    ring = to_shapely(st_.layers[0].part)
    expected = ring.buffer(3.3, quad_segs=64).difference(ring)
    for layer in st_.layers:
        s = to_shapely(layer.scaffold)
        # only the surround (outside and inside the hole), nothing more than the mitred
        # buffer (mitred polygon buffer = round within the filter on a fine circle)
        assert s.symmetric_difference(expected).area < 0.06 * expected.length
    job = Job().replace(**{"scaffold.buffer_mm": 0.0})
    assert all(layer.scaffold.is_empty for layer in add_scaffold(make_stack(prism(), job)))


def test_overhang_mode_supports_only_steep_overhangs():
    # cone grows 0.1 mm per layer: tan(angle) * 0.25 = 0.1 at 21.8 deg
    steep = Job().replace(**{"scaffold.mode": "overhang", "scaffold.overhang_angle_deg": 10.0,
                             "scaffold.min_width_mm": 0.0})
    st_ = add_scaffold(make_stack(cone_down(), steep))
    check_overhang_invariants(st_, 10.0)
    assert st_.layers[0].scaffold.area > 0
    # the bottom layer carries everything above: the top disc
    top = to_shapely(st_.layers[-1].part)
    base = to_shapely(st_.layers[0].part).union(to_shapely(st_.layers[0].scaffold))
    assert top.difference(base).area < 1e-3
    gentle = steep.replace(**{"scaffold.overhang_angle_deg": 30.0})
    st2 = add_scaffold(make_stack(cone_down(), gentle))
    assert all(layer.scaffold.is_empty for layer in st2.layers)
    # the table needs support under the slab whatever the angle
    st3 = add_scaffold(make_stack(table(), gentle))
    check_overhang_invariants(st3, 30.0)
    slab = to_shapely(st3.layers[-1].part)
    for layer in st3.layers[:20]:
        both = to_shapely(layer.part).union(to_shapely(layer.scaffold))
        assert slab.difference(both).area < 1.0  # all but the self-supporting rim


def test_subset_limits_scaffold_height():
    job = Job().replace(**{"scaffold.subset": (0.5, 1.0)})
    st_ = add_scaffold(make_stack(prism(12), job))
    assert all(layer.scaffold.is_empty for layer in st_.layers[:6])
    assert all(not layer.scaffold.is_empty for layer in st_.layers[6:])


def test_hook_wall_only_where_the_layer_keeps_scaffold():
    # the hook wall anchors scaffold (thesis 3.7): no scaffold, no wall room
    job = Job().replace(**{"scaffold.hook_wall": True, "scaffold.buffer_mm": 0.0})
    st_ = add_scaffold(make_stack(prism(24), job))  # classic support, no overhang
    assert all(layer.scaffold.is_empty for layer in st_.layers)
    job = Job().replace(**{"scaffold.hook_wall": True, "scaffold.subset": (0.5, 1.0)})
    st_ = add_scaffold(make_stack(prism(24), job))
    assert all(layer.scaffold.is_empty for layer in st_.layers[:12])
    assert all(not layer.scaffold.is_empty for layer in st_.layers[12:])
    # where the layer keeps scaffold the wall's band is added (layers 0-19)
    st_ = add_scaffold(make_stack(prism(24), job.replace(**{"scaffold.subset": (0.0, 1.0)})))
    plain = add_scaffold(make_stack(prism(24), Job()))
    assert st_.layers[5].scaffold.area > plain.layers[5].scaffold.area + 50
    assert st_.layers[22].scaffold.area == pytest.approx(plain.layers[22].scaffold.area)


def test_disabled_gives_empty_scaffold():
    job = Job().replace(**{"scaffold.enabled": False})
    st_ = add_scaffold(make_stack(table(), job))
    assert all(layer.scaffold.is_empty for layer in st_.layers)


def test_thin_scaffold_pieces_removed_unless_they_carry_part():
    # two blocks 1 mm apart: the scaffold in the 1 mm slot is thinner than 1.5 mm
    blocks = geo.region_from_rings([rect(0, 0, 10, 10), rect(11, 0, 21, 10)])
    job = Job().replace(**{"scaffold.buffer_mm": 3.3})
    st_ = add_scaffold(make_stack([blocks] * 4, job))
    slot = shapely.box(10, 0, 11, 10)
    for layer in st_.layers:
        # only a margin of twice the point filter next to the kept scaffold stays
        margin = 2 * geo.FILTER_MM + 1e-3
        assert to_shapely(layer.scaffold).intersection(slot).area < 2 * margin * 1.0 + 1e-6
    check_invariants(st_, None)
    # a bridge above the slot: the thin slot scaffold under it is kept
    bridge = geo.region_from_rings([rect(0, 0, 21, 10)])
    st2 = add_scaffold(make_stack([blocks] * 4 + [bridge], job))
    check_invariants(st2, None)
    for layer in st2.layers[:4]:
        assert to_shapely(layer.scaffold).intersection(slot).area == pytest.approx(10, abs=1e-3)


def test_thin_part_features_are_reported():
    fin = geo.union(geo.region_from_rings([rect(0, 0, 20, 20)]),
                    geo.region_from_rings([rect(20, 9.5, 30, 10.5)]))
    st_ = add_scaffold(make_stack([fin] * 2))
    msgs = [w for w in st_.warnings if "narrower than the path width" in w]
    assert len(msgs) == 2
    assert "layer 0" in msgs[0] and "x = 25" in msgs[0]
    assert not add_scaffold(make_stack(prism(2))).warnings


def test_parallel_equals_serial():
    parts = cone_down(50)
    a = add_scaffold(make_stack(parts, Job().replace(**{"cell.cpus": 1})))
    b = add_scaffold(make_stack(parts, Job().replace(**{"cell.cpus": 2})))
    for la, lb in zip(a.layers, b.layers):
        assert la.scaffold.area == pytest.approx(lb.scaffold.area, abs=1e-9)


@st.composite
def random_stack(draw):
    n = draw(st.integers(2, 6))
    regions = []
    for _ in range(n):
        k = draw(st.integers(1, 3))
        rings = []
        for _ in range(k):
            cx, cy = draw(st.floats(-20, 20)), draw(st.floats(-20, 20))
            w, h = draw(st.floats(2, 15)), draw(st.floats(2, 15))
            rings.append(rect(cx, cy, cx + w, cy + h))
        region = geo.union(*rings)
        if draw(st.booleans()):
            cx, cy = draw(st.floats(-20, 20)), draw(st.floats(-20, 20))
            region = geo.difference(region, [circle(draw(st.floats(1, 4)), 32, (cx, cy))])
        regions.append(region)
    return regions


@settings(max_examples=25)
@given(random_stack(), st.sampled_from([0.0, 1.0, 3.3]), st.sampled_from([0.0, 1.5]))
def test_property_invariants_random_parts(regions, buffer, min_width):
    job = Job().replace(**{"scaffold.buffer_mm": buffer, "cell.cpus": 1,
                           "scaffold.min_width_mm": min_width})
    st_ = add_scaffold(make_stack(regions, job))
    # thin-piece removal may take away surround narrower than min_width (never support)
    check_invariants(st_, buffer if buffer > 0 and min_width == 0 else None)


@st.composite
def scanned_stack(draw):
    """Layers of one or two wiggling disks that move and shrink or grow from layer to
    layer (a scan's ear tips): the smoothed walls and the leaning pass at work."""
    n = draw(st.integers(2, 5))
    layers = []
    for _ in range(n):
        disks = [rippled_disk(draw(st.floats(3.0, 15.0)), 300, draw(st.floats(0.0, 0.3)),
                              draw(st.floats(2.0, 8.0)), draw(st.floats(0.0, 0.03)),
                              draw(st.integers(0, 1000)),
                              (draw(st.floats(-10, 10)), draw(st.floats(-10, 10))))
                 for _ in range(draw(st.integers(1, 2)))]
        layers.append(geo.union(*disks))
    return layers


@settings(max_examples=25, deadline=None)
@given(scanned_stack(), st.sampled_from([0.1, 0.5]), st.sampled_from([30.0, 45.0]))
def test_property_invariants_scanned_parts(regions, smoothing, angle):
    job = Job().replace(**{"scaffold.smoothing_mm": smoothing, "cell.cpus": 1,
                           "scaffold.overhang_angle_deg": angle, "scaffold.min_width_mm": 0.0})
    check_invariants(add_scaffold(make_stack(regions, job)), 3.3)


def test_a_fuzzed_scaffold_keeps_no_needle_of_clippers():
    """A part found by fuzzing plan_layer (a star-like blob with a smaller copy beside it,
    tests/data/regions/needle-scaffold.npz): Clipper2's difference of its wall and the
    part returned a 3-point "hole" 8.5 mm long and 3.5e-5 mm wide inside another hole,
    which made the scaffold polygon invalid (overlapping holes; under the nonzero rule a
    sliver of scaffold inside the part's hole). No ring narrower on average than one grid
    unit is left, and the scaffold's area is the area of the wall less the part."""
    part = fuzzed_part("needle-scaffold")
    job = Job()
    st_ = add_scaffold(make_stack([part] * 2, job))
    for layer in st_.layers:
        for reg in (layer.part, layer.scaffold):
            check_region_structure(reg)
            rings = list(reg.rings)
            assert np.all(2.0 * np.abs(geo.ring_areas(rings)) * geo.SCALE
                          >= geo.ring_perimeters(rings))
        # apart but for Clipper's grid along the part's edge
        grid = 2.0 / geo.SCALE * float(geo.ring_perimeters(list(layer.part.rings)).sum())
        S, Pt = to_shapely(layer.scaffold), to_shapely(layer.part)
        assert S.intersection(Pt).area < grid
        assert S.union(Pt).area == pytest.approx(layer.scaffold.area + layer.part.area,
                                                 abs=grid)


def test_a_stack_a_program_built_is_checked_before_scaffold_and_paths():
    # a tester's outer rings wound clockwise got no part path and a scaffold around
    # nothing; a negative layer thickness commanded a negative volume; a NaN stack
    # thickness passed the thickness check
    from icefab import Layer, Region, Stack, add_scaffold, plan_paths
    from icefab.errors import ConfigError, GeometryError

    job = Job().replace(**{"slicing.layer_thickness_mm": 1.0})
    sq = np.array([[-20, -15], [20, -15], [20, 15], [-20, 15]], float)
    hole = np.array([[-5, -5], [-5, 5], [5, 5], [5, -5]], float)     # clockwise: a hole

    def stack(rings, parent, thickness=float("nan"), of=1.0):
        return Stack(tuple(Layer(i, i + 0.5, Region(tuple(rings), np.array(parent)),
                                 thickness=thickness) for i in range(2)), job, of)

    for f in (add_scaffold, plan_paths):
        with pytest.raises(GeometryError, match="layer 0: part ring 0 is an outer ring wound "
                                                "clockwise"):
            f(stack([sq[::-1]], [-1]), job)
        with pytest.raises(GeometryError, match="part ring 1 is a hole wound "
                                                "counter-clockwise"):
            f(stack([sq, hole[::-1]], [-1, 0]), job)
        with pytest.raises(GeometryError, match=r"layer 0: thickness -1\.0 mm"):
            f(stack([sq], [-1], thickness=-1.0), job)
        with pytest.raises(ConfigError, match="sliced at nan mm"):
            f(stack([sq], [-1], of=float("nan")), job)
    good = plan_paths(add_scaffold(stack([sq, hole], [-1, 0]), job), job)
    assert any(p.material == "part" and p.depositing for p in good.layers[0].paths)


def test_a_stack_goes_up_and_fits_the_paths_budget():
    # a tester's stack with its layers top first, or a NaN z, went through add_scaffold and
    # plan_paths; a 4 km square took add_scaffold 52 s and 3.5 GB before plan_paths
    # refused it for its fill
    from icefab import Layer, Region, Stack, add_scaffold, plan_paths
    from icefab.errors import ConfigError, GeometryError

    job = Job().replace(**{"slicing.layer_thickness_mm": 1.0})
    sq = np.array([[-20, -15], [20, -15], [20, 15], [-20, 15]], float)

    def stack(zs, ring=sq):
        return Stack(tuple(Layer(i, z, Region((ring,), np.array([-1])))
                           for i, z in enumerate(zs)), job, 1.0)

    for f in (add_scaffold, plan_paths):
        with pytest.raises(GeometryError, match=r"layer 1: z = 0.5 mm: layers must be given "
                                                r"bottom first.*above the one below \(1.5"):
            f(stack([1.5, 0.5]), job)
        with pytest.raises(GeometryError, match="layer 0: z = nan mm"):
            f(stack([float("nan"), 1.5]), job)
        with pytest.raises(GeometryError, match="layer 1: z = 0.5"):
            f(stack([0.5, 0.5]), job)
    with pytest.raises(ConfigError, match="fill_width_mm.*m of fill paths"):
        add_scaffold(stack([0.5], sq * 1e5), job)
    assert len(add_scaffold(stack([0.5, 1.5]), job).layers) == 2
