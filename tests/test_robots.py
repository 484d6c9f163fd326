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
