"""The build runner: a closed-loop build on a cell that survives crashes (thesis 2.5, 5.2).

Per layer of the build's trajectories (``icefab.motion``), in the order the cell runs them:

1. the valve programs of the layer's deposition trajectories are planned with the current
   control action (:func:`icefab.sim.layer_valves`: nu-controller flow x (1 + u); for the
   c-controller the trajectories are re-timed and every re-timed speed is checked against
   ``motion.speed_mm_s``, findings journaled);
2. every trajectory (deposition with its program, travel) goes to the cell as one
   :class:`~icefab.runcell.CellPath`; the command is journaled **before** it is sent and
   completed in the journal when the cell reports the path done;
3. the layer's end (the deposit freezes);
4. on a measurement layer (one with measurement paths; ``paths`` adds them every
   ``feedback.interval_layers``): the measurement paths, the laser samples (tagged with
   the end-effector position at their instant; the calibrated latency
   ``cell.laser_latency_s`` is taken off by reading the trajectory that much earlier and
   the calibrated ``cell.laser_offset_mm`` puts them under the laser, thesis 5.2.1;
   each path's samples are journaled before the next path is sent),
   the SMF update (:func:`icefab.feedback.smf_update` on the samples' surface,
   eq. 5.1) and its state and action journaled.

Exactly once (:mod:`icefab.journal`, :mod:`icefab.runcell`): every command has a sequence
number, kept when it is re-sent after a crash; the cell answers a number it completed
with "done" instead of running it again. On start the runner asks the cell what it
completed (``status``): journaled commands at or below it are completed in the journal,
a path a cell fault cut short is recorded as cut (never re-run: half a path twice would
deposit its first half twice), and the surface is measured at the end of that layer (with
the nearest measurement layer's paths when it has none of its own: journal event
"fault-measure"), so SMF absorbs the error before the next layer. Whole
layers the journal shows complete are skipped; the control action is restored from the
journal's last SMF row, so the re-planned programs are the ones an uninterrupted build
sends (their digests are checked against the journal). Numbers run in order: the cell
runs commands in the order of their numbers, which is what makes "at or below
``last_done``" mean "done".

So that the robot does not wait for the PC: each path is sent with the next one
(``upcoming``, journaled as sent first), which the cell uploads while the path moves;
the next layer's first path goes with a layer's last one, numbered after that layer's
end; the next layer's valve programs and cell paths are planned on a thread while a
layer runs (its motion plan alone when a measurement comes first: the action then
changes); the report's pictures are drawn once the next layer runs. A cell fault that
cuts a layer's last path after the next layer's first path was numbered is not
measured at once (the measurement would be numbered after a path that must run first):
journaled, SMF absorbs it at the next measurement.

Files in BUILD: ``journal.sqlite``, ``trajectories.npz`` (planned once at the start),
``job.toml``, ``status.json`` (:func:`write_status`), ``report.html``
(:func:`write_report`), ``cell/`` (the state of ``icefab cell serve`` with ``--virtual``).
The cell is an :class:`icefab.runcell.Cell`: :class:`icefab.linkedcell.LinkedCell` on the
cell's links for ``icefab build``.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from icefab.errors import MOVE_PART, CellRefused, ConfigError, IcefabError, WorkspaceError
from icefab.robots import check_workspace, get_robot
from icefab.journal import Journal, JournalError, digest_text, pack_arrays, unpack_arrays
from icefab.runcell import Cell, CellError, CellPath
from icefab.core import HeightMap

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job
    from icefab.motion import BuildMotion, LayerMotion

log = logging.getLogger(__name__)

JOURNAL = "journal.sqlite"
TRAJECTORIES = "trajectories.npz"
STATUS = "status.json"
REPORT = "report.html"
STOP_REQUEST = "stop.request"
CELL_DIR = "cell"
#: The journal's meta key of the number up to which the cell had completed commands when
#: the build started (in the journal's first write, with the meta; builds since 2026-11-29).
CELL_DONE_AT_START = "cell_done_at_start"
#: The journal's meta key saying the user started the build with ``--platform-cleared``
#: (true or absent).
PLATFORM_CLEARED = "platform_cleared"

#: Cobra 600 vertical (joint 3) stroke, mm (thesis Table 2-1); the build checks the job's
#: cell.stroke_mm (this default).
Z_STROKE_MM = 210.0


class BuildStopped(IcefabError):
    """The build was stopped (``--stop``, Ctrl-C): valves off, robot safe, journaled."""


# =========================================================================== checks


def check_build_robot(job: "Job") -> None:
    """ConfigError unless ``job``'s robot is one the build runner drives: the Cobra 600
    SCARA, through the Adept C40's V+ server (:mod:`icefab.cell.vplus`) and its virtual
    cell. A gantry job went down that link as if its carriage positions were the SCARA's
    tool positions, and the virtual cell built it (a gantry hunt's); a gantry takes the
    G-code of ``icefab plan --gcode`` / ``icefab export gcode``."""
    if job.cell.robot != "scara":
        raise ConfigError(f"cell.robot = {job.cell.robot!r}: the build runner drives the "
                          "Cobra 600 SCARA through its C40 controller's V+ server (or a "
                          "virtual cell of it); for a gantry, write its G-code ('icefab plan "
                          "--gcode' or 'icefab export gcode') and run that on its controller")


def check_build(motion: "BuildMotion", job: "Job", layers: int) -> None:
    """Refuse, before anything moves, a build the cell cannot make: a trajectory point
    beyond the reach or a joint's range of this job's cell (the planner checked the job it
    planned with; the cell the build runs on may differ), a part taller than the vertical
    stroke (WorkspaceError naming layer, path and point, or the stroke and the layer), a
    measurement path with more laser values than the controller stores (ConfigError
    naming the layer, path and ``simulation.laser_rate_hz``), SMF gains that make the loop
    unstable (ConfigError; gains with a pole on the unit circle only warn), a robot the
    runner does not drive (:func:`check_build_robot`). Each names the first offending
    layer in build order and how many layers (paths) offend.
    Adaptive layers (own thicknesses) are refused: the runner's SMF interval and the
    virtual cell still count in layers of ``slicing.layer_thickness_mm``."""
    check_build_robot(job)
    if any(np.isfinite(lm.thickness) for lm in motion.layers):
        raise ConfigError("these trajectories have adaptive layers (slicing.cusp_height_mm > "
                          "0): the build runner does not run them yet; simulate them "
                          "('icefab simulate') or plan with slicing.cusp_height_mm = 0")
    from icefab.feedback import gains_verdict

    verdict = gains_verdict(job)
    if verdict is not None and verdict[0] == "grows":
        raise ConfigError(f"{verdict[1]}; refused before anything moves")
    if verdict is not None:
        log.warning("%s", verdict[1])
    _check_reach(motion, job, layers)
    _check_laser_storage(motion, job, layers)
    _check_stroke(motion, job, layers)


def _check_stroke(motion: "BuildMotion", job: "Job", layers: int) -> None:
    """WorkspaceError when a layer's top among the first ``layers`` is above the vertical
    stroke ``cell.stroke_mm`` (mm), naming the first such layer; the Cobra 600's own
    stroke (thesis Table 2-1) is quoted for a SCARA only (a gantry's said "Cobra 600")."""
    tops = np.array([lm.top(job) for lm in motion.layers[:layers]])
    stroke = job.cell.stroke_mm
    above = np.flatnonzero(tops > stroke)
    if len(above):   # the first layer above it (it named none: a review's)
        k = int(above[0])
        cobra = " (Cobra 600: 210 mm, thesis Table 2-1)" if job.cell.robot == "scara" else ""
        raise WorkspaceError(f"the part is {tops.max():.1f} mm tall over its first {layers} "
                             "layers: beyond the robot's vertical stroke "
                             f"cell.stroke_mm = {stroke:g} mm{cobra} from layer "
                             f"{motion.layers[k].index} on, its top at {tops[k]:.1f} mm"
                             f"{_first_of(len(above), 'layers above it')}")


def _first_of(n: int, what: str) -> str:
    """`` (the first of N WHAT)`` for a refusal naming the first of ``n`` offenders (the
    one a user fixing the file starts at; they named the tightest: a review's); nothing
    for one."""
    return f" (the first of {n} {what})" if n > 1 else ""


def _check_reach(motion: "BuildMotion", job: "Job", layers: int) -> None:
    """WorkspaceError naming the first layer (in build order), path and point of the first
    ``layers`` beyond this job's cell (its reach and joint ranges, whatever the planner's
    job was), and how many layers have such points."""
    robot = get_robot(job)
    first, n_bad = None, 0
    for lm in motion.layers[:layers]:
        trajs = [t for t in lm.trajectories if len(t.xy)]
        if not trajs:
            continue
        pts = np.concatenate([np.asarray(t.xy, dtype=np.float64) for t in trajs])
        bad, _reasons = robot.workspace_violations(pts)
        if len(bad):
            n_bad += 1
            if first is None:
                ends = np.cumsum([len(t.xy) for t in trajs])
                first = (lm, trajs, int(np.searchsorted(ends, int(bad[0]), side="right")))
    if first is None:
        return
    lm, trajs, k = first
    where = ("before anything moves (cell.reach_mm, cell.joint_range_deg)"
             if job.cell.robot == "scara" else "before anything moves")
    try:
        check_workspace(trajs[k].xy, robot, layer=int(lm.index), path=k, what=where)
    except WorkspaceError as exc:
        text = str(exc)
        if n_bad > 1:   # the count beside the layer, before the settings that move the part
            head, sep, tail = text.partition(MOVE_PART)
            text = head + _first_of(n_bad, "layers with points out of reach") + sep + tail
        raise WorkspaceError(text) from None


def _check_laser_storage(motion: "BuildMotion", job: "Job", layers: int) -> None:
    """Refuse a measurement path whose values the laser controller cannot hold: it stores
    one every cycle (``simulation.laser_rate_hz``) while the path runs and 65 536 at most
    (LK-G3001P, thesis Table 2-3); the cell reads them after the path, so a longer path
    would be measured only in part, with nothing to say so. The paths stage keeps its
    spirals within half of it at the laser's speed (``paths.MEASURE_MAX_SAMPLES``); a
    single ring is as long as the part makes it."""
    from icefab.cell.lkg import STORAGE_CAPACITY

    rate = float(job.simulation.laser_rate_hz)
    over = [(lm.index, i, tr.duration) for lm in motion.layers[:layers]
            for i, tr in _items(lm)[1]
            if int(math.floor(tr.duration * rate + 1e-9)) + 1 > STORAGE_CAPACITY]
    if over:   # the first path, and a rate every one of them fits in (the longest's)
        layer, i, duration = over[0]
        n = int(math.floor(duration * rate + 1e-9)) + 1
        longest = max(d for *_, d in over)
        raise ConfigError(
            f"layer {layer}, measurement path {i}: {duration:.1f} s at "
            f"simulation.laser_rate_hz = {rate:g} Hz is {n} laser values, more than "
            f"the laser controller stores ({STORAGE_CAPACITY}, LK-G3001P)"
            f"{_first_of(len(over), 'such measurement paths')}; lower "
            f"simulation.laser_rate_hz to at most {(STORAGE_CAPACITY - 1) / longest:.0f} Hz")


def check_speeds(trajectories, job: "Job", layer: int) -> list[str]:
    """Findings for re-timed trajectories (c-controller, thesis 5.2.2) faster than the
    Cartesian speed bound ``motion.speed_mm_s``: one line per trajectory."""
    vmax = job.motion.speed_mm_s
    out = []
    for k, tr in enumerate(trajectories):
        if len(tr.xy) < 2:
            continue
        v = float(np.max(np.linalg.norm(np.diff(tr.xy, axis=0), axis=1)) / tr.dt)
        if v > vmax * (1 + 1e-6):
            out.append(f"layer {layer}: re-timed trajectory {k} reaches {v:.1f} mm/s, above "
                       f"motion.speed_mm_s = {vmax:g}")
    return out


#: Journal events that say something about the build's programs, once per build.
FINDING_EVENTS = ("saturation", "clamp", "motion-limit")


def _volume_finding(programs, layer: int, volumes, what) -> str | None:
    """One line for a layer whose valve programs' findings ``volumes`` counts (paths,
    layers, mm^3 given, mm^3 asked), None without any: ``what(paths, of)``, then the volume
    given of the volume asked."""
    paths, _, got, asked = volumes([(layer, text) for prog in programs
                                    for text in prog.warnings])
    if not paths:
        return None
    return (f"layer {layer}: {what(paths, len(programs))}: {got:.4g} of the {asked:.4g} mm^3 "
            f"asked ({100.0 * (got / asked - 1.0):+.1f} %)")


def saturation_finding(programs, layer: int) -> str | None:
    """Where the valve saturated SMF's correction at its range (thesis 5.2.2,
    :func:`icefab.flow.valve_frequency`): how many paths, the volume given of the volume
    asked; None if nowhere."""
    from icefab.findings import saturated_volume

    return _volume_finding(programs, layer, saturated_volume, lambda p, n: (
        f"the valve saturated SMF's correction on {p} of {n} paths (thesis 5.2.2)"))


def clamp_finding(programs, layer: int) -> str | None:
    """Where ``flow.out_of_range = "clamp"`` clamped the nominal flow to the valve's range
    (the build clamped unsaid; ``icefab valves`` reports the same); None if nowhere."""
    from icefab.findings import clamped_volume

    return _volume_finding(programs, layer, clamped_volume, lambda p, n: (
        f"the flow of {p} of {n} paths was clamped to the valve's range "
        "(flow.out_of_range = 'clamp')"))


# =========================================================================== SMF state


def pack_smf(state, action_u: HeightMap | None, filled: np.ndarray | None) -> bytes:
    """The SMF controller state and its action as npz bytes (:func:`unpack_smf`)."""
    def hm(prefix: str, h: HeightMap | None) -> dict:
        if h is None:
            return {}
        return {f"{prefix}_origin": h.origin, f"{prefix}_spacing": np.float64(h.spacing),
                f"{prefix}_z": h.z}

    return pack_arrays(k=np.int64(state.k), **hm("integral", state.integral),
                       **hm("previous", state.previous_error), **hm("u", action_u),
                       filled=filled)


def unpack_smf(data: bytes):
    """(SmfState, action sampler or None) from :func:`pack_smf` bytes."""
    from icefab import feedback

    a = unpack_arrays(data)

    def hm(prefix: str) -> HeightMap | None:
        if f"{prefix}_z" not in a:
            return None
        return HeightMap(origin=a[f"{prefix}_origin"], spacing=float(a[f"{prefix}_spacing"]),
                         z=a[f"{prefix}_z"])

    state = feedback.SmfState(integral=hm("integral"), previous_error=hm("previous"),
                              k=int(a["k"]))
    u = hm("u")
    if u is None:
        return state, None
    z = np.zeros_like(u.z)
    action = feedback.ControlAction(u=u, unsaturated=u, p=z, i=z, d=z, saturated=0.0,
                                    _filled=a.get("filled"))
    return state, feedback.action_sampler(action)


def smf_from_samples(samples: np.ndarray, nominal_z: float, state, job: "Job",
                     footprint: tuple[np.ndarray, HeightMap] | None = None):
    """One SMF update from part-frame laser samples (m, 3): (new state, action u
    HeightMap, filled u, measured RMS mm, finding).

    footprint: the layer's (mask, grid) (:func:`icefab.sim.commanded_footprint`); the
    measured surface is restricted to it as the simulator's is
    (:func:`icefab.feedback.restrict_to_footprint`: the samples' convex hull spanned the
    platform between a part's arms, and heights interpolated there fed SMF). None: the
    samples' convex hull.
    Too few or collinear samples, or none on the footprint: the state is kept and the
    action is the integral term alone (:func:`icefab.feedback.held_action`; None before
    the first update: nominal flow), and the finding (else None) says so; an action of 0
    lost the integral's bias of a lasting flow error for an interval."""
    from icefab import feedback

    rms = float(np.sqrt(np.mean((samples[:, 2] - nominal_z) ** 2))) if len(samples) \
        else float("nan")
    new, action, held = feedback.measured_update(
        state, samples, nominal_z, job.feedback.interval_layers *
        job.slicing.layer_thickness_mm, job, footprint)
    if held is not None:
        log.warning("%s", held)
    if action is None:
        return new, None, None, rms, held
    return new, action.u, action._filled, rms, held


# =========================================================================== the run


@dataclass
class Progress:
    """What the runner reports after every path (``icefab build`` prints it)."""

    layer_pos: int = 0          # layers completed
    layers: int = 0             # layers to build
    layer: int = 0              # toolpaths index of the current layer
    paths_done: int = 0
    paths: int = 0
    remaining_s: float = 0.0    # planned motion time left, s
    last_rms_mm: float = float("nan")
    state: str = "running"
    rms: list = field(default_factory=list)   # (layer, nominal z, measured RMS)
    waiting: str = ""           # the link fault the build is waiting out ("" when none)
    longest_s: float = 0.0      # the current layer's longest path, s (see UPDATE_MARGIN_S)
    # this run's pace (eta_wall_s): when it began (time.monotonic(), s) and the planned
    # motion left then, s; NaN until the runner has its link
    pace_since: float = float("nan")
    pace_left0_s: float = float("nan")

    def eta_wall_s(self, now: float | None = None) -> float | None:
        """Wall time left, s, at the pace this run has kept (:func:`pace_eta_s`); None
        when not running or too early to tell. ``now``: time.monotonic()."""
        if self.state != "running":
            return None
        now = time.monotonic() if now is None else now
        return pace_eta_s(self.remaining_s, self.pace_left0_s - self.remaining_s,
                          now - self.pace_since)


#: Planned motion, s, a run must have done before its pace gives an ETA: one path's pace
#: (its upload, a layer's end between) says little of the next hour's.
PACE_MIN_RAN_S = 10.0


def pace_eta_s(left_s: float, ran_s: float, wall_s: float,
               min_ran_s: float = PACE_MIN_RAN_S) -> float | None:
    """Wall time left, s: ``left_s`` s of planned motion at the ``wall_s`` wall seconds
    that ``ran_s`` s of planned motion took so far. The planned motion time read as wall
    time said 0:40:00 for a virtual-cell build that took 92 s (a reviewer's); a real cell
    adds its uploads, layer ends and SMF updates. None before ``min_ran_s`` s ran."""
    if not ran_s >= min_ran_s or not wall_s > 0.0:   # NaN too: no pace yet
        return None
    return max(left_s, 0.0) * wall_s / ran_s   # float sums leave -1e-13 s at the end


def measures(lm: "LayerMotion") -> bool:
    """Whether a layer has measurement trajectories (the runner measures it after its
    deposition, before the layer counts as done)."""
    return bool(_items(lm)[1])


def layer_finished(layer: int, ended: set, measured: set, measures: bool, cut: set) -> bool:
    """Whether a layer is done, from the journal: it ended (``ended``: its layer end is
    done) and, if it measures or a fault cut a path of it short (``cut``), its
    measurement is in (``measured``). The runner skips such a layer on a resume and
    ``icefab build --status`` counts it, by this one rule."""
    return layer in ended and (not (measures or layer in cut) or layer in measured)


def _ran_s(journal, lm: "LayerMotion") -> float:
    """Motion time, s, of the trajectories of layer ``lm`` the journal shows done."""
    return float(sum(lm.trajectories[i].duration for i in journal.done_items(int(lm.index))
                     if 0 <= i < len(lm.trajectories)))


def _items(lm: "LayerMotion") -> tuple[list[tuple[int, object]], list[tuple[int, object]]]:
    """(deposition and travel, measurement) trajectories of a layer as (index, traj)."""
    run, measure = [], []
    for i, tr in enumerate(lm.trajectories):
        if len(tr.xy) == 0:
            continue
        role = tr.path.role if tr.path is not None else "travel"
        (measure if role == "measure" else run).append((i, tr))
    return run, measure


def laser_to_part(raw: np.ndarray, traj, job: "Job") -> np.ndarray:
    """(m, 3) part-frame laser samples from a cell's (m, 4) rows (t s, EE x, y base frame,
    z): the calibrated latency ``cell.laser_latency_s`` taken off (the spot read the
    surface where the trajectory was that long before the sample's instant; clamped at
    the path's start) and the calibrated laser offset applied (thesis 5.2.1)."""
    if len(raw) == 0:
        return np.zeros((0, 3))
    xy = np.asarray(traj.xy, dtype=np.float64)
    t = np.arange(len(xy)) * float(traj.dt)
    tq = np.maximum(raw[:, 0] - job.cell.laser_latency_s, 0.0)
    pos = np.column_stack([np.interp(tq, t, xy[:, 0]), np.interp(tq, t, xy[:, 1])])
    part = pos - np.asarray(job.cell.ee_origin_mm) + np.asarray(job.cell.laser_offset_mm)
    return np.column_stack([part, raw[:, 3]])


def check_cell_numbers(last: int, platform_cleared: bool = False) -> None:
    """Whether a new build may start on a cell that has completed commands up to number
    ``last`` since its program started (0: none). CellRefused (sending again cannot change
    it) when ``last`` is past half the link's numbers, or when it is above 0 and the user
    did not say the platform was cleared (``--platform-cleared``): the cell ran an earlier
    build, whose ice its platform may hold, and this build's first layers would put the
    nozzle into it (a review's: it was a note)."""
    from icefab.cell.robot_protocol import MAX_SEQ  # the robot link's numbers

    if last <= 0:
        return
    if last > MAX_SEQ // 2:
        raise CellRefused(f"the cell has completed commands up to number {last}, past half "
                          f"the link's {MAX_SEQ}: restart its program (it counts from 0 "
                          "again) before a new build")
    if not platform_cleared:
        raise CellRefused(
            f"the cell has completed commands up to number {last} since its program "
            "started: an earlier build ran on it, and its platform may hold that build's "
            "ice, which this build's nozzle would run into; nothing was sent. Clear the "
            "platform, then run the build (or its --resume) again with --platform-cleared "
            "(or restart the cell's program)")


class Runner:
    """Runs (or resumes) a build on a cell; see the module docstring.

    build_dir: BUILD; motion: the layers to build; job; journal: the build's journal;
    connect: returns a connected :class:`~icefab.runcell.Cell` (called again after a cell
    fault: for the virtual cell it restarts the cell process); on_progress: called with a
    :class:`Progress` after every path; should_stop: polled between paths. The runner owns
    the cells ``connect`` gives it: :meth:`run` closes the one it holds when it returns or
    raises (``cell`` is then None).
    """

    #: the wait after the first link fault in a row and the longest (doubling between), s:
    #: with ``max_faults`` 20 the back-off sleeps add up to about 75 s, and each try waits
    #: its own timeout on top (a silent valve link: 137 s in all; a robot that does not
    #: reply: 325 s)
    FAULT_BACKOFF_S = (0.1, 5.0)

    def __init__(self, build_dir: Path, motion: "BuildMotion", job: "Job", journal: Journal,
                 connect: Callable[[], Cell], *,
                 on_progress: Callable[[Progress], None] | None = None,
                 should_stop: Callable[[], bool] = lambda: False,
                 max_faults: int = 20, accept_cell_reset: bool = False,
                 platform_cleared: bool = False) -> None:
        self.dir = Path(build_dir)
        self.motion = motion
        self.job = job
        self.journal = journal
        self.connect = connect
        self.on_progress = on_progress
        self.should_stop = should_stop
        self.max_faults = max_faults
        self.accept_cell_reset = accept_cell_reset
        self.platform_cleared = platform_cleared
        self.cell: Cell | None = None
        self.faults = 0            # link faults in a row (a call that works resets it)
        self._fault_since = 0.0
        # what the journal already says (a resumed build re-plans the layer it stopped in
        # and would say it again)
        self.findings: list[str] = [e["text"] for e in journal.events()
                                    if e["kind"] in FINDING_EVENTS]
        summary = getattr(motion.layers, "summary", None)   # a file's: no layer decoded
        if summary is not None:
            durations, n_paths = summary()
        else:
            n_paths = [len(_items(lm)[0]) + len(_items(lm)[1]) for lm in motion.layers]
            durations = [lm.duration for lm in motion.layers]
        self.progress = Progress(layers=len(motion.layers), paths=int(sum(n_paths)))
        self._durations = [float(d) for d in durations]
        self._last_status = 0.0
        self._pool = None       # one thread that plans the next layer ahead (_prefetch)
        self._ahead = None      # (layer position, future of (plan, valves, action))
        self._plan = None       # (layer position, its LayerPlan): a measurement's footprint
        self._report_due = False   # a measurement's report, drawn once the next layer runs
        self._pictures: tuple[str, str] | None = None   # the report's, till the next one

    # ------------------------------------------------------------------ cell link

    def _link(self) -> Cell:
        if self.cell is None:
            cell = self.connect()
            try:
                cell.hello()
            except BaseException:
                cell.close()
                raise
            self.cell = cell
            self._number_after_the_cell()
            self._reconcile()
        return self.cell

    def _number_after_the_cell(self) -> None:
        """A new build numbers its commands after those the cell completed: the cell keeps
        its last completed number across builds (it must, across a crash of the PC) and
        answers any number at or below it "done", so a second build on a cell numbered
        from 1 was complete at once with nothing deposited (a tester's). A cell that
        completed commands since its program started ran an earlier build, whose ice its
        platform may hold: refused before anything is sent (:func:`check_cell_numbers`),
        unless ``platform_cleared`` (the user's ``--platform-cleared``) or the journal says
        it was when the build started (its meta ``PLATFORM_CLEARED``: a resume needs no
        flag the start had)."""
        meta = self.journal.meta()
        if self.journal.has_commands() or "first_seq" in meta:
            return
        st = self.cell.status()
        last = max(int(st.last_done), int(st.cut))
        start = meta.get(CELL_DONE_AT_START)
        if start is not None and last > int(start):
            # the cell completed commands since this journal was made, and the journal
            # holds none: it lost its records (its -wal file deleted or left behind when
            # the folder was copied); numbering after the cell's, a hunt's resume built the
            # whole part again over the first, and said it was complete
            raise JournalError(
                f"{self.journal.path}: holds no command of this build, but the cell has "
                f"completed commands up to number {last} since it started (up to {start} "
                "before): the journal lost its records (was its -wal file deleted, or the "
                "folder copied without it?); nothing was sent. Restore the journal's files, "
                "or clear the platform and start a new build")
        if last <= 0:
            return
        check_cell_numbers(last, self.platform_cleared or bool(meta.get(PLATFORM_CLEARED)))
        self.journal.number_from(last + 1)
        self.journal.event("cell-numbers", f"the cell has completed commands up to number "
                           f"{last} (an earlier build; its platform was said cleared): "
                           f"this build numbers from {last + 1}")

    def _drop_link(self) -> None:
        cell, self.cell = self.cell, None
        if cell is not None:
            try:
                cell.close()
            except (OSError, CellError):
                pass

    def _reconcile(self) -> None:
        """Bring the journal up to what the cell completed (after a crash or fault).

        A cell whose record of completed commands ends below a path the journal has done
        lost its record (a new state folder, a controller restarted) or is another cell:
        a command sent but not confirmed may or may not have run there, and its platform
        may not hold this build's part. JournalError, unless ``accept_cell_reset`` (the
        user's ``--cell-lost-record``): then the journal's record stands and such a
        command counts as cut, never run twice (a tester's fresh cell ran a path the old
        one had run, and the build was 'complete' over a part missing its first layers)."""
        st = self.cell.status()
        highest = self.journal.highest_done()
        reset = highest > st.last_done
        if reset and not self.accept_cell_reset:
            raise JournalError(
                f"the cell's record of completed paths ends at number {st.last_done}, but "
                f"this build's journal has path {highest} done: the cell lost its record "
                "(a new state folder, its controller restarted) or is another cell, and "
                "its platform may not hold this build's part. Resume on the cell that ran "
                "it, or, if its platform holds the part, resume with --cell-lost-record "
                "(the journal's record then stands; a path sent but not confirmed counts "
                "as cut)")
        if reset:
            self.journal.event("cell-reset", f"the cell's record ends at {st.last_done}, "
                               f"the journal's at {highest}: the journal's record stands "
                               "(--cell-lost-record)", layer=self.progress.layer)
        first_open = True   # the first command sent and not confirmed: it may have run
        for c in self.journal.commands(open_only=True):
            if reset and c["sent"] is not None and c["seq"] > st.last_done:
                if first_open:
                    first_open = False
                elif c["kind"] == "path":
                    # a path after it was only uploaded ahead: its GO waits for the one
                    # before to be journaled done, so it never ran and is sent again (it
                    # was counted cut too, and the part missed it, a hunt's)
                    continue
                self.journal.done(c["seq"], cut=True)
                self.journal.event("cell-fault", f"{c['kind']} {c['layer']}/{c['item']} "
                                   f"(seq {c['seq']}) was sent before the cell lost its "
                                   "record: counted cut, not run again", layer=c["layer"])
            elif c["seq"] == st.cut:
                self.journal.done(c["seq"], cut=True)
                self.journal.event("cell-fault", f"{c['kind']} {c['layer']}/{c['item']} "
                                   f"(seq {c['seq']}) was cut short by a cell fault and is not "
                                   "run again: a deposition path's rest is missing (SMF "
                                   "absorbs it), a measurement path's samples are "
                                   "lost with it",
                                   layer=c["layer"])
            elif c["seq"] <= st.last_done:
                self.journal.done(c["seq"])

    def _call(self, fn: Callable[[Cell], object]) -> object:
        """A cell call, reconnecting (and reconciling) after a broken link."""
        while True:
            try:
                result = fn(self._link())
            except CellRefused as exc:    # the same again would be refused again
                self.journal.event("cell-refused", f"refused: {exc}",
                                   layer=self.progress.layer)
                self._drop_link()
                raise
            except CellError as exc:
                self.faults += 1
                self.journal.event("cell-link", f"cell link lost: {exc}",
                                   layer=self.progress.layer)
                self._drop_link()
                if self.faults > self.max_faults:
                    raise CellError(f"{exc} (gave up after {self.faults} link faults in a "
                                    f"row over {time.monotonic() - self._fault_since:.0f} s; "
                                    "resume when the cell answers again)") from None
                if self.faults == 1:
                    self._fault_since = time.monotonic()
                # the console and the status say it waits on the cell (a tester's stalled
                # cell left both silent for a minute)
                self.progress.waiting = f"link fault {self.faults}: {exc}"
                self._report(force=True)
                # faults in a row, backing off: a controller that takes a minute to come
                # back is waited for (a tester's three outages of 25 s ended a build: the
                # limit counted every fault of the run, 0.1 s apart); a stop asked
                # meanwhile ends the wait ('icefab build --stop' and Ctrl-C went unheard
                # for the 137 s a silent valve link took, a hunt's)
                first, most = self.FAULT_BACKOFF_S
                until = time.monotonic() + min(first * 2.0 ** (self.faults - 1), most)
                while True:
                    asked = self.should_stop()
                    if asked:
                        self.stop(f"{stop_cause(asked)} while the build waited for the "
                                  "cell's link")
                    left = until - time.monotonic()
                    if left <= 0:
                        break
                    time.sleep(min(left, 0.1))
                continue
            if self.faults:
                self.faults = 0
                self.progress.waiting = ""
                self._report(force=True)
            return result

    def _send(self, kind: str, layer: int, item: int, digest: str,
              fn: Callable[..., bool], upcoming: tuple | None = None) -> bool:
        """Journal, send and complete one command. ``upcoming``: (kind, layer, item,
        digest, CellPath) of the path after this one, which the cell may upload while this
        one runs (journaled as sent first); ``fn(cell, seq)``, or ``fn(cell, seq, (seq,
        CellPath) or None)`` when ``upcoming`` is given. False when the journal had it
        done before this call (a resumed layer's first paths: their time is not left)."""
        seq, _ = self.journal.command(kind, layer, item, digest)
        if self.journal.is_done(seq):
            return False
        self._call(lambda cell: None)  # connected and reconciled before sending
        if self.journal.is_done(seq):  # the reconciliation found it done or cut
            return False
        self.journal.sent(seq)
        if upcoming is not None:
            up_seq, _ = self.journal.command(*upcoming[:4])
            if self.journal.is_done(up_seq):
                up = None
            else:
                self.journal.sent(up_seq)     # it may reach the cell from now on
                up = (up_seq, upcoming[4])
            call = fn
            fn = lambda cell, s: call(cell, s, up)    # noqa: E731
        # after a lost link _call reconnects and reconciles, then calls again: a command the
        # reconciliation found done or cut must not be sent a second time (a cut path sent
        # again would deposit its first part twice)
        executed = self._call(lambda cell: None if self.journal.is_done(seq)
                              else fn(cell, seq))
        if self.journal.is_done(seq):  # a fault during the call, reconciled
            return True
        self.journal.acked(seq)
        self.journal.done(seq)
        if executed is False:
            log.info("%s %d/%d (seq %d): the cell had done it already", kind, layer, item,
                     seq)
        return True

    # ------------------------------------------------------------------ the build

    def _restore(self):
        """The SMF state and action sampler after the journal's last SMF update."""
        from icefab import feedback

        last = self.journal.last_smf()
        if last is None:
            return feedback.SmfState(), None
        return unpack_smf(last[2])

    def run(self) -> Progress:
        """Run (or resume) the build to its end; see the module docstring."""
        try:
            return self._run()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool, self._ahead = None, None
            # a link left open lives until the runner is collected: its socket then closes
            # at some later moment (CI warned of an unclosed socket in an unrelated test)
            self._drop_link()

    def _run(self) -> Progress:
        job = self.job
        state, action = self._restore()
        done_layers = set(self.journal.layers_done())
        measured = {m["layer"]: m for m in self.journal.measurements(samples=False)}
        smf_layers = self.journal.measured_layers()
        dh = job.slicing.layer_thickness_mm
        p = self.progress
        p.rms = [(m["layer"], m["nominal_z"], m["rms_measured"]) for m in measured.values()]
        if p.rms:
            p.last_rms_mm = p.rms[-1][2]
        p.paths_done = self.journal.paths_done()

        def finished(j: int) -> bool:
            lm = self.motion.layers[j]
            return layer_finished(int(lm.index), done_layers, smf_layers, measures(lm),
                                  self.journal.cut_layers())

        # the status names the layer the build goes on with (a build killed before its
        # first status after a resume read "layer 0 (3 of 3), ETA 0:00:00")
        j0 = next((j for j in range(len(self.motion.layers)) if not finished(j)),
                  len(self.motion.layers))
        if self.motion.layers:
            self._name_layer(min(j0, len(self.motion.layers) - 1))
            p.layer_pos = j0
            p.remaining_s = float(sum(self._durations[j0:]))
        ran0 = 0.0
        # a journal with every layer finished (killed before it journaled "complete") has
        # nothing to send: its cell may be gone, and waiting for it stopped there
        if j0 < len(self.motion.layers):
            self._call(lambda cell: None)
            # less what a partly built layer ran before, as the journal says once the
            # cell's record is in (it said "paths 30/164, ETA" of the whole layer: a hunt's)
            ran0 = _ran_s(self.journal, self.motion.layers[j0])
            p.remaining_s -= ran0
        # this run's pace from here: linked, what ran before it not counted
        p.pace_since, p.pace_left0_s = time.monotonic(), p.remaining_s
        # running from here on for 'icefab build --stop': without it a stop asked during
        # the first path found no status, told the cell directly, and the build ran on
        self._report(force=True)
        for j, lm in enumerate(self.motion.layers):
            L = int(lm.index)
            meas_items = _items(lm)[1]
            self._name_layer(j)
            p.layer_pos = j
            # the partly built layer less what it ran (a stop before its first path said
            # the whole layer's ETA again: a hunt's)
            p.remaining_s = float(sum(self._durations[j:])) - (ran0 if j == j0 else 0.0)
            cut_here = L in self.journal.cut_layers()
            if finished(j):
                continue
            lv, cps = self._layer_valves(j, action)
            for kind, said in (("saturation", saturation_finding(lv.programs, L)),
                               ("clamp", clamp_finding(lv.programs, L))):
                if said is not None and said not in self.findings:
                    self.findings.append(said)
                    self.journal.event(kind, said, layer=L)
            # the action stays until this layer's end unless it measures: plan the next
            # layer's programs while this one runs (from its first path on: the planning
            # thread holds the GIL in stretches, which must not delay the first GO)
            ahead = not meas_items and not cut_here
            if job.feedback.controller == "speed" and action is not None:
                for f in check_speeds(lv.trajectories, job, L):
                    if f not in self.findings:
                        self.findings.append(f)
                        self.journal.event("motion-limit", f, layer=L)
            z_mm = lm.top(job)   # the layer's top (its cutting plane lm.z is inside it)
            le_digest = digest_text(f"layer_end {L}")
            for k, (i, tr, cp, dg) in enumerate(cps):
                self._stop_point()
                # the next path goes to the cell while this one moves
                if k + 1 < len(cps):
                    nxt = cps[k + 1]
                    upcoming = ("path", L, nxt[0], nxt[3], nxt[2])
                else:
                    upcoming = self._next_layer_first(j, done_layers)
                    if upcoming is not None:
                        # numbered in the order the cell runs them: this layer's end first
                        self.journal.command("layer_end", L, -1, le_digest)
                ran = self._send("path", L, i, dg,
                                 lambda c, s, u=None, cp=cp: c.run_path(s, cp, u),
                                 upcoming=upcoming)
                p.paths_done = self.journal.paths_done()
                if ran:   # one done before this run is not in the time left (ran0)
                    p.remaining_s -= float(tr.duration)
                if k == 0:   # after the counts: its report names the path done
                    self._layer_started(j, action, ahead)
                self._report()
            if not cps:
                self._layer_started(j, action, ahead)
            self._stop_point()
            self._send("layer_end", L, -1, le_digest, lambda c, s, L=L: c.end_layer(s, L))
            kind = "path"
            if not meas_items and L in self.journal.cut_layers():  # cut during this layer
                # a cell fault cut a path of this layer short: measure the surface before
                # the next layer (with the nearest measurement layer's paths) so SMF absorbs
                # the missing material now, not n_d layers later
                meas_items = self._fault_measure_items(j)
                kind = "fault_measure"
                # another layer's scans: the next status may come after the longest of them
                p.longest_s = max([p.longest_s, *(float(tr.duration) for _, tr in meas_items)])
                if meas_items and self._numbered_beyond(L, le_digest):
                    # the fault cut the layer's last path while the next layer's first
                    # path had been sent ahead: numbered before any measurement now, it
                    # must run first (numbers run in order); SMF absorbs the error at the
                    # next measurement
                    meas_items = []
                    if L not in smf_layers:
                        self.journal.event("fault-measure", f"layer {L}: not measured after "
                                           "the cell fault (the next layer's first path was "
                                           "sent already); SMF absorbs it at the next "
                                           "measurement", layer=L)
                elif meas_items and L not in smf_layers:
                    self.journal.event("fault-measure", f"layer {L}: surface measured after "
                                       "the cell fault, before the next layer", layer=L)
            if meas_items:
                raws = []
                for i, tr in meas_items:
                    self._stop_point()
                    cp = CellPath(layer=L, item=i, role="measure", tool="laser",
                                  xy=np.asarray(tr.xy, np.float64), dt_s=float(tr.dt),
                                  z_mm=z_mm, width_mm=0.0)
                    ran = self._send(kind, L, i, cp.digest(),
                                     lambda c, s, cp=cp: c.run_path(s, cp))
                    seq, _ = self.journal.command(kind, L, i, cp.digest())
                    raw = self.journal.laser_of(seq)
                    if raw is None and self.journal.is_cut(seq):   # a fault stopped it
                        raw = np.zeros((0, 4))
                    elif raw is None:
                        # journaled before the next path: the laser keeps one path's values
                        raw = self._call(lambda c, s=seq, cp=cp: c.laser_samples(s, cp))
                        self.journal.laser(seq, raw)
                    if len(raw) == 0 and L not in smf_layers:
                        self.journal.event("measurement", f"layer {L}: measurement path {i} "
                                           "gave no laser samples", layer=L)
                    raws.append(laser_to_part(np.asarray(raw), tr, job))
                    p.paths_done = self.journal.paths_done()
                    # a fault's measurement was never in the plan's time, one done before
                    # this run is not in the time left
                    if kind == "path" and ran:
                        p.remaining_s -= float(tr.duration)
                    # a minutes-long measurement left the status and the console silent,
                    # as a hung build would (a hunt's)
                    self._report()
                samples = np.concatenate(raws) if raws else np.zeros((0, 3))
                nominal = (j + 1) * dh
                if L not in smf_layers:
                    state, u, filled, rms, note = smf_from_samples(
                        samples, nominal, state, job, self._footprint(j))
                    if note is not None:
                        self.journal.event("measurement", f"layer {L}: {note}", layer=L)
                    k = len(smf_layers) + 1
                    self.journal.measurement(k, L, nominal, samples, rms,
                                             smf_state=pack_smf(state, u, filled))
                    smf_layers.add(L)
                    p.rms.append((L, nominal, rms))
                    p.last_rms_mm = rms
                state, action = self._restore()
                # the report's pictures take a while: drawn once the next layer runs
                self._report_due = True
            p.layer_pos = j + 1
            if j + 1 < len(self.motion.layers):   # the status names the layer that is next
                self._name_layer(j + 1)
            self._report(force=True)
        p.state = "complete"
        p.layer_pos = len(self.motion.layers)
        p.remaining_s = 0.0
        self.journal.event("complete", f"build complete: {p.paths_done} paths")
        self._report(force=True, measured=True)
        return p

    def _layer_started(self, j: int, action, ahead: bool) -> None:
        """Work that waits until layer position ``j`` runs (its first path done): plan
        the next layer ahead (with a measurement first only its motion plan, which no
        action changes) and draw the report a measurement left due."""
        self._prefetch(j + 1, action, plan_only=not ahead)
        if self._report_due:
            self._report_due = False
            self._report(force=True, measured=True)

    def _layer_valves(self, j: int, action):
        """(valve programs, cell paths) of layer position ``j`` with ``action``: the
        prefetched ones when they were planned with this very action, else planned now.
        Cell paths: (trajectory index, trajectory, CellPath, its digest) of every
        deposition and travel trajectory in order."""
        from icefab import sim as simmod

        fut, self._ahead = self._ahead, None
        if fut is not None and fut[0] == j:
            plan, lv, cps, with_action = fut[1].result()
            self._plan = (j, plan)
            if lv is not None and with_action is action:
                return lv, cps
        else:
            plan = self._layer_plan(j)
        lv = simmod.layer_valves(plan, self.job, action)
        return lv, self._cell_paths(j, lv)

    def _layer_plan(self, j: int):
        """The LayerPlan of layer position ``j`` (:func:`icefab.sim.plan_layer_motion`):
        the one its valve programs were made from when that was this layer (a measurement
        takes its footprint from it), else planned and kept."""
        from icefab import sim as simmod

        if self._plan is None or self._plan[0] != j:
            self._plan = (j, simmod.plan_layer_motion(self.motion.layers[j], self.job))
        return self._plan[1]

    def _footprint(self, j: int) -> tuple[np.ndarray, HeightMap]:
        """The cells layer position ``j``'s beads cover, and their grid
        (:func:`icefab.sim.commanded_footprint`): SMF's measured surface is restricted to
        them, as the simulator's is."""
        from icefab import sim as simmod

        return simmod.commanded_footprint(self._layer_plan(j), self.job,
                                          self.motion.layers[j].thickness)

    def _cell_paths(self, j: int, lv) -> list:
        from icefab import flow

        job = self.job
        lm = self.motion.layers[j]
        L = int(lm.index)
        dep = iter(zip(lv.trajectories, lv.programs))
        z_mm = lm.top(job)
        cps = []
        for i, tr in _items(lm)[0]:
            path = tr.path
            if path is not None and path.depositing:
                traj, prog = next(dep)
                cp = CellPath(layer=L, item=i, role=path.role, tool=path.material,
                              xy=np.asarray(traj.xy, np.float64), dt_s=float(traj.dt),
                              z_mm=z_mm, width_mm=flow.trajectory_width(traj, path.material,
                                                                        job),
                              program=flow.encode_valve_program(prog))
            else:
                cp = CellPath(layer=L, item=i, role="travel", tool="none",
                              xy=np.asarray(tr.xy, np.float64), dt_s=float(tr.dt),
                              z_mm=z_mm, width_mm=0.0)
            cps.append((i, tr, cp, cp.digest()))
        return cps

    def _prefetch(self, j: int, action, *, plan_only: bool = False) -> None:
        """Plan layer position ``j`` (motion plan and valve programs with ``action``, or
        with ``plan_only`` the motion plan alone, which no action changes) on a
        background thread; :meth:`_layer_valves` takes it when its turn comes."""
        from concurrent.futures import ThreadPoolExecutor

        from icefab import sim as simmod

        if j >= len(self.motion.layers) or (self._ahead is not None and self._ahead[0] == j):
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="plan-ahead")
        lm, job = self.motion.layers[j], self.job

        def plan_ahead():
            plan = simmod.plan_layer_motion(lm, job)
            if plan_only:
                return plan, None, None, None
            lv = simmod.layer_valves(plan, job, action)
            return plan, lv, self._cell_paths(j, lv), action
        self._ahead = (j, self._pool.submit(plan_ahead))

    def _next_layer_first(self, j: int, done_layers: set) -> tuple | None:
        """(kind, layer, item, digest, CellPath) of the first path of layer position
        ``j + 1`` when it was planned ahead (with this layer's action) and is ready: the
        cell may upload it while this layer's last path moves. None otherwise (a layer
        with measurement or a cut path before it: its action changes)."""
        a = self._ahead
        if a is None or a[0] != j + 1 or not a[1].done() or a[1].exception() is not None:
            return None
        L = int(self.motion.layers[j].index)
        nxt = self.motion.layers[j + 1]
        if _items(self.motion.layers[j])[1] or L in self.journal.cut_layers() \
                or int(nxt.index) in done_layers:
            return None
        cps = a[1].result()[2]
        if not cps:
            return None
        i, _tr, cp, dg = cps[0]
        return ("path", int(nxt.index), i, dg, cp)

    def _numbered_beyond(self, layer: int, le_digest: str) -> bool:
        """Whether a command of a later layer was numbered after layer ``layer``'s end
        (its own fault measurement, numbered on an earlier run, does not count)."""
        seq, _ = self.journal.command("layer_end", layer, -1, le_digest)
        return self.journal.numbered_after(seq, layer)

    def _fault_measure_items(self, j: int) -> list:
        """The measurement trajectories nearest layer position ``j`` (the last measurement
        layer at or below it, else the next one above): their paths cover the part's
        footprint there."""
        order = sorted(range(len(self.motion.layers)), key=lambda k: (abs(k - j), k > j))
        for k in order:
            _run, meas = _items(self.motion.layers[k])
            if meas:
                return meas
        return []

    def _name_layer(self, j: int) -> None:
        """The progress names the layer at position ``j``: its index, and its longest path
        (how soon the status is written again: :data:`UPDATE_MARGIN_S`)."""
        lm = self.motion.layers[j]
        self.progress.layer = int(lm.index)
        self.progress.longest_s = float(lm.durations.max(initial=0.0))

    def _stop_point(self) -> None:
        asked = self.should_stop()
        if asked:
            self.stop(stop_cause(asked))

    def stop(self, why: str) -> None:
        """Valves off first, robot to its safe point (the cell's ``stop``), journaled;
        then BuildStopped, saying why (``why``) and what the cell did
        (:func:`stop_outcome`)."""
        if self.cell is None:    # between link faults: there is no link to tell it by
            done = stop_outcome(told=False)
        else:
            try:
                done = stop_outcome(told=True, lifted_mm=self.cell.stop())
            except CellError as exc:
                self.journal.event("stop", f"the cell did not answer the stop ({exc})",
                                   layer=self.progress.layer)
                done = stop_outcome(told=True, error=str(exc))
        self.journal.event("stop", f"stopped at layer {self.progress.layer} after "
                           f"{self.progress.paths_done} paths: {why}; {done}",
                           layer=self.progress.layer)
        self.progress.state = "stopped"
        self._report(force=True, measured=True)
        raise BuildStopped(f"stopped at layer {self.progress.layer}: {why}; {done}; resume "
                           f"with 'icefab build --resume {self.dir}'")

    def fail(self, message: str) -> None:
        """Record that the build ended on an error (journal event, status and report say
        so): a valve program refused mid-build left status.json and report.html saying
        "running" (a tester's)."""
        self.journal.event("failed", f"the build stopped on an error: {message}")
        self.progress.state = "failed"
        self.progress.waiting = ""
        write_status(self.dir, self.progress, self.journal)
        write_report(self.dir, self.progress, self.journal, self.job)

    def _report(self, *, force: bool = False, measured: bool = False) -> None:
        if self.on_progress is not None:
            self.on_progress(self.progress)
        now = time.monotonic()
        if force or now - self._last_status > 1.0:
            self._last_status = now
            write_status(self.dir, self.progress, self.journal)
            # the page with every status (it was written at measurements only: missing
            # for the first layers, frozen between, "stopped" through a resume: a hunt's);
            # its pictures drawn again only after a measurement
            if measured:
                self._pictures = report_pictures(self.progress, self.journal, self.job)
            elif self._pictures is None:
                self._report_due = True   # drawn once a path runs, not before the first GO
            if self._pictures is not None:
                write_report(self.dir, self.progress, self.journal, self.job, self._pictures)


def stop_cause(asked) -> str:
    """Why the build stops, from what ``should_stop`` returned: its words when it says
    who asked (``icefab build``: Ctrl-C, SIGTERM, ``--stop``), else a stop was asked."""
    return asked if isinstance(asked, str) else "a stop was asked for"


def stop_outcome(*, told: bool, lifted_mm: float | None = None,
                 error: str | None = None) -> str:
    """What a stop did at the cell, for the stop's message: ``told``, whether there was
    a link to tell the cell by; ``error``, the cell's failure to answer; ``lifted_mm``,
    how far the cell's ``stop`` lifted the tool, mm (0: not lifted; None: the cell does
    not say). Only what was done: the message said "a stop was asked for" and never
    whether the valves were closed or the tool lifted (a reviewer's)."""
    if not told:
        return "the cell was not told (no link to it then): check it"
    if error is not None:
        return f"the cell did not answer the stop ({error}): check it"
    if lifted_mm is None:
        return "the cell was told to stop (valves off first, then the robot)"
    if lifted_mm > 0:
        return f"valves closed, robot stopped, tool lifted {lifted_mm:g} mm"
    return "valves closed, robot stopped where it was (the tool was not lifted)"


# =========================================================================== status, report


#: The keys of ``status.json`` and of ``icefab build --status --json``, in every state
#: (preparing: null where not known yet; state one of preparing, running, stopped,
#: interrupted, failed, complete). ``eta_s``: the planned motion time left, s (not wall
#: time: a virtual cell runs faster, a real one adds uploads, layer ends and SMF
#: updates); ``eta_wall_s``: the wall time left at this run's pace so far, s
#: (:func:`pace_eta_s`; null until it ran PACE_MIN_RAN_S of planned motion, and when not
#: running).
STATUS_KEYS = ("state", "pid", "time", "update_by", "layer", "layers_done", "layers",
               "paths_done", "paths", "eta_s", "eta_wall_s", "last_rms_mm", "rms", "waiting",
               "events")

#: A running build writes its status again within twice the current layer's longest path
#: (a path's wait on the cell times out at 1.5 times its length plus 10 s, and the fault
#: is reported) plus this, s: the measurement's SMF update, the next layer's valve
#: programs. ``update_by`` in the status: a status older than that, still "running", is a
#: build whose process ended without a word (killed, its PC stopped); the page said
#: "running" and reloaded for ever (a hunt's).
UPDATE_MARGIN_S = 120.0


def status_dict(progress: Progress, journal: Journal) -> dict:
    now = time.time()
    return {"state": progress.state, "pid": os.getpid(), "time": now,
            "update_by": now + 2.0 * progress.longest_s + UPDATE_MARGIN_S
            if progress.state == "running" else None,
            "layer": progress.layer, "layers_done": progress.layer_pos,
            "layers": progress.layers, "paths_done": progress.paths_done,
            "paths": progress.paths, "eta_s": progress.remaining_s,
            "eta_wall_s": progress.eta_wall_s(),
            "last_rms_mm": None if not math.isfinite(progress.last_rms_mm)
            else progress.last_rms_mm,
            "rms": [{"layer": int(a), "nominal_z_mm": float(b),
                     "rms_measured_mm": None if not math.isfinite(c) else float(c)}
                    for a, b, c in progress.rms],
            "waiting": progress.waiting or None,
            "events": [e["text"] for e in journal.events()[-20:]]}


def write_status(build_dir: Path, progress: Progress, journal: Journal) -> None:
    from icefab.atomic import write_atomic

    write_atomic(Path(build_dir) / STATUS,
                 json.dumps(status_dict(progress, journal), indent=1) + "\n")


def format_eta(seconds: float) -> str:
    s = max(0, int(round(seconds)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


def eta_text(planned_s: float, wall_s: float | None) -> str:
    """The ETA as the console, ``--status`` and the report say it: at this run's pace
    (``wall_s``, s) with the planned motion left (``planned_s``, s) beside it, or the
    planned motion alone, labelled so (it read as wall time: a reviewer's)."""
    if wall_s is None:
        return f"ETA {format_eta(planned_s)} (planned motion)"
    return f"ETA {format_eta(wall_s)} (pace so far; planned motion {format_eta(planned_s)})"


def layer_place(layer: int, layers_done: int, layers: int) -> str:
    """"8 (9 of 12)": the layer's index, as every other message names layers (the stop's
    "stopped at layer 8"), and its place in the build, counted from 1."""
    return f"{layer} ({min(layers_done + 1, layers)} of {layers})"


def progress_line(p: Progress) -> str:
    rms = f"{p.last_rms_mm:.3f} mm" if math.isfinite(p.last_rms_mm) else "-"
    wait = f"; waiting for the cell ({p.waiting})" if p.waiting else ""
    return (f"layer {layer_place(p.layer, p.layer_pos, p.layers)}, paths {p.paths_done}/"
            f"{p.paths}, {eta_text(p.remaining_s, p.eta_wall_s())}, last RMS {rms}{wait}")


def report_pictures(progress: Progress, journal: Journal, job: "Job") -> tuple[str, str]:
    """The report's pictures as HTML: RMS vs height (inline SVG) and the latest measured
    error surface (a PNG, or a line saying why there is none)."""
    import base64
    import io

    from icefab.report import pyplot

    plt = pyplot()
    rows = progress.rms
    fig, ax = plt.subplots(figsize=(6.4, 3.4))
    if rows:
        zs = [r[1] for r in rows]
        ax.plot(zs, [r[2] for r in rows], "o-", label="measured RMS")
    else:
        ax.text(0.5, 0.5, "no layer measured", ha="center", va="center",
                transform=ax.transAxes, color="0.4")
    ax.set_xlabel("nominal height (mm)")
    ax.set_ylabel("RMS height error (mm)")
    ax.set_title("RMS error vs height (laser samples)")
    ax.grid(alpha=0.3)
    fig.tight_layout()   # the x axis' label was cut off below the picture (a hunt's)
    buf = io.StringIO()
    fig.savefig(buf, format="svg")
    plt.close(fig)
    svg = buf.getvalue()
    svg = svg[svg.index("<svg"):].replace("<svg", '<svg id="rms-plot" role="img"', 1)
    surface_img = ""
    meas = journal.measurements(last=True)
    if meas:
        from icefab import feedback
        from icefab.errors import GeometryError

        m = meas[-1]
        try:
            surf = feedback.surface_from_samples(m["samples"], None, job.feedback.grid_mm)
            err = surf.z - m["nominal_z"]
            x, y = surf.grid()
            fig, ax = plt.subplots(figsize=(5.2, 4.2))
            lim = float(np.nanmax(np.abs(err))) if np.isfinite(err).any() else 1.0
            im = ax.pcolormesh(x, y, err, cmap="RdBu_r", vmin=-lim, vmax=lim, shading="nearest")
            fig.colorbar(im, ax=ax, label="measured - nominal (mm)")
            ax.set_aspect("equal")
            ax.set_xlabel("x, part frame (mm)")
            ax.set_ylabel("y, part frame (mm)")
            ax.set_title(f"error surface, layer {m['layer']} (z = {m['nominal_z']:.2f} mm)")
            fig.tight_layout()
            b = io.BytesIO()
            fig.savefig(b, format="png", dpi=80)
            plt.close(fig)
            surface_img = ('<img id="error-surface" alt="latest error surface" src="data:image/'
                           f'png;base64,{base64.b64encode(b.getvalue()).decode()}">')
        except GeometryError:
            surface_img = "<p>too few laser samples for a surface</p>"
    return svg, surface_img


def write_report(build_dir: Path, progress: Progress, journal: Journal, job: "Job",
                 pictures: tuple[str, str] | None = None) -> None:
    """``BUILD/report.html``: RMS vs height (inline SVG), the latest measured error
    surface (PNG), status and ETA, findings and events; self-contained, refreshes itself
    every 30 s while the build runs (a finished build's page stays put), no scripts.
    ``pictures``: :func:`report_pictures`' (drawn here when not given)."""
    import html

    from icefab.atomic import write_atomic

    svg, surface_img = pictures if pictures is not None else report_pictures(
        progress, journal, job)
    st = status_dict(progress, journal)
    e = html.escape
    status_rows = "".join(
        f"<tr><th>{e(k)}</th><td>{e(str(v))}</td></tr>" for k, v in (
            ("state", st["state"]),
            ("layer", layer_place(progress.layer, progress.layer_pos, progress.layers)),
            ("paths", f"{progress.paths_done} of {progress.paths}"),
            ("ETA (planned motion)", format_eta(progress.remaining_s)),
            *([("ETA (pace so far)", format_eta(st["eta_wall_s"]))]
              if st["eta_wall_s"] is not None else []),
            ("last RMS (mm)", "-" if st["last_rms_mm"] is None
             else f"{st['last_rms_mm']:.4f}"),
            ("updated", time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(st["time"]))),
            *([("next update by", time.strftime("%Y-%m-%d %H:%M:%S",
                                                time.localtime(st["update_by"]))
                + " (if this page is older then, the build's process has ended: "
                f"'icefab build --status {Path(build_dir).name}')")]
              if st["update_by"] is not None else [])))
    events = "".join(f"<li>{e(time.strftime('%H:%M:%S', time.localtime(ev['time'])))} "
                     f"[{e(ev['kind'])}] {e(ev['text'])}</li>" for ev in journal.events()[-30:])
    # an open-loop build never measures: "no measurement yet" promised one (a tester's)
    # and a finished build that measured no layer (a short one) will not measure one
    no_surface = ("none: this build measures nothing (feedback.enabled = false)"
                  if not job.feedback.enabled else "no measurement yet"
                  if st["state"] in ("running", "preparing")
                  else "none: no layer of this build was measured")
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
{'<meta http-equiv="refresh" content="30">' if st["state"] == "running" else ""}
<title>icefab build: {e(st['state'])}</title>
<style>body{{font-family:sans-serif;margin:1.5em;max-width:60em}}
th{{text-align:left;padding-right:1em}} img,svg{{max-width:100%;height:auto}}</style>
</head><body>
<h1>icefab build</h1>
<table id="status">{status_rows}</table>
<h2>RMS height error vs height</h2>
{svg}
<h2>Latest error surface</h2>
{surface_img or f'<p>{no_surface}</p>'}
<h2>Findings and events</h2>
<ul id="events">{events or '<li>none</li>'}</ul>
</body></html>
"""
    write_atomic(Path(build_dir) / REPORT, page)
