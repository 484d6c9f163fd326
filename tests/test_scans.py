"""Open and self-crossing scans (issue 11): holes closed in 3D, regions simple, closures
bounded.

The test meshes are made here (trimesh): a sphere "scan" with holes of several sizes and
an open base, two overlapping closed shells, and prisms whose section crosses itself (a
bow tie, winding +-1, and a pentagram, winding 2 in its centre). For every layer the region
must be valid (shapely ``is_valid``) and its area must equal the non-zero union of an
independent section of the repaired mesh: trimesh's ``section`` noded by shapely into
faces, each face kept when the section's rings wind around a point inside it (winding
number not zero).
"""
from __future__ import annotations

import numpy as np
import pytest
import shapely
import trimesh

from icefab import Job
from icefab.core import Mesh
from icefab.errors import GeometryError
from icefab.mesh import check_mesh, prepare_parts, write_stl
from icefab.mesh.holes import close_holes
from icefab.slicing import slice_mesh, slice_report

EXACT = Job().replace(**{"slicing.min_point_spacing_mm": 0.0,
                         "slicing.max_filter_deviation_mm": 0.0,
                         "slicing.layer_thickness_mm": 0.5})


def as_mesh(tm: trimesh.Trimesh, name: str = "scan") -> Mesh:
    return Mesh(np.asarray(tm.vertices, np.float64), np.asarray(tm.faces, np.int64), name)


def holed_sphere() -> trimesh.Trimesh:
    """A 40 mm sphere scan: holes of ~2, ~8 and ~20 mm across and a ~32 mm open base."""
    tm = trimesh.creation.icosphere(subdivisions=4, radius=20.0)
    c = tm.triangles_center
    drop = c[:, 2] < -12.0                                     # the open base
    for direction, r in (((1, 0, 0), 1.0), ((0, 1, 0), 4.0), ((-1, -1, 0.6), 10.0)):
        centre = 20.0 * np.array(direction) / np.linalg.norm(direction)
        drop |= np.linalg.norm(c - centre, axis=1) < r
    out = trimesh.Trimesh(tm.vertices, tm.faces[~drop], process=False)
    out.remove_unreferenced_vertices()
    return out


def overlapping_shells() -> trimesh.Trimesh:
    a = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    b = trimesh.creation.box(extents=(14.0, 14.0, 14.0))
    b.apply_translation((8.0, 3.0, 2.0))
    return trimesh.util.concatenate([a, b])


def prism(ring: np.ndarray, height: float = 10.0) -> trimesh.Trimesh:
    """A closed prism over a (possibly self-crossing) ring: walls and fan caps."""
    k = len(ring)
    v = np.vstack([np.c_[ring, np.zeros(k)], np.c_[ring, np.full(k, height)]])
    f = []
    for i in range(k):
        j = (i + 1) % k
        f += [[i, j, k + j], [i, k + j, k + i]]
    for i in range(1, k - 1):
        f += [[0, i + 1, i], [k, k + i, k + i + 1]]
    return trimesh.Trimesh(v, np.array(f), process=False)


BOWTIE = np.array([[0.0, 0.0], [10.0, 10.0], [10.0, 0.0], [0.0, 10.0]])
PENTAGRAM = np.array([[10 * np.cos(np.pi / 2 + 4 * np.pi * i / 5),
                       10 * np.sin(np.pi / 2 + 4 * np.pi * i / 5)] for i in range(5)])


def winding_number(rings: list[np.ndarray], x: float, y: float) -> int:
    """How many times the rings wind around (x, y): the sum of the angles their edges
    subtend, over 2 pi (the textbook definition, not icefab's code)."""
    total = 0.0
    for r in rings:
        d = r - (x, y)
        a = np.arctan2(d[:, 1], d[:, 0])
        total += float(np.sum((np.roll(a, -1) - a + np.pi) % (2 * np.pi) - np.pi))
    return int(round(total / (2 * np.pi)))


def nonzero_area(rings: list[np.ndarray]) -> float:
    """Area of the non-zero union of closed rings, computed without icefab: shapely nodes
    the rings into faces; a face counts when the rings' winding number around a point
    inside it is not zero."""
    if not rings:
        return 0.0
    lines = shapely.node(shapely.MultiLineString([np.vstack([r, r[:1]]) for r in rings]))
    total = 0.0
    for face in shapely.get_parts(shapely.polygonize(shapely.get_parts(lines))):
        p = face.representative_point()
        if winding_number(rings, p.x, p.y) != 0:
            total += face.area
    return total


def oriented_by_facets(tm: trimesh.Trimesh, ring: np.ndarray, z: float) -> np.ndarray:
    """The section ring (k, 2) turned so the material lies on its left (outer rings
    counter-clockwise): the facet under its first edge's midpoint points outwards, i.e. to
    the right of travel. trimesh's section does not keep this orientation."""
    a, b = ring[0], ring[1]
    mid = np.array([[(a[0] + b[0]) / 2, (a[1] + b[1]) / 2, z]])
    tri = tm.triangles
    closest = trimesh.triangles.closest_point(tri, np.repeat(mid, len(tri), axis=0))
    face = int(np.argmin(np.linalg.norm(closest - mid, axis=1)))
    n = tm.face_normals[face]
    t = b - a
    return ring if n[0] * t[1] - n[1] * t[0] >= 0 else ring[::-1]


def independent_areas(tm: trimesh.Trimesh, zs) -> list[float]:
    out = []
    for z in zs:
        sec = tm.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
        rings = [] if sec is None else [d[:, :2] for d in sec.discrete if len(d) >= 4]
        rings = [r[:-1] if np.allclose(r[0], r[-1]) else r for r in rings]
        out.append(nonzero_area([oriented_by_facets(tm, r, z) for r in rings]))
    return out


def region_polygon(region) -> shapely.Geometry:
    """The region as shapely sees it: outer rings with their holes (from the nesting)."""
    depth = region.depth()
    rings = list(region.rings)
    polys = []
    for i, r in enumerate(rings):
        if depth[i] % 2 == 0:
            holes = [rings[j] for j in range(len(rings)) if region.parent[j] == i]
            polys.append(shapely.Polygon(r, holes))
    return shapely.MultiPolygon(polys) if polys else shapely.Polygon()


def check_stack(stack, repaired: trimesh.Trimesh) -> None:
    expected = independent_areas(repaired, [L.z for L in stack])
    for layer, want in zip(stack, expected):
        geom = region_polygon(layer.part)
        assert geom.is_valid, (layer.index, shapely.is_valid_reason(geom))
        # united layers: Clipper's 1e-4 mm grid moves crossing points by up to 1e-4 mm
        assert layer.part.area == pytest.approx(want, rel=1e-5, abs=1e-9), layer.index
        assert geom.area == pytest.approx(layer.part.area, rel=1e-9, abs=1e-9)


def test_scan_with_holes_of_several_sizes_is_closed_in_3d_then_sliced():
    scan = holed_sphere()
    mesh = as_mesh(scan)
    assert check_mesh(mesh).open_edges > 0
    with pytest.raises(GeometryError, match="slicing.open_contours"):  # no 3D closing:
        slice_mesh(mesh, EXACT)                            # long chords are refused
    closed, report = close_holes(mesh)
    assert len(report.holes) == 4 and report.unclosed_edges == 0
    spans = sorted(h.span_mm for h in report.holes)
    assert spans[0] < 4 < spans[1] < 12 < spans[2] < 25 < spans[3]  # ~2, ~8, ~20, ~32 mm
    after = check_mesh(closed)
    assert after.open_edges == after.non_manifold_edges == after.misoriented_edges == 0
    np.testing.assert_array_equal(closed.faces[:len(mesh.faces)], mesh.faces)
    stack = slice_mesh(closed, EXACT)                      # default: refuse long chords
    rep = slice_report(stack)
    assert rep.open_chains == 0 and rep.large_gaps_closed == 0 and not rep.empty_layers
    check_stack(stack, trimesh.Trimesh(closed.vertices, closed.faces, process=False))


@pytest.mark.parametrize("make", [overlapping_shells, lambda: prism(BOWTIE),
                                  lambda: prism(PENTAGRAM)],
                         ids=["overlapping-shells", "bowtie", "pentagram"])
def test_self_crossing_sections_give_simple_regions_of_the_nonzero_union(make):
    tm = make()
    stack = slice_mesh(as_mesh(tm), EXACT)
    assert slice_report(stack).union_layers          # the crossing layers are united
    check_stack(stack, tm)


def test_nonzero_union_areas_are_the_analytic_ones():
    """The independent computation itself, against hand-worked areas: the bow tie's two
    triangles (2 x 25 mm^2); the pentagram with its centre pentagon (winding 2), i.e. ten
    triangles (centre, tip, inner corner) of area R r sin(pi/5) / 2 each."""
    assert nonzero_area([BOWTIE]) == pytest.approx(50.0)
    big, small = 10.0, 10.0 * np.cos(2 * np.pi / 5) / np.cos(np.pi / 5)
    assert nonzero_area([PENTAGRAM]) == pytest.approx(5 * big * small * np.sin(np.pi / 5),
                                                      rel=1e-9)


def test_pipeline_closes_holes_and_locates_defects_in_build_mm(tmp_path):
    """prepare_parts: the holes are closed in 3D, and the positions reported are where
    they are in the build (after scale, rotation and translation), not in the file."""
    tm = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    tm.apply_translation((105.0, 5.0, 5.0))                # file: x 100..110
    top = np.flatnonzero(np.isclose(tm.triangles_center[:, 2], 10.0))
    open_box = trimesh.Trimesh(tm.vertices, np.delete(tm.faces, top, axis=0), process=False)
    write_stl(as_mesh(open_box, "box"), tmp_path / "box.stl")
    job = Job().replace(**{"parts.files": ["box.stl"], "parts.scale": [2.0, 2.0, 2.0],
                           "parts.translation": [0.0, 0.0, 0.0]})
    mesh = prepare_parts(job, base_dir=tmp_path)
    assert check_mesh(mesh).open_edges == 0
    (w,) = [w for w in mesh.warnings if "holes closed in 3D" in w]
    assert "1 holes" in w and "(10, 10, 20) mm" in w      # build: x 0..20, top at z 20
    assert not any("open edges" in w for w in mesh.warnings)
    kept = Job().replace(**{"parts.files": ["box.stl"], "parts.scale": [2.0, 2.0, 2.0],
                            "parts.translation": [0.0, 0.0, 0.0], "parts.close_holes": False})
    raw = prepare_parts(kept, base_dir=tmp_path)
    (w,) = [w for w in raw.warnings if "open edges" in w]
    assert "build coordinates" in w and "105" not in w and "110" not in w
