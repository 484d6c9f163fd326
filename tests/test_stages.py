"""Stage settings (issue 12): which settings each step reads is declared once
(icefab.stages), and what an earlier stage decided travels with its output."""

from __future__ import annotations

import numpy as np
import pytest

from icefab import stages
from icefab.config import Job
from icefab.core import Layer, Region, Stack
from icefab.errors import ConfigError
from icefab.paths import plan_paths
from icefab.regions import add_scaffold


def _settings(job: Job) -> list[str]:
    return list(stages._flat(job))


def test_every_setting_is_read_by_exactly_one_first_step():
    for key in _settings(Job()):
        step = stages.step_of(key)
        assert step in stages.STEPS or key in stages.NEUTRAL, key
    assert set(stages.PLACEMENT + stages.MEASURED) <= set(_settings(Job()))


@pytest.mark.parametrize("change,first", [
    ({"slicing.layer_thickness_mm": 0.5}, "slice"),
    ({"scaffold.buffer_mm": 3.0}, "scaffold"),
    ({"materials.part.fill_pattern": "zigzag"}, "paths"),
    ({"motion.jerk_limited": False}, "motion"),
    ({"motion.dt_s": 0.008}, "paths"),  # the seconds of one path the robot stores
    ({"flow.tick_s": 0.001}, "valves"),
    ({"simulation.seed": 7}, "simulate"),
    ({"cell.cpus": 1}, None),  # the worker count never changes a result
])
def test_a_change_invalidates_its_first_reader_and_after(change, first):
    a, b = Job(), Job().replace(**change)
    assert stages.first_invalidated(a, b) == first
    for step in stages.STEPS:
        same = first is None or stages.STEPS.index(step) < stages.STEPS.index(first)
        assert (stages.digest(a, step) == stages.digest(b, step)) == same, step


def _stack(thickness: float) -> Stack:
    sq = np.array([[0, 0], [20, 0], [20, 20], [0, 20]], float)
    layers = tuple(Layer(k, (k + 0.5) * thickness, Region((sq,), np.array([-1])),
                         top_z=(k + 1) * thickness) for k in range(3))
    return Stack(layers, Job(), thickness)


def test_a_job_contradicting_the_stacks_thickness_is_an_error():
    # the case: sliced at 0.25 mm, scaffolded with a 0.5 mm job
    stack = _stack(0.25)
    thick = Job().replace(**{"slicing.layer_thickness_mm": 0.5})
    with pytest.raises(ConfigError, match=r"slicing.layer_thickness_mm = 0.5, but the stack "
                                          r"was sliced at 0.25 mm"):
        add_scaffold(stack, thick)
    with pytest.raises(ConfigError, match="sliced at 0.25 mm"):
        plan_paths(stack, thick)
    assert len(add_scaffold(stack, Job())) == 3  # agreeing: fine


def test_trajectories_must_agree_on_the_part_origin_toolpaths_need_not():
    """Trajectories are in the robot's frame, toolpaths in the part's: another part origin
    is refused for the first (SimulationError from the simulator's check) and planned for
    the second; the time step moves no material."""
    from icefab.errors import SimulationError
    from icefab.sim import check_motion_job

    a = Job()
    b = a.replace(**{"cell.ee_origin_mm": (250.0, -90.0), "motion.dt_s": 0.008})
    with pytest.raises(SimulationError, match=r"^t.npz: the trajectories were made with "
                                              r"cell.ee_origin_mm = "):
        check_motion_job(a, b, "t.npz: the trajectories")
    stages.check_agrees(a, b, "tp.npz: the toolpaths", "icefab paths")
    check_motion_job(a, a.replace(**{"motion.dt_s": 0.008}))
    with pytest.raises(SimulationError, match="feedback.interval_layers = 4, the job has 2"):
        check_motion_job(a, a.replace(**{"feedback.interval_layers": 2}))


@pytest.mark.parametrize("change,named", [
    ({"slicing.layer_thickness_mm": 0.5}, "slicing.layer_thickness_mm = 0.25, the job has 0.5"),
    ({"materials.part.fill_width_mm": 2.0}, "materials.part.fill_width_mm"),
    ({"feedback.interval_layers": 1}, "feedback.interval_layers = 4, the job has 1"),
    ({"feedback.enabled": False}, "feedback.enabled = True, the job has False"),
])
def test_a_job_that_contradicts_what_a_file_was_made_with_is_refused(change, named):
    """Decided settings (layer thickness, widths, offsets, the measured layers) must agree
    between an input file's job and the job a later step runs it with; others (speeds, the
    valve's settings, the worker count) may differ."""
    made = Job()
    with pytest.raises(ConfigError, match="tp.npz: the toolpaths were made with") as exc:
        stages.check_agrees(made, made.replace(**change), "tp.npz: the toolpaths",
                            "icefab paths")
    assert named in str(exc.value) and "'icefab paths'" in str(exc.value)
    two = made.replace(**{"slicing.layer_thickness_mm": 0.5, "feedback.interval_layers": 2})
    with pytest.raises(ConfigError, match=r"\(and 1 more\)"):
        stages.check_agrees(made, two, "tp.npz: the toolpaths", "icefab paths")
    stages.check_agrees(made, made.replace(**{"motion.speed_mm_s": 80.0, "flow.mode": "pwm",
                                              "cell.cpus": 1}), "x", "y")
    # two jobs that measure nothing do not disagree on how often
    off = made.replace(**{"feedback.enabled": False})
    stages.check_agrees(off, off.replace(**{"feedback.interval_layers": 9}), "x", "y")
    assert set(stages.DECIDED) <= set(_settings(Job()))


ADAPTIVE = {"slicing.cusp_height_mm": 0.1, "slicing.min_layer_thickness_mm": 0.1,
            "slicing.max_layer_thickness_mm": 0.5}


def _adaptive_stack() -> Stack:
    """Three 0.5 mm layers cut with adaptive layers (thicker than the default job's
    0.25 mm: a job that knows nothing of them refused them)."""
    sq = np.array([[0, 0], [20, 0], [20, 20], [0, 20]], float)
    layers = tuple(Layer(k, (k + 0.5) * 0.5, Region((sq,), np.array([-1])),
                         top_z=(k + 1) * 0.5, thickness=0.5) for k in range(3))
    return Stack(layers, Job().replace(**ADAPTIVE), 0.25)


def test_a_job_with_adaptive_layers_off_takes_the_stacks():
    """A speed-only job on an adaptive stack: the stack decided its adaptive layers, the
    later step takes them (it said 'layer 0: thickness 0.5 mm: expected ... (0, 0.25] mm',
    blaming the stack); a job that turns them on otherwise is refused naming the stack
    and the setting, as the other decided settings are."""
    stack = _adaptive_stack()
    speed = Job().replace(**{"motion.speed_mm_s": 100.0})
    tp = plan_paths(stack, speed)
    assert len(tp.layers) == 3 and [lp.thickness for lp in tp.layers] == [0.5] * 3
    adopted = stages.adopt_layers(stack.job, speed)
    assert adopted.slicing == stack.job.slicing and adopted.motion.speed_mm_s == 100.0
    assert stages.adopt_layers(Job(), speed) is speed   # a uniform file: nothing to take
    other = stack.job.replace(**{"slicing.max_layer_thickness_mm": 1.0})
    assert stages.adopt_layers(stack.job, other) is other   # on: the job's own, checked
    with pytest.raises(ConfigError, match=r"^the stack's layers were made with "
                                          r"slicing.max_layer_thickness_mm = 0.5, the job "
                                          r"has 1.0: .*'icefab slice'"):
        plan_paths(stack, other)
    with pytest.raises(ConfigError, match=r"slicing.cusp_height_mm = 0.1, the job has 0.2"):
        add_scaffold(stack, speed.replace(**{"slicing.cusp_height_mm": 0.2}))


def test_adaptive_settings_are_decided_unless_the_job_has_them_off():
    made = Job().replace(**ADAPTIVE)
    assert set(stages.ADAPTIVE) <= set(stages.DECIDED) and \
        set(stages.ADAPTIVE) <= set(stages.PLACEMENT)
    stages.check_agrees(made, Job().replace(**{"motion.speed_mm_s": 80.0}), "x", "y")
    with pytest.raises(ConfigError, match=r"^tp.npz: the toolpaths were made with "
                                          r"slicing.cusp_height_mm = 0.0, the job has 0.1"):
        # uniform toolpaths, a job that says they are adaptive
        stages.check_agrees(Job(), made, "tp.npz: the toolpaths", "icefab paths")
    with pytest.raises(ConfigError, match=r"slicing.min_layer_thickness_mm = 0.1, the job "
                                          r"has 0.2"):
        stages.check_agrees(made, made.replace(**{"slicing.min_layer_thickness_mm": 0.2}),
                            "tp.npz: the toolpaths", "icefab paths")


def test_paths_cli_takes_an_adaptive_stacks_layers_with_a_speed_only_job(tmp_path, capsys):
    """The reviewer's case through the command: 'icefab paths stack.npz -c JOB' with a job
    that changes a speed plans the stack's layers and records the stack's adaptive
    settings; a job contradicting them exits 2 naming the stack file and the setting."""
    from icefab.cli import main
    from icefab.resultfiles import load_toolpaths, save_stack

    save_stack(_adaptive_stack(), tmp_path / "stack.npz")
    (tmp_path / "speed.toml").write_text("[motion]\nspeed_mm_s = 100.0\n")
    (tmp_path / "other.toml").write_text("[slicing]\ncusp_height_mm = 0.2\n")
    assert main(["paths", str(tmp_path / "stack.npz"), "-c", str(tmp_path / "speed.toml"),
                 "-o", str(tmp_path / "out")]) == 0
    tp = load_toolpaths(tmp_path / "out" / "toolpaths.npz")
    assert tp.job.slicing.cusp_height_mm == 0.1 and tp.job.motion.speed_mm_s == 100.0
    capsys.readouterr()
    assert main(["paths", str(tmp_path / "stack.npz"), "-c", str(tmp_path / "other.toml"),
                 "-o", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / 'stack.npz'}: the stack's layers were made with " \
           "slicing.cusp_height_mm = 0.1, the job has 0.2" in err
    assert not (tmp_path / "bad").exists()
