"""MTTS trajectories (thesis Ch. 4): bounds, exact path following, rests at corners,
joint limits near the reach boundary (Fig. 4-9), analytic durations."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import shapely

from icefab import Job, Toolpath
from icefab.errors import IcefabError, WorkspaceError
from icefab.motion import (constant_spacing, followed_path, gcode_moves, pathsplit,
                           plan_motion, plan_paths_motion, thesis_test_path)
from icefab.robots import Scara, get_robot

from _polylines import zigzag

log = logging.getLogger(__name__)

#: Inputs kept with the tests (tests/data).
DATA = Path(__file__).parent / "data"
JOB = Job()
JOB_NOJERK = JOB.replace(**{"motion.jerk_limited": False})
JOB_RAW = JOB.replace(**{"motion.smoothing_tolerance_mm": 0.0})  # path smoothing off
#: issue 4: "the sampled trajectory follows the path within 0.02 mm" (the user's path)
FOLLOW_MM = 0.02
WELL = (250.0, -80.0)  # thesis Fig. 4-3, well placed


def poorly_placed_offset() -> tuple[float, float]:
    """Offset putting the test path's farthest point 1 mm inside the maximum reach."""
    p = thesis_test_path()
    lo, hi = 300.0, 560.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        r = np.hypot(p[:, 0] + mid, p[:, 1] - 30.0).max()
        lo, hi = (mid, hi) if r < 599.0 else (lo, mid)
    return (lo, -30.0)


POOR = poorly_placed_offset()


def check_trajectory(tr, pts, job, robot=None, *, vcap=None, follow_mm=FOLLOW_MM):
    """The bounds of the issue; returns jerk statistics (mm/s^3). follow_mm: how close to
    the input path the samples and the joints' positions must be (the issue's 0.02 mm;
    more only for tests that ask for a looser smoothing tolerance)."""
    robot = robot or get_robot(job)
    m = job.motion
    dt = tr.dt
    assert dt == m.dt_s
    n = len(tr.xy)
    assert tr.joints.shape[0] == n and len(tr.speed) == n
    assert abs(tr.duration - (n - 1) * dt) < 1e-9
    # follows the INPUT path within 0.02 mm (issue 4): the samples and the joints' forward
    # kinematics (Savitzky-Golay smoothed); the samples also within the smoothing
    # tolerance (a hard bound: on the path itself with smoothing off)
    tol = m.smoothing_tolerance_mm
    line = shapely.LineString(pts) if len(pts) > 1 else shapely.Point(pts[0])
    d_xy = shapely.distance(shapely.points(tr.xy), line)
    d_q = shapely.distance(shapely.points(robot.fk(tr.joints)), line)
    assert d_xy.max() <= min(tol, follow_mm) + 1e-9, (d_xy.max(), tol)
    assert d_q.max() <= follow_mm + 1e-9, d_q.max()
    if tol > 0 and len(pts) > 1:  # the samples lie on the smoothed path they follow
        followed = shapely.MultiLineString(followed_path(pts, job))
        assert shapely.distance(shapely.points(tr.xy), followed).max() < 1e-3
    # starts and ends on the path's ends, at rest
    np.testing.assert_allclose(tr.xy[0], pts[0], atol=1e-9)
    np.testing.assert_allclose(tr.xy[-1], pts[-1], atol=1e-9)
    assert tr.speed[0] == 0.0 and tr.speed[-1] == 0.0
    # finite-difference speed, total acceleration, joint speeds
    v = np.hypot(*np.diff(tr.xy, axis=0).T) / dt
    assert v.max() <= (vcap or m.speed_mm_s) * 1.01
    acc = np.hypot(*np.diff(tr.xy, 2, axis=0).T) / dt ** 2 if n > 2 else np.zeros(1)
    assert acc.max() <= m.accel_mm_s2 * 1.10, acc.max()
    qd = np.abs(np.diff(tr.joints, axis=0)) / dt
    lim = robot.joint_speed_max
    fin = np.isfinite(lim)
    assert (qd[:, fin] <= lim[fin] * 1.02).all(), (qd.max(axis=0), lim)
    jerk = np.hypot(*np.diff(tr.xy, 3, axis=0).T) / dt ** 3 if n > 3 else np.zeros(1)
    stats = {"max": float(jerk.max()), "p99": float(np.percentile(jerk, 99)),
             "over": float(np.mean(jerk > m.jerk_mm_s3 * 1.2))}
    log.info("jerk mm/s^3: max %.0f p99 %.0f, %.1f %% of steps above bound + 20 %%",
             stats["max"], stats["p99"], 100 * stats["over"])
    return stats


# --------------------------------------------------------------------------- shapes


@pytest.mark.parametrize("settings, pts", [
    ({"motion.accel_mm_s2": 1.0}, [[300.0, -60.0], [300.0, 40.0]]),
    ({"motion.accel_mm_s2": 50.0}, [[300.0, -60.0], [300.0, 40.0]]),
    ({"motion.rest_accel_mm_s2": 1e6}, [[300.0, -60.0], [320.0, -60.0], [300.0, -59.8]])])
def test_the_rest_curves_keep_the_acceleration_bound(settings, pts):
    # the rest curves started at rest_accel_mm_s2 whatever accel_mm_s2 (a tester's: 2.6
    # times the bound at accel 1 mm/s^2, 2.1 times with rest_accel 1e6); both in range
    job = Job().replace(**settings)
    check_trajectory(plan_motion(np.array(pts), job), np.array(pts), job)


@pytest.mark.parametrize("settings", [{"motion.point_spacing_mm": 1.0},
                                      {"motion.dt_s": 0.1}])
def test_the_ends_of_the_grid_and_step_ranges_keep_the_bounds(settings):
    # a tester's: a 10 mm grid planned 1.8 times the acceleration bound on a straight line,
    # a 1 s step planned a 31 mm ring as one point; the ranges end where the bounds hold
    from icefab.errors import ConfigError

    job = Job().replace(**settings)
    t = np.linspace(0.0, 2.0 * np.pi, 100, endpoint=False)
    for pts in (np.array([[300.0, -60.0], [400.0, -60.0]]),
                np.c_[300.0 + 5.0 * np.cos(t), -60.0 + 5.0 * np.sin(t)]):
        tr = plan_motion(pts, job)
        check_trajectory(tr, pts, job)
        chords = np.hypot(*np.diff(tr.xy, axis=0).T).sum()
        assert chords > 0.9 * np.hypot(*np.diff(pts, axis=0).T).sum()
    (name, value), = settings.items()
    with pytest.raises(ConfigError, match=f"{name} = {2 * value!r}: must be"):
        Job().replace(**{name: 2 * value})


def test_straight_line_trapezoid_duration():
    # far from singularities the joint bounds do not bind: T = L/V + V/A (jerk off)
    pts = np.array([[250.0, -150.0], [250.0, 50.0]])
    tr = plan_motion(pts, JOB_NOJERK)
    check_trajectory(tr, pts, JOB_NOJERK)
    expect = 200.0 / 125.0 + 125.0 / 500.0
    assert expect - 0.01 <= tr.duration <= expect + 0.016 + 0.01
    assert tr.speed.max() == pytest.approx(125.0, rel=0.01)  # minus the dt rounding
    # with jerk on it takes longer, and both start and end at rest
    trj = plan_motion(pts, JOB)
    check_trajectory(trj, pts, JOB)
    assert trj.duration > tr.duration
    assert len(trj.pieces) == 1
    check_trajectory(plan_motion(pts, JOB_RAW), pts, JOB_RAW)


@pytest.mark.parametrize("radius", [1.0, 2.0, 5.0, 10.0, 20.0, 50.0])
@pytest.mark.parametrize("job", [JOB_NOJERK, JOB, JOB_RAW],
                         ids=["jerk-off", "jerk-on", "smoothing-off"])
def test_circles_speed_set_by_radial_acceleration(radius, job):
    th = np.linspace(0.0, 2 * np.pi, int(2 * np.pi * radius / 0.05) + 1)
    pts = np.c_[300.0 + radius * np.cos(th), -60.0 + radius * np.sin(th)]
    tr = plan_motion(pts, job)
    check_trajectory(tr, pts, job)
    # eq. 4.9: c_max = sqrt(a_max r_c), capped by the speed bound
    cmax = min(np.sqrt(job.motion.accel_mm_s2 * radius), job.motion.speed_mm_s)
    assert tr.speed.max() <= cmax * 1.005
    if job is JOB_NOJERK:
        assert tr.speed.max() >= cmax * 0.97


@pytest.mark.parametrize("dt", [0.008, 0.002, 0.001])
@pytest.mark.parametrize("radius, spacing", [(2.0, 0.05), (20.0, 0.4), (50.0, 2.6)],
                         ids=["small-circle", "round-circle", "fill-ring-polygon"])
def test_finer_output_step_is_not_slower(radius, spacing, dt):
    # the same path, jerk on, sampled at 16 ms and at a finer step: a finer output step
    # resolves the same motion, so it may only gain the rounding to whole steps (the
    # ring: the slicer's fill rings turn ~6 deg every ~2.6 mm, motion docstring). When the
    # samples followed the 0.4 mm grid whatever dt, each grid point bounded
    # v |turning| / dt <= A, and the circle took 2.85 s at 1 ms against 1.55 s
    # (motion._denser_input)
    th = np.linspace(0.0, 2 * np.pi, int(2 * np.pi * radius / spacing) + 1)
    pts = np.c_[300.0 + radius * np.cos(th), -60.0 + radius * np.sin(th)]
    coarse = plan_motion(pts, JOB)
    fine_job = JOB.replace(**{"motion.dt_s": dt})
    fine = plan_motion(pts, fine_job)
    check_trajectory(fine, pts, fine_job)
    assert fine.duration <= coarse.duration * 1.02, (coarse.duration, fine.duration)


@pytest.mark.parametrize("offset", [WELL, POOR], ids=["well-placed", "near-reach"])
@pytest.mark.parametrize("job", [JOB, JOB_RAW], ids=["default", "smoothing-off"])
def test_thesis_path_within_0_02_mm_of_the_input(offset, job):
    # the 0.02 mm against the user's path (Fig. 4-2 path, Fig. 4-3 placements)
    pts = thesis_test_path(offset)
    check_trajectory(plan_motion(pts, job), pts, job)
    check_trajectory(plan_motion(pts, job.replace(**{"motion.jerk_limited": False})), pts,
                     job)


@pytest.mark.parametrize("tol", [0.0, 0.005, 0.01, 0.015, 0.02, 0.05])
def test_smoothing_and_joint_filter_share_the_0_02_mm(tol):
    # smoothing tolerance + joint Savitzky-Golay deviation fit inside the 0.02 mm
    # (a looser tolerance is the user's own bound: then no joint filter)
    from icefab.motion import savgol_deviation_mm
    job = JOB.replace(**{"motion.smoothing_tolerance_mm": tol})
    sg = savgol_deviation_mm(job)
    assert 0.0 <= sg <= 0.01
    assert tol + sg <= max(FOLLOW_MM, tol) + 1e-12
    pts = thesis_test_path(POOR)
    check_trajectory(plan_motion(pts, job), pts, job, follow_mm=max(FOLLOW_MM, tol))


def test_default_smoothing_within_0_02_mm():
    assert JOB.motion.smoothing_tolerance_mm <= FOLLOW_MM
    # a coarse polygon: every vertex is rounded off as far as the tolerance allows
    th = np.linspace(0, 2 * np.pi, 73)
    pts = np.c_[300 + 30 * np.cos(th), 30 * np.sin(th)]
    tr = plan_motion(pts, JOB)
    check_trajectory(tr, pts, JOB)
    d = shapely.distance(shapely.points(tr.xy), shapely.LineString(pts))
    assert d.max() > 0.5 * JOB.motion.smoothing_tolerance_mm  # the smoothing is at work


def test_thesis_path_splits_and_stops_at_the_corner():
    pts = thesis_test_path(WELL)
    tr = plan_motion(pts, JOB)
    stats = check_trajectory(tr, pts, JOB)
    assert len(tr.pieces) == 2 and tr.pieces[0] == 0
    k = int(tr.pieces[1])
    np.testing.assert_allclose(tr.xy[k], np.array([0.0, 60.0]) + WELL, atol=1e-9)
    assert tr.speed[k] == 0.0
    # at rest: the samples on either side of the corner are close to it
    assert np.hypot(*(tr.xy[k + 1] - tr.xy[k])) < 0.05
    assert stats["max"] < 20 * JOB.motion.jerk_mm_s3
    assert len(pathsplit(pts, JOB)) == 2
    pieces = pathsplit(pts, JOB.replace(**{"motion.smoothing_tolerance_mm": 0.0}))
    assert len(pieces) == 2
    for p in pieces:
        d = np.hypot(*np.diff(p, axis=0).T)
        assert d.max() <= 0.4 + 1e-9 and d.max() - d.min() < 0.05


def test_jerk_limits_reduce_jerk():
    pts = thesis_test_path(WELL)
    on = plan_motion(pts, JOB)
    off = plan_motion(pts, JOB_NOJERK)
    s_on = check_trajectory(on, pts, JOB)
    s_off = check_trajectory(off, pts, JOB_NOJERK)
    assert on.duration > off.duration
    assert s_on["p99"] < s_off["p99"]
    log.info("jerk on: %.3f s, off: %.3f s (+%.1f %%)", on.duration, off.duration,
             100 * (on.duration / off.duration - 1))


def test_joint_limits_bind_near_reach_fig_4_9():
    well = plan_motion(thesis_test_path(WELL), JOB)
    pts = thesis_test_path(POOR)
    assert 598.9 < np.hypot(*pts.T).max() < 599.01
    poor = plan_motion(pts, JOB)
    check_trajectory(poor, pts, JOB)
    assert poor.duration > 1.15 * well.duration
    # theta2 rate reaches its bound (thesis: "the theta2 max constraint has been imposed")
    robot = get_robot(JOB)
    qd = np.abs(np.diff(poor.joints, axis=0)) / poor.dt
    assert qd[:, 1].max() >= 0.97 * robot.joint_speed_max[1]
    # x-motion (radial here) is slowed, y-motion much less
    # on the side nearest the reach boundary (local x = 100, running along y) the y-motion
    # is far less restricted than the x-motion on the sides running along x
    def side_speeds(tr, off):
        v = np.diff(tr.xy, axis=0) / tr.dt
        loc = tr.xy[1:] - off
        right = loc[:, 0] > 99.0
        top_far = (loc[:, 1] > 59.0) & (loc[:, 0] > 60.0)
        return np.abs(v[right, 1]).max(), np.abs(v[top_far, 0]).max()

    vy_p, vx_p = side_speeds(poor, POOR)
    vy_w, vx_w = side_speeds(well, WELL)
    log.info("near reach: |vy| %.1f |vx| %.1f mm/s; well placed: %.1f, %.1f",
             vy_p, vx_p, vy_w, vx_w)
    assert vx_p < 0.6 * vx_w
    assert vy_p > 0.8 * vy_w


def test_joint_jerk_limits_bind_near_reach(monkeypatch):
    # eq. 4.10's joint jerk bounds: a wavy path (4 mm amplitude, 20 mm period) 5 mm
    # inside the maximum reach, where theta2 moves fast for little tool motion
    import dataclasses

    import icefab.motion as motion_mod
    y = np.linspace(-40.0, 40.0, 801)
    pts = np.c_[590.0 + 4.0 * np.sin(2 * np.pi * y / 20.0), y]
    assert np.hypot(*pts.T).max() < 596.0
    robot = get_robot(JOB)
    free = dataclasses.replace(robot, joint_jerk_max=np.full(3, np.inf))
    # the planner's first plans (without jerk bounds theta2's sampled acceleration reaches
    # 1.35x its bound here, and the re-plan under lower bounds is slower than the plan
    # with them)
    monkeypatch.setattr(motion_mod, "JOINT_REPLANS", 0)
    limited = plan_motion(pts, JOB)
    unlimited = plan_motion(pts, JOB, robot=free)
    check_trajectory(limited, pts, JOB)
    # the joint jerk bounds bind: measured +11 % time on this path
    assert limited.duration > 1.05 * unlimited.duration

    def joint_jerk(tr):  # (n - 3, 2) |third difference| / dt^3, in units of the bound
        return np.abs(np.diff(tr.joints[:, :2], 3, axis=0)) / tr.dt ** 3 / \
            robot.joint_jerk_max[:2]

    on, off = joint_jerk(limited), joint_jerk(unlimited)
    p50, p95, p99 = (np.percentile(on, q, axis=0) for q in (50, 95, 99))
    log.info("joint jerk / bound (theta1, theta2): median %s, p95 %s, p99 %s, max %s; "
             "without joint jerk bounds p95 %s, max %s", p50.round(2), p95.round(2),
             p99.round(2), on.max(axis=0).round(2), np.percentile(off, 95, axis=0).round(2),
             off.max(axis=0).round(2))
    # Sampled third differences exceed the bound now and then: the planner bounds jerk
    # through the speed envelope and the acceleration ramps of ACON on the 0.4 mm grid,
    # JCON only acts on decrease spikes above bound + 20 % (thesis 4.2.4), and the
    # tangential acceleration is piecewise constant between grid points. Measured p95
    # 1.39x (theta2) with the bounds, 2.68x without; 2x is the test's margin.
    assert (p95 <= 2.0).all(), p95
    assert np.percentile(on, 95, axis=0)[1] < 0.7 * np.percentile(off, 95, axis=0)[1]


@pytest.mark.parametrize("cx, radius", [(580.0, 5.0), (588.0, 5.0), (592.0, 5.4),
                                        (594.0, 4.0), (560.0, 30.0)])
@pytest.mark.parametrize("jerk", [True, False], ids=["jerk", "no-jerk"])
def test_paths_near_the_reach_keep_the_joints_accelerations(cx, radius, jerk):
    """Circles 2-15 mm inside the SCARA's full reach: between grid points the joints' rates
    change faster than the bounds at the points say, and their slow-down to rest reached
    1.04-1.10 times joint 2's bound (a hunt's; 1.26 on a fill ring). A trajectory whose
    sampled joint acceleration exceeds a bound is planned again under lower bounds
    (motion.JOINT_REPLANS): every second difference of the joints stays within it."""
    job = JOB.replace(**{"motion.jerk_limited": jerk})
    robot = get_robot(job)
    th = np.linspace(0.0, 2.0 * np.pi, 120, endpoint=False)
    pts = np.c_[cx + radius * np.cos(th), radius * np.sin(th)]
    path = Toolpath(pts, role="boundary", width=1.5, closed=True, frame="base")
    tr = plan_motion(path, job)
    q2 = np.abs(np.diff(tr.joints[:, :2], 2, axis=0)) / tr.dt ** 2
    assert (q2.max(axis=0) <= robot.joint_accel_max[:2] * (1.0 + 1e-6)).all()
    check_trajectory(tr, np.vstack([pts, pts[:1]]), job)
    # planned among other paths (one compiled call; the re-plan takes its polyline out of
    # the call's concatenated points): as long, and within the bound too
    far = Toolpath(pts - [cx - 400.0, 0.0], role="boundary", width=1.5, closed=True,
                   frame="base")
    together = plan_paths_motion([far, path, far], job)[1]
    assert together.duration == tr.duration
    q2 = np.abs(np.diff(together.joints[:, :2], 2, axis=0)) / together.dt ** 2
    assert (q2.max(axis=0) <= robot.joint_accel_max[:2] * (1.0 + 1e-6)).all()


@pytest.mark.parametrize("jerk", [True, False], ids=["jerk", "no-jerk"])
@pytest.mark.parametrize("reach_mm", [599.0, 599.9, 599.99])
def test_stops_at_full_reach_keep_the_joint_accelerations(reach_mm, jerk):
    # Towards the SCARA's full extension (l1 + l2 = 600 mm) the elbow's rate along the path
    # grows like 1 / sqrt(distance): a stop there took its rest acceleration (80 mm/s^2)
    # over the mean rate of the last grid segment and turned joint 2 at 1.27 / 3.2 / 4.1
    # times its acceleration bound at 599 / 599.9 / 599.99 mm (2.5x with jerk off). The
    # rest points' own rates now bound it: measured 0.98 / 0.96 / 0.90 (jerk on).
    job = JOB.replace(**{"motion.jerk_limited": jerk})
    robot = get_robot(job)
    u = np.array([np.cos(0.3), np.sin(0.3)])
    across = np.array([-u[1], u[0]])
    radial = np.linspace(300.0 * u, reach_mm * u, 200)
    hairpin = np.array([400.0 * u, reach_mm * u, 400.0 * u + 5.0 * across])
    for pts in (radial, hairpin):
        tr = plan_motion(pts, job)
        np.testing.assert_allclose(np.hypot(*tr.xy[-1 if pts is radial else 0:].T).max(),
                                   reach_mm, atol=1e-6)
        q2 = np.abs(np.diff(tr.joints[:, :2], 2, axis=0)) / tr.dt ** 2
        assert (q2.max(axis=0) <= 1.02 * robot.joint_accel_max[:2]).all(), \
            q2.max(axis=0) / robot.joint_accel_max[:2]


PIECE_PATHS = {
    "line": np.array([[250.0, -150.0], [250.0, 50.0]]),
    "thesis-well": thesis_test_path(WELL),
    "thesis-near-reach": thesis_test_path(POOR),
    # tangential near the reach: joint 1 turns 1 mm / 595 mm per mm of travel
    "tangent-near-reach": np.array([[595.0, -20.0], [595.0, 20.0]]),
    "zigzag-near-reach": np.array([[590.0, -20.0], [592.0, -18.0], [590.0, -16.0],
                                   [592.0, -14.0], [590.0, -12.0]]),
    "short": np.array([[300.0, 0.0], [300.0, 0.2]]),
}


def _end_steps_deg(tr):
    """(first, last) joint step of every piece: the largest |change| of joints 1, 2, deg."""
    q = np.degrees(tr.joints[:, :2])
    ends = list(tr.pieces) + [len(q) - 1]
    return [(np.abs(q[a + 1] - q[a]).max(), np.abs(q[b] - q[b - 1]).max())
            for a, b in zip(ends[:-1], ends[1:])]


@pytest.mark.parametrize("name", sorted(PIECE_PATHS))
@pytest.mark.parametrize("resolution", [None, 0.003], ids=["default", "coarse"])
@pytest.mark.parametrize("job", [JOB, JOB_NOJERK], ids=["jerk-on", "jerk-off"])
def test_rest_steps_move_joints_beyond_encoder_resolution(name, resolution, job):
    # AREST (thesis 4.2.6): the commanded displacement of the first and the last step of
    # every piece (from and to rest) turns a joint by at least its encoder resolution
    if resolution is not None:
        job = job.replace(**{"cell.encoder_resolution_deg": resolution})
    res = job.cell.encoder_resolution_deg
    pts = PIECE_PATHS[name]
    tr = plan_motion(pts, job)
    check_trajectory(tr, pts, job)
    steps = _end_steps_deg(tr)
    assert len(steps) == len(tr.pieces)
    for first, last in steps:
        assert first >= res and last >= res, (steps, res)


def test_gantry_per_axis_limits():
    job = JOB_NOJERK.replace(**{"cell.robot": "gantry", "motion.speed_mm_s": 400.0,
                                "motion.accel_mm_s2": 5000.0,
                                "motion.gantry_speed_mm_s": [100.0, 200.0]})
    pts = np.array([[10.0, 10.0], [210.0, 10.0], [210.0, 210.0]])
    tr = plan_motion(pts, job)
    robot = get_robot(job)
    check_trajectory(tr, pts, job, robot, vcap=400.0)
    v = np.abs(np.diff(tr.xy, axis=0)) / tr.dt
    assert v[:, 0].max() == pytest.approx(100.0, rel=0.01)
    assert v[:, 1].max() == pytest.approx(200.0, rel=0.01)
    assert len(tr.pieces) == 2
    lines = gcode_moves(tr)
    assert lines[0].startswith("G0 X10.000 Y10.000") and "F" in lines[-1]
    check_gcode_feedrates(lines, tr)

@pytest.mark.parametrize("axis_cap", [True, False], ids=["axis-speed-binds", "cartesian-binds"])
def test_gantry_line_jerk_where_an_axis_speed_binds(axis_cap):
    """A straight line whose speed an axis bound caps eases into cruise as one the
    Cartesian bound caps does (JCON's search for a change of acceleration sign took the
    envelope's rounding, 1e-8 mm/s^2 of either sign, for one: the axis' jerk 2.7 times its
    bound, hunt Q)."""
    caps = ({"motion.speed_mm_s": 200.0, "motion.gantry_speed_mm_s": [100.0, 100.0]}
            if axis_cap else
            {"motion.speed_mm_s": 100.0, "motion.gantry_speed_mm_s": [1000.0, 1000.0]})
    job = JOB.replace(**{"cell.robot": "gantry", "motion.accel_mm_s2": 600.0,
                         "motion.jerk_mm_s3": 5000.0, "motion.gantry_accel_mm_s2": [600.0, 600.0],
                         "motion.gantry_jerk_mm_s3": [5000.0, 5000.0], **caps})
    tr = plan_motion(np.array([[100.0, 100.0], [100.0, 200.0]]), job)
    jerk = np.diff(tr.xy[:, 1], 3) / tr.dt ** 3
    # the tolerance the other jerk checks allow for a sampled ramp (check_trajectory)
    assert np.abs(jerk).max() <= 1.15 * 5000.0, np.abs(jerk).max()
    assert tr.duration == pytest.approx(1.264, abs=0.02)



def check_gcode_feedrates(lines, tr):
    """Every G1 move ends on a sample and its F (mm/min) is the trajectory's speed over
    that step (mean of the two samples' speeds) x 60, within 2 % + 0.5 mm/s (the speed is
    not linear in time inside a step: rest curves, grid segments)."""
    xy = tr.xy
    k = 0
    checked = 0
    for line in lines[1:]:
        words = dict((w[0], float(w[1:])) for w in line.split()[1:])
        assert line.startswith("G1 ") and set(words) == {"X", "Y", "F"}, line
        k += 1
        while np.hypot(words["X"] - xy[k, 0], words["Y"] - xy[k, 1]) > 1e-3:
            k += 1  # a zero-length step has no move
        expect = 60.0 * 0.5 * (tr.speed[k - 1] + tr.speed[k])
        assert words["F"] == pytest.approx(expect, rel=0.02, abs=30.0), (k, line, expect)
        checked += 1
    assert k == len(xy) - 1 and checked >= 0.9 * (len(xy) - 1)


@pytest.mark.parametrize("job", [JOB, JOB_NOJERK], ids=["jerk-on", "jerk-off"])
def test_gcode_feedrates_are_the_sample_speeds(job):
    job = job.replace(**{"cell.robot": "gantry"})
    pts = thesis_test_path((100.0, 120.0))
    tr = plan_motion(pts, job)
    check_trajectory(tr, pts, job)
    lines = gcode_moves(tr)
    check_gcode_feedrates(lines, tr)
    assert max(float(x.split("F")[1]) for x in lines[1:]) == pytest.approx(
        60.0 * job.motion.speed_mm_s, rel=0.01)


# --------------------------------------------------------------------------- inputs


def test_path_objects_frames_and_measure_speed():
    th = np.linspace(0, 2 * np.pi, 400, endpoint=False)
    ring = np.c_[40 * np.cos(th), 40 * np.sin(th)]
    water = Toolpath(points=ring, material="part", role="measure", closed=True, layer=2)
    tr = plan_motion(water, JOB)
    assert tr.path is water
    from icefab.paths import to_base_frame
    base = to_base_frame(water.polyline(), "laser", JOB)
    check_trajectory(tr, base, JOB, vcap=50.0)
    assert tr.speed.max() <= 50.0 * 1.001
    dep = Toolpath(points=ring, material="part", role="boundary", closed=True, layer=2)
    assert plan_motion(dep, JOB).speed.max() > 60.0


def test_workspace_error_before_planning_names_layer_path_point():
    ok = Toolpath(points=np.array([[0.0, 0.0], [10.0, 0.0]]), layer=4)
    far = Toolpath(points=np.array([[0.0, 0.0], [10.0, 0.0], [600.0, 0.0]]), layer=4)
    with pytest.raises(WorkspaceError, match=r"layer 4, path 1: point 2 at .*radius"):
        plan_paths_motion([ok, far], JOB)
    with pytest.raises(WorkspaceError, match="point 1"):
        plan_motion(np.array([[300.0, 0.0], [700.0, 0.0]]), JOB)
    with pytest.raises(WorkspaceError, match="point 0 at"):
        plan_motion(np.array([[0.0, 0.0]]), JOB)
    # a chord through the hole inside the minimum reach
    with pytest.raises(WorkspaceError, match="segment from point 0 to point 1"):
        plan_motion(np.array([[150.0, -100.0], [150.0, 100.0]]), JOB)


def test_path_errors_name_the_path():
    # a Path knows its layer, material and role, not its index: no made-up "path 0"
    far = Toolpath(points=np.array([[0.0, 0.0], [400.0, 0.0]]), layer=7, material="scaffold",
               role="fill")
    with pytest.raises(WorkspaceError) as exc:
        plan_motion(far, JOB)
    msg = str(exc.value)
    assert msg.startswith("layer 7, scaffold fill path: point 1 at") and "path 0" not in msg
    with pytest.raises(WorkspaceError, match=r"^layer 7, path 3 \(scaffold fill\): point 1"):
        plan_motion(far, JOB, index=3)
    nan = Toolpath(points=np.array([[0.0, 0.0], [np.nan, 0.0]]), role="travel")
    with pytest.raises(IcefabError, match=r"^part travel path: point 1 is not finite"):
        plan_motion(nan, JOB)


def test_build_workspace_check_finds_chords_through_the_inner_hole():
    # both ends reachable, the chord between them passes inside the minimum reach: found
    # by the up-front check, before any layer is planned
    from icefab import LayerPaths, Toolpaths
    from icefab.motion import check_build_workspace, plan_toolpaths
    ok = Toolpath(points=np.array([[300.0, 0.0], [310.0, 0.0]]), layer=0, frame="base")
    chord = Toolpath(points=np.array([[300.0, 0.0], [150.0, -100.0], [150.0, 100.0]]), layer=1,
                 frame="base")
    tp = Toolpaths(layers=(LayerPaths(index=0, z=0.25, paths=(ok,)),
                           LayerPaths(index=1, z=0.5, paths=(ok, chord))), job=JOB)
    with pytest.raises(WorkspaceError, match=r"^layer 1, path 1: the segment from point 1 "
                                             r"to point 2 passes \(150.000, 0.000\) mm"):
        check_build_workspace(tp)
    calls = []
    with pytest.raises(WorkspaceError, match="segment from point 1 to point 2"):
        plan_toolpaths(tp, JOB.replace(**{"cell.cpus": 1}),
                       progress=lambda d, t: calls.append(d))
    assert calls == []  # no layer was planned


def test_bad_points_rejected():
    with pytest.raises(IcefabError, match="shape"):
        plan_motion(np.zeros((4, 3)), JOB)
    with pytest.raises(IcefabError, match="not finite"):
        plan_motion(np.array([[300.0, 0.0], [np.nan, 1.0]]), JOB)


def test_degenerate_paths():
    one = plan_motion(np.array([[300.0, 0.0]]), JOB)
    assert len(one.xy) == 1 and one.duration == 0.0
    dup = plan_motion(np.array([[300.0, 0.0], [300.0, 0.0], [300.0, 0.0]]), JOB)
    assert dup.duration == 0.0
    tiny = np.array([[300.0, 0.0], [300.01, 0.0]])
    tr = plan_motion(tiny, JOB)
    check_trajectory(tr, tiny, JOB)
    assert tr.duration > 0
    # zero-length segments in the middle are merged, not split on
    pts = np.array([[300.0, 0.0], [310.0, 0.0], [310.0, 0.0], [320.0, 0.0]])
    tr = plan_motion(pts, JOB)
    assert len(tr.pieces) == 1


@pytest.mark.parametrize("job", [JOB, JOB_NOJERK], ids=["jerk-on", "jerk-off"])
def test_constant_spacing_output(job):
    pts = thesis_test_path(WELL)
    tr = plan_motion(pts, job)
    p, durations = constant_spacing(tr, 0.5)
    line = shapely.LineString(pts)
    along = np.diff(shapely.line_locate_point(line, shapely.points(p)))
    assert np.allclose(along, 0.5, rtol=0.01)
    assert durations.sum() == pytest.approx(tr.duration, rel=1e-6)
    # the speed each point implies (spacing over the mean of its two durations) is the
    # trajectory's speed there (its samples' speed, linear in arc length between them):
    # within 5 % beyond 2 mm of a rest point (the implied speed averages over 1 mm, where
    # the speed changes by up to ~4 %; durations shifted by one interval are 13 % off)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(tr.xy, axis=0).T))])
    sp = np.hypot(*np.diff(p, axis=0).T)
    sq = np.concatenate([[0.0], np.cumsum(sp)])
    v_traj = np.interp(sq[1:-1], s, tr.speed)
    v_impl = (sp[:-1] + sp[1:]) / (durations[:-1] + durations[1:])
    rest = s[tr.speed == 0.0]
    far = (np.abs(sq[1:-1, None] - rest[None, :]) > 2.0).all(axis=1)
    assert far.sum() > 0.9 * len(far)
    rel = np.abs(v_impl - v_traj)[far] / v_traj[far]
    assert rel.max() < 0.05, rel.max()
    assert np.percentile(rel, 99) < 0.03


@pytest.mark.parametrize("bad", [0, 0.0, -0.5, float("nan"), float("inf"), "x"])
def test_constant_spacing_rejects_bad_spacing(bad):
    tr = plan_motion(np.array([[250.0, -150.0], [250.0, 50.0]]), JOB)
    with pytest.raises(IcefabError, match="spacing_mm"):
        constant_spacing(tr, bad)
    # no spacing: the job's point spacing
    p, _ = constant_spacing(tr)
    assert np.hypot(*np.diff(p, axis=0).T).max() <= JOB.motion.point_spacing_mm + 1e-9


@pytest.mark.parametrize("tol", [0.0, 0.01])
def test_savgol_smoothing_keeps_path(tol):
    # the joint filter moves the tool by at most what the smoothing leaves of 0.02 mm
    job = JOB.replace(**{"motion.smoothing_tolerance_mm": tol})
    pts = thesis_test_path(WELL)
    raw = plan_motion(pts, job.replace(**{"motion.savgol_window": 0}))
    sm = plan_motion(pts, job)
    np.testing.assert_allclose(raw.xy, sm.xy)
    robot = get_robot(job)
    dev = np.hypot(*(robot.fk(sm.joints) - sm.xy).T)
    assert dev.max() <= min(0.01, FOLLOW_MM - tol) + 1e-12
    assert not np.array_equal(raw.joints, sm.joints)
    # rest points (piece ends) keep their planned joints: AREST's end steps
    for k in list(sm.pieces) + [len(sm.xy) - 1]:
        np.testing.assert_array_equal(sm.joints[k], raw.joints[k])


def test_savgol_skipped_when_smoothing_takes_the_whole_budget():
    job = JOB.replace(**{"motion.smoothing_tolerance_mm": FOLLOW_MM})
    pts = thesis_test_path(WELL)
    tr = plan_motion(pts, job)
    np.testing.assert_array_equal(tr.joints, get_robot(job).ik(tr.xy))


@pytest.mark.parametrize("dt", [0.016, 0.008, 0.002, 0.001])
def test_followed_path_has_a_point_every_step_at_25_mm_s(dt):
    # a polygon with vertices 2.6 mm apart and a few repeated points: with smoothing on,
    # the followed polyline gets a point every 25 mm/s x dt (the 0.4 mm grid at 16 ms),
    # every one within the tolerance of the input, chords included
    th = np.linspace(0.0, 1.5 * np.pi, 31)
    pts = np.c_[300.0 + 30.0 * np.cos(th), -60.0 + 30.0 * np.sin(th)]
    pts = np.insert(pts, [5, 5, 17], pts[[5, 5, 17]], axis=0)
    job = JOB.replace(**{"motion.dt_s": dt})
    line = shapely.LineString(pts)
    (piece,) = followed_path(pts, job)
    gaps = np.hypot(*np.diff(piece, axis=0).T)
    assert gaps.max() <= min(0.4, 25.0 * dt) + 1e-9
    assert gaps.min() > 0.0
    assert shapely.distance(shapely.points(piece), line).max() <= 0.02 + 1e-9
    mids = 0.5 * (piece[:-1] + piece[1:])
    assert shapely.distance(shapely.points(mids), line).max() <= 0.02 + 1e-9
    np.testing.assert_allclose(piece[[0, -1]], pts[[0, -1]], atol=1e-9)


def test_optional_path_smoothing_within_tolerance():
    # a polygonal circle: smoothing lets the robot go faster, within the tolerance
    th = np.linspace(0, 2 * np.pi, 73)
    pts = np.c_[300 + 30 * np.cos(th), 30 * np.sin(th)]
    job = JOB.replace(**{"motion.smoothing_tolerance_mm": 0.05, "motion.smooth_angle_deg": 10.0})
    raw_job = job.replace(**{"motion.smoothing_tolerance_mm": 0.0})
    raw_tr = plan_motion(pts, raw_job)
    check_trajectory(raw_tr, pts, raw_job)
    tr = plan_motion(pts, job)
    check_trajectory(tr, pts, job, follow_mm=0.05)  # asked for 0.05 mm
    line = shapely.LineString(pts)
    # the smoothed path (points and chords) is within the tolerance; the samples follow it
    for piece in followed_path(pts, job):
        assert shapely.distance(shapely.points(piece), line).max() <= 0.05 + 1e-9
    d = shapely.distance(shapely.points(tr.xy), line)
    assert d.max() <= 0.05 + 1e-9
    # the 5-degree vertices no longer cap the speed: r = 30 mm allows 122 mm/s (eq. 4.9)
    assert raw_tr.speed.max() < 100.0
    assert tr.speed.max() > 115.0
    assert tr.duration < 0.85 * raw_tr.duration

    def max_turn(pieces):
        out = 0.0
        for q in pieces:
            e = np.diff(q, axis=0)
            a = np.arctan2(e[:, 1], e[:, 0])
            turn = np.abs(np.angle(np.exp(1j * np.diff(a))))[15:-15]  # ends stay put
            out = max(out, turn.max())
        return out

    raw = pathsplit(pts, job.replace(**{"motion.smoothing_tolerance_mm": 0.0}))
    assert max_turn(pathsplit(pts, job)) < 0.5 * max_turn(raw)


def test_elbow_left_also_plans():
    job = JOB.replace(**{"cell.elbow": "left"})
    pts = thesis_test_path(WELL)
    tr = plan_motion(pts, job, robot=Scara(elbow="left"))
    assert (tr.joints[:, 1] <= 1e-12).all()
    check_trajectory(tr, pts, job)


# --------------------------------------------------------------------------- real layers


@pytest.fixture(scope="module")
def mug_toolpaths():
    from icefab.demo import demo_mug
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh
    job = Job().replace(**{"parts.part_fraction": [0.5, 0.503]})
    stack = add_scaffold(slice_mesh(demo_mug(), job), job)
    return plan_paths(stack, job), job


@pytest.mark.parametrize("smoothing", [None, 0.0], ids=["default", "smoothing-off"])
def test_real_layers_follow_paths_within_bounds(mug_toolpaths, smoothing):
    from icefab.motion import path_limits, plan_toolpaths
    from icefab.paths import estimate_build_time, to_base_frame
    tp, job = mug_toolpaths
    if smoothing is not None:
        job = job.replace(**{"motion.smoothing_tolerance_mm": smoothing})
    motion = plan_toolpaths(tp, job.replace(**{"cell.cpus": 1}))
    assert len(motion) == len(tp)
    n = 0
    worst = 0.0
    for lm, lp in zip(motion.layers, tp.layers):
        assert len(lm.trajectories) == len(lp.paths)
        for tr, p in zip(lm.trajectories, lp.paths):
            assert tr.path is p
            base = to_base_frame(p.polyline(), p.tool_name, job)
            if len(tr.xy) > 1:
                stats = check_trajectory(tr, base, job, vcap=path_limits(p, job))
                worst = max(worst, stats["p99"])
                n += 1
    assert n > 10
    _, const = estimate_build_time(tp, job)
    log.info("mug layers: MTTS %.1f s vs constant speed %.1f s; worst p99 jerk %.0f",
             motion.duration, const, worst)
    assert motion.duration < const


# --------------------------------------------------------------------------- sweeps


def test_cubic_root_of_eq_4_7_matches_numpy():
    from icefab._mtts import _cubic_root
    rng = np.random.default_rng(1)
    for _ in range(300):
        j0 = rng.uniform(100, 1e5)
        a0 = rng.choice([0.0, rng.uniform(0, 2000)])
        v0 = rng.choice([0.0, rng.uniform(0, 200)])
        ds = rng.uniform(0.01, 1.0)
        roots = np.roots([j0 / 6, a0 / 2, v0, -ds])
        real = roots[np.abs(roots.imag) < 1e-9].real
        expect = real[real > 0]
        assert len(expect) == 1
        assert _cubic_root(j0, a0, v0, ds) == pytest.approx(expect[0], rel=1e-9)


def _random_polyline(rng, n_vertices, max_turn_deg, spacing):
    ang = np.cumsum(np.radians(rng.uniform(-max_turn_deg, max_turn_deg, n_vertices)))
    steps = spacing * rng.uniform(0.5, 1.5, n_vertices)[:, None] * np.c_[np.cos(ang),
                                                                           np.sin(ang)]
    pts = np.concatenate([[[0.0, 0.0]], np.cumsum(steps, axis=0)])
    return pts - pts.mean(axis=0) + np.array([300.0, -60.0])


@pytest.mark.parametrize("seed", range(12))
def test_random_polylines_respect_bounds(seed):
    rng = np.random.default_rng(seed)
    spacing = rng.choice([0.3, 1.0, 3.0])
    n = min(int(rng.integers(20, 120)), int(120 / spacing))  # stays well inside the reach
    pts = _random_polyline(rng, n, rng.choice([4.0, 12.0, 40.0]), spacing)
    job = JOB if seed % 2 else JOB_NOJERK
    # path smoothing off, 0.01, 0.02 mm (the default), or looser (0.1 mm): the samples
    # within the tolerance of the input, and within 0.02 mm unless the tolerance is looser
    tol = (0.0, 0.01, 0.02, 0.1)[(seed // 2) % 4]
    job = job.replace(**{"motion.smoothing_tolerance_mm": tol})
    tr = plan_motion(pts, job)
    check_trajectory(tr, pts, job, follow_mm=max(FOLLOW_MM, tol))
    assert (tr.speed[tr.pieces] == 0).all()


def test_kernels_match_numpy_reference():
    # the compiled helpers against plain numpy: positions on the followed polyline
    # (np.interp), turning vectors and arc length, and the merged followed points
    from icefab import _mtts
    rng = np.random.default_rng(5)
    start = np.array([0, 7, 20, 23], dtype=np.int64)
    pts = np.cumsum(rng.uniform(0.1, 1.0, (23, 2)), axis=0)
    s_loc, tau = _mtts.polyline_vertices(pts, start)
    for a, b in zip(start[:-1], start[1:]):
        seg = np.hypot(*np.diff(pts[a:b], axis=0).T)
        np.testing.assert_allclose(s_loc[a:b], np.r_[0.0, np.cumsum(seg)], atol=1e-12)
        u = np.diff(pts[a:b], axis=0) / seg[:, None]
        np.testing.assert_allclose(tau[a + 1:b - 1], np.diff(u, axis=0), atol=1e-12)
        assert not tau[a].any() and not tau[b - 1].any()
    # samples along each piece (parameter fu in S units, piece start s0)
    s0 = np.array([0.0, 100.0, 200.0])
    fu = np.concatenate([s0[k] + s_loc[a:b] for k, (a, b) in
                         enumerate(zip(start[:-1], start[1:]))])
    L = np.array([s_loc[b - 1] for b in start[1:]])
    ns = np.array([9, 30, 4])
    sstart = np.r_[0, np.cumsum(ns)].astype(np.int64)
    sl = np.concatenate([np.r_[0.0, np.sort(rng.uniform(0, Lk * 1.01, n - 2)), Lk]
                         for Lk, n in zip(L, ns)])
    xy = _mtts.follow_samples(sl, sstart, L, start, fu, pts, s0)
    sg = np.minimum(sl, np.repeat(L, ns)) + np.repeat(s0, ns)
    ref = np.c_[np.interp(sg, fu, pts[:, 0]), np.interp(sg, fu, pts[:, 1])]
    np.testing.assert_allclose(xy, ref, atol=1e-9)


_DIGEST = """
import hashlib, numpy as np
from icefab import Job
from icefab.motion import plan_motion, thesis_test_path
tr = plan_motion(thesis_test_path((250.0, -30.0)), Job())
h = hashlib.sha256()
for a in (tr.xy, tr.joints, tr.speed):
    h.update(np.ascontiguousarray(a).tobytes())
print(h.hexdigest())
"""


def test_trajectories_do_not_depend_on_whether_numbas_cache_existed(tmp_path):
    """The kernels compiled in the process and the same kernels loaded from numba's cache
    give the same samples, bit for bit (fast-math "reassoc" and "contract" made them round
    differently, _mtts._FM)."""
    import os
    import subprocess
    import sys
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    runs = [subprocess.run([sys.executable, "-c", _DIGEST], env=env, capture_output=True,
                           text=True, check=True).stdout for _ in range(2)]
    assert (tmp_path / "numba").is_dir()        # the first run compiled, the second loaded
    assert runs[0] == runs[1] and len(runs[0].strip()) == 64


@pytest.mark.parametrize("jerk", [True, False], ids=["jerk", "no-jerk"])
def test_tour_corners_near_the_reach_keep_the_joint_accelerations(jerk):
    """A tour's travel curves near the SCARA's full reach turn 32-43 degrees between two
    samples: the vertex bounds took only the Cartesian acceleration, so joint 2 turned at
    1.29 / 1.31 times its bound (jerk on / off), and no re-plan under lower joint bounds
    changed the corners' speed (hunt Q). The vertices' bounds now take the joints'
    through their Jacobian (_mtts._vertex_bounds)."""
    pts = np.loadtxt(DATA / "tour-near-reach.csv", delimiter=",")
    job = JOB.replace(**{"cell.ee_origin_mm": (260.0, -100.0), "motion.jerk_limited": jerk})
    robot = get_robot(job)
    tr = plan_motion(Toolpath(pts, role="fill", width=3.0), job)
    q2 = np.abs(np.diff(tr.joints[:, :2], 2, axis=0)) / tr.dt ** 2
    assert (q2.max(axis=0) <= robot.joint_accel_max[:2] * (1.0 + 1e-6)).all(), \
        q2.max(axis=0) / robot.joint_accel_max[:2]
    # in the base frame: the cell frame's origin and the part nozzle's offset
    check_trajectory(tr, pts + (tr.xy[0] - pts[0]), job)


@pytest.mark.parametrize("dt", [0.001, 0.002, 0.004, 0.016])
@pytest.mark.parametrize("side", [1.0, 5.0])
@pytest.mark.parametrize("job", [JOB, JOB_NOJERK], ids=["jerk-on", "jerk-off"])
def test_polyline_vertices_keep_the_bounds_at_every_step(job, side, dt):
    # 25 deg zigzags: with smoothing on, a vertex kept most of its turn at one point of
    # the followed polyline, and an arc shorter than the 0.4 mm grid was missed by the
    # tangential budget, so at 1-4 ms the samples reached 1.14-1.18 times the
    # acceleration bound (jerk off); corners are now arcs and the followed polyline's own
    # curvature bounds the speed (motion._round_corners, _mtts._followed_curvature)
    job = job.replace(**{"motion.dt_s": dt})
    pts = zigzag(25.0, side)
    tr = plan_motion(pts, job)
    check_trajectory(tr, pts, job)
    coarse = plan_motion(pts, job.replace(**{"motion.dt_s": 0.016}))
    # a finer step resolves the same motion: not pathologically slower (was 3.3-4.2x)
    assert tr.duration <= 2.2 * coarse.duration, (tr.duration, coarse.duration)
