"""The virtual cell: a build simulator for surface mapping feedback (thesis 5.3, 5.6-5.7).

What it models
--------------
* **Deposition.** The part and the scaffold share one height map ``z (ny, nx)`` on a fine
  grid (``job.simulation.grid_mm``). Every deposition path is cut into segments; a segment
  spreads its volume uniformly over the piece of strip of the path width that it sweeps,
  cut at its ends on the bisectors of its joints (mitre joins), so a path leaves an even
  strip without overlaps or gaps at its corners. Each cell gets the exact area of its
  overlap (polygon clipping, numba) and the weights are normalised per segment, so the
  volume is conserved to rounding. A straight path deposited with flow ``q`` at speed
  ``v`` leaves a strip of width ``w`` and height ``q / (w v)``.
* **Commanded volume** (``job.simulation.deposition = "flow"``, the default: an ideal
  valve). With variable-flow valve control the valve follows the speed so that the volume
  per millimetre is ``w * dh * c`` (thesis eq. 6.2, ``c`` = ``job.flow.layer_scale``),
  whatever the speed profile. This mode therefore does not need the trajectories: it
  follows each path's own polyline (what the robot follows),
  with every edge longer than one time step at the constant speed of its role (boundary
  ``job.motion.boundary_speed_mm_s``, fill ``job.motion.fill_speed_mm_s``, times
  ``job.motion.dt_s``) split, so that the control action is applied at least once per
  time step, and gives each segment the volume ``w * dh * c * length``. (Sampling the
  paths themselves at dt instead would deposit along 2 mm chords whose seams between
  neighbouring rings leave systematic gaps that grow layer after layer.)
* **Valve pulses** (``job.simulation.deposition = "valves"``, thesis Ch. 6): the build
  runs as the cell runs it, on its minimum-time trajectories (``icefab.motion``, variable
  speed, at rest at split corners; planned here from toolpaths, or read from a
  ``trajectories.npz``) and their valve programs (:func:`icefab.flow.replan_valves`: the
  frequency follows the speed, eq. 6.2-6.6, pulse instants in 2 ms ticks, the control
  action applied). Each pulse drops the calibrated volume per pulse at its frequency
  (``Q / nu`` from the table nu = h(Q); PWM: in proportion to the pulse width) at the
  nozzle's position at the pulse instant (the trajectory interpolated in time), and the
  drop is spread over the path width along the strip between the midpoints to its
  neighbouring drops (:func:`deposit_pulses`): drops evenly spaced along the path leave
  an even strip, crowded drops a higher one. So pulse quantisation (whole pulses, 2 ms
  ticks) at variable speed shows in the surface.
* **Liquid flow.** Before it freezes, the liquid of a layer flows downhill over the frozen
  surface for a diffusion length ``spread_mm`` (:func:`level_liquid`): it fills gaps
  between paths narrower than about twice that and evens out single drops, but does not
  run off the footprint.
* **Disturbances** (thesis 5.6, eq. 5.29), drawn from ``job.simulation.seed`` so an
  open-loop and a closed-loop run see the same ones: the actual flow is the commanded flow
  times ``(1 + flow_error) * (1 + flow_drift_per_cm3 * V)``, ``V`` the volume in cm^3 that
  valve has already deposited (the thesis saw up to +20 %, Ch. 6.4; the setting's name is
  kept for compatibility, its unit is per cm^3; with valve pulses it multiplies every
  drop); correlated random height noise per layer; debris pulses (Gaussian bumps, Poisson
  number per layer); weaker deposition within one path width of the free edges of each
  layer's deposit (``edge_loss``: the outer rim and the holes of the merged part +
  scaffold footprint; not the part/scaffold interface).
* **Laser** (thesis 5.2.1): samples at ``laser_rate_hz`` along the measurement paths at the
  measurement speed (along the measurement trajectories, in time, when the build runs on
  trajectories), with Gaussian noise and an uncompensated latency: a sample tagged with
  the position at time ``t`` reads the surface where the laser was at ``t - latency``.
* **Control** (thesis 5.1.3, 5.2.2): with ``deposition = "flow"`` the nu-controller
  scales the flow of every segment by ``1 + u`` evaluated at the segment's midpoint, and
  the c-controller (speed ``1 / (1 + u)``, the same volume per millimetre) gives the same
  surface. With ``"valves"`` the action goes where the cell puts it: after each
  measurement the valve programs of the next n_d layers are re-planned with it
  (:func:`icefab.flow.replan_valves`: flow x (1 + u), or re-timed trajectories for the
  c-controller), and the surface gets what their pulses deliver.

The core (:func:`deposit`, :func:`deposit_pulses`, :func:`laser_measure`,
:func:`run_cell`) works on plain arrays and a controller callable; :func:`simulate_build`
prepares a ``Toolpaths`` or a ``BuildMotion`` (:func:`plan_layer`,
:func:`plan_layer_motion`) and, for closed loop, plugs in the surface mapping feedback of
:mod:`icefab.feedback`.

Heights are measured from the build platform (z = 0 before the first simulated layer); the
nominal top of the j-th simulated layer (j = 0, 1, ...) is ``(j + 1) * dh``.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np
from numba import njit
from scipy import ndimage

from icefab.errors import GeometryError, SimulationError
from icefab.core import HeightMap, LayerPaths, Toolpath, Toolpaths, Trajectory
from icefab.workload import check_grid

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job
    from icefab.flow import FrequencyPlan
    from icefab.motion import BuildMotion, LayerMotion
    from icefab.core import ValveProgram

log = logging.getLogger(__name__)

MATERIAL_ID = {"part": 0, "scaffold": 1}

# u(xy) for (n, 2) points -> (n,) control action (fraction, 0 = nominal)
ActionFn = Callable[[np.ndarray], np.ndarray]


# --------------------------------------------------------------------------- deposition


@njit(cache=True)
def _clip_area(px, py, qx, qy, n, la, lb, lc):  # pragma: no cover - numba
    """Area of the convex polygon (px, py)[:n] cut by the half-planes la x + lb y <= lc.

    Sutherland-Hodgman clipping, one half-plane after another, ping-ponging between the
    buffers p and q (each long enough for n + number of planes vertices).
    """
    for k in range(la.shape[0]):
        m = 0
        for i in range(n):
            j = (i + 1) % n
            vi = la[k] * px[i] + lb[k] * py[i] - lc[k]
            vj = la[k] * px[j] + lb[k] * py[j] - lc[k]
            if vi <= 0.0:
                qx[m] = px[i]
                qy[m] = py[i]
                m += 1
            if (vi < 0.0 < vj) or (vj < 0.0 < vi):
                t = vi / (vi - vj)
                qx[m] = px[i] + t * (px[j] - px[i])
                qy[m] = py[i] + t * (py[j] - py[i])
                m += 1
        n = m
        if n < 3:
            return 0.0
        for i in range(n):
            px[i] = qx[i]
            py[i] = qy[i]
    area = 0.0
    for i in range(n):
        j = (i + 1) % n
        area += px[i] * py[j] - px[j] * py[i]
    return 0.5 * abs(area)


@njit(cache=True)
def _splat_segments(z, ox, oy, g, ax, ay, bx, by, vol, half_w, n0, n1,
                    ext):  # pragma: no cover - numba
    """Add each segment's volume to ``z`` over the strip it sweeps (see :func:`deposit`).

    The strip of segment s is the band ``|across| <= half_w`` cut at its ends by the lines
    through ``a`` with normal ``n0`` and through ``b`` with normal ``n1`` (the bisectors at
    the joints with the previous/next segment: mitre joins, so consecutive strips tile
    without gap or overlap; the segment direction at free ends: butt ends). ``ext`` is how
    far (mm) a mitre may reach beyond the segment ends; a zero-length segment covers a
    w x w square. A cell's weight is the exact area of its intersection with that shape
    (polygon clipping), and the weights are normalised by their sum over the unclipped
    bounding box, so cells outside the map only take their share away (volume outside the
    map is lost, nothing else moves). Returns the lost volume.
    """
    ny, nx = z.shape
    lost = 0.0
    hg = 0.5 * g
    la = np.empty(4)
    lb = np.empty(4)
    lc = np.empty(4)
    px = np.empty(16)
    py = np.empty(16)
    qx = np.empty(16)
    qy = np.empty(16)
    full = g * g
    buf = np.empty(1024)
    for s in range(vol.shape[0]):
        v = vol[s]
        if v == 0.0:
            continue
        hw = half_w[s]
        dx = bx[s] - ax[s]
        dy = by[s] - ay[s]
        length = math.sqrt(dx * dx + dy * dy)
        point = length < 1e-12
        if point:
            ux, uy = 1.0, 0.0
        else:
            ux, uy = dx / length, dy / length
        # half-planes la x + lb y <= lc, coordinates relative to a
        la[0], lb[0], lc[0] = -uy, ux, hw          # across <= hw
        la[1], lb[1], lc[1] = uy, -ux, hw          # -across <= hw
        if point:
            la[2], lb[2], lc[2] = -1.0, 0.0, hw
            la[3], lb[3], lc[3] = 1.0, 0.0, hw
        else:
            la[2], lb[2], lc[2] = -n0[s, 0], -n0[s, 1], 0.0
            la[3], lb[3], lc[3] = n1[s, 0], n1[s, 1], n1[s, 0] * dx + n1[s, 1] * dy
        reach = hw + g + (hw if point else ext[s])
        j0 = int(math.floor((min(ax[s], bx[s]) - reach - ox) / g))
        j1 = int(math.ceil((max(ax[s], bx[s]) + reach - ox) / g))
        i0 = int(math.floor((min(ay[s], by[s]) - reach - oy) / g))
        i1 = int(math.ceil((max(ay[s], by[s]) + reach - oy) / g))
        nj = j1 - j0 + 1
        if (i1 - i0 + 1) * nj > buf.shape[0]:
            buf = np.empty(2 * (i1 - i0 + 1) * nj)
        total = 0.0
        for i in range(i0, i1 + 1):
            cy = oy + i * g - ay[s]
            row = (i - i0) * nj
            for j in range(j0, j1 + 1):
                cx = ox + j * g - ax[s]
                cut = False
                empty = False
                for k in range(4):
                    vc = la[k] * cx + lb[k] * cy - lc[k]
                    spread = hg * (abs(la[k]) + abs(lb[k]))
                    if vc - spread >= 0.0:
                        empty = True
                        break
                    if vc + spread > 0.0:
                        cut = True
                w = 0.0
                if not empty:
                    if cut:
                        px[0], py[0] = cx - hg, cy - hg
                        px[1], py[1] = cx + hg, cy - hg
                        px[2], py[2] = cx + hg, cy + hg
                        px[3], py[3] = cx - hg, cy + hg
                        w = _clip_area(px, py, qx, qy, 4, la, lb, lc)
                    else:
                        w = full
                buf[row + j - j0] = w
                total += w
        if total <= 0.0:
            continue
        scale = v / (total * full)
        inside = 0.0
        for i in range(max(i0, 0), min(i1, ny - 1) + 1):
            row = (i - i0) * nj
            for j in range(max(j0, 0), min(j1, nx - 1) + 1):
                w = buf[row + j - j0]
                if w > 0.0:
                    z[i, j] += w * scale
                    inside += w
        if total > 0.0:
            lost += v * (1.0 - inside / total)
    return lost


# Joints turning by more than this (cosine of the turn below -0.5, i.e. > 120 deg) get butt
# ends instead of a mitre, so a mitre never reaches more than tan(60 deg) half widths.
_MITRE_MIN_COS = -0.5


def _joints(a: np.ndarray, b: np.ndarray, half_w: np.ndarray, starts: np.ndarray,
            closed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut lines at the ends of consecutive segments (mitre joins, butt free ends).

    a, b: (m, 2) segment ends; segments of one path are consecutive, path p starts at
    segment ``starts[p]``; ``closed[p]`` joins its last segment to its first.
    Returns n0, n1 (m, 2) unit normals of the start and end cut lines and ext (m,) how far a
    mitre reaches beyond the segment ends, mm.
    """
    m = len(a)
    d = b - a
    length = np.linalg.norm(d, axis=1)
    u = np.divide(d, length[:, None], out=np.zeros_like(d), where=length[:, None] > 0)
    ends = np.append(starts[1:], m) if len(starts) else starts
    prev = np.arange(m) - 1
    nxt = np.arange(m) + 1
    prev[starts] = np.where(closed, ends - 1, -1)
    nxt[ends - 1] = np.where(closed, starts, -1)
    n0, e0 = _bisector(u, prev)
    n1, e1 = _bisector(u, nxt)
    return n0, n1, half_w * np.maximum(e0, e1)


def _bisector(u: np.ndarray, other: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normal of the cut between each segment and ``other`` (-1: none), and tan(turn / 2)."""
    uo = np.where(other[:, None] >= 0, u[np.maximum(other, 0)], 0.0)
    cos = np.einsum("ij,ij->i", u, uo)
    mitre = (other >= 0) & (cos > _MITRE_MIN_COS) & np.any(uo != 0, axis=1)
    nsum = u + uo
    norm = np.linalg.norm(nsum, axis=1)
    n = np.where(mitre[:, None], nsum / np.where(norm > 0, norm, 1.0)[:, None], u)
    ratio = np.divide(1 - cos, 1 + cos, out=np.zeros_like(cos), where=mitre)
    tan_half = np.sqrt(np.clip(ratio, 0.0, None))
    return np.ascontiguousarray(n), tan_half


def _segments(xy: np.ndarray, volume: np.ndarray, width: np.ndarray, starts: np.ndarray,
              closed: np.ndarray) -> tuple[np.ndarray, ...]:
    """Samples -> segments: sample i deposits ``volume[i]`` along xy[i] -> xy[i + 1].

    ``starts`` are the first sample of each path. The last sample of a closed path deposits
    along the closing segment back to the path's first sample; that of an open path has
    no successor and deposits on a w x w square around it.
    Returns a (n, 2), b (n, 2), volume (n,), half width (n,), n0, n1, ext (:func:`_joints`).
    """
    n = len(xy)
    ends = np.append(starts[1:], n)
    nxt = np.arange(1, n + 1)
    nxt[ends - 1] = np.where(closed, starts, ends - 1)
    b = xy[nxt]
    hw = 0.5 * width
    n0, n1, ext = _joints(xy, b, hw, starts, closed)
    return xy, b, volume, hw, n0, n1, ext


def deposit(surface: HeightMap, xy: np.ndarray, volume: np.ndarray,
            width: float | np.ndarray, *, path_starts: Sequence[int] | None = None,
            closed: bool | Sequence[bool] = False) -> HeightMap:
    """Deposit material along sampled paths onto a height map.

    surface: the current surface; its ``z`` must be finite (ny, nx) float64, mm.
    xy: (n, 2) float64, mm, sample points of one or more paths, in deposition order.
    volume: (n,) float64, mm^3; ``volume[i]`` is deposited uniformly over the strip of
        width ``width`` swept from ``xy[i]`` to ``xy[i + 1]`` (for the last sample of a
        path: back to its first sample when closed, else a w x w square). Consecutive
        strips meet on the bisector of their joint (mitre; butt ends at turns sharper
        than 120 deg), so a polyline leaves a strip without gaps or overlaps at its
        corners.
    width: path width, mm, scalar or (n,) per sample.
    path_starts: index of the first sample of each path (default: one path).
    closed: per path (or one for all), whether it returns to its first sample (which is
        not repeated, as in :class:`~icefab.core.Toolpath`).

    Returns a new HeightMap with the deposited heights added. The added volume (sum of
    height increments x cell area) equals ``volume.sum()`` to rounding unless the strip
    reaches past the edge of the map, where the part outside is lost.
    """
    xy = np.ascontiguousarray(xy, dtype=np.float64)
    volume = np.ascontiguousarray(volume, dtype=np.float64)
    n = len(xy)
    if xy.ndim != 2 or xy.shape[1] != 2 or volume.shape != (n,):
        raise SimulationError(f"deposit: xy must be (n, 2) and volume (n,), got {xy.shape} "
                              f"and {volume.shape}")
    width_arr = np.broadcast_to(np.asarray(width, dtype=np.float64), (n,)).copy()
    if not (np.isfinite(xy).all() and np.isfinite(volume).all()
            and np.all(width_arr > 0)):
        raise SimulationError("deposit: xy and volume must be finite and width > 0")
    z = np.array(surface.z, dtype=np.float64, copy=True)
    if n:
        starts = np.asarray([0] if path_starts is None else path_starts, dtype=np.int64)
        if starts.ndim != 1 or len(starts) == 0 or starts[0] != 0 or \
                np.any(np.diff(starts) <= 0) or starts[-1] >= n:
            raise SimulationError(f"deposit: path_starts must increase from 0 below {n}, "
                                  f"got {starts.tolist()}")
        closed_arr = np.broadcast_to(np.asarray(closed, dtype=bool), starts.shape)
        _splat(z, surface.origin, surface.spacing,
               *_segments(xy, volume, width_arr, starts, closed_arr))
    return HeightMap(origin=np.asarray(surface.origin, dtype=np.float64),
                     spacing=float(surface.spacing), z=z)


def _splat(z: np.ndarray, origin: np.ndarray, spacing: float, a: np.ndarray, b: np.ndarray,
           vol: np.ndarray, half_w: np.ndarray, n0: np.ndarray, n1: np.ndarray,
           ext: np.ndarray) -> float:
    """In-place core of :func:`deposit` on segments; returns the volume lost off the map."""
    c = np.ascontiguousarray
    return float(_splat_segments(z, float(origin[0]), float(origin[1]), float(spacing),
                                 c(a[:, 0]), c(a[:, 1]), c(b[:, 0]), c(b[:, 1]),
                                 c(vol, dtype=np.float64), c(half_w, dtype=np.float64),
                                 c(n0), c(n1), c(ext, dtype=np.float64)))


def empty_surface(lo: np.ndarray, hi: np.ndarray, spacing: float, margin: float = 0.0
                  ) -> HeightMap:
    """A flat (z = 0) height map covering the box ``lo``-``hi`` (mm) plus ``margin``."""
    lo = np.asarray(lo, dtype=np.float64) - margin
    hi = np.asarray(hi, dtype=np.float64) + margin
    if not (spacing > 0 and np.all(hi >= lo)):
        raise SimulationError(f"empty_surface: need spacing > 0 and hi >= lo, got spacing "
                              f"{spacing}, lo {lo}, hi {hi}")
    nx = int(math.floor((hi[0] - lo[0]) / spacing)) + 2
    ny = int(math.floor((hi[1] - lo[1]) / spacing)) + 2
    return HeightMap(origin=lo, spacing=float(spacing), z=np.zeros((ny, nx)))


_TINY_MM = 1e-9  # shorter steps along a path are the same point, mm


def _pulse_segments(xy: np.ndarray, dt: float, pulse_t: np.ndarray, drop: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Drops of one trajectory as deposition segments (see :func:`deposit_pulses`).

    Returns a, b (m, 2) segment ends along the followed polyline (repeated samples
    dropped, so corners keep their mitre), vol (m,) mm^3, (at (k, 2), at_vol (k,)): the
    positions and volumes of drops that own no length of path (three or more at one
    place, or a trajectory that does not move), and whether the polyline returns to its
    start (closed).
    """
    xy = np.asarray(xy, dtype=np.float64)
    n = len(xy)
    p = len(pulse_t)
    none = np.zeros((0, 2))
    if p == 0 or n == 0:
        return none, none, np.zeros(0), (none, np.zeros(0)), False
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    S = np.concatenate([[0.0], np.cumsum(seg)])
    length = float(S[-1])
    if length <= _TINY_MM:
        return none, none, np.zeros(0), (np.repeat(xy[:1], p, axis=0), drop.copy()), False
    # where the nozzle is at each pulse instant: arc length at that time (thesis 6.2)
    s_p = np.interp(pulse_t, np.arange(n) * dt, S)
    bounds = np.concatenate([[0.0], 0.5 * (s_p[:-1] + s_p[1:]), [length]])
    keep = np.concatenate([[True], seg > _TINY_MM])
    poly, s_v = xy[keep], S[keep]
    cuts = np.unique(np.concatenate([s_v, bounds]))
    cuts = cuts[np.concatenate([[True], np.diff(cuts) > _TINY_MM])]
    cuts[-1] = length
    lens = np.diff(cuts)
    owner = np.clip(np.searchsorted(bounds, 0.5 * (cuts[:-1] + cuts[1:]), side="right") - 1,
                    0, p - 1)
    strip = bounds[owner + 1] - bounds[owner]
    vol = drop[owner] * np.divide(lens, strip, out=np.zeros_like(lens), where=strip > 0)
    pts = _at(poly, s_v, cuts)
    # drops whose strip is (nearly) empty keep their volume as a w x w square
    rest = drop - np.bincount(owner, weights=vol, minlength=p)
    lone = rest > 1e-9 * np.maximum(drop, 1e-300)
    at = _at(poly, s_v, s_p[lone]) if lone.any() else none
    closed = bool(np.linalg.norm(xy[-1] - xy[0]) <= 1e-6)
    return pts[:-1], pts[1:], vol, (at, rest[lone]), closed


def pulse_segments(xy: Sequence[np.ndarray], dt: Sequence[float],
                   pulse_times_s: Sequence[np.ndarray], drop_mm3: Sequence[np.ndarray],
                   width: Sequence[float]) -> tuple[np.ndarray, ...]:
    """Deposition segments of many trajectories' valve pulses (see :func:`deposit_pulses`).

    Per trajectory i: ``xy[i] (n_i, 2)`` mm part-frame nozzle positions every ``dt[i]`` s,
    pulse instants ``pulse_times_s[i] (p_i,)`` s from its start, drop volumes
    ``drop_mm3[i] (p_i,)``, path width ``width[i]`` mm.
    Returns a (m, 2), b (m, 2), volume (m,) mm^3, half width (m,) mm, owner (m,) int64
    (the trajectory each segment comes from), n0, n1, ext (:func:`_joints`), in the
    trajectories' order.
    """
    a_l, b_l, v_l, hw_l, own_l, starts, closed = [], [], [], [], [], [], []
    count = 0
    for i, (pts, step, t, drop, w) in enumerate(zip(xy, dt, pulse_times_s, drop_mm3, width)):
        a, b, vol, (at, at_vol), cl = _pulse_segments(pts, float(step),
                                                       np.asarray(t, dtype=np.float64),
                                                       np.asarray(drop, dtype=np.float64))
        pieces = [(a, b, vol, cl)] if len(a) else []
        # lone drops: a zero-length segment each, a path of its own (w x w square)
        pieces += [(at[k:k + 1], at[k:k + 1], at_vol[k:k + 1], False) for k in range(len(at))]
        for pa, pb, pv, pc in pieces:
            starts.append(count)
            closed.append(pc)
            count += len(pa)
            a_l.append(pa)
            b_l.append(pb)
            v_l.append(pv)
            hw_l.append(np.full(len(pa), 0.5 * float(w)))
            own_l.append(np.full(len(pa), i, dtype=np.int64))
    if not a_l:
        z2, z1 = np.zeros((0, 2)), np.zeros(0)
        return z2, z2, z1, z1, np.zeros(0, dtype=np.int64), z2, z2, z1
    a, b, hw = np.concatenate(a_l), np.concatenate(b_l), np.concatenate(hw_l)
    n0, n1, ext = _joints(a, b, hw, np.asarray(starts, dtype=np.int64),
                          np.asarray(closed, dtype=bool))
    return a, b, np.concatenate(v_l), hw, np.concatenate(own_l), n0, n1, ext


def deposit_pulses(surface: HeightMap, xy: np.ndarray, dt: float, pulse_times_s: np.ndarray,
                   drop_mm3: float | np.ndarray, width: float) -> HeightMap:
    """Deposit the drops of one valve program along one trajectory onto a height map.

    surface: the current surface (finite ``z``).
    xy: (n, 2) float64, mm, nozzle positions in the part frame every ``dt`` s (a
        :class:`~icefab.core.Trajectory` through :func:`icefab.flow.trajectory_part_xy`).
    pulse_times_s: (p,) float64, s, non-decreasing pulse instants from the trajectory start
        (:func:`icefab.flow.pulse_times`).
    drop_mm3: volume of each drop, mm^3, scalar or (p,) (:func:`pulse_drops`).
    width: path width, mm.

    Each drop lands where the nozzle is at its instant (the trajectory interpolated in
    time) and is spread over the path width along its share of the path: from the
    midpoint to the previous drop to the midpoint to the next (the first from the
    trajectory's start, the last to its end), cut into pieces at the polyline's vertices
    and laid down with the strip kernel of :func:`deposit` (mitre joins; a trajectory
    ending where it starts is closed). Drops evenly spaced along the path give a strip of
    even height, ``drop / (width * spacing)``; drops that own no length of path (three
    at one place) cover a w x w square. The added volume is the sum of the drops.
    """
    pulse_t = np.asarray(pulse_times_s, dtype=np.float64).reshape(-1)
    drop = np.broadcast_to(np.asarray(drop_mm3, dtype=np.float64), pulse_t.shape).copy()
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or not (dt > 0 and width > 0) \
            or not (np.isfinite(xy).all() and np.isfinite(pulse_t).all()
                    and np.isfinite(drop).all()) or np.any(np.diff(pulse_t) < 0):
        raise SimulationError("deposit_pulses: need xy (n, 2) finite, dt > 0, width > 0 and "
                              "finite, non-decreasing pulse times")
    a, b, vol, hw, _, n0, n1, ext = pulse_segments([xy], [dt], [pulse_t], [drop], [width])
    z = np.array(surface.z, dtype=np.float64, copy=True)
    if len(a):
        _splat(z, surface.origin, surface.spacing, a, b, vol, hw, n0, n1, ext)
    return HeightMap(origin=np.asarray(surface.origin, dtype=np.float64),
                     spacing=float(surface.spacing), z=z)


def pulse_drops(program: "ValveProgram", frequency: "FrequencyPlan | None",
                material: str, job: "Job") -> tuple[np.ndarray, np.ndarray]:
    """Pulse instants of a valve program and the volume each pulse drops (thesis 6.1).

    program: from :func:`icefab.flow.plan_valves` / ``replan_valves``; frequency: the
        commanded signal along the same trajectory (:func:`icefab.flow.valve_frequency`,
        same action); needed in FM mode only.
    Returns (t (p,) float64 s from the trajectory start, volume (p,) float64 mm^3).
    FM: a pulse at frequency nu (the commanded frequency at its instant) drops the
    calibrated volume per pulse ``Q(nu) / nu`` of the material's table (below the table's
    first non-zero frequency: its slope there). PWM: ``Q(f) / f`` at the PWM frequency
    scaled by ``width / flow.calibration_pulse_ms``. The simulated flow gain is applied
    by the caller.
    """
    from icefab import flow

    t = flow.pulse_times(program)
    if len(t) == 0:
        return t, np.zeros(0)
    cal = flow.calibration_for(material, job)
    if program.widths_us is None:
        if frequency is None:
            raise SimulationError("pulse_drops: an FM program needs its frequency plan")
        nu = np.interp(t, frequency.t, frequency.nu)
        pos = cal.frequency_hz[cal.frequency_hz > 0]
        floor = 1e-6 * float(pos[0]) if len(pos) else 1e-9
        nu = np.maximum(nu, floor)
        return t, cal.flow(nu) / nu
    f = job.flow.pwm_frequency_hz
    per_pulse = float(cal.flow(np.array([f]))[0]) / f
    widths_ms = np.concatenate([pc.widths_us for pc in flow.program_pieces(program)]
                               ).astype(np.float64) / 1000.0
    return t, per_pulse * widths_ms / job.flow.calibration_pulse_ms


# --------------------------------------------------------------------------- laser


def sample_surface(surface: HeightMap, xy: np.ndarray) -> np.ndarray:
    """Bilinear height of ``surface`` at (n, 2) points (mm); edge values beyond the map."""
    g = surface.spacing
    coords = np.stack([(xy[:, 1] - surface.origin[1]) / g, (xy[:, 0] - surface.origin[0]) / g])
    return ndimage.map_coordinates(surface.z, coords, order=1, mode="nearest")


def _resample(points: np.ndarray, closed: bool, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``spacing`` mm along a polyline: (k, 2) points and (k,) arc length."""
    poly = np.vstack([points, points[:1]]) if closed and len(points) > 1 else points
    if len(poly) < 2:
        return poly.copy(), np.zeros(len(poly))
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    if total <= 0:
        return poly[:1].copy(), np.zeros(1)
    k = max(1, int(math.ceil(total / spacing - 1e-9)))
    t = np.linspace(0.0, total, k + 1)
    return _at(poly, s, t), t


def _refine(points: np.ndarray, closed: bool, max_step: float) -> np.ndarray:
    """The polyline of a path (closed: first point repeated at the end) with every edge
    longer than ``max_step`` split into equal parts, repeated points dropped."""
    poly = np.vstack([points, points[:1]]) if closed and len(points) > 1 else points
    if len(poly) < 2:
        return poly
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    poly = poly[keep]
    seg = seg[keep[1:]]
    if len(poly) < 2:
        return poly
    parts = np.maximum(1, np.ceil(seg / max_step - 1e-9).astype(np.int64))
    start = np.repeat(poly[:-1], parts, axis=0)
    step = np.repeat(np.diff(poly, axis=0) / parts[:, None], parts, axis=0)
    k = np.arange(parts.sum()) - np.repeat(np.cumsum(parts) - parts, parts)
    return np.vstack([start + k[:, None] * step, poly[-1:]])


def _at(poly: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points at arc lengths ``t`` along the polyline ``poly`` with cumulative length ``s``."""
    keep = np.concatenate([[True], np.diff(s) > 0])  # drop repeated points
    return np.stack([np.interp(t, s[keep], poly[keep, 0]),
                     np.interp(t, s[keep], poly[keep, 1])], axis=1)


def laser_positions(points: np.ndarray, closed: bool, *, speed_mm_s: float, rate_hz: float,
                    latency_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the laser samples along one measurement path (thesis 5.2.1).

    points: (k, 2) float64, mm, the measurement path in part coordinates (laser frame
        offset already applied).
    Returns (tagged, true): (m, 2) positions the samples are reported at (every
    ``speed / rate`` mm) and where the surface was actually read: ``speed * latency`` mm
    earlier along the path (clamped at the path start).
    """
    spacing = speed_mm_s / rate_hz
    poly = np.vstack([points, points[:1]]) if closed and len(points) > 1 else points
    tagged, t = _resample(points, closed, spacing)
    if len(poly) < 2 or latency_s == 0:
        return tagged, tagged.copy()
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    true = _at(poly, s, np.maximum(t - speed_mm_s * latency_s, 0.0))
    return tagged, true


def laser_measure(surface: HeightMap, tagged: np.ndarray, true: np.ndarray, *,
                  noise_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Simulated laser samples: (m, 3) float64 x, y (tagged position), z (mm).

    ``z`` is the surface height at the ``true`` positions plus Gaussian noise of std
    ``noise_mm``. Use :func:`laser_positions` for the positions along a path.
    """
    z = sample_surface(surface, true)
    if noise_mm > 0:
        z = z + rng.normal(0.0, noise_mm, size=len(z))
    return np.column_stack([tagged, z])


# --------------------------------------------------------------------------- plans


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
    trajectories: tuple[Trajectory, ...] = ()

    @property
    def midpoints(self) -> np.ndarray:
        return 0.5 * (self.a + self.b)


def plan_layer(index: int, paths: Sequence[Toolpath], job: "Job") -> LayerPlan:
    """Cut the deposition paths of one layer into constant-speed segments (see module doc).

    Each boundary/fill path's polyline has its edges split to at most ``speed * dt`` mm
    (speed by role from ``job.motion``); a segment carries ``width * dh * layer_scale *
    length`` mm^3 (eq. 6.2).
    Measurement paths give the laser sample positions (:func:`laser_positions`).
    """
    m = job.motion
    sim = job.simulation
    dh = job.slicing.layer_thickness_mm * job.flow.layer_scale
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
            # part (ice) is measured slowly, scaffold at full speed (icefab.paths.path_speed)
            speed = m.measure_speed_mm_s if p.material == "part" else m.speed_mm_s
            tg, tr = laser_positions(pts, p.closed, speed_mm_s=speed,
                                     rate_hz=sim.laser_rate_hz, latency_s=sim.laser_latency_s)
            tag_parts.append(tg)
            true_parts.append(tr)
            continue
        if not p.depositing:
            continue
        if not p.width > 0:
            raise SimulationError(f"layer {index}: {p.material} {p.role} path has width "
                                  f"{p.width}; expected > 0 mm")
        if p.material not in MATERIAL_ID:
            raise SimulationError(f"layer {index}: unknown material {p.material!r}")
        speed = m.boundary_speed_mm_s if p.role == "boundary" else m.fill_speed_mm_s
        pts_s = _refine(pts, p.closed, speed * m.dt_s)
        if len(pts_s) < 2:
            continue
        pieces.append((pts_s, bool(p.closed), float(p.width), p.material))
        dep_paths.append(p)
    return _layer_plan(index, pieces, dh, tag_parts, true_parts, paths=tuple(dep_paths))


def _layer_plan(index: int, pieces: list[tuple[np.ndarray, bool, float, str]], dh: float,
                tag_parts: list[np.ndarray], true_parts: list[np.ndarray], *,
                paths: tuple[Toolpath, ...], trajectories: tuple = ()) -> LayerPlan:
    """Segments of a layer from its deposition polylines: ``pieces`` holds (points (k >= 2,
    2) mm part frame, closed, width mm, material) per path, each segment carrying the
    commanded ``width * dh * length`` mm^3 (eq. 6.2); laser samples as given."""
    def cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        return np.concatenate(parts) if parts else np.zeros(shape, dtype=dtype)

    a = cat([pts[:-1] for pts, *_ in pieces], (0, 2))
    b = cat([pts[1:] for pts, *_ in pieces], (0, 2))
    counts = [len(pts) - 1 for pts, *_ in pieces]
    starts = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)]).astype(np.int64)
    w = cat([np.full(c, wd) for c, (_, _, wd, _) in zip(counts, pieces)], (0,))
    mat = cat([np.full(c, MATERIAL_ID[m], dtype=np.int8)
               for c, (_, _, _, m) in zip(counts, pieces)], (0,), np.int8)
    hw = 0.5 * w
    n0, n1, ext = _joints(a, b, hw, starts[:-1].copy(),
                          np.asarray([c for _, c, _, _ in pieces], dtype=bool))
    return LayerPlan(index=index, a=a, b=b, volume=w * dh * np.linalg.norm(b - a, axis=1),
                     half_width=hw, material=mat, n0=n0, n1=n1, ext=ext, paths=paths,
                     laser_tagged=cat(tag_parts, (0, 2)),
                     laser_true=cat(true_parts, (0, 2)), trajectories=trajectories)




def _laser_in_time(xy: np.ndarray, dt: float, rate_hz: float, latency_s: float
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
    from icefab import flow

    sim = job.simulation
    dh = job.slicing.layer_thickness_mm * job.flow.layer_scale
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
            tg, tr = _laser_in_time(part_xy, float(traj.dt), sim.laser_rate_hz,
                                    sim.laser_latency_s)
            tag_parts.append(tg)
            true_parts.append(tr)
            continue
        if not p.depositing:
            continue
        pts = flow.trajectory_part_xy(traj, p.material, job)
        if len(pts) > 1:
            step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
            pts = pts[np.concatenate([[True], step > _TINY_MM])]
        if len(pts) < 2:
            pts = np.vstack([pts[:1], pts[:1]])  # at rest: a w x w square, no volume
        closed = bool(len(pts) > 2 and np.linalg.norm(pts[-1] - pts[0]) <= 1e-6)
        pieces.append((pts, closed, flow.trajectory_width(traj, p.material, job), p.material))
        dep.append(traj)
    return _layer_plan(layer.index, pieces, dh, tag_parts, true_parts,
                       paths=tuple(t.path for t in dep), trajectories=tuple(dep))


# --------------------------------------------------------------------------- the build


@dataclass(frozen=True, eq=False)
class Measurement:
    """What the cell hands to the controller at a measurement layer (thesis 5.1.1).

    layer: toolpaths layer index just deposited; k: measurement count, 1 for the first.
    nominal_z: nominal height of the surface, mm (from the platform).
    interval_mm: measurement interval dh_m = n_d * dh, mm.
    samples: (m, 3) float64, mm, laser samples (x, y, z).
    footprint: (ny, nx) bool on the simulator grid ``grid``: the merged (part + scaffold)
        footprint of the layer.
    grid: the simulator grid (its ``z`` is the nominal-height plane, NaN outside).
    """

    layer: int
    k: int
    nominal_z: float
    interval_mm: float
    samples: np.ndarray
    footprint: np.ndarray
    grid: HeightMap


Controller = Callable[[Measurement], ActionFn | None]


@dataclass(frozen=True, eq=False)
class SimResult:
    """Outcome of a simulated build, one entry per measurement layer.

    layers: (m,) int64 toolpaths layer index of each measurement layer.
    nominal_z: (m,) float64, mm, nominal surface height there.
    rms: (m,) float64, mm, RMS deviation of the true surface from nominal over the part
        footprint of that layer (the thesis' sigma_l*, Fig. 5-9); NaN when the layer
        holds no part.
    max_abs: (m,) float64, mm, largest absolute deviation over the part footprint.
    rms_measured: (m,) float64, mm, RMS of the laser samples' deviation from nominal.
    height: final surface; NaN where nothing was ever deposited.
    surfaces: error surfaces (true height - nominal, NaN outside the merged footprint and
        on its partly covered outermost cells) at the layers asked for, by toolpaths
        layer index.
    closed_loop: whether the controller ran.
    volume_commanded, volume_deposited: mm^3 over the build (deposited includes the flow
        error, drift, edge loss and control action).
    flow_gain: final flow gain of each valve (part, scaffold), drift included.
    n_layers: layers simulated.
    pulses: valve pulses deposited (``deposition = "valves"``; 0 with ``"flow"``).
    findings: ``(layer index, text)`` of every valve-limit finding of the programs run
        (``deposition = "valves"``), e.g. what ``flow.out_of_range = "clamp"`` clamped
        and the volume it cost (``icefab.findings.clamped_volume``).
    """

    layers: np.ndarray
    nominal_z: np.ndarray
    rms: np.ndarray
    max_abs: np.ndarray
    rms_measured: np.ndarray
    height: HeightMap
    surfaces: dict[int, HeightMap]
    closed_loop: bool
    volume_commanded: float
    volume_deposited: float
    flow_gain: tuple[float, float]
    n_layers: int
    pulses: int = 0
    findings: tuple[tuple[int, str], ...] = ()

    def as_dict(self) -> dict:
        """JSON-ready figures (no surfaces)."""
        return {"closed_loop": self.closed_loop, "n_layers": self.n_layers,
                "layers": self.layers.tolist(), "nominal_z_mm": self.nominal_z.tolist(),
                "rms_mm": self.rms.tolist(), "max_abs_mm": self.max_abs.tolist(),
                "rms_measured_mm": self.rms_measured.tolist(),
                "volume_commanded_mm3": self.volume_commanded,
                "volume_deposited_mm3": self.volume_deposited,
                "flow_gain": list(self.flow_gain), "pulses": self.pulses}


def _grid_for(plans: Sequence[LayerPlan], job: "Job") -> HeightMap:
    pts = [p.a for p in plans if len(p.a)] + [p.b for p in plans if len(p.b)]
    if not pts:
        raise SimulationError("nothing to deposit: the layers have no boundary or fill paths "
                              "(or trajectories)")
    allp = np.concatenate(pts)
    wmax = max(float(p.half_width.max()) for p in plans if len(p.half_width))
    margin = 2 * wmax + 2 * job.simulation.grid_mm
    check_grid(allp.min(axis=0) - margin, allp.max(axis=0) + margin, job.simulation.grid_mm,
               "simulation.grid_mm")
    return empty_surface(allp.min(axis=0), allp.max(axis=0), job.simulation.grid_mm, margin)


@njit(cache=True)
def _level_kernel(z, liquid, domain, alpha, iters):  # pragma: no cover - numba
    """Let the liquid layer flow downhill over the frozen surface ``z`` (in place).

    Explicit 4-neighbour scheme on the free-surface height ``z + liquid``: across every
    pair of neighbouring cells inside ``domain`` a flux ``alpha * difference`` moves from
    the higher to the lower cell, at most a quarter of the giving cell's liquid per step, so
    liquid stays >= 0 and its total is conserved exactly.
    """
    ny, nx = liquid.shape
    flow = np.zeros_like(liquid)
    for _ in range(iters):
        flow[:, :] = 0.0
        for i in range(ny):
            for j in range(nx):
                if not domain[i, j]:
                    continue
                s = z[i, j] + liquid[i, j]
                for di, dj in ((0, 1), (1, 0)):
                    k = i + di
                    m = j + dj
                    if k >= ny or m >= nx or not domain[k, m]:
                        continue
                    d = s - (z[k, m] + liquid[k, m])
                    if d > 0.0:
                        q = min(alpha * d, 0.25 * liquid[i, j])
                    else:
                        q = -min(-alpha * d, 0.25 * liquid[k, m])
                    flow[i, j] -= q
                    flow[k, m] += q
        for i in range(ny):
            for j in range(nx):
                liquid[i, j] += flow[i, j]


def level_liquid(z: np.ndarray, liquid: np.ndarray, spacing: float, spread_mm: float
                 ) -> np.ndarray:
    """The liquid of one layer after it flowed before freezing (volume conserved).

    z: (ny, nx) frozen surface below, mm; liquid: (ny, nx) the layer just deposited, mm.
    The liquid flows downhill (towards a level top) for as many steps as make a diffusion
    length of ``spread_mm``, inside the wet area: cells with liquid and gaps between them
    up to ``2 * spread_mm`` wide (a morphological closing), less the outermost cells of
    that area (partly covered by the strips' edges); so it fills narrow gaps between paths
    and evens out seams, but never runs off the layer's footprint (that is ``edge_loss``).
    Returns a new array.
    """
    if spread_mm <= 0:
        return liquid.copy()
    alpha = 0.25
    cells = spread_mm / spacing
    iters = max(1, int(math.ceil(cells * cells / (2 * alpha))))
    wet = liquid > 0
    radius = max(1, int(math.ceil(cells)))
    # wet cells and the gaps between them, less the partly covered rim of the footprint
    domain = ndimage.binary_erosion(
        ndimage.binary_closing(wet, iterations=radius, border_value=0) | wet)
    out = np.ascontiguousarray(liquid, dtype=np.float64).copy()
    _level_kernel(np.ascontiguousarray(z, dtype=np.float64), out, domain, alpha, iters)
    return out


def _noise_field(rng: np.random.Generator, shape: tuple[int, int], sigma_cells: float
                 ) -> np.ndarray:
    """Unit-std Gaussian random field with correlation length ``sigma_cells``."""
    f = rng.standard_normal(shape)
    if sigma_cells > 0.5:
        f = ndimage.gaussian_filter(f, sigma_cells, mode="wrap")
        sd = f.std()
        if sd > 0:
            f /= sd
    return f


def _edge_factor(layer_z: np.ndarray, thresh: float, width: float, spacing: float,
                 loss: float) -> np.ndarray:
    """1 - loss within one path width of the edge of the deposited area, ramping to 1."""
    mask = layer_z > thresh
    d = ndimage.distance_transform_edt(mask) * spacing  # distance to the nearest outside cell
    ramp = np.clip(1.0 - (d - 0.5 * spacing) / width, 0.0, 1.0)
    return 1.0 - loss * ramp


def run_cell(plans: Sequence[LayerPlan], job: "Job", *, measure_layers: Sequence[int],
             controller: Controller | None = None, keep_surfaces: Sequence[int] = (),
             progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Deposit ``plans`` layer by layer on the virtual cell, measuring and controlling.

    plans: the layers to deposit, bottom first (:func:`plan_layer`, or
        :func:`plan_layer_motion` for trajectories).
    measure_layers: positions in ``plans`` (0-based) after which the surface is measured.
    controller: called with a :class:`Measurement` after each measurement layer; returns
        the control action u(xy) applied to every segment until the next measurement
        (None: keep nominal flow). Without a controller the build runs open loop. With
        ``simulation.deposition = "valves"`` the action re-plans the valve programs of the
        next ``feedback.interval_layers`` layers (:func:`layer_valves`), whose pulses are
        then deposited (the plans must come from :func:`plan_layer_motion`).
    keep_surfaces: toolpaths layer indices whose error surfaces are kept.
    """
    sim = job.simulation
    dh = job.slicing.layer_thickness_mm
    n_d = job.feedback.interval_layers
    valves = sim.deposition == "valves"
    if valves:
        for plan in plans:
            if len(plan.paths) and not plan.trajectories:
                raise SimulationError(
                    f"layer {plan.index}: simulation.deposition = 'valves' needs the "
                    "layer's trajectories (plan_layer_motion, or simulate_build, which plans "
                    "them); this plan was made from paths (plan_layer)")
    surface = _grid_for(plans, job)
    z = surface.z
    g = surface.spacing
    ever = np.zeros(z.shape, dtype=bool)
    rng_noise = np.random.default_rng([sim.seed, 1])
    rng_debris = np.random.default_rng([sim.seed, 2])
    rng_laser = np.random.default_rng([sim.seed, 3])
    used_cm3 = np.zeros(2)
    edge_width = max(job.materials.part.path_width_mm, job.materials.scaffold.path_width_mm)
    measure_set = set(int(i) for i in measure_layers)
    keep = set(int(i) for i in keep_surfaces)
    action: ActionFn | None = None
    rows: list[tuple[int, float, float, float, float]] = []
    surfaces: dict[int, HeightMap] = {}
    vol_cmd_total = 0.0
    vol_dep_total = 0.0
    pulses = 0
    findings: list[tuple[int, str]] = []
    k = 0
    for j, plan in enumerate(plans):
        nominal = (j + 1) * dh
        layer_img = np.zeros((2,) + z.shape)
        vol_cmd_total += float(plan.volume.sum())
        if valves:
            # thesis 5.1.3: a measurement's action goes into the valve programs of the
            # layers after it; planned when the layer's turn comes (the action only
            # changes at a measurement, so this is the program re-planned there)
            lv = layer_valves(plan, job, action)
            a, b, v_all, hw, mat_of, n0, n1, ext, n_p = valve_segments(lv, job)
            pulses += n_p
            findings += [(plan.index, w) for prog in lv.programs for w in prog.warnings]
        else:
            u = np.zeros(len(plan.volume))
            if action is not None and len(plan.volume):
                u = np.asarray(action(plan.midpoints), dtype=np.float64)
                u = np.where(np.isfinite(u), u, 0.0)
            v_all = plan.volume * np.clip(1.0 + u, 0.0, None)
            a, b, hw, mat_of = plan.a, plan.b, plan.half_width, plan.material
            n0, n1, ext = plan.n0, plan.n1, plan.ext
        for mat in (0, 1):
            sel = mat_of == mat
            if not sel.any():
                continue
            v_cmd = v_all[sel]
            # flow gain with drift by valve use (thesis 6.4): volume already through the valve
            before = used_cm3[mat] + (np.cumsum(v_cmd) - v_cmd) / 1000.0
            gain = (1.0 + sim.flow_error) * (1.0 + sim.flow_drift_per_cm3 * before)
            used_cm3[mat] += v_cmd.sum() / 1000.0
            vol = v_cmd * gain
            _splat(layer_img[mat], surface.origin, g, a[sel], b[sel], vol, hw[sel], n0[sel],
                   n1[sel], ext[sel])
        if sim.edge_loss > 0:
            # liquid runs off free edges: the edge of the merged footprint (outer rim and
            # holes), not the part/scaffold interface where the materials support each other
            layer_img *= _edge_factor(layer_img[0] + layer_img[1], 0.25 * dh, edge_width, g,
                                      sim.edge_loss)
        added = layer_img[0] + layer_img[1]
        vol_dep_total += float(added.sum() * g * g)
        mask = added > 0.25 * dh
        # part cells wholly inside this layer's part deposit (not the partly covered rim)
        part_mask = ndimage.binary_erosion(layer_img[0] > 0.25 * dh)
        if not part_mask.any():  # a part narrower than two cells: keep its rim
            part_mask = layer_img[0] > 0.25 * dh
        if sim.spread_mm > 0:
            added = level_liquid(z, added, g, sim.spread_mm)
            mask |= added > 0.25 * dh
        if sim.noise_mm > 0 and mask.any():
            added += sim.noise_mm * mask * _noise_field(rng_noise, z.shape,
                                                          sim.noise_corr_mm / g)
        if sim.debris_rate > 0 and len(plan.volume):
            n_debris = rng_debris.poisson(sim.debris_rate)
            if n_debris:
                where = plan.midpoints[rng_debris.integers(0, len(plan.volume), n_debris)]
                # Gaussian bumps on the layer's footprint (thesis 5.6: d_pulse), each
                # summed over a +-4 sigma window: impulses at the debris cells, filtered
                impulse = np.zeros(z.shape)
                ix = np.clip(np.rint((where[:, 0] - surface.origin[0]) / g).astype(np.int64),
                             0, z.shape[1] - 1)
                iy = np.clip(np.rint((where[:, 1] - surface.origin[1]) / g).astype(np.int64),
                             0, z.shape[0] - 1)
                np.add.at(impulse, (iy, ix), 1.0)
                sigma = sim.debris_radius_mm / g
                bumps = ndimage.gaussian_filter(impulse, sigma, mode="constant", truncate=4.0)
                added += mask * sim.debris_height_mm * 2 * np.pi * sigma ** 2 * bumps
        z += added
        ever |= mask
        if j in measure_set:
            k += 1
            err = z - nominal
            if part_mask.any():
                e = err[part_mask]
                rms = float(np.sqrt(np.mean(e ** 2)))
                mx = float(np.abs(e).max())
            else:
                rms = mx = float("nan")
            tagged, true = plan.laser_tagged, plan.laser_true
            if len(tagged) == 0:
                # no measurement paths in this layer: read along the deposition segments
                tagged = true = plan.midpoints
            samples = laser_measure(surface, tagged, true, noise_mm=sim.laser_noise_mm,
                                    rng=rng_laser)
            rms_meas = float(np.sqrt(np.mean((samples[:, 2] - nominal) ** 2))) \
                if len(samples) else float("nan")
            rows.append((plan.index, nominal, rms, mx, rms_meas))
            log.debug("layer %d (%.2f mm): RMS %.4f mm, max %.4f mm, measured RMS %.4f mm",
                      plan.index, nominal, rms, mx, rms_meas)
            if plan.index in keep:
                # without the partly covered outermost cells of the footprint
                surfaces[plan.index] = HeightMap(origin=surface.origin.copy(), spacing=g,
                                                 z=np.where(ndimage.binary_erosion(mask),
                                                            err, np.nan))
            if controller is not None:
                plane = np.where(mask, nominal, np.nan)
                action = controller(Measurement(
                    layer=plan.index, k=k, nominal_z=nominal, interval_mm=n_d * dh,
                    samples=samples, footprint=mask,
                    grid=HeightMap(origin=surface.origin.copy(), spacing=g, z=plane)))
        if progress is not None:
            progress(j + 1, len(plans))
    arr = np.array(rows, dtype=np.float64).reshape(-1, 5)
    final = HeightMap(origin=surface.origin.copy(), spacing=g, z=np.where(ever, z, np.nan))
    gains = tuple(float((1 + sim.flow_error) * (1 + sim.flow_drift_per_cm3 * c))
                  for c in used_cm3)
    return SimResult(layers=arr[:, 0].astype(np.int64), nominal_z=arr[:, 1], rms=arr[:, 2],
                     max_abs=arr[:, 3], rms_measured=arr[:, 4], height=final,
                     surfaces=surfaces, closed_loop=controller is not None,
                     volume_commanded=vol_cmd_total, volume_deposited=vol_dep_total,
                     flow_gain=gains, n_layers=len(plans),  # type: ignore[arg-type]
                     pulses=pulses, findings=tuple(findings))


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
    from icefab import flow

    u = None if action is None else _finite(action)
    trajs, progs = flow.replan_valves(plan.trajectories, job, action=u)
    return LayerValves(trajectories=tuple(trajs), programs=tuple(progs), action=u)


def valve_segments(valves: LayerValves, job: "Job") -> tuple:
    """The deposition segments of a layer's valve pulses (:func:`pulse_segments`).

    Returns a, b (m, 2), volume (m,) mm^3 (drops as commanded, before the simulated flow
    gain), half width (m,), material (m,) int8, n0, n1, ext, and the number of pulses.
    """
    from icefab import flow

    xs, dts, ts, drops, widths, mats = [], [], [], [], [], []
    for traj, prog in zip(valves.trajectories, valves.programs):
        p = traj.path
        if p is None or not p.depositing:
            continue
        freq = flow.valve_frequency(traj, p.material, job, action=valves.action) \
            if prog.widths_us is None else None
        t, d = pulse_drops(prog, freq, p.material, job)
        xs.append(flow.trajectory_part_xy(traj, p.material, job))
        dts.append(float(traj.dt))
        ts.append(t)
        drops.append(d)
        widths.append(flow.trajectory_width(traj, p.material, job))
        mats.append(MATERIAL_ID[p.material])
    a, b, vol, hw, owner, n0, n1, ext = pulse_segments(xs, dts, ts, drops, widths)
    material = np.asarray(mats, dtype=np.int8)[owner] if len(owner) else \
        np.zeros(0, dtype=np.int8)
    return a, b, vol, hw, material, n0, n1, ext, int(sum(len(t) for t in ts))


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


def _chosen(build: "Toolpaths | BuildMotion", job: "Job", layers: int | None) -> tuple:
    n = layers if layers is not None else job.simulation.layers
    if n is not None and n < 0:
        raise SimulationError(f"layers = {n}: expected >= 0 (0: all)")
    chosen = build.layers[:n] if n else build.layers
    if not chosen:
        raise SimulationError("the build has no layers to simulate")
    return tuple(chosen)


def _has_laser(layer: "LayerPaths | LayerMotion") -> bool:
    """Whether a layer has a measurement path (trajectory) with at least one point: the
    layers :func:`plan_layer` / :func:`plan_layer_motion` give laser samples."""
    if isinstance(layer, LayerPaths):
        return any(p.role == "measure" and len(p.points) > 0 for p in layer.paths)
    return any(t.path is not None and t.path.role == "measure" and len(t.xy) > 0
               for t in layer.trajectories)


def measured_layers(build: "Toolpaths | BuildMotion", job: "Job | None" = None, *,
                    layers: int | None = None) -> list[int]:
    """Layer indices :func:`simulate_build` measures for these arguments, found without
    simulating (so that options such as a surface layer are checked up front)."""
    job = job if job is not None else build.job
    chosen = _chosen(build, job, layers)
    flags = [_has_laser(lay) for lay in chosen]
    return [chosen[j].index for j in _measured(flags, job.feedback.interval_layers)]


#: Settings that shape where trajectories put the material; a build simulated with another
#: job than the one its trajectories were planned with must agree on them.
MOTION_SETTINGS = ("slicing.layer_thickness_mm", "cell.ee_origin_mm", "cell.laser_offset_mm",
                   "materials.part.nozzle_offset_mm", "materials.scaffold.nozzle_offset_mm",
                   "materials.part.path_width_mm", "materials.part.fill_width_mm",
                   "materials.scaffold.path_width_mm", "materials.scaffold.fill_width_mm")


def check_motion_job(planned: "Job", job: "Job", source: str = "the trajectories") -> None:
    """SimulationError if ``job`` differs from the job trajectories were ``planned`` with
    in a setting that moves the material (:data:`MOTION_SETTINGS`): frames, tool offsets,
    widths, layer thickness. Names the first difference and counts the others."""
    from icefab.config import to_dict

    a, b = to_dict(planned), to_dict(job)

    def get(d: dict, dotted: str):
        for key in dotted.split("."):
            d = d[key]
        return d

    diff = [(k, get(a, k), get(b, k)) for k in MOTION_SETTINGS if get(a, k) != get(b, k)]
    if diff:
        k, va, vb = diff[0]
        more = f" (and {len(diff) - 1} more)" if len(diff) > 1 else ""
        raise SimulationError(f"{source} were planned with {k} = {va}, the job has {vb}{more}: "
                              "simulate with the job they were planned with, or plan them "
                              "again with this job ('icefab plan')")


def simulate_build(build: "Toolpaths | BuildMotion", job: "Job | None" = None, *,
                   layers: int | None = None, closed_loop: bool = True,
                   controller: Controller | None = None,
                   keep_surfaces: Sequence[int] | None = None,
                   progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Build on the virtual cell, open loop or with surface mapping feedback.

    build: the toolpaths (``icefab.paths.plan_paths``) or their trajectories
        (``icefab.motion.plan_toolpaths`` / ``load_trajectories``); job: settings
        (default: the job the build was made with; for trajectories it must agree with
        that job on :data:`MOTION_SETTINGS`).
    With ``job.simulation.deposition = "flow"`` the commanded volume is laid along the
    paths (or the trajectories' sample chords). With ``"valves"`` every layer's
    deposition trajectories run through their valve programs, pulse by pulse
    (:func:`layer_valves`, :func:`deposit_pulses`); from toolpaths the minimum-time
    trajectories of the simulated layers are planned first
    (:func:`icefab.motion.plan_toolpaths`, ``cell.cpus`` processes) — to simulate the
    same build twice, plan once and pass the ``BuildMotion``.
    layers: simulate only the first N layers (default ``job.simulation.layers``, 0 = all).
    closed_loop: run the SMF controller (``controller``, default :func:`smf_controller`)
        after every measurement layer; False runs open loop (no control action).
    keep_surfaces: toolpaths layer indices of measurement layers whose error surfaces
        are kept in the result (for plots like thesis Fig. 5-8); default: the last
        measurement layer.
    progress: called as ``progress(done, total)`` after every layer.
    """
    from icefab.motion import BuildMotion, plan_toolpaths

    job = job if job is not None else build.job
    chosen = _chosen(build, job, layers)
    if isinstance(build, BuildMotion):
        if job is not build.job:
            check_motion_job(build.job, job)
        plans = [plan_layer_motion(lm, job) for lm in chosen]
    elif job.simulation.deposition == "valves":
        motion = plan_toolpaths(Toolpaths(layers=chosen, job=build.job), job)
        plans = [plan_layer_motion(lm, job) for lm in motion.layers]
    else:
        plans = [plan_layer(lp.index, lp.paths, job) for lp in chosen]
    measure = measurement_layers(plans, job.feedback.interval_layers)
    if keep_surfaces is None:
        keep_surfaces = [plans[measure[-1]].index] if measure else []
    if closed_loop and controller is None:
        controller = smf_controller(job)
    return run_cell(plans, job, measure_layers=measure,
                    controller=controller if closed_loop else None,
                    keep_surfaces=keep_surfaces, progress=progress)


def smf_controller(job: "Job") -> Controller:
    """The surface mapping feedback of :mod:`icefab.feedback` as a simulator controller.

    At each measurement: the laser samples become a surface on the controller grid
    (``job.feedback.grid_mm``, Delaunay-linear, optional robust smoothing), restricted to
    the layer's merged footprint (footprint nodes outside the samples' hull take the
    nearest sample); the normalised error drives one step of the spatial PID (eq. 5.1,
    saturation and anti-windup); the returned u(xy) samples the saturated action
    (thesis 5.1-5.2).
    """
    from scipy.spatial import cKDTree

    from icefab import feedback

    fb = job.feedback
    state = feedback.SmfState()

    def control(m: Measurement) -> ActionFn:
        nonlocal state
        try:
            surf = feedback.surface_from_samples(m.samples, None, fb.grid_mm,
                                                 smoothing=fb.smoothing)
        except GeometryError as exc:
            # e.g. a tiny top layer with too few or collinear samples: the cell carries on
            # at nominal flow until the next measurement
            log.warning("layer %d: no surface from %d laser samples (%s); no control action",
                        m.layer, len(m.samples), exc)
            return lambda xy: np.zeros(len(xy))
        x, y = surf.grid()
        g = m.grid.spacing
        ix = np.rint((x - m.grid.origin[0]) / g).astype(np.int64)
        iy = np.rint((y - m.grid.origin[1]) / g).astype(np.int64)
        ny, nx = m.footprint.shape
        okx = (ix >= 0) & (ix < nx)
        oky = (iy >= 0) & (iy < ny)
        inside = m.footprint[np.clip(iy, 0, ny - 1)][:, np.clip(ix, 0, nx - 1)]
        inside &= oky[:, None] & okx[None, :]
        z = np.where(inside, surf.z, np.nan)
        hole = inside & ~np.isfinite(surf.z)
        if hole.any():
            hy, hx = np.nonzero(hole)
            _, nearest = cKDTree(m.samples[:, :2]).query(np.column_stack([x[hx], y[hy]]))
            z[hy, hx] = m.samples[nearest, 2]
        if not np.isfinite(z).any():
            log.warning("layer %d: the laser samples miss the footprint; no control action",
                        m.layer)
            return lambda xy: np.zeros(len(xy))
        error = feedback.error_surface(HeightMap(origin=surf.origin, spacing=surf.spacing,
                                                 z=z), m.nominal_z, m.interval_mm)
        action, state = feedback.smf_update(state, error, job)
        return feedback.action_sampler(action)

    return control
