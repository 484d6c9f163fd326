"""``icefab plan`` end to end: toolpath file and mesh inputs, outputs, errors."""
from __future__ import annotations

import numpy as np

from icefab import Job
from icefab.cli import main
from icefab.motion import load_trajectories


def test_plan_toolpath_file(tmp_path, capsys):
    from icefab.paths import save_toolpaths
    from test_motion_io import _toolpaths
    job = Job()
    tp = _toolpaths(job, 3)
    src = tmp_path / "tp.npz"
    save_toolpaths(tp, src)
    out = tmp_path / "out"
    assert main(["plan", str(src), "-o", str(out), "--layers", "0,2"]) == 0
    text = capsys.readouterr().out
    assert "constant-speed estimate" in text and "build motion time (MTTS)" in text
    assert "constant speed, planned" in text
    assert (out / "speed_layer_0.png").stat().st_size > 1000
    assert (out / "speed_layer_2.png").exists()
    motion = load_trajectories(out / "trajectories.npz")
    assert len(motion) == 3
    assert "reduction" in (out / "summary.txt").read_text()


def test_plan_mesh_no_jerk(tmp_path, capsys):
    import trimesh
    mesh = trimesh.creation.annulus(r_min=15, r_max=30, height=0.75, sections=96)
    src = tmp_path / "ring.stl"
    mesh.export(src)
    out = tmp_path / "o"
    assert main(["plan", str(src), "-o", str(out), "--no-jerk", "--layers", "0"]) == 0
    assert "jerk off" in capsys.readouterr().out
    motion = load_trajectories(out / "trajectories.npz")
    assert motion.n_points > 100
    assert not motion.job.motion.jerk_limited
    assert np.isfinite([lm.duration for lm in motion.layers]).all()


def test_plan_errors_leave_nothing(tmp_path, capsys):
    out = tmp_path / "o"
    assert main(["plan", str(tmp_path / "nope.stl"), "-o", str(out)]) == 2
    assert "not found" in capsys.readouterr().err
    assert not out.exists()
    from icefab.paths import save_toolpaths
    from test_motion_io import _toolpaths
    src = tmp_path / "tp.npz"
    save_toolpaths(_toolpaths(Job(), 2), src)
    assert main(["plan", str(src), "-o", str(out), "--layers", "7"]) == 2
    assert "--layers" in capsys.readouterr().err
    assert not out.exists()
