"""Programs for other machines: G-code for a gantry cell (thesis 7: "many three-axis CNC
machines use positioning data coupled with feedrates", and MTTS output converts to it).

Convention: **Marlin 2.x with its cutter (laser/spindle) output driving the valve**
(``LASER_FEATURE``, ``CUTTER_POWER_UNIT`` PWM255; ``LASER_POWER_INLINE`` too before
Marlin 2.0.9.5, which removed it -- a build that defines it stops with an ``#error``, as
``M3 I`` turns inline mode on). Marlin applies inline power per planner block, so the
valve's duty changes exactly with the moves, the way the C40's trigger keeps the valve
controller in step with the robot (thesis 2.3.1).

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
  part (the trajectories' base-frame samples), so the tool change applies no offset: the
  machine's tool offsets (``HOTEND_OFFSET``) must be 0, or Marlin shifts every move after a
  ``T1`` by the scaffold nozzle's offset once more. The header says so, and that the
  program does not home (``G28`` first: X, Y, Z are machine positions).
* Travel and measurement paths: ``G0`` moves, valve closed (``S0``). Nothing triggers the
  laser on a measurement path: :func:`save_gcode`'s findings say what they cost
  (:func:`measure_finding`; ``feedback.enabled = false`` plans none).
* Deposition paths: ``G0`` to the first sample, then one ``G1 X Y F S`` per time step
  (:func:`icefab.motion.gcode_moves`): ``F`` the step's length over ``dt`` (mm/min), so
  each move lasts one time step (thesis 4.3), and ``S`` the valve's power over that step,
  0..255 (:func:`path_power`): the path's PWM valve program (:func:`icefab.flow.plan_valves`
  with ``flow.mode = "pwm"``, thesis 6.1: flow by pulse width at ``flow.pwm_frequency_hz``)
  per step, made playable. Set the machine's cutter PWM frequency
  (``SPINDLE_LASER_FREQUENCY``) to ``flow.pwm_frequency_hz``. A step at rest is a dwell
  ``G4 P<ms>`` (valve closed).
* What Marlin does with ``S``: it opens the valve for ``S / 255`` of *every* PWM period
  the move lasts (``dt / period`` of them: 2 at 16 ms and 125 Hz), not for the valve
  program's pulses. So ``S`` is 0 or at least ``S_min = ceil(255 x flow.min_pulse_ms /
  period)`` (16 at 0.5 ms and 8 ms: 0.502 ms a period), never 1..S_min - 1, which would ask
  the valve for openings shorter than it makes (S8 is 0.25 ms). Where a path's flow asks
  for less than ``S_min`` per move (slow boundaries), its moves alternate S0 and
  ``S >= S_min`` with the difference carried along the path (:func:`step_power`), so the
  volume laid up to any move follows the program's within about half a shortest move
  (``(S_min + 1) / 2 / 255 x dt`` of opening at most; 0.50 ms, one shortest pulse, at the
  defaults). What is lost there: the flow's placement finer than one move -- each open
  move lays at least ``dt / period`` shortest pulses; the findings (:func:`save_gcode`)
  say on which paths, how far apart their open moves lie and the volume laid.
* End: ``G0 Z`` :data:`END_LIFT_MM` above the last layer's top (at most ``cell.stroke_mm``),
  valve closed, then ``M5`` (valve off). The file ended at the last path's end with the
  nozzle on the last bead, where the machine left it until someone moved it (``icefab
  build``'s stop lifts the tool as far, ``icefab.linkedcell.SAFE_LIFT_MM``).

**What the machine's Marlin must be built with** for every move to last its one step
(``dt`` = ``motion.dt_s``, 16 ms by default): ``DEFAULT_MINSEGMENTTIME`` at most ``dt``
in microseconds (stock 20 000: Marlin stretches shorter moves when its buffer runs low,
and the valve's duty with them), ``MIN_STEPS_PER_SEGMENT`` 1 (stock 6: a move of fewer
steps, 0.075 mm at 80 steps/mm, is folded into the next at that move's F, and a path's
slowing steps lose their time), ``SLOWDOWN`` off, ``LASER_POWER_TRAP`` off (the stock
setting: on, Marlin scales each block's power by its speed over the block's acceleration
and deceleration, while ``S`` already holds the step's duty at its own speed, so the
valve would lay less on every accelerating or slowing step), and a planner buffer
(``BLOCK_BUFFER_SIZE``) and serial link that stream 1 / dt moves a second. The file's
header says so too.
"""

from __future__ import annotations

import os

import numpy as np

__all__ = ["save_gcode", "measure_finding", "step_duty", "shortest_power", "min_power",
           "step_power", "path_power", "power_finding", "gcode_lines", "check_gcode_robot"]

#: Marlin's PWM255 power scale: S0 closed .. S255 open all period
S_MAX = 255

TOOL_NUMBER = {"part": 0, "scaffold": 1}

#: How far the program's last move lifts the nozzle above the last layer's top, mm (capped
#: at ``cell.stroke_mm``): as far as a stopped build lifts it (``linkedcell.SAFE_LIFT_MM``).
END_LIFT_MM = 20.0


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


def shortest_power(period_s: float, min_pulse_ms: float) -> float:
    """S units (of 255, not rounded) of the valve's shortest opening ``min_pulse_ms`` (ms) in
    a PWM period of ``period_s`` (s): ``255 x min_pulse / period`` (15.94 for 0.5 ms at
    125 Hz). At most 255: the PWM frequency is at most ``1 / min_pulse_ms``
    (:func:`icefab.flow.check_flow_settings`)."""
    return min(S_MAX * min_pulse_ms * 1e-3 / period_s, float(S_MAX))


def min_power(period_s: float, min_pulse_ms: float) -> int:
    """The smallest S (of 255) that opens the valve for at least ``min_pulse_ms`` (ms) in a
    PWM period of ``period_s`` (s): Marlin opens it ``S / 255 x period_s`` a period, so
    ``ceil(255 x min_pulse / period)`` (16 for 0.5 ms at 125 Hz: 0.502 ms; 15 gives
    0.471 ms, under the valve's shortest opening)."""
    # 1e-9: a ratio whole in exact arithmetic may come out a hair above it in floats
    return int(np.ceil(shortest_power(period_s, min_pulse_ms) - 1e-9))


def step_power(want_s: np.ndarray, moving: np.ndarray, shortest_s: float) -> np.ndarray:
    """(n,) int64 Marlin power S per move, each 0 or in ``[ceil(shortest_s), 255]``, from
    the power ``want_s`` (n,) float64 asked per move in S units (255 x the step's duty,
    :func:`step_duty`; ``shortest_s``: the valve's shortest opening in S units,
    :func:`shortest_power`), by first-order error diffusion (sigma-delta) along the path,
    as :func:`icefab.flow._pwm_widths_us` lays widths under the shortest pulse and
    eq. 6.6 counts FM pulses: what a move is asked plus what the moves before missed (the
    carry, S units) gives S0 under half the shortest opening, ``S_min = ceil(shortest_s)``
    under ``S_min``, else its nearest integer, at most 255. A move that does not move
    (``moving`` False: Marlin dwells there with the valve closed,
    :func:`icefab.motion.gcode_moves`) or asks for nothing gets S0 and passes its ask on:
    the valve never opens where the program has no flow (a tour's travel), and the flow
    asked over a dwell is laid by the moves after it.

    The threshold is half the exact shortest opening, not ``S_min / 2``: at 16 ms moves
    and 8 ms periods a path the program gives one shortest pulse asks 7.97, and ``S_min``'s
    ceiling made ``S_min / 2`` 8.0, which dropped every such path. So at every move the
    power laid so far is within ``[-(S_min - shortest_s / 2), shortest_s / 2]`` of the power
    asked, inside ``+-(S_min + 1) / 2`` (S units, the integer S steps' rounding included;
    times ``dt / 255`` s of opening: -0.504..+0.500 ms at 16 ms, 125 Hz and 0.5 ms, one
    shortest pulse), plus what dwells asked and the moves after them have not laid yet
    (they fall behind only above duty 1). Sequential (the carry), so compiled."""
    from icefab._pulses import sigma_delta_power

    want = np.ascontiguousarray(want_s, dtype=np.float64)
    ok = np.ascontiguousarray(moving, dtype=np.bool_)
    s_min = int(np.ceil(shortest_s - 1e-9))
    return sigma_delta_power(want, ok, float(shortest_s), s_min, S_MAX)


def _open_gap_mm(trajectory, power: np.ndarray) -> float:
    """The longest stretch of path, mm, with the valve closed between two moves that open it
    (0 for fewer than two), within one span of a tour's valve (over its travel the valve is
    off anyway)."""
    moved = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(trajectory.xy, axis=0).T))])
    k = np.flatnonzero(power > 0)
    if len(k) < 2:
        return 0.0
    gaps = moved[k[1:]] - moved[k[:-1] + 1]
    spans = trajectory.on_spans
    if spans is not None and len(spans):
        mid = (k + 0.5) * float(trajectory.dt)
        span = np.searchsorted(np.asarray(spans)[:, 0], mid, side="right")
        gaps = gaps[span[1:] == span[:-1]]
    return float(gaps.max()) if len(gaps) else 0.0


def path_power(trajectory, program, material: str, job) -> tuple[np.ndarray, list[str]]:
    """Marlin's power per time step of a deposition ``trajectory`` under its PWM valve
    ``program`` (``job`` in PWM mode, :func:`gcode_job`) and the findings where the G-code
    cannot play the program's flow move by move.

    Returns ``(S (n - 1,) int64, findings)``: S from :func:`step_duty` over the PWM period,
    made 0 or at least :func:`min_power` by :func:`step_power`; findings, the program's own
    (``program.warnings``, the valve's limits as ``icefab valves`` reports them) and
    :func:`power_finding`'s."""
    fl = job.flow
    period = 1.0 / fl.pwm_frequency_hz
    want = S_MAX * step_duty(trajectory, program, period)
    moving = np.hypot(*np.diff(trajectory.xy, axis=0).T) > 0.0
    power = step_power(want, moving, shortest_power(period, fl.min_pulse_ms))
    found = power_finding(trajectory, program, want, moving, power, material, job)
    return power, list(program.warnings) + ([found] if found else [])


def power_finding(trajectory, program, want_s: np.ndarray, moving: np.ndarray,
                  power: np.ndarray, material: str, job) -> str:
    """The finding ('' for none) where the G-code's ``power`` (n - 1,) S per step cannot play
    the PWM valve ``program``'s flow move by move (:func:`path_power`): the moves that ask
    (``want_s``, S units) for less than the shortest opening and how far apart the open
    moves then lie, steps at rest (``moving`` False) that asked for flow, and the volume the
    G-code lays against the program's, mm^3 (on-time x the calibration's flow fully open at
    the PWM frequency, as :func:`icefab.flow._pwm` scales pulse widths) -- also alone when
    it lies beyond :func:`step_power`'s bound."""
    from icefab import flow

    fl = job.flow
    period = 1.0 / fl.pwm_frequency_hz
    dt = float(trajectory.dt)
    s_min = min_power(period, fl.min_pulse_ms)
    asks = want_s > 1e-6
    low = int(np.count_nonzero(asks & moving
                               & (want_s < shortest_power(period, fl.min_pulse_ms) - 1e-6)))
    resting = int(np.count_nonzero(asks & ~moving))
    # S units x dt / 255 is seconds open; the program's pulses (whole us) are its on-time
    asked_s = sum(float(p.widths_us.astype(np.float64).sum()) * 1e-6
                  for p in flow.program_pieces(program) if p.widths_us is not None)
    laid_s = float(power.sum()) * dt / S_MAX
    off = abs(laid_s - asked_s) > (0.5 * (s_min + 1) + 1e-6) * dt / S_MAX
    if not (low or resting or off):
        return ""
    cal = flow.calibration_for(material, job)
    open_mm3_s = float(cal.flow(np.array([fl.pwm_frequency_hz]))[0]) / fl.pwm_frequency_hz \
        / (fl.calibration_pulse_ms * 1e-3)
    p = trajectory.path
    where = f"layer {p.layer} {p.material} {p.role} path" if p is not None else "trajectory"
    parts = []
    if low:
        parts.append(f"{low} of {int(np.count_nonzero(asks & moving))} moves ask the valve "
                     f"for less than flow.min_pulse_ms = {fl.min_pulse_ms:g} ms a "
                     f"{period * 1e3:g} ms PWM period (under S{s_min}): laid as S0 and "
                     f"S{s_min}+ moves, open moves up to {_open_gap_mm(trajectory, power):.2f}"
                     f" mm apart (path width {getattr(p, 'width', float('nan')):.3g} mm)")
    if resting:
        parts.append(f"{resting} step{'s' if resting != 1 else ''} at rest ask"
                     f"{'' if resting != 1 else 's'} for flow (G4, valve closed): laid by the "
                     "moves after")
    return (f"{where}: G-code at {dt * 1e3:g} ms a move: " + "; ".join(parts)
            + ("; " if parts else "") + "against the valve program, "
            + flow.volume_error(laid_s * open_mm3_s, asked_s * open_mm3_s))


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


def gcode_lines(motion, job=None, findings: list | None = None):
    """The G-code of a BuildMotion planned for a gantry, line by line (see the module
    docstring; :func:`check_gcode_robot`). findings: a list to which each deposition path's
    findings (:func:`path_power`) are appended as ``(layer index, text)`` pairs, for
    :func:`icefab.flow.summarise_findings`."""
    from icefab import flow
    from icefab.motion import gcode_moves
    from icefab.stages import layer_height

    check_gcode_robot(motion.robot, "the trajectories")
    job = job if job is not None else motion.job
    pwm = gcode_job(job, "the trajectories")
    yield (f"; icefab G-code for a gantry, Marlin 2.x (cutter PWM drives the valve, inline "
           f"power 0-255, PWM at {pwm.flow.pwm_frequency_hz:g} Hz)")
    yield (f"; dt {job.motion.dt_s:g} s, {motion.duration:.1f} s of motion; "
           "X, Y: carriage (base frame), mm; F: mm/min; T0 part, T1 scaffold")
    yield (f"; every move lasts dt: needs DEFAULT_MINSEGMENTTIME <= "
           f"{job.motion.dt_s * 1e6:.0f} us, MIN_STEPS_PER_SEGMENT 1, SLOWDOWN off")
    yield ("; S is each step's valve duty at its own speed: LASER_POWER_TRAP off (it scales "
           "power by speed again)")
    # what the program assumes of the machine and does not do itself (a gantry hunt's)
    yield ("; home the machine first (G28): X, Y, Z are machine positions, Z0 the nozzle on "
           "the platform; the program does not home")
    yield ("; T0/T1 route the cutter PWM to that nozzle's valve with no tool offset "
           "(HOTEND_OFFSET 0): X, Y already put that nozzle on the part")
    period = 1.0 / pwm.flow.pwm_frequency_hz
    yield (f"; S: 0 (closed) or S{min_power(period, pwm.flow.min_pulse_ms)}..255, the valve "
           f"open S/255 of each {period * 1e3:g} ms period, at least its "
           f"{pwm.flow.min_pulse_ms:g} ms shortest opening")
    rapid = 60.0 * job.motion.travel_speed_mm_s
    yield "G21"
    yield "G90"
    yield "M3 I S0"
    tool = None
    top = None
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
            # the layer's own thickness (adaptive layers) and the path's number in errors,
            # as icefab valves plans it (the default thickness laid a thick layer short)
            prog = flow.plan_path_valves(lm.index, i, tr, p.material, pwm,
                                         layer_height(lm.thickness, job),
                                         flow.calibration_for(p.material, pwm))
            s, found = path_power(tr, prog, p.material, pwm)
            if findings is not None:
                findings.extend((lm.index, text) for text in found)
            moves = gcode_moves(tr, power=s, dwell=True, rapid_mm_min=rapid)
            yield moves[0] + " S0"   # the G0 to the path's start, valve closed
            yield from moves[1:]
    if top is not None:
        # clear of the part: the nozzle stood on the last bead when the program ended
        lift = max(min(top + END_LIFT_MM, float(job.cell.stroke_mm)), top)
        yield f"G0 Z{lift:.4f} F{rapid:.1f} S0"
    yield "M5"


def save_gcode(motion, path: str | os.PathLike, job=None) -> list[str]:
    """Write :func:`gcode_lines` to ``path`` atomically (``icefab plan --gcode``, ``icefab
    export gcode``). Returns the paths' findings condensed one line per kind
    (:func:`icefab.flow.summarise_findings`; empty when the G-code plays every path's valve
    program move by move)."""
    from icefab.atomic import atomic_path
    from icefab.flow import summarise_findings

    found: list[tuple[int, str]] = []
    with atomic_path(path, suffix=".gcode") as tmp, open(tmp, "w", encoding="utf-8") as fh:
        for line in gcode_lines(motion, job, found):
            fh.write(line + "\n")
    return summarise_findings(found) + ([m] if (m := measure_finding(motion)) else [])


def measure_finding(motion) -> str:
    """The finding ('' for none) that the G-code runs the laser's measurement paths
    (``feedback.enabled``): it moves the carriage along them, valve closed, but triggers and
    reads no laser and runs no SMF, so their time is spent for nothing. A gantry job left at
    the default (feedback on) got minutes of such moves unsaid."""
    trs = [(lm.index, t) for lm in motion.layers for t in lm.trajectories
           if t.path is not None and t.path.role == "measure" and len(t.xy)]
    if not trs:
        return ""
    spent = sum(float(t.duration) for _, t in trs)
    n, k = len(trs), len({layer for layer, _ in trs})
    return (f"{n} measurement path{'s' if n != 1 else ''} in {k} layer{'s' if k != 1 else ''}"
            f" ({spent:.1f} s of the {float(motion.duration):.1f} s of motion): the G-code "
            "moves the laser over them but neither triggers nor reads it (no SMF); plan with "
            "feedback.enabled = false to leave them out")
