"""Adaptive layers by cusp height (icefab.adaptive, Zhang & Liou IV): the cusp bound
checked analytically on a sphere, flats as layer boundaries, the thickness carried through
the result files, the scaffold, the paths' measurement schedule, the valve flow and the
simulator; the default unchanged."""
from __future__ import annotations

import math
import subprocess
import sys

import manifold3d as m3
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from icefab.adaptive import plan_layers
from icefab.config import Job, job_from_dict
from icefab.core import Mesh
from icefab.errors import ConfigError, StackFileError
from icefab.flow import valve_frequency
from icefab.motion import plan_toolpaths
from icefab.paths import plan_paths
from icefab.regions import add_scaffold
from icefab.resultfiles import (load_stack, load_toolpaths, load_trajectories, save_stack,
                                save_toolpaths, save_trajectories)
from icefab.sim import simulate_build
from icefab.slicing import slice_mesh, slice_report
from icefab.stages import measured_layers

R = 15.0
CUSP = 0.05


def mesh_of(solid) -> Mesh:
    m = solid.to_mesh()
    return Mesh(np.asarray(m.vert_properties)[:, :3].astype(np.float64),
                np.asarray(m.tri_verts).astype(np.int64), name="manifold")


def sphere_mesh(segments: int = 256) -> Mesh:
    return mesh_of(m3.Manifold.sphere(R, segments).translate([0.0, 0.0, R]))


ADAPTIVE = job_from_dict({"slicing": {"cusp_height_mm": CUSP,
                                      "min_layer_thickness_mm": CUSP,
                                      "max_layer_thickness_mm": 1.0}})


def test_sphere_cusp_within_bound_in_every_layer():
    """Each layer is the extrusion of its cut contour (a circle of the sphere's radius at
    the cutting height) from its bottom to its top; every point of that wall is within the
    cusp bound of the true sphere (distance along the normal, |sqrt(rho^2 + z^2) - R|),
    plus the facets' own sag (256 segments: R (1 - cos(pi / 256)) = 1.1 um)."""
    stack = slice_mesh(sphere_mesh(), ADAPTIVE)
    t = stack.thicknesses
    top = np.array([L.top_z for L in stack])
    bottom = top - t
    zc = np.array([L.z for L in stack]) - R
    rho = np.sqrt(np.maximum(R * R - zc * zc, 0.0))
    sag = R * (1 - math.cos(math.pi / 256))
    worst = 0.0
    for b, tp, r in zip(bottom, top, rho):
        z = np.linspace(b, tp, 50) - R
        worst = max(worst, float(np.abs(np.sqrt(r * r + z * z) - R).max()))
    assert worst <= CUSP + sag
    assert np.all(t <= 1.0 + 1e-12) and np.isclose(top[-1], 2 * R) and np.isclose(bottom[0], 0)
    np.testing.assert_allclose(bottom[1:], top[:-1], atol=1e-9)  # no gap, no overlap
    # uniform slicing needs C_max-thick layers for the poles: 600 of them
    rep = slice_report(stack)
    assert rep.uniform_layers == round(2 * R / CUSP)
    assert len(stack) < 0.75 * rep.uniform_layers
    assert rep.max_cusp_mm <= CUSP + 1e-12
    assert t.max() > 0.5  # near the equator the wall is steep: thick layers there


def test_top_layers_under_the_minimum_are_said():
    """The last two layers share what the part's height leaves when that is under two
    minimum layers (plan_layers keeps the cusp bound): the stack says so, with the layers
    and the thinnest (a tester's spot ended in two 0.08 mm layers under 0.1 mm, unsaid)."""
    job = job_from_dict({"slicing": {"cusp_height_mm": CUSP, "min_layer_thickness_mm": 0.1,
                                     "max_layer_thickness_mm": 1.0}})
    stack = slice_mesh(sphere_mesh(64), job)
    t = stack.thicknesses
    thin = np.flatnonzero(t < 0.1 - 1e-12)
    assert thin.tolist() == [len(t) - 2, len(t) - 1]
    (said,) = [w for w in stack.warnings if "adaptive layers thinner" in w]
    assert said.startswith(f"2 adaptive layers thinner than slicing.min_layer_thickness_mm "
                           f"= 0.1 (layers {len(t) - 2}-{len(t) - 1}, {t.min():.4g} mm")
    for other in (ADAPTIVE, ADAPTIVE.replace(**{"slicing.min_layer_thickness_mm": 0.02})):
        st = slice_mesh(sphere_mesh(64), other)         # said exactly when there are some
        under = (st.thicknesses < other.slicing.min_layer_thickness_mm - 1e-12).any()
        assert any("adaptive layers thinner" in w for w in st.warnings) == under


def test_flats_end_layers_and_vertical_walls_take_the_largest_thickness():
    """A 10 mm block under a 3 mm one: vertical walls need no thin layers, and the step's
    flat at z = 10 is a layer boundary."""
    mesh = mesh_of(m3.Manifold.cube([10.0, 10.0, 10.0])
                   + m3.Manifold.cube([5.0, 5.0, 3.0]).translate([0.0, 0.0, 10.0]))
    a = plan_layers(mesh, 0.0, 13.0, 0.05, 0.05, 1.0)
    np.testing.assert_allclose(a.edges, np.arange(14.0), atol=1e-9)
    assert a.cusp.max() == 0.0
    with pytest.raises(ValueError, match="t_min"):
        plan_layers(mesh, 0.0, 13.0, 0.05, 2.0, 1.0)


def _steps(widths, heights) -> tuple[Mesh, list[float]]:
    """Square boxes centred on the z axis stacked bottom up (each narrower than the one
    below; touching, as the reviewer's STL), and the heights of their tops under the last
    (the flats), mm. Built in float64 so the flats lie at exactly those heights (a
    manifold's float32 vertices put them 1e-7 mm off)."""
    cube = np.array([[x, y, z] for z in (0, 1) for y in (-1, 1) for x in (-1, 1)], float)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2),
             (1, 3, 7, 5)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], np.int64)
    vertices, faces, z, flats = [], [], 0.0, []
    for w, h in zip(widths, heights):
        v = cube * [w / 2, w / 2, 1.0]
        v[:, 2] = np.where(cube[:, 2] > 0, z + h, z)
        faces.append(tris + 8 * len(vertices))
        vertices.append(v)
        z = z + h
        flats.append(z)
    return Mesh(np.concatenate(vertices), np.concatenate(faces), name="steps"), flats[:-1]


def _flat_layers(edges, flats):
    """(k, thickness) of every layer with a flat strictly inside it."""
    return [(k, b1 - b0) for k, (b0, b1) in enumerate(zip(edges[:-1], edges[1:]))
            if any(b0 + 1e-9 < f < b1 - 1e-9 for f in flats)]


def test_a_flat_within_the_minimum_of_a_layers_bottom_caps_the_layer():
    """The reviewer's part: a 20 mm square 1 mm tall, a 14 mm step from 1.00 to 1.15 mm, an
    8 mm column to 5 mm; cusp 0.1, minimum 0.2, maximum 2 mm. The layer from 1 mm held the
    step's flat 0.15 mm above its bottom, took 2 mm and was cut at 2 mm: the step was lost
    (areas 400, 64, 64 mm^2) with a 2 mm cusp, unsaid. The flat counts like any facet: its
    layer is at most max(0.2, 0.1) mm, cut through the step, and the cusp the minimum
    leaves there (0.2 mm against 0.1 mm) is warned naming both settings."""
    mesh, flats = _steps([20.0, 14.0, 8.0], [1.0, 0.15, 3.85])
    a = plan_layers(mesh, 0.0, 5.0, 0.1, 0.2, 2.0)
    assert a.edges[:3] == pytest.approx([0.0, 1.0, 1.2])
    assert _flat_layers(a.edges, flats) == [(1, pytest.approx(0.2))]
    assert a.cusp.max() == pytest.approx(0.2)
    job = job_from_dict({"slicing": {"cusp_height_mm": 0.1, "min_layer_thickness_mm": 0.2,
                                     "max_layer_thickness_mm": 2.0}})
    stack = slice_mesh(mesh, job)
    assert [round(L.part.area) for L in stack][:3] == [400, 196, 64]
    (said,) = [w for w in stack.warnings if "cusp height above" in w]
    assert said.startswith("1 adaptive layers keep a cusp height above "
                           "slicing.cusp_height_mm = 0.1 (layers 1, 0.2 mm at the most): "
                           "slicing.min_layer_thickness_mm = 0.2 allows no thinner layer")
    # a minimum within the bound keeps it: no warning
    ok = slice_mesh(mesh, job.replace(**{"slicing.min_layer_thickness_mm": 0.05}))
    assert not any("cusp height above" in w for w in ok.warnings)
    assert slice_report(ok).max_cusp_mm <= 0.1


def test_a_layer_ends_the_minimum_below_a_flat_just_above_it():
    """A 2.1 mm block under a 1 mm one, layers up to 2 mm: the first layer took 2 mm and
    the next held the flat 0.1 mm above its bottom (a 1.1 mm cusp); ending the first
    0.2 mm below the flat lets the next, 0.2 mm, end on it: no cusp anywhere."""
    mesh, _ = _steps([10.0, 5.0], [2.1, 1.0])
    a = plan_layers(mesh, 0.0, 3.1, 0.1, 0.2, 2.0)
    np.testing.assert_allclose(a.edges, [0.0, 1.9, 2.1, 3.1], atol=1e-9)
    assert a.cusp.max() == 0.0


def test_a_cusp_bound_the_minimum_prevents_on_a_wall_is_warned():
    """A cone with cusp 0.05 and minimum 0.1 mm: its wall's layers keep 0.0857 mm; the
    summary said so with no warning."""
    cone = mesh_of(m3.Manifold.cylinder(6.0, 10.0, 0.0, 64))
    job = job_from_dict({"slicing": {"cusp_height_mm": 0.05, "min_layer_thickness_mm": 0.1,
                                     "max_layer_thickness_mm": 0.5}})
    stack = slice_mesh(cone, job)
    worst = slice_report(stack).max_cusp_mm
    assert worst > 0.05
    (said,) = [w for w in stack.warnings if "cusp height above" in w]
    assert f"{worst:.4g} mm at the most" in said and \
        "slicing.min_layer_thickness_mm = 0.1" in said and "slicing.cusp_height_mm = 0.05" in said
    fine = slice_mesh(cone, job.replace(**{"slicing.min_layer_thickness_mm": 0.05}))
    assert not any("cusp height above" in w for w in fine.warnings)


@settings(max_examples=60, deadline=None)
@given(steps=st.lists(st.tuples(st.integers(1, 300), st.integers(1, 5)), min_size=2,
                      max_size=5),
       cusp=st.integers(1, 50), t_min=st.integers(1, 50), spread=st.integers(0, 300))
def test_every_flat_inside_a_layer_caps_it_or_is_warned(steps, cusp, t_min, spread):
    """Random stepped parts (heights and settings in hundredths of a mm): every flat
    strictly between two layer edges leaves that layer no thicker than max(minimum, cusp)
    and counted in its cusp; a cusp above the bound comes only from a minimum above it,
    and is warned naming both settings."""
    from icefab.slicing import cusp_warnings

    heights = [k / 100 for k, _ in steps]
    widths = [40.0 - 6.0 * i - w for i, (_, w) in enumerate(steps)]
    mesh, flats = _steps(widths, heights)
    c, lo = cusp / 100, t_min / 100
    a = plan_layers(mesh, 0.0, float(sum(heights)), c, lo, lo + spread / 100)
    assert np.all(np.diff(a.edges) > 0) and a.edges[-1] == pytest.approx(sum(heights))
    for k, t in _flat_layers(a.edges, flats):
        assert t <= max(lo, c) + 1e-9, (k, t)
        assert a.cusp[k] == pytest.approx(t)
    job = job_from_dict({"slicing": {"cusp_height_mm": c, "min_layer_thickness_mm": lo,
                                     "max_layer_thickness_mm": lo + spread / 100}})
    said = cusp_warnings(a.cusp, job)
    assert bool(said) == bool(a.cusp.max() > c * (1 + 1e-9))
    if said:
        assert lo > c and f"slicing.min_layer_thickness_mm = {lo:g}" in said[0]


def test_default_is_uniform_and_settings_are_checked():
    stack = slice_mesh(sphere_mesh(64), Job())
    assert np.isnan([L.thickness for L in stack]).all()
    assert len(stack) == round(2 * R / 0.25)
    with pytest.raises(ConfigError, match="slicing.min_layer_thickness_mm = 0.5 must not "
                                          "exceed"):
        job_from_dict({"slicing": {"cusp_height_mm": 0.1, "min_layer_thickness_mm": 0.5}})
    with pytest.raises(ConfigError, match="slicing.cusp_height_mm"):
        job_from_dict({"slicing": {"cusp_height_mm": -1.0}})


def test_measurement_schedule_is_by_height():
    job = Job()  # interval_layers 4 x 0.25 mm = 1 mm
    n = job.feedback.interval_layers
    uniform = measured_layers([math.nan] * 12, job)
    assert uniform == [(k + 1) % n == 0 for k in range(12)]
    # 0.1 mm layers then 0.5 mm: measured when the height crosses 1, 2, 3 mm
    t = [0.1] * 10 + [0.5] * 4
    flags = measured_layers(t, job)
    h = np.cumsum(t)
    assert [round(float(x), 6) for x in h[np.array(flags)]] == [1.0, 2.0, 3.0]


@pytest.fixture(scope="module")
def adaptive_build():
    job = job_from_dict({"slicing": {"cusp_height_mm": CUSP, "min_layer_thickness_mm": CUSP},
                         "scaffold": {"mode": "overhang"}})
    stack = add_scaffold(slice_mesh(sphere_mesh(96), job), job)
    tp = plan_paths(stack, job)
    motion = plan_toolpaths(tp, job)
    return job, stack, tp, motion


def test_thickness_travels_through_the_files(adaptive_build, tmp_path):
    job, stack, tp, motion = adaptive_build
    t = stack.thicknesses
    assert t.min() < 0.1 and t.max() == pytest.approx(0.25)
    save_stack(stack, tmp_path / "stack.npz")
    save_toolpaths(tp, tmp_path / "toolpaths.npz")
    save_trajectories(motion, tmp_path / "trajectories.npz")
    np.testing.assert_array_equal(load_stack(tmp_path / "stack.npz").thicknesses, t)
    np.testing.assert_array_equal([lp.thickness for lp in
                                   load_toolpaths(tmp_path / "toolpaths.npz").layers], t)
    np.testing.assert_array_equal([lm.thickness for lm in
                                   load_trajectories(tmp_path / "trajectories.npz").layers], t)
    with np.load(tmp_path / "stack.npz") as f:
        members = dict(f)
    members["layer_height"] = -members["layer_height"]
    np.savez(tmp_path / "bad.npz", **members)
    with pytest.raises(StackFileError, match="member layer_height"):
        load_stack(tmp_path / "bad.npz")


def test_measurement_paths_every_millimetre_of_height(adaptive_build):
    job, stack, tp, _ = adaptive_build
    measured = [any(p.role == "measure" for p in lp.paths) for lp in tp.layers]
    height = np.cumsum(stack.thicknesses)
    step = job.feedback.interval_layers * job.slicing.layer_thickness_mm
    crossed = np.floor(height / step + 1e-9)
    due = crossed > np.r_[0.0, crossed[:-1]]
    assert due.sum() == int(np.floor(height[-1] / step + 1e-9)) == 30
    # measured exactly where due, but for a layer too small to hold a measurement ring
    # (the top of the sphere: a 1.5 mm wide square)
    for k, (m, d) in enumerate(zip(measured, due)):
        assert m == d or (d and stack[k].part.area < 2.0), k


def test_valve_flow_uses_the_layer_thickness(adaptive_build):
    """q = w * dh_k * c (eq. 6.2) with each layer's own dh_k: the flow per mm of path of a
    thin layer's trajectory over the path width (each sample's, for a variable-width
    path) is that layer's thickness."""
    from icefab.flow import sample_widths
    job, stack, _, motion = adaptive_build
    thin = min(motion.layers, key=lambda lm: lm.thickness)
    traj = next(t for t in thin.trajectories if t.path is not None and t.path.depositing)
    plan = valve_frequency(traj, traj.path.material, job, layer_thickness=thin.thickness)
    moving = traj.speed > 1.0
    w = sample_widths(traj, traj.path.material, job)
    dh = plan.q[moving] / (w[moving] * traj.speed[moving])
    np.testing.assert_allclose(dh, thin.thickness, rtol=1e-9)
    assert thin.thickness < 0.5 * job.slicing.layer_thickness_mm


def test_simulated_surface_follows_the_thin_layers(adaptive_build):
    """Open loop, no disturbances: the simulated part's top after each measured layer lies
    at the summed thicknesses (not k x 0.25 mm)."""
    job, stack, _, motion = adaptive_build
    quiet = job_from_dict({**_as_dict(job), "simulation": {
        "noise_mm": 0.0, "debris_rate": 0.0, "flow_error": 0.0, "flow_drift_per_cm3": 0.0,
        "edge_loss": 0.0, "spread_mm": 0.5, "laser_noise_mm": 0.0}})
    n = 70
    res = simulate_build(motion, quiet, layers=n, closed_loop=False)
    heights = np.cumsum(stack.thicknesses[:n])
    assert len(res.layers) >= 3
    for index, nominal in zip(res.layers, res.nominal_z):
        assert nominal == pytest.approx(heights[int(index)])
    # the deposited volume follows the thin layers too: the true surface stays within a
    # default layer (0.25 mm) of those heights (had the flow used 0.25 mm per layer, the
    # part would stand 4-5 times too tall here)
    assert np.nanmax(res.rms) < 0.25


def _as_dict(job):
    from icefab.config import to_dict
    return to_dict(job)


def test_slice_cli_reports_the_layers_saved(tmp_path):
    path = tmp_path / "sphere.stl"
    import trimesh
    m = sphere_mesh(64)
    trimesh.Trimesh(m.vertices, m.faces).export(path)
    job = tmp_path / "job.toml"
    job.write_text("[slicing]\ncusp_height_mm = 0.05\nmin_layer_thickness_mm = 0.05\n"
                   "max_layer_thickness_mm = 1.0\n[parts]\ntranslation = [0.0, 0.0, 0.0]\n")
    r = subprocess.run([sys.executable, "-m", "icefab", "slice", str(path), "-c", str(job),
                        "-o", str(tmp_path / "out")], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "(adaptive)" in r.stdout and "uniform layers thin enough" in r.stdout


def test_valves_command_uses_each_layer_thickness(adaptive_build, tmp_path):
    """``icefab valves`` on adaptive trajectories: a layer's pulses (FM: frequency follows
    the flow q = w dh_k c) scale with its own thickness against the same trajectories
    taken as uniform 0.25 mm layers (the layer_height member removed)."""
    import csv
    job, stack, _, motion = adaptive_build
    save_trajectories(motion, tmp_path / "adaptive.npz")
    with np.load(tmp_path / "adaptive.npz") as f:
        members = {k: v for k, v in f.items() if k != "layer_height"}
    np.savez_compressed(tmp_path / "uniform.npz", **members)
    pulses = {}
    for name in ("adaptive", "uniform"):
        r = subprocess.run([sys.executable, "-m", "icefab", "valves", str(tmp_path /
                            f"{name}.npz"), "-o", str(tmp_path / name), "--layers", "0,1,150"],
                           capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        with open(tmp_path / name / "valves-paths.csv", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        per, paths = {}, {}
        for row in rows:
            per[int(row["layer"])] = per.get(int(row["layer"]), 0) + int(row["pulses"])
            paths[int(row["layer"])] = paths.get(int(row["layer"]), 0) + 1
        pulses[name] = per
    for k, n in pulses["adaptive"].items():
        # each path's pulse count is a whole number: it misses its share by under one
        # pulse, in both runs (a thin layer's few dozen pulses: several per cent)
        r = stack.thicknesses[k] / 0.25
        assert abs(n - r * pulses["uniform"][k]) <= (1.0 + r) * paths[k], k
        assert n / pulses["uniform"][k] == pytest.approx(r, rel=0.1), k
