"""Which settings each pipeline step reads, declared once.

PrusaSlicer's ``PrintObjectStep`` invalidation is the model: every job setting belongs to
the first step that reads it; changing it invalidates that step and every step after it
(an earlier step's output stays valid). Used wherever a result of one job meets another
job: the simulator's check of trajectories against the job it runs with, and the
benchmarks' caches of stacks and toolpaths. A setting no step's output depends on
(``cell.cpus``: the worker count never changes a result) is in :data:`NEUTRAL`.

What an earlier step decided travels with its output (``Stack.layer_thickness``, the job
stored in every result file); :func:`check_agrees` turns a contradiction between that and
the job a later step is given into one error naming the setting and both values. A
command reading a result file with ``-c JOB`` runs with the file's job overlaid with the
settings the job file names (:func:`overlay_job`): a named decided setting that differs
is refused the same way, anything else named applies, nothing unnamed changes.

May import: ``icefab.config``, ``icefab.errors``.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import TYPE_CHECKING, AbstractSet, Any, Sequence

import numpy as np

from icefab.config import SCARA_EE_ORIGIN_MM, PartSetup, to_dict
from icefab.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job

#: The steps in pipeline order.
STEPS = ("slice", "scaffold", "paths", "motion", "valves", "simulate")

#: Settings (dotted names; a trailing "." names a whole section) by the first step that
#: reads them. Checked by the tests to cover every setting of the Job exactly once.
READS: dict[str, tuple[str, ...]] = {
    "slice": ("parts.", "slicing.", "cell.stroke_mm"),  # the stroke: checked before slicing
    # the part's path width: the scaffold's report of part features thinner than a path
    # and the hook wall's ring width (tests/test_stage_reads.py found it read there)
    "scaffold": ("scaffold.", "materials.part.path_width_mm"),
    "paths": ("materials.part.fill_width_mm",
              "materials.part.initial_offset_mm", "materials.part.boundary_count",
              "materials.part.fill_pattern", "materials.part.fill_angle_deg",
              "materials.part.fill_smoothing_mm", "materials.scaffold.fill_smoothing_mm",
              "materials.part.fill_angle_mode", "materials.scaffold.fill_angle_mode",
              "materials.part.hybrid_rings", "materials.part.hybrid_angle_step_deg",
              "materials.part.nozzle_offset_mm", "materials.part.gap_fill",
              "materials.part.min_bead_width_mm", "materials.scaffold.min_bead_width_mm",
              "materials.part.variable_width", "materials.scaffold.variable_width",
              "materials.part.tour_max_turn_deg", "materials.scaffold.tour_max_turn_deg",
              "materials.scaffold.path_width_mm", "materials.scaffold.fill_width_mm",
              "materials.scaffold.initial_offset_mm", "materials.scaffold.boundary_count",
              "materials.scaffold.fill_pattern", "materials.scaffold.fill_angle_deg",
              "materials.scaffold.hybrid_rings", "materials.scaffold.hybrid_angle_step_deg",
              "materials.scaffold.nozzle_offset_mm", "materials.scaffold.gap_fill",
              "materials.order", "cell.laser_offset_mm", "feedback.enabled",
              "feedback.interval_layers", "feedback.measure_spacing_mm",
              # the PATHSPLIT angle: a closed path starts at one of its corners
              # (paths._start_candidates), where the robot stops anyway
              "motion.smooth_angle_deg",
              # the laser's speeds and sampling rate: a measurement spiral's lane changes
              # and its length within the laser's storage (paths.join_measure_rings)
              "motion.measure_speed_mm_s", "motion.speed_mm_s", "simulation.laser_rate_hz",
              # tours only where travel may move at the deposition's speed bound
              # (paths.plan_layer); tours and measurement paths within the seconds of
              # motion the robot controller stores of one path (paths.path_store_s)
              "motion.travel_speed_mm_s", "motion.dt_s"),
    "motion": ("motion.", "cell.robot", "cell.l1_mm", "cell.l2_mm", "cell.reach_mm",
               "cell.joint_range_deg", "cell.elbow", "cell.gantry_travel_mm",
               "cell.ee_origin_mm", "cell.encoder_resolution_deg"),
    "valves": ("flow.", "materials.part.calibration_file", "materials.part.density_g_cm3",
               "materials.scaffold.calibration_file", "materials.scaffold.density_g_cm3"),
    "simulate": ("simulation.", "feedback.", "cell.laser_latency_s"),
}

#: Settings no step's output depends on.
NEUTRAL = ("cell.cpus",)

#: Later steps' settings a step reads only to refuse, before it starts, work a later step
#: could not do (icefab.workload's estimates): they never change the step's output.
CHECKED_EARLY: dict[str, tuple[str, ...]] = {
    "paths": ("motion.point_spacing_mm",),  # fill samples budget (workload.check_paths)
    # the same budget before the scaffold's walls (a 4 km square took them 52 s, 3.5 GB)
    "scaffold": ("materials.part.fill_width_mm", "materials.scaffold.fill_width_mm",
                 "motion.point_spacing_mm"),
}

#: Adaptive layers' settings (the switch, the bound and the thickness range): the layers'
#: own thicknesses were cut with them. A job with them off (``slicing.cusp_height_mm = 0``,
#: the default) says nothing of them and takes the file's (:func:`adopt_layers`).
ADAPTIVE = ("slicing.cusp_height_mm", "slicing.min_layer_thickness_mm",
            "slicing.max_layer_thickness_mm")

#: Settings that decide where a build's material goes once its paths exist: frames, tool
#: offsets, widths, layer thickness. Trajectories simulated with another job than the one
#: they were planned with must agree on these (the simulator re-plans valve programs and
#: deposits with the job's other settings).
PLACEMENT = ("slicing.layer_thickness_mm", *ADAPTIVE, "cell.ee_origin_mm",
             "cell.laser_offset_mm", "materials.part.nozzle_offset_mm",
             "materials.scaffold.nozzle_offset_mm", "materials.part.path_width_mm",
             "materials.part.fill_width_mm", "materials.scaffold.path_width_mm",
             "materials.scaffold.fill_width_mm")


#: Which layers carry measurement paths (paths decides; simulate and build measure there).
MEASURED = ("feedback.enabled", "feedback.interval_layers")

#: The part's description (its files, their placement, the sliced fraction): a result
#: file's geometry was made from them. A job naming other parts describes another build
#: (a tester's spot stack given fandisk's job recorded fandisk's files and scale).
PARTS = tuple(f"parts.{f.name}" for f in dataclasses.fields(PartSetup))

#: Settings an earlier step decided that a later step reads again: the layers were cut
#: and the paths laid for them (layer thickness, the adaptive layers' settings, bead
#: widths, nozzle and laser offsets, which layers carry measurement paths). A later step
#: given other values would lay or measure another build than its input file holds: the
#: valves of 0.5 mm layers along paths sliced at 0.25 mm give twice the water (a tester's
#: bunny), an SMF that expects a measurement every layer along paths measured every 4th
#: corrects less. The part's origin is not among them: toolpaths are in the part's frame,
#: and may be planned anywhere the robot reaches (trajectories, in the robot's, add it:
#: ``icefab.sim.MOTION_SETTINGS``). The parts (:data:`PARTS`) are: the geometry was made
#: from them.
DECIDED = tuple(k for k in PLACEMENT if k != "cell.ee_origin_mm") + MEASURED + PARTS


def _flat(job: "Job") -> dict[str, Any]:
    out: dict[str, Any] = {}

    def walk(d: dict, prefix: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            else:
                out[prefix + k] = v

    walk(to_dict(job), "")
    return out


def step_of(setting: str) -> str | None:
    """The first step that reads ``setting`` (dotted name), None for a neutral one."""
    if setting in NEUTRAL:
        return None
    best, rank = None, -1
    for step in STEPS:
        for name in READS[step]:
            hit = setting == name or (name.endswith(".") and setting.startswith(name))
            if hit and len(name) > rank:  # the most specific declaration wins
                best, rank = step, len(name)
    if best is None:
        raise KeyError(f"setting {setting!r} is read by no step: declare it in "
                       "icefab.stages.READS")
    return best


def settings_up_to(step: str, job: "Job") -> list[str]:
    """Every setting of ``job`` that ``step`` or an earlier step reads, in job order."""
    last = STEPS.index(step)
    return [k for k in _flat(job) if (s := step_of(k)) is not None and STEPS.index(s) <= last]


def differences(a: "Job", b: "Job", step: str) -> list[tuple[str, Any, Any]]:
    """(setting, value in a, value in b) for every setting up to ``step`` that differs."""
    fa, fb = _flat(a), _flat(b)
    return [(k, fa[k], fb[k]) for k in settings_up_to(step, a) if fa[k] != fb[k]]


def first_invalidated(a: "Job", b: "Job") -> str | None:
    """The first step whose output made with ``a`` is not valid for ``b`` (None: all are)."""
    fa, fb = _flat(a), _flat(b)
    steps = [step_of(k) for k in fa if fa[k] != fb[k]]
    steps = [s for s in steps if s is not None]
    return min(steps, key=STEPS.index) if steps else None


def digest(job: "Job", step: str) -> str:
    """A text of every setting up to ``step`` (for cache keys: equal for two jobs exactly
    when ``step``'s output is the same)."""
    f = _flat(job)
    return "\n".join(f"{k}={f[k]!r}" for k in settings_up_to(step, job))


def check_agrees(made: "Job", job: "Job", source: str, remake: str,
                 settings: Sequence[str] = DECIDED,
                 error: type[Exception] = ConfigError) -> None:
    """``error`` if ``job`` differs from the job an input file was ``made`` with in one of
    ``settings`` (default :data:`DECIDED`), naming the first difference and counting the
    others. ``source`` names the file's contents ("out/toolpaths.npz: the toolpaths"),
    ``remake`` the command that makes them again with ``job``. The measurement interval of
    two jobs that both measure nothing does not count, nor do the :data:`ADAPTIVE`
    settings of a job with adaptive layers off: it takes the file's (:func:`adopt_layers`;
    a speed-only job was refused for an adaptive stack's layers, thicker than its own
    default maximum). For whole jobs (API callers); a command given a job file lays what
    it names over the file's job instead (:func:`overlay_job`)."""
    fa, fb = _flat(made), _flat(job)
    quiet = _moot(fa, fb)
    if not fb["slicing.cusp_height_mm"] > 0:
        quiet |= set(ADAPTIVE)
    diff = [(k, fa[k], fb[k]) for k in settings if k not in quiet and fa[k] != fb[k]]
    _refuse(diff, source, remake, error)


def _moot(fa: dict[str, Any], fb: dict[str, Any]) -> set[str]:
    """Settings of two flat jobs that decide nothing in either: the measurement interval
    when neither measures, the adaptive layers' bounds when neither has adaptive layers."""
    quiet = {"feedback.interval_layers"} if not (fa["feedback.enabled"]
                                                  or fb["feedback.enabled"]) else set()
    if not (fa["slicing.cusp_height_mm"] > 0 or fb["slicing.cusp_height_mm"] > 0):
        quiet |= set(ADAPTIVE[1:])
    return quiet


def overlay_job(made: "Job", given: "Job", named: AbstractSet[str], source: str,
                remake: str, settings: Sequence[str] = DECIDED,
                error: type[Exception] = ConfigError) -> "Job":
    """The job a command that reads a result file runs with when given ``-c JOB``: the job
    the file was ``made`` with, with ``given``'s values of the settings the job file
    ``named`` (dotted: :func:`icefab.config.load_named_job`); the others are the file's,
    not ``given``'s defaults (a flow-only job on 1.0 mm layers was refused for the
    default 0.25 mm it never named). ``error`` (``source``, ``remake`` as in
    :func:`check_agrees`) when a named setting among ``settings`` (default
    :data:`DECIDED`) differs from the file's, unless it decides nothing in either job (the
    measurement interval when neither measures, the adaptive bounds when neither has
    adaptive layers). A job file naming another robot and no ``cell.ee_origin_mm`` gives
    the new robot its default part origin (:func:`_origin_of_new_robot`). API callers pass
    whole jobs and keep :func:`check_agrees`."""
    fa, fg = _flat(made), _flat(given)
    unknown = sorted(set(named) - set(fg))
    if unknown:   # a caller's slip: load_named_job names only settings of a Job
        raise KeyError(f"not settings of a Job: {', '.join(unknown)}")
    changes = {k: fg[k] for k in fa if k in named}   # in job order: the first is named
    merged = {**fa, **changes}
    quiet = _moot(fa, merged)
    _refuse([(k, fa[k], merged[k]) for k in settings
             if k in changes and k not in quiet and fa[k] != merged[k]], source, remake, error)
    changes.update(_origin_of_new_robot(fa, changes))
    try:
        return made.replace(**changes) if changes else made
    except ConfigError as exc:   # the two jobs' settings together break a joint rule
        raise error(f"{source} were made with a job that, with the job file's "
                    f"settings, is invalid: {exc}") from None


def _origin_of_new_robot(made: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``cell.ee_origin_mm`` for an overlay whose job file names another robot than
    ``made``'s (dotted settings) and no origin: the new robot's default (the setting's
    default, which a gantry takes as the centre of its travel: ``config._placed``). The
    origin is a point of the robot's base frame; the file's, another robot's, meant
    nothing there: a gantry's (150, 150) was kept for a SCARA, whose part then lay
    inside its minimum reach (a review's). Nothing when the origin is named.

    Likewise a gantry whose job file gives it another travel (``cell.gantry_travel_mm``)
    and no origin, when the file's origin is the centre of the file's travel (the default
    ``_placed`` put there, or the same point set by hand): the default again, the new
    travel's centre. The old centre (150, 150) was kept for a 160 mm travel, and the part
    was refused naming ``cell.ee_origin_mm``, a setting the user never set (a gantry
    hunt's). An origin elsewhere in the old travel was set on purpose and is kept."""
    robot = changes.get("cell.robot", made["cell.robot"])
    if "cell.ee_origin_mm" in changes:
        return {}
    if robot != made["cell.robot"]:
        return {"cell.ee_origin_mm": SCARA_EE_ORIGIN_MM}
    old = tuple(map(float, made["cell.gantry_travel_mm"]))
    new = tuple(map(float, changes.get("cell.gantry_travel_mm", old)))
    centred = tuple(map(float, made["cell.ee_origin_mm"])) == tuple(0.5 * v for v in old)
    if robot == "gantry" and new != old and centred:
        return {"cell.ee_origin_mm": SCARA_EE_ORIGIN_MM}   # config._placed: the centre
    return {}


def _quoted(remake: str) -> str:
    """``remake`` with each command in quotes: "'icefab paths', then 'icefab plan'" (the
    whole phrase in one pair read as one command); one naming no command, whole."""
    out = re.sub(r"\bicefab [a-z]+", lambda m: f"'{m.group()}'", remake)
    return out if out != remake else f"'{remake}'"


def _refuse(diff: Sequence[tuple[str, Any, Any]], source: str, remake: str,
            error: type[Exception]) -> None:
    """``error`` naming the first of ``diff`` (setting, file's value, job's value) and
    counting the others (:func:`check_agrees`); nothing when ``diff`` is empty."""
    if diff:
        k, va, vb = diff[0]
        more = f" (and {len(diff) - 1} more)" if len(diff) > 1 else ""
        raise error(f"{source} were made with {k} = {va}, the job has {vb}{more}: use "
                    f"the job they were made with, or make them again with this job "
                    f"({_quoted(remake)})")


def _adaptive(job: "Job") -> dict[str, Any]:
    """The :data:`ADAPTIVE` settings of ``job`` by dotted name, read as attributes (a
    stage's job may be a view that records what it reads: tests/test_stage_reads.py)."""
    return {k: getattr(job.slicing, k.rpartition(".")[2]) for k in ADAPTIVE}


def check_layers_agree(made: "Job", job: "Job", source: str, remake: str,
                       error: type[Exception] = ConfigError) -> None:
    """:func:`check_agrees` on the :data:`ADAPTIVE` settings alone (a stage given a stack:
    :func:`icefab.regions.check_stack`); a job with adaptive layers off agrees."""
    if not job.slicing.cusp_height_mm > 0:
        return
    fa, fb = _adaptive(made), _adaptive(job)
    _refuse([(k, fa[k], fb[k]) for k in ADAPTIVE if fa[k] != fb[k]], source, remake, error)


def adopt_layers(made: "Job | None", job: "Job") -> "Job":
    """``job`` with the :data:`ADAPTIVE` settings of the job a file was ``made`` with when
    ``job`` has adaptive layers off (``slicing.cusp_height_mm = 0``) and the file's are on:
    the file's layers were cut with them, and a later step checks them (the thickest layer
    a stack may hold, :func:`icefab.regions.check_stack`) and writes them into its own
    file. Otherwise ``job`` as it is (:func:`check_agrees` refuses it when it contradicts
    the file)."""
    if made is None or made is job or job.slicing.cusp_height_mm > 0 or \
            not made.slicing.cusp_height_mm > 0:
        return job
    return job.replace(**_adaptive(made))


def check_layer_thickness(stack_thickness: float, job: "Job", what: str = "the stack") -> None:
    """ConfigError if ``job.slicing.layer_thickness_mm`` contradicts the thickness a stack
    was sliced at (it travels with the stack: ``Stack.layer_thickness``)."""
    t = float(job.slicing.layer_thickness_mm)
    # a NaN passed the comparison below (a tester's Stack built by a program)
    if not (math.isfinite(float(stack_thickness)) and float(stack_thickness) > 0) or \
            abs(t - float(stack_thickness)) > 1e-12 * max(1.0, abs(t)):
        raise ConfigError(f"slicing.layer_thickness_mm = {t:g}, but {what} was sliced at "
                          f"{float(stack_thickness):g} mm: use the stack's thickness or slice "
                          "again with this job")


def layer_height(thickness: float, job: "Job") -> float:
    """A layer's thickness, mm: its own (adaptive slicing carries one per layer through
    the stack, toolpaths and trajectories) or, when that is NaN, the job's
    ``slicing.layer_thickness_mm``."""
    return float(thickness) if math.isfinite(thickness) else job.slicing.layer_thickness_mm


def measured_layers(thicknesses: Sequence[float], job: "Job") -> list[bool]:
    """Which layers carry measurement paths (thesis 5.2.1): every
    ``feedback.interval_layers``-th layer; with adaptive layers (own thicknesses) the
    interval is a height, ``interval_layers * layer_thickness_mm``, and a layer is
    measured when the build's height crosses a multiple of it."""
    fb = job.feedback
    t = np.asarray(list(thicknesses), dtype=np.float64)
    if not fb.enabled:
        return [False] * len(t)
    if not np.isfinite(t).any():
        return [(k + 1) % fb.interval_layers == 0 for k in range(len(t))]
    h = np.cumsum(np.where(np.isfinite(t), t, job.slicing.layer_thickness_mm))
    step = fb.interval_layers * job.slicing.layer_thickness_mm
    count = np.floor(h / step + 1e-9)
    return list(np.diff(np.concatenate([[0.0], count])) > 0)
