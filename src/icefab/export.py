"""Programs for other machines: G-code for a gantry cell (thesis 7: "many three-axis CNC
machines use positioning data coupled with feedrates", and MTTS output converts to it).

Convention: **Marlin 2.x with its cutter (laser/spindle) output driving the valve**
(``LASER_FEATURE``, ``LASER_POWER_INLINE``, power unit PWM255). Marlin applies inline
power per planner block, so the valve's duty changes exactly with the moves, the way
the C40's trigger keeps the valve controller in step with the robot (thesis 2.3.1).

* ``G21``, ``G90``; ``M3 I S0``: inline power mode, valve closed.
* Per layer: ``; layer K top z Z (cut at C)`` and ``G0 Z..``: the layer's nominal top, mm
  above the platform (``LayerMotion.top``; the nozzle's own offset is the machine's).
* Every ``G0`` carries its ``F``: ``motion.travel_speed_mm_s`` (Marlin caps it at each
  axis' own maximum). F is modal: without it a layer's move up and over to its first
  path ran at the last path's slowing step, ~50 mm/min (a tester's gantry mug: 20 312 s of
  such moves beside 18 738 s of planned motion).
* Material (nozzle) change: ``T0 S1`` (part, water) / ``T1 S1`` (scaffold) before a path of
  the other material (``S1``: Marlin does not move the tool in XY for the change; the next
  line moves it). The machine routes the cutter PWM to that nozzle's valve in its tool
  change (for example Marlin's ``EVENT_GCODE_TOOLCHANGE_T0`` / ``_T1`` switching a mux pin
  with ``M42``). X, Y are already the carriage positions that put the chosen nozzle on the
  part (the trajectories' base-frame samples), so the tool change applies no offset.
* Travel and measurement paths: ``G0`` moves, valve closed (``S0``).
* Deposition paths: ``G0`` to the first sample, then one ``G1 X Y F S`` per time step
  (:func:`icefab.motion.gcode_moves`): ``F`` the step's length over ``dt`` (mm/min), so
  each move lasts one time step (thesis 4.3), and ``S`` the valve's duty over that step,
  0..255: the pulse widths of the path's PWM valve program (:func:`icefab.flow.plan_valves`
  with ``flow.mode = "pwm"``, thesis 6.1: flow by pulse width at
  ``flow.pwm_frequency_hz``) falling in the step, over the step's length. Set the
  machine's cutter PWM frequency (``SPINDLE_LASER_FREQUENCY``) to
  ``flow.pwm_frequency_hz``. A step at rest is a dwell ``G4 P<ms>`` (valve closed).
* End: ``M5`` (valve off).

**What the machine's Marlin must be built with** for every move to last its one step
(``dt`` = ``motion.dt_s``, 16 ms by default): ``DEFAULT_MINSEGMENTTIME`` at most ``dt``
in microseconds (stock 20 000: Marlin stretches shorter moves when its buffer runs low,
and the valve's duty with them), ``MIN_STEPS_PER_SEGMENT`` 1 (stock 6: a move of fewer
steps, 0.075 mm at 80 steps/mm, is folded into the next at that move's F, and a path's
slowing steps lose their time), ``SLOWDOWN`` off, and a planner buffer
(``BLOCK_BUFFER_SIZE``) and serial link that stream 1 / dt moves a second. The file's
header says so too.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["save_gcode", "step_duty", "gcode_lines", "check_gcode_robot"]

TOOL_NUMBER = {"part": 0, "scaffold": 1}


def step_duty(trajectory, program, period_s: float | None = None) -> np.ndarray:
    """(n - 1,) float64 in [0, 1]: the valve's duty over each time step of ``trajectory``
    (samples every ``dt``) under the PWM ``program`` (pulse instants from
    :func:`icefab.flow.pulse_times`, with their widths).

    period_s: the PWM period. Each pulse's width is then spread over its period, so a step
    shorter than the period gets the duty of the period it lies in: the duty Marlin's
    cutter PWM takes per move (a whole pulse counted in the step it started in left the
    steps between pulses at S0 and the others at twice the duty). None: the time the
    pulses hold the valve open within each step. Either way the steps' on-time sums to
    the pulses' (up to the last step's clip at duty 1)."""
    from icefab import flow

    n = len(trajectory.xy)
    if n < 2:
        return np.zeros(0)
    dt = float(trajectory.dt)
    t = flow.pulse_times(program)
    widths = np.concatenate([p.widths_us for p in flow.program_pieces(program)]
                            ).astype(np.float64) * 1e-6 if len(t) else np.zeros(0)
    on = np.zeros(n - 1)
    if len(t):
        span = widths if period_s is None else np.full(len(t), float(period_s))
        rate = np.where(span > 0, widths / np.where(span > 0, span, 1.0), 0.0)
        first = np.floor(t / dt + 1e-9).astype(np.int64)
        end = t + span
        for j in range(int(np.ceil(span.max() / dt)) + 2):
            k = first + j
            part = (np.minimum(end, (k + 1) * dt) - np.maximum(t, k * dt)) * rate
            ok = part > 0.0
            on += np.bincount(np.clip(k[ok], 0, n - 2), weights=part[ok], minlength=n - 1)
    return np.clip(on / dt, 0.0, 1.0)


def check_gcode_robot(robot: str, what: str, *, planning: bool = False) -> None:
    """Refuse G-code from trajectories planned for another robot than a gantry.

    The G-code's X, Y are a gantry's carriage positions and each move's F holds the
    speed MTTS planned under that robot's limits. A SCARA's trajectories are in its base
    frame (the Cobra's part at Y -160..-61 mm) and timed by its joint limits: on a gantry
    they would build elsewhere, at other speeds, under a header that said "gantry".
    what: the file or option named in the message; planning: the job is about to plan
    them (``plan --gcode``). Raises ConfigError.
    """
    from icefab.errors import ConfigError

    if robot != "gantry":
        whose = "the job plans for" if planning else "these trajectories were planned for"
        raise ConfigError(f"{what}: G-code is for a gantry, not the {robot} {whose} (its "
                          "base frame, its joint limits); plan for a gantry with [cell] "
                          "robot = \"gantry\"")


def gcode_job(job, what: str):
    """The job G-code's valve follows: ``flow.mode = "pwm"`` (Marlin's cutter PWM drives
    it, at ``flow.pwm_frequency_hz``). ConfigError naming ``what`` and why when that job
    is not valid: an FM job whose valve tops out below the PWM frequency was refused
    only after planning, naming a setting the user never set (hunt W)."""
    from icefab.errors import ConfigError

    if job.flow.mode == "pwm":
        return job
    try:
        return job.replace(**{"flow.mode": "pwm"})
    except ConfigError as exc:
        raise ConfigError(f"{what}: G-code drives the valve by PWM (Marlin's cutter output), "
                          f"and this job's PWM settings do not hold: {exc}") from None


def gcode_lines(motion, job=None):
    """The G-code of a BuildMotion planned for a gantry, line by line (see the module
    docstring; :func:`check_gcode_robot`)."""
    from icefab import flow
    from icefab.motion import gcode_moves

    check_gcode_robot(motion.robot, "the trajectories")
    job = job if job is not None else motion.job
    pwm = gcode_job(job, "the trajectories")
    yield (f"; icefab G-code for a gantry, Marlin 2.x (cutter PWM drives the valve, inline "
           f"power 0-255, PWM at {pwm.flow.pwm_frequency_hz:g} Hz)")
    yield (f"; dt {job.motion.dt_s:g} s, {motion.duration:.1f} s of motion; "
           "X, Y: carriage (base frame), mm; F: mm/min; T0 part, T1 scaffold")
    yield (f"; every move lasts dt: needs DEFAULT_MINSEGMENTTIME <= "
           f"{job.motion.dt_s * 1e6:.0f} us, MIN_STEPS_PER_SEGMENT 1, SLOWDOWN off")
    rapid = 60.0 * job.motion.travel_speed_mm_s
    yield "G21"
    yield "G90"
    yield "M3 I S0"
    tool = None
    for lm in motion.layers:
        # the nozzle at the layer's top (its cutting plane lm.z lies inside it: at mid-height
        # by default, which put the nozzle into its own bead)
        top = lm.top(job)
        yield f"; layer {lm.index} top z {top:.4f} (cut at {lm.z:.4f})"
        # every G0 with S0: Marlin's G0 keeps the inline power of the move before unless
        # built with LASER_MOVE_G0_OFF, and a layer's last move may be depositing
        yield f"G0 Z{top:.4f} F{rapid:.1f} S0"
        for i, tr in enumerate(lm.trajectories):
            if len(tr.xy) == 0:
                continue
            p = tr.path
            role = p.role if p is not None else "travel"
            depositing = p is not None and p.depositing
            what = f"{p.material} {role}, width {p.width:g} mm" if p is not None else "path"
            yield f"; path {i}: {what}, {tr.duration:.3f} s"
            if not depositing:
                # travel or measurement: positioning only, valve closed
                for line in gcode_moves(tr, dwell=True, rapid_mm_min=rapid):
                    yield line.replace("G1 ", "G0 ", 1) + " S0" if line.startswith("G") \
                        and not line.startswith("G4") else line
                continue
            if tool != p.material:
                tool = p.material
                yield f"T{TOOL_NUMBER[tool]} S1"
            prog = flow.plan_valves(tr, p.material, pwm)
            s = np.rint(255.0 * step_duty(tr, prog, 1.0 / pwm.flow.pwm_frequency_hz)
                        ).astype(np.int64)
            moves = gcode_moves(tr, power=s, dwell=True, rapid_mm_min=rapid)
            yield moves[0] + " S0"   # the G0 to the path's start, valve closed
            yield from moves[1:]
    yield "M5"


def save_gcode(motion, path: str | os.PathLike, job=None) -> None:
    """Write :func:`gcode_lines` to ``path`` atomically (``icefab plan --gcode``)."""
    from icefab.atomic import atomic_path

    with atomic_path(path, suffix=".gcode") as tmp, open(tmp, "w", encoding="utf-8") as fh:
        for line in gcode_lines(motion, job):
            fh.write(line + "\n")
