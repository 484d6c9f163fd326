"""Layer plans of the virtual cell: what one layer deposits and measures, from toolpaths
(:func:`plan_layer`) or trajectories (:func:`plan_layer_motion`), the valve programs the cell
runs for it (:func:`layer_valves`) and which layers are measured.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from icefab import flow
from icefab.config import Job
from icefab.core import (LayerMotion, Toolpath, Trajectory, ValveProgram, arc_lengths,
                         offsets, tour_members, true_runs)
from icefab.errors import SimulationError
from icefab.paths import laser_speed
from icefab.stages import layer_height
from icefab.sim.deposition import (MATERIAL_ID, _TINY_MM, ActionFn, _joints, pulse_drops,
                                   pulse_segments)
from icefab.sim.laser import _refine, laser_positions, uncompensated_latency_s

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class LayerPlan:
    """One layer prepared for the simulator: every deposition segment and laser sample.

    index: toolpaths layer index.
    a, b: (m, 2) float64, mm, segment ends (part coordinates), in deposition order.
    volume: (m,) float64, mm^3, commanded volume of each segment (no control action).
    half_width: (m,) float64, mm.
    material: (m,) int8, 0 part, 1 scaffold.
    n0, n1: (m, 2) float64 unit normals of the cut lines at the segment ends and ext (m,)
        float64 mm, the mitre reach (see :func:`_joints`).
    paths: the deposition paths, in deposition order.
    laser_tagged, laser_true: (k, 2) float64, mm, laser sample positions (empty when the
        layer has no measurement paths).
    thickness: the layer's own thickness, mm (adaptive layers), NaN for the job's.
    trajectories: the deposition trajectories (robot base frame, as planned) when the
        layer was prepared from trajectories (:func:`plan_layer_motion`); the segments are
        then their sample chords, path i being trajectory i. Empty for
        :func:`plan_layer`.
    """

    index: int
    a: np.ndarray
    b: np.ndarray
    volume: np.ndarray
    half_width: np.ndarray
    material: np.ndarray
    n0: np.ndarray
    n1: np.ndarray
    ext: np.ndarray
    paths: tuple[Toolpath, ...] = ()
    laser_tagged: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    laser_true: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    #: The layer's own thickness, mm (adaptive layers); NaN: the job's layer thickness.
    thickness: float = float("nan")
    trajectories: tuple[Trajectory, ...] = ()

    @property
    def midpoints(self) -> np.ndarray:
        return 0.5 * (self.a + self.b)


def plan_layer(index: int, paths: Sequence[Toolpath], job: "Job",
               thickness: float = float("nan")) -> LayerPlan:
    """Cut the deposition paths of one layer into constant-speed segments (see module doc).

    Each boundary/fill path's polyline has its edges split to at most ``speed * dt`` mm
    (speed by role from ``job.motion``); a segment carries ``width * dh * layer_scale *
    length`` mm^3 (eq. 6.2), dh the layer's ``thickness`` (NaN: the job's).
    Measurement paths give the laser sample positions (:func:`laser_positions`).
    """
    m = job.motion
    sim = job.simulation
    dh = layer_height(thickness, job) * job.flow.layer_scale
    pieces: list[tuple[np.ndarray, bool, float, str]] = []
    dep_paths = []
    tag_parts, true_parts = [], []
    for p in paths:
        pts = np.asarray(p.points, dtype=np.float64)
        if len(pts) == 0 or p.role == "travel":
            continue
        if p.frame != "part":
            raise SimulationError(f"layer {index}: {p.material} {p.role} path given in the "
                                  f"{p.frame!r} frame; the simulator needs part-frame paths "
                                  "(as icefab.paths.plan_paths makes them)")
        if not np.isfinite(pts).all():
            raise SimulationError(f"layer {index}: {p.material} {p.role} path has NaN or "
                                  "infinite points")
        if p.role == "measure":
            speed = laser_speed(p.material, job)   # ice slowly, scaffold at full speed
            tg, tr = laser_positions(pts, p.closed, speed_mm_s=speed,
                                     rate_hz=sim.laser_rate_hz,
                                     latency_s=uncompensated_latency_s(job))
            tag_parts.append(tg)
            true_parts.append(tr)
            continue
        if not p.depositing:
            continue
        if p.material not in MATERIAL_ID:
            raise SimulationError(f"layer {index}: unknown material {p.material!r}")
        if p.width == 0 and p.widths is None:
            # no width given: its material's, as the valve programs take it (the two
            # disagreed on the same path, a hunt's)
            p = dataclasses.replace(p, width=flow.material_width(p.material, p.role, job))
        speed = m.boundary_speed_mm_s if p.role == "boundary" else m.fill_speed_mm_s
        # a tour deposits its paths, not its travel (Toolpath.off)
        for q in tour_members(p):
            pts_s = _refine(np.asarray(q.points, dtype=np.float64), q.closed, speed * m.dt_s)
            if len(pts_s) < 2:
                continue
            width: float | np.ndarray = float(q.width)
            if q.widths is not None:   # a variable width: its widths where the points are
                poly = q.polyline()
                width = np.interp(arc_lengths(np.linalg.norm(np.diff(pts_s, axis=0), axis=1)),
                                  arc_lengths(np.linalg.norm(np.diff(poly, axis=0), axis=1)),
                                  q.polyline_widths())
            pieces.append((pts_s, bool(q.closed), width, p.material))
        dep_paths.append(p)
    return _layer_plan(index, pieces, dh, tag_parts, true_parts, paths=tuple(dep_paths),
                       thickness=thickness)


def _layer_plan(index: int, pieces: list[tuple[np.ndarray, bool, float, str]], dh: float,
                tag_parts: list[np.ndarray], true_parts: list[np.ndarray], *,
                paths: tuple[Toolpath, ...], trajectories: tuple = (),
                thickness: float = float("nan")) -> LayerPlan:
    """Segments of a layer from its deposition polylines: ``pieces`` holds (points (k >= 2,
    2) mm part frame, closed, width mm (or (k,) one per point), material) per path, each
    segment carrying the commanded ``width * dh * length`` mm^3 (eq. 6.2, the width at the
    segment's middle); laser samples as given."""
    def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        return np.concatenate(parts) if parts else np.zeros(shape, dtype=dtype)

    a = cat([pts[:-1] for pts, *_ in pieces], (0, 2))
    b = cat([pts[1:] for pts, *_ in pieces], (0, 2))
    counts = [len(pts) - 1 for pts, *_ in pieces]
    starts = offsets(counts)
    w = cat([np.full(c, wd) if np.ndim(wd) == 0 else 0.5 * (wd[:-1] + wd[1:])
             for c, (_, _, wd, _) in zip(counts, pieces)], (0,))
    mat = cat([np.full(c, MATERIAL_ID[m], dtype=np.int8)
               for c, (_, _, _, m) in zip(counts, pieces)], (0,), np.int8)
    hw = 0.5 * w
    n0, n1, ext = _joints(a, b, hw, starts[:-1].copy(),
                          np.asarray([c for _, c, _, _ in pieces], dtype=bool))
    return LayerPlan(index=index, a=a, b=b, volume=w * dh * np.linalg.norm(b - a, axis=1),
                     half_width=hw, material=mat, n0=n0, n1=n1, ext=ext, paths=paths,
                     laser_tagged=cat(tag_parts, (0, 2)),
                     laser_true=cat(true_parts, (0, 2)), trajectories=trajectories,
                     thickness=thickness)




def laser_in_time(xy: np.ndarray, dt: float, rate_hz: float, latency_s: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Laser samples along a measurement trajectory (part frame, every ``dt`` s): every
    ``1 / rate_hz`` s from its start, tagged with the position then and reading where the
    laser was ``latency_s`` earlier (clamped at the start). Returns (tagged, true)."""
    t = np.arange(len(xy)) * dt
    tk = np.arange(int(math.floor(t[-1] * rate_hz + 1e-9)) + 1) / rate_hz

    def at(tq: np.ndarray) -> np.ndarray:
        return np.stack([np.interp(tq, t, xy[:, 0]), np.interp(tq, t, xy[:, 1])], axis=1)

    return at(tk), at(np.maximum(tk - latency_s, 0.0))


def plan_layer_motion(layer: "LayerMotion", job: "Job") -> LayerPlan:
    """One layer of trajectories (``icefab.motion``) prepared for the simulator.

    Deposition trajectories (boundary, fill) are kept for their valve programs; their
    samples, taken to the part frame under the material's nozzle
    (:func:`icefab.flow.trajectory_part_xy`), make the segments (repeated samples where
    the robot rests dropped), each with the commanded volume ``width * dh * layer_scale *
    length`` (eq. 6.2: the figure for ``deposition = "flow"`` and for the commanded
    total). Measurement trajectories give the laser samples in time
    (``simulation.laser_rate_hz``, latency). Travel is skipped.
    """

    sim = job.simulation
    dh = layer_height(layer.thickness, job) * job.flow.layer_scale
    pieces: list[tuple[np.ndarray, bool, float, str]] = []
    dep, tag_parts, true_parts = [], [], []
    for k, traj in enumerate(layer.trajectories):
        p = traj.path
        xy = np.asarray(traj.xy, dtype=np.float64)
        if p is None:
            raise SimulationError(f"layer {layer.index}: trajectory {k} has no path, so no "
                                  "material or role; plan it from a Path")
        if len(xy) == 0 or p.role == "travel":
            continue
        if xy.ndim != 2 or xy.shape[1] != 2 or not np.isfinite(xy).all():
            raise SimulationError(f"layer {layer.index}: {p.material} {p.role} trajectory {k} "
                                  "has NaN, infinite or malformed samples")
        if not traj.dt > 0:
            raise SimulationError(f"layer {layer.index}: trajectory {k} has time step "
                                  f"{traj.dt} s; expected > 0")
        if p.material not in MATERIAL_ID:
            raise SimulationError(f"layer {layer.index}: unknown material {p.material!r}")
        if p.role == "measure":
            part_xy = flow.trajectory_part_xy(traj, p.tool_name, job)  # under the laser
            tg, tr = laser_in_time(part_xy, float(traj.dt), sim.laser_rate_hz,
                                    uncompensated_latency_s(job))
            tag_parts.append(tg)
            true_parts.append(tr)
            continue
        if not p.depositing:
            continue
        xy_all = flow.trajectory_part_xy(traj, p.material, job)
        w_all = flow.sample_widths(traj, p.material, job)
        for t, width in on_stretches(traj, w_all, p.material, job):   # a tour: not its travel
            pts = flow.positions_at(xy_all, float(traj.dt), t)
            if len(pts) > 1:
                step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
                moved = np.concatenate([[True], step > _TINY_MM])
                pts, width = pts[moved], width[moved]
            if len(pts) < 2:
                pts = np.vstack([pts[:1], pts[:1]])  # at rest: a w x w square, no volume
                width = np.concatenate([width[:1], width[:1]])
            closed = bool(len(pts) > 2 and np.linalg.norm(pts[-1] - pts[0]) <= 1e-6)
            pieces.append((pts, closed, width, p.material))
        dep.append(traj)
    return _layer_plan(layer.index, pieces, dh, tag_parts, true_parts,
                       paths=tuple(t.path for t in dep), trajectories=tuple(dep),
                       thickness=layer.thickness)




@dataclass(frozen=True, eq=False)
class LayerValves:
    """The valve programs of one layer, as the cell runs them (thesis Ch. 6, 5.1.3).

    trajectories: the deposition trajectories (re-timed by the c-controller when
        ``feedback.controller = "speed"``); programs: their valve programs, in order;
    action: the control action they were planned with (None: nominal flow).
    """

    trajectories: tuple[Trajectory, ...]
    programs: tuple["ValveProgram", ...]
    action: ActionFn | None = None
    #: The layer's own thickness, mm (adaptive layers); NaN: the job's.
    thickness: float = float("nan")


def _finite(action: ActionFn) -> ActionFn:
    """The action with NaN/inf read as 0 (no correction), as the flow mode does."""
    def u(xy: np.ndarray) -> np.ndarray:
        v = np.asarray(action(xy), dtype=np.float64).reshape(-1)
        return np.where(np.isfinite(v), v, 0.0)
    return u


def layer_valves(plan: LayerPlan, job: "Job", action: ActionFn | None = None) -> LayerValves:
    """Plan (or re-plan, with the control action) the valve programs of one layer.

    ``plan`` from :func:`plan_layer_motion`; the programs come from
    :func:`icefab.flow.replan_valves` (nu-controller: flow x (1 + u); c-controller:
    re-timed trajectories at nominal flow per mm x (1 + u)).
    """

    u = None if action is None else _finite(action)
    trajs, progs = flow.replan_valves(plan.trajectories, job, action=u,
                                      layer_thickness=layer_height(plan.thickness, job))
    return LayerValves(trajectories=tuple(trajs), programs=tuple(progs), action=u,
                       thickness=plan.thickness)


def valve_segments(valves: LayerValves, job: "Job") -> tuple:
    """The deposition segments of a layer's valve pulses (:func:`pulse_segments`).

    Returns a, b (m, 2), volume (m,) mm^3 (drops as commanded, before the simulated flow
    gain), half width (m,), material (m,) int8, n0, n1, ext, and the number of pulses.
    """

    xs, dts, ts, drops, widths, mats = [], [], [], [], [], []
    for traj, prog in zip(valves.trajectories, valves.programs):
        p = traj.path
        if p is None or not p.depositing:
            continue
        freq = flow.valve_frequency(traj, p.material, job, action=valves.action,
                                    layer_thickness=layer_height(valves.thickness, job)) \
            if prog.widths_us is None else None
        t, d = pulse_drops(prog, freq, p.material, job)
        xy = flow.trajectory_part_xy(traj, p.material, job)
        w = flow.sample_widths(traj, p.material, job)
        # a tour's stretches apart: a drop's strip never reaches over the travel between
        for times, wk in on_stretches(traj, w, p.material, job):
            t0 = float(times[0])
            inside = (t >= t0 - 1e-12) & (t <= float(times[-1]) + 1e-12)
            xs.append(flow.positions_at(xy, float(traj.dt), times))
            dts.append(times - t0)
            ts.append(t[inside] - t0)
            drops.append(d[inside])
            widths.append(wk)
            mats.append(MATERIAL_ID[p.material])
            t, d = t[~inside], d[~inside]
    a, b, vol, hw, owner, n0, n1, ext = pulse_segments(xs, dts, ts, drops, widths)
    material = np.asarray(mats, dtype=np.int8)[owner] if len(owner) else \
        np.zeros(0, dtype=np.int8)
    return a, b, vol, hw, material, n0, n1, ext, int(sum(len(t) for t in ts))


def on_stretches(traj: Trajectory, widths: np.ndarray, material: str, job: "Job"
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Where a trajectory deposits, as ``(t (k,) s from its start, widths (k,) mm)`` per
    stretch: a continuous tour's spans (:attr:`~icefab.core.Trajectory.on_spans`) from the
    exact instant its valve opens to the one it closes, the samples between (the ends as
    wide as the nearest sample inside, or the path when none is); without spans the sample
    runs of :func:`on_runs` (a whole path, or a tour from a file before version 6)."""
    lay = flow.span_layout(traj)
    if lay is None:
        dt = float(traj.dt)
        return [(np.arange(a, b + 1) * dt, widths[a:b + 1]) for a, b in on_runs(widths)]
    w = lay.laid_out(widths, lay.end_widths(widths, flow.trajectory_width(traj, material,
                                                                         job)))
    return [(lay.t[a:b], w[a:b]) for a, b in zip(lay.start[:-1].tolist(),
                                                   lay.start[1:].tolist())]


def on_runs(widths: np.ndarray) -> list[tuple[int, int]]:
    """The sample ranges ``(first, last)`` (inclusive) of a trajectory that deposit: every
    segment between two samples of which one is wider than 0 (a tour's travel is 0 wide,
    :attr:`icefab.core.Toolpath.off`); the whole trajectory when no two consecutive
    samples are 0 wide (a single sample: ``[(0, 0)]``)."""
    w = np.asarray(widths)
    if len(w) < 2:
        return [(0, len(w) - 1)] if len(w) else []
    on = (w[:-1] > 0) | (w[1:] > 0)
    if on.all():
        return [(0, len(w) - 1)]
    return true_runs(on)     # segments a .. b - 1: samples a .. b


def _measured(has_laser: Sequence[bool], interval_layers: int) -> list[int]:
    with_paths = [j for j, h in enumerate(has_laser) if h]
    if with_paths:
        return with_paths
    return [j for j in range(len(has_laser)) if (j + 1) % interval_layers == 0]


def measurement_layers(plans: Sequence[LayerPlan], interval_layers: int) -> list[int]:
    """Positions in ``plans`` after which the surface is measured.

    The layers that carry measurement paths when any does (``icefab.paths`` adds them every
    ``job.feedback.interval_layers`` layers); otherwise every ``interval_layers``-th layer
    (the laser then reads along that layer's deposition paths).
    """
    return _measured([len(p.laser_tagged) > 0 for p in plans], interval_layers)
