"""The thesis' "constant-speed" case (4.4) planned with real accelerations:
``icefab.motion.constant_speed_motion`` against analytic ramp times and against MTTS."""
from __future__ import annotations

import math

import numpy as np
import pytest

from icefab import Job, LayerPaths, Toolpath, Toolpaths
from icefab.errors import IcefabError
from icefab.motion import (constant_speed_motion, plan_paths_motion, plan_toolpaths,
                           thesis_test_path)

LINE = np.array([[250.0, -150.0], [250.0, 50.0]])  # 200 mm, far from singularities


def _line_time(length, v, a, j=None):
    """Rest-to-rest time along a straight line at cruise speed v: trapezoid (jerk off,
    T = L/v + v/a) or the symmetric jerk-limited S-curve (T = L/v + 2 sqrt(v/j) when
    v < a^2/j, else L/v + v/a + a/j)."""
    if j is None:
        return length / v + v / a
    if v < a * a / j:
        return length / v + 2.0 * math.sqrt(v / j)
    return length / v + v / a + a / j


@pytest.mark.parametrize("jerk", [False, True], ids=["jerk-off", "jerk-on"])
@pytest.mark.parametrize("role,speed", [("boundary", 25.0), ("fill", 125.0),
                                        ("fill", 60.0)])
def test_straight_line_constant_speed_plus_ramps(jerk, role, speed):
    # from/to-rest curves starting at zero acceleration: the textbook S-curve
    job = Job().replace(**{"motion.jerk_limited": jerk, "motion.rest_accel_mm_s2": 0.0})
    m = job.motion
    p = Toolpath(points=LINE, role=role, frame="base", width=1.5)
    tr = plan_paths_motion([p], job, role_speeds={role: speed})[0]
    expect = _line_time(200.0, speed, m.accel_mm_s2, m.jerk_mm_s3 if jerk else None)
    assert expect - 1e-6 <= tr.duration + 1e-9
    assert tr.duration <= expect + 2 * m.dt_s
    v = np.hypot(*np.diff(tr.xy, axis=0).T) / m.dt_s
    assert v.max() <= speed * 1.01
    assert v.max() >= speed * 0.98


def _box_toolpaths(job):
    """Two layers: the thesis test path (Fig. 4-2) as a boundary and a zigzag-like fill."""
    off = np.array([250.0, -80.0])
    bnd = thesis_test_path(tuple(off))
    ys = np.arange(5.0, 56.0, 5.0)
    zz = []
    for k, y in enumerate(ys):
        xs = (8.0, 92.0) if k % 2 == 0 else (92.0, 8.0)
        zz += [[xs[0], y], [xs[1], y]]
    fill = np.asarray(zz) + off
    layers = []
    for k in range(2):
        paths = (Toolpath(points=bnd, role="boundary", frame="base", layer=k, width=1.5),
                 Toolpath(points=fill, role="fill", frame="base", layer=k, width=3.0))
        layers.append(LayerPaths(index=k, z=0.25 * (k + 1), paths=paths))
    return Toolpaths(layers=tuple(layers), job=job)


def test_mtts_never_slower_than_constant_speed():
    job = Job().replace(**{"cell.cpus": 1})
    tp = _box_toolpaths(job)
    mtts = plan_toolpaths(tp, job)
    const = constant_speed_motion(tp, job)
    for lm, lc in zip(mtts.layers, const.layers):
        for a, b in zip(lm.trajectories, lc.trajectories):
            assert a.duration <= b.duration + 1e-9
            # same rests: the same split corners
            assert len(a.pieces) == len(b.pieces)
    assert mtts.duration < const.duration
    # boundaries at 25 mm/s: constant-speed time at least length / 25
    for lc in const.layers:
        tb = lc.trajectories[0]
        L = np.hypot(*np.diff(tb.path.points, axis=0).T).sum()
        assert tb.duration >= L / 25.0
        assert tb.speed.max() <= 25.0 * 1.01
    # the zigzag fill stops at each of its 20 corners: 11 lines and 10 links
    assert len(const.layers[0].trajectories[1].pieces) == 21
    # all at 25 mm/s (the thesis' concentric constant-speed case) is slower still
    slow = constant_speed_motion(tp, job, fill_mm_s=25.0)
    assert slow.duration > const.duration


def test_constant_speed_parallel_matches_serial():
    job = Job()
    tp = _box_toolpaths(job)
    a = constant_speed_motion(tp, job.replace(**{"cell.cpus": 1}))
    b = constant_speed_motion(tp, job.replace(**{"cell.cpus": 2}))
    np.testing.assert_allclose(a.layer_durations, b.layer_durations)


def test_bad_role_speeds():
    tp = _box_toolpaths(Job())
    with pytest.raises(IcefabError, match="fill"):
        constant_speed_motion(tp, Job(), fill_mm_s=-1.0)
    with pytest.raises(IcefabError, match="unknown path role"):
        plan_paths_motion(tp.layers[0].paths, Job(), role_speeds={"wall": 10.0})


@pytest.mark.parametrize("constant", [False, True])
def test_durations_without_samples_equal_the_planned_ones(constant):
    """plan_paths_durations (the constant-speed comparison's worker) gives exactly the
    durations plan_paths_motion samples, for rings, open paths, travel and a one-point
    path, at MTTS and at the constant speeds."""
    from icefab.motion import _constant_speeds, plan_paths_durations
    job = Job()
    th = np.linspace(0.0, 2.0 * np.pi, 90, endpoint=False)
    ring = np.c_[40.0 * np.cos(th), 25.0 * np.sin(th)]
    zig = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 3.0], [0.0, 3.0], [0.0, 6.0]])
    paths = [Toolpath(points=ring, closed=True, role="boundary", width=1.5),
             Toolpath(points=zig, role="fill", width=3.0),
             Toolpath(points=np.array([[0.0, 6.0], [40.0, 0.0]]), role="travel"),
             Toolpath(points=np.array([[5.0, 5.0]]), role="fill", width=3.0),
             Toolpath(points=ring * 0.5, closed=True, role="measure")]
    speeds = _constant_speeds(job, None, None) if constant else None
    planned = [t.duration for t in plan_paths_motion(paths, job, role_speeds=speeds)]
    got = plan_paths_durations(paths, job, role_speeds=speeds)
    assert got.tolist() == planned
    assert got[3] == 0.0 and (got[[0, 1, 2, 4]] > 0).all()
    assert plan_paths_durations([], job).shape == (0,)


@pytest.mark.parametrize("speeds", [None, {"boundary": 25.0, "fill": 60.0},
                                    {"boundary": 125.0, "fill": 125.0}])
def test_one_preparation_plans_both_cases_as_two_would(speeds):
    """icefab plan's worker (_plan_layer_and_time) splits and checks a layer once for both
    the MTTS plan and the constant-speed time, and plans again only the pieces whose
    bound differs (the boundaries at the default speeds; the fill too at 60 mm/s; none
    when every bound is MTTS'): the same trajectories, sample for sample, and the same time
    as planning each case on its own; an empty layer takes no time."""
    from icefab.motion import (_constant_speeds, _plan_layer, _plan_layer_and_time,
                               plan_paths_durations)
    job = Job()
    th = np.linspace(0.0, 2.0 * np.pi, 90, endpoint=False)
    ring = np.c_[40.0 * np.cos(th), 25.0 * np.sin(th)]
    zig = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 3.0], [0.0, 3.0], [0.0, 6.0]])
    paths = (Toolpath(points=ring, closed=True, role="boundary", width=1.5, layer=3),
             Toolpath(points=zig, role="fill", width=3.0, layer=3),
             Toolpath(points=np.array([[0.0, 6.0], [40.0, 0.0]]), role="travel", layer=3),
             Toolpath(points=np.array([[5.0, 5.0]]), role="fill", width=3.0, layer=3),
             Toolpath(points=ring * 0.5, closed=True, role="measure", layer=3))
    lp = LayerPaths(index=3, z=1.0, paths=paths)
    speeds = speeds or _constant_speeds(job, None, None)
    lm, const_s = _plan_layer_and_time(lp, job, speeds)
    want = _plan_layer(lp, job)
    assert len(lm.trajectories) == len(want.trajectories) == 5
    for a, b in zip(lm.trajectories, want.trajectories):
        np.testing.assert_array_equal(a.xy, b.xy)
        np.testing.assert_array_equal(a.joints, b.joints)
        np.testing.assert_array_equal(a.speed, b.speed)
        np.testing.assert_array_equal(a.pieces, b.pieces)
        assert a.duration == b.duration and a.path is b.path
    assert const_s == float(plan_paths_durations(paths, job, layer=3,
                                                 role_speeds=speeds).sum())
    assert const_s >= lm.duration > 0.0
    assert (const_s > lm.duration) == (speeds["boundary"] < 125.0)
    empty, t = _plan_layer_and_time(LayerPaths(index=4, z=1.2, paths=()), job, speeds)
    assert empty.trajectories == () and t == 0.0


def test_any_pieces_planned_alone_get_the_durations_planned_together():
    """_piece_times plans a subset of a layer's pieces on their own rows: each gets the
    duration the whole layer's compiled call gives it (pieces are independent)."""
    from icefab.motion import _paths_input, _piece_times, _prepare, _profiles
    from icefab.robots import get_robot
    job = Job()
    robot = get_robot(job)
    rng = np.random.default_rng(7)
    paths = [Toolpath(points=np.cumsum(rng.uniform(-8, 8, (int(k), 2)), axis=0),
                      role="fill", width=1.5, closed=bool(k % 2))
             for k in rng.integers(1, 12, 25)]
    V, counts, caps, labels = _paths_input(paths, job, 0, None)
    caps = rng.uniform(20.0, 125.0, len(caps))
    prep = _prepare((V, counts), job, robot, labels)
    T = _profiles(prep, caps, job, robot).T
    assert len(T) > 25
    for sel in (np.arange(len(T)), np.array([0]), np.array([len(T) - 1]),
                np.flatnonzero(rng.random(len(T)) < 0.4), np.zeros(0, np.int64)):
        assert _piece_times(prep, caps, job, robot, sel).tolist() == T[sel].tolist()
