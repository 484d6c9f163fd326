"""Slicing against ground truth: analytic parts, an independent library, invariants."""
from __future__ import annotations

import math
import re

import numpy as np
import pytest
import shapely
import trimesh
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from icefab.config import Job
from icefab.errors import GeometryError
from icefab.slicing import layer_planes, slice_mesh, slice_report
from icefab.core import Mesh, signed_area

# The tests of the per-layer last resort consent to chords longer than max_gap_mm
# ("close"); the default refuses them (test_long_chord_refused_without_consent).
EXACT = Job().replace(**{"slicing.min_point_spacing_mm": 0.0,
                         "slicing.max_filter_deviation_mm": 0.0,
                         "slicing.open_contours": "close"})


def as_mesh(tm: trimesh.Trimesh, name: str = "test") -> Mesh:
    return Mesh(np.asarray(tm.vertices, dtype=np.float64),
                np.asarray(tm.faces, dtype=np.int64), name)


def job_with(**kw) -> Job:
    return EXACT.replace(**{f"slicing.{k}": v for k, v in kw.items()})


def box(extents, z0=0.0, center=(0.0, 0.0)) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=extents)
    b.apply_translation((center[0], center[1], z0 + extents[2] / 2))
    return b


def check_orientation_and_nesting(stack) -> None:
    """Outer rings (even depth) CCW, holes (odd depth) CW; each hole inside its parent."""
    for layer in stack:
        reg = layer.part
        depth = reg.depth()
        areas = reg.ring_areas()
        assert np.all((areas > 0) == (depth % 2 == 0)), layer.index
        for i, p in enumerate(reg.parent):
            if p >= 0:
                inner = shapely.Polygon(reg.rings[i])
                outer = shapely.Polygon(reg.rings[p])
                assert outer.contains(inner.representative_point())


def independent_area(tm: trimesh.Trimesh, z: float) -> float:
    """Cross-section area at height z: trimesh's plane section, rings combined even-odd
    (symmetric difference) by shapely."""
    sec = tm.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
    if sec is None:
        return 0.0
    region = shapely.Polygon()
    for ring in sec.discrete:
        if len(ring) >= 3:
            region = region.symmetric_difference(shapely.Polygon(ring[:, :2]).buffer(0))
    return float(region.area)


# --------------------------------------------------------------------------- planes


@pytest.mark.parametrize("cut", [0.0, 0.5, 1.0])
def test_box_exactly_n_layers_tall(cut):
    tm = box((10.0, 20.0, 5.0))
    stack = slice_mesh(as_mesh(tm), job_with(cut_fraction=cut))
    assert len(stack) == 20                                  # 5 mm / 0.25 mm
    for k, layer in enumerate(stack):
        assert layer.index == k
        assert layer.z == pytest.approx(min(5.0, max(0.0, (k + cut) * 0.25)))
        assert layer.top_z == pytest.approx((k + 1) * 0.25)
        assert layer.part.area == pytest.approx(200.0, rel=1e-9)
        assert len(layer.part.rings) == 1
        assert len(layer.part.rings[0]) == 4                  # collinear points removed
    assert stack.warnings == ()


def test_layer_planes_rounding_and_part_fraction():
    job = Job()
    bottom, top, z, q = layer_planes(0.0, 10.1, job)
    assert len(z) == 40                                       # round(40.4)
    assert np.all(q >= z) and np.all(z <= 10.1)
    job = Job().replace(**{"parts.part_fraction": [0.5, 1.0]})
    bottom, top, z, q = layer_planes(0.0, 10.0, job)
    assert len(z) == 20 and bottom[0] == pytest.approx(5.0)


def test_part_fraction_slices_only_that_height():
    tm = box((10.0, 10.0, 10.0))
    stack = slice_mesh(as_mesh(tm), EXACT.replace(**{"parts.part_fraction": [0.2, 0.6]}))
    assert len(stack) == 16
    assert stack[0].z == pytest.approx(2.125)
    assert all(L.part.area == pytest.approx(100.0) for L in stack)


def test_flat_mesh_is_an_error():
    tm = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    with pytest.raises(GeometryError, match="height"):
        slice_mesh(as_mesh(tm), EXACT)


# --------------------------------------------------------------------------- analytic parts


@pytest.mark.parametrize("sections", [32, 64])
def test_tube_area_nesting_orientation(sections):
    r_in, r_out, h = 3.0, 6.0, 10.0
    tm = trimesh.creation.annulus(r_min=r_in, r_max=r_out, height=h, sections=sections)
    tm.apply_translation((0, 0, h / 2))
    stack = slice_mesh(as_mesh(tm), EXACT)
    # exact area of the inscribed regular polygons
    expected = 0.5 * sections * math.sin(2 * math.pi / sections) * (r_out ** 2 - r_in ** 2)
    assert len(stack) == 40
    for layer in stack:
        reg = layer.part
        assert reg.area == pytest.approx(expected, rel=1e-6)
        assert len(reg.rings) == 2
        assert sorted(reg.parent.tolist()) == [-1, 0]
        outer = int(np.flatnonzero(reg.parent == -1)[0])
        assert signed_area(reg.rings[outer]) > 0
        assert signed_area(reg.rings[1 - outer]) < 0
    check_orientation_and_nesting(stack)


def test_sphere_area_matches_independent_cut():
    tm = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    tm.apply_translation((0, 0, 10.0))
    stack = slice_mesh(as_mesh(tm), job_with(layer_thickness_mm=0.5))
    assert len(stack) == 40
    for layer in stack:
        expected = independent_area(tm, layer.z)
        assert layer.part.area == pytest.approx(expected, rel=1e-6), layer.index
        # and close to the true circle it approximates
        r2 = 100.0 - (layer.z - 10.0) ** 2
        assert layer.part.area <= math.pi * r2 * (1 + 1e-9)
    check_orientation_and_nesting(stack)


def test_nested_islands_in_holes():
    """Box with a square hole, an island inside the hole, and a hole in the island."""
    import manifold3d as m3d

    def cube(s, h=4.0):
        return m3d.Manifold.cube([s, s, h], center=True).translate([0, 0, h / 2])

    solid = (cube(40) - cube(30, 6).translate([0, 0, -1])) + (cube(20) - cube(10, 6).translate(
        [0, 0, -1]))
    mm = solid.to_mesh()
    mesh = Mesh(np.asarray(mm.vert_properties[:, :3], dtype=np.float64),
                np.asarray(mm.tri_verts, dtype=np.int64), "nested")
    stack = slice_mesh(mesh, EXACT)
    for layer in stack:
        reg = layer.part
        assert reg.area == pytest.approx(1600 - 900 + 400 - 100, rel=1e-9)
        assert sorted(reg.depth().tolist()) == [0, 1, 2, 3]
        assert len(reg.polygons()) == 2
    check_orientation_and_nesting(stack)


@pytest.mark.parametrize("cut", [0.0, 0.5, 1.0])
def test_stacked_boxes_of_different_sizes(cut):
    """Three boxes stacked face to face: horizontal faces lie exactly on layer borders."""
    tm = trimesh.util.concatenate([box((20, 20, 2.5)), box((10, 10, 2.5), z0=2.5),
                                   box((4, 6, 1.0), z0=5.0)])
    stack = slice_mesh(as_mesh(tm), job_with(cut_fraction=cut))
    assert len(stack) == 24
    for layer in stack:
        mid = layer.top_z - 0.125                  # the layer's material
        expected = 400.0 if mid < 2.5 else 100.0 if mid < 5.0 else 24.0
        assert layer.part.area == pytest.approx(expected, rel=1e-9), (cut, layer.index)
        assert len(layer.part.rings) == 1
    assert stack.warnings == ()


@pytest.mark.parametrize("cut", [0.0, 1.0])
def test_welded_step_with_vertices_on_planes(cut):
    """A single welded manifold step: vertices and horizontal faces on cutting planes."""
    import manifold3d as m3d

    solid = m3d.Manifold.cube([20, 20, 2.5]) + m3d.Manifold.cube([10, 10, 2.5]).translate(
        [5, 5, 2.5])
    mm = solid.to_mesh()
    mesh = Mesh(np.asarray(mm.vert_properties[:, :3], dtype=np.float64),
                np.asarray(mm.tri_verts, dtype=np.int64), "step")
    stack = slice_mesh(mesh, job_with(cut_fraction=cut))
    rep = slice_report(stack)
    assert rep.open_chains == 0 and rep.tolerance_matched_ends == 0
    assert len(stack) == 20
    for layer in stack:
        expected = 400.0 if layer.top_z <= 2.5 + 1e-9 else 100.0
        assert layer.part.area == pytest.approx(expected, rel=1e-9)
        assert [len(r) for r in layer.part.rings] == [4]


def test_octahedron_vertex_on_plane():
    """Equator vertices exactly on a plane; the section there is the equator square."""
    tm = trimesh.Trimesh(vertices=[[1, 0, 1], [0, 1, 1], [-1, 0, 1], [0, -1, 1],
                                   [0, 0, 0], [0, 0, 2]],
                         faces=[[0, 1, 5], [1, 2, 5], [2, 3, 5], [3, 0, 5],
                                [1, 0, 4], [2, 1, 4], [3, 2, 4], [0, 3, 4]])
    stack = slice_mesh(as_mesh(tm), job_with(layer_thickness_mm=0.5, cut_fraction=0.0))
    # planes at 0, .5, 1, 1.5: section just above the plane -> squares of half-diag 1 - |z-1|
    expected = [2 * (1 - abs(z - 1)) ** 2 for z in (0.0, 0.5, 1.0, 1.5)]
    assert [L.part.area for L in stack] == pytest.approx(expected, rel=1e-9)
    assert stack[0].part.is_empty                 # the apex: a point, no area
    assert all(len(L.part.rings) == 1 and len(L.part.rings[0]) == 4 for L in stack[1:])
    assert slice_report(stack).open_chains == 0


# --------------------------------------------------------------------------- defects


def test_unwelded_mesh_falls_back_to_tolerance_matching():
    tm = trimesh.creation.annulus(r_min=2, r_max=5, height=4, sections=24)
    soup = trimesh.Trimesh(tm.triangles.reshape(-1, 3), np.arange(len(tm.faces) * 3).reshape(
        -1, 3), process=False)
    soup.apply_translation((0, 0, 2))
    tm.apply_translation((0, 0, 2))
    stack = slice_mesh(as_mesh(soup), EXACT)
    ref = slice_mesh(as_mesh(tm), EXACT)
    rep = slice_report(stack)
    assert rep.tolerance_matched_ends > 0 and rep.open_chains == 0
    assert any("tolerance" in w for w in stack.warnings)
    for a, b in zip(stack, ref):
        assert a.part.area == pytest.approx(b.part.area, rel=1e-9)
    check_orientation_and_nesting(stack)


def _box_without_side(extent=(10.0, 20.0, 5.0)):
    tm = box(extent)
    side = np.flatnonzero(np.isclose(tm.face_normals[:, 0], 1.0))
    keep = np.setdiff1d(np.arange(len(tm.faces)), side)
    return trimesh.Trimesh(tm.vertices, tm.faces[keep], process=False)


def test_open_mesh_gap_closed_and_reported():
    stack = slice_mesh(as_mesh(_box_without_side()), EXACT)
    assert len(stack) == 20
    for layer in stack:
        assert layer.part.area == pytest.approx(200.0, rel=1e-9)
    big = [w for w in stack.warnings if "20.00 mm gap" in w]
    assert len(big) == 20 and "layer 0 " in big[0]
    assert slice_report(stack).empty_layers == []


def test_long_chord_refused_without_consent():
    """Default settings: a 20 mm chord (> max_gap_mm = 2) stops slicing with one line
    naming the layer and the settings that decide; nothing is built from it."""
    job = EXACT.replace(**{"slicing.open_contours": "refuse"})
    with pytest.raises(GeometryError) as e:
        slice_mesh(as_mesh(_box_without_side()), job)
    msg = str(e.value)
    assert "\n" not in msg and "layer 0 " in msg and "20.00 mm" in msg
    assert "slicing.open_contours" in msg and "slicing.max_gap_mm = 2" in msg
    assert Job().slicing.open_contours == "refuse"


def test_open_mesh_drop_mode_drops_and_reports():
    stack = slice_mesh(as_mesh(_box_without_side()), job_with(open_contours="drop"))
    assert all(L.part.is_empty for L in stack)
    assert sum("dropped" in w for w in stack.warnings) == 20
    assert sum("empty cross-section" in w for w in stack.warnings) == 20


def test_open_chains_joined_across_two_pieces():
    """A tube cut lengthwise into two open halves: the chains join into one ring each layer."""
    tm = trimesh.creation.cylinder(radius=5, height=4, sections=32)
    tm.apply_translation((0, 0, 2))
    ang = np.degrees(np.arctan2(tm.vertices[:, 1], tm.vertices[:, 0])) % 360.0
    fa = ang[tm.faces]
    # remove the facet columns between 90 and 101.25 deg and 270 and 281.25 deg
    gap = np.flatnonzero(np.all((fa > 89.9) & (fa < 101.3), axis=1)
                         | np.all((fa > 269.9) & (fa < 281.3), axis=1))
    gap = gap[np.abs(tm.face_normals[gap, 2]) < 0.5]
    keep = np.setdiff1d(np.arange(len(tm.faces)), gap)
    half = trimesh.Trimesh(tm.vertices, tm.faces[keep], process=False)
    stack = slice_mesh(as_mesh(half), EXACT)
    ref = slice_mesh(as_mesh(tm), EXACT)
    rep = slice_report(stack)
    assert rep.open_chains == 2 * len(stack)
    for a, b in zip(stack, ref):
        assert len(a.part.rings) == 1
        assert a.part.area == pytest.approx(b.part.area, rel=1e-9)


# --------------------------------------------------------------------------- options


def test_2d_mode_copies_one_section():
    tm = trimesh.creation.cone(radius=5, height=10, sections=32)
    stack = slice_mesh(as_mesh(tm), job_with(mode="2d"))
    areas = {round(L.part.area, 9) for L in stack}
    assert len(stack) == 40 and len(areas) == 1
    assert areas.pop() == pytest.approx(independent_area(tm, stack[20].z), rel=1e-6)


def test_progress_is_reported():
    calls = []
    slice_mesh(as_mesh(box((5, 5, 5))), EXACT, progress=lambda d, t: calls.append((d, t)))
    assert calls and calls[-1] == (20, 20)


# --------------------------------------------------------------------------- properties


@given(ex=st.tuples(*[st.floats(1.0, 30.0)] * 3),
       angles=st.tuples(*[st.floats(0.0, 2 * math.pi)] * 3),
       t=st.sampled_from([0.25, 0.4, 1.0]))
def test_random_rotated_boxes_match_convex_sections(ex, angles, t):
    tm = trimesh.creation.box(extents=ex)
    tm.apply_transform(trimesh.transformations.euler_matrix(*angles))
    tm.apply_translation((0, 0, -tm.bounds[0, 2]))
    stack = slice_mesh(as_mesh(tm), job_with(layer_thickness_mm=t))
    height = tm.bounds[1, 2]
    assert len(stack) == max(1, round(height / t))
    assert slice_report(stack).open_chains == 0
    for layer in stack.layers[::max(1, len(stack) // 12)]:
        reg = layer.part
        lines = trimesh.intersections.mesh_plane(tm, [0, 0, 1], [0, 0, layer.z])
        pts = lines.reshape(-1, 3)[:, :2]
        if len(pts) < 3:
            continue
        try:
            expected = ConvexHull(pts).volume
        except Exception:  # degenerate (flat) hull of a sliver section
            continue
        assert len(reg.rings) == 1
        assert reg.area > 0
        assert reg.area == pytest.approx(expected, rel=1e-6, abs=1e-9)


def test_compiled_cut_equals_numpy_cut():
    """The parallel compiled kernel and the numpy expansion give identical segments."""
    import _slicing_twins as twins

    from icefab import slicing as S

    tm = trimesh.creation.icosphere(subdivisions=3, radius=7.0)
    tm = trimesh.util.concatenate([tm, box((3, 4, 20), z0=-8)])
    mesh = as_mesh(tm)
    v, f = mesh.vertices, mesh.faces
    _, _, _, q = S.layer_planes(v[:, 2].min(), v[:, 2].max(), EXACT)
    fz = v[:, 2][f]
    lo = np.searchsorted(q, fz.min(axis=1), side="right")
    hi = np.searchsorted(q, fz.max(axis=1), side="right")
    nbr = S._facet_adjacency(f, len(v))
    for k0, k1 in [(0, len(q)), (5, 30)]:
        a = S._intersect(v, f, fz, q, lo, hi, k0, k1, nbr)
        b = twins._intersect_numpy(v, f, fz, q, lo, hi, k0, k1, nbr)
        for name in ("layer", "facet", "edge", "points", "partner"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_adjacency_hash_equals_sort():
    """Hash-table adjacency equals the sorting version, with boundary and non-manifold edges."""
    import _slicing_twins as twins

    from icefab import slicing as S

    tm = trimesh.creation.icosphere(subdivisions=2)
    faces = np.asarray(tm.faces, dtype=np.int64)
    # open it (drop two faces) and add a fin sharing an edge (non-manifold)
    fin = np.array([[faces[5, 0], faces[5, 1], len(tm.vertices)]])
    faces = np.vstack([faces[2:], fin])
    n = len(tm.vertices) + 1
    a = S._facet_adjacency(faces, n)
    b = twins._facet_adjacency_numpy(faces, n)
    assert np.array_equal(a, b)
    assert (a == -1).any() and (a == -2).sum() == 3


@given(z=st.lists(st.floats(-5, 15, allow_nan=False), min_size=1, max_size=50),
       n=st.integers(1, 40), cut=st.sampled_from([0.0, 0.3, 0.5, 1.0]))
def test_plane_range_equals_searchsorted(z, n, cut):
    from icefab import slicing as S

    job = EXACT.replace(**{"slicing.cut_fraction": cut})
    _, _, _, q = S.layer_planes(0.0, n * 0.25, job)
    zz = np.array(z + [float(v) for v in q[:5]] + [float(np.nextafter(q[0], -1))])
    v = np.column_stack([np.zeros((len(zz), 2)), zz])
    f = np.column_stack([np.arange(len(zz))] * 3)
    lo, hi = S._facet_plane_range(v, f, q)
    assert np.array_equal(lo, np.searchsorted(q, zz, side="right"))
    assert np.array_equal(hi, lo)


def test_non_manifold_edge_falls_back_and_keeps_area():
    """Two cubes welded along one vertical edge (4 facets on it): ends on that edge are
    matched by tolerance; the area is still exact."""
    a = box((1, 1, 1), center=(0.5, 0.5))
    b = box((1, 1, 1), center=(1.5, 1.5))
    tm = trimesh.util.concatenate([a, b])
    tm.merge_vertices()
    mesh = as_mesh(tm)
    from icefab import slicing as S
    assert (S._facet_adjacency(mesh.faces, len(mesh.vertices)) == -2).any()
    stack = slice_mesh(mesh, job_with(layer_thickness_mm=0.25))
    rep = slice_report(stack)
    assert rep.tolerance_matched_ends > 0
    for layer in stack:
        assert layer.part.area == pytest.approx(2.0, rel=1e-9)


def test_overlapping_shells_give_their_union():
    """Two closed boxes overlapping (separate shells, as in merged parts or a handle pushed
    into a body): the layer is their union, not an even-odd mix."""
    a = box((10, 10, 2))
    b = box((10, 4, 2), center=(6, 0))          # sticks out of a by 6 x 4
    stack = slice_mesh(as_mesh(trimesh.util.concatenate([a, b])), EXACT)
    rep = slice_report(stack)
    assert rep.union_layers == list(range(len(stack)))
    for layer in stack:
        assert layer.part.area == pytest.approx(100 + 24, rel=1e-6)
        assert len(layer.part) == 1
    check_orientation_and_nesting(stack)


def test_open_stub_into_a_body_is_united():
    """An open tube (no caps) whose end lies inside a closed body: its chains are closed
    across the gaps and united with the body (teapot spout/handle case)."""
    body = box((20, 20, 10))
    tube = trimesh.creation.cylinder(radius=3, height=15, sections=16)
    tube.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    tube.apply_translation((12.5, 0, 5))           # x from 5 (inside the body) to 20
    walls = np.flatnonzero(np.abs(tube.face_normals[:, 0]) < 0.5)
    open_tube = trimesh.Trimesh(tube.vertices, tube.faces[walls], process=False)
    stack = slice_mesh(as_mesh(trimesh.util.concatenate([body, open_tube])),
                       job_with(layer_thickness_mm=0.5))
    rep = slice_report(stack)
    assert rep.open_chains > 0 and rep.empty_layers == []
    for layer in stack:
        sq = shapely.box(-10, -10, 10, 10)
        sec = tube.section(plane_origin=[0, 0, layer.z], plane_normal=[0, 0, 1])
        expected = sq
        if sec is not None:
            for ring in sec.discrete:
                expected = expected.union(shapely.Polygon(ring[:, :2]).buffer(0))
        assert layer.part.area == pytest.approx(expected.area, rel=1e-5), layer.index
    check_orientation_and_nesting(stack)


@given(ex=st.tuples(*[st.floats(2.0, 20.0)] * 3),
       angles=st.tuples(*[st.floats(0.0, 2 * math.pi)] * 3),
       drop=st.integers(0, 11))
def test_random_boxes_with_a_missing_facet_keep_their_area(ex, angles, drop):
    """A planar facet missing from a (rotated) box: each gap it leaves lies in that facet's
    plane, so closing it with a straight line restores the exact section; every layer
    keeps its area, and the gaps are counted or reported."""
    tm = trimesh.creation.box(extents=ex)
    tm.apply_transform(trimesh.transformations.euler_matrix(*angles))
    tm.apply_translation((0, 0, -tm.bounds[0, 2]))
    full = slice_mesh(as_mesh(tm), job_with(layer_thickness_mm=0.5))
    keep = np.setdiff1d(np.arange(12), [drop])
    holed = trimesh.Trimesh(tm.vertices, tm.faces[keep], process=False)
    stack = slice_mesh(as_mesh(holed), job_with(layer_thickness_mm=0.5))
    rep = slice_report(stack)
    assert len(stack) == len(full)
    for a, b in zip(stack, full):
        assert a.part.area == pytest.approx(b.part.area, rel=1e-6, abs=1e-6)
    assert rep.empty_layers == slice_report(full).empty_layers
    # every closure is reported one by one with its layer and location
    closures = [w for w in stack.warnings if "open contour closed across" in w]
    assert len(closures) == rep.gaps_closed + rep.large_gaps_closed
    assert all(re.match(r"layer \d+ \(z = [\d.]+ mm\): .* gap at \(", w) for w in closures)


def test_inside_out_mesh_still_gives_the_section():
    """All facets flipped (normals inwards): contours are re-oriented, areas unchanged."""
    tm = trimesh.creation.annulus(r_min=2, r_max=5, height=3, sections=24)
    tm.apply_translation((0, 0, 1.5))
    ref = slice_mesh(as_mesh(tm), EXACT)
    inv = Mesh(np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64)[:, ::-1].copy())
    stack = slice_mesh(inv, EXACT)
    assert slice_report(stack).rings_reoriented > 0
    assert slice_report(stack).union_layers == []
    for a, b in zip(stack, ref):
        assert a.part.area == pytest.approx(b.part.area, rel=1e-9)
    check_orientation_and_nesting(stack)


@pytest.mark.parametrize("shift", [(8.0, 8.0), (-8.0, 3.0), (0.0, 9.5)])
def test_crossing_rings_of_separate_shells_are_united(shift):
    """Two closed boxes overlapping at a corner or an edge, whichever ring's points fall
    inside the other: the section is their union (no double counting)."""
    a = box((10, 10, 1))
    b = box((10, 10, 1), center=shift)
    expected = shapely.box(-5, -5, 5, 5).union(
        shapely.box(shift[0] - 5, shift[1] - 5, shift[0] + 5, shift[1] + 5)).area
    for parts in ([a, b], [b, a]):
        stack = slice_mesh(as_mesh(trimesh.util.concatenate(parts)), EXACT)
        for layer in stack:
            assert layer.part.area == pytest.approx(expected, rel=1e-6)
        check_orientation_and_nesting(stack)


@pytest.mark.parametrize("cut", [0.0, 0.5, 1.0])
def test_part_thinner_than_a_layer_gives_one_full_layer(cut):
    stack = slice_mesh(as_mesh(box((4, 5, 0.1))), job_with(cut_fraction=cut))
    assert len(stack) == 1
    assert 0.0 <= stack[0].z <= 0.1
    assert stack[0].part.area == pytest.approx(20.0, rel=1e-9)


def test_a_mesh_built_by_a_program_is_checked_before_slicing():
    # a tester's Mesh from trimesh with a face index past its vertices segfaulted the cut
    # kernel (or gave layers of 1e8 mm^2); a NaN x gave empty layers without a word
    import trimesh

    from icefab.core import Mesh

    job = Job().replace(**{"slicing.layer_thickness_mm": 1.0})
    b = trimesh.creation.box((40, 30, 5))
    b.apply_translation((0, 0, 2.5))
    V, F = np.asarray(b.vertices, float), np.asarray(b.faces, np.int64)
    for index in (100_000_000, 8, -1):
        bad = F.copy()
        bad[3, 1] = index
        with pytest.raises(GeometryError, match=rf"box: face 3 has vertex index .*{index}.* "
                                                r"out of range: the mesh has 8 vertices"):
            slice_mesh(Mesh(V, bad, name="box"), job)
    nan = V.copy()
    nan[2, 0] = np.nan
    with pytest.raises(GeometryError, match=r"vertex 2 is \[nan"):
        slice_mesh(Mesh(nan, F), job)
    with pytest.raises(GeometryError, match=r"vertices \(8, 2\)"):
        slice_mesh(Mesh(V[:, :2], F), job)
    with pytest.raises(GeometryError, match="integer vertex indices"):
        slice_mesh(Mesh(V, F + 0.5), job)
    # lists are arrays of numbers too
    a, b2 = slice_mesh(Mesh(V.tolist(), F.tolist()), job), slice_mesh(Mesh(V, F), job)
    assert [lay.part.area for lay in a] == [lay.part.area for lay in b2]
