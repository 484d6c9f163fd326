"""Optimality against an independent solver: with the jerk bounds off, MTTS durations are
within 3 % of TOPP-RA (the ``toppra`` package) on the same speed and acceleration bounds.

TOPP-RA's acceleration constraint is per axis, so the total-acceleration disc is bracketed
between a 64-sided polygon inscribed in it (slower) and one circumscribing it (faster). The
path handed to TOPP-RA stacks (x, y, 1000 theta1, 1000 theta2, s): joints scaled by 1000
(its solver found no solution in raw radians on several paths) and the arc length s so
that the Cartesian speed bound is exact.
"""
from __future__ import annotations

import logging

import numpy as np
import pytest

from icefab import Job
from icefab.motion import pathsplit, plan_motion, thesis_test_path
from icefab.robots import get_robot

from _polylines import zigzag

log = logging.getLogger(__name__)
logging.getLogger("toppra").setLevel(logging.ERROR)

# dt 4 ms: the rounding of each piece to whole steps stays below 0.5 %, and a step still
# spans several vertices of the finely sampled test paths (MTTS sees the polyline the
# samples follow; TOPP-RA a spline through it)
JOB = Job().replace(**{"motion.jerk_limited": False, "motion.dt_s": 0.004})


def toppra_duration(pts: np.ndarray, job: Job, robot, *, sides: int = 64,
                    inscribed: bool = True) -> float:
    """TOPP-RA's minimum time along one piece (rest to rest), s."""
    import toppra as ta
    import toppra.algorithm as algo
    import toppra.constraint as constraint

    d = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(d)])
    q = robot.ik(pts)
    lim_v = np.asarray(robot.joint_speed_max, dtype=np.float64)
    lim_a = np.asarray(robot.joint_accel_max, dtype=np.float64)
    fin = np.isfinite(lim_v) & np.isfinite(lim_a)
    scale = 1000.0 if robot.name == "scara" else 1.0
    q = q[:, fin] * scale
    way = np.column_stack([pts, q, s])
    dof = way.shape[1]
    path = ta.SplineInterpolator(s, way)
    m = job.motion
    big = 1e9
    vlim = np.concatenate([[big, big], lim_v[fin] * scale, [m.speed_mm_s]])
    alim = np.concatenate([[big, big], lim_a[fin] * scale, [big]])
    pc_vel = constraint.JointVelocityConstraint(np.column_stack([-vlim, vlim]))
    pc_acc = constraint.JointAccelerationConstraint(np.column_stack([-alim, alim]))
    ang = 2 * np.pi * np.arange(sides) / sides
    F = np.zeros((sides, dof))
    F[:, 0] = np.cos(ang)
    F[:, 1] = np.sin(ang)
    amax = m.accel_mm_s2 * (1.0 if inscribed else 1.0 / np.cos(np.pi / sides))
    g = np.full(sides, amax)
    pc_tot = constraint.SecondOrderConstraint(
        lambda q_, qd, qdd: qdd, lambda q_: F, lambda q_: g, dof=dof,
        discretization_scheme=constraint.DiscretizationType.Collocation)
    inst = algo.TOPPRA([pc_vel, pc_acc, pc_tot], path, gridpoints=s,
                       parametrizer="ParametrizeConstAccel")
    traj = inst.compute_trajectory(0, 0)
    if traj is None:
        raise RuntimeError("TOPP-RA found no solution")
    return float(traj.duration)


def toppra_bracket(pts: np.ndarray, job: Job, robot) -> tuple[float, float]:
    """(faster circumscribed, slower inscribed) TOPP-RA durations summed over the pieces."""
    pieces = pathsplit(pts, job)
    fast = sum(toppra_duration(p, job, robot, inscribed=False) for p in pieces)
    slow = sum(toppra_duration(p, job, robot, inscribed=True) for p in pieces)
    return fast, slow


def _circle(r, c=(300.0, -60.0)):
    th = np.linspace(0.0, 2 * np.pi, int(2 * np.pi * r / 0.01) + 1)
    return np.c_[c[0] + r * np.cos(th), c[1] + r * np.sin(th)]


def _wavy(seed=3):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, 15000)
    x = 220 + 150 * t
    y = -60 + sum(rng.uniform(2, 12) * np.sin(2 * np.pi * (k + 1) * t + rng.uniform(0, 6))
                  for k in range(4))
    return np.c_[x, y]


def _poor():
    from test_motion import POOR
    return thesis_test_path(POOR, step_mm=0.01)


CASES = {
    "thesis-path-well": lambda: thesis_test_path((250.0, -80.0), step_mm=0.01),
    "thesis-path-near-reach": _poor,
    "circle-2": lambda: _circle(2.0),
    "circle-10": lambda: _circle(10.0),
    "circle-50": lambda: _circle(50.0),
    "line-near-reach": lambda: np.array([[420.0, -300.0], [420.0, 300.0]]),
    "wavy": _wavy,
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_duration_within_3_percent_of_toppra(name):
    pts = CASES[name]()
    robot = get_robot(JOB)
    tr = plan_motion(pts, JOB)
    fast, slow = toppra_bracket(pts, JOB, robot)
    log.info("%s: MTTS %.4f s, TOPP-RA %.4f..%.4f s", name, tr.duration, fast, slow)
    assert fast <= slow * (1 + 1e-6)
    assert 0.97 * fast <= tr.duration <= 1.03 * slow


def test_gantry_against_toppra():
    job = JOB.replace(**{"cell.robot": "gantry", "motion.speed_mm_s": 300.0,
                         "motion.accel_mm_s2": 3000.0,
                         "motion.gantry_speed_mm_s": [150.0, 250.0],
                         "motion.gantry_accel_mm_s2": [1500.0, 2500.0]})
    robot = get_robot(job)
    th = np.linspace(0, 2 * np.pi, 3000)
    pts = np.c_[150 + 60 * np.cos(th), 150 + 40 * np.sin(2 * th)]
    tr = plan_motion(pts, job)
    fast, slow = toppra_bracket(pts, job, robot)
    log.info("gantry: MTTS %.4f s, TOPP-RA %.4f..%.4f s", tr.duration, fast, slow)
    assert 0.97 * fast <= tr.duration <= 1.03 * slow


@pytest.mark.parametrize("dt", [0.001, 0.002, 0.004])
def test_fine_step_zigzag_within_1_5_times_toppra(dt):
    # a 25 deg zigzag with 3 mm sides: the path smoothing left 20 of each vertex's 25 deg
    # at one point of the followed polyline, whose vertex bound A dt / turn gave 2.7 /
    # 1.9 / 1.4 times TOPP-RA's time at 1 / 2 / 4 ms; the corners are now arcs within the
    # tolerance (motion._round_corners), 1.37 / 1.33 / 1.20. TOPP-RA times the same
    # followed (smoothed) polyline.
    from icefab.motion import followed_path
    job = JOB.replace(**{"motion.dt_s": dt})
    pts = zigzag(25.0, 3.0)
    robot = get_robot(job)
    tr = plan_motion(pts, job)
    top = sum(toppra_duration(p, job, robot) for p in followed_path(pts, job))
    log.info("zigzag dt %g: MTTS %.3f s, TOPP-RA %.3f s", dt, tr.duration, top)
    assert tr.duration <= 1.5 * top
