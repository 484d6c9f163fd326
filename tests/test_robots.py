"""Robot kinematics: IK/FK round trips, thesis joint conventions, workspace errors."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from icefab import Job
from icefab.config import load_job, to_toml
from icefab.errors import WorkspaceError
from icefab.robots import (ROBOTS, Gantry, Robot, Scara, check_workspace, get_robot,
                           register_robot)


@pytest.fixture
def robot_registry():
    """The registry as it was before the test: robots a test registers are removed."""
    saved = dict(ROBOTS)
    yield ROBOTS
    ROBOTS.clear()
    ROBOTS.update(saved)


def test_registry_builds_cobra_defaults():
    robot = get_robot(Job())
    assert isinstance(robot, Robot)
    assert robot.name == "scara"
    assert robot.l1 == 325.0 and robot.l2 == 275.0
    np.testing.assert_allclose(np.degrees(robot.joint_speed_max[:2]), [33.0, 39.0])
    np.testing.assert_allclose(np.degrees(robot.joint_accel_max[:2]), [165.0, 195.0])
    np.testing.assert_allclose(np.degrees(robot.joint_jerk_max[:2]), [1320.0, 1560.0])
    assert np.isinf(robot.joint_speed_max[2])  # joint 4 unconstrained (thesis 4.2.1)
    gantry = get_robot(Job().replace(**{"cell.robot": "gantry"}))
    assert gantry.name == "gantry" and isinstance(gantry, Robot)


def test_register_robot_by_name(robot_registry):
    class FakeCell:
        robot = "mine"

    class FakeJob:
        cell = FakeCell()

    register_robot("mine", lambda job: Gantry(travel=(10.0, 10.0)))
    assert get_robot(FakeJob()).travel == (10.0, 10.0)
    assert "mine" in robot_registry


def test_registry_left_as_found():
    # the fixture of the test above removed its robot (whatever the test order)
    assert set(ROBOTS) >= {"scara", "gantry"}
    assert "mine" not in ROBOTS


def test_gantry_default_part_origin_at_travel_centre(tmp_path):
    # the default part origin (260, -100) mm is a SCARA position: a gantry left at it
    # builds at the centre of its travel, resolved when the job is built (also from a
    # file, and kept through a save); an origin the user set is kept
    job = Job().replace(**{"cell.robot": "gantry", "cell.gantry_travel_mm": [400.0, 200.0]})
    assert tuple(job.cell.ee_origin_mm) == (200.0, 100.0)
    own = job.replace(**{"cell.ee_origin_mm": [50.0, 60.0]})
    assert tuple(own.cell.ee_origin_mm) == (50.0, 60.0)
    assert tuple(Job().cell.ee_origin_mm) == (260.0, -100.0)  # SCARA unchanged
    f = tmp_path / "gantry.toml"
    f.write_text('[cell]\nrobot = "gantry"\n', encoding="utf-8")
    assert tuple(load_job(f).cell.ee_origin_mm) == (150.0, 150.0)
    saved = tmp_path / "saved.toml"
    saved.write_text(to_toml(job), encoding="utf-8")
    assert load_job(saved) == job


def test_scara_joint_resolution_from_the_job():
    robot = get_robot(Job().replace(**{"cell.encoder_resolution_deg": 0.002}))
    np.testing.assert_allclose(np.degrees(robot.joint_resolution), [0.002, 0.002, 0.0])
    np.testing.assert_allclose(np.degrees(Scara().joint_resolution), [0.001, 0.001, 0.0])


def test_scara_known_configurations():
    r = Scara()
    q = r.ik(np.array([[600.0, 0.0], [325.0, 275.0], [0.0, 600.0]]))
    np.testing.assert_allclose(q[0, :2], [0.0, 0.0], atol=1e-6)
    # elbow right: theta2 >= 0, point straight above the end of link 1
    np.testing.assert_allclose(np.degrees(q[1, :2]), [0.0, 90.0], atol=1e-9)
    np.testing.assert_allclose(np.degrees(q[2, :2]), [90.0, 0.0], atol=1e-6)
    # eq. 4.11: theta4 keeps the end-effector orientation phi
    np.testing.assert_allclose(q[:, 2], 0.0 - q[:, 0] - q[:, 1])
    left = Scara(elbow="left").ik(np.array([[325.0, -275.0]]))
    np.testing.assert_allclose(np.degrees(left[0, :2]), [0.0, -90.0], atol=1e-9)


@given(st.floats(170.0, 599.0), st.floats(-1.5, 1.5), st.sampled_from(["right", "left"]))
def test_scara_fk_inverts_ik(r, ang, elbow):
    robot = Scara(elbow=elbow)
    p = np.array([[r * np.cos(ang), r * np.sin(ang)]])
    q = robot.ik(p)
    np.testing.assert_allclose(robot.fk(q), p, atol=1e-9)
    assert (q[0, 1] >= 0) == (elbow == "right") or abs(q[0, 1]) < 1e-12


def test_scara_reach_matches_joint_2_range():
    # the minimum reach 163 mm corresponds to theta2 = 150 deg (thesis Cobra 600 data)
    r = Scara()
    rmin = np.sqrt(r.l1 ** 2 + r.l2 ** 2 + 2 * r.l1 * r.l2 * np.cos(np.radians(150.0)))
    assert abs(rmin - 163.0) < 0.5


@pytest.mark.parametrize("point, words", [
    ((612.0, 10.0), "radius 612.082 mm outside the reach"),
    ((100.0, 0.0), "radius 100.000 mm outside the reach"),
    ((-400.0, 50.0), "joint 1"),
])
def test_workspace_error_names_layer_path_point(point, words):
    pts = np.array([[300.0, 0.0], [310.0, 0.0], point, [300.0, 5.0]])
    with pytest.raises(WorkspaceError) as exc:
        check_workspace(pts, Scara(), layer=7, path=3)
    msg = str(exc.value)
    assert "layer 7" in msg and "path 3" in msg and "point 2" in msg
    assert f"({point[0]:.3f}, {point[1]:.3f})" in msg
    assert words in msg


def test_workspace_ok_and_bad_shape():
    check_workspace(np.array([[300.0, -100.0], [260.0, 40.0]]), Scara())
    with pytest.raises(WorkspaceError, match="shape"):
        check_workspace(np.zeros((3, 3)), Scara())


def test_gantry_identity_and_travel():
    g = Gantry(travel=(200.0, 100.0))
    p = np.array([[0.0, 0.0], [150.0, 99.0]])
    np.testing.assert_array_equal(g.ik(p), p)
    np.testing.assert_array_equal(g.fk(g.ik(p)), p)
    check_workspace(p, g)
    with pytest.raises(WorkspaceError, match=r"point 1 at \(10.000, 120.000\).*y = 120.000"):
        check_workspace(np.array([[1.0, 1.0], [10.0, 120.0]]), g, path=0)


# -- the whole-box reach test (issue 17: the paths and motion stages skip the point-by-point
# inverse kinematics of a layer whose box lies inside every limit)

_scaras = st.builds(
    lambda l1, l2, rmin, rmax, j1, j2, elbow: Scara(
        l1=l1, l2=l2, reach=(rmin, rmax), joint_range=(np.radians(j1), np.radians(j2)),
        elbow=elbow),
    st.floats(150.0, 400.0), st.floats(100.0, 400.0), st.floats(0.0, 300.0),
    st.floats(300.0, 800.0), st.floats(30.0, 179.0), st.floats(30.0, 179.0),
    st.sampled_from(["right", "left"]))


def _near(robot: Scara, f1: float, f2: float) -> np.ndarray:
    """A point of the robot's: joints at fractions f1, f2 (-1..1) of their ranges."""
    j1, j2 = robot.joint_range
    q2 = abs(f2) * j2 * (1.0 if robot.elbow == "right" else -1.0)
    return robot.fk(np.array([[f1 * j1, q2]]))[0]


#: joint fractions, often near the ends of the range (where a careless box test fails)
_fractions = st.one_of(st.floats(-1.0, 1.0), st.floats(0.9, 1.0), st.floats(-1.0, -0.9))


@given(_scaras, _fractions, _fractions, st.floats(0.0, 150.0), st.floats(0.0, 150.0))
def test_a_box_the_scara_passes_holds_no_unreachable_point_nor_chord(robot, f1, f2, w, h):
    c = _near(robot, f1, f2)   # boxes about reachable points: a fair share passes
    lo, hi = c - [w / 2.0, h / 2.0], c + [w / 2.0, h / 2.0]
    if not robot.box_reachable(lo, hi):
        return
    # a dense grid over the box, its corners and its edges; chords between any two of
    # them stay in the box, so the grid's points stand for them
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 41), np.linspace(lo[1], hi[1], 41))
    pts = np.c_[gx.ravel(), gy.ravel()]
    bad, _ = robot._point_violations(pts)
    assert not len(bad)


def test_the_box_test_passes_what_lies_inside_and_refuses_what_does_not():
    r = Scara()   # reach 163..600 mm, joints 1 / 2 within 105 / 150 deg
    assert r.box_reachable([200.0, -150.0], [480.0, 150.0])   # the bunny's place, about
    assert not r.box_reachable([-10.0, -10.0], [10.0, 10.0])          # around the base
    assert not r.box_reachable([500.0, -10.0], [620.0, 10.0])          # beyond the reach
    assert not r.box_reachable([np.nan, 0.0], [300.0, 10.0])
    assert not r.box_reachable([300.0, 0.0], [200.0, 10.0])            # lo above hi
    # joint 1 near its limit: behind the base on the side the elbow swings out to
    q = np.radians([[104.0, 30.0], [104.9, 30.0], [105.1, 30.0]])
    p = r.fk(q)
    assert r.box_reachable(p[0] - 1e-3, p[0] + 1e-3)
    assert r.box_reachable(p[1] - 1e-3, p[1] + 1e-3)   # 0.1 deg inside: not too careful
    assert not r.box_reachable(p[2] - 1e-3, p[2] + 1e-3)
    # the shoulder's angle peaks inside the box's radii, at r = sqrt(l1^2 - l2^2) = 173.2
    # mm, 7.4e-4 rad above its value at 165 and 185 mm: joint 1's range 3e-4 rad short of
    # it leaves the box's middle out of range, though its ends are in
    c2 = (30_000.0 - 325.0 ** 2 - 275.0 ** 2) / (2.0 * 325.0 * 275.0)
    peak = float(np.arctan2(275.0 * np.sin(np.arccos(c2)), 325.0 + 275.0 * c2))
    short = Scara(joint_range=(peak - 3e-4, np.radians(150.0)))
    assert short._point_violations(np.array([[np.sqrt(30_000.0), 0.0]]))[0].size == 1
    assert not short.box_reachable([165.0, -1e-3], [185.0, 1e-3])
    assert Scara(joint_range=(peak + 3e-4, np.radians(150.0))).box_reachable(
        [165.0, -1e-3], [185.0, 1e-3])
    g = Gantry(travel=(200.0, 100.0))
    assert g.box_reachable([0.0, 0.0], [200.0, 100.0])
    assert not g.box_reachable([0.0, 0.0], [200.1, 100.0])


@given(_scaras, st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(0.1, 400.0),
       st.lists(st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)), min_size=1,
                max_size=30))
def test_workspace_violations_are_those_point_by_point(robot, f1, f2, spread, pts):
    xy = _near(robot, f1, f2) + spread * np.array(pts, dtype=np.float64)
    bad, reasons = robot.workspace_violations(xy)
    bad0, reasons0 = robot._point_violations(xy)
    np.testing.assert_array_equal(bad, bad0)
    assert reasons == reasons0


def test_the_scara_jacobian_is_the_derivative_of_its_ik():
    """The analytic Jacobian the planner's vertex bounds take (``Scara.jacobian``) against
    central differences of ``ik`` (what a robot without one gets, motion._ik_jacobian), over
    the reach and behind the base where joint 1's angle wraps."""
    from icefab.motion import _ik_jacobian

    class OnlyIk:
        def __init__(self, robot):
            self.robot = robot

        def ik(self, xy):
            return self.robot.ik(xy)

    robot = Scara()
    rng = np.random.default_rng(3)
    th = rng.uniform(-np.pi, np.pi, 3000)
    r = rng.uniform(170.0, 598.0, 3000)
    xy = np.c_[r * np.cos(th), r * np.sin(th)]
    own, fd = robot.jacobian(xy), _ik_jacobian(OnlyIk(robot), xy)
    scale = np.abs(own).max(axis=(1, 2))[:, None, None]
    assert np.abs(own - fd).max(axis=(1, 2)).max() <= 1e-6 * scale.max()
    assert (np.abs(own - fd) <= 1e-6 * scale).all()
    g = get_robot(Job().replace(**{"cell.robot": "gantry"}))
    np.testing.assert_array_equal(g.jacobian(xy[:4]), np.broadcast_to(np.eye(2), (4, 2, 2)))
