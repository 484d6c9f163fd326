"""Deposition kernels of the virtual cell: paths and valve pulses onto a height map, and the
liquid flowing before it freezes (thesis 5.3, 5.6; Ch. 6 for pulses).

The model is described in :mod:`icefab.sim`. Arrays: points (n, 2) float64 mm, volumes mm^3,
height maps :class:`~icefab.core.HeightMap`.
"""

from __future__ import annotations

import logging
import math
from typing import Callable, Sequence

import numpy as np
from numba import njit
from scipy import ndimage

from icefab import flow
from icefab.config import Job
from icefab.core import HeightMap, ValveProgram, arc_lengths
from icefab.errors import SimulationError
from icefab.flow import FrequencyPlan

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


def _at(poly: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points at arc lengths ``t`` along the polyline ``poly`` with cumulative length ``s``."""
    keep = np.concatenate([[True], np.diff(s) > 0])  # drop repeated points
    return np.stack([np.interp(t, s[keep], poly[keep, 0]),
                     np.interp(t, s[keep], poly[keep, 1])], axis=1)


def _pulse_segments(xy: np.ndarray, dt: float | np.ndarray, pulse_t: np.ndarray,
                    drop: np.ndarray, width: float | np.ndarray = 0.0) -> tuple:
    """Drops of one trajectory as deposition segments (see :func:`deposit_pulses`).

    dt: the time step, s, or (n,) the points' instants from the first (a tour's stretch,
    cut where its valve switches, :func:`icefab.sim.plans.on_stretches`).
    width: the path width, mm: one for the whole path or (n,) one per sample (a
    variable-width path, linear between samples).
    Returns a, b (m, 2) segment ends along the followed polyline (repeated samples
    dropped, so corners keep their mitre), vol (m,) mm^3, w (m,) mm the width at each
    segment's middle, (at (k, 2), at_vol (k,), at_w (k,)): the positions, volumes and
    widths of drops that own no length of path (three or more at one place, or a
    trajectory that does not move), and whether the polyline returns to its start
    (closed).
    """
    xy = np.asarray(xy, dtype=np.float64)
    n = len(xy)
    p = len(pulse_t)
    none = np.zeros((0, 2))
    wn = np.broadcast_to(np.asarray(width, dtype=np.float64), (n,))
    if p == 0 or n == 0:
        return none, none, np.zeros(0), np.zeros(0), (none, np.zeros(0), np.zeros(0)), False
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    S = arc_lengths(seg)
    length = float(S[-1])
    if length <= _TINY_MM:
        return (none, none, np.zeros(0), np.zeros(0),
                (np.repeat(xy[:1], p, axis=0), drop.copy(), np.full(p, wn[0])), False)
    # where the nozzle is at each pulse instant: arc length at that time (thesis 6.2)
    times = np.arange(n) * dt if np.ndim(dt) == 0 else np.asarray(dt, dtype=np.float64)
    s_p = np.interp(pulse_t, times, S)
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
    w_seg = np.interp(0.5 * (cuts[:-1] + cuts[1:]), s_v, wn[keep])
    return (pts[:-1], pts[1:], vol, w_seg,
            (at, rest[lone], np.interp(s_p[lone], s_v, wn[keep])), closed)


def pulse_segments(xy: Sequence[np.ndarray], dt: Sequence[float],
                   pulse_times_s: Sequence[np.ndarray], drop_mm3: Sequence[np.ndarray],
                   width: Sequence[float | np.ndarray]) -> tuple[np.ndarray, ...]:
    """Deposition segments of many trajectories' valve pulses (see :func:`deposit_pulses`).

    Per trajectory i: ``xy[i] (n_i, 2)`` mm part-frame nozzle positions every ``dt[i]`` s
    (or at the (n_i,) instants ``dt[i]``),
    pulse instants ``pulse_times_s[i] (p_i,)`` s from its start, drop volumes
    ``drop_mm3[i] (p_i,)``, path width ``width[i]`` mm (or (n_i,) one per sample: a
    variable-width path).
    Returns a (m, 2), b (m, 2), volume (m,) mm^3, half width (m,) mm, owner (m,) int64
    (the trajectory each segment comes from), n0, n1, ext (:func:`_joints`), in the
    trajectories' order.
    """
    a_l, b_l, v_l, hw_l, own_l, starts, closed = [], [], [], [], [], [], []
    count = 0
    for i, (pts, step, t, drop, w) in enumerate(zip(xy, dt, pulse_times_s, drop_mm3, width)):
        a, b, vol, ws, (at, at_vol, at_w), cl = _pulse_segments(
            pts, step if np.ndim(step) else float(step), np.asarray(t, dtype=np.float64),
            np.asarray(drop, dtype=np.float64), w)
        pieces = [(a, b, vol, ws, cl)] if len(a) else []
        # lone drops: a zero-length segment each, a path of its own (w x w square)
        pieces += [(at[k:k + 1], at[k:k + 1], at_vol[k:k + 1], at_w[k:k + 1], False)
                   for k in range(len(at))]
        for pa, pb, pv, pw, pc in pieces:
            starts.append(count)
            closed.append(pc)
            count += len(pa)
            a_l.append(pa)
            b_l.append(pb)
            v_l.append(pv)
            hw_l.append(0.5 * pw)
            own_l.append(np.full(len(pa), i, dtype=np.int64))
    if not a_l:
        z2, z1 = np.zeros((0, 2)), np.zeros(0)
        return z2, z2, z1, z1, np.zeros(0, dtype=np.int64), z2, z2, z1
    a, b, hw = np.concatenate(a_l), np.concatenate(b_l), np.concatenate(hw_l)
    n0, n1, ext = _joints(a, b, hw, np.asarray(starts, dtype=np.int64),
                          np.asarray(closed, dtype=bool))
    return a, b, np.concatenate(v_l), hw, np.concatenate(own_l), n0, n1, ext


def deposit_pulses(surface: HeightMap, xy: np.ndarray, dt: float, pulse_times_s: np.ndarray,
                   drop_mm3: float | np.ndarray, width: float | np.ndarray) -> HeightMap:
    """Deposit the drops of one valve program along one trajectory onto a height map.

    surface: the current surface (finite ``z``).
    xy: (n, 2) float64, mm, nozzle positions in the part frame every ``dt`` s (a
        :class:`~icefab.core.Trajectory` through :func:`icefab.flow.trajectory_part_xy`).
    pulse_times_s: (p,) float64, s, non-decreasing pulse instants from the trajectory start
        (:func:`icefab.flow.pulse_times`).
    drop_mm3: volume of each drop, mm^3, scalar or (p,) (:func:`pulse_drops`).
    width: path width, mm, or (n,) the width at every sample (a variable-width path,
        :func:`icefab.flow.sample_widths`; each piece of a drop's share is as wide as the
        path at its middle).

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
    w = np.asarray(width, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or not dt > 0 \
            or w.shape not in ((), (len(xy),)) or not np.all(w > 0) \
            or not (np.isfinite(xy).all() and np.isfinite(pulse_t).all()
                    and np.isfinite(drop).all() and np.isfinite(w).all()) \
            or np.any(np.diff(pulse_t) < 0):
        raise SimulationError("deposit_pulses: need xy (n, 2) finite, dt > 0, width > 0 "
                              "(one, or one per sample) and finite, non-decreasing pulse "
                              "times")
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

    t = flow.pulse_times(program)
    if len(t) == 0:
        return t, np.zeros(0)
    cal = flow.calibration_for(material, job)
    if program.widths_us is None:
        if frequency is None:
            raise SimulationError("pulse_drops: an FM program needs its frequency plan")
        # a tour's pulses at the signal over its spans (off between them, not 0 at the
        # spans' ends)
        sig = frequency if frequency.on is None else frequency.on
        nu = np.interp(t, sig.t, sig.nu)
        pos = cal.frequency_hz[cal.frequency_hz > 0]
        floor = 1e-6 * float(pos[0]) if len(pos) else 1e-9
        nu = np.maximum(nu, floor)
        return t, cal.flow(nu) / nu
    f = job.flow.pwm_frequency_hz
    per_pulse = float(cal.flow(np.array([f]))[0]) / f
    widths_ms = np.concatenate([pc.widths_us for pc in flow.program_pieces(program)]
                               ).astype(np.float64) / 1000.0
    return t, per_pulse * widths_ms / job.flow.calibration_pulse_ms




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
