"""Work estimates refuse what the cell cannot build, or absurd work, before it starts
(issue 10: a vertex at z = 1e9 was a 29.8 GiB allocation; a 2 m model ran for minutes; a
1.7 mm model sliced into 7 layers without a word)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from icefab import Job
from icefab.errors import ConfigError, SimulationError, WorkspaceError
from icefab.mesh import load_mesh, prepare_parts, transform, write_stl
from icefab.slicing import slice_mesh
from icefab.core import Mesh
from icefab import workload


def _box(extents, centre=(0.0, 0.0, 0.0)) -> Mesh:
    b = trimesh.creation.box(extents=extents)
    v = np.asarray(b.vertices) + np.asarray(centre) + [0, 0, extents[2] / 2]
    return Mesh(v, np.asarray(b.faces, np.int64), "box")


def _job_for(tmp_path, mesh, **settings) -> Job:
    f = tmp_path / "part.stl"
    write_stl(mesh, f)
    return Job().replace(**{"parts.files": [str(f)], **settings})


def test_a_stray_vertex_at_1e9_is_refused_before_slicing():
    m = _box((40, 40, 40))
    v = m.vertices.copy()
    v[0, 2] = 1e9
    with pytest.raises(ConfigError, match="would make 4e\\+09 layers, more than 500000"):
        slice_mesh(Mesh(v, m.faces, "tall"), Job())


def test_a_bit_flipped_stl_exponent_is_refused_in_one_line(tmp_path):
    f = tmp_path / "flip.stl"
    write_stl(_box((40, 40, 40)), f)
    data = bytearray(f.read_bytes())
    corners = np.frombuffer(bytes(data[84:]), np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)),
                                                        ("a", "<u2")]))["v"]
    facet, corner = np.argwhere(corners[:, :, 2] == 40.0)[0]
    at = 84 + 50 * facet + 12 + 12 * corner + 8  # that corner's z, little-endian float32
    data[at + 3] ^= 0x20  # one exponent bit: 40 -> 40 * 2**64
    f.write_bytes(bytes(data))
    z = float(np.frombuffer(bytes(data[at:at + 4]), "<f4")[0])
    assert abs(z) > 1e20
    job = Job().replace(**{"parts.files": [str(f)]})
    with pytest.raises(WorkspaceError, match="mm tall .*a stray vertex.*cell.stroke_mm = 210"):
        prepare_parts(job)


def test_a_2_m_part_is_taller_than_the_stroke(tmp_path):
    job = _job_for(tmp_path, _box((50, 50, 2000)))
    with pytest.raises(WorkspaceError, match="2000 mm tall.*cell.stroke_mm = 210"):
        prepare_parts(job)
    # the same part sliced in part fits: the setting named in the message works
    short = job.replace(**{"parts.part_fraction": [0.0, 0.1]})
    assert prepare_parts(short).bounds[1, 2] == pytest.approx(2000)


def test_a_flat_part_wider_than_the_reach_is_refused(tmp_path):
    job = _job_for(tmp_path, _box((2000, 2000, 10)))
    with pytest.raises(WorkspaceError, match="beyond the reach cell.reach_mm"):
        prepare_parts(job)


def test_a_part_over_the_robot_base_is_inside_the_minimum_reach(tmp_path):
    # the default part origin is (260, -100) in the base frame: a part placed at
    # (-260, 100) sits on the base
    job = _job_for(tmp_path, _box((20, 20, 10)), **{"parts.translation": [-270.0, 90.0, 0.0]})
    with pytest.raises(WorkspaceError, match="inside the minimum reach"):
        prepare_parts(job)


def test_a_part_behind_the_robot_is_refused_before_slicing(tmp_path):
    """Every point within the reach, but joint 1 would need 129 degrees (range +-105): the
    part passed 'icefab slice' and only 'icefab paths' refused it (a hunt's)."""
    job = _job_for(tmp_path, _box((12, 12, 1)), **{
        "cell.ee_origin_mm": [-300.0, 0.0], "slicing.layer_thickness_mm": 0.5})
    with pytest.raises(WorkspaceError, match=r"joint 1 at 1[23]\d\.\d+ deg .* beyond its "
                                             r"range \+/-105 deg"):
        prepare_parts(job)


def test_an_edge_through_the_minimum_reach_is_refused_before_slicing(tmp_path):
    """A triangle whose three corners lie outside the 163 mm minimum reach while an edge
    passes 127 mm from the base (a hunt's); the same triangle moved out is accepted."""
    from shapely.geometry import Polygon

    tri = trimesh.creation.extrude_polygon(Polygon([(200, -20), (300, 300), (-20, 200)]), 1.0)
    mesh = Mesh(np.asarray(tri.vertices), np.asarray(tri.faces, np.int64), "triangle")
    at = {"parts.translation": ["orig", "orig", 0.0], "cell.ee_origin_mm": [0.0, 0.0],
          "feedback.enabled": False, "scaffold.enabled": False,
          "slicing.layer_thickness_mm": 0.5}
    assert min(np.hypot(*mesh.vertices[:, :2].T)) > 163.0
    with pytest.raises(WorkspaceError, match=r"within 127\.\d mm of the robot base along an "
                                             r"edge.*minimum reach"):
        prepare_parts(_job_for(tmp_path, mesh, **at))
    prepare_parts(_job_for(tmp_path, mesh, **{**at, "cell.ee_origin_mm": [60.0, 60.0]}))


def test_a_part_over_the_robot_base_is_refused_with_every_edge_outside_the_reach(tmp_path):
    """An equilateral plate around the base axis: corners at 340 mm, edges 170 mm from it
    (outside the 163 mm minimum reach), a joint 1 that turns all the way round: the
    vertex, edge and joint checks pass it, its section holds the base axis."""
    from shapely.geometry import Polygon

    r = 340.0
    tri = Polygon([(r * np.cos(a), r * np.sin(a)) for a in np.radians([90, 210, 330])])
    plate = trimesh.creation.extrude_polygon(tri, 1.0)
    mesh = Mesh(np.asarray(plate.vertices), np.asarray(plate.faces, np.int64), "plate")
    job = _job_for(tmp_path, mesh, **{
        "parts.translation": ["orig", "orig", 0.0], "cell.ee_origin_mm": [0.0, 0.0],
        "cell.joint_range_deg": [180.0, 150.0], "feedback.enabled": False,
        "scaffold.enabled": False, "slicing.layer_thickness_mm": 0.5})
    with pytest.raises(WorkspaceError, match="lies over the robot base"):
        prepare_parts(job)


def test_a_gantry_part_outside_its_travel_is_refused(tmp_path):
    job = _job_for(tmp_path, _box((500, 50, 10)), **{"cell.robot": "gantry"})
    with pytest.raises(WorkspaceError, match="outside its travel cell.gantry_travel_mm"):
        prepare_parts(job)
    # a part inside the travel whose scaffold is not: the message says the scaffold
    # reaches out, not that a point inside the travel is outside it
    small = _job_for(tmp_path, _box((50, 50, 10)), **{
        "cell.robot": "gantry", "cell.gantry_travel_mm": [52.0, 52.0],
        "cell.ee_origin_mm": [26.0, 26.0]})
    with pytest.raises(WorkspaceError, match=r"with the scaffold around it \(scaffold.buffer_mm "
                       r"= 3.3\): part point .* and the scaffold reaches 3.3 mm beyond it, "
                       r"outside its travel .* \(0 to 52 x 0 to 52 mm"):
        prepare_parts(small)


def test_a_part_the_laser_cannot_reach_is_refused_before_slicing(tmp_path):
    # the nozzles reach it, the laser (offset [-30, 19] in the EE frame) does not: the
    # paths stage refused a measurement path after every layer's scaffold, naming no laser
    job = _job_for(tmp_path, _box((20, 20, 3)), **{"parts.translation": [300.0, "cent", 0.0]})
    with pytest.raises(WorkspaceError, match=r"under the laser \(cell.laser_offset_mm = "
                       r"\[-30.0, 19.0\]; feedback.enabled measures it\) reaches .* beyond "
                       r"the reach"):
        prepare_parts(job)
    prepare_parts(job.replace(**{"feedback.enabled": False}))   # no laser: it fits


def test_a_fraction_thinner_than_a_layer_names_the_fraction(tmp_path):
    # a 3 mm box at part_fraction [0.99, 1]: the message blamed parts.scale
    job = _job_for(tmp_path, _box((20, 20, 3)), **{"parts.part_fraction": [0.99, 1.0]})
    with pytest.raises(ConfigError, match=r"parts.part_fraction = \[0.99, 1.0\]: the slice of "
                       r"the 3 mm tall part to build is 0.03 mm tall, less than one layer"):
        prepare_parts(job)


def test_a_file_in_metres_is_refused_with_the_scale_to_set(tmp_path):
    job = _job_for(tmp_path, _box((0.08, 0.08, 0.1)))
    with pytest.raises(ConfigError, match=r"file in metres or inches\? set parts.scale"):
        prepare_parts(job)
    ok = job.replace(**{"parts.scale": [1000.0, 1000.0, 1000.0]})
    assert prepare_parts(ok).bounds[1, 2] == pytest.approx(100.0)


def test_the_demo_mug_and_the_thesis_defaults_pass(tmp_path):
    import icefab
    job = _job_for(tmp_path, icefab.demo_mug())
    placed = prepare_parts(job)
    workload.check_placed_part(placed.vertices, job)


def test_a_part_placed_above_the_stroke_or_below_the_plate_is_refused(tmp_path):
    """Its height fits the stroke, its place does not: at z = 180 mm a 60 mm part passed
    slicing and paths (a tester's spot) and stopped at 'icefab build'; kept at its file's
    coordinates it went 30 mm below the plate, into the G-code too."""
    job = _job_for(tmp_path, _box((60, 60, 60)))
    high = job.replace(**{"parts.translation": ["cent", "cent", 180.0]})
    with pytest.raises(WorkspaceError, match=r"spans z 180 to 240 mm, above the vertical "
                                             r"stroke cell.stroke_mm = 210"):
        prepare_parts(high)
    low = job.replace(**{"parts.translation": ["cent", "cent", -30.0]})
    with pytest.raises(WorkspaceError, match=r"spans z -30 to 30 mm, below the build plate"):
        prepare_parts(low)
    assert prepare_parts(job.replace(**{"parts.translation": ["cent", "cent", 150.0]})
                         ).bounds[1, 2] == pytest.approx(210.0)


def test_copies_wider_than_the_workspace_are_refused_before_copying():
    job = Job().replace(**{"parts.copies": [100, 100, 100]})
    big = _box((80, 80, 100))
    with pytest.raises(WorkspaceError, match="parts.copies = \\[100, 100, 100\\]: the grid"):
        transform(big, job.parts, job)
    small = transform(big, Job().replace(**{"parts.copies": [2, 2, 3]}).parts)
    assert len(small.faces) == 3 * len(big.faces)


def test_grid_budget_names_the_setting():
    with pytest.raises(SimulationError, match="simulation.grid_mm = 0.05: a 600 x 600 mm grid"):
        workload.check_grid(np.zeros(2), np.array([600.0, 600.0]), 0.05, "simulation.grid_mm")
    workload.check_grid(np.zeros(2), np.array([200.0, 200.0]), 0.05, "simulation.grid_mm")


def test_motion_budget_counts_both_spacings():
    job = Job()
    workload.check_motion(1e6, 1e5, job)  # 1 km of paths at the defaults: fine
    slow = job.replace(**{"motion.speed_mm_s": 1.0, "motion.dt_s": 0.001})
    with pytest.raises(ConfigError, match="motion.dt_s = 0.001 with motion.speed_mm_s = 1"):
        workload.check_motion(1e6, 1e5, slow)
    fine = job.replace(**{"motion.point_spacing_mm": 0.01})
    with pytest.raises(ConfigError, match="motion.point_spacing_mm = 0.01"):
        workload.check_motion(1e6, 0.0, fine)


def test_paths_budget_refuses_hairline_fill_before_planning():
    job = Job()
    workload.check_paths((2.5e6, 2.5e6), job)  # about the demo mug's 500 layers
    workload.check_paths((2e7, 2e7), job)      # 8x the mug's area at the default widths
    hairline = job.replace(**{"materials.part.fill_width_mm": 0.5,
                              "materials.scaffold.fill_width_mm": 0.5})
    with pytest.raises(ConfigError, match=r"materials.\*.fill_width_mm = 0.5 / 0.5: .* m of "
                                          "fill paths"):
        workload.check_paths((2e7, 2e7), hairline)


def test_a_part_thinner_than_one_layer_is_refused(tmp_path):
    # bench/settings_walk.py: parts.scale z at 1e-4 made the demo mug 0.0125 mm tall and the
    # demo failed with an IndexError after slicing one layer
    job = _job_for(tmp_path, _box((40, 40, 40)), **{"parts.scale": [1.0, 1.0, 1e-4]})
    with pytest.raises(ConfigError, match="0.004 mm tall, less than one layer"):
        prepare_parts(job)


def test_an_adaptive_part_thinner_than_one_layer_but_not_the_minimum_is_sliced(tmp_path):
    """With adaptive layers the thinnest layer is slicing.min_layer_thickness_mm: a 0.2 mm
    plate (minimum 0.1 mm) was refused as under one slicing.layer_thickness_mm = 0.25 mm
    layer; under the minimum it is refused naming the minimum."""
    adaptive = {"slicing.cusp_height_mm": 0.1, "slicing.min_layer_thickness_mm": 0.1,
                "slicing.max_layer_thickness_mm": 0.5}
    job = _job_for(tmp_path, _box((20, 20, 0.2)), **adaptive)
    stack = slice_mesh(prepare_parts(job), job)
    assert len(stack) == 1 and stack.thicknesses[0] == pytest.approx(0.2)
    thin = _job_for(tmp_path, _box((20, 20, 0.08)), **adaptive)
    with pytest.raises(ConfigError, match=r"0.08 mm tall, less than one layer "
                                          r"\(slicing.min_layer_thickness_mm = 0.1\)"):
        prepare_parts(thin)
    with pytest.raises(ConfigError, match=r"less than one layer "
                                          r"\(slicing.layer_thickness_mm = 0.25\)"):
        prepare_parts(_job_for(tmp_path, _box((20, 20, 0.2))))   # uniform: one 0.25 mm


def test_the_scaffold_buffer_counts_in_the_reach(tmp_path):
    """A 40 mm box at the default origin fits; surrounded by a 100 mm scaffold it reaches
    inside the minimum reach (the scaffold nozzle lays it there): refused before slicing,
    naming scaffold.buffer_mm; without the scaffold the same buffer is harmless."""
    box = _box((40, 40, 10))
    prepare_parts(_job_for(tmp_path, box))
    with pytest.raises(WorkspaceError, match=r"with the scaffold around it "
                                             r"\(scaffold.buffer_mm = 100\)"):
        prepare_parts(_job_for(tmp_path, box, **{"scaffold.buffer_mm": 100.0}))
    prepare_parts(_job_for(tmp_path, box, **{"scaffold.buffer_mm": 100.0,
                                              "scaffold.enabled": False}))


def test_valve_pulse_budget_names_the_frequency():
    """Pulses counted at the highest rate the valve is driven, before any program: a
    500 s path at a 50 kHz PWM would be 2.5e7 pulses on one path; 30 000 paths of 20 s at
    1 kHz are 6e8 in the build."""
    from icefab.core import LayerMotion, Toolpath, Trajectory

    def layer(durations):
        path = Toolpath(points=np.zeros((2, 2)), role="fill", width=1.5)
        return LayerMotion(0, 0.125, tuple(
            Trajectory(dt=d, xy=np.zeros((2, 2)), joints=np.zeros((2, 0)),
                       speed=np.zeros(2), duration=d, path=path) for d in durations))

    workload.check_pulses([layer([100.0] * 10)], Job())
    fast = Job().replace(**{"flow.mode": "pwm", "flow.pwm_frequency_hz": 5e4,
                            "flow.max_frequency_hz": 1e5, "flow.tick_s": 1e-5,
                            "flow.min_pulse_ms": 0.01})
    with pytest.raises(ConfigError, match="flow.pwm_frequency_hz = 50000: the longest"):
        workload.check_pulses([layer([500.0])], fast)
    many = Job().replace(**{"flow.max_frequency_hz": 1000.0, "flow.tick_s": 1e-3,
                            "flow.calibration_pulse_ms": 0.5})
    with pytest.raises(ConfigError, match="MAX_BUILD_PULSES"):
        workload.check_pulses([layer([20.0] * 30000)], many)


def test_streamed_budget_is_per_layer_and_larger_for_the_build():
    from icefab.motion import _checked_items
    job = Job()
    # six layers of a quarter of MAX_SAMPLES each: refused in memory, fine as a stream;
    # one layer over MAX_SAMPLES is refused by name; 60 layers exceed the streamed budget
    th = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    ring = np.c_[50 * np.cos(th), 50 * np.sin(th)]
    per_layer = 2 * np.pi * 50  # mm
    n_laps = int(workload.MAX_SAMPLES * job.motion.point_spacing_mm / per_layer / 4)
    from icefab import LayerPaths, Toolpath, Toolpaths
    laps = Toolpath(points=np.tile(ring, (n_laps, 1)), role="fill", width=1.5, closed=False,
                    z=0.25)
    tp = Toolpaths(layers=tuple(LayerPaths(index=k, z=0.25 * (k + 1), paths=(laps,))
                                for k in range(6)), job=job)
    with pytest.raises(ConfigError, match=r"the build would need .* \(icefab.workload.MAX_SAMPLES\)"):
        _checked_items(tp, job, None)
    assert len(_checked_items(tp, job, None, streamed=True)) == 6
    big = Toolpaths(layers=(LayerPaths(index=7, z=0.25, paths=(
        Toolpath(points=np.tile(ring, (5 * n_laps, 1)), role="fill", width=1.5, z=0.25),)),),
        job=job)
    with pytest.raises(ConfigError, match=r"layer 7 would need .* \(icefab.workload.MAX_SAMPLES\)"):
        _checked_items(big, job, None, streamed=True)
    many = Toolpaths(layers=tp.layers * 10, job=job)
    with pytest.raises(ConfigError, match=r"MAX_STREAMED_SAMPLES"):
        _checked_items(many, job, None, streamed=True)


def _scaffold_joint1_reference(poly: np.ndarray, rho: float, job: Job) -> float:
    """Largest |joint 1| (rad) along the scaffold's outline: the part's outline ``poly``
    (part frame, CCW) offset by ``rho`` mm as the scaffold's wall is (Clipper's mitred
    offset, geometry.expand), densely sampled, under the scaffold nozzle."""
    from icefab import geometry as geo
    from icefab.frames import to_base_frame
    from icefab.robots import get_robot

    wall = geo.expand(geo.region_from_rings([poly]), rho, 0.0)
    ring = np.vstack([wall.rings[0], wall.rings[0][:1]])
    seg = np.diff(ring, axis=0)
    n = np.maximum(np.ceil(np.hypot(seg[:, 0], seg[:, 1]) / 0.05), 1).astype(int)
    pts = np.concatenate([ring[i] + np.linspace(0, 1, k, endpoint=False)[:, None] * seg[i]
                          for i, k in enumerate(n)])
    base = to_base_frame(pts, "scaffold", job)
    return float(np.abs(get_robot(job).ik(base)[:, 0]).max())


@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.floats(340.0, 420.0), st.floats(-0.5, 0.5), st.sampled_from([-1.0, 1.0]),
       st.floats(5.0, 30.0), st.floats(2.0, 30.0), st.floats(0.0, np.pi),
       st.floats(3.0, 60.0), st.booleans())
def test_the_scaffold_joint_1_check_agrees_with_its_mitred_wall(r0, dphi, side, w, d, rot,
                                                                 buffer, triangle):
    """The slicer's joint-1 check of the scaffold against the mitred outline the paths
    stage lays (hunt Q: a box's scaffold 100 mm out passed the slicer's check and only
    'icefab paths' refused it). It must never refuse a scaffold within joint 1's range
    (the paths stage would lay it), and must refuse one more than 1 degree beyond it."""
    from icefab.robots import get_robot

    job = Job().replace(**{"scaffold.buffer_mm": buffer, "feedback.enabled": False,
                           "cell.ee_origin_mm": (0.0, 0.0)})
    robot = get_robot(job)
    lim = float(robot.joint_range[0])
    f0 = float(robot.ik(np.array([[r0, 0.0]]))[0, 0])
    phi = side * lim - f0 + dphi          # joint 1 near its limit at radius r0
    if triangle:
        poly = np.array([[0.0, 0.0], [w, 0.0], [0.3 * w, d]])
    else:
        poly = np.array([[0.0, 0.0], [w, 0.0], [w, d], [0.0, d]])
    c, s = np.cos(rot), np.sin(rot)
    poly = (poly - poly.mean(axis=0)) @ np.array([[c, s], [-s, c]])
    poly = poly + r0 * np.array([np.cos(phi), np.sin(phi)])
    verts = np.vstack([np.c_[poly, np.zeros(len(poly))], np.c_[poly, np.full(len(poly), 2.0)]])
    tm = trimesh.convex.convex_hull(verts)
    mat = job.materials.scaffold
    rho = buffer - mat.initial_offset_mm - mat.path_width_mm
    try:
        workload.check_placed_part(np.asarray(tm.vertices), job, np.asarray(tm.faces))
        refused = None
    except WorkspaceError as e:
        refused = str(e)
    part_max = float(np.abs(robot.ik(poly)[:, 0]).max())   # the water nozzle's own
    assume(part_max < lim - 0.05 and (refused is None or "scaffold" in refused))
    worst = _scaffold_joint1_reference(poly, rho, job) if rho > 0 else part_max
    if refused is not None:
        assert "joint 1" in refused and worst > lim, refused
    else:
        assert worst <= lim + np.radians(1.0), (np.degrees(worst), np.degrees(lim))
