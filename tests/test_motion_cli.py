"""``icefab plan`` end to end: toolpath file and mesh inputs, outputs, errors."""
from __future__ import annotations

import numpy as np
import pytest

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
    summary = (out / "plan-summary.txt").read_text()
    assert "minimum-time trajectories take" in summary and "reduction" not in summary


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


def test_plan_a_build_with_empty_layers(tmp_path, capsys):
    # two boxes one above the other, no scaffold: the layers between them have no path,
    # and the trajectory file's writer joined their (0, 0) joints with (k, 3) ones (a
    # hunt's traceback)
    import trimesh
    boxes = trimesh.util.concatenate([
        trimesh.creation.box(bounds=[[0, 0, 0], [20, 20, 1.5]]),
        trimesh.creation.box(bounds=[[0, 0, 2.5], [20, 20, 4.0]])])
    src = tmp_path / "boxes.stl"
    boxes.export(src)
    job = tmp_path / "job.toml"
    job.write_text("[scaffold]\nenabled = false\n[feedback]\nenabled = false\n")
    out = tmp_path / "o"
    assert main(["plan", str(src), "-c", str(job), "-o", str(out)]) == 0
    motion = load_trajectories(out / "trajectories.npz")
    counts = [len(lm.trajectories) for lm in motion.layers]
    assert 0 in counts and counts[0] > 0 and counts[-1] > 0


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


def _toolpath_file(tmp_path, n_layers=2):
    from icefab.paths import save_toolpaths
    from test_motion_io import _toolpaths
    src = tmp_path / "tp.npz"
    save_toolpaths(_toolpaths(Job(), n_layers), src)
    return src


def test_plan_refuses_a_job_that_contradicts_the_toolpaths(tmp_path, capsys):
    """Toolpaths sliced at 0.25 mm planned with a job of 0.5 mm layers: one error naming
    the setting, nothing written (the valves would have laid twice the water)."""
    src = _toolpath_file(tmp_path)
    job = tmp_path / "job.toml"
    job.write_text("[slicing]\nlayer_thickness_mm = 0.5\n")
    out = tmp_path / "o"
    assert main(["plan", str(src), "-c", str(job), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "the toolpaths were made with slicing.layer_thickness_mm = 0.25, the job has 0.5" \
        in err and "icefab paths" in err
    assert not out.exists()


def test_plan_gcode_and_constant_spacing_outputs(tmp_path, capsys):
    src = _toolpath_file(tmp_path)
    out = tmp_path / "o"
    gantry = tmp_path / "gantry.toml"
    gantry.write_text('[cell]\nrobot = "gantry"\n')
    assert main(["plan", str(src), "-c", str(gantry), "-o", str(out), "--layers", "0",
                 "--gcode", "--constant-spacing", "0.5"]) == 0
    assert "trajectories.gcode" in capsys.readouterr().out
    motion = load_trajectories(out / "trajectories.npz")
    trajs = [t for lm in motion.layers for t in lm.trajectories]
    # G-code (icefab.export): per layer a Z move, per path a comment, G0 to its start,
    # then a move per time step (G1 ... S duty depositing, G0 ... S0 travel) whose
    # feedrates are the trajectory's speeds x 60 (mm/min)
    text = (out / "trajectories.gcode").read_text()
    assert text.count("G0 Z") == len(motion.layers) + 1   # and the lift at the end
    # the nozzle goes to each layer's top, not its cutting plane at mid-height (a tester's
    # box had its nozzle ordered into its own bead)
    dh = motion.job.slicing.layer_thickness_mm
    zs = [float(ln[4:].split()[0]) for ln in text.splitlines() if ln.startswith("G0 Z")]
    np.testing.assert_allclose(zs[:-1], [lm.z + 0.5 * dh for lm in motion.layers], atol=1e-4)
    # the steps' moves: not a layer's Z move nor a path's G0 to its start (its first move
    # after its comment), which carry the travel speed as their F
    g1, first = [], False
    for ln in text.splitlines():
        if ln.startswith("; path"):
            first = True
        elif ln.startswith(("G1 ", "G0 ")) and not ln.startswith("G0 Z"):
            if not first:
                g1.append(ln)
            first = False
    assert len(g1) == sum(len(t.xy) - 1 for t in trajs)
    feeds = np.array([float(ln.split("F")[1].split()[0]) for ln in g1])
    speeds = np.concatenate([0.5 * (t.speed[1:] + t.speed[:-1]) for t in trajs])
    np.testing.assert_allclose(feeds, 60.0 * speeds, rtol=0.02, atol=30.0)
    assert feeds.max() <= 60.0 * motion.job.motion.speed_mm_s * 1.01
    # constant spacing: points every <= 0.5 mm, durations adding up to each trajectory's
    with np.load(out / "constant_spacing.npz") as z:
        assert str(z["format"]) == "icefab-constant-spacing" and int(z["version"]) == 1
        assert float(z["spacing_mm"]) == 0.5
        xy, dur, start = z["xy"], z["duration"], z["path_start"]
        assert len(start) == len(trajs) + 1 and start[-1] == len(xy) == len(dur)
        for i, t in enumerate(trajs):
            a, b = start[i], start[i + 1]
            np.testing.assert_allclose(xy[a], t.xy[0])
            np.testing.assert_allclose(xy[b - 1], t.xy[-1], atol=1e-9)
            assert dur[b - 1] == 0.0
            assert dur[a:b].sum() == pytest.approx(t.duration, rel=1e-9)
            if b - a > 1:
                assert np.hypot(*np.diff(xy[a:b], axis=0).T).max() <= 0.5 + 1e-9
        np.testing.assert_array_equal(z["layer"], [t.path.layer for t in trajs])
    assert not list(tmp_path.glob(".o.*"))  # no temporary folder left behind
    # a re-run without those options into the same folder leaves none of them behind
    # (they would no longer match the new trajectories); other files stay
    (out / "notes.txt").write_text("mine")
    assert main(["plan", str(src), "-o", str(out), "--layers", "0"]) == 0
    assert not (out / "trajectories.gcode").exists()
    assert not (out / "constant_spacing.npz").exists()
    assert (out / "trajectories.npz").exists() and (out / "notes.txt").read_text() == "mine"


def test_plan_bad_constant_spacing_and_layers_fail_before_planning(tmp_path, capsys,
                                                                    monkeypatch):
    import icefab.motion
    src = _toolpath_file(tmp_path)
    out = tmp_path / "o"
    planned = []
    real = icefab.motion.plan_toolpaths
    monkeypatch.setattr(icefab.motion, "plan_toolpaths",
                        lambda *a, **k: planned.append(1) or real(*a, **k))
    assert main(["plan", str(src), "-o", str(out), "--constant-spacing", "0"]) == 2
    assert "--constant-spacing" in capsys.readouterr().err
    # positive, but billions of points held in memory (a tester's 0.0001 mm on a 60 mm
    # part: 23 GB, then the kernel's out-of-memory killer)
    assert main(["plan", str(src), "-o", str(out), "--constant-spacing", "1e-6"]) == 2
    err = capsys.readouterr().err
    assert "--constant-spacing 1e-06: the build's constant-spacing output would need" in err \
        and "MAX_SAMPLES" in err
    assert main(["plan", str(src), "-o", str(out), "--layers", "0,9"]) == 2
    assert "--layers" in capsys.readouterr().err
    assert planned == [] and not out.exists()


def test_gcode_whose_pwm_the_job_cannot_hold_is_refused_before_planning(tmp_path, capsys,
                                                                         monkeypatch):
    """An FM job whose valve tops out at 100 Hz is a valid job, but G-code drives the
    valve by PWM at 125 Hz: 'plan --gcode' planned every layer, then failed naming a
    setting the user never set, and 'export gcode' failed the same way (hunt W)."""
    import icefab.motion
    src = _toolpath_file(tmp_path)
    cfg = tmp_path / "g.toml"
    cfg.write_text('[cell]\nrobot = "gantry"\n[flow]\nmax_frequency_hz = 100.0\n')
    planned = []
    real = icefab.motion.plan_toolpaths
    monkeypatch.setattr(icefab.motion, "plan_toolpaths",
                        lambda *a, **k: planned.append(1) or real(*a, **k))
    out = tmp_path / "o"
    assert main(["plan", str(src), "-c", str(cfg), "-o", str(out), "--layers", "0",
                 "--gcode"]) == 2
    err = capsys.readouterr().err
    assert "--gcode: G-code drives the valve by PWM" in err
    assert "flow.pwm_frequency_hz = 125: must not exceed flow.max_frequency_hz = 100" in err
    assert planned == [] and not out.exists()
    assert main(["plan", str(src), "-c", str(cfg), "-o", str(out), "--layers", "0"]) == 0
    capsys.readouterr()
    assert main(["export", "gcode", str(out / "trajectories.npz"), "-o",
                 str(tmp_path / "g")]) == 2
    assert "G-code drives the valve by PWM" in capsys.readouterr().err
    assert not (tmp_path / "g").exists()


def test_gcode_ends_with_the_nozzle_lifted_clear_of_the_part(tmp_path):
    """The program ended at the last path's end: the nozzle stood on the last bead (in the
    ice) when the machine stopped. Its last move lifts it 20 mm above the last layer's top,
    valve closed, at most to the vertical stroke, before the valve is switched off."""
    from icefab.export import END_LIFT_MM, gcode_lines

    src = _toolpath_file(tmp_path)
    cfg = tmp_path / "g.toml"
    cfg.write_text('[cell]\nrobot = "gantry"\n')
    out = tmp_path / "o"
    assert main(["plan", str(src), "-c", str(cfg), "-o", str(out), "--layers", "0",
                 "--gcode"]) == 0
    motion = load_trajectories(out / "trajectories.npz")
    top = motion.layers[-1].top(motion.job)
    lines = (out / "trajectories.gcode").read_text().splitlines()
    assert END_LIFT_MM == 20.0
    assert lines[-1] == "M5" and lines[-2].startswith(f"G0 Z{top + 20.0:.4f} F") \
        and lines[-2].endswith(" S0")
    # the last XY move before the lift is the last path's end, at the layer's top
    last = [ln for ln in lines if ln.startswith(("G0 X", "G1 X"))][-1]
    assert lines.index(last) < len(lines) - 2
    # a stroke that leaves less than 20 mm above the part: lifted to the stroke's end
    short = motion.job.replace(**{"cell.stroke_mm": top + 5.0})
    lines = list(gcode_lines(motion, short))
    assert lines[-1] == "M5" and lines[-2].startswith(f"G0 Z{top + 5.0:.4f} F")


def test_gcode_of_no_layers_is_refused_and_one_layer_is_one(tmp_path, capsys):
    """A trajectories file of no layers gave a G-code file of no moves, exit 0; one layer
    was "1 layers" (hunt W)."""
    import dataclasses

    from icefab.resultfiles import save_trajectories
    src = _toolpath_file(tmp_path)
    cfg = tmp_path / "g.toml"
    cfg.write_text('[cell]\nrobot = "gantry"\n')
    out = tmp_path / "o"
    assert main(["plan", str(src), "-c", str(cfg), "-o", str(out), "--layers", "0"]) == 0
    motion = load_trajectories(out / "trajectories.npz")
    save_trajectories(dataclasses.replace(motion, layers=()), tmp_path / "zero.npz")
    capsys.readouterr()
    assert main(["export", "gcode", str(tmp_path / "zero.npz"), "-o", str(tmp_path / "z")]) == 2
    assert "holds no layers" in capsys.readouterr().err and not (tmp_path / "z").exists()
    save_trajectories(dataclasses.replace(motion, layers=motion.layers[:1]),
                      tmp_path / "one.npz")
    assert main(["export", "gcode", str(tmp_path / "one.npz"), "-o", str(tmp_path / "g")]) == 0
    assert "(Marlin, 1 layer, " in capsys.readouterr().out


def test_plan_gantry_with_the_default_cell(tmp_path, capsys):
    # [cell] robot = "gantry" alone: the default part origin (260, -100) is a SCARA
    # position; the gantry builds at the centre of its travel
    import trimesh
    mesh = trimesh.creation.annulus(r_min=15, r_max=30, height=0.75, sections=96)
    src = tmp_path / "ring.stl"
    mesh.export(src)
    cfg = tmp_path / "gantry.toml"
    cfg.write_text('[cell]\nrobot = "gantry"\n', encoding="utf-8")
    out = tmp_path / "o"
    assert main(["plan", str(src), "-c", str(cfg), "-o", str(out), "--gcode"]) == 0
    assert "(gantry, jerk on)" in capsys.readouterr().out
    motion = load_trajectories(out / "trajectories.npz")
    assert motion.robot == "gantry" and motion.joint_names == ("x", "y")
    assert tuple(motion.job.cell.ee_origin_mm) == (150.0, 150.0)
    xy = np.concatenate([t.xy for lm in motion.layers for t in lm.trajectories])
    assert (xy >= 0.0).all() and (xy <= 300.0).all()
    # the part (a 60 mm ring centred on its origin) sits around the travel centre
    assert np.abs(xy.mean(axis=0) - 150.0).max() < 15.0
    assert (out / "trajectories.gcode").stat().st_size > 1000


def test_gantry_default_origin_is_the_same_in_every_stage():
    """A gantry job that never went through the motion stage (paths to base frame, valve
    programs' part points, the simulator) uses the same travel-centre origin as the
    planner, so a trajectory planned here maps back onto its part points."""
    import numpy as np

    from icefab import Job
    from icefab.flow import trajectory_part_xy
    from icefab.motion import plan_motion
    from icefab.paths import to_base_frame
    from icefab.core import Toolpath

    job = Job().replace(**{"cell.robot": "gantry"})
    centre = 0.5 * np.asarray(job.cell.gantry_travel_mm, dtype=float)
    assert np.allclose(job.cell.ee_origin_mm, centre)
    part = np.array([[-20.0, -10.0], [20.0, -10.0], [20.0, 10.0], [-20.0, 10.0]])
    path = Toolpath(points=part, material="part", role="boundary", closed=True, width=1.5)
    traj = plan_motion(path, job)  # a part-frame Path goes to the base frame in the planner
    assert np.abs(traj.xy[0] - to_base_frame(part, "part", job)[0]).max() < 1e-6
    back = trajectory_part_xy(traj, "part", job)
    assert np.abs(back[0] - part[0]).max() < 1e-6
    assert back[:, 0].min() >= -20.0 - 1e-6 and back[:, 0].max() <= 20.0 + 1e-6
    # a SCARA job keeps the thesis origin untouched
    assert np.allclose(Job().cell.ee_origin_mm, (260.0, -100.0))
