"""The c-controller's re-timing keeps every motion limit (issue 14; thesis 5.2.2 speeds a
path up by up to feedback.saturation = 30 %, which on a path planned at its limits would
break them: 1.3 x 125 mm/s, 1.69 x the acceleration). Limits measured on the re-timed
samples by finite differences, against the job's and the robot's bounds."""
from __future__ import annotations

import numpy as np
import pytest

from icefab import Job
from icefab.core import Toolpath
from icefab.feedback import retime_trajectory
from icefab.flow import replan_valves
from icefab.motion import limit_ratio, plan_motion, speedup_cap
from icefab.robots import get_robot


def rates(traj):
    """(speed, acceleration) magnitudes mm/s, mm/s^2 and joint speeds (k, m) of the
    samples, by finite differences at the trajectory's dt."""
    d1 = np.diff(traj.xy, axis=0) / traj.dt
    d2 = np.diff(d1, axis=0) / traj.dt
    q1 = np.diff(traj.joints, axis=0) / traj.dt
    return np.hypot(*d1.T), np.hypot(*d2.T), q1


@pytest.fixture(scope="module")
def fill_line():
    """A 216 mm fill path planned at 100 mm/s, run on a cell whose bound is 125 mm/s: the
    c-controller has room to speed it up on its cruise, not where it accelerates."""
    path = Toolpath(points=np.array([[-60.0, -90.0], [60.0, 90.0]]), role="fill",
                    width=1.5, material="part")
    traj = plan_motion(path, Job().replace(**{"motion.speed_mm_s": 100.0}))
    return Job(), traj


def test_uncapped_retiming_breaks_the_limits(fill_line):
    """The check can fail: without the cap a 30 % speed-up exceeds the speed bound."""
    job, traj = fill_line
    fast = retime_trajectory(traj, np.full(len(traj.xy), -0.25), max_change=0.3)
    v, a, _ = rates(fast)
    assert v.max() > 1.02 * job.motion.speed_mm_s


def test_the_cap_alone_keeps_the_speed_bound(fill_line):
    job, traj = fill_line
    fast = retime_trajectory(traj, np.full(len(traj.xy), -0.25), max_change=0.3,
                             cap=speedup_cap(traj, job))
    v, _a, _q = rates(fast)
    assert v.max() <= job.motion.speed_mm_s * (1 + 1e-6)
    # a slowed-down path is not held back by the cap
    slow = retime_trajectory(traj, np.full(len(traj.xy), 0.25), max_change=0.3,
                             cap=speedup_cap(traj, job))
    assert slow.duration == pytest.approx(traj.duration / 0.8, rel=0.02)


def test_speed_controller_replan_uses_the_cap(fill_line):
    """feedback.controller = 'speed' re-times through replan_valves: the action asks for
    +30 %, the re-timed trajectory stays within the speed bound."""
    job, traj = fill_line
    job = job.replace(**{"feedback.controller": "speed"})
    v0, a0, q0 = rates(traj)
    trajs, _progs = replan_valves([traj], job, action=lambda xy: np.full(len(xy), -0.25))
    v, a, q1 = rates(trajs[0])
    assert v.max() <= job.motion.speed_mm_s * (1 + 1e-6)
    # the sampled profile's own acceleration may exceed the bound by its discretisation;
    # the re-timed one may not exceed that
    assert a.max() <= max(job.motion.accel_mm_s2, a0.max()) * (1 + 1e-6)
    qv = np.asarray(get_robot(job).joint_speed_max)
    assert np.all(np.abs(q1).max(axis=0) <= np.maximum(qv, np.abs(q0).max(axis=0)) * (1 + 1e-6))
    assert float(limit_ratio(trajs[0], job).min()) >= min(
        1.0, float(limit_ratio(traj, job).min())) * (1 - 1e-6)
    assert trajs[0].duration < traj.duration  # sped up where the limits allowed
