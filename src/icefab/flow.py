"""Variable-flow valve control (VFVC): trajectories -> valve pulse programs.

Thesis Ch. 6 and 2.3.1. For every deposition trajectory the valve must deliver the volume
per millimetre ``w * dh_d`` whatever the (variable, MTTS-shaped) speed ``c``, corrected by
the surface-mapping control action ``u``:

* nominal flow ``q_nom = w * dh_d * c * layer_scale`` (eq. 6.2; ``layer_scale`` is
  ``job.flow.layer_scale``, 1 by default), corrected ``q = (u + 1) q_nom`` (eq. 6.3);
* frequency ``nu = h(q)`` by linear interpolation in the valve's calibration table
  (eq. 6.4, :func:`load_calibration`);
* cumulative pulses ``N(t) = integral of nu dt`` (eq. 6.5, trapezoidal rule on the
  trajectory's constant time step) and pulse instants where ``N`` crosses ``0.5, 1.5, ...``
  (eq. 6.6: each pulse sits in the middle of its unit of volume, so the pulse count differs
  from the integral of the frequency by at most half a pulse);
* instants as ``uint16`` ticks of ``job.flow.tick_s`` (2 ms) from the start of the piece
  (thesis 2.3.1); a program whose piece would last longer than :func:`piece_max_s`
  (131.071 s: ``max_piece_s``, the firmware's 131.072 s, within 65 535.5 ticks of 2 ms, so
  that every pulse's tick, rounded, fits a uint16) or hold more than ``max_pulses``
  (16 384) pulses is split automatically into pieces that start on trajectory samples (the
  trajectory is split there too).

Limits (thesis 6.1), all recorded in :attr:`ValveProgram.warnings` (one text per limit and
path, naming the setting; :func:`summarise_findings` condenses them per kind):

* FM: a flow outside the calibration table (zero flow is 0 Hz, whatever the table's first
  row) or a frequency above ``min(max_frequency_hz, 1 / calibration_pulse_ms)`` raises
  :class:`FlowError` naming the path, the flow and the table's range under
  ``job.flow.out_of_range = "error"``; under ``"clamp"`` it is clamped and the finding
  states the volume delivered against the volume commanded. Pulses sharing a tick
  (frequencies above ``1 / tick_s``) are counted; fewer drops than ``min_drops_per_mm``
  where the nozzle moves are reported. Neither is changed.
* PWM keeps the frequency at ``pwm_frequency_hz`` (at most ``min(max_frequency_hz,
  1 / tick_s, 1 / min_pulse_ms)`` and inside the table: ConfigError otherwise) and varies
  the pulse width (volume per pulse proportional to the width, calibrated by the table at
  ``calibration_pulse_ms``); widths below ``min_pulse_ms / 2`` are dropped, below
  ``min_pulse_ms`` raised to it, above the period -- or above the width giving the
  table's highest flow, the most the table supports (:func:`pwm_max_width_ms`) -- cut to
  it (or FlowError under ``"error"``); the counts and the resulting volume error are
  reported.
* Both: where the nominal flow fits the valve (:func:`valve_flow_range`) but SMF's control
  action asks for more (or less) than it gives, the flow is held at the range's end
  whatever ``out_of_range`` says -- the actuator's saturation (thesis 5.2.2) -- and the
  finding states the volume delivered against the volume asked. The limits above are the
  plan's; this one is the controller's.

Trajectories must be sampled as documented: ``dt > 0`` and ``duration = (n - 1) dt``
(:func:`check_trajectory`, FlowError naming the path otherwise).

Files (:func:`write_valve_program` / :func:`read_valve_program`), binary form,
little-endian throughout::

    offset size  field
    0      4     magic b"ICEV"
    4      2     uint16 format version (1)
    6      1     uint8 mode: 0 = FM, 1 = PWM
    7      1     uint8 reserved (0)
    8      4     uint32 tick length, microseconds (2000)
    12     4     uint32 number of pieces P
    then for each of the P pieces:
           4     uint32 number of pulses n
           4     uint32 piece duration, microseconds
           2n    uint16 ticks (pulse instants from the piece start)
           2n    uint16 pulse widths, microseconds (PWM only)

Layer files (:func:`write_valve_layer` / :func:`read_valve_layer`): every program of one
layer in build order, in one file a controller link can stream from start to end (the host
uploads each record's program bytes with PROG_BEGIN / PROG_DATA, firmware/PROTOCOL.md,
section 5). Binary form, little-endian::

    offset size  field
    0      4     magic b"ICVL"
    4      2     uint16 format version (1)
    6      2     uint16 reserved (0)
    8      4     uint32 layer index
    12     4     uint32 number of programs N
    then for each of the N programs, in the order the paths are built:
           4     uint32 path number (the trajectory's index in its layer of trajectories.npz)
           1     uint8 valve: 0 = part, 1 = scaffold (PROTOCOL.md's valve numbers)
           3     reserved (0)
           4     uint32 length L of the program, bytes
           L     the program exactly as the binary form above (b"ICEV" ...)

Text form of a layer: ``icefab-valve-layer 1``, ``layer K``, ``programs N``, then per
program a line ``program PATH valve part|scaffold`` followed by the program's text form.

Text form (one item per line, ``#`` comments)::

    icefab-valve-program 1
    mode fm
    tick_s 0.002
    pieces 1
    piece 0 duration_s 12.345 pulses 3
    17
    18 500        <- PWM: tick and width in microseconds
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterable, Iterator, Sequence, Union

import numpy as np

from icefab import feedback
from icefab.atomic import write_atomic
from icefab.errors import ConfigError, FlowError, StackFileError
from icefab.findings import numbers_hidden
from icefab.inputs import check_input, read_input_text
from icefab.frames import to_part_frame
from icefab.motion import limit_ratio, speedup_cap
from icefab.parallel import parallel_map
from icefab.stages import layer_height
from icefab.core import (MATERIALS, HeightMap, Trajectory, ValveProgram, checked_widths,
                         offsets, spans_fine, spans_problem)

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job
    from icefab.core import LayerMotion

log = logging.getLogger(__name__)

DATA_DIR = Path(__file__).resolve().parent / "data"
LAYER_MAGIC = b"ICVL"
LAYER_TEXT_MAGIC = "icefab-valve-layer"
#: Valve number of each material on the controller (firmware/PROTOCOL.md, icefab.cell.valve).
VALVE_NUMBER = {"part": 0, "scaffold": 1}
MAGIC = b"ICEV"
VERSION = 1
TEXT_MAGIC = "icefab-valve-program"


# =========================================================================== calibration


@dataclass(frozen=True, eq=False)
class Calibration:
    """A valve frequency-flow table nu = h(Q) (thesis 6.1, Fig. 6-1).

    frequency_hz: (m,) float64, strictly increasing, Hz.
    flow_mm3_s: (m,) float64, strictly increasing, mm^3/s.
    source: file it was read from (used in messages).
    """

    frequency_hz: np.ndarray
    flow_mm3_s: np.ndarray
    source: str = ""

    @property
    def max_flow(self) -> float:
        return float(self.flow_mm3_s[-1])

    @property
    def min_flow(self) -> float:
        return float(self.flow_mm3_s[0])

    def frequency(self, flow_mm3_s: np.ndarray) -> np.ndarray:
        """nu = h(Q): (n,) Hz by linear interpolation; values outside the table are clamped
        to its ends (callers check the range first)."""
        return np.interp(flow_mm3_s, self.flow_mm3_s, self.frequency_hz)

    def flow(self, frequency_hz: np.ndarray) -> np.ndarray:
        """Q = h^-1(nu): (n,) mm^3/s by linear interpolation (clamped at the table ends)."""
        return np.interp(frequency_hz, self.frequency_hz, self.flow_mm3_s)


def load_calibration(path: str | os.PathLike) -> Calibration:
    """Read a calibration CSV: ``frequency_hz,flow_mm3_s`` per line.

    An optional header line (any text in the first column) and ``#`` comments are allowed.
    Both columns must be finite and strictly increasing, with at least two rows. Raises
    FlowError naming the file and line.
    """
    path = Path(path)
    text = read_input_text(path, "calibration", FlowError, "calibration table")
    freq: list[float] = []
    flow: list[float] = []
    lines: list[int] = []
    header_seen = False
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        cells = [c.strip() for c in line.replace(";", ",").split(",")]
        if len(cells) != 2:
            raise FlowError(f"{path}:{n}: expected 2 columns (frequency_hz, flow_mm3_s), got "
                            f"{len(cells)}: {raw.strip()!r}")
        try:
            f, q = float(cells[0]), float(cells[1])
        except ValueError:
            if not freq and not header_seen:
                header_seen = True
                continue
            raise FlowError(f"{path}:{n}: expected two numbers, got {raw.strip()!r}") from None
        if not (np.isfinite(f) and np.isfinite(q)):
            raise FlowError(f"{path}:{n}: values must be finite, got {raw.strip()!r}")
        if f < 0 or q < 0:
            raise FlowError(f"{path}:{n}: frequency and flow must be >= 0, got "
                            f"{raw.strip()!r}")
        if freq and (f <= freq[-1] or q <= flow[-1]):
            col = "frequency" if f <= freq[-1] else "flow"
            raise FlowError(f"{path}:{n}: {col} must increase strictly from line {lines[-1]} "
                            f"({freq[-1]:g} Hz, {flow[-1]:g} mm^3/s) to "
                            f"({f:g} Hz, {q:g} mm^3/s)")
        freq.append(f)
        flow.append(q)
        lines.append(n)
    if len(freq) < 2:
        raise FlowError(f"{path}: calibration table needs at least 2 rows, found {len(freq)}")
    return Calibration(np.array(freq), np.array(flow), str(path))


@functools.lru_cache(maxsize=16)
def _cached_calibration(path: str, mtime: float) -> Calibration:
    return load_calibration(path)


def calibration_for(material: str, job: "Job") -> Calibration:
    """The calibration of a material: ``job.materials[material].calibration_file`` or the
    built-in table ``icefab/data/calibration_<material>.csv``."""
    settings = job.materials[material]
    path = Path(settings.calibration_file) if settings.calibration_file else \
        DATA_DIR / f"calibration_{material}.csv"
    what = ("calibration table" + (f" (materials.{material}.calibration_file)"
                                   if settings.calibration_file else ""))
    check_input(path, "calibration", FlowError, what)
    mtime = path.stat().st_mtime
    return _cached_calibration(str(path), mtime)


# =========================================================================== frequency


@dataclass(frozen=True, eq=False)
class SpanSignal:
    """The valve's signal over the spans a continuous tour's valve is on
    (:attr:`~icefab.core.Trajectory.on_spans`): rows ``start[k]:start[k+1]`` are span k,
    its exact start instant, the samples strictly inside it, its exact end instant.

    t: (R,) float64 s from the trajectory start; q: (R,) flow, mm^3/s; nu: (R,) frequency,
    Hz (as :class:`FrequencyPlan`'s, at the span ends from :func:`_span_ends`); start:
    (S + 1,) int64.
    """

    t: np.ndarray
    q: np.ndarray
    nu: np.ndarray
    start: np.ndarray


@dataclass(frozen=True, eq=False)
class FrequencyPlan:
    """The commanded valve signal along a trajectory, before pulses are placed.

    t: (n,) float64 sample times, s. q: (n,) corrected flow, mm^3/s (eq. 6.3).
    u: (n,) control action applied. nu: (n,) frequency, Hz (eq. 6.4), limits applied.
    clamped: number of samples whose flow or frequency was clamped.
    warnings: human-readable findings (limits reached), each naming the quantity.
    on: a continuous tour's signal over the spans its valve is on, exact at their ends
        (None: the valve follows the samples all along); the pulses are placed in it.
    """

    t: np.ndarray
    q: np.ndarray
    u: np.ndarray
    nu: np.ndarray
    clamped: int = 0
    warnings: tuple[str, ...] = ()
    on: SpanSignal | None = None


def trajectory_part_xy(trajectory: Trajectory, material: str, job: "Job") -> np.ndarray:
    """(n, 2) float64, mm: where the material's nozzle (or, with ``material = "laser"``, the
    laser spot) is, in the part (building) frame.

    Trajectory samples are end-effector positions in the robot base frame; the inverse of
    :func:`icefab.frames.to_base_frame` (``base = p + ee_origin - tool_offset``) gives the
    part point ``p = base - ee_origin + tool_offset`` under the material's nozzle
    (:func:`icefab.frames.to_part_frame`).
    Control-action surfaces are measured in the part frame, so they are sampled here.
    """
    return to_part_frame(trajectory.xy, material, job)


#: A control action (fraction, 0 = nominal) given as: nothing; one value per trajectory
#: sample ((n,) array or sequence); a surface sampled at the nozzle (HeightMap or
#: ControlAction); or a callable mapping (n, 2) part-frame points, mm, to (n,) values.
ActionLike = Union[None, np.ndarray, Sequence[float], HeightMap, feedback.ControlAction,
                   Callable[[np.ndarray], np.ndarray]]


def _action_values(action: ActionLike, trajectory: Trajectory, material: str,
                   job: "Job") -> np.ndarray:
    n = len(trajectory.xy)
    if action is None:
        return np.zeros(n)
    if isinstance(action, np.ndarray) or isinstance(action, (list, tuple)):
        u = np.asarray(action, dtype=np.float64)
        if u.shape != (n,):
            raise FlowError(f"control action: expected shape ({n},) (one value per trajectory "
                            f"sample), got {u.shape}")
    else:
        xy = trajectory_part_xy(trajectory, material, job)
        if isinstance(action, (HeightMap, feedback.ControlAction)):
            u = feedback.action_along(action, xy)
        elif callable(action):
            u = np.asarray(action(xy), dtype=np.float64).reshape(-1)
            if u.shape != (n,):
                raise FlowError(f"control action callable returned shape {u.shape}, "
                                f"expected ({n},)")
        else:
            raise FlowError(f"control action of type {type(action).__name__}: expected an "
                            "array, a HeightMap, a ControlAction or a callable")
    if not np.all(np.isfinite(u)):
        raise FlowError("control action: contains NaN or infinite values")
    return u


def trajectory_width(trajectory: Trajectory, material: str, job: "Job") -> float:
    """Deposition width of a trajectory, mm: its path's own, else the material's by role
    (fill width for fill, path width otherwise; a trajectory file's stand-in paths and a
    bare array carry none)."""
    path = trajectory.path
    if path is not None and path.width > 0:
        return float(path.width)
    return material_width(material, path.role if path is not None else "", job)


def material_width(material: str, role: str, job: "Job") -> float:
    """The width a deposition path of ``role`` given none (0) is laid at, mm: the
    material's fill width for fill, its path width otherwise (the valve programs and the
    simulator alike)."""
    settings = job.materials[material]
    return float(settings.fill_width_mm if role == "fill" else settings.path_width_mm)


def sample_widths(trajectory: Trajectory, material: str, job: "Job") -> np.ndarray:
    """(n,) float64 mm: the deposition width at every sample: a variable-width
    trajectory's own (:attr:`~icefab.core.Trajectory.widths`), else
    :func:`trajectory_width` all along. FlowError naming the path when the widths are not
    one finite number >= 0 per sample."""
    n = len(trajectory.xy)
    if trajectory.widths is None:
        return np.full(n, trajectory_width(trajectory, material, job))
    w = np.asarray(trajectory.widths)
    if w.shape != (n,) or w.dtype.kind not in "fiu" or not np.all(np.isfinite(w)) \
            or np.any(w < 0):
        raise FlowError(f"{_where(trajectory)}: trajectory widths must be ({n},) finite "
                        f"numbers >= 0 mm, one per sample; got shape {w.shape}")
    return w.astype(np.float64, copy=False)


def variable_widths(trajectories: "Sequence[Trajectory]") -> tuple[np.ndarray, np.ndarray]:
    """The widths of many variable-width trajectories, checked all at once
    (:func:`icefab.core.checked_widths`): ``(ok (m,) bool`` - one finite number >= 0 per
    sample -, ``widths`` of the ok ones concatenated, float64 mm``)``.
    :func:`sample_widths` names a bad one."""
    return checked_widths([t.widths for t in trajectories], [len(t.xy) for t in trajectories])


def _pwm_limit_hz(job: "Job") -> float:
    """Highest usable PWM frequency: ``min(max_frequency_hz, 1 / tick_s, 1 / min_pulse_ms)``
    (the valve's limit, one pulse per microcontroller tick, a shortest pulse per period)."""
    fl = job.flow
    return min(fl.max_frequency_hz, 1.0 / fl.tick_s, 1000.0 / fl.min_pulse_ms)


def check_flow_settings(job: "Job", calibration: Calibration | None = None) -> None:
    """Cross-checks of ``job.flow`` made where the settings are used (thesis 6.1, 2.3.1).

    * ``calibration_pulse_ms`` >= ``min_pulse_ms`` (the table was measured with pulses the
      valve can make);
    * PWM: ``pwm_frequency_hz`` <= ``min(max_frequency_hz, 1 / tick_s, 1 / min_pulse_ms)``
      (above ``1 / tick_s`` consecutive pulses would share a 2 ms tick) and, when a
      ``calibration`` is given, inside the table's frequencies with a positive flow (the
      flow per pulse at the PWM frequency is read from it).

    Raises ConfigError (FlowError for calibration_pulse_ms) naming the setting, its value and the limit.
    """
    fl = job.flow
    if fl.calibration_pulse_ms < fl.min_pulse_ms:
        raise FlowError(f"flow.calibration_pulse_ms = {fl.calibration_pulse_ms:g}: below the "
                        f"valve's shortest opening flow.min_pulse_ms = {fl.min_pulse_ms:g}")
    if fl.mode != "pwm":
        return
    f = fl.pwm_frequency_hz
    limit = _pwm_limit_hz(job)
    if f > limit * (1 + 1e-12):
        raise ConfigError(
            f"flow.pwm_frequency_hz = {f:g}: above the highest usable PWM frequency {limit:g} Hz "
            f"= min(flow.max_frequency_hz = {fl.max_frequency_hz:g}, 1 / flow.tick_s = "
            f"{1.0 / fl.tick_s:g} (one pulse per tick), 1 / flow.min_pulse_ms = "
            f"{1000.0 / fl.min_pulse_ms:g})")
    if calibration is not None:
        lo, hi = float(calibration.frequency_hz[0]), float(calibration.frequency_hz[-1])
        if not lo <= f <= hi or float(calibration.flow(np.array([f]))[0]) <= 0:
            raise ConfigError(f"flow.pwm_frequency_hz = {f:g}: outside the calibration table "
                              f"{calibration.source} (frequencies {lo:g}..{hi:g} Hz with a "
                              "positive flow), which gives the flow per pulse in PWM mode")


def check_trajectory(trajectory: Trajectory) -> None:
    """The sampling contract a valve program relies on: ``xy (n, 2)``, ``n >= 1``, ``dt > 0``
    finite, and ``duration == (n - 1) * dt`` (within 1 us): pulse instants are computed on
    the samples' time axis and the program lasts ``duration``. Raises FlowError naming the
    path."""
    xy = np.asarray(trajectory.xy)
    where = _where(trajectory)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 1:
        raise FlowError(f"{where}: trajectory xy has shape {xy.shape}, expected (n, 2) with "
                        "n >= 1")
    dt = float(trajectory.dt)
    if not (np.isfinite(dt) and dt > 0):
        raise FlowError(f"{where}: trajectory dt = {trajectory.dt!r} s: must be finite and > 0")
    duration = float(trajectory.duration)
    expected = (len(xy) - 1) * dt
    if not np.isfinite(duration) or abs(duration - expected) > 1e-6 + 1e-9 * expected:
        raise FlowError(f"{where}: trajectory duration = {duration!r} s disagrees with its "
                        f"{len(xy)} samples at dt = {dt:g} s ((n - 1) dt = {expected:.6g} s); "
                        "a constant-dt trajectory lasts (n - 1) dt")


def out_of_range_hint(dh: float, job: "Job", clamp_words: str, above: bool = True) -> str:
    """What to change when a path's flow is beyond its valve, ending in the ``flow.
    out_of_range = 'clamp'`` alternative (``clamp_words``: what clamping does).

    The speed sets the flow (q = w dh c, eq. 6.2), and with adaptive layers
    (``slicing.cusp_height_mm`` > 0) so does the layer's own thickness ``dh`` mm: a flow
    ``above`` the valve's then also names the thickest layers' cap,
    ``slicing.max_layer_thickness_mm`` (the demo's 0.5 mm adaptive layers asked 955 Hz of
    a 500 Hz valve, and the hint named only the speed)."""
    clamp = f"set flow.out_of_range = 'clamp' to {clamp_words}"
    sl = job.slicing
    if above and sl.cusp_height_mm > 0:
        cap = sl.max_layer_thickness_mm or sl.layer_thickness_mm
        return (f"this adaptive layer is {dh:.3g} mm thick: lower the speed or "
                f"slicing.max_layer_thickness_mm (now {cap:g} mm), or {clamp}")
    return f"lower the speed or {clamp}"


def valve_frequency(trajectory: Trajectory, material: str, job: "Job", *,
                    action: ActionLike = None, layer_thickness: float | None = None,
                    calibration: Calibration | None = None) -> FrequencyPlan:
    """Corrected flow and valve frequency at every trajectory sample (eqs. 6.2-6.4).

    trajectory: sampled at constant dt; ``speed (n,)`` mm/s is the path speed c;
        ``duration`` must be ``(n - 1) * dt`` (:func:`check_trajectory`).
    material: "part" or "scaffold" (selects width, calibration and nozzle frame).
    action: control action u: None (0), (n,) array, HeightMap / ControlAction (sampled
        in the part frame, 0 outside), or a callable ``u(xy_part (n, 2)) -> (n,)``.
    layer_thickness: dh_d in mm (default ``job.slicing.layer_thickness_mm``).
    calibration: table to use (default :func:`calibration_for`).

    FM: a flow outside the calibration table (zero flow excepted: 0 Hz) or a frequency
    above ``min(max_frequency_hz, 1 / calibration_pulse_ms)`` raises FlowError under
    ``flow.out_of_range = "error"``; under ``"clamp"`` it is clamped and the finding says
    how much volume that costs (delivered vs commanded). Where only the control action
    takes the flow out of the valve's range (:func:`valve_flow_range`), it is held at the
    range's end whatever ``out_of_range`` says (:func:`_saturated`, thesis 5.2.2) and a
    finding states the volume given of the volume asked. PWM: ``nu`` is the FM-equivalent
    frequency h(q), for information; the PWM limits are applied per pulse by
    :func:`plan_valves`.
    """
    fl = job.flow
    check_trajectory(trajectory)
    check_flow_settings(job)
    n = len(trajectory.xy)
    speed = np.asarray(trajectory.speed, dtype=np.float64)
    if speed.shape != (n,):
        raise FlowError(f"trajectory speed: expected shape ({n},), got {speed.shape}")
    if not np.all(np.isfinite(speed)) or np.any(speed < 0):
        raise FlowError("trajectory speed: must be finite and >= 0")
    dh = float(job.slicing.layer_thickness_mm if layer_thickness is None else layer_thickness)
    if not (np.isfinite(dh) and dh > 0):
        raise FlowError(f"layer thickness = {dh!r} mm: must be > 0")
    cal = calibration or calibration_for(material, job)
    u = _action_values(action, trajectory, material, job)
    w = sample_widths(trajectory, material, job)   # eq. 6.2 with a width per sample
    q_nom = (w * dh * fl.layer_scale) * speed
    q = np.clip((1.0 + u), 0.0, None) * q_nom  # eq. 6.2-6.3
    t = np.arange(n) * float(trajectory.dt)
    warnings: list[str] = []
    clamped = np.zeros(n, dtype=bool)
    where = _where(trajectory)
    q_lo, q_hi = valve_flow_range(cal, job)
    saturated = _saturated(q, q_nom, q_lo, q_hi)
    if np.any(saturated):
        asked = q.copy()
        q[saturated] = np.clip(q[saturated], q_lo, q_hi)
        worst = float(asked[saturated].max() if np.any(asked[saturated] > q_hi)
                      else asked[saturated].min())
        warnings.append(f"{where}: SMF's correction saturated at the valve's "
                        f"[{q_lo:.4g}, {q_hi:.4g}] mm^3/s (thesis 5.2.2; asked {worst:.4g} "
                        f"mm^3/s) at {int(np.count_nonzero(saturated))} of {n} samples, "
                        f"{volume_error(_integral(q, t), _integral(asked, t))}")
    # the flow follows the speed array (eq. 6.2), the nozzle the samples: they must agree
    travelled = float(np.linalg.norm(np.diff(np.asarray(trajectory.xy, np.float64), axis=0),
                                     axis=1).sum()) if n > 1 else 0.0
    integrated = _integral(speed, t)
    if abs(integrated - travelled) > max(SPEED_MISMATCH_MM, SPEED_MISMATCH * travelled):
        off = (f"{100.0 * (integrated / travelled - 1.0):+.1f} %" if travelled > 0 else
               f"{dh * _integral(w * speed, t):.4g} mm^3")
        warnings.append(f"{where}: the trajectory speed integrates to {integrated:.4g} mm but "
                        f"its samples travel {travelled:.4g} mm: the flow follows the speed, "
                        f"so the volume is {off} off nominal")
    flowing = q > 0  # zero flow is 0 Hz whatever the table's first row
    limits: list[str] = []

    def out_of_range(mask: np.ndarray, msg: str, above: bool = True) -> None:
        """Raise under flow.out_of_range = "error", else note the samples as clamped;
        ``above``: some flow is above the valve's (not only below)."""
        if fl.out_of_range == "error":
            raise FlowError(f"{where}: {msg}; "
                            f"{out_of_range_hint(dh, job, 'clamp and report instead', above)}")
        limits.append(msg)
        np.logical_or(clamped, mask, out=clamped)

    if fl.mode == "fm":
        hi = q > cal.max_flow
        lo = flowing & (q < cal.min_flow)
        if np.any(hi | lo):
            worst = float(q[hi].max()) if np.any(hi) else float(q[lo].min())
            out_of_range(hi | lo, f"flow {worst:.4g} mm^3/s outside the calibration table "
                         f"[{cal.min_flow:g}, {cal.max_flow:g}] mm^3/s ({cal.source}) at "
                         f"{int(np.count_nonzero(hi | lo))} of {n} samples", bool(np.any(hi)))
    nu = np.where(flowing, cal.frequency(q), 0.0)  # eq. 6.4 (clamped to the table's ends)
    if fl.mode == "fm":
        nu_max = max_valve_frequency(job)
        # a flow at the valve's top (saturated there, or nominal) is the table's flow at
        # nu_max: its frequency read back may exceed nu_max by the interpolation's
        # rounding, which is no limit reached
        over = nu > nu_max * (1.0 + 1e-9)
        if np.any(over):
            out_of_range(over, f"valve frequency {float(nu.max()):.4g} Hz above the limit "
                         f"{nu_max:g} Hz (flow.max_frequency_hz, 1 / "
                         f"flow.calibration_pulse_ms) at {int(np.count_nonzero(over))} of "
                         f"{n} samples")
        nu = np.minimum(nu, nu_max)
        if limits:
            commanded = _integral(q, t)
            delivered = _integral(np.where(nu > 0, cal.flow(nu), 0.0), t)
            warnings.append(f"{where}: {'; '.join(limits)}: clamped (flow.out_of_range = "
                            f"'clamp'), {volume_error(delivered, commanded)}")
        moving = speed > 1e-9
        drops = np.divide(nu, speed, out=np.full(n, np.inf), where=moving)
        few = moving & (drops < fl.min_drops_per_mm) & (q > 0)
        if np.any(few):
            warnings.append(f"{where}: fewer than flow.min_drops_per_mm = "
                            f"{fl.min_drops_per_mm:g} drops per mm ({float(drops[few].min()):.3g}"
                            f") at {int(np.count_nonzero(few))} samples")
    else:  # PWM: one drop per period (thesis 6.1: >= 1 drop per mm)
        moving = speed > 1e-9
        few = moving & (fl.pwm_frequency_hz < fl.min_drops_per_mm * speed)
        if np.any(few):
            warnings.append(f"{where}: flow.pwm_frequency_hz = {fl.pwm_frequency_hz:g} gives "
                            f"fewer than {fl.min_drops_per_mm:g} drops per mm at speeds up to "
                            f"{float(speed.max()):.4g} mm/s ({int(np.count_nonzero(few))} "
                            "samples)")
    for m in warnings:  # per path: callers summarise them (:func:`summarise_findings`)
        log.debug(m)
    on = None
    if trajectory.on_spans is not None:   # a tour: the valve on over its paths only
        problem = spans_problem(trajectory.on_spans, float(trajectory.duration))
        if problem:
            raise FlowError(f"{where}: {problem}")
        lay = span_layout(trajectory)
        q_nom_e, q_e = _span_ends(lay, speed, u, w,
                                  np.full(len(lay.ends),
                                          trajectory_width(trajectory, material, job)),
                                  dh, job)
        sat = _saturated(q_e, q_nom_e, q_lo, q_hi)
        q_e[sat] = np.clip(q_e[sat], q_lo, q_hi)
        nu_e = np.where(q_e > 0, cal.frequency(q_e), 0.0)
        if fl.mode == "fm":
            nu_e = np.minimum(nu_e, max_valve_frequency(job))
        on = _span_signal(lay, q, nu, q_e, nu_e)
    return FrequencyPlan(t=t, q=q, u=u, nu=nu, clamped=int(np.count_nonzero(clamped)),
                         warnings=tuple(warnings), on=on)


def _on_ends(on: SpanSignal) -> np.ndarray:
    """(S, 2) s: each span's start and end instant."""
    return np.column_stack([on.t[on.start[:-1]], on.t[on.start[1:] - 1]])


def _span_signal(lay: _SpanLayout, q: np.ndarray, nu: np.ndarray, q_ends: np.ndarray,
                 nu_ends: np.ndarray) -> SpanSignal:
    """The :class:`SpanSignal` of a layout: the samples' ``q``, ``nu`` inside the spans,
    ``q_ends``, ``nu_ends`` at their ends."""
    return SpanSignal(t=lay.t, q=lay.laid_out(q, q_ends), nu=lay.laid_out(nu, nu_ends),
                      start=lay.start)


def _kept_in_spans(times: np.ndarray, per_span: np.ndarray, ends: np.ndarray, tick: float
                   ) -> np.ndarray:
    """Pulse instants ``times``, ``per_span (S,)`` of them in each span ``ends (S, 2)`` s
    in turn, moved at most half a tick so that the controller's tick (the nearest to each,
    :func:`_split`) stays within their span: into ``[start + tick / 2, end - tick / 2]``,
    or the middle of a span shorter than a tick. Without it a pulse a hair before a switch
    could be rounded onto the travel (0.13 mm at 125 mm/s and 1 ms).

    Pulses a tick apart or more stay so: the i-th of a span's n is kept within
    ``[start + tick / 2 + i tick, end - tick / 2 - (n - 1 - i) tick]`` (a span too short
    for its pulses at one a tick: as above). Clamped to the span's end alone, the last
    two pulses of a span at the valve's highest frequency (1 / tick) shared a tick."""
    if not len(times):
        return times
    a = np.repeat(ends[:, 0], per_span)
    b = np.repeat(ends[:, 1], per_span)
    long_enough = b - a >= tick
    lo = np.where(long_enough, a + 0.5 * tick, 0.5 * (a + b))
    hi = np.where(long_enough, b - 0.5 * tick, 0.5 * (a + b))
    n = np.repeat(per_span, per_span)
    i = np.arange(len(times)) - np.repeat(offsets(per_span)[:-1], per_span)
    room = long_enough & ((n - 1) * tick <= hi - lo)
    lo = np.where(room, lo + i * tick, lo)
    hi = np.where(room, hi - (n - 1 - i) * tick, hi)
    return np.minimum(np.maximum(times, lo), hi)


#: A sample closer than this fraction of a time step to a span's end is that end itself.
SPAN_SNAP = 1e-6


@dataclass(frozen=True, eq=False)
class _SpanLayout:
    """Where the rows of :class:`SpanSignal` come from, for spans of trajectories whose
    samples are rows ``first + 0 .. n - 1`` of flat arrays (:func:`_span_layout`).

    rows: (R,) int64 the sample row each takes, -1 at the span ends; t: (R,) s from the
    trajectory start; start: (S + 1,) int64; ends: (2 S,) int64 the span ends' rows in
    R; left: (2 S,) int64 the sample row before (or at) each end and
    frac (2 S,) its place towards the next, to interpolate; inner: (2 S,) int64 the
    nearest sample strictly inside the span, -1 when none is.
    """

    rows: np.ndarray
    t: np.ndarray
    start: np.ndarray
    ends: np.ndarray
    left: np.ndarray
    frac: np.ndarray
    inner: np.ndarray

    def at_ends(self, values: np.ndarray) -> np.ndarray:
        """(2 S,) per-sample ``values`` interpolated linearly at the span ends."""
        v0 = values[self.left]
        return v0 + self.frac * (values[self.left + 1] - v0)

    def end_widths(self, widths: np.ndarray, path_width: float | np.ndarray) -> np.ndarray:
        """(2 S,) mm: the width at the span ends, the nearest sample's inside the span
        (``widths`` per sample row), or ``path_width`` where no sample falls inside (a
        switch point is where the width steps, so it is not interpolated across)."""
        return np.where(self.inner >= 0, widths[np.maximum(self.inner, 0)], path_width)

    def laid_out(self, values: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """(R,) per-sample ``values`` at the rows inside the spans, ``ends`` (2 S,) at
        their ends."""
        out = np.empty(len(self.rows))
        inside = self.rows >= 0
        out[inside] = values[self.rows[inside]]
        out[self.ends] = ends
        return out


def _span_layout(spans: np.ndarray, first: np.ndarray, n: np.ndarray, dt: np.ndarray
                 ) -> _SpanLayout:
    """The rows of the spans ``(S, 2)`` s of trajectories of ``n (S,) >= 2`` samples every
    ``dt (S,)`` s starting at row ``first (S,)`` (one entry per span)."""
    S = len(spans)
    pos = spans / dt[:, None]                              # in samples
    i_lo = np.floor(pos[:, 0] + SPAN_SNAP).astype(np.int64) + 1
    i_hi = np.minimum(np.ceil(pos[:, 1] - SPAN_SNAP).astype(np.int64) - 1, n - 1)
    count = np.maximum(i_hi - i_lo + 1, 0)
    start = offsets(count + 2)
    R = int(start[-1])
    rows = np.full(R, -1, dtype=np.int64)
    local = np.arange(R) - np.repeat(start[:-1], count + 2)
    inside = (local > 0) & (local <= np.repeat(count, count + 2))
    span_of = np.repeat(np.arange(S), count + 2)
    rows[inside] = (first + i_lo - 1)[span_of[inside]] + local[inside]
    ends = np.column_stack([start[:-1], start[1:] - 1]).reshape(-1)
    end_pos = pos.reshape(-1)
    owner_n = np.repeat(n, 2)
    i0 = np.clip(np.floor(end_pos).astype(np.int64), 0, owner_n - 2)
    frac = np.clip(end_pos - i0, 0.0, 1.0)
    base = np.repeat(first, 2)
    t = np.empty(R)
    t[inside] = ((rows[inside] - first[span_of[inside]]).astype(np.float64)
                 * dt[span_of[inside]])
    t[ends] = spans.reshape(-1)
    has = np.repeat(count > 0, 2)
    near = np.column_stack([first + i_lo, first + i_lo + count - 1]).reshape(-1)
    return _SpanLayout(rows=rows, t=t, start=start, ends=ends, left=base + i0, frac=frac,
                       inner=np.where(has, near, -1))


def span_layout(trajectory: Trajectory) -> _SpanLayout | None:
    """The rows of a continuous tour's spans (:func:`_span_layout` for one trajectory of
    two samples or more); None for any other trajectory."""
    n = len(trajectory.xy)
    if trajectory.on_spans is None or n < 2:
        return None
    spans = np.asarray(trajectory.on_spans, dtype=np.float64).reshape(-1, 2)
    S = len(spans)
    return _span_layout(spans, np.zeros(S, np.int64), np.full(S, n, np.int64),
                        np.full(S, float(trajectory.dt)))


def on_times(trajectory: Trajectory) -> list[np.ndarray]:
    """The instants, s from the trajectory start, of each stretch over which its valve is
    on: a continuous tour's spans (their exact ends and the samples between), or every
    sample of any other trajectory."""
    lay = span_layout(trajectory)
    if lay is None:
        return [np.arange(len(trajectory.xy)) * float(trajectory.dt)]
    return [lay.t[a:b] for a, b in zip(lay.start[:-1].tolist(), lay.start[1:].tolist())]


def positions_at(xy: np.ndarray, dt: float, t: np.ndarray) -> np.ndarray:
    """(k, 2) the samples ``xy`` (every ``dt`` s) at the instants ``t``, linear between
    them as the robot follows them (at a sample's instant, the sample itself)."""
    if len(xy) < 2:
        return xy[np.zeros(len(t), dtype=np.int64)]
    pos = t / dt
    i = np.clip(np.floor(pos + 1e-9).astype(np.int64), 0, len(xy) - 2)
    f = np.clip(pos - i, 0.0, 1.0)[:, None]
    out = xy[i] + f * (xy[i + 1] - xy[i])
    exact = np.abs(pos - np.rint(pos)) <= 1e-9
    out[exact] = xy[np.clip(np.rint(pos[exact]).astype(np.int64), 0, len(xy) - 1)]
    return out


def _span_ends(lay: _SpanLayout, speed: np.ndarray, u: np.ndarray | None, w: np.ndarray,
               w_path: np.ndarray, dh: float, job: "Job") -> tuple[np.ndarray, np.ndarray]:
    """``(q_nom, q)`` (2 S,) mm^3/s at the span ends: eq. 6.2-6.3 with the speed (and the
    control action ``u``) interpolated there and the width of the nearest sample inside the
    span (``w``, per sample row), or ``w_path`` (2 S,) when no sample falls inside.

    The robot does not stop at a switch, so the speed there lies between two neighbouring
    samples' and the flow between theirs: it is not checked against the calibration table
    again; the caller holds it in the valve's range where the action saturates it and
    clamps its frequency to the table and the valve's limit, as the samples'."""
    q_nom = (lay.end_widths(w, w_path) * dh * job.flow.layer_scale) * lay.at_ends(speed)
    if u is None:
        return q_nom, q_nom
    return q_nom, np.clip((1.0 + lay.at_ends(u)), 0.0, None) * q_nom


def max_valve_frequency(job: "Job") -> float:
    """The highest valve frequency the cell makes, Hz: ``flow.max_frequency_hz``, and one
    calibration pulse at a time (``1 / flow.calibration_pulse_ms``)."""
    fl = job.flow
    return min(fl.max_frequency_hz, 1000.0 / fl.calibration_pulse_ms)


def valve_flow_range(calibration: Calibration, job: "Job") -> tuple[float, float]:
    """The flows the valve gives, ``(lowest, highest)`` mm^3/s.

    FM: the calibration table's range, up to its flow at the highest frequency the cell
    makes (:func:`max_valve_frequency`). PWM: from no pulse to the longest pulse
    :func:`pwm_max_width_ms` allows (pulse widths scale the table's volume at
    ``flow.calibration_pulse_ms``, see :func:`_pwm`): at most the table's highest flow.
    """
    fl = job.flow
    cal = calibration
    if fl.mode == "fm":
        top = float(cal.flow(np.array([max_valve_frequency(job)]))[0])
        return cal.min_flow, min(cal.max_flow, top)
    f = fl.pwm_frequency_hz
    return 0.0, float(cal.flow(np.array([f]))[0]) * pwm_max_width_ms(cal, job) \
        / fl.calibration_pulse_ms


def pwm_max_width_ms(calibration: Calibration, job: "Job") -> float:
    """The longest PWM pulse, ms: the period ``1 / flow.pwm_frequency_hz`` (65.535 ms at
    most, uint16 microseconds), and no longer than gives the calibration table's highest
    flow, ``calibration.max_flow`` mm^3/s.

    Why the flow cap: the PWM model scales the volume of a pulse linearly with its width
    from the table's at ``flow.calibration_pulse_ms`` (:func:`_pwm`). That is an
    extrapolation the table does not measure: its flows grow less than proportionally with
    the valve's duty (thesis Fig. 6-1), and its highest row (195 mm^3/s at 1000 Hz x 0.5 ms
    by default) is the most the valve was seen to pass. A valve fully open at 125 Hz
    counted as 16 x the 0.5 ms pulse's volume, 495 mm^3/s, and G-code was written for
    paths asking 378 mm^3/s, which thesis 6.1 contradicts as well (FM gives the larger
    flow range, not PWM). So the PWM flow stops at the table's highest flow, as FM's
    does: a nominal flow beyond it is ``flow.out_of_range``'s (refused or clamped), an
    SMF correction beyond it is saturated."""
    fl = job.flow
    f = fl.pwm_frequency_hz
    period_ms = min(1000.0 / f, 65.535)
    per_pulse = float(calibration.flow(np.array([f]))[0])   # mm^3/s at calibration pulses
    if per_pulse <= 0:
        return period_ms
    return min(period_ms, fl.calibration_pulse_ms * calibration.max_flow / per_pulse)


def _saturated(q: np.ndarray, q_nom: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The samples ``(n,) bool`` whose corrected flow ``q`` leaves the valve's range
    ``[lo, hi]`` mm^3/s (:func:`valve_flow_range`) while the nominal flow ``q_nom`` is
    inside it.

    There the control action, not the plan, asks too much, and the valve's range is the
    actuator's saturation (thesis 5.2.2: "if valve frequency is the control action,
    saturation keeps the requested frequency within the range of valve capabilities"):
    the flow is held at the range's end whatever ``flow.out_of_range`` says. A nominal
    flow beyond the range is the plan's fault and stays ``out_of_range``'s matter.
    """
    lo, hi = lo * (1 - 1e-12), hi * (1 + 1e-12)   # a flow at the range's ends is inside
    nominal_fits = (q_nom <= hi) & ((q_nom >= lo) | (q_nom <= 0))
    return nominal_fits & (q > 0) & ((q > hi) | (q < lo))


#: A trajectory whose speed integrates to a length differing from the distance its samples
#: travel by more than SPEED_MISMATCH (relative) and SPEED_MISMATCH_MM is reported: the
#: valve would deposit that much too little or too much (wrong units, a re-timed path whose
#: speed was not updated).
SPEED_MISMATCH = 0.05
SPEED_MISMATCH_MM = 0.5


def _integral(y: np.ndarray, t: np.ndarray) -> float:
    """Trapezoidal integral of samples ``y (n,)`` over times ``t (n,)``."""
    from scipy.integrate import trapezoid  # scipy.integrate takes 0.4 s to import: here only
    return float(trapezoid(y, t)) if len(t) > 1 else 0.0


def volume_error(delivered: float, commanded: float) -> str:
    """'delivers D of C mm^3 commanded (+x %)': the volume a limit costs (or adds)."""
    pct = f"{100.0 * (delivered / commanded - 1.0):+.1f} %" if commanded > 0 else "n/a"
    return f"delivers {delivered:.4g} of {commanded:.4g} mm^3 commanded ({pct})"


def _where(trajectory: Trajectory) -> str:
    p = trajectory.path
    if p is None:
        return "trajectory"
    return f"layer {p.layer} {p.material} {p.role} path"


# =========================================================================== pulses


def pulse_instants(t: np.ndarray, nu: np.ndarray) -> np.ndarray:
    """(p,) float64 pulse instants, s, for the frequency ``nu (n,)`` Hz at times ``t (n,)``.

    Cumulative pulses N(t) by the trapezoidal rule (eq. 6.5); pulse j (j = 0, 1, ...) where
    N = j + 0.5 (eq. 6.6), found by linear interpolation of t in N. The count is
    ``floor(N_end + 0.5)``, within half a pulse of the integral N_end.
    """
    if len(t) < 2:
        return np.zeros(0)
    from scipy.integrate import cumulative_trapezoid  # slow to import (see _integral)
    cum = cumulative_trapezoid(nu, t, initial=0.0)
    total = float(cum[-1])
    p = int(np.floor(total + 0.5))
    if p <= 0:
        return np.zeros(0)
    targets = np.arange(p) + 0.5
    targets = targets[targets <= total]
    idx = np.searchsorted(cum, targets, side="left")  # cum[idx-1] < target <= cum[idx]
    idx = np.clip(idx, 1, len(cum) - 1)
    c0 = cum[idx - 1]
    c1 = cum[idx]
    frac = (targets - c0) / np.where(c1 > c0, c1 - c0, 1.0)
    return t[idx - 1] + frac * (t[idx] - t[idx - 1])


#: Most pulses of a PWM piece icefab makes. A piece's widths follow all its ticks and
#: leave the controller's 12 288-byte store only at its end; the next piece's header,
#: ticks and first widths must be there by then (firmware/PROTOCOL.md 5: at most 3 069
#: pulses, 4 n + 10 bytes). At that limit the next piece's third pulse needs bytes the PC
#: can send only once the widths went (2 pulses, 4 ms at 500 Hz, where one PROG_DATA frame
#: takes 21 ms at 115 200 baud); at 2 048 the store holds (12 288 - 4 n - 10) / 2 = 2 043
#: of its pulses (4 s at 500 Hz). Pieces cost nothing else: their starts are exact (from
#: the cumulative microseconds). FM pieces stream through the store and keep
#: flow.max_pulses.
PWM_PIECE_PULSES = 2048


def piece_pulses(job: "Job") -> int:
    """Most pulses in one program piece: ``flow.max_pulses``, and in PWM mode at most what
    the controller's store holds whole (:data:`PWM_PIECE_PULSES`)."""
    fl = job.flow
    return fl.max_pulses if fl.mode == "fm" else min(fl.max_pulses, PWM_PIECE_PULSES)


#: A piece's duration is stored as a uint32 count of microseconds (the binary layout,
#: :func:`encode_valve_program`).
PIECE_MAX_US = 2 ** 32 - 1


def piece_max_s(job: "Job") -> float:
    """The longest valve program piece, s: ``flow.max_piece_s``, with every pulse instant
    within uint16 ticks of the piece's start (less than 65 535.5 ticks) and the duration
    within the layout's uint32 microseconds (4 294.97 s: a 1 mm/s path at a 0.1 s tick
    crashed the binary writer)."""
    tick = job.flow.tick_s
    return min(job.flow.max_piece_s, 65535.5 * tick, (PIECE_MAX_US - 1) / 1e6)


def _split(times: np.ndarray, widths: np.ndarray | None, duration: float, dt: float,
           job: "Job") -> ValveProgram:
    """Pieces of at most max_piece_s and :func:`piece_pulses` pulses, boundaries on
    trajectory samples."""
    fl = job.flow
    most = piece_pulses(job)
    tick = fl.tick_s
    max_len = piece_max_s(job)
    pieces: list[ValveProgram] = []
    t0 = 0.0
    i0 = 0
    p = len(times)
    tick_us = int(round(tick * 1e6))
    start_us = 0    # the pieces before this one, in the whole microseconds the file holds
    while True:
        limit = t0 + max_len
        if p - i0 > most:
            # pulse i0 + max_pulses must open the next piece
            limit = min(limit, float(times[i0 + most]))
        last = limit >= duration and p - i0 <= most
        if last:
            t_end, i1 = duration, p
        else:
            t_end = float(np.floor(limit / dt + 1e-9) * dt) if dt > 0 else limit
            if t_end > limit:  # rounding of the snap: stay below the limit
                t_end -= dt
            if t_end <= t0 + 1e-12:  # a time step longer than the piece: cut between samples
                t_end = limit
            i1 = min(int(np.searchsorted(times, t_end, side="left")), i0 + most)
        # each pulse on the tick nearest its instant, counted from the piece's start as
        # the controller rounds it (PROTOCOL.md 7: S = floor(sum of durations / tick +
        # 1/2)): from the unrounded start, a boundary at half a tick or more put the next
        # piece's first pulse a tick late, on the tick of the one before (one drop lost,
        # a firmware review's). Half up (with a hair of tolerance): instants exactly one
        # tick apart at a half-tick phase (PWM at 1 / tick_s) keep distinct ticks; rint's
        # half-to-even would put two of them on one tick
        start = piece_start_tick(start_us, tick_us)
        ticks = np.clip(np.floor(times[i0:i1] / tick + (0.5 + 1e-9)) - start, 0,
                        65535).astype(np.uint16)
        w = None if widths is None else widths[i0:i1]
        pieces.append(ValveProgram(ticks=ticks, tick_s=tick, duration=float(t_end - t0),
                                   widths_us=w))
        if last:
            break
        start_us += int(round((t_end - t0) * 1e6))   # as the binary layout stores it
        t0, i0 = t_end, i1
    first = pieces[0]
    return dataclasses.replace(first, pieces=tuple(pieces[1:]))


def plan_valves(trajectory: Trajectory, material: str, job: "Job | None" = None, *,
                action: ActionLike = None, layer_thickness: float | None = None,
                calibration: Calibration | None = None) -> ValveProgram:
    """The valve program of one trajectory (thesis 6.2, 2.3.1).

    trajectory: constant-dt samples with speed (n,) mm/s and ``duration = (n - 1) dt``
        (FlowError otherwise); a trajectory whose path does not deposit (travel,
        measure) gets an empty program of the same duration.
    material: "part" or "scaffold".
    job: the settings; ``Job()`` when None, as every other stage takes it.
    action: control action u (see :func:`valve_frequency`): flow x (1 + u), the
        nu-controller of thesis 5.4.
    layer_thickness: dh_d, mm (default ``job.slicing.layer_thickness_mm``).

    A continuous tour (``trajectory.on_spans``, issue 15) is pulsed over the spans its
    valve is on only, each as a path of its own (FM: its own pulse count from its exact
    start to its exact end; PWM: its own periods), every pulse's tick within its span
    (:func:`_kept_in_spans`): nothing over the travel between its paths.

    Returns the first piece; further pieces (split at :func:`piece_max_s` and
    :func:`piece_pulses`: 131.071 s / 16 384 pulses by default, on trajectory samples)
    are in ``.pieces``; :func:`program_pieces` lists all of them and :func:`pulse_times`
    gives the instants from the trajectory start. ``.warnings`` lists
    every valve limit reached on this path (clamped flow and the volume it costs, PWM pulses
    dropped / raised / cut and the volume error, too few drops per mm, pulses sharing a
    tick); :func:`summarise_findings` condenses them over many paths.
    """
    if job is None:
        from icefab.config import Job

        job = Job()
    if material not in MATERIALS:
        raise FlowError(f"material {material!r}: expected one of {', '.join(MATERIALS)}")
    fl = job.flow
    check_trajectory(trajectory)
    check_flow_settings(job)
    duration = float(trajectory.duration)
    path = trajectory.path
    if path is not None and not path.depositing:
        return ValveProgram(ticks=np.zeros(0, np.uint16), tick_s=fl.tick_s, duration=duration,
                            widths_us=None if fl.mode == "fm" else np.zeros(0, np.uint16),
                            commanded_mm3=0.0, laid_mm3=0.0)
    cal = calibration or calibration_for(material, job)
    plan = valve_frequency(trajectory, material, job, action=action,
                           layer_thickness=layer_thickness, calibration=cal)
    dh = float(job.slicing.layer_thickness_mm if layer_thickness is None else layer_thickness)
    warnings = list(plan.warnings)
    if fl.mode == "fm":
        if plan.on is None:
            times = pulse_instants(plan.t, plan.nu)
            sig, start, per_stretch = plan, np.array([0, len(plan.t)]), np.array([len(times)])
        else:   # a tour: each of its paths' spans counts its own pulses
            from icefab._pulses import pulse_instants_many
            times, per = pulse_instants_many(plan.on.t, plan.on.nu, plan.on.start)
            times = _kept_in_spans(times, np.diff(per), _on_ends(plan.on), fl.tick_s)
            sig, start, per_stretch = plan.on, plan.on.start, np.diff(per)
        passed = np.where(sig.nu > 0, cal.flow(sig.nu), 0.0)
        volumes = tuple(float(v.sum()) for v in _fm_volumes(sig.t, sig.q, sig.nu, start,
                                                              per_stretch, passed))
        prog = _split(times, None, duration, float(trajectory.dt), job)
    else:
        speed = np.asarray(trajectory.speed, dtype=np.float64)
        moving = speed > 1e-9
        per_mm = float(np.max(plan.q[moving] / speed[moving])) if np.any(moving) else 0.0
        if plan.on is None:
            times, widths, found, volumes = _pwm(plan, cal, job, duration,
                                                 _where(trajectory), dh, per_mm)
        else:
            times, widths, found, volumes = _pwm_spans(plan.on, cal, job, _where(trajectory),
                                                       dh, per_mm)
        warnings.extend(found)
        prog = _split(times, widths, duration, float(trajectory.dt), job)
    prog = dataclasses.replace(prog, commanded_mm3=volumes[0], laid_mm3=volumes[1])
    shared = sum(int(np.count_nonzero(np.diff(p.ticks.astype(np.int64)) == 0))
                 for p in program_pieces(prog))
    if shared:  # thesis 2.3.1: one instant per uint16 entry, resolution one tick
        warnings.append(f"{_where(trajectory)}: {shared} pulses share a {fl.tick_s * 1e3:g} ms "
                        f"tick with the pulse before (valve frequency up to "
                        f"{float(plan.nu.max()):.4g} Hz, above 1 / flow.tick_s = "
                        f"{1.0 / fl.tick_s:g} Hz)")
    return dataclasses.replace(prog, warnings=tuple(warnings)) if warnings else prog


def _pwm(plan: FrequencyPlan, cal: Calibration, job: "Job", duration: float, where: str,
         dh: float, per_mm: float = 0.0
         ) -> tuple[np.ndarray, np.ndarray, list[str], tuple[float, float]]:
    """PWM (thesis 6.1): constant frequency f = ``flow.pwm_frequency_hz``, the pulse width
    carries the flow.

    Pulse k starts at (k + 1/2) / f (every instant within ``duration``) and delivers the
    volume commanded over its period [k / f, (k + 1) / f] (the last period runs to the end
    of the trajectory). The table was measured with pulses of ``calibration_pulse_ms``, so
    one such pulse at f passes ``V_ref = h^-1(f) / f``; the volume of a pulse is taken
    proportional to its width, giving ``width = calibration_pulse_ms * V / V_ref``.

    Limits (thesis 6.1: widths in [min_pulse_ms, period]): widths below ``min_pulse_ms``
    are laid as shortest pulses in some periods and none in others, what each period misses
    carried into the next (:func:`_pwm_widths_us`), so the path gets its volume within half
    a shortest pulse as FM's pulse count (eq. 6.6) however slowly it runs; a width above
    :func:`pwm_max_width_ms` (the period, 65.535 ms -- uint16 us --, and the width that
    gives the calibration table's highest flow: the table supports no more) is cut to it
    -- or FlowError under ``flow.out_of_range = "error"`` naming the flow asked, the
    valve's highest and the speed at which the path fits. Every limit hit is reported with
    its counts and the resulting volume error. ``dh``: the layer's thickness, mm (the
    error's hint, :func:`out_of_range_hint`); ``per_mm``: the path's largest volume per mm
    of travel, mm^3/mm (the flow over the speed: the speed that fits is the highest flow
    over it; 0 when unknown).
    Returns ``(times (p,) s, widths (p,) uint16 us, findings, (commanded, laid) mm^3)``.
    """
    fl = job.flow
    check_flow_settings(job, cal)
    f = fl.pwm_frequency_hz
    period = 1.0 / f
    count = int(np.floor(duration * f + 0.5 + 1e-9))  # pulses at (k + 1/2) / f <= duration
    if count == 0 and duration > 0:
        count = 1  # a trajectory shorter than half a period still gets its one pulse
    times = (np.arange(count) + 0.5) * period
    if count == 1:
        times = np.minimum(times, 0.5 * duration)
    edges = np.append(np.arange(count) * period, duration)
    from scipy.integrate import cumulative_trapezoid  # slow to import (see _integral)
    cum = cumulative_trapezoid(plan.q, plan.t, initial=0.0) if len(plan.t) > 1 else \
        np.zeros(len(plan.t))
    vol = np.diff(np.interp(edges, plan.t, cum)) if len(plan.t) > 1 else np.zeros(count)
    vol = np.maximum(vol, 0.0)
    vol_ref = float(cal.flow(np.array([f]))[0]) / f  # one calibration pulse at f, mm^3
    width_ms = fl.calibration_pulse_ms * vol / vol_ref
    w_max_ms = pwm_max_width_ms(cal, job)
    longest = pwm_longest_text(w_max_ms, period * 1000.0)
    cut = width_ms > w_max_ms * (1 + 1e-9)
    if np.any(cut) and fl.out_of_range == "error":
        q_max = vol_ref * (w_max_ms / fl.calibration_pulse_ms) * f
        fits = (f"; it fits at speeds up to {q_max / per_mm:.4g} mm/s" if per_mm > 0 else "")
        raise FlowError(f"{where}: flow {float(vol.max()) * f:.4g} mm^3/s above the "
                        f"{q_max:.4g} mm^3/s the valve gives by PWM at "
                        f"flow.pwm_frequency_hz = {f:g} Hz ({longest}) at "
                        f"{int(np.count_nonzero(cut))} of {count} pulses{fits}; "
                        f"{out_of_range_hint(dh, job, 'cut them and report')}")
    widths_us = _pwm_widths_us(width_ms, fl.min_pulse_ms, w_max_ms)
    keep = widths_us > 0
    dropped = int(np.count_nonzero(~keep & (vol > 0)))
    raised = int(np.count_nonzero(keep & (width_ms < fl.min_pulse_ms)))
    findings: list[str] = []
    delivered = float(np.sum(vol_ref * widths_us / 1000.0 / fl.calibration_pulse_ms))
    if dropped or raised or np.any(cut):
        findings.append(
            f"{where}: PWM at flow.pwm_frequency_hz = {f:g} Hz: {dropped} of {count} pulses "
            f"dropped and {raised} raised to flow.min_pulse_ms = {fl.min_pulse_ms:g} ms "
            f"(widths below it laid as shortest pulses in some periods), "
            f"{int(np.count_nonzero(cut))} cut to {w_max_ms:.4g} ms ({longest}); "
            f"{volume_error(delivered, float(np.sum(vol)))}")
    return (times[keep], widths_us[keep].astype(np.uint16), findings,
            (float(np.sum(vol)), delivered))


def pwm_longest_text(w_max_ms: float, period_ms: float) -> str:
    """What bounds the longest PWM pulse ``w_max_ms`` (:func:`pwm_max_width_ms`), words."""
    if w_max_ms < min(period_ms, 65.535) * (1 - 1e-9):
        return (f"pulses of at most {w_max_ms:.4g} ms of the {period_ms:g} ms period: the "
                "calibration table's highest flow")
    return f"pulses of at most {w_max_ms:.4g} ms, the valve open the whole period"


def _pwm_widths_us(width_ms: np.ndarray, min_ms: float, max_ms: float) -> np.ndarray:
    """(k,) float64 whole microseconds: the pulse widths ``width_ms`` (k,) ms asked period by
    period, made within the valve's ``[min_ms, max_ms]`` (0: no pulse) with what each
    period's width misses carried into the next, as eq. 6.6 carries the pulse count: a
    period asking (with the carry) less than ``min_ms / 2`` gets no pulse, less than
    ``min_ms`` the shortest pulse, more than ``max_ms`` the longest (the part of its own
    width beyond ``max_ms`` is cut, not carried: that flow the valve cannot pass anywhere).
    So the widths never lie more than half a shortest pulse (and half a microsecond) from
    the sum asked up to any period, whatever the flow: a slow path's volume is laid by
    shortest pulses in some periods, not lost by rounding every period to none (a
    tester's bunny boundaries at 4 mm^3/s, an eighth of a shortest pulse a period, got
    none)."""
    from icefab._pulses import pwm_widths_us

    lo_us = float(np.ceil(min_ms * 1000.0 - 1e-6))
    hi_us = float(np.floor(max_ms * 1000.0 + 1e-6))
    # sequential (the carry), so compiled: in Python it doubled the bunny's PWM 'valves'
    return pwm_widths_us(np.ascontiguousarray(width_ms, dtype=np.float64) * 1000.0,
                         lo_us, hi_us)


def _pwm_spans(on: SpanSignal, cal: Calibration, job: "Job", where: str, dh: float,
               per_mm: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray, list[str], tuple[float, float]]:
    """:func:`_pwm` over each span a tour's valve is on, as if each were a path of its own
    (its first period from the span's start, no pulse over the travel): the pulses of all
    of them in order, their findings and ``(commanded, laid)`` mm^3 over all."""
    times, widths, found = [], [], []
    commanded = laid = 0.0
    for a, b in zip(on.start[:-1].tolist(), on.start[1:].tolist()):
        t0 = float(on.t[a])
        t = on.t[a:b] - t0
        sub = FrequencyPlan(t=t, q=on.q[a:b], u=np.zeros(b - a), nu=on.nu[a:b])
        ti, wi, fi, (c, d) = _pwm(sub, cal, job, float(t[-1]), where, dh, per_mm)
        times.append(_kept_in_spans(ti + t0, np.array([len(ti)]),
                                    np.array([[t0, float(on.t[b - 1])]]), job.flow.tick_s))
        widths.append(wi)
        found.extend(fi)
        commanded += c
        laid += d
    return (np.concatenate(times) if times else np.zeros(0),
            np.concatenate(widths) if widths else np.zeros(0, np.uint16), found,
            (commanded, laid))


def _stretch_integrals(t: np.ndarray, y: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(S,) the trapezoidal integral of ``y`` over ``t`` on each stretch of rows
    ``start[k]:start[k+1]`` (each of two rows or more)."""
    step = np.zeros(len(t))
    seg = np.ones(len(t), dtype=bool)
    seg[np.asarray(start[1:]) - 1] = False           # no step from a stretch's last row
    k = np.flatnonzero(seg)
    step[k] = (t[k + 1] - t[k]) * (y[k + 1] + y[k]) / 2.0
    return np.add.reduceat(step, np.asarray(start[:-1])) if len(start) > 1 else np.zeros(0)


def _fm_volumes(t: np.ndarray, q: np.ndarray, nu: np.ndarray, start: np.ndarray,
                pulses: np.ndarray, passed: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """``(commanded, laid)`` (S,) mm^3 of FM pulses over each stretch ``start[k]:
    start[k+1]`` (a whole path, or a span a tour's valve is on): the flow ``q`` commanded,
    and of the flow the valve ``passed`` at ``nu`` (the table's; default ``q``: a flow
    within the table passes as commanded, since ``nu`` is its frequency there), the share
    its ``pulses[k]`` pulses make of the ``integral of nu dt`` it needs (eq. 6.5; eq. 6.6
    rounds that to whole pulses, so a short path may get none)."""
    commanded = _stretch_integrals(t, q, start)
    need = _stretch_integrals(t, nu, start)
    flowed = commanded if passed is None else _stretch_integrals(t, passed, start)
    laid = np.divide(flowed * pulses, need, out=np.zeros(len(need)), where=need > 0)
    return commanded, laid


# =========================================================================== helpers


def program_pieces(prog: ValveProgram) -> tuple[ValveProgram, ...]:
    """All pieces of a program in order (the first piece, then ``prog.pieces``)."""
    if not prog.pieces:  # one piece (most programs): itself, without a copy
        return (prog,)
    first = dataclasses.replace(prog, pieces=())
    return (first, *prog.pieces)


def piece_start_tick(start_us: int, tick_us: int) -> int:
    """The tick at which the valve controller starts a piece whose earlier pieces last
    ``start_us`` whole microseconds (their durations as the binary layout stores them):
    ``floor(start_us / tick_us + 1/2)`` (PROTOCOL.md 7), in integers."""
    return (2 * start_us + tick_us) // (2 * tick_us)


def pulse_times(prog: ValveProgram) -> np.ndarray:
    """(p,) float64 pulse instants, s, from the start of the trajectory (all pieces): as
    the valve controller plays them, each piece from its start rounded to a tick
    (PROTOCOL.md 7: the sum of the pieces' whole microseconds before it, over the tick,
    rounded half up)."""
    if not prog.pieces:  # one piece (most programs): its ticks, without joining pieces
        return prog.ticks.astype(np.float64) * prog.tick_s
    out = []
    start_us = 0
    for piece in program_pieces(prog):
        start = piece_start_tick(start_us, int(round(piece.tick_s * 1e6)))
        out.append((start + piece.ticks.astype(np.float64)) * piece.tick_s)
        start_us += int(round(piece.duration * 1e6))
    return np.concatenate(out) if out else np.zeros(0)


def n_pulses(prog: ValveProgram) -> int:
    """Total number of pulses over all pieces."""
    return int(sum(len(p.ticks) for p in program_pieces(prog)))


def total_duration(prog: ValveProgram) -> float:
    """Total duration over all pieces, s."""
    return float(sum(p.duration for p in program_pieces(prog)))


def finding_kind(text: str) -> str:
    """The kind of a valve-limit finding: its text with every number replaced by ``#``
    (layer numbers, counts and values differ from path to path; the limit does not)."""
    return numbers_hidden(text)


def summarise_findings(findings: "Sequence[tuple[int, str]]") -> list[str]:
    """Condense per-path valve-limit findings for people: one line per kind.

    findings: ``(layer index, finding text)`` pairs, e.g. from the ``warnings`` of the
        :class:`ValveProgram` of every path of a build.
    Returns lines ``"N paths in L layers (a-b): <first finding of that kind>"`` (up to 5
    layers that are not a run named one by one: ``(0, 5, 23)``), the most
    frequent kind first (ties in order of first appearance); a kind whose findings state
    the volume a limit costs (:func:`volume_error`) ends with its total over all of them,
    ``"; in all, delivers D of C mm^3 commanded (x %)"`` (a kind names the material and
    role, so this is the volume lost per material and role).
    """
    groups: dict[str, list[tuple[int, str]]] = {}
    for layer, text in findings:
        groups.setdefault(finding_kind(text), []).append((int(layer), text))
    out = []
    for items in sorted(groups.values(), key=lambda g: -len(g)):  # stable: first seen first
        layers = sorted({k for k, _ in items})
        if len(layers) == 1:
            span = f"layer {layers[0]}"
        elif layers[-1] - layers[0] + 1 == len(layers) or len(layers) > 5:
            span = f"{len(layers)} layers ({layers[0]}-{layers[-1]})"
        else:   # a few apart: named ("3 layers (0-23)" read as a range, a hunt's)
            span = f"{len(layers)} layers ({', '.join(map(str, layers))})"
        n = len(items)
        line = f"{n} path{'s' if n != 1 else ''} in {span}: {items[0][1]}"
        said = [_VOLUME.search(text) for _, text in items]
        if n > 1 and all(said):
            delivered = sum(float(m.group(1)) for m in said)
            line += f"; in all, {volume_error(delivered, sum(float(m.group(2)) for m in said))}"
        out.append(line)
    return out


#: The volume a finding states (:func:`volume_error`): delivered, commanded.
_VOLUME = re.compile(r"delivers (\S+) of (\S+) mm\^3 commanded")


# =========================================================================== files


def _atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, data)


def encode_valve_program(prog: ValveProgram) -> bytes:
    """The binary form (see the module docstring) as bytes."""
    pieces = program_pieces(prog)
    pwm = any(p.widths_us is not None for p in pieces)
    tick_us = int(round(prog.tick_s * 1e6))
    out = [MAGIC, struct.pack("<HBBII", VERSION, 1 if pwm else 0, 0, tick_us, len(pieces))]
    for p in pieces:
        ticks = np.asarray(p.ticks, dtype="<u2")
        out.append(struct.pack("<II", len(ticks), int(round(p.duration * 1e6))))
        out.append(ticks.tobytes())
        if pwm:
            w = np.zeros(len(ticks), "<u2") if p.widths_us is None else \
                np.asarray(p.widths_us, dtype="<u2")
            out.append(w.tobytes())
    return b"".join(out)


def decode_valve_program(data: bytes, source: str = "valve program") -> ValveProgram:
    """Parse the binary form; StackFileError when truncated or corrupt."""
    if len(data) < 16 or data[:4] != MAGIC:
        raise StackFileError(f"{source}: not an icefab valve program (bad magic or too short)")
    version, mode, _, tick_us, n_pieces = struct.unpack_from("<HBBII", data, 4)
    if version != VERSION:
        raise StackFileError(f"{source}: valve program version {version}, expected {VERSION}")
    if mode not in (0, 1) or tick_us == 0:
        raise StackFileError(f"{source}: corrupt header (mode {mode}, tick {tick_us} us)")
    pos = 16
    pieces = []
    for i in range(n_pieces):
        if pos + 8 > len(data):
            raise StackFileError(f"{source}: truncated in the header of piece {i}")
        n, dur_us = struct.unpack_from("<II", data, pos)
        pos += 8
        need = 2 * n * (2 if mode == 1 else 1)
        if pos + need > len(data):
            raise StackFileError(f"{source}: truncated in piece {i} ({n} pulses announced)")
        ticks = np.frombuffer(data, "<u2", n, pos).astype(np.uint16)
        pos += 2 * n
        widths = None
        if mode == 1:
            widths = np.frombuffer(data, "<u2", n, pos).astype(np.uint16)
            pos += 2 * n
        pieces.append(ValveProgram(ticks=ticks, tick_s=tick_us * 1e-6, duration=dur_us * 1e-6,
                                   widths_us=widths))
    if pos != len(data):
        raise StackFileError(f"{source}: {len(data) - pos} bytes after the last piece")
    if not pieces:
        raise StackFileError(f"{source}: no pieces")
    return dataclasses.replace(pieces[0], pieces=tuple(pieces[1:]))


def format_valve_program(prog: ValveProgram) -> str:
    """The text form (see the module docstring)."""
    pieces = program_pieces(prog)
    pwm = any(p.widths_us is not None for p in pieces)
    lines = [f"{TEXT_MAGIC} {VERSION}", f"mode {'pwm' if pwm else 'fm'}",
             f"tick_s {prog.tick_s:.9g}", f"pieces {len(pieces)}"]
    for i, p in enumerate(pieces):
        lines.append(f"piece {i} duration_s {p.duration:.6f} pulses {len(p.ticks)}")
        if pwm:
            w = p.widths_us if p.widths_us is not None else np.zeros(len(p.ticks), np.uint16)
            lines.extend(f"{int(a)} {int(b)}" for a, b in zip(p.ticks, w))
        else:
            lines.extend(str(int(a)) for a in p.ticks)
    return "\n".join(lines) + "\n"


def parse_valve_program(text: str, source: str = "valve program") -> ValveProgram:
    """Parse the text form; StackFileError naming the line on any problem."""
    rows = [(n, raw.split("#", 1)[0].split()) for n, raw in enumerate(text.splitlines(), 1)]
    rows = [(n, r) for n, r in rows if r]
    it = iter(rows)

    def expect(key: str, count: int) -> tuple[int, list[str]]:
        try:
            n, r = next(it)
        except StopIteration:
            raise StackFileError(f"{source}: truncated, expected {key!r}") from None
        if r[0] != key or len(r) != count:
            raise StackFileError(f"{source}:{n}: expected {key!r} line, got {' '.join(r)!r}")
        return n, r

    try:
        n, r = expect(TEXT_MAGIC, 2)
        if r[1] != str(VERSION):
            raise StackFileError(f"{source}:{n}: version {r[1]}, expected {VERSION}")
        n, r = expect("mode", 2)
        if r[1] not in ("fm", "pwm"):
            raise StackFileError(f"{source}:{n}: mode {r[1]!r}, expected fm or pwm")
        pwm = r[1] == "pwm"
        _, r = expect("tick_s", 2)
        tick = float(r[1])
        _, r = expect("pieces", 2)
        n_pieces = int(r[1])
        pieces = []
        for i in range(n_pieces):
            n, r = expect("piece", 6)
            dur = float(r[3])
            count = int(r[5])
            vals = np.zeros((count, 2 if pwm else 1), dtype=np.int64)
            for j in range(count):
                try:
                    n, r = next(it)
                except StopIteration:
                    raise StackFileError(f"{source}: truncated in piece {i}: {j} of {count} "
                                         "pulses") from None
                if len(r) != vals.shape[1]:
                    raise StackFileError(f"{source}:{n}: expected {vals.shape[1]} numbers")
                vals[j] = [int(x) for x in r]
            if np.any(vals < 0) or np.any(vals > 65535):
                raise StackFileError(f"{source}: piece {i}: values must fit uint16")
            pieces.append(ValveProgram(ticks=vals[:, 0].astype(np.uint16), tick_s=tick,
                                       duration=dur,
                                       widths_us=vals[:, 1].astype(np.uint16) if pwm else None))
    except ValueError as exc:
        if isinstance(exc, StackFileError):
            raise
        raise StackFileError(f"{source}: bad number ({exc})") from None
    extra = next(it, None)
    if extra is not None:
        raise StackFileError(f"{source}:{extra[0]}: unexpected data after the last piece")
    if not pieces:
        raise StackFileError(f"{source}: no pieces")
    return dataclasses.replace(pieces[0], pieces=tuple(pieces[1:]))


def write_valve_program(prog: ValveProgram, path: str | os.PathLike, fmt: str = "bin") -> None:
    """Write a program in the binary (``fmt="bin"``) or text (``"txt"``) form, atomically."""
    path = Path(path)
    if fmt == "bin":
        data = encode_valve_program(prog)
    elif fmt == "txt":
        data = format_valve_program(prog).encode("utf-8")
    else:
        raise FlowError(f"valve program format {fmt!r}: expected 'bin' or 'txt'")
    _atomic_write(path, data)


def read_valve_program(path: str | os.PathLike) -> ValveProgram:
    """Read a program written by :func:`write_valve_program` (either form, detected)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise StackFileError(f"{path}: valve program not found") from None
    if data[:4] == MAGIC:
        return decode_valve_program(data, str(path))
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise StackFileError(f"{path}: neither a binary nor a text valve program") from None
    return parse_valve_program(text, str(path))


@dataclass(frozen=True)
class LayerProgram:
    """One path's valve program in a layer file.

    path: the trajectory's index in its layer (``trajectories.npz``); material: "part" or
    "scaffold" (the valve, :data:`VALVE_NUMBER`); program: the pulses.
    """

    path: int
    material: str
    program: ValveProgram


def plan_layer_valves(layer: "LayerMotion", job: "Job") -> list[LayerProgram]:
    """The nominal valve programs (no control action) of every depositing trajectory of one
    layer, in build order, each with its trajectory's index in the layer (thesis 6.2).

    The flow uses the layer's own thickness with adaptive layers (``slicing.
    layer_thickness_mm`` otherwise); a trajectory without a path (a bare trajectory file)
    deposits part material. The calibration tables are read once per layer. The programs
    are :func:`plan_valves`' (in FM mode most are made for the whole layer at once,
    :func:`_nominal_fm_programs`, identical to it).
    """
    dh = layer_height(layer.thickness, job)
    tables: dict[str, Calibration] = {}
    picked: list[tuple[int, str, Trajectory]] = []
    for i, traj in enumerate(layer.trajectories):
        path = traj.path
        if path is not None and not path.depositing:
            continue
        material = path.material if path is not None else "part"
        if material not in tables:
            tables[material] = calibration_for(material, job)
        picked.append((i, material, traj))
    progs = (_nominal_fm_programs([x[2] for x in picked], [x[1] for x in picked], dh,
                                  tables, job)
             if job.flow.mode == "fm" else [None] * len(picked))
    return [LayerProgram(i, material, prog if prog is not None else plan_path_valves(
                layer.index, i, traj, material, job, dh, tables[material]))
            for (i, material, traj), prog in zip(picked, progs)]


def plan_path_valves(layer: int, index: int, trajectory: Trajectory, material: str,
                     job: "Job", dh: float, calibration: Calibration) -> ValveProgram:
    """:func:`plan_valves` of trajectory ``index`` of a layer, whose errors name that index
    as motion's do, "layer 3, path 5 (part fill): ..." (the trajectory does not know it:
    "layer 3 part fill path" left a docs hunt to guess which of the layer's fill paths).
    dh: the layer's thickness, mm."""
    try:
        return plan_valves(trajectory, material, job, layer_thickness=dh,
                           calibration=calibration)
    except FlowError as e:
        text, where, p = str(e), _where(trajectory), trajectory.path
        if text.startswith(f"{where}: "):
            text = text[len(where) + 2:]
        label = f"layer {layer}, path {index}" + (f" ({p.material} {p.role})" if p else "")
        raise type(e)(f"{label}: {text}") from None


def _nominal_fm_programs(trajs: "Sequence[Trajectory]", materials: Sequence[str], dh: float,
                         tables: dict[str, Calibration], job: "Job"
                         ) -> list["ValveProgram | None"]:
    """:func:`plan_valves` of many depositing trajectories (FM, no control action, layer
    thickness ``dh`` mm) in a few array operations over all their samples, for the common
    case: each program equals plan_valves' bit for bit (the same elementwise operations,
    the pulse instants by :func:`icefab._pulses.pulse_instants_many`).

    None for a trajectory this does not make (a sampling contract broken, a speed that does
    not integrate to the distance travelled, a flow outside the calibration table, a
    frequency above the valve's limit, fewer than two samples): the caller plans it with
    plan_valves, which makes or refuses it with its own messages. Programs of more than
    one piece are split by plan_valves' own ``_split``. Issue 17: one call per path made
    ``icefab valves`` spend two minutes in Python on the 1 M-facet bunny.
    """
    from icefab._pulses import pulse_instants_many

    fl = job.flow
    m = len(trajs)
    if not m:
        return []
    check_flow_settings(job)
    n = n_all = np.array([len(t.xy) for t in trajs], dtype=np.int64)
    dt = np.array([float(t.dt) for t in trajs])
    dur = np.array([float(t.duration) for t in trajs])
    ok = (n >= 2) & np.isfinite(dt) & (dt > 0)
    expected = (n - 1) * dt
    ok &= np.isfinite(dur) & (np.abs(dur - expected) <= 1e-6 + 1e-9 * expected)
    ok &= np.array([np.shape(t.speed) == (len(t.xy),) and np.shape(t.xy)[1:] == (2,)
                    for t in trajs])
    var = np.array([t.widths is not None for t in trajs], dtype=bool)
    if var.any():   # bad widths: plan_valves refuses the path, in its turn
        var_ok, var_w = variable_widths([t for t, v in zip(trajs, var) if v])
        ok[np.flatnonzero(var)[~var_ok]] = False
    spanned = [i for i, t in enumerate(trajs) if t.on_spans is not None]
    if spanned:   # bad spans: the same
        shaped = [i for i in spanned if np.ndim(trajs[i].on_spans) == 2
                  and np.shape(trajs[i].on_spans)[1] == 2
                  and np.asarray(trajs[i].on_spans).dtype.kind in "fiu"]
        ok[sorted(set(spanned) - set(shaped))] = False
        if shaped:
            count = [len(trajs[i].on_spans) for i in shaped]
            fine = spans_fine(np.repeat(np.arange(len(shaped)), count),
                              np.concatenate([np.asarray(trajs[i].on_spans, np.float64)
                                              for i in shaped]),
                              dur[shaped])
            ok[np.asarray(shaped)[~fine]] = False
    out: list[ValveProgram | None] = [None] * m
    idx = np.flatnonzero(ok)
    if not len(idx):
        return out
    sel = [trajs[i] for i in idx]
    n, dt, dur = n[idx], dt[idx], dur[idx]
    starts = np.concatenate([[0], np.cumsum(n)])
    owner = np.repeat(np.arange(len(idx)), n)
    first = starts[:-1]
    speed = np.concatenate([np.asarray(t.speed, np.float64) for t in sel])
    xy = np.concatenate([np.asarray(t.xy, np.float64) for t in sel])
    bad = ~(np.isfinite(speed) & (speed >= 0))
    # the flow, frequency and time axis of every sample, as valve_frequency makes them
    own_width = np.array([trajectory_width(t, materials[i], job) for t, i in zip(sel, idx)])
    width = own_width[owner]
    mine = np.flatnonzero(var[idx])
    if len(mine):   # variable-width paths: eq. 6.2 with w(s), into their samples' places
        # var_w holds the widths of every variable-width trajectory with good ones; the
        # selected are among them (bad widths made a trajectory not ok)
        good = np.flatnonzero(var)[var_ok]
        w_first = offsets(n_all[good])[:-1][np.searchsorted(good, idx[mine])]
        lens = n[mine]
        within = np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens)
        width[np.repeat(first[mine], lens) + within] = var_w[np.repeat(w_first, lens) + within]
    q = width * dh * fl.layer_scale * speed
    t = (np.arange(len(speed)) - first[owner]).astype(np.float64) * dt[owner]
    mats = [materials[i] for i in idx]
    lo_flow = np.array([tables[mt].min_flow for mt in mats])[owner]
    hi_flow = np.array([tables[mt].max_flow for mt in mats])[owner]
    flowing = q > 0
    nu = np.zeros(len(q))
    for mt in set(mats):
        rows = np.array([x == mt for x in mats])[owner]
        nu[rows] = np.where(flowing[rows], tables[mt].frequency(q[rows]), 0.0)
    nu_max = max_valve_frequency(job)
    bad |= (q > hi_flow) | (flowing & (q < lo_flow)) | (nu > nu_max)
    # the speed must integrate to the distance travelled (valve_frequency's warning)
    inner = np.ones(len(q), dtype=bool)
    inner[starts[1:] - 1] = False               # the step from each path's last sample
    step = np.zeros(len(q))
    seg = np.flatnonzero(inner)
    d = xy[seg + 1] - xy[seg]
    step[seg] = np.sqrt(d[:, 0] ** 2 + d[:, 1] ** 2)
    trap = np.zeros(len(q))
    trap[seg] = (t[seg + 1] - t[seg]) * (speed[seg + 1] + speed[seg]) / 2.0
    travelled = np.add.reduceat(step, first)
    integrated = np.add.reduceat(trap, first)
    mismatch = np.abs(integrated - travelled) > np.maximum(SPEED_MISMATCH_MM,
                                                           SPEED_MISMATCH * travelled)
    fast = ~(np.add.reduceat(bad.astype(np.int64), first) > 0) & ~mismatch
    # fewer drops per mm than flow.min_drops_per_mm
    moving = speed > 1e-9
    drops = np.divide(nu, speed, out=np.full(len(q), np.inf), where=moving)
    few = moving & (drops < fl.min_drops_per_mm) & flowing
    n_few = np.add.reduceat(few.astype(np.int64), first)
    few_min = np.minimum.reduceat(np.where(few, drops, np.inf), first)
    nu_peak = np.maximum.reduceat(nu, first)
    # pulses only for the paths this pass programs: the others go their own way below
    # (refused, or clamped one by one), and a table reaching 1e12 Hz made ~1e11 pulses a
    # step here before they were refused (a hunt's: 'icefab valves' ran for minutes)
    nu_fast = np.where(fast[owner], nu, 0.0)
    times, toff = pulse_instants_many(t, nu_fast, starts)
    # what the valve passes: the commanded flow within its table, the table's end where
    # flow.out_of_range = "clamp" clamped the frequency there (taking q everywhere, a
    # clamped tour's laid volume came out 4.5 % above plan_valves')
    passed = np.where(flowing, np.clip(q, lo_flow, hi_flow), 0.0)
    commanded, laid = _fm_volumes(t, q, nu_fast, starts, np.diff(toff), passed)
    tours = np.array([tr.on_spans is not None for tr in sel], dtype=bool) & fast
    if tours.any():
        times, toff, c_tour, l_tour = _tour_pulses(sel, tours, times, toff, speed, nu_fast, q,
                                                   passed, width, own_width, first, n, dt,
                                                   mats, tables, dh, job)
        commanded[tours], laid[tours] = c_tour, l_tour
    tick = fl.tick_s
    most = piece_pulses(job)
    max_len = piece_max_s(job)
    ticks_all = np.clip(np.floor(times / tick + (0.5 + 1e-9)), 0, 65535).astype(np.uint16)
    # pulses sharing a tick with the one before, within each path's one-piece program
    same = np.zeros(len(ticks_all), dtype=np.int64)
    same[1:] = ticks_all[1:] == ticks_all[:-1]
    same[toff[:-1][toff[:-1] < len(same)]] = 0       # no "before" at a path's first pulse
    counted = offsets(same)
    shared_one = counted[toff[1:]] - counted[toff[:-1]]
    for k in np.flatnonzero(fast):
        tr = sel[k]
        where = _where(tr)
        warnings = []
        if n_few[k]:
            warnings.append(f"{where}: fewer than flow.min_drops_per_mm = "
                            f"{fl.min_drops_per_mm:g} drops per mm ({float(few_min[k]):.3g}) at "
                            f"{int(n_few[k])} samples")
        a, b = toff[k], toff[k + 1]
        one = b - a <= most and max_len >= dur[k]    # one piece (_split's first and last)
        prog = None
        if one:
            shared = int(shared_one[k])
        else:
            prog = _split(times[a:b], None, float(dur[k]), float(dt[k]), job)
            shared = sum(int(np.count_nonzero(np.diff(p.ticks.astype(np.int64)) == 0))
                         for p in program_pieces(prog))
        if shared:
            warnings.append(f"{where}: {shared} pulses share a {tick * 1e3:g} ms tick with "
                            f"the pulse before (valve frequency up to {float(nu_peak[k]):.4g} "
                            f"Hz, above 1 / flow.tick_s = {1.0 / tick:g} Hz)")
        for w in warnings:
            log.debug(w)
        if prog is None:   # made with its findings (a copy per program cost the bunny 1 s)
            out[idx[k]] = ValveProgram(ticks=ticks_all[a:b], tick_s=tick,
                                       duration=float(dur[k]), warnings=tuple(warnings),
                                       commanded_mm3=float(commanded[k]),
                                       laid_mm3=float(laid[k]))
        else:
            out[idx[k]] = dataclasses.replace(prog, warnings=tuple(warnings),
                                              commanded_mm3=float(commanded[k]),
                                              laid_mm3=float(laid[k]))
    return out


def _tour_pulses(sel: "Sequence[Trajectory]", tours: np.ndarray, times: np.ndarray,
                 toff: np.ndarray, speed: np.ndarray, nu: np.ndarray,
                 q: np.ndarray, passed: np.ndarray, width: np.ndarray,
                 own_width: np.ndarray, first: np.ndarray,
                 n: np.ndarray, dt: np.ndarray, mats: Sequence[str],
                 tables: dict[str, Calibration], dh: float, job: "Job"
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pulse instants of :func:`_nominal_fm_programs` with the tours' (``tours`` (m,)
    bool over ``sel``) placed over the spans their valve is on, as :func:`plan_valves`
    places them (:func:`_span_layout`, :func:`_span_ends`, the same operations over all
    the tours' spans at once): ``(times, offsets)`` as ``pulse_instants_many`` gives
    them, and each tour's ``(commanded, laid)`` mm^3 (:func:`_fm_volumes`, over its
    spans; ``passed`` (N,) mm^3/s: the flow the valve passes at each sample)."""
    from icefab._pulses import pulse_instants_many

    which = np.flatnonzero(tours)
    spans = [np.asarray(sel[k].on_spans, np.float64).reshape(-1, 2) for k in which]
    count = np.array([len(x) for x in spans], dtype=np.int64)
    owner = np.repeat(which, count)
    lay = _span_layout(np.concatenate(spans), first[owner], n[owner], dt[owner])
    _, q_e = _span_ends(lay, speed, None, width, np.repeat(own_width[owner], 2), dh, job)
    nu_e = np.zeros(len(q_e))
    end_mat = np.repeat(np.array(mats, dtype=object)[owner], 2)
    for mt in set(end_mat.tolist()):
        rows = end_mat == mt
        nu_e[rows] = np.where(q_e[rows] > 0, tables[mt].frequency(q_e[rows]), 0.0)
    nu_e = np.minimum(nu_e, max_valve_frequency(job))
    passed_e = np.zeros(len(q_e))   # the ends' flows as the valve passes them
    for mt in set(end_mat.tolist()):
        rows = (end_mat == mt) & (nu_e > 0)
        passed_e[rows] = tables[mt].flow(nu_e[rows])
    on = _span_signal(lay, q, nu, q_e, nu_e)
    span_times, span_off = pulse_instants_many(on.t, on.nu, on.start)
    span_times = _kept_in_spans(span_times, np.diff(span_off), _on_ends(on), job.flow.tick_s)
    span_vol = _fm_volumes(on.t, on.q, on.nu, on.start, np.diff(span_off),
                           lay.laid_out(passed, passed_e))
    tour_of_span = np.repeat(np.arange(len(count)), count)
    tour_vol = [np.bincount(tour_of_span, weights=v, minlength=len(count)) for v in span_vol]
    # every trajectory's pulses: its own, or its spans' in order
    per = np.diff(toff)
    span_per = np.diff(span_off)
    tour_total = np.bincount(np.repeat(np.arange(len(count)), count), weights=span_per,
                             minlength=len(count)).astype(np.int64)
    per[which] = tour_total
    new_off = offsets(per)
    out = np.empty(int(new_off[-1]))
    plain = np.ones(len(per), dtype=bool)
    plain[which] = False
    src = np.repeat(toff[:-1][plain], per[plain])
    dst = np.repeat(new_off[:-1][plain], per[plain])
    run = np.arange(len(src)) - np.repeat(offsets(per[plain])[:-1], per[plain])
    out[dst + run] = times[src + run]
    dst_t = np.repeat(new_off[:-1][which], tour_total)
    run_t = np.arange(len(dst_t)) - np.repeat(offsets(tour_total)[:-1], tour_total)
    out[dst_t + run_t] = span_times
    return out, new_off, tour_vol[0], tour_vol[1]


def _layer_valves_task(item: tuple["LayerMotion", "Job"]) -> list[LayerProgram]:
    return plan_layer_valves(*item)


def plan_build_valves(layers: "Sequence[LayerMotion]", job: "Job",
                      progress: Callable[[int, int], None] | None = None
                      ) -> list[list[LayerProgram]]:
    """:func:`plan_layer_valves` of every layer, in layer order. progress: called as
    ``progress(done, total)`` in layers.

    FM (the default) runs in this process: a layer's programs take a few milliseconds
    (7 ms a bunny layer, :func:`_nominal_fm_programs`), less than sending its trajectories
    to a worker process costs. PWM, planned path by path, runs on the job's worker
    processes (``cell.cpus``); the programs never depend on the number of workers."""
    if job.flow.mode == "fm":
        out = []
        for k, lm in enumerate(layers):
            out.append(plan_layer_valves(lm, job))
            if progress is not None:
                progress(k + 1, len(layers))
        return out
    return parallel_map(_layer_valves_task, [(lm, job) for lm in layers], job, min_items=8,
                        progress=progress)


#: Layers planned per batch by :func:`iter_build_valves`: enough to keep the workers busy
#: (PWM), few enough that a batch's programs are small next to the trajectories.
VALVE_BATCH_LAYERS = 96


def iter_build_valves(layers: "Iterable[LayerMotion]", job: "Job",
                      progress: Callable[[int, int], None] | None = None,
                      batch: int = VALVE_BATCH_LAYERS, total: int | None = None
                      ) -> "Iterator[tuple[LayerMotion, list[LayerProgram]]]":
    """``(layer, its programs)`` for every layer in order, planned ``batch`` layers at a
    time by :func:`plan_build_valves`: a caller that writes each layer's programs as they
    come never holds the whole build's (issue 17), and ``layers`` may be a stream (e.g.
    ``icefab.resultfiles.TrajectoryFile.iter_layers``), of which ``batch`` layers are taken
    at a time. progress as plan_build_valves', over ``total`` layers (default
    ``len(layers)``)."""
    if total is None:
        total = len(layers)  # type: ignore[arg-type]
    stream = iter(layers)
    done = 0
    while chunk := list(itertools.islice(stream, batch)):
        report = None if progress is None else \
            (lambda d, t, base=done: progress(base + d, total))
        yield from zip(chunk, plan_build_valves(chunk, job, progress=report))
        done += len(chunk)


def encode_valve_layer(layer: int, programs: "Sequence[LayerProgram]") -> bytes:
    """The binary layer form (module docstring) as bytes."""
    out = [LAYER_MAGIC, struct.pack("<HHII", VERSION, 0, int(layer), len(programs))]
    for lp in programs:
        body = encode_valve_program(lp.program)
        out.append(struct.pack("<IB3xI", int(lp.path), VALVE_NUMBER[lp.material], len(body)))
        out.append(body)
    return b"".join(out)


def decode_valve_layer(data: bytes, source: str = "valve layer file"
                       ) -> tuple[int, list[LayerProgram]]:
    """Parse the binary layer form: (layer index, programs); StackFileError naming the
    record when truncated or corrupt."""
    if len(data) < 16 or data[:4] != LAYER_MAGIC:
        raise StackFileError(f"{source}: not an icefab valve layer file (bad magic or too "
                             "short)")
    version, _, layer, n = struct.unpack_from("<HHII", data, 4)
    if version != VERSION:
        raise StackFileError(f"{source}: valve layer file version {version}, expected "
                             f"{VERSION}")
    valves = {v: k for k, v in VALVE_NUMBER.items()}
    pos, out = 16, []
    for i in range(n):
        if pos + 12 > len(data):
            raise StackFileError(f"{source}: truncated in the header of program {i}")
        path, valve, length = struct.unpack_from("<IB3xI", data, pos)
        pos += 12
        if valve not in valves:
            raise StackFileError(f"{source}: program {i}: valve {valve}, expected 0 or 1")
        if pos + length > len(data):
            raise StackFileError(f"{source}: truncated in program {i} ({length} bytes "
                                 "announced)")
        prog = decode_valve_program(data[pos:pos + length], f"{source}: program {i}")
        out.append(LayerProgram(int(path), valves[valve], prog))
        pos += length
    if pos != len(data):
        raise StackFileError(f"{source}: {len(data) - pos} bytes after the last program")
    return int(layer), out


def format_valve_layer(layer: int, programs: "Sequence[LayerProgram]") -> str:
    """The text layer form (module docstring)."""
    parts = [f"{LAYER_TEXT_MAGIC} {VERSION}\nlayer {int(layer)}\nprograms {len(programs)}\n"]
    for lp in programs:
        parts.append(f"program {int(lp.path)} valve {lp.material}\n")
        parts.append(format_valve_program(lp.program))
    return "".join(parts)


def parse_valve_layer(text: str, source: str = "valve layer file"
                      ) -> tuple[int, list[LayerProgram]]:
    """Parse the text layer form; StackFileError naming the line on any problem."""
    lines = text.splitlines()
    head = [(i + 1, ln.split("#", 1)[0].split()) for i, ln in enumerate(lines[:3])]
    want = ((LAYER_TEXT_MAGIC, str(VERSION)), ("layer",), ("programs",))
    for (n, r), w in zip(head, want):
        if len(r) != 2 or r[0] != w[0] or (len(w) == 2 and r[1] != w[1]):
            raise StackFileError(f"{source}:{n}: expected {' '.join(w)!r}")
    if len(head) < 3:
        raise StackFileError(f"{source}: truncated header")
    try:
        layer, n_programs = int(head[1][1][1]), int(head[2][1][1])
    except ValueError:
        raise StackFileError(f"{source}: layer and programs must be integers") from None
    starts = [i for i, ln in enumerate(lines) if ln.startswith("program ")]
    if len(starts) != n_programs:
        raise StackFileError(f"{source}: {len(starts)} programs, the header says "
                             f"{n_programs}")
    out = []
    for k, i in enumerate(starts):
        r = lines[i].split()
        if len(r) != 4 or r[2] != "valve" or r[3] not in VALVE_NUMBER or not r[1].isdigit():
            raise StackFileError(f"{source}:{i + 1}: expected 'program PATH valve "
                                 "part|scaffold'")
        end = starts[k + 1] if k + 1 < len(starts) else len(lines)
        prog = parse_valve_program("\n".join(lines[i + 1:end]),
                                   f"{source}: program {k} (line {i + 2})")
        out.append(LayerProgram(int(r[1]), r[3], prog))
    return layer, out


def write_valve_layer(layer: int, programs: "Sequence[LayerProgram]",
                      path: str | os.PathLike, fmt: str = "bin") -> None:
    """Write every program of a layer into one file (binary or text), atomically."""
    if fmt == "bin":
        data = encode_valve_layer(layer, programs)
    elif fmt == "txt":
        data = format_valve_layer(layer, programs).encode("utf-8")
    else:
        raise FlowError(f"valve layer file format {fmt!r}: expected 'bin' or 'txt'")
    _atomic_write(Path(path), data)


def read_valve_layer(path: str | os.PathLike) -> tuple[int, list[LayerProgram]]:
    """Read a layer file written by :func:`write_valve_layer` (either form, detected)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise StackFileError(f"{path}: valve layer file not found") from None
    if data[:4] == LAYER_MAGIC:
        return decode_valve_layer(data, str(path))
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise StackFileError(f"{path}: neither a binary nor a text valve layer file") from None
    return parse_valve_layer(text, str(path))


# =========================================================================== re-planning


#: Time over which the c-controller's speed-up may change, s: a step in the speed factor
#: f at speed v adds v df / dt of acceleration and v d2f / dt2 of jerk, so the cap ramps.
CAP_RAMP_S = 0.5


def _smooth_cap(cap: np.ndarray, dt: float) -> np.ndarray:
    """The speed-up cap eased into ramps of :data:`CAP_RAMP_S`: a moving minimum over the
    ramp (so it never exceeds the cap) averaged over the same window (so it changes
    gradually)."""
    from scipy.ndimage import minimum_filter1d, uniform_filter1d

    w = max(3, int(round(CAP_RAMP_S / dt)) | 1)
    finite = np.minimum(cap, 10.0)
    low = minimum_filter1d(finite, size=2 * w + 1, mode="nearest")
    return np.minimum(uniform_filter1d(low, size=w, mode="nearest"), finite)


def _retime_within_limits(traj: Trajectory, u: np.ndarray, job: "Job") -> Trajectory:
    """The c-controller's re-timing (:func:`icefab.feedback.retime_trajectory`) with
    speed-ups only where every motion limit still holds: the re-timed path is not planned
    again by MTTS, so speed, acceleration and jerk, Cartesian and per joint, are kept by
    capping the speed-up (:func:`icefab.motion.speedup_cap`) and checked on the result
    (:func:`icefab.motion.limit_ratio`); where the cap's own changes along the path still
    break a limit, the speed-ups are halved until none does (no speed-up at all last)."""
    nominal = min(1.0, float(limit_ratio(traj, job).min()))
    cap = _smooth_cap(speedup_cap(traj, job), float(traj.dt))
    out = traj
    for _ in range(8):
        out = feedback.retime_trajectory(traj, u, max_change=job.feedback.saturation, cap=cap)
        if float(limit_ratio(out, job).min()) >= nominal * (1.0 - 1e-6):
            return out
        cap = 1.0 + 0.5 * (cap - 1.0)
    return feedback.retime_trajectory(traj, u, max_change=job.feedback.saturation,
                                      cap=np.ones(len(traj.xy)))


def replan_valves(trajectories: "Sequence[Trajectory]", job: "Job", *,
                  action: ActionLike = None, layer_thickness: float | None = None
                  ) -> tuple[list[Trajectory], list[ValveProgram]]:
    """Apply a control action to the trajectories of the next n_d layers (thesis 5.1.3).

    trajectories: the deposition (and travel) trajectories of the layers to adjust; the
        material of each is ``traj.path.material`` ("part" when there is no path).
    action: the SMF control action (HeightMap / ControlAction / callable, see
        :func:`valve_frequency`); None: nominal flow.

    ``job.feedback.controller == "flow"`` (nu-controller, default): trajectories are kept,
    flow x (1 + u). ``"speed"`` (c-controller, eq. 5.7-5.10): depositing trajectories are
    re-timed to c_nom / (1 + u) within +-``feedback.saturation`` and every motion limit
    (:func:`_retime_within_limits`)
    (:func:`icefab.feedback.retime_trajectory`) and the valve keeps the nominal flow along
    them, so the volume per mm becomes (1 + u) times nominal. Returns the (possibly
    re-timed) trajectories and their valve programs, in order.
    """

    out_t: list[Trajectory] = []
    out_p: list[ValveProgram] = []
    speed_ctl = job.feedback.controller == "speed" and action is not None
    if isinstance(action, (HeightMap, feedback.ControlAction)):
        action = feedback.action_sampler(action)  # prepare the grid once for all paths
    for traj in trajectories:
        material = traj.path.material if traj.path is not None else "part"
        depositing = traj.path is None or traj.path.depositing
        if speed_ctl and depositing:
            u = _action_values(action, traj, material, job)
            traj = _retime_within_limits(traj, u, job)
            u_new = _action_values(action, traj, material, job)
            prog = plan_valves(traj, material, job, action=u_new,
                               layer_thickness=layer_thickness)
        else:
            prog = plan_valves(traj, material, job, action=action if depositing else None,
                               layer_thickness=layer_thickness)
        out_t.append(traj)
        out_p.append(prog)
    return out_t, out_p
