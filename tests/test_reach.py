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

    check = motion.check_layer_workspace

    def refusing(lp, job, robot=None):
        if lp.index == 2:
            raise WorkspaceError(f"layer {lp.index}, path 0: point 0 at (0.000, 0.000) mm "
                                 "(robot base frame) is out of the scara workspace: a test")
        check(lp, job, robot)

    monkeypatch.setattr(paths, "plan_layer", counting)
    monkeypatch.setattr(motion, "check_layer_workspace", refusing)
    tm = trimesh.creation.box(extents=(20.0, 20.0, 5.0))
    write_stl(Mesh(tm.vertices, tm.faces, "box"), tmp_path / "box.stl")
    (tmp_path / "job.toml").write_text("[cell]\ncpus = 1\n")   # serial: layers in order
    code = main(["paths", str(tmp_path / "box.stl"), "-c", str(tmp_path / "job.toml"),
                 "-o", str(tmp_path / "out")])
    _out, err = capsys.readouterr()
    assert code == 2 and "layer 2, path 0" in err
    assert planned == [0, 1, 2] and not (tmp_path / "out").exists()
