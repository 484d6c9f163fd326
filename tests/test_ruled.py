"""Ruled layer edges (icefab.ruled; Zhang & Liou IV-V): tilts against analytic surfaces,
contour correspondence with branching, ledges, the nearest-point search against shapely,
the ruled.npz file and ``icefab export ruled``."""
from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import manifold3d as m3
import numpy as np
import pytest
import shapely
from hypothesis import given, settings, strategies as st

from icefab.config import job_from_dict
from icefab.core import Mesh
from icefab.errors import StackFileError
from icefab.geometry import nearest_on_rings
from icefab.resultfiles import load_ruled, save_ruled, save_stack
from icefab.ruled import corresponding, ruled_edges
from icefab.slicing import slice_mesh

#: No point filter: the filter moves a contour by up to its deviation (0.05 mm by default),
#: which over a 0.25 mm layer tilts an edge by up to atan(0.1 / 0.25) = 22 degrees.
EXACT = job_from_dict({"slicing": {"min_point_spacing_mm": 0.0}})


def loft(ring_at, zs) -> Mesh:
    """A closed mesh through the rings ``ring_at(z)`` ((m, 2) CCW, same m) at heights zs,
    capped by fans at both ends."""
    rows = [np.asarray(ring_at(z), dtype=np.float64) for z in zs]
    m, n_rows = len(rows[0]), len(zs)
    v = np.concatenate([np.c_[r, np.full(m, z)] for r, z in zip(rows, zs)])
    cb, ct = len(v), len(v) + 1
    v = np.vstack([v, [[*rows[0].mean(0), zs[0]], [*rows[-1].mean(0), zs[-1]]]])
    i = np.arange(m)
    i1 = (i + 1) % m
    faces = []
    for j in range(n_rows - 1):
        a, b, c, d = j * m + i, j * m + i1, (j + 1) * m + i1, (j + 1) * m + i
        faces += [np.c_[a, b, c], np.c_[a, c, d]]
    top = (n_rows - 1) * m
    faces += [np.c_[np.full(m, cb), i1, i], np.c_[np.full(m, ct), top + i, top + i1]]
    return Mesh(v, np.concatenate(faces).astype(np.int64), name="loft")


def manifold_mesh(solid) -> Mesh:
    mm = solid.to_mesh()
    return Mesh(np.asarray(mm.vert_properties)[:, :3].astype(np.float64),
                np.asarray(mm.tri_verts).astype(np.int64), name="manifold")


CIRCLE = np.linspace(0.0, 2.0 * math.pi, 256, endpoint=False)


@pytest.mark.parametrize("r0, r1", [(30.0, 25.0), (20.0, 26.0)])
def test_cone_tilt_is_the_half_angle(r0, r1):
    """A frustum from radius r0 to r1 over 10 mm: every generator leans by the cone's half
    angle atan((r1 - r0) / 10), out of the material when it widens. Error budget: the 256
    facets make vertex and mid-facet offsets differ by a factor cos(pi / 256)."""
    h = 10.0
    mesh = loft(lambda z: np.c_[np.cos(CIRCLE), np.sin(CIRCLE)] * (r0 + (r1 - r0) * z / h),
                [0.0, h])
    stack = slice_mesh(mesh, EXACT)
    edges = ruled_edges(stack)
    below_top = edges.layer < len(stack) - 1
    assert edges.matched[below_top].all()
    assert not edges.matched[~below_top].any()
    want = math.degrees(math.atan((r1 - r0) / h))
    got = np.degrees(edges.tilt[below_top])
    assert np.abs(got - want).max() < 0.01
    # the generator ends on the next layer's contour: the radius there
    r_next = np.hypot(*edges.match[below_top].T)
    z_next = edges.z[below_top] + edges.dz[below_top]
    r_true = r0 + (r1 - r0) * z_next / h
    assert np.abs(r_next - r_true).max() < r_true.max() * (1 - math.cos(math.pi / 256)) + 1e-9


def test_twisted_extrusion_tilt():
    """A 20 mm square twisted by 45 degrees over 20 mm (omega rad/mm): at distance s from a
    side's middle the wall leans by atan(omega * s), into the material where the twist
    carries the side inwards. Tolerance: the generator joins two sections omega * dz
    apart, so its slope differs from the surface's by up to a * omega^2 * dz (0.22 deg),
    checked away from the corners (0.5 mm) where the nearest point turns the corner."""
    a, height = 10.0, 20.0
    omega = (math.pi / 4) / height
    s = np.linspace(-a, a, 81)[:-1]
    square = np.concatenate([np.c_[np.full(80, a), s], np.c_[-s, np.full(80, a)],
                             np.c_[np.full(80, -a), -s], np.c_[s, np.full(80, -a)]])

    def section(z):
        c, si = math.cos(omega * z), math.sin(omega * z)
        return square @ np.array([[c, si], [-si, c]])

    stack = slice_mesh(loft(section, np.linspace(0.0, height, 81)), EXACT)
    edges = ruled_edges(stack)
    ok = edges.matched
    p, z = edges.point[ok], edges.z[ok]
    c, si = np.cos(-omega * z), np.sin(-omega * z)
    q = np.c_[c * p[:, 0] - si * p[:, 1], si * p[:, 0] + c * p[:, 1]]  # untwisted
    on_x = np.abs(q[:, 0]) >= np.abs(q[:, 1])  # on a side x = +-a (else y = +-a)
    along = np.where(on_x, q[:, 1] * np.sign(q[:, 0]), -q[:, 0] * np.sign(q[:, 1]))
    middle = np.abs(along) < a - 0.5
    assert middle.sum() > 0.8 * ok.sum()
    want = -np.degrees(np.arctan(omega * along[middle]))
    got = np.degrees(edges.tilt[ok][middle])
    bound = math.degrees(a * omega ** 2 * stack.layer_thickness)
    assert np.abs(got - want).max() <= bound
    assert np.abs(got).max() > 20.0  # the test sees real tilts (atan(omega * 9.5) = 20.5)


def v_groove_stack():
    """A 40 x 20 x 20 mm block with a 45-degree V groove along y whose bottom is at z = 8:
    one contour below 8 mm, two above (branching)."""
    block = m3.Manifold.cube([40.0, 20.0, 20.0]).translate([-20.0, -10.0, 0.0])
    wedge = m3.Manifold.hull_points(np.array(
        [[sx * 13.0, sy * 11.0, 21.0] for sx in (-1, 1) for sy in (-1, 1)]
        + [[0.0, sy * 11.0, 8.0] for sy in (-1, 1)]))
    return slice_mesh(manifold_mesh(block - wedge), EXACT)


def test_branching_contour_joins_both_branches():
    stack = v_groove_stack()
    zs = np.array([L.z for L in stack])
    k = int(np.searchsorted(zs, 8.0)) - 1
    assert len(stack[k].part) == 1 and len(stack[k + 1].part) == 2
    assert sorted(corresponding(stack[k].part, stack[k + 1].part)[0].tolist()) == [0, 1]
    edges = ruled_edges(stack)
    at_k = edges.layer == k
    assert edges.matched[at_k].all()
    assert set(edges.match_ring[at_k].tolist()) == {0, 1}
    walls = edges.matched & (edges.z > 9.0)
    inner = walls & (np.abs(edges.point[:, 0]) < 19.9)
    outer = walls & (np.abs(np.abs(edges.point[:, 0]) - 20.0) < 1e-9)
    assert inner.sum() >= 4 * 10 and outer.sum() >= 4 * 10
    np.testing.assert_allclose(np.degrees(edges.tilt[inner]), -45.0, atol=1e-6)
    np.testing.assert_allclose(np.degrees(edges.tilt[outer]), 0.0, atol=1e-6)


def test_holes_match_holes():
    """A tube (outer radius 30) whose conical hole widens from radius 10 to 15 over 10 mm:
    hole points match the hole above and lean into the material by atan(0.5); outer points
    match the outer ring, vertical."""
    tube = (m3.Manifold.cylinder(10.0, 30.0, 30.0, 256)
            - m3.Manifold.cylinder(12.0, 9.0, 15.0 + 0.5, 256).translate([0, 0, -1.0]))
    stack = slice_mesh(manifold_mesh(tube), EXACT)
    edges = ruled_edges(stack)
    ok = edges.matched
    r = np.hypot(*edges.point.T)
    hole, outer = ok & (r < 25.0), ok & (r > 25.0)
    depth = {k: stack[k].part.depth() for k in range(len(stack))}
    up_depth = np.array([depth[k + 1][j] for k, j in zip(edges.layer[ok], edges.match_ring[ok])])
    assert (up_depth[r[ok] < 25.0] == 1).all() and (up_depth[r[ok] > 25.0] == 0).all()
    np.testing.assert_allclose(np.degrees(edges.tilt[outer]), 0.0, atol=0.01)
    want = -math.degrees(math.atan(6.5 / 12.0))
    assert np.abs(np.degrees(edges.tilt[hole]) - want).max() < 0.05


def test_ledges_have_no_edge():
    """A 10 mm leg under a 40 mm slab: the leg's top contour is 5-15 mm from the slab's,
    flatter than max_tilt over one layer, so it gets no generator (a ledge), while the
    walls below and above are vertical."""
    solid = (m3.Manifold.cube([10.0, 10.0, 5.0]).translate([-5.0, -5.0, 0.0])
             + m3.Manifold.cube([40.0, 40.0, 3.0]).translate([-20.0, -20.0, 5.0]))
    stack = slice_mesh(manifold_mesh(solid), EXACT)
    edges = ruled_edges(stack)
    zs = np.array([L.z for L in stack])
    k = int(np.searchsorted(zs, 5.0)) - 1
    assert not edges.matched[edges.layer == k].any()
    others = (edges.layer != k) & (edges.layer < len(stack) - 1)
    assert edges.matched[others].all()
    np.testing.assert_allclose(edges.tilt[others], 0.0, atol=1e-9)
    # a limit outside (0, 90) degrees is refused
    with pytest.raises(ValueError, match="max_tilt_deg"):
        ruled_edges(stack, 90.0)


def star(n: int, radii: list[float], centre=(0.0, 0.0)) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    r = np.resize(np.asarray(radii), n)
    return np.c_[centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)]


@settings(max_examples=60, deadline=None, derandomize=True)
@given(radii=st.lists(st.floats(1.0, 20.0), min_size=3, max_size=40),
       points=st.lists(st.tuples(st.floats(-40, 40), st.floats(-40, 40)), min_size=1,
                       max_size=50),
       spacing=st.floats(0.05, 5.0))
def test_nearest_on_rings_matches_shapely(radii, points, spacing):
    rings = [star(len(radii), radii), star(7, [3.0, 5.0], centre=(25.0, 0.0))[::-1]]
    q = np.asarray(points, dtype=np.float64)
    dist, foot, which = nearest_on_rings(q, rings, spacing=spacing)
    lines = [shapely.LinearRing(r) for r in rings]
    want = np.min([shapely.distance(shapely.points(q), ln) for ln in lines], axis=0)
    np.testing.assert_allclose(dist, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.hypot(*(q - foot).T), dist, rtol=0, atol=1e-9)
    on = np.array([shapely.distance(shapely.Point(f), lines[w]) for f, w in zip(foot, which)])
    assert on.max() < 1e-9


def test_ruled_file_round_trip_and_damage(tmp_path):
    stack = v_groove_stack()
    edges = ruled_edges(stack)
    path = save_ruled(edges, stack.job, tmp_path / "ruled.npz")
    back, job = load_ruled(path)
    for name in ("layer", "ring", "point", "z", "match", "match_ring", "dz", "tilt"):
        np.testing.assert_array_equal(getattr(back, name), getattr(edges, name))
    assert job.slicing == stack.job.slicing
    # a match given where match_ring says none, a tilt beyond vertical, another file kind
    with np.load(path) as f:
        members = dict(f)
    bad = dict(members)
    bad["match_ring"] = np.where(members["match_ring"] >= 0, -1, -1)
    np.savez(tmp_path / "b1.npz", **bad)
    with pytest.raises(StackFileError, match="b1.npz: member match: must be given exactly"):
        load_ruled(tmp_path / "b1.npz")
    bad = dict(members)
    bad["tilt"] = np.where(members["match_ring"] >= 0, 2.0, np.nan)
    np.savez(tmp_path / "b2.npz", **bad)
    with pytest.raises(StackFileError, match="b2.npz: member tilt: value 2.0 above"):
        load_ruled(tmp_path / "b2.npz")
    save_stack(stack, tmp_path / "stack.npz")
    with pytest.raises(StackFileError, match="not an icefab ruled edges file"):
        load_ruled(tmp_path / "stack.npz")


def _icefab(*args):
    return subprocess.run([sys.executable, "-m", "icefab", *args], capture_output=True,
                          text=True, timeout=300)


def test_export_ruled_cli(tmp_path):
    stack = v_groove_stack()
    save_stack(stack, tmp_path / "stack.npz")
    r = _icefab("export", "ruled", str(tmp_path / "stack.npz"), "-o", str(tmp_path / "out"),
                "--layers", "10,40")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "out" / "ruled.png").stat().st_size > 10_000
    edges, _ = load_ruled(tmp_path / "out" / "ruled.npz")
    assert len(edges) == sum(L.part.n_points for L in stack)
    assert "tilt from vertical" in r.stdout and "uncertain by up to 0.0 deg" in r.stdout
    assert "over layers 0.25 mm thick at the thinnest" in r.stdout
    # adaptive layers: the thinnest one bounds the tilts' uncertainty, not the nominal
    thin = dataclasses.replace(stack, layers=tuple(
        dataclasses.replace(L, thickness=0.08 if k == 3 else 0.25)
        for k, L in enumerate(stack.layers)))
    save_stack(thin, tmp_path / "thin.npz")
    r = _icefab("export", "ruled", str(tmp_path / "thin.npz"), "-o", str(tmp_path / "out2"))
    assert r.returncode == 0, r.stderr
    assert "over layers 0.08 mm thick at the thinnest" in r.stdout
    for args, msg in ((["--max-tilt", "95"], "--max-tilt 95.0: expected"),
                      (["--max-tilt", "nan"], "--max-tilt nan: expected"),
                      (["--layers", "999"], "--layers '999': layer numbers")):
        r = _icefab("export", "ruled", str(tmp_path / "stack.npz"), "-o",
                    str(tmp_path / "bad"), *args)
        assert r.returncode == 2 and msg in r.stderr and len(r.stderr.splitlines()) == 1
        assert not (tmp_path / "bad").exists()
    r = _icefab("export", "ruled", str(tmp_path / "none.npz"), "-o", str(tmp_path / "bad"))
    assert r.returncode == 2 and "none.npz" in r.stderr and len(r.stderr.splitlines()) == 1
