"""Out-of-reach parts (issue 11): the error names the settings that move the part, and
`icefab paths` checks reach before it prints a build-time estimate."""
from __future__ import annotations

import trimesh

from icefab.cli import main
from icefab.core import Mesh
from icefab.errors import MOVE_PART, WorkspaceError
from icefab.mesh import write_stl


def test_reach_errors_name_the_settings_that_move_the_part():
    e = WorkspaceError("point 219 at (177.2, -270.3) mm is out of the scara workspace: "
                       "joint 1 at -106.96 deg beyond its range")
    assert str(e).endswith(MOVE_PART) and "cell.ee_origin_mm" in str(e)
    assert "parts.translation" in str(e)
    other = WorkspaceError("path points must be an (n, 2) array in mm, got shape (3,)")
    assert "cell.ee_origin_mm" not in str(other)
    # the placement checks name the settings themselves: not twice (hunt Q)
    placed = WorkspaceError("the placed part needs joint 1 at -170.16 deg at part point (-450, "
                            "-198) mm, beyond its range +/-105 deg (cell.joint_range_deg): "
                            "move or scale it (...) or the part origin (cell.ee_origin_mm = "
                            "[260.0, -100.0])")
    assert MOVE_PART not in str(placed)


def test_a_scaffold_path_out_of_reach_names_the_scaffold_buffer(tmp_path, capsys):
    """A scaffold 100 mm around a small box leaves joint 1's range: the message named only
    the part's placement (hunt Q). The slicer's check of the placed part took the
    scaffold's angle as buffer / radius at the box's corners and passed it; it now takes
    the circles around the part and the mitred corners of its hull (the paths stage's
    check is met from a stack sliced without the buffer)."""
    tm = trimesh.creation.box(extents=(20.0, 20.0, 3.0))
    write_stl(Mesh(tm.vertices, tm.faces, "box"), tmp_path / "box.stl")
    (tmp_path / "job.toml").write_text("[scaffold]\nbuffer_mm = 100.0\n")
    code = main(["slice", str(tmp_path / "box.stl"), "-c", str(tmp_path / "job.toml"),
                 "-o", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 2 and not (tmp_path / "s").exists()
    assert "with the scaffold around it (scaffold.buffer_mm = 100) needs joint 1 at -109.2" \
        in err and "beyond its range +/-105 deg" in err
    (tmp_path / "job.toml").write_text("[scaffold]\nbuffer_mm = 60.0\n")
    assert main(["slice", str(tmp_path / "box.stl"), "-c", str(tmp_path / "job.toml"),
                 "-o", str(tmp_path / "s")]) == 0   # within range: the check passes it
    (tmp_path / "job.toml").write_text("[scaffold]\nbuffer_mm = 100.0\n")
    capsys.readouterr()
    code = main(["paths", str(tmp_path / "s" / "stack.npz"), "-c",
                 str(tmp_path / "job.toml"), "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "beyond its range" in err
    assert "(a scaffold path: the scaffold reaches scaffold.buffer_mm = 100 mm beyond the " \
           "part); move the part" in err


def test_paths_refuses_an_unreachable_placement_before_its_estimate(tmp_path, capsys):
    tm = trimesh.creation.box(extents=(20.0, 20.0, 2.0))
    write_stl(Mesh(tm.vertices, tm.faces, "box"), tmp_path / "box.stl")
    (tmp_path / "job.toml").write_text("[cell]\nee_origin_mm = [2000.0, 0.0]\n")
    code = main(["paths", str(tmp_path / "box.stl"), "-c", str(tmp_path / "job.toml"),
                 "-o", str(tmp_path / "out")])
    out, err = capsys.readouterr()
    assert code == 2
    errors = [line for line in err.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and "cell.ee_origin_mm" in errors[0]
    assert "build time" not in out.lower() and not (tmp_path / "out").exists()


def test_paths_stops_planning_at_the_first_unreachable_layer(tmp_path, monkeypatch, capsys):
    """Each layer's reach is checked as the layer comes back: a build that leaves the
    workspace at layer 2 is refused there, without planning the 18 layers above it."""
    import icefab.motion as motion
    import icefab.paths as paths

    planned = []
    plan_layer = paths.plan_layer

    def counting(layer, job, measured=None):
        planned.append(layer.index)
        return plan_layer(layer, job, measured)

    check = motion.check_packed_workspace

    def refusing(index, packed, job, robot=None):
        if index == 2:
            raise WorkspaceError(f"layer {index}, path 0: point 0 at (0.000, 0.000) mm "
                                 "(robot base frame) is out of the scara workspace: a test")
        check(index, packed, job, robot)

    monkeypatch.setattr(paths, "plan_layer", counting)
    monkeypatch.setattr(motion, "check_packed_workspace", refusing)
    tm = trimesh.creation.box(extents=(20.0, 20.0, 5.0))
    write_stl(Mesh(tm.vertices, tm.faces, "box"), tmp_path / "box.stl")
    (tmp_path / "job.toml").write_text("[cell]\ncpus = 1\n")   # serial: layers in order
    code = main(["paths", str(tmp_path / "box.stl"), "-c", str(tmp_path / "job.toml"),
                 "-o", str(tmp_path / "out")])
    _out, err = capsys.readouterr()
    assert code == 2 and "layer 2, path 0" in err
    assert planned == [0, 1, 2] and not (tmp_path / "out").exists()


def _layer_of(paths):
    from icefab.core import LayerPaths
    return LayerPaths(index=7, z=1.0, paths=tuple(paths))


def _reach_error(check, *args):
    try:
        check(*args)
    except WorkspaceError as e:
        return str(e)
    return None


def test_the_packed_reach_check_is_the_paths_one():
    """icefab paths checks the workers' packed layers (check_packed_workspace): the same
    verdict and message as check_layer_workspace on the same paths, for a point out of
    reach, a chord across the inner reach circle, a closing edge, other tools' offsets
    and points already in the base frame."""
    import numpy as np

    from icefab import Job
    from icefab.core import Toolpath
    from icefab.motion import check_layer_workspace, check_packed_workspace
    from icefab.resultfiles import pack_paths
    job = Job()
    ok = Toolpath(points=np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0]]), role="fill",
                  width=1.0, closed=True)
    cases = {
        "reachable": [ok, Toolpath(points=np.array([[5.0, 5.0]]), role="measure"),
                      Toolpath(points=np.array([[0.0, 0.0], [3.0, 0.0]]), role="travel",
                               material="scaffold", tool="scaffold")],
        "far point": [ok, Toolpath(points=np.array([[0.0, 0.0], [900.0, 0.0]]),
                                   role="fill", width=1.0)],
        # the base origin is inside the minimum reach: a chord through it
        "chord": [Toolpath(points=np.array([[-300.0, -5.0], [300.0, -5.0]]), frame="base",
                           role="travel")],
        "closing edge": [ok, Toolpath(points=np.array([[300.0, 0.0], [300.0, 1.0],
                                                       [-300.0, 1.0]]), frame="base",
                                      role="boundary", width=1.0, closed=True)],
        "laser": [ok, Toolpath(points=np.array([[0.0, 290.0], [0.0, 900.0]]),
                               role="measure")],
    }
    for name, paths in cases.items():
        lp = _layer_of(paths)
        want = _reach_error(check_layer_workspace, lp, job)
        got = _reach_error(check_packed_workspace, 7, pack_paths(paths), job)
        assert got == want, name
        assert (want is None) == (name == "reachable"), (name, want)
    assert _reach_error(check_packed_workspace, 7, pack_paths([]), job) is None


def test_the_paths_summary_tally_of_packed_layers_is_the_paths_one():
    """PathTally.add_packed (icefab paths' counts, lengths and estimate, from the workers'
    packed layers) gives what the paths themselves give: path_lengths summed one path
    after the other per kind, layer_estimate per layer."""
    import numpy as np

    from icefab import Job
    from icefab.cli.paths_cmd import PathTally
    from icefab.core import Toolpath, path_lengths
    from icefab.paths import layer_estimate
    from icefab.resultfiles import pack_paths
    rng = np.random.default_rng(3)
    job = Job()
    tally = PathTally(job)
    want_counts, want_length = {}, {}
    for li in range(4):
        paths = [Toolpath(points=rng.uniform(-50, 50, (int(rng.integers(1, 6)), 2)),
                          role=str(rng.choice(["boundary", "fill", "measure", "travel"])),
                          material=str(rng.choice(["part", "scaffold"])),
                          closed=bool(rng.integers(2)), width=1.0, layer=li)
                 for _ in range(int(rng.integers(0, 30)))]
        tally.add_packed(pack_paths(paths))
        for p, mm in zip(paths, path_lengths(paths).tolist()):
            key = f"{p.material} {p.role}" if p.role != "travel" else "travel"
            want_counts[key] = want_counts.get(key, 0) + 1
            want_length[key] = want_length.get(key, 0.0) + mm
        assert tally.per_layer[-1] == layer_estimate(_layer_of(paths), job)
    assert tally.counts == want_counts and tally.length == want_length


def test_a_path_where_joint_1_turns_through_180_degrees_is_refused():
    """With cell.joint_range_deg at 180 or more, a path could cross the line where the
    SCARA's joint 1 turns through +/-180 deg: the inverse kinematics gives joint 1 within
    one turn, so its rates read as a full turn in one step, and a 25 degree arc planned
    as 11.7 days of 63 M samples (a hunt's; 'icefab plan' ran out of memory). Refused by
    name; the same arc elsewhere plans in two seconds."""
    import numpy as np
    import pytest

    from icefab import Job
    from icefab.motion import plan_motion
    from icefab.robots import get_robot

    a = np.radians(np.linspace(-150.0, -125.0, 200))
    arc = 400.0 * np.c_[np.cos(a), np.sin(a)]
    for wide in (180.0, 200.0):
        job = Job().replace(**{"cell.joint_range_deg": [wide, 150.0]})
        t1 = np.degrees(get_robot(job).ik(arc)[[0, -1], 0])
        assert t1[0] > 160 and t1[1] < -160          # it does cross +/-180
        with pytest.raises(WorkspaceError, match=r"path: passes \(-2\d\d\.\d+, -2\d\d\.\d+\) "
                           r"mm .*joint 1 would turn through \+/-180 deg"):
            plan_motion(arc, job)
        front = plan_motion(-arc, job)
        assert front.duration < 5.0
        assert np.abs(np.diff(front.joints[:, 0])).max() < np.radians(1.0)
