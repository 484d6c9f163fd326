"""A ``-c`` job given to a command that reads a result file (README, "A command reading
another command's file"): the file's job overlaid with the settings the job file names.
A named setting the file decided (``icefab.stages.DECIDED``: layers, widths, offsets,
measured layers, the parts) that differs from the file's is refused naming the file and
the setting; anything else named applies; nothing unnamed changes (a reviewer's flow-only
job on 1.0 mm layers was refused for the default 0.25 mm it never named, and paths
recorded another part's files beside a stack's geometry)."""

from __future__ import annotations

import pytest
from hypothesis import given, settings, strategies as st

from icefab import stages
from icefab.cli import main
from icefab.config import Job, load_named_job
from icefab.errors import ConfigError

CLAMP = '[flow]\nout_of_range = "clamp"\n'


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A 30 x 30 x 4 mm box sliced, laid and planned at 1.0 mm layers through the commands
    with one job file (the reviewer's repro, smaller than the demo mug): its folder."""
    import trimesh

    d = tmp_path_factory.mktemp("thick")
    for name, size in (("box", (30.0, 30.0, 4.0)), ("other", (20.0, 10.0, 4.0))):
        box = trimesh.creation.box(extents=size)
        box.apply_translation((0.0, 0.0, 2.0))
        box.export(d / f"{name}.stl")
    (d / "b.toml").write_text("[cell]\ncpus = 1\n[slicing]\nlayer_thickness_mm = 1.0\n")
    job = ["-c", str(d / "b.toml")]
    assert main(["slice", str(d / "box.stl"), *job, "-o", str(d / "s")]) == 0
    assert main(["paths", str(d / "s" / "stack.npz"), *job, "-o", str(d / "p")]) == 0
    assert main(["plan", str(d / "p" / "toolpaths.npz"), *job, "-o", str(d / "t")]) == 0
    return d


@pytest.mark.parametrize("command", ["valves", "simulate"])
def test_a_flow_only_job_runs_on_thicker_layers_and_takes_effect(built, tmp_path, capsys,
                                                                 command):
    """The reviewer's M1: trajectories of 1.0 mm layers, a job file naming only the flow's
    out-of-range rule: it runs with the file's layers and clamps (without it the same
    trajectories stop at the valve's limit: the setting took effect)."""
    traj = str(built / "t" / "trajectories.npz")
    (tmp_path / "clamp.toml").write_text(CLAMP)
    capsys.readouterr()
    assert main([command, traj, "-o", str(tmp_path / "plain")]) == 2
    assert "set flow.out_of_range = 'clamp'" in capsys.readouterr().err
    assert main([command, traj, "-c", str(tmp_path / "clamp.toml"),
                 "-o", str(tmp_path / "out")]) == 0
    said = capsys.readouterr()
    assert "clamped (flow.out_of_range = 'clamp')" in said.out, said.err


@pytest.mark.parametrize("command", ["valves", "simulate"])
@pytest.mark.parametrize("text,named", [
    ("[slicing]\nlayer_thickness_mm = 0.5\n", "slicing.layer_thickness_mm = 1.0, the job "
                                               "has 0.5"),
    ("[parts]\nscale = [2.0, 2.0, 2.0]\n", "parts.scale = [1.0, 1.0, 1.0], the job has "
                                          "[2.0, 2.0, 2.0]"),
])
def test_a_job_naming_other_decided_settings_is_refused(built, tmp_path, capsys, command,
                                                        text, named):
    """A job file naming another layer thickness or other parts than the trajectories
    were made with: one error naming the file and the setting, each command to run again
    in its own quotes (they were one: "('icefab paths, then icefab plan')")."""
    traj = built / "t" / "trajectories.npz"
    (tmp_path / "other.toml").write_text(CLAMP + text)
    assert main([command, str(traj), "-c", str(tmp_path / "other.toml"),
                 "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert f"{traj}: the trajectories were made with {named}" in err, err
    assert "('icefab paths', then 'icefab plan')" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_paths_refuses_another_parts_job_and_keeps_the_stacks(built, tmp_path, capsys):
    """The reviewer's M3: 'icefab paths stack.npz -c JOB' with another part's job exited 0
    and recorded that part's files and scale beside the stack's geometry; now refused
    naming the setting. A job naming a speed applies it and keeps the stack's parts."""
    from icefab.resultfiles import load_stack, load_toolpaths

    stack = built / "s" / "stack.npz"
    (tmp_path / "other.toml").write_text(   # the stack's layers, another part
        f'[parts]\nfiles = ["{built / "other.stl"}"]\nscale = [4.0, 4.0, 4.0]\n'
        "[slicing]\nlayer_thickness_mm = 1.0\n")
    capsys.readouterr()
    assert main(["paths", str(stack), "-c", str(tmp_path / "other.toml"),
                 "-o", str(tmp_path / "q")]) == 2
    err = capsys.readouterr().err
    assert f"{stack}: the stack's layers were made with parts.files = " \
           f"['{built / 'box.stl'}'], the job has ['{built / 'other.stl'}'] (and 1 more)" \
           in err, err
    assert not (tmp_path / "q").exists()
    (tmp_path / "speed.toml").write_text("[motion]\nspeed_mm_s = 100.0\n")
    assert main(["paths", str(stack), "-c", str(tmp_path / "speed.toml"),
                 "-o", str(tmp_path / "fast")]) == 0
    job = load_toolpaths(tmp_path / "fast" / "toolpaths.npz").job
    assert job.motion.speed_mm_s == 100.0
    assert job.replace(**{"motion.speed_mm_s": load_stack(stack).job.motion.speed_mm_s}) \
        == load_stack(stack).job


def test_a_legacy_control_file_names_its_entries(tmp_path):
    """A legacy control file is a job file too: its entries are what it names (a vector
    switched off names nothing), so the same file agrees with what it made."""
    (tmp_path / "box.stl").write_text("")
    (tmp_path / "control.txt").write_text(
        "1\t[int] Number of STL and/or PLY files to import\n"
        "box.stl\t[char] STL and/or PLY file names\n"
        "1.0\t[mm] Slice thickness\n"
        "0 2 2 2\t[float] Scaling vector\n")
    job, named = load_named_job(tmp_path / "control.txt")
    assert named == {"parts.files", "slicing.layer_thickness_mm"}
    made = Job().replace(**{"parts.files": job.parts.files,
                            "slicing.layer_thickness_mm": 1.0, "motion.speed_mm_s": 90.0})
    assert stages.overlay_job(made, job, named, "s.npz: the stack's layers", "x") == made


def test_a_toml_job_names_its_keys(tmp_path):
    """A TOML job names its keys, not the defaults it is filled with (an empty table names
    nothing)."""
    f = tmp_path / "j.toml"
    f.write_text('[flow]\nout_of_range = "clamp"\n[materials.part]\nfill_angle_deg = 30.0\n'
                 "[motion]\n")
    job, named = load_named_job(f)
    # an angle given asks for it: the mode it sets ('fixed') is named too
    assert named == {"flow.out_of_range", "materials.part.fill_angle_deg",
                     "materials.part.fill_angle_mode"}
    assert job.materials.part.fill_angle_mode == "fixed"


#: A file's job and a job file's (its unnamed settings the defaults), differing in decided
#: settings (layer thickness, parts, the measurement interval) and in others.
MADE = Job().replace(**{"slicing.layer_thickness_mm": 1.0, "parts.scale": (2.0, 2.0, 2.0),
                        "feedback.interval_layers": 2, "motion.speed_mm_s": 80.0,
                        "cell.cpus": 1})
GIVEN = Job().replace(**{"flow.out_of_range": "clamp", "motion.speed_mm_s": 60.0,
                         "simulation.seed": 5, "materials.part.fill_pattern": "zigzag",
                         "feedback.kp": 0.5, "parts.close_holes": False})
KEYS = list(stages._flat(Job()))


@settings(max_examples=60, deadline=None)
@given(st.sets(st.sampled_from(KEYS), max_size=12))
def test_the_overlay_is_the_files_job_but_for_the_named_settings(named):
    """Property: for any set of named settings, the job is the file's except the named
    ones, which are the job file's; or, when a named decided setting differs, an error
    naming the first such."""
    fm, fg = stages._flat(MADE), stages._flat(GIVEN)
    bad = [k for k in stages.DECIDED if k in named and fm[k] != fg[k]]
    if bad:
        with pytest.raises(ConfigError, match=rf"^t.npz: the toolpaths were made with "
                                              rf"{bad[0]} = "):
            stages.overlay_job(MADE, GIVEN, named, "t.npz: the toolpaths", "icefab paths")
        return
    out = stages._flat(stages.overlay_job(MADE, GIVEN, named, "t.npz: the toolpaths",
                                          "icefab paths"))
    assert out == {k: (fg[k] if k in named else fm[k]) for k in KEYS}


def test_a_named_setting_that_decides_nothing_in_either_job_is_applied():
    """The measurement interval of two jobs that measure nothing, the adaptive bounds of
    two uniform ones (as check_agrees has it): named, they apply."""
    off = MADE.replace(**{"feedback.enabled": False})
    again = Job().replace(**{"feedback.enabled": False, "feedback.interval_layers": 9,
                             "slicing.max_layer_thickness_mm": 2.0})
    out = stages.overlay_job(off, again, {"feedback.enabled", "feedback.interval_layers",
                                          "slicing.max_layer_thickness_mm"}, "x", "y")
    assert out.feedback.interval_layers == 9 and out.slicing.max_layer_thickness_mm == 2.0
    with pytest.raises(ConfigError, match="slicing.cusp_height_mm = 0.0, the job has 0.1"):
        stages.overlay_job(off, again.replace(**{"slicing.cusp_height_mm": 0.1}),
                           {"slicing.cusp_height_mm"}, "x", "y")


def test_a_job_naming_another_robot_gives_it_that_robots_part_origin():
    """A gantry's result file given a job naming robot = "scara" kept the gantry's part
    origin (150, 150), a point of the gantry's base frame, for the SCARA (a review's):
    the new robot takes its default origin unless the job file names one."""
    from icefab.config import SCARA_EE_ORIGIN_MM

    gantry = Job().replace(**{"cell.robot": "gantry"})
    assert tuple(gantry.cell.ee_origin_mm) == (150.0, 150.0)   # the centre of its travel
    out = stages.overlay_job(gantry, Job(), {"cell.robot"}, "t.npz: the toolpaths", "x")
    assert out.cell.robot == "scara"
    assert tuple(out.cell.ee_origin_mm) == SCARA_EE_ORIGIN_MM
    wide = gantry.replace(**{"cell.gantry_travel_mm": (400.0, 200.0)})
    back = stages.overlay_job(out, wide, {"cell.robot", "cell.gantry_travel_mm"}, "t", "x")
    assert back.cell.robot == "gantry" and tuple(back.cell.ee_origin_mm) == (200.0, 100.0)
    moved = Job().replace(**{"cell.ee_origin_mm": (300.0, 0.0)})
    named = stages.overlay_job(gantry, moved, {"cell.robot", "cell.ee_origin_mm"}, "t", "x")
    assert tuple(named.cell.ee_origin_mm) == (300.0, 0.0)
    own = gantry.replace(**{"cell.ee_origin_mm": (100.0, 120.0)})   # the same robot named
    assert tuple(stages.overlay_job(own, gantry, {"cell.robot"}, "t", "x").cell.ee_origin_mm) \
        == (100.0, 120.0)


def test_simulating_trajectories_with_another_robot_is_refused_naming_the_robot(
        built, tmp_path, capsys):
    """Trajectories are samples in their robot's base frame: a job naming another robot
    is refused naming cell.robot (it ran a gantry's samples with a SCARA job; with the
    new robot's own origin it would have named the origin, which the job did not name)."""
    (tmp_path / "g.toml").write_text('[cell]\ncpus = 1\nrobot = "gantry"\n'
                                     "[slicing]\nlayer_thickness_mm = 1.0\n")
    assert main(["plan", str(built / "box.stl"), "-c", str(tmp_path / "g.toml"), "-o",
                 str(tmp_path / "t")]) == 0
    (tmp_path / "scara.toml").write_text('[cell]\nrobot = "scara"\n' + CLAMP)
    traj = tmp_path / "t" / "trajectories.npz"
    capsys.readouterr()
    assert main(["simulate", str(traj), "-c", str(tmp_path / "scara.toml"), "-o",
                 str(tmp_path / "s")]) == 2
    assert f"{traj}: the trajectories were made with cell.robot = gantry, the job has " \
           "scara" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


def test_api_callers_whole_jobs_keep_their_check():
    """check_agrees compares whole jobs (API callers): a job of defaults contradicts a file
    of 1.0 mm layers, and the parts are decided now."""
    with pytest.raises(ConfigError, match="slicing.layer_thickness_mm = 1.0, the job has "
                                          r"0.25 \(and 2 more\)"):
        stages.check_agrees(MADE, Job(), "t.npz: the toolpaths", "icefab paths")
    with pytest.raises(ConfigError, match=r"parts.files = \[\], the job has \['a.stl'\]"):
        stages.check_agrees(Job(), Job().replace(**{"parts.files": ("a.stl",)}), "x", "y")
    assert set(stages.PARTS) <= set(stages.DECIDED)


def test_a_gantry_given_another_travel_keeps_its_part_at_the_travels_centre():
    """A gantry's result file given a job with cell.gantry_travel_mm = [160, 160] kept the
    old travel's centre (150, 150) as the part origin, and the part was refused naming
    cell.ee_origin_mm, which the user never set (a gantry hunt's): the origin the old
    travel's default placed moves to the new travel's centre; one set elsewhere stays."""
    gantry = Job().replace(**{"cell.robot": "gantry"})
    small = gantry.replace(**{"cell.gantry_travel_mm": (160.0, 120.0)})
    out = stages.overlay_job(gantry, small, {"cell.gantry_travel_mm"}, "t", "x")
    assert tuple(out.cell.ee_origin_mm) == (80.0, 60.0)
    own = gantry.replace(**{"cell.ee_origin_mm": (100.0, 90.0)})
    kept = stages.overlay_job(own, small, {"cell.gantry_travel_mm"}, "t", "x")
    assert tuple(kept.cell.ee_origin_mm) == (100.0, 90.0)
    named = stages.overlay_job(gantry, small.replace(**{"cell.ee_origin_mm": (70.0, 50.0)}),
                               {"cell.gantry_travel_mm", "cell.ee_origin_mm"}, "t", "x")
    assert tuple(named.cell.ee_origin_mm) == (70.0, 50.0)
    same = stages.overlay_job(gantry, gantry, {"cell.gantry_travel_mm"}, "t", "x")
    assert tuple(same.cell.ee_origin_mm) == (150.0, 150.0)
