"""Minimum-time trajectory shaping (MTTS, thesis Ch. 4).

Turns deposition, measurement and travel paths into the fastest trajectories a robot can
follow exactly under Cartesian and joint speed, acceleration and jerk bounds, sampled at a
constant time step (default 16 ms; the speed lives in the point spacing, thesis Fig. 4-11).

Steps (thesis 4.1, compiled kernels in :mod:`icefab._mtts`):

1. PATHSPLIT (4.1.1): split each path where its direction turns by more than
   ``motion.smooth_angle_deg``; the robot stops there. Each piece is resampled along its
   length at ``motion.point_spacing_mm`` (at least 2 segments). Path smoothing within
   ``motion.smoothing_tolerance_mm`` (default 0.02 mm, see "Path following" below; 0
   turns it off): a local quadratic regression along each piece (biweight
   window of 3 ``SMOOTH_SIGMA_MM``, narrowed where the path turns by more than
   ``SMOOTH_MAX_TURN_DEG`` within it, piece ends fixed), evaluated at the grid points and
   at the input's own vertices, displacements scaled smoothly to stay within the
   tolerance (``_smooth.smooth_pieces``); at an output step under 16 ms also at points
   added so that the polyline has one at least every ``FOLLOW_STEP_SPEED_MM_S`` x dt
   (``_denser_input``: a finer step would otherwise be slower, as every point of the
   polyline bounds v |turning| / dt). The output follows that polyline, so every
   sample is within the tolerance of the input (a hard bound: both ends of each of its
   chords are moved by <= the tolerance from one input segment). It matters on real
   layers: the slicer's 0.4 mm / 0.05 mm point filter and the Clipper offsets leave fill
   rings as polygons turning ~6 deg every ~2.6 mm, and a vertex turning by alpha costs
   v alpha / dt of acceleration at speed v (about 76 mm/s where the ring's 25 mm radius
   allows 112).
2. VCON (4.1.2): the maximum-speed envelope from the Cartesian speed, total acceleration
   (tangential + radial, eq. 4.8) and jerk bounds and from every joint's speed,
   acceleration and jerk bounds (eqs. 4.2-4.5, 4.10). The joints come from the robot's
   inverse kinematics on the resampled points, differentiated along s. Curvature is taken
   as the robot sees it: it receives one point per dt, so second derivatives are averaged
   over the step v dt, and every vertex of the polyline followed limits the speed by the
   acceleration of three samples centred on it, v |turning| / dt (``_mtts._vertex_bounds``;
   on a finely sampled curve this is v^2 kappa, at a coarse polygon's vertex it is what a
   0.4 mm grid curvature would underestimate). Jerk bounds use curvature averaged over
   ``JERK_WINDOW_MM``.
3. ACON (4.1.3, Fig. 4-5): forward and backward acceleration curves; with jerk on, each
   curve ramps its acceleration with the jerk bound (explicit positive root of eq. 4.7).
4. JCON (4.1.4, Fig. 4-6, eq. 4.12): speed-decrease jerk spikes are spread by cubic
   velocity polynomials (speeds only lowered).
5. AREST (4.1.5, 4.2.6): every piece starts and ends at rest; with jerk on the from/to
   rest curves start with ``motion.rest_accel_mm_s2`` (80 mm/s^2), or less where the
   joints' acceleration bounds at the rest point allow less (their rates taken at the
   point itself: near the SCARA's full reach they grow like 1 / sqrt(distance)). The first and the
   last output step of every piece must turn some joint by at least its encoder
   resolution (``cell.encoder_resolution_deg``, ``Robot.joint_resolution``): where they
   would not (tangential motion near the reach, short pieces, the last step shortened by
   the rounding to whole steps), that end's initial acceleration is raised, up to the
   total and joint acceleration bounds at rest (``_mtts.rest_accelerations``; jerk off
   too). A rest curve may let its acceleration fall (negative jerk) so long as the speed
   still rises monotonically.
6. Sampling at constant dt: each piece is slowed uniformly by at most one time step so
   that it ends exactly on a sample; pieces are concatenated (the corner sample is shared:
   the robot is at rest there, ``Trajectory.pieces`` gives the indices). Joint angles are
   the inverse kinematics of the samples, smoothed with the 7-point cubic Savitzky-Golay
   filter of thesis 4.2.6 (``motion.savgol_window``) away from trajectory ends and rest
   points, wherever that moves the tool by at most :func:`savgol_deviation_mm`.

Path following (issue 4: within 0.02 mm of the path, ``PATH_FOLLOW_MM``): the samples lie
on the followed polyline, within ``motion.smoothing_tolerance_mm`` of the input; the joint
smoothing may move the tool by what the tolerance leaves of 0.02 mm (at most
``SAVGOL_MAX_DEVIATION_MM`` = 0.01), so the tool (forward kinematics of the joints) stays
within 0.02 mm of the input. The default tolerance, 0.02 mm, leaves the joint filter no
room (it is skipped): measured on the bunny and a rounded box, it keeps twice the
build-time gain of 0.01 mm + joint filter, at the same joint jerk (BENCHMARKS.md). A
tolerance above 0.02 mm is the user's choice of a looser bound. Between two samples
the robot's own interpolation cuts chords: up to ~A dt^2 / 8 = 0.016 mm on curves at
the acceleration bound, more across the input polygon's vertices (not part of the bound).

Phi of eq. 4.11 (theta4 = phi - theta1 - theta2, the end-effector orientation) is 0:
``Scara.phi`` is not a job setting.

A gantry whose part origin was left at the default (a SCARA position) builds at the
centre of its travel (resolved when the Job is built, ``config.CellSettings``; the
trajectories' job records the origin used).

Comparison with constant speed (thesis 4.4): :func:`constant_speed_motion` plans the
thesis' "constant-speed" technique (boundaries 25 mm/s, fill 125 mm/s) with the same
machinery and the path's speed bound set to that constant, so ramps, stops at split
corners and curvature limits count; ``icefab.paths.estimate_build_time`` is the
idealised length / speed figure.

The planner only knows the :class:`icefab.robots.Robot` protocol (the Klipper rule: a
robot can only tighten limits).

The trajectory file (``save_trajectories`` / ``load_trajectories``) is documented in
:mod:`icefab.resultfiles`.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, replace as _replace
from functools import lru_cache
from typing import Callable, Iterator, Mapping, NamedTuple, Sequence

import numpy as np
from scipy.ndimage import convolve1d

from icefab import _mtts
from icefab.atomic import atomic_path
from icefab.config import Job
from icefab.errors import IcefabError, WorkspaceError
from icefab.frames import to_base_frame
from icefab.parallel import parallel_imap, parallel_map
from icefab.resultfiles import (TRAJECTORIES_FORMAT as FORMAT,  # noqa: F401 (old home)
                                TRAJECTORIES_VERSION as VERSION, TrajectoryFile,
                                TrajectoryWriter, load_trajectories, open_trajectories,
                                LayerHead, PackedToolpaths, owner_arrays, pack_layer_paths,
                                packed_lengths, packed_polylines, packed_tools,
                                pack_trajectories, save_trajectories, unpack_layer_paths,
                                unpack_trajectories)
from icefab.robots import Robot, Scara, get_robot, points_box
from icefab.core import (DEPOSITING_CODES, MATERIALS, ROLES, BuildMotion, LayerMotion, LayerPaths,
                         Toolpath, Toolpaths, Trajectory, arc_lengths, checked_widths, offsets,
                         off_problem, path_lengths, split_rows, widths_problem)
from icefab.workload import check_motion

log = logging.getLogger(__name__)

__all__ = ["plan_motion", "plan_paths_motion", "plan_paths_durations", "plan_toolpaths",
           "iter_plan_toolpaths",
           "iter_plan_and_compare", "iter_plan_packed", "PlannedLayer",
           "unpack_layer_motion",
           "constant_speed_motion",
           "constant_speed_time",
           "check_build_workspace", "check_layer_workspace", "LayerMotion", "BuildMotion",
           "save_trajectories", "load_trajectories", "open_trajectories", "TrajectoryFile",
           "TrajectoryWriter",
           "constant_spacing", "gcode_moves",
           "path_limits"]

#: How closely the tool follows the input path (issue 4), mm: path smoothing within
#: ``motion.smoothing_tolerance_mm`` plus the joints' Savitzky-Golay smoothing share it.
PATH_FOLLOW_MM = 0.02
#: Joint smoothing (Savitzky-Golay) is kept only where it moves the tool less than this,
#: and less than what the path smoothing leaves of PATH_FOLLOW_MM (savgol_deviation_mm).
SAVGOL_MAX_DEVIATION_MM = 0.01
#: Jerk spikes above the bound by more than this fraction are smoothed by JCON (thesis
#: 4.2.4 detects jerk violations at +20 %).
JCON_TOLERANCE = 0.2
#: Curvature (and joint second derivatives) are averaged over this length before their
#: slope is taken for the jerk bounds (about one output step at full speed), mm.
JERK_WINDOW_MM = 2.0
#: Width of the path smoothing (the biweight window's half-width is 3 x this), mm.
SMOOTH_SIGMA_MM = 2.0
#: The smoothing window narrows until the path turns by at most this much within it, deg.
SMOOTH_MAX_TURN_DEG = 60.0
#: With path smoothing on, the followed polyline has a point at least every output step
#: at this speed, mm/s (:func:`_denser_input`; the 0.4 mm grid at 16 ms already does).
FOLLOW_STEP_SPEED_MM_S = 25.0
#: With path smoothing on and an output step under the grid's (``_round_corners``), the
#: share of ``motion.smoothing_tolerance_mm`` that rounds the input's corners into arcs;
#: the regression smoothing gets the rest.
CORNER_SHARE = 0.5
#: Points closer than this are merged before planning (zero-length segments), mm.
MERGE_MM = 1e-9
#: Gap inserted between pieces in the concatenated arc length (keeps it increasing), mm.
_GAP = 1.0



# --------------------------------------------------------------------------- inputs


def path_limits(path: Toolpath, job: Job) -> float:
    """Speed bound along one path, mm/s: ``motion.speed_mm_s``, lowered to
    ``motion.measure_speed_mm_s`` for part (ice) measurement paths (thesis 4.2.1) and to
    ``motion.travel_speed_mm_s`` for travel moves."""
    m = job.motion
    v = m.speed_mm_s
    if path.role == "measure" and path.material == "part":
        v = min(v, m.measure_speed_mm_s)
    if path.role == "travel":
        v = min(v, m.travel_speed_mm_s)
    return float(v)


def _role_cap(path: Toolpath, job: Job, role_speeds: Mapping[str, float] | None) -> float:
    """Speed bound of one path: :func:`path_limits`, or ``role_speeds[path.role]`` (capped
    by ``motion.speed_mm_s``) when given for its role."""
    if role_speeds and path.role in role_speeds:
        return float(min(role_speeds[path.role], job.motion.speed_mm_s))
    return path_limits(path, job)


def _check_role_speeds(role_speeds: Mapping[str, float] | None) -> None:
    for role, v in (role_speeds or {}).items():
        if role not in ROLES:
            raise IcefabError(f"role speeds: unknown path role {role!r}, expected one of "
                              f"{', '.join(ROLES)}")
        if not (math.isfinite(v) and v > 0.0):
            raise IcefabError(f"role speeds: the speed of {role} paths must be a positive "
                              f"number of mm/s, got {v!r}")


def _base_points(path: Toolpath, job: Job) -> np.ndarray:
    """(k, 2) float64 mm: a Path's points in the robot base frame (closing point repeated)."""
    pts = path.polyline()
    if path.frame == "base":
        return np.asarray(pts, dtype=np.float64)
    return to_base_frame(pts, path.tool_name, job)


def _as_points(points: np.ndarray, what: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise IcefabError(f"{what}: points must be an (n, 2) array in mm, got shape "
                          f"{pts.shape}")
    if len(pts) == 0:
        raise IcefabError(f"{what}: a path needs at least one point, got none")
    if not np.isfinite(pts).all():
        i = int(np.flatnonzero(~np.isfinite(pts).all(axis=1))[0])
        raise IcefabError(f"{what}: point {i} is not finite: {pts[i].tolist()}")
    return pts


# --------------------------------------------------------------------------- core


def _label(labels: Sequence[tuple[int, int] | str] | None, k: int) -> str:
    """How error messages name polyline k: "path k" without labels, the label itself when
    it is a string, else "layer L, path i" from a (layer, index) pair (layer -1: none)."""
    if labels is None:
        return "path" if k == 0 else f"path {k}"
    if isinstance(labels[k], str):
        return labels[k]
    layer, idx = labels[k]
    parts = []
    if layer >= 0:
        parts.append(f"layer {layer}")
    parts.append(f"path {idx}")
    return ", ".join(parts)


@dataclass
class _Split:
    """PATHSPLIT result for a batch of polylines (flat arrays, see _pathsplit)."""

    V: np.ndarray          # (K, 2) merged vertices
    pid: np.ndarray        # (K,) polyline of each vertex
    counts: np.ndarray     # (P,) vertices per polyline after merging
    pstart: np.ndarray     # (P+1,)
    orig_index: np.ndarray  # (K,) index of each merged vertex in its input polyline
    a: np.ndarray          # (Q,) first vertex of each piece
    piece_path: np.ndarray  # (Q,)
    PV: np.ndarray         # piece vertex lists, concatenated
    pvs: np.ndarray        # (Q+1,) piece p has PV[pvs[p]:pvs[p+1]]
    S: np.ndarray          # arc length of PV with a gap between pieces
    s0: np.ndarray         # (Q,) S at each piece start
    L: np.ndarray          # (Q,) piece lengths, mm
    nseg: np.ndarray       # (Q,) segments of the resampled grid
    hk: np.ndarray         # (Q,) grid spacing, mm
    gstart: np.ndarray     # (Q+1,) grid offsets
    gxy: np.ndarray        # (G, 2) resampled (and optionally smoothed) points
    gs: np.ndarray         # (G,) arc length (S units) of the grid points
    fxy: np.ndarray        # (F, 2) the polyline the samples follow (PV, or the smoothed
    fu: np.ndarray         # grid with kept sharp vertices), its parameter (S units)
    fstart: np.ndarray     # (Q+1,) piece p follows fxy[fstart[p]:fstart[p+1]]


def _pathsplit(V: np.ndarray, counts: np.ndarray, job: Job) -> _Split:
    """PATHSPLIT (thesis 4.1.1) for polylines concatenated in ``V (K, 2)`` with ``counts``
    points each: merge repeated points, split at turns above ``motion.smooth_angle_deg``,
    resample every piece uniformly at <= ``motion.point_spacing_mm`` (>= 2 segments),
    optionally smooth."""
    m = job.motion
    P = len(counts)
    pid = np.repeat(np.arange(P), counts)
    pstart = offsets(counts)
    # ---- merge repeated points (zero-length segments are dropped)
    seg = np.diff(V, axis=0)
    seglen = np.hypot(seg[:, 0], seg[:, 1])
    same = pid[1:] == pid[:-1]
    keep = np.ones(len(V), dtype=bool)
    keep[1:] = ~(same & (seglen <= MERGE_MM))
    orig_index = np.flatnonzero(keep) - np.repeat(pstart[:-1], counts)[keep]
    V = V[keep]
    pid = pid[keep]
    counts = np.bincount(pid, minlength=P)
    pstart = offsets(counts)
    K = len(V)

    # ---- PATHSPLIT (thesis 4.1.1): break where the direction turns more than the angle
    e = np.diff(V, axis=0)
    within = pid[1:] == pid[:-1]
    brk = np.zeros(K, dtype=bool)
    brk[pstart[:-1]] = True
    brk[pstart[1:] - 1] = True
    if K > 2:
        e0, e1 = e[:-1], e[1:]
        n0 = np.hypot(e0[:, 0], e0[:, 1])
        n1 = np.hypot(e1[:, 0], e1[:, 1])
        cosang = (e0[:, 0] * e1[:, 0] + e0[:, 1] * e1[:, 1]) / np.maximum(n0 * n1, 1e-300)
        interior = within[:-1] & within[1:]
        split = interior & (cosang < math.cos(math.radians(m.smooth_angle_deg)))
        brk[1:-1] |= split
    bidx = np.flatnonzero(brk)
    a = bidx[:-1]
    b = bidx[1:]
    ok = pid[a] == pid[b]
    a, b = a[ok], b[ok]
    piece_path = pid[a]
    Q = len(a)
    if Q == 0:  # every path is a single point
        e = np.zeros(0, dtype=np.int64)
        z = np.zeros(0)
        return _Split(V=V, pid=pid, counts=counts, pstart=pstart, orig_index=orig_index, a=a,
                      piece_path=piece_path, PV=np.zeros((0, 2)), pvs=np.zeros(1, np.int64),
                      S=z, s0=z, L=z, nseg=e, hk=z, gstart=np.zeros(1, np.int64),
                      gxy=np.zeros((0, 2)), gs=z, fxy=np.zeros((0, 2)), fu=z,
                      fstart=np.zeros(1, np.int64))

    # ---- piece vertex lists and their concatenated arc length (gap between pieces)
    plen = b - a + 1
    pvs = offsets(plen)
    idx = np.arange(pvs[-1]) - np.repeat(pvs[:-1] - a, plen)
    PV = V[idx]
    d = np.diff(PV, axis=0)
    sl = np.concatenate([[0.0], np.hypot(d[:, 0], d[:, 1])])
    sl[pvs[1:-1]] = _GAP
    S = np.cumsum(sl)
    s0 = S[pvs[:-1]]
    L = S[pvs[1:] - 1] - s0

    # ---- resample each piece uniformly (PATHSPLIT, 0.4 mm)
    nseg = np.maximum(2, np.ceil(L / m.point_spacing_mm - 1e-9).astype(np.int64))
    hk = L / nseg
    gstart = offsets(nseg + 1)
    G = int(gstart[-1])
    loc = np.arange(G) - np.repeat(gstart[:-1], nseg + 1)
    gl = loc * np.repeat(hk, nseg + 1)  # from the piece start, mm
    last = gstart[1:] - 1
    gl[last] = L
    gs = np.repeat(s0, nseg + 1) + gl
    gs[last] = s0 + L
    gxy = _mtts.follow_samples(gl, gstart, L, pvs.astype(np.int64), S, PV, s0)
    fxy, fu, fstart = PV, S, pvs.astype(np.int64)
    if m.smoothing_tolerance_mm > 0.0:
        step = FOLLOW_STEP_SPEED_MM_S * m.dt_s
        tol = float(m.smoothing_tolerance_mm)
        DV, DS, dvs = _denser_input(PV, S, pvs, s0, hk, nseg, step)
        if _rounds_corners(m):
            # an output step under the grid's (16 ms): corners become arcs (see there)
            e = CORNER_SHARE * tol
            DV, DS, dvs, gxy = _round_corners(PV, S, pvs, DV, DS, dvs, gxy, gs, e,
                                              float(m.accel_mm_s2), float(m.dt_s), step)
            tol -= e
        gxy, fxy, fu, fstart = _smooth(gxy, gs, gstart, DV, DS, dvs, s0, hk, nseg, tol,
                                       SMOOTH_SIGMA_MM / m.point_spacing_mm)
        if _rounds_corners(m):
            fu = _chord_parameter(fxy, fstart, s0, L)

    return _Split(V=V, pid=pid, counts=counts, pstart=pstart, orig_index=orig_index, a=a,
                  piece_path=piece_path, PV=PV, pvs=pvs, S=S, s0=s0, L=L, nseg=nseg, hk=hk,
                  gstart=gstart, gxy=gxy, gs=gs, fxy=fxy, fu=fu, fstart=fstart)


def _denser_input(PV: np.ndarray, S: np.ndarray, pvs: np.ndarray, s0: np.ndarray,
                  hk: np.ndarray, nseg: np.ndarray, spacing: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pieces' vertex lists (PV (K, 2) mm, arc length S (K,), piece offsets pvs) with
    points added on their segments, so that with the grid (spacing hk, nseg segments per
    piece) they are at most ``spacing`` mm apart: the grid split into equal parts.

    The samples follow the smoothed grid and input vertices linearly, and every point of
    that polyline turning by alpha bounds the speed by v alpha / dt <= A
    (``_mtts._vertex_bounds``). On a curve of curvature kappa with points h apart,
    alpha = kappa h: with h fixed at the 0.4 mm grid, a finer output step lowered that
    bound under the curvature's own (v^2 kappa <= A), and an r 20 mm circle took 2.85 s
    at dt 1 ms against 1.55 s at 16 ms. The added points lie on the input, so the
    smoothing moves them onto its curve like any input vertex, within its tolerance.
    Returns (PV, S, pvs) unchanged when the grid is fine enough (the default dt).
    """
    m = np.maximum(1, np.ceil(hk / spacing - 1e-9)).astype(np.int64)
    if not (m > 1).any():
        return PV, S, pvs
    Q = len(hk)
    count = np.where(m > 1, nseg * m - 1, 0)  # the finer grid's interior points
    piece = np.repeat(np.arange(Q), count)
    k = np.arange(len(piece)) - np.repeat(offsets(count)[:-1], count) + 1
    on_grid = k % m[piece] == 0
    piece, k = piece[~on_grid], k[~on_grid]
    q = s0[piece] + k * (hk / m)[piece]
    # not on an input vertex (S is increasing: pieces are apart by _GAP)
    j = np.clip(np.searchsorted(S, q), 1, len(S) - 1)
    apart = np.minimum(S[j] - q, q - S[j - 1]) > 1e-9
    piece, q = piece[apart], q[apart]
    xy = np.column_stack([np.interp(q, S, PV[:, 0]), np.interp(q, S, PV[:, 1])])
    order = np.argsort(np.concatenate([S, q]), kind="stable")
    added = offsets(np.bincount(piece, minlength=Q))
    return (np.concatenate([PV, xy])[order], np.concatenate([S, q])[order],
            pvs + added)


def _rounds_corners(m) -> bool:
    """Whether the motion settings ``m`` (:class:`icefab.config.MotionSettings`) make the
    followed polyline finer than the grid, with the input's corners as arcs
    (:func:`_round_corners`): path smoothing on and an output step under the grid's,
    ``FOLLOW_STEP_SPEED_MM_S`` x dt < ``point_spacing_mm`` (not at the defaults)."""
    return bool(m.smoothing_tolerance_mm > 0.0
                and FOLLOW_STEP_SPEED_MM_S * m.dt_s < m.point_spacing_mm * (1.0 - 1e-9))


def _chord_parameter(fxy: np.ndarray, fstart: np.ndarray, s0: np.ndarray, L: np.ndarray
                     ) -> np.ndarray:
    """(F,) the followed polyline's parameter (S units) by its own chord length, each piece
    (``fxy[fstart[p]:fstart[p+1]]`` mm) scaled onto [s0[p], s0[p] + L[p]].

    The samples are placed along it by this parameter (``_mtts.follow_samples``). By the
    input's arc length instead, the smoothing's displacements, which vary from point to
    point below the grid's scale, stretch its chords unevenly (by ~1e-3), and at a fine
    step that is tangential acceleration: a wavy path sampled at 1 ms reached 1.5 times
    the bound. The vertex bounds already measure the polyline by its chords
    (``_mtts.polyline_vertices``).
    """
    d = np.hypot(*np.diff(fxy, axis=0).T)
    d[fstart[1:-1] - 1] = 0.0   # no chord between pieces
    c = np.concatenate([[0.0], np.cumsum(d)])
    piece = np.repeat(np.arange(len(L)), np.diff(fstart))
    c0 = c[fstart[:-1]][piece]
    tot = (c[fstart[1:] - 1] - c[fstart[:-1]])[piece]
    u = s0[piece] + (c - c0) / np.maximum(tot, 1e-300) * L[piece]
    u[fstart[1:] - 1] = s0 + L
    return u


def _round_corners(PV: np.ndarray, S: np.ndarray, pvs: np.ndarray, DV: np.ndarray,
                   DS: np.ndarray, dvs: np.ndarray, gxy: np.ndarray, gs: np.ndarray,
                   e: float, accel: float, dt: float, step: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every interior vertex of the pieces' input (PV (K, 2) mm, arc length S (K,), piece
    offsets pvs) replaced by a circular arc tangent to its two segments, at most ``e`` mm
    inside the vertex, in the followed points (DV, DS, dvs: the input with
    :func:`_denser_input`'s points) and in the grid (gxy (G, 2) mm at arc length gs).

    Why (thesis 4.1.1-4.1.2): the samples follow the followed polyline linearly, and a
    point of it turning by beta costs v beta / dt of acceleration at speed v
    (``_mtts._vertex_bounds``). The path smoothing moves every point by at most its
    tolerance, by scaling a regression's displacement; at a polygon's vertex that keeps
    most of the turn at one point (a 25 deg zigzag with 3 mm sides: 20 deg), whose bound
    A dt / beta shrinks with dt: 21 mm/s at 16 ms, 1.4 mm/s at 1 ms (the zigzag 3.6 times
    slower at 1 ms than at 16 ms, 2.7 times TOPP-RA's time). An arc of radius r allows
    sqrt(A r) at every dt (the vertex bound of its points, sampled every
    ``0.5 dt sqrt(A r)`` mm and at most ``step`` mm apart, is twice that). Applied only at
    an output step under the grid's (16 ms at the defaults), where a vertex passed at
    speed is crossed in under one grid step; at 16 ms the step itself spreads the turn.

    The arc takes the parameter range S_v -+ t (t its tangent length, at most half of
    each segment, which bounds r), mapped linearly onto its angle; input points inside it
    are dropped. Its points are within e of the input, its chords within e too (the
    sagitta is kept under 1 % of e). Returns (DV, DS, dvs, gxy) with the arcs.
    """
    Q = len(pvs) - 1
    # interior vertices of every piece
    j = np.arange(len(PV))
    first = np.zeros(len(PV), dtype=bool)
    first[pvs[:-1]] = True
    last = np.zeros(len(PV), dtype=bool)
    last[pvs[1:] - 1] = True
    j = j[~first & ~last]
    if not len(j) or e <= 0.0:
        return DV, DS, dvs, gxy
    din = PV[j] - PV[j - 1]
    dout = PV[j + 1] - PV[j]
    lin = np.hypot(din[:, 0], din[:, 1])
    lout = np.hypot(dout[:, 0], dout[:, 1])
    uin = din / lin[:, None]
    uout = dout / lout[:, None]
    cross = uin[:, 0] * uout[:, 1] - uin[:, 1] * uout[:, 0]
    dot = uin[:, 0] * uout[:, 0] + uin[:, 1] * uout[:, 1]
    alpha = np.abs(np.arctan2(cross, dot))   # the turn, rad (< smooth_angle_deg)
    keep = alpha > 1e-9
    j, uin, uout, cross, alpha = j[keep], uin[keep], uout[keep], cross[keep], alpha[keep]
    lin, lout = lin[keep], lout[keep]
    if not len(j):
        return DV, DS, dvs, gxy
    half = 0.5 * alpha
    ee = 0.99 * e   # the rest (1 %) for the chords' sagitta
    # e = r (1 / cos(alpha / 2) - 1) at the vertex; t = r tan(alpha / 2)
    r = ee / (1.0 / np.cos(half) - 1.0)
    t = np.minimum(r * np.tan(half), 0.5 * np.minimum(lin, lout))
    r = t / np.tan(half)
    sgn = np.where(cross > 0.0, 1.0, -1.0)   # left turn: the centre on the left
    T1 = PV[j] - t[:, None] * uin
    C = T1 + (r * sgn)[:, None] * np.column_stack([-uin[:, 1], uin[:, 0]])
    a0 = np.arctan2(T1[:, 1] - C[:, 1], T1[:, 0] - C[:, 0])
    q0 = S[j] - t
    q1 = S[j] + t
    # arc points: every 0.5 dt sqrt(A r) mm, at most step, sagitta d^2 / (8 r) <= 0.01 e
    d = np.minimum(np.minimum(0.5 * dt * np.sqrt(accel * r), step), np.sqrt(0.08 * e * r))
    cnt = np.maximum(2, np.ceil(2.0 * t / d - 1e-9).astype(np.int64) + 1)
    k = np.arange(int(cnt.sum())) - np.repeat(offsets(cnt)[:-1], cnt)
    span = np.repeat(np.arange(len(j)), cnt)
    frac = k / (cnt[span] - 1)
    aq = q0[span] + frac * (2.0 * t[span])

    def on_arc(sp: np.ndarray, fr: np.ndarray) -> np.ndarray:
        th = a0[sp] + sgn[sp] * alpha[sp] * fr
        return np.column_stack([C[sp, 0] + r[sp] * np.cos(th), C[sp, 1] + r[sp] * np.sin(th)])

    axy = on_arc(span, frac)
    # the spans are apart (t <= half of each segment) and increasing with S
    def inside(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        w = np.searchsorted(q0, q, side="right") - 1
        ok = (w >= 0) & (q > q0[np.maximum(w, 0)]) & (q < q1[np.maximum(w, 0)])
        return ok, np.maximum(w, 0)

    def inside_ends(q: np.ndarray) -> np.ndarray:   # on an arc's end (MERGE_MM)
        w = np.clip(np.searchsorted(q0, q), 0, len(q0) - 1)
        v = np.clip(np.searchsorted(q1, q), 0, len(q1) - 1)
        return ((np.abs(q - q0[w]) <= MERGE_MM) | (np.abs(q - q0[np.maximum(w - 1, 0)])
                <= MERGE_MM) | (np.abs(q - q1[v]) <= MERGE_MM)
                | (np.abs(q - q1[np.maximum(v - 1, 0)]) <= MERGE_MM))

    ok, w = inside(DS)
    piece = np.repeat(np.arange(Q), np.diff(dvs))
    apiece = np.repeat(np.searchsorted(pvs, j, side="right") - 1, cnt)
    # the arc's end points lie on the input segments: drop input points there too
    drop = ok | np.isin(DS, aq) | inside_ends(DS)
    allS = np.concatenate([DS[~drop], aq])
    order = np.argsort(allS, kind="stable")
    # two arcs whose tangent lengths both take half of their shared segment meet at its
    # middle: one point there (a repeated point is a zero-length segment)
    twice = np.zeros(len(order), dtype=bool)
    twice[1:] = np.diff(allS[order]) <= MERGE_MM
    order = order[~twice]
    nDV = np.concatenate([DV[~drop], axy])[order]
    npiece = np.concatenate([piece[~drop], apiece])[order]
    ndvs = offsets(np.bincount(npiece, minlength=Q))
    gxy = gxy.copy()
    gok, gw = inside(gs)
    if gok.any():
        g = np.flatnonzero(gok)
        sp = gw[g]
        gxy[g] = on_arc(sp, (gs[g] - q0[sp]) / (2.0 * t[sp]))
    return nDV, allS[order], ndvs, gxy


def _smooth(gxy: np.ndarray, gs: np.ndarray, gstart: np.ndarray, PV: np.ndarray,
            S: np.ndarray, pvs: np.ndarray, s0: np.ndarray, hk: np.ndarray,
            nseg: np.ndarray, tol: float, sigma_pts: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Optional smoothing of the resampled pieces (thesis 4.1.1) within ``tol`` mm.

    The followed polyline is the grid plus the input's interior vertices (merged by arc
    length), all moved onto the smoothing curve (``_mtts.smooth_followed``) by at most
    ``tol``; two consecutive points lie on one input segment, so every chord is within
    ``tol`` of the input too. Returns (smoothed grid (G, 2), followed polyline (F, 2), its
    parameter (F,) in S units, piece starts (Q+1,)).
    """
    return _mtts.smooth_followed(gstart, gxy, gs, hk, s0, PV, S, pvs.astype(np.int64),
                                 sigma_pts, tol, math.radians(SMOOTH_MAX_TURN_DEG))


def pathsplit(points: np.ndarray, job: Job | None = None) -> list[np.ndarray]:
    """PATHSPLIT of one polyline ``(k, 2)`` mm: the resampled pieces, each ``(n_i, 2)``
    float64 mm, uniformly spaced at <= ``motion.point_spacing_mm`` (thesis 4.1.1)."""
    job = job or Job()
    pts = _as_points(points, "path")
    sp = _pathsplit(pts, np.array([len(pts)]), job)
    return [sp.gxy[a:b] for a, b in zip(sp.gstart[:-1], sp.gstart[1:])]


def followed_path(points: np.ndarray, job: Job | None = None) -> list[np.ndarray]:
    """The polylines the trajectory of one path ``(k, 2)`` mm follows, one ``(n_i, 2)``
    float64 mm per piece: the input's own pieces, or with ``motion.smoothing_tolerance_mm``
    > 0 the smoothed grid and input vertices (``_smooth``), within the tolerance of the
    input."""
    job = job or Job()
    pts = _as_points(points, "path")
    sp = _pathsplit(pts, np.array([len(pts)]), job)
    return [sp.fxy[a:b] for a, b in zip(sp.fstart[:-1], sp.fstart[1:])]


class _Profiles(NamedTuple):
    """The speed profiles of many polylines (:func:`_speed_profiles`), before sampling."""

    sp: _Split             # the PATHSPLIT pieces
    P: int                 # polylines
    v: np.ndarray          # (G,) speed at the grid points, mm/s
    T: np.ndarray          # (Q,) duration of every piece, s
    a0: np.ndarray         # (Q,) rest accelerations at the piece starts and ends
    a1: np.ndarray


class _Prepared(NamedTuple):
    """What the speed profiles of a set of polylines share whatever their speed bounds
    (:func:`_prepare`): ``icefab plan`` plans every layer twice, at MTTS' bounds and at
    the constant-speed case's, and PATHSPLIT, the joint angles at the grid points and the
    workspace checks were a third of each plan (issue 17)."""

    sp: _Split             # the PATHSPLIT pieces
    P: int                 # polylines
    qgrid: np.ndarray      # (G, j) joint angles at the grid points (joints with a bound)
    used: np.ndarray       # (J,) bool: the robot's joints with a finite bound
    vertices: tuple        # the followed polyline of every piece (:func:`_vertices`)
    gjac: np.ndarray       # (G, m, 2) the joints' Jacobian at the grid points
    rest: tuple            # the first and last steps' bounds (:func:`_rest_step_bounds`)


def _prepare(polys: Sequence[np.ndarray] | tuple[np.ndarray, np.ndarray], job: Job,
             robot: Robot, labels: Sequence[tuple[int, int]] | None = None) -> _Prepared:
    """PATHSPLIT and the workspace checks of many polylines, and what their speed profiles
    need besides the speed bounds (no pieces when every polyline is a single point).
    Arguments as :func:`_plan_polylines`."""
    if isinstance(polys, tuple):
        V, counts = polys
    else:
        counts = np.array([len(p) for p in polys], dtype=np.int64)
        V = (np.concatenate(polys).astype(np.float64, copy=False) if len(polys)
             else np.zeros((0, 2)))
    P = len(counts)

    sp = _pathsplit(V, counts, job)
    single = np.flatnonzero(sp.counts == 1)
    if len(single):  # single-point paths have no grid: check their point here
        sbad, sreasons = robot.workspace_violations(sp.V[sp.pstart[single]])
        if len(sbad):
            k = int(single[sbad[0]])
            x, y = sp.V[sp.pstart[k]]
            raise WorkspaceError(f"{_label(labels, k)}: point 0 at ({x:.3f}, {y:.3f}) mm "
                                 f"(robot base frame) is out of the {robot.name} workspace: "
                                 f"{sreasons[0]}")
    if len(sp.a) == 0:
        return _Prepared(sp=sp, P=P, qgrid=np.zeros((0, 0)), used=np.zeros(0, bool),
                         vertices=(), rest=(), gjac=np.zeros((0, 0, 2)))
    V, pid, orig_index = sp.V, sp.pid, sp.orig_index
    a, piece_path, pvs, S = sp.a, sp.piece_path, sp.pvs, sp.S
    hk, gstart, gxy, gs = sp.hk, sp.gstart, sp.gxy, sp.gs
    K = len(V)

    # ---- workspace check before any planning: every input point, then every grid point
    # (a chord can leave the workspace between two reachable points, e.g. across the inner
    # reach circle: the message names the segment)
    qgrid = robot.ik(gxy)
    gbad, greasons = robot.workspace_violations(gxy, qgrid)
    vbad, vreasons = robot.workspace_violations(V)
    if len(vbad):
        i = int(vbad[0])
        k = int(pid[i])
        raise WorkspaceError(f"{_label(labels, k)}: point {orig_index[i]} at ({V[i, 0]:.3f}, "
                             f"{V[i, 1]:.3f}) mm (robot base frame) is out of the "
                             f"{robot.name} workspace: {vreasons[0]}")
    if len(gbad):
        g = int(gbad[0])
        q = int(np.searchsorted(gstart, g, side="right") - 1)
        k = int(piece_path[q])
        j = int(np.searchsorted(S, gs[g], side="right") - 1)
        j = min(max(j, pvs[q]), pvs[q + 1] - 2)
        vert = a[q] + (j - pvs[q])
        i0 = int(orig_index[vert])
        i1 = int(orig_index[min(vert + 1, K - 1)])
        raise WorkspaceError(f"{_label(labels, k)}: the segment from point {i0} to point {i1} "
                             f"passes ({gxy[g, 0]:.3f}, {gxy[g, 1]:.3f}) mm (robot base "
                             f"frame), out of the {robot.name} workspace: {greasons[0]}")
    _check_no_joint_wrap(qgrid, gstart, gxy, piece_path, labels, robot)
    # only joints with a finite bound take part in the planning
    qv = np.asarray(robot.joint_speed_max, dtype=np.float64)
    qa = np.asarray(robot.joint_accel_max, dtype=np.float64)
    qj = np.asarray(robot.joint_jerk_max, dtype=np.float64)
    used = np.isfinite(qv) | np.isfinite(qa) | np.isfinite(qj)
    qfull = qgrid
    qgrid = np.ascontiguousarray(qgrid[:, used])
    # the polyline each piece follows (its vertices, turning vectors, arc length)
    vertices = _vertices(sp.fxy, sp.fstart)
    # the joints' Jacobian at the grid points, for the vertex bounds (at a vertex, the
    # nearest grid point's: 0.4 mm away at most); per vertex it cost 16 ms a bunny layer
    gjac = np.ascontiguousarray(_ik_jacobian(robot, gxy, qfull)[:, used])
    rest = _rest_step_bounds(gstart, hk, qgrid, robot, used, qa[used],
                             float(job.motion.accel_mm_s2), gxy)
    return _Prepared(sp=sp, P=P, qgrid=qgrid, used=used, vertices=vertices, rest=rest,
                     gjac=gjac)


def _check_no_joint_wrap(qgrid: np.ndarray, gstart: np.ndarray, gxy: np.ndarray,
                         piece_path: np.ndarray, labels, robot: Robot) -> None:
    """WorkspaceError when a path's grid crosses the half-line from a SCARA's base where
    its joint 1 turns through +/-180 degrees: the inverse kinematics gives joint 1 within
    one turn, so there it jumps by a full turn between neighbouring points. A joint range
    of 180 degrees or more (cell.joint_range_deg) lets such a path through the range
    checks, and its rates read as a full turn in one step: a hunt's 25 degree arc planned
    as 11.7 days of 63 M samples (6 GB), and 'icefab plan' ran out of memory."""
    if not isinstance(robot, Scara) or len(qgrid) < 2:
        return
    jump = np.abs(np.diff(qgrid[:, 0])) > np.pi
    jump[gstart[1:-1] - 1] = False      # from one piece's last point to the next's first
    if not jump.any():
        return
    g = int(np.flatnonzero(jump)[0])
    q = int(np.searchsorted(gstart, g, side="right") - 1)
    x, y = gxy[g]
    raise WorkspaceError(
        f"{_label(labels, int(piece_path[q]))}: passes ({x:.3f}, {y:.3f}) mm (robot base "
        "frame), where the SCARA's joint 1 would turn through +/-180 deg: icefab plans "
        "joint 1 within one turn (-180 to 180 deg), whatever cell.joint_range_deg allows; "
        "move or turn the part so that no path crosses that line (cell.ee_origin_mm, "
        "parts.rotation_deg)")


def _profiles(prep: _Prepared, vcaps: np.ndarray, job: Job, robot: Robot) -> _Profiles:
    """The minimum-time speed profile of every piece of ``prep`` under the speed bounds
    ``vcaps`` ((P,) mm/s, one per polyline): VCON, ACON, JCON, AREST in one compiled call
    for all of them, up to the durations."""
    sp = prep.sp
    if len(sp.a) == 0:
        z = np.zeros(0)
        return _Profiles(sp=sp, P=prep.P, v=z, T=z, a0=z, a1=z)
    vcap_piece = np.asarray(vcaps, dtype=np.float64)[sp.piece_path]
    v, T, a0, a1 = _piece_profiles(sp.gstart, sp.hk, sp.gxy, prep.vertices, prep.qgrid,
                                   prep.gjac,
                                   prep.rest, vcap_piece, prep.used, job, robot)
    return _Profiles(sp=sp, P=prep.P, v=v, T=T, a0=a0, a1=a1)


def _piece_profiles(gstart: np.ndarray, hk: np.ndarray, gxy: np.ndarray, vertices: tuple,
                    qgrid: np.ndarray, gjac: np.ndarray, rest: tuple, vcap_piece: np.ndarray,
                    used: np.ndarray, job: Job, robot: Robot
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The compiled speed profiles of pieces on their grids (:class:`_Prepared`'s arrays,
    ``vcap_piece`` (Q,) mm/s one per piece): v (G,), T, a0, a1 (Q,). Each piece is
    planned on its own rows alone, so any subset of pieces gets the same values."""
    m = job.motion
    qv = np.asarray(robot.joint_speed_max, dtype=np.float64)[used]
    qa = np.asarray(robot.joint_accel_max, dtype=np.float64)[used]
    qj = np.asarray(robot.joint_jerk_max, dtype=np.float64)[used]

    # ---- VCON, ACON, JCON, AREST (compiled)
    jerk_on = bool(m.jerk_limited)
    # the rest curves' initial acceleration within the total bound (a rest_accel_mm_s2
    # above accel_mm_s2 planned 2.6 times the bound; both settings in their ranges)
    a_rest = min(float(m.rest_accel_mm_s2), float(m.accel_mm_s2))
    vstart, vs_loc, vtau = vertices
    dmin0, dmin1, cap0, cap1 = rest
    v, env, T = _mtts.speed_profiles(
        _mtts.PieceGrid(gstart, hk, gxy, vstart, vs_loc, vtau, gjac),
        _mtts.CartesianLimits(vcap_piece, float(m.accel_mm_s2), float(m.jerk_mm_s3),
                              bool(jerk_on), a_rest, cap0, cap1),
        _mtts.JointLimits(qgrid, qv, qa, qj),
        _mtts.Sampling(float(m.dt_s), JERK_WINDOW_MM, JCON_TOLERANCE, _rounds_corners(m)))

    # ---- AREST with the encoder resolution: first and last steps of every piece
    dt = float(m.dt_s)
    a0, a1, T = _mtts.rest_accelerations(gstart, hk, v, T, dt,
                                         a_rest if jerk_on else -1.0,
                                         dmin0, dmin1, cap0, cap1)
    return v, T, a0, a1


def _ragged_rows(starts: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the ragged items ``sel`` (item k: rows ``starts[k]:starts[k + 1]``): their
    row indices, in order, and their own starts (len(sel) + 1,)."""
    counts = np.diff(starts)[sel]
    new = offsets(counts)
    return np.repeat(starts[:-1][sel] - new[:-1], counts) + np.arange(new[-1]), new


def _piece_times(prep: _Prepared, vcaps: np.ndarray, job: Job, robot: Robot,
                 sel: np.ndarray) -> np.ndarray:
    """(len(sel),) s: the durations :func:`_profiles` gives the pieces ``sel`` (indices)
    under ``vcaps`` ((P,) mm/s, one per polyline), planning those pieces alone."""
    sp = prep.sp
    if not len(sel):
        return np.zeros(0)
    rows, gstart = _ragged_rows(sp.gstart, sel)
    vstart, vs_loc, vtau = prep.vertices
    vrows, vnew = _ragged_rows(vstart, sel)
    rest = tuple(np.ascontiguousarray(r[sel]) for r in prep.rest)
    return _piece_profiles(gstart, np.ascontiguousarray(sp.hk[sel]),
                           np.ascontiguousarray(sp.gxy[rows]),
                           (vnew, np.ascontiguousarray(vs_loc[vrows]),
                            np.ascontiguousarray(vtau[vrows])),
                           np.ascontiguousarray(prep.qgrid[rows]),
                           np.ascontiguousarray(prep.gjac[rows]), rest,
                           np.asarray(vcaps, dtype=np.float64)[sp.piece_path[sel]],
                           prep.used, job, robot)[1]


def _speed_profiles(polys: Sequence[np.ndarray] | tuple[np.ndarray, np.ndarray],
                    vcaps: np.ndarray, job: Job, robot: Robot,
                    labels: Sequence[tuple[int, int]] | None = None) -> _Profiles:
    """PATHSPLIT, workspace checks and the minimum-time speed profile of every piece (one
    compiled call for all of them), up to the durations (no pieces, and empty profiles,
    when every polyline is a single point). Arguments as :func:`_plan_polylines`."""
    return _profiles(_prepare(polys, job, robot, labels), vcaps, job, robot)


def _piece_samples(T: np.ndarray, dt: float) -> np.ndarray:
    """Sampling steps of every piece: its duration in whole steps of dt (>= 1)."""
    return np.maximum(1, np.ceil(T / dt - 1e-9).astype(np.int64))


def _plan_durations(polys: Sequence[np.ndarray] | tuple[np.ndarray, np.ndarray],
                    vcaps: np.ndarray, job: Job, robot: Robot,
                    labels: Sequence[tuple[int, int]] | None = None) -> np.ndarray:
    """(P,) the duration, s, of every polyline's trajectory as :func:`_plan_polylines`
    samples it (its pieces' whole steps of dt; 0 for a single point), without the
    samples: what a comparison of build times needs (``icefab plan``'s constant-speed
    case), at the cost of the speed profiles alone."""
    return _durations(_speed_profiles(polys, vcaps, job, robot, labels), job)


def _durations(pr: _Profiles, job: Job) -> np.ndarray:
    """(P,) s: every polyline's duration from its pieces' profiles (whole steps of dt)."""
    dt = float(job.motion.dt_s)
    if len(pr.T) == 0:
        return np.zeros(pr.P)
    return np.bincount(pr.sp.piece_path, weights=_piece_samples(pr.T, dt), minlength=pr.P) * dt


def _plan_polylines(polys: Sequence[np.ndarray] | tuple[np.ndarray, np.ndarray],
                    vcaps: np.ndarray, job: Job, robot: Robot,
                    labels: Sequence[tuple[int, int]] | None = None,
                    paths: Sequence[Toolpath | None] | None = None,
                    profiles: _Profiles | None = None) -> list[Trajectory]:
    """Plan many polylines at once (one compiled call for all of them).

    polys: P arrays (k_i, 2) float64 mm in the robot base frame (closed paths with their
    first point repeated at the end), or already concatenated: a tuple (V (K, 2) float64
    mm, counts (P,) int64). vcaps: (P,) mm/s speed bound per path.
    labels: (layer, path index) per polyline, for error messages.
    profiles: ``_speed_profiles(polys, vcaps, job, robot, labels)`` when the caller has
    them already.

    A trajectory whose joints' sampled acceleration (second differences at ``dt``)
    exceeds a joint's bound by a factor is planned again under the joints' acceleration
    bounds lowered by the square root of that factor and ``JOINT_REPLAN_MARGIN`` (up to
    ``JOINT_REPLANS`` times; the excess does not scale with the bounds, a whole factor
    slowed a path 1.35 times over by 17 %): near the SCARA's full reach the joints' rates
    change within a grid step faster than the bounds at its points say (a hunt's circles
    2-15 mm inside the reach reached 1.04-1.26 times joint 2's bound in their slow-down to
    rest). :func:`plan_paths_durations` times the first plan.
    """
    out = _plan_polylines_once(polys, vcaps, job, robot, labels, paths, profiles)
    qa = np.asarray(robot.joint_accel_max, dtype=np.float64)
    if not (np.isfinite(qa).any() and out):
        return out
    pts = None   # the polylines one by one, split only when a path is planned again
    scale = np.ones(len(out))
    for _ in range(JOINT_REPLANS):
        over = _joint_accel_over(out, qa)
        if not over:
            break
        if pts is None:
            pts = (split_rows(polys[0], np.cumsum(polys[1])[:-1])
                   if isinstance(polys, tuple) else list(polys))
        ks = sorted(over)
        for k in ks:
            scale[k] *= (JOINT_REPLAN_MARGIN / over[k]) ** 0.5
        # one plan per distinct factor (every path of a call is planned alike)
        for f in sorted({float(scale[k]) for k in ks}):
            sub = [k for k in ks if float(scale[k]) == f]
            slow = _replace(robot, joint_accel_max=qa * f)
            again = _plan_polylines_once(
                [pts[k] for k in sub], np.asarray(vcaps, dtype=np.float64)[sub], job, slow,
                [labels[k] for k in sub] if labels else None,
                [paths[k] for k in sub] if paths else None)
            for k, tr in zip(sub, again):
                out[k] = tr
    return out


#: Re-plans of a trajectory whose sampled joint acceleration exceeds its bound
#: (:func:`_plan_polylines`), each under the bounds lowered by the square root of the
#: excess and this margin.
JOINT_REPLANS = 4
JOINT_REPLAN_MARGIN = 0.98


def _joint_accel_over(trajs: Sequence[Trajectory], qa: np.ndarray) -> dict[int, float]:
    """{index: ratio > 1} of the trajectories whose joints' second differences exceed the
    joint acceleration bounds ``qa`` (rad/s^2, inf where none) by more than 1e-6."""
    ks = [k for k, tr in enumerate(trajs)
          if tr.joints.ndim == 2 and len(tr.joints) >= 3 and tr.joints.shape[1] == len(qa)]
    if not ks:
        return {}
    # all at once (one numpy pass; a loop over a bunny layer's paths cost 35 us each)
    n = np.array([len(trajs[k].joints) for k in ks])
    q = np.concatenate([trajs[k].joints for k in ks])
    dt = np.repeat([float(trajs[k].dt) for k in ks], n - 2)
    a = np.abs(q[2:] - 2.0 * q[1:-1] + q[:-2])
    start = offsets(n)[:-1]
    inside = np.ones(len(a), dtype=bool)   # the windows within one trajectory
    inside[np.concatenate([start[1:] - 2, start[1:] - 1])] = False
    r = (a[inside] / qa).max(axis=1) / (dt * dt)
    worst = np.maximum.reduceat(r, offsets(n - 2)[:-1])
    return {ks[i]: float(w) for i, w in enumerate(worst) if w > 1.0 + 1e-6}


def _plan_polylines_once(polys: Sequence[np.ndarray] | tuple[np.ndarray, np.ndarray],
                         vcaps: np.ndarray, job: Job, robot: Robot,
                         labels: Sequence[tuple[int, int]] | None = None,
                         paths: Sequence[Toolpath | None] | None = None,
                         profiles: _Profiles | None = None) -> list[Trajectory]:
    """:func:`_plan_polylines` without the joint acceleration's re-plans."""
    pr = profiles if profiles is not None else _speed_profiles(polys, vcaps, job, robot,
                                                               labels)
    in_counts = (polys[1] if isinstance(polys, tuple) else
                 np.array([len(p) for p in polys], dtype=np.int64))
    if len(pr.T) == 0:
        return [_single_point(pr.sp.V[pr.sp.pstart[k]], job, robot, paths[k] if paths else None)
                for k in range(pr.P)]
    sp, P, v, T, a0, a1 = pr.sp, pr.P, pr.v, pr.T, pr.a0, pr.a1
    trajs_empty = sp.counts == 1
    V, pstart = sp.V, sp.pstart
    piece_path, s0, L = sp.piece_path, sp.s0, sp.L
    hk, gstart = sp.hk, sp.gstart
    Q = len(sp.a)
    dt = float(job.motion.dt_s)

    # ---- constant-dt sampling
    nsamp = _piece_samples(T, dt)
    sstart = offsets(nsamp + 1)
    s_loc, spd = _mtts.sample_pieces(gstart, hk, v, T, nsamp, sstart[:-1].copy(), dt, a0, a1)
    # follow the input polyline, or the smoothed one (piecewise linear, parameter in S
    # units: the grid's s is the resampled path's arc length); rest points exactly on the
    # corners
    xy = _mtts.follow_samples(s_loc, sstart, L, sp.fstart, sp.fu, sp.fxy, s0)
    own = bool(paths) and any(_own_widths(p) for p in paths)
    off = _segment_off(paths, in_counts, sp, labels) if own else None
    widths = _sample_widths(paths, in_counts, labels, sp, s_loc, nsamp, off) if own else None

    # ---- concatenate the pieces of each path: the shared corner sample appears once
    first_of_path = np.ones(Q, dtype=bool)
    first_of_path[1:] = piece_path[1:] != piece_path[:-1]
    keep_s = np.ones(len(xy), dtype=bool)
    keep_s[sstart[:-1][~first_of_path]] = False
    xy = xy[keep_s]
    spd = spd[keep_s]
    if widths is not None:
        widths = widths[keep_s]
    piece_n = nsamp + first_of_path  # samples each piece contributes
    path_n = np.bincount(piece_path, weights=piece_n, minlength=P).astype(np.int64)
    tstart = offsets(path_n)
    # piece start indices within their trajectory
    cum = offsets(piece_n)[:-1]
    piece_first_sample = cum - tstart[piece_path]
    piece_first_sample[~first_of_path] -= 1  # the shared corner sample
    spans = (_switch_spans(paths, off, sp, s_loc, nsamp, keep_s, tstart, dt)
             if own and any(p is not None and p.off is not None for p in paths) else {})

    rests = tstart[piece_path] + piece_first_sample  # every piece's first sample
    joints = _joint_samples(xy, tstart, job, robot, rests)

    out: list[Trajectory] = []
    # pieces of path k: piece_path is sorted, so they are qb[k]:qb[k+1]
    qb = np.searchsorted(piece_path, np.arange(P + 1)).tolist()
    piece_first_sample = piece_first_sample.astype(np.int64)
    ts = tstart.tolist()
    empty = trajs_empty.tolist()
    for k in range(P):
        pth = paths[k] if paths else None
        if empty[k]:
            out.append(_single_point(V[pstart[k]], job, robot, pth))
            continue
        r0, r1 = ts[k], ts[k + 1]
        out.append(Trajectory(dt=dt, xy=xy[r0:r1], joints=joints[r0:r1], speed=spd[r0:r1],
                              duration=(r1 - r0 - 1) * dt, path=pth,
                              pieces=piece_first_sample[qb[k]:qb[k + 1]],
                              widths=widths[r0:r1] if _own_widths(pth) else None,
                              on_spans=spans.get(k)))
    return out


def _own_widths(path: Toolpath | None) -> bool:
    """Whether a path's trajectory carries a width per sample: a variable-width path, or
    one with ``off`` segments (a tour: 0 wide where the valve is off)."""
    return path is not None and (path.widths is not None or path.off is not None)


def _sample_widths(paths: Sequence[Toolpath | None], in_counts: np.ndarray,
                   labels: Sequence[tuple[int, int]] | None, sp: _Split, s_loc: np.ndarray,
                   nsamp: np.ndarray, off: np.ndarray | None = None) -> np.ndarray:
    """(M,) float64 mm: the deposition width at every sample of every piece (before the
    shared corner samples are dropped): the paths' per-point widths
    (:meth:`~icefab.core.Toolpath.polyline_widths`), linear along each segment, at the
    sample's arc position (the samples follow the path, or its smoothing within
    ``motion.smoothing_tolerance_mm``, at the same parameter); 0 on the segments that are
    ``off`` (a tour's travel: the valve is off there, Ossino's OFF). IcefabError naming the
    path when its widths are not one finite number >= 0 per point, or its ``off`` not one
    bool per point. off: :func:`_segment_off`, when the caller has it."""
    starts = offsets(in_counts)
    # every point at its path's width, then the variable paths' own
    W = np.repeat([0.0 if p is None else float(p.width) for p in paths], in_counts)
    if off is None:
        off = _segment_off(paths, in_counts, sp, labels)
    var = [k for k, p in enumerate(paths) if p is not None and p.widths is not None]
    # all of them checked at once, path by path only to name the first bad one
    ok, _w = checked_widths([paths[k].widths for k in var],
                            [len(paths[k].points) for k in var])
    if not ok.all():
        for k in var:
            problem = widths_problem(paths[k])
            if problem:
                raise IcefabError(f"{_label(labels, k)}: {problem}")
    for k in var:
        W[starts[k]:starts[k + 1]] = paths[k].polyline_widths()
    Wv = W[offsets(in_counts)[:-1][sp.pid] + sp.orig_index]   # the merged vertices'
    plen = np.diff(sp.pvs)
    pv = np.arange(sp.pvs[-1]) - np.repeat(sp.pvs[:-1] - sp.a, plen)
    Wpv = Wv[pv]
    q = np.repeat(np.arange(len(nsamp)), nsamp + 1)
    x = np.minimum(s_loc, sp.L[q]) + sp.s0[q]
    out = np.interp(x, sp.S, Wpv)
    if off.any():
        Opv = off[pv]
        # the segment each sample lies on, named by its first vertex (a piece's last
        # sample by the segment it ends)
        j = np.searchsorted(sp.S, x, side="right") - 1
        j = np.maximum(np.minimum(j, sp.pvs[1:][q] - 2), sp.pvs[:-1][q])
        out[Opv[j]] = 0.0
    return out


def _segment_off(paths: Sequence[Toolpath | None], in_counts: np.ndarray, sp: _Split,
                 labels: Sequence[tuple[int, int]] | None = None) -> np.ndarray:
    """(K,) bool per merged vertex (``sp.V``): the segment leaving it is ``off`` (a tour's
    travel). A vertex that stands for repeated points takes the state of the segment that
    leaves the last of them, the one with a length. IcefabError naming the path when its
    ``off`` is not one bool per point."""
    starts = offsets(in_counts)
    O = np.zeros(int(starts[-1]), dtype=bool)
    for k, p in enumerate(paths):
        if p is not None and p.off is not None:
            problem = off_problem(p)
            if problem:
                raise IcefabError(f"{_label(labels, k)}: {problem}")
            O[starts[k]:starts[k] + len(p.points)] = np.asarray(p.off, dtype=bool)
    g = starts[:-1][sp.pid] + sp.orig_index          # each merged vertex's own point
    last = g.copy()
    same = sp.pid[1:] == sp.pid[:-1]
    last[:-1][same] = g[1:][same] - 1                # the last of the points it merges
    return O[last]


def _switch_spans(paths: Sequence[Toolpath | None], off: np.ndarray, sp: _Split,
                  s_loc: np.ndarray, nsamp: np.ndarray, keep_s: np.ndarray,
                  tstart: np.ndarray, dt: float) -> dict[int, np.ndarray]:
    """The spans the valve is on (:attr:`~icefab.core.Trajectory.on_spans`) of every path
    with ``off`` segments, by path index: the instants where the samples pass each point
    at which the path's segments switch between on and off (a tour's path ends and
    starts), linear in arc between the two samples around it -- the samples are followed
    linearly, so the nozzle is at the switch point at that instant (the smoothed path's
    parameter is the input path's arc, so the point is where the path has it).

    off: :func:`_segment_off`; s_loc, nsamp: the pieces' samples before the shared corner
    samples are dropped (``keep_s`` False at those); tstart: first kept sample of every
    path."""
    tours = np.array([k for k, p in enumerate(paths) if p is not None and p.off is not None],
                     dtype=np.int64)
    # every piece's segments, by their first vertex, in path order
    plen = np.diff(sp.pvs)
    pv = np.arange(sp.pvs[-1]) - np.repeat(sp.pvs[:-1] - sp.a, plen)   # merged vertex
    is_seg = np.ones(len(pv), dtype=bool)
    is_seg[sp.pvs[1:] - 1] = False
    seg = np.flatnonzero(is_seg)
    seg_q = np.repeat(np.arange(len(plen)), plen - 1)
    seg_path = sp.piece_path[seg_q]
    state_off = off[pv[seg]]
    change = np.zeros(len(seg), dtype=bool)
    change[1:] = (state_off[1:] != state_off[:-1]) & (seg_path[1:] == seg_path[:-1])
    # the time at which each switch point is passed, linear in arc between two samples
    sw = np.flatnonzero(change)
    X = sp.S[seg[sw]]
    q = seg_q[sw]
    sstart = offsets(nsamp + 1)
    lo, hi = sstart[:-1][q], sstart[1:][q] - 1                # the piece's first and last
    q_of = np.repeat(np.arange(len(nsamp)), nsamp + 1)
    x = np.minimum(s_loc, sp.L[q_of]) + sp.s0[q_of]          # arc position, S units
    i = np.clip(np.searchsorted(x, X, side="right") - 1, lo, np.maximum(hi - 1, lo))
    j = np.minimum(i + 1, hi)
    kept = np.cumsum(keep_s) - 1          # a dropped corner sample is the one before it
    t_i = (kept[i] - tstart[sp.piece_path[q]]) * dt          # within its trajectory
    t_j = (kept[j] - tstart[sp.piece_path[q]]) * dt
    run = x[j] - x[i]
    frac = np.clip(np.divide(X - x[i], run, out=np.zeros(len(X)), where=run > 0), 0.0, 1.0)
    t_sw = t_i + frac * (t_j - t_i)
    # each tour's edges: its start if it starts on, its switches, its end if it ends on
    first_seg = np.searchsorted(seg_path, tours)
    last_seg = np.searchsorted(seg_path, tours, side="right") - 1
    has = (first_seg < len(seg)) & (last_seg >= first_seg)       # a segment at all
    has[has] &= seg_path[first_seg[has]] == tours[has]
    tours, first_seg, last_seg = tours[has], first_seg[has], last_seg[has]
    duration = (tstart[tours + 1] - tstart[tours] - 1) * dt
    opens = ~state_off[first_seg]
    closes = ~state_off[last_seg]
    sw_path = seg_path[sw]
    mine = np.isin(sw_path, tours)
    owner = np.concatenate([tours[opens], sw_path[mine], tours[closes]])
    order = np.concatenate([np.full(int(opens.sum()), -1.0), np.arange(len(sw))[mine],
                            np.full(int(closes.sum()), np.inf)])
    dur_of = np.zeros(len(paths))
    dur_of[tours] = duration
    value = np.concatenate([np.zeros(int(opens.sum())), t_sw[mine], duration[closes]])
    by = np.lexsort((order, owner))
    owner, value = owner[by], np.clip(value[by], 0.0, dur_of[owner[by]])
    # never backwards within a tour: a running maximum, tour by tour
    base = np.zeros(len(paths))
    base[tours] = offsets(duration + 1.0)[:-1]
    value = np.maximum.accumulate(value + base[owner]) - base[owner]
    bounds = np.searchsorted(owner, np.append(tours, len(paths)))
    edges = value.reshape(-1, 2)
    return {k: edges[a // 2:b // 2] for k, a, b in zip(tours.tolist(), bounds[:-1].tolist(),
                                                       bounds[1:].tolist())}


def _vertices(pts: np.ndarray, start: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices of concatenated polylines (piece k is ``pts[start[k]:start[k+1]]``):
    (start, arc length from the piece start (K,) mm, turning vectors (K, 2) = change of
    the unit tangent, zero at the piece ends)."""
    start = start.astype(np.int64)
    s_loc, tau = _mtts.polyline_vertices(np.ascontiguousarray(pts, dtype=np.float64), start)
    return start, s_loc, tau


def _wrapped(dq: np.ndarray) -> np.ndarray:
    """Joint differences over a step of a fraction of a millimetre, into [-pi, pi): a
    rotary joint's angle wraps at +-pi (a prismatic one moves far less than pi mm)."""
    return dq - (2.0 * np.pi) * np.round(dq / (2.0 * np.pi))


#: Step of the central differences of :func:`_ik_jacobian`, mm.
JACOBIAN_STEP_MM = 1e-4


def _ik_jacobian(robot: Robot, xy: np.ndarray, joints: np.ndarray | None = None
                 ) -> np.ndarray:
    """(k, joints, 2): d joints / d (x, y) at points xy (k, 2) mm: the robot's own
    (``robot.jacobian``, the SCARA's and the gantry's analytic) or central differences of
    ``robot.ik`` (a registered robot without one); one-sided where a step leaves the
    reach (NaN), zero where both do. ``joints``: ``robot.ik(xy)`` when at hand."""
    own = getattr(robot, "jacobian", None)
    if own is not None:   # the differences cost 4 ik calls and the wrapping per point
        return np.asarray(own(xy, joints), dtype=np.float64)
    e = JACOBIAN_STEP_MM
    q0 = robot.ik(xy) if joints is None else joints
    out = np.zeros(q0.shape + (2,))
    for c in range(2):
        d = np.zeros(2)
        d[c] = e
        qp, qm = robot.ik(xy + d), robot.ik(xy - d)
        col = _wrapped(qp - qm) / (2.0 * e)
        col = np.where(np.isnan(col), _wrapped(qp - q0) / e, col)
        col = np.where(np.isnan(col), _wrapped(q0 - qm) / e, col)
        out[:, :, c] = np.nan_to_num(col, nan=0.0, posinf=0.0, neginf=0.0)
    return out


def _single_point(p: np.ndarray, job: Job, robot: Robot, path: Toolpath | None) -> Trajectory:
    xy = np.asarray(p, dtype=np.float64).reshape(1, 2)
    widths = None
    if path is not None and path.widths is not None:
        widths = np.asarray(path.polyline_widths()[:1], dtype=np.float64)
    return Trajectory(dt=float(job.motion.dt_s), xy=xy, joints=robot.ik(xy),
                      speed=np.zeros(1), duration=0.0, path=path,
                      pieces=np.zeros(1, dtype=np.int64), widths=widths)


@lru_cache(maxsize=8)
def _savgol_coeffs(window: int) -> np.ndarray:
    """(window,) float64: the cubic Savitzky-Golay smoothing filter (thesis 4.2.6)."""
    from scipy.signal import savgol_coeffs  # scipy.signal is slow to import; only here
    coeffs = savgol_coeffs(window, 3)
    coeffs.setflags(write=False)
    return coeffs


#: The step, mm, over which a joint's rate along the path is taken at a rest point
#: (:func:`_rest_step_bounds`): short enough to see the rate blow up near a singularity
#: (0.01 mm from the SCARA's full reach, within 3 % of the exact rate), long enough that
#: the inverse kinematics' rounding stays far below it.
REST_RATE_STEP_MM = 1e-3


def _rest_step_bounds(gstart: np.ndarray, hk: np.ndarray, qgrid: np.ndarray, robot: Robot,
                      used: np.ndarray, qa: np.ndarray, accel: float, gxy: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What AREST needs at both ends of every piece (thesis 4.2.6).

    dmin0, dmin1 (Q,) mm: the shortest first / last step that turns some joint by its
    encoder resolution (``robot.joint_resolution``, e.g. ``cell.encoder_resolution_deg``;
    2 % margin for the joints' curvature over the step), from the joints' rate along s
    over the end grid segment; 0 where no joint with a resolution moves. cap0, cap1 (Q,)
    mm/s^2: the largest initial acceleration at rest (total acceleration bound and every
    joint's acceleration bound: |q'_j| a <= qa_j at zero speed), with the rate the larger
    of the end segment's and the rest point's own (over ``REST_RATE_STEP_MM`` towards the
    next grid point): towards the SCARA's full reach the elbow's rate grows like
    1 / sqrt(distance), so a stop 1 mm from it met the segment's mean rate with 80 mm/s^2
    and turned joint 2 at 1.27 times its bound.
    """
    Q = len(gstart) - 1
    res = getattr(robot, "joint_resolution", None)
    res = (np.zeros(int(used.sum())) if res is None
           else np.asarray(res, dtype=np.float64)[used])
    g0 = gstart[:-1]
    g1 = gstart[1:] - 1
    out = []
    for a, b, end in ((g0, g0 + 1, g0), (g1 - 1, g1, g1)):
        rate = np.abs(qgrid[b] - qgrid[a]) / hk[:, None]  # joint units per mm
        other = a + b - end
        step = gxy[other] - gxy[end]
        step *= (REST_RATE_STEP_MM / np.maximum(hk, REST_RATE_STEP_MM))[:, None]
        near = robot.ik(gxy[end] + step)[:, used]
        at_rest = np.maximum(rate, np.abs(near - qgrid[end]) / REST_RATE_STEP_MM)
        with np.errstate(divide="ignore", invalid="ignore"):
            need = np.where((res > 0.0) & (rate > 1e-12), res / rate, np.inf)
            cap = np.where(np.isfinite(qa) & (at_rest > 1e-12), qa / at_rest, np.inf)
        dmin = need.min(axis=1) if need.shape[1] else np.full(Q, np.inf)
        out.append(np.where(np.isfinite(dmin), 1.02 * dmin, 0.0))
        out.append(np.minimum(cap.min(axis=1) if cap.shape[1] else np.inf, accel)
                   * np.ones(Q))
    return out[0], out[2], out[1], out[3]


def _joint_samples(xy: np.ndarray, tstart: np.ndarray, job: Job, robot: Robot,
                   rests: np.ndarray | None = None) -> np.ndarray:
    """(M, j) joints of the samples: inverse kinematics, then the 7-point cubic
    Savitzky-Golay filter (thesis 4.2.6) away from trajectory ends and rest points
    (``rests``: sample indices of every piece start; AREST's end steps stay as planned),
    kept where the tool moves by less than :func:`savgol_deviation_mm`."""
    q = robot.ik(xy)
    w = int(job.motion.savgol_window)
    bound = savgol_deviation_mm(job)
    if w == 0 or len(q) < w or bound <= 0.0:
        return q
    sm = convolve1d(q, _savgol_coeffs(w), axis=0, mode="nearest")
    h = w // 2
    near_end = np.zeros(len(q), dtype=bool)
    ends = np.concatenate([tstart[:-1], tstart[1:] - 1]
                          + ([np.asarray(rests, dtype=np.int64)] if rests is not None else []))
    off = np.arange(-h, h + 1)
    near = (ends[:, None] + off[None, :]).ravel()
    near_end[near[(near >= 0) & (near < len(q))]] = True
    dev = np.hypot(*(robot.fk(sm) - xy).T)
    raw = near_end | (dev > bound) | ~np.isfinite(dev)
    sm[raw] = q[raw]
    return sm


def savgol_deviation_mm(job: Job) -> float:
    """How far the joints' Savitzky-Golay smoothing may move the tool, mm: what the path
    smoothing leaves of ``PATH_FOLLOW_MM``, at most ``SAVGOL_MAX_DEVIATION_MM`` (0.01 up
    to a smoothing tolerance of 0.01 mm; 0, filter skipped, from 0.02 mm up: the
    default)."""
    return float(min(SAVGOL_MAX_DEVIATION_MM,
                     max(0.0, PATH_FOLLOW_MM - job.motion.smoothing_tolerance_mm)))


# --------------------------------------------------------------------------- public


def _path_label(path: Toolpath, index: int | None) -> str:
    """A Path's identity for error messages: its layer, its index in the layer when the
    caller knows it, else its material and role."""
    parts = [f"layer {path.layer}"] if path.layer >= 0 else []
    parts.append(f"path {index} ({path.material} {path.role})" if index is not None
                 else f"{path.material} {path.role} path")
    return ", ".join(parts)


def plan_motion(path_or_points: Toolpath | np.ndarray, job: Job | None = None, *,
                robot: Robot | None = None, index: int | None = None) -> Trajectory:
    """Minimum-time trajectory along one path (thesis Ch. 4).

    path_or_points: a :class:`~icefab.core.Toolpath` (converted to the robot base frame with
        its tool's frame, ``icefab.frames.to_base_frame``; speed bound lowered for
        measurement and travel paths, :func:`path_limits`), or plain ``(k, 2) float64``
        points in mm in the robot base frame (an open path).
    job: settings (``job.motion``, ``job.cell``); default ``Job()``.
    robot: overrides the robot named by the job.
    index: the path's index within its layer, for error messages (a Path does not know
        it; without it a Path is named by its layer, material and role).

    Returns one Trajectory at constant ``dt``: ``xy (n, 2)`` mm in the base frame,
    ``joints (n, j)``, ``speed (n,)`` mm/s, ``duration`` s, ``pieces`` (rest points at
    split corners). Raises WorkspaceError (naming the point) before planning if any point
    is unreachable.
    """
    job = job or Job()
    robot = robot or get_robot(job)
    if isinstance(path_or_points, Toolpath):
        pts = _as_points(_base_points(path_or_points, job), _path_label(path_or_points, index))
        return _plan_polylines([pts], np.array([path_limits(path_or_points, job)]), job,
                               robot, labels=[_path_label(path_or_points, index)],
                               paths=[path_or_points])[0]
    pts = _as_points(path_or_points, "path")
    return _plan_polylines([pts], np.array([job.motion.speed_mm_s]), job, robot)[0]


def plan_paths_motion(paths: Sequence[Toolpath], job: Job | None = None, *,
                      robot: Robot | None = None, layer: int = -1,
                      role_speeds: Mapping[str, float] | None = None) -> list[Trajectory]:
    """Trajectories of many paths (e.g. one layer) in one compiled call; one per path.

    role_speeds: optional speed bound (mm/s) per path role ("boundary", "fill", ...),
    replacing :func:`path_limits` for paths of that role (never above
    ``motion.speed_mm_s``); used by :func:`constant_speed_motion`.
    """
    job = job or Job()
    _check_role_speeds(role_speeds)
    robot = robot or get_robot(job)
    if not paths:
        return []
    V, counts, caps, labels = _paths_input(paths, job, layer, role_speeds)
    return _plan_polylines((V, counts), caps, job, robot, labels=labels, paths=list(paths))


def plan_paths_durations(paths: Sequence[Toolpath], job: Job | None = None, *,
                         robot: Robot | None = None, layer: int = -1,
                         role_speeds: Mapping[str, float] | None = None) -> np.ndarray:
    """(P,) float64 s: the duration of each path's trajectory, exactly as
    :func:`plan_paths_motion` plans it, without sampling it (the speed profiles alone:
    what a comparison of build times needs); a path that :func:`plan_paths_motion` plans
    again for its joints' sampled acceleration (near the SCARA's reach) takes longer."""
    job = job or Job()
    _check_role_speeds(role_speeds)
    robot = robot or get_robot(job)
    if not paths:
        return np.zeros(0)
    V, counts, caps, labels = _paths_input(paths, job, layer, role_speeds)
    return _plan_durations((V, counts), caps, job, robot, labels=labels)


def _paths_input(paths: Sequence[Toolpath], job: Job, layer: int,
                 role_speeds: Mapping[str, float] | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """The paths as the planner takes them: all points in the robot base frame (closed
    paths back to their first point), checked finite; points per path, speed bound per
    path, (layer, index) labels for messages."""
    polys = []
    for i, p in enumerate(paths):
        pts = p.polyline()
        if not (isinstance(pts, np.ndarray) and pts.dtype == np.float64 and pts.ndim == 2
                and pts.shape[1] == 2 and len(pts)):
            pts = _as_points(pts, f"layer {p.layer}, path {i}")
        polys.append(pts)
    V, counts = _to_base(paths, polys, job)
    if not np.isfinite(V).all():
        bad = np.flatnonzero(~np.isfinite(V).all(axis=1))[0]
        ends = np.cumsum(counts)
        i = int(np.searchsorted(ends, bad, side="right"))
        _as_points(V[ends[i] - counts[i]:ends[i]], f"layer {paths[i].layer}, path {i}")
    caps = np.array([_role_cap(p, job, role_speeds) for p in paths], dtype=np.float64)
    labels = [(p.layer if p.layer >= 0 else layer, i) for i, p in enumerate(paths)]
    return V, counts, caps, labels


def _plan_layer(lp: LayerPaths, job: Job,
                role_speeds: Mapping[str, float] | None = None) -> LayerMotion:
    trajs = (plan_paths_motion(lp.paths, job, layer=lp.index, role_speeds=role_speeds)
             if lp.paths else [])
    return LayerMotion(index=lp.index, z=lp.z, trajectories=tuple(trajs),
                       thickness=lp.thickness, top_z=lp.top_z)


class _ShippedLayer:
    """A layer's paths on their way to a worker: pickled as the few flat arrays of
    :func:`icefab.resultfiles.pack_layer_paths` and whole again on arrival (one pickled
    object per path cost the bunny's ``icefab plan`` 2.0 s to send and 4.8 s to receive,
    240 MB through the pipes); a serial run (no pickling) packs nothing."""

    __slots__ = ("_lp", "_packed")

    def __init__(self, lp: LayerPaths | None = None, packed: tuple | None = None) -> None:
        """lp: the layer; or ``packed``, the layer as ``pack_layer_paths`` gives it (a
        :class:`~icefab.resultfiles.PackedToolpaths` layer: sent as it is)."""
        self._lp = lp
        self._packed = packed

    @property
    def lp(self) -> LayerPaths:
        if self._lp is None:
            self._lp = unpack_layer_paths(self._packed)
        return self._lp

    def __reduce__(self):
        return _arrived_layer, (self._packed if self._packed is not None
                                else pack_layer_paths(self._lp),)


def _arrived_layer(packed: tuple) -> _ShippedLayer:
    return _ShippedLayer(unpack_layer_paths(packed))


def _plan_layer_task(args: tuple) -> dict[str, np.ndarray]:
    """Worker: plan one layer and return its trajectories packed in a few flat arrays
    (sending one object per trajectory, with its Toolpath, back through the pipe costs more
    than planning it). args: (_ShippedLayer, Job, role_speeds or None)."""
    shipped, job, role_speeds = args
    return pack_trajectories(_plan_layer(shipped.lp, job, role_speeds).trajectories,
                             empty_pieces=True)


def _layer_time_task(args: tuple) -> float:
    """Worker: one layer's motion time, s; its samples are not sent back. args as
    :func:`_plan_layer_task`'s."""
    shipped, job, role_speeds = args
    lp = shipped.lp
    return float(plan_paths_durations(lp.paths, job, layer=lp.index,
                                      role_speeds=role_speeds).sum())


def _plan_layer_and_time(lp: LayerPaths, job: Job, role_speeds: Mapping[str, float]
                         ) -> tuple[LayerMotion, float]:
    """A layer planned (as :func:`_plan_layer`) and its motion time at ``role_speeds``
    (as :func:`_layer_time_task`), the same values, from one PATHSPLIT, one set of joint
    angles and one workspace check (:func:`_prepare`)."""
    if not lp.paths:
        return _plan_layer(lp, job), 0.0
    robot = get_robot(job)
    V, counts, caps, labels = _paths_input(lp.paths, job, lp.index, None)
    other = np.array([_role_cap(p, job, role_speeds) for p in lp.paths], dtype=np.float64)
    prep = _prepare((V, counts), job, robot, labels)
    pr = _profiles(prep, caps, job, robot)
    trajs = _plan_polylines((V, counts), caps, job, robot, labels=labels,
                            paths=list(lp.paths), profiles=pr)
    lm = LayerMotion(index=lp.index, z=lp.z, trajectories=tuple(trajs),
                     thickness=lp.thickness, top_z=lp.top_z)
    # a piece under the same bound in both cases has the same profile (the fill, travel
    # and measurement paths at the default speeds): only the others are planned again
    if len(pr.T):
        piece = prep.sp.piece_path
        again = np.flatnonzero(caps[piece] != other[piece])
        T = pr.T.copy()
        T[again] = _piece_times(prep, other, job, robot, again)
        pr = pr._replace(T=T)
    return lm, float(_durations(pr, job).sum())


def _plan_packed_task(args: tuple) -> tuple[dict[str, np.ndarray], float, object]:
    """Worker: a layer's trajectories packed (as :func:`_plan_layer_task`), its
    constant-speed time (:func:`_layer_time_task` at ``speeds``) and ``per_layer``'s result
    on its trajectories. args: (_ShippedLayer, Job, speeds, per_layer or None)."""
    shipped, job, speeds, per_layer = args
    lm, const_s = _plan_layer_and_time(shipped.lp, job, speeds)
    extra = per_layer(lm, job) if per_layer is not None else None
    return pack_trajectories(lm.trajectories, empty_pieces=True), const_s, extra


def total_path_length(toolpaths: Toolpaths | PackedToolpaths) -> float:
    """Length of every path of a build, depositing or not, mm (the closing edge of closed
    paths included)."""
    packed = isinstance(toolpaths, PackedToolpaths)
    lengths = (_packed_path_lengths(toolpaths.layers) if packed
               else _path_lengths(list(toolpaths.layers)))
    return float(np.sum(lengths))


def _checked_items(toolpaths: Toolpaths | PackedToolpaths, job: Job,
                   role_speeds: Mapping[str, float] | None,
                   streamed: bool = False) -> list[tuple]:
    """The per-layer work items of a build's planning, once the build has passed the checks
    made before any layer is planned (role speeds, sample budget, workspace).

    The sample budget: the whole build within :data:`icefab.workload.MAX_SAMPLES` when it
    is held in memory; ``streamed`` (one layer's samples at a time): every layer within it
    and the build within ``MAX_STREAMED_SAMPLES``. A :class:`PackedToolpaths` build is
    checked and sent as its arrays (no Toolpath made in this process)."""
    _check_role_speeds(role_speeds)
    packed = isinstance(toolpaths, PackedToolpaths)
    heads = toolpaths.heads if packed else list(toolpaths.layers)
    # sample budget before any planning
    lengths = _packed_path_lengths(toolpaths.layers) if packed else _path_lengths(heads)
    if streamed:
        for lp, (dep, other) in zip(heads, lengths):
            check_motion(dep, other, job, what=f"layer {lp.index}")
        check_motion(*lengths.sum(axis=0), job, streamed=True)
    else:
        check_motion(*lengths.sum(axis=0), job)
    robot = get_robot(job)
    if not packed:
        check_build_workspace(toolpaths, job, robot)
        return [(_ShippedLayer(lp), job, role_speeds) for lp in heads]
    for head, arrays in zip(heads, toolpaths.layers):
        check_packed_workspace(head.index, arrays, job, robot)
    return [(_ShippedLayer(packed=toolpaths.packed_layer(k)), job, role_speeds)
            for k in range(len(heads))]


def unpack_layer_motion(lp: LayerPaths, packed: dict[str, np.ndarray]) -> LayerMotion:
    """The LayerMotion of a layer's packed trajectories (a worker's, :class:`PlannedLayer`)."""
    return LayerMotion(index=lp.index, z=lp.z,
                       trajectories=tuple(unpack_trajectories(packed, lp.paths)),
                       thickness=lp.thickness, top_z=lp.top_z)


def _to_base(paths: Sequence[Toolpath], polys: Sequence[np.ndarray], job: Job
             ) -> tuple[np.ndarray, np.ndarray]:
    """(points (N, 2) float64 mm, counts (P,) int64): the polylines ``polys`` of ``paths``
    concatenated and moved to the robot base frame (:func:`_base_points` of each), each
    path by its tool's offset, one shift per tool added to all points at once."""
    counts = np.array([len(q) for q in polys], dtype=np.int64)
    if not len(polys):
        return np.zeros((0, 2)), counts
    shift = _tool_shifts(["" if p.frame == "base" else p.tool_name for p in paths], job)
    pts = np.concatenate([np.asarray(q, dtype=np.float64) for q in polys])
    return pts + np.repeat(shift, counts, axis=0), counts


def _tool_shifts(tools: Sequence[str], job: Job) -> np.ndarray:
    """(P, 2) mm: what moves each path's points into the robot base frame, by the tool
    that follows it ("": points already in the base frame), one shift per tool."""
    shifts: dict[str, np.ndarray] = {"": np.zeros(2)}
    out = np.empty((len(tools), 2))
    for i, key in enumerate(tools):
        if key not in shifts:
            shifts[key] = to_base_frame(np.zeros((1, 2)), key, job)[0]
        out[i] = shifts[key]
    return out


def _path_lengths(layers: Sequence[LayerPaths]) -> np.ndarray:
    """(L, 2) float64 mm: per layer, the total length of its depositing paths and of its
    other paths."""
    out = np.zeros((len(layers), 2))
    for k, lp in enumerate(layers):
        if lp.paths:
            per = path_lengths(lp.paths)
            dep = np.array([p.depositing for p in lp.paths])
            out[k] = per[dep].sum(), per[~dep].sum()
    return out


def _packed_path_lengths(layers: Sequence[dict[str, np.ndarray]]) -> np.ndarray:
    """:func:`_path_lengths` of layers given as :func:`icefab.resultfiles.pack_paths`
    packs them, the same values."""
    out = np.zeros((len(layers), 2))
    for k, d in enumerate(layers):
        if len(d["z"]):
            per = packed_lengths(d)
            dep = np.isin(d["role"], DEPOSITING_CODES)
            out[k] = per[dep].sum(), per[~dep].sum()
    return out


def _locate(ends: np.ndarray, i: int) -> tuple[int, int]:
    """(path, point within it) of row ``i`` of concatenated paths ending at ``ends``."""
    k = int(np.searchsorted(ends, i, side="right"))
    return k, i - (int(ends[k - 1]) if k else 0)


def check_build_workspace(toolpaths: Toolpaths, job: Job | None = None,
                          robot: Robot | None = None) -> None:
    """Raise WorkspaceError (layer, path, point or segment, coordinates, why) for the first
    place of any path of the build, in the robot base frame, that the robot cannot reach
    (:func:`check_layer_workspace`, layer by layer)."""
    job = job or toolpaths.job
    robot = robot or get_robot(job)
    for lp in toolpaths.layers:
        check_layer_workspace(lp, job, robot)


def check_layer_workspace(lp: LayerPaths, job: Job, robot: Robot | None = None) -> None:
    """Raise WorkspaceError (layer, path, point or segment, coordinates, why) for the first
    place of one layer's paths, in the robot base frame, that the robot cannot reach.

    Checked: every point, and every segment's point nearest the robot base origin when it
    lies inside the segment. A chord between two reachable points leaves a SCARA's
    annular reach only by passing inside the minimum reach, so this catches it before any
    layer is planned for one extra point per segment (a gantry's box is convex: chords
    never leave it); the planner still checks every resampled (and smoothed) grid point
    of each layer (e.g. a chord swinging joint 1 beyond its range around the back).
    """
    if not lp.paths:
        return
    pts, counts = _to_base(lp.paths, [p.polyline() for p in lp.paths], job)
    scaffold = np.array([p.material == "scaffold" for p in lp.paths])
    _check_reach(lp.index, pts, counts, robot or get_robot(job), _scaffold_note(scaffold, job))


def check_packed_workspace(index: int, packed: dict[str, np.ndarray], job: Job,
                           robot: Robot | None = None) -> None:
    """:func:`check_layer_workspace` of layer ``index`` given as
    :func:`icefab.resultfiles.pack_paths` packed its paths (``icefab paths`` checks the
    workers' layers so: no Toolpath made for it, issue 17); the same checks, points and
    messages."""
    if not len(packed["z"]):
        return
    robot = robot or get_robot(job)
    shift = _tool_shifts(packed_tools(packed).tolist(), job)
    # the box of the points in the base frame first: the closed polylines' points are the
    # same points, and a layer inside the reach (all of them but a bad part's) needs no
    # copy of them (issue 17: 0.8 s of the bunny's main process)
    if _in_reach_box(robot, packed["points"]
                     + np.repeat(shift, np.diff(packed["path_start"]), axis=0)):
        return
    pts, counts = packed_polylines(packed)
    scaffold = np.asarray(packed["material"]) == MATERIALS.index("scaffold")
    _check_reach(index, pts + np.repeat(shift, counts, axis=0), counts, robot,
                 _scaffold_note(scaffold, job))


def _scaffold_note(scaffold: np.ndarray, job: Job) -> Callable[[int], str]:
    """What a reach error of path k adds when it is a scaffold path (``scaffold`` (P,)
    bool): the setting that puts the scaffold there (a hunt's scaffold 100 mm around a
    part left joint 1's range and the message named only the part's placement)."""
    b = job.scaffold.buffer_mm
    return lambda k: (f" (a scaffold path: the scaffold reaches scaffold.buffer_mm = {b:g} mm "
                      "beyond the part)" if scaffold[k] else "")


def _in_reach_box(robot: Robot, pts: np.ndarray) -> bool:
    """Whether the box of ``pts`` (N, 2) mm, base frame, is surely reachable
    (``robot.box_reachable``, optional): then so is every chord between them."""
    box = getattr(robot, "box_reachable", None)
    return bool(len(pts)) and box is not None and box(*points_box(pts))


def _check_reach(index: int, pts: np.ndarray, counts: np.ndarray, robot: Robot,
                 note: Callable[[int], str] = lambda k: "") -> None:
    """The reach checks of :func:`check_layer_workspace` on a layer's polylines in the
    robot base frame (``pts`` (N, 2) mm, ``counts`` (P,) points each); ``note(k)``: what
    the message of path k adds."""
    if _in_reach_box(robot, pts):
        return   # the segments lie in the points' box too
    ends = np.cumsum(counts)
    bad, reasons = robot.workspace_violations(pts)
    if len(bad):
        i = int(bad[0])
        k, j = _locate(ends, i)
        raise WorkspaceError(f"layer {index}, path {k}: point {j} at ({pts[i, 0]:.3f}, "
                             f"{pts[i, 1]:.3f}) mm (robot base frame) is out of the "
                             f"{robot.name} workspace: {reasons[0]}{note(k)}")
    # segments (within a path): the point nearest the base origin
    a, b = pts[:-1], pts[1:]
    within = np.ones(len(a), dtype=bool)
    within[ends[:-1] - 1] = False
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -np.einsum("ij,ij->i", a, d) / dd
    inner = within & (dd > 0.0) & (t > 0.0) & (t < 1.0)
    seg = np.flatnonzero(inner)
    if not len(seg):
        return
    near = a[seg] + t[seg, None] * d[seg]
    sbad, sreasons = robot.workspace_violations(near)
    if len(sbad):
        k, j = _locate(ends, int(seg[sbad[0]]))
        x, y = near[sbad[0]]
        raise WorkspaceError(f"layer {index}, path {k}: the segment from point {j} to "
                             f"point {j + 1} passes ({x:.3f}, {y:.3f}) mm (robot base "
                             f"frame), out of the {robot.name} workspace: {sreasons[0]}"
                             f"{note(k)}")


def plan_toolpaths(toolpaths: Toolpaths, job: Job | None = None,
                   progress: Callable[[int, int], None] | None = None, *,
                   role_speeds: Mapping[str, float] | None = None) -> BuildMotion:
    """Trajectories of all paths of a build, layer-parallel across ``cell.cpus`` processes.

    Every point of every path, and every chord's point nearest the robot base, is checked
    against the workspace before any layer is planned (:func:`check_build_workspace`;
    WorkspaceError names layer, path and point or segment); the resampled points of each
    layer are checked again when it is planned.
    ``progress(done, total)`` is called as layers complete (:func:`icefab.parallel.parallel_map`).
    ``role_speeds``: see
    :func:`plan_paths_motion`. The whole build is held in memory, within
    :data:`icefab.workload.MAX_SAMPLES`; :func:`iter_plan_toolpaths` streams it.
    """
    job = job or toolpaths.job
    robot = get_robot(job)
    layers = list(toolpaths.layers)
    packed = parallel_map(_plan_layer_task, _checked_items(toolpaths, job, role_speeds),
                          job, min_items=2, progress=progress)
    out = [unpack_layer_motion(lp, p) for lp, p in zip(layers, packed)]
    return BuildMotion(layers=tuple(out), job=job, robot=robot.name,
                       joint_names=tuple(robot.joint_names))


def iter_plan_toolpaths(toolpaths: Toolpaths, job: Job | None = None,
                        progress: Callable[[int, int], None] | None = None
                        ) -> Iterator[LayerMotion]:
    """:func:`plan_toolpaths`' layers, yielded in build order as the workers plan them
    (:func:`icefab.parallel.parallel_imap`): a caller that writes each layer away
    (:class:`icefab.resultfiles.TrajectoryWriter`) holds a few layers' samples, not the
    build's (issue 17). Same checks before the first layer, with the streamed sample
    budget (every layer within ``MAX_SAMPLES``, the build within ``MAX_STREAMED_SAMPLES``);
    the same trajectories."""
    job = job or toolpaths.job
    items = _checked_items(toolpaths, job, None, streamed=True)
    for lp, packed in zip(toolpaths.layers, parallel_imap(_plan_layer_task, items, job,
                                                          progress=progress)):
        yield unpack_layer_motion(lp, packed)


def iter_plan_and_compare(toolpaths: Toolpaths, job: Job | None = None,
                          progress: Callable[[int, int], None] | None = None
                          ) -> Iterator[tuple[LayerMotion, float]]:
    """:func:`iter_plan_toolpaths` with each layer's :func:`constant_speed_time` (s)
    beside it, planned by the same worker in the same pass (``icefab plan``'s comparison:
    one pass over the build, one set of checks, instead of two)."""
    for pl in iter_plan_packed(toolpaths, job, progress):
        yield unpack_layer_motion(pl.paths, pl.packed), pl.const_s


class PlannedLayer(NamedTuple):
    """One layer as :func:`iter_plan_packed` hands it over."""

    #: The layer's paths (trajectory i follows ``paths.paths[i]``), or its LayerHead
    #: (see ``path_arrays``).
    paths: LayerPaths | LayerHead
    #: Its trajectories as :func:`icefab.resultfiles.pack_trajectories` packs them
    #: (pieces kept empty where a trajectory has none), what
    #: :meth:`icefab.resultfiles.TrajectoryWriter.add_packed` writes.
    packed: dict
    #: The layer's :func:`constant_speed_time`, s.
    const_s: float
    #: What ``per_layer`` gave in the worker (None without one).
    extra: object
    #: For a :class:`~icefab.resultfiles.PackedToolpaths` build, the layer's paths as
    #: :func:`~icefab.resultfiles.pack_paths` packs them (``paths`` is then the layer's
    #: :class:`~icefab.resultfiles.LayerHead`); None otherwise.
    path_arrays: dict | None = None


def iter_plan_packed(toolpaths: Toolpaths | PackedToolpaths, job: Job | None = None,
                     progress: Callable[[int, int], None] | None = None,
                     per_layer: Callable[[LayerMotion, Job], object] | None = None
                     ) -> Iterator[PlannedLayer]:
    """:func:`iter_plan_and_compare` with the trajectories left packed, as the workers send
    them: a caller that writes them to a file (``icefab plan``) needs no Trajectory objects
    (unpacking and packing again took the bunny's main process 4-5 s, issue 17).
    ``per_layer(layer, job)``, a module-level function (it reaches the workers by name, e.g.
    :func:`icefab.headroom.layer_headroom`), runs in the worker on each planned layer; its
    result comes back with the layer. A :class:`~icefab.resultfiles.PackedToolpaths` build
    (``icefab plan`` loads its file so) is checked and sent as its arrays, and each
    PlannedLayer carries them (``path_arrays``)."""
    job = job or toolpaths.job
    speeds = _constant_speeds(job, None, None)
    _check_role_speeds(speeds)
    items = [(lp, j, speeds, per_layer)
             for lp, j, _ in _checked_items(toolpaths, job, None, streamed=True)]
    planned = parallel_imap(_plan_packed_task, items, job, progress=progress)
    if isinstance(toolpaths, PackedToolpaths):
        for head, arrays, (packed, t, extra) in zip(toolpaths.heads, toolpaths.layers,
                                                     planned):
            yield PlannedLayer(head, packed, t, extra, arrays)
        return
    for lp, (packed, t, extra) in zip(toolpaths.layers, planned):
        yield PlannedLayer(lp, packed, t, extra)


def constant_speed_motion(toolpaths: Toolpaths, job: Job | None = None, *,
                          boundary_mm_s: float | None = None, fill_mm_s: float | None = None,
                          progress: Callable[[int, int], None] | None = None) -> BuildMotion:
    """The thesis' "constant-speed" case (4.4) planned with the robot's real limits.

    Boundary paths at ``boundary_mm_s`` (default ``motion.boundary_speed_mm_s``, 25 mm/s:
    the speed whose radial acceleration stays below the bound on a 1 mm radius, thesis
    4.2, eq. 4.9), fill paths at ``fill_mm_s`` (default ``motion.fill_speed_mm_s``,
    125 mm/s), measurement and travel paths at their usual bounds (:func:`path_limits`).
    Every path is planned by the MTTS machinery with its Cartesian speed bound set to
    that constant speed, so acceleration and jerk ramps, stops at split corners (e.g. at
    every end of a zigzag fill line) and curvature and joint limits are honoured; unlike
    ``icefab.paths.estimate_build_time`` (length / speed), this is a time a robot could
    achieve. Layer-parallel like :func:`plan_toolpaths`.
    """
    job = job or toolpaths.job
    return plan_toolpaths(toolpaths, job, progress,
                          role_speeds=_constant_speeds(job, boundary_mm_s, fill_mm_s))


def _constant_speeds(job: Job, boundary_mm_s: float | None, fill_mm_s: float | None
                     ) -> dict[str, float]:
    """The role speeds of the constant-speed case (defaults: the job's, thesis 4.4)."""
    m = job.motion
    return {"boundary": float(m.boundary_speed_mm_s if boundary_mm_s is None
                              else boundary_mm_s),
            "fill": float(m.fill_speed_mm_s if fill_mm_s is None else fill_mm_s)}


def constant_speed_time(toolpaths: Toolpaths, job: Job | None = None, *,
                        boundary_mm_s: float | None = None, fill_mm_s: float | None = None,
                        progress: Callable[[int, int], None] | None = None) -> float:
    """The build motion time, s, of :func:`constant_speed_motion`, without its samples.

    The comparison with constant speed needs only the time; keeping the samples doubled
    ``icefab plan``'s memory on a 1 M-facet part (issue 17: 5.9 GB). Each worker plans its
    layers and sends back their times.
    """
    job = job or toolpaths.job
    speeds = _constant_speeds(job, boundary_mm_s, fill_mm_s)
    times = parallel_map(_layer_time_task, _checked_items(toolpaths, job, speeds, True),
                         job, min_items=2, progress=progress)
    return float(sum(times))


# --------------------------------------------------------------------------- outputs


def speedup_cap(traj: Trajectory, job: Job | None = None) -> np.ndarray:
    """:func:`limit_ratio`, never below 1: a sample already at a limit is not slowed, only
    not sped up."""
    return np.maximum(limit_ratio(traj, job), 1.0)


def limit_ratio(traj: Trajectory, job: Job | None = None) -> np.ndarray:
    """(n,) the largest factor by which a trajectory's speed may be raised at each sample
    without breaking a motion limit it respects (thesis 4.1: the limits MTTS planned it
    under), for the c-controller's re-timing (thesis 5.2.2, which speeds paths up by up to
    ``feedback.saturation``).

    Raising the speed uniformly by f scales speeds by f, accelerations by f^2 and jerks by
    f^3, Cartesian (``motion.speed_mm_s``, ``accel_mm_s2``, ``jerk_mm_s3`` when
    ``motion.jerk_limited``) and per joint (the robot's bounds) alike, so the cap is the
    smallest of ``limit / value``, its square root and its cube root over the quantities,
    each measured by finite differences of the samples (at the trajectory's dt) and taken
    over the samples each difference spans. Below 1 where a limit is exceeded (by that
    factor); inf where nothing bounds a sample.
    """
    job = job or Job()
    m = job.motion
    robot = get_robot(job)
    dt = float(traj.dt)
    xy = np.asarray(traj.xy, dtype=np.float64)
    n = len(xy)
    cap = np.full(n, np.inf)
    if n < 2 or not dt > 0:
        return np.full(n, np.inf)

    def bound(values: np.ndarray, limit, power: float) -> None:
        """values (k, ...) the order-th differences over samples i..i+order; limit scalar
        or per column; the cap of every sample a difference spans."""
        if not len(values):
            return
        lim = np.asarray(limit, dtype=np.float64)
        mag = np.abs(values) if values.ndim > 1 else values
        with np.errstate(divide="ignore", invalid="ignore"):
            r = np.where(mag > 1e-12, lim / mag, np.inf) ** (1.0 / power)
        r = r.min(axis=1) if r.ndim > 1 else r
        order = n - len(r)
        for k in range(order + 1):
            cap[k:k + len(r)] = np.minimum(cap[k:k + len(r)], r)

    d1 = np.diff(xy, axis=0) / dt
    bound(np.hypot(d1[:, 0], d1[:, 1]), m.speed_mm_s, 1.0)
    d2 = np.diff(d1, axis=0) / dt
    bound(np.hypot(d2[:, 0], d2[:, 1]), m.accel_mm_s2, 2.0)
    if m.jerk_limited:
        d3 = np.diff(d2, axis=0) / dt
        bound(np.hypot(d3[:, 0], d3[:, 1]), m.jerk_mm_s3, 3.0)
    q = np.asarray(traj.joints, dtype=np.float64)
    if q.ndim == 2 and len(q) == n and q.shape[1] == len(robot.joint_speed_max):
        q1 = np.diff(q, axis=0) / dt
        bound(q1, robot.joint_speed_max, 1.0)
        q2 = np.diff(q1, axis=0) / dt
        bound(q2, robot.joint_accel_max, 2.0)
        if m.jerk_limited:
            bound(np.diff(q2, axis=0) / dt, robot.joint_jerk_max, 3.0)
    return cap


def constant_spacing(traj: Trajectory, spacing_mm: float | None = None,
                     job: Job | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The optional output with constant point spacing and variable duration.

    Returns (points (k, 2) float64 mm every ``spacing_mm`` along the trajectory (default
    ``motion.point_spacing_mm``; the last interval ends on the trajectory's end, so the
    spacing is the largest that divides the length into whole intervals, <= spacing_mm),
    durations (k - 1,) float64 s from each point to the next: the trajectory's time at
    each point, linear in arc length between its samples). Raises IcefabError naming
    ``spacing_mm`` unless it is a positive finite number of mm.
    """
    if spacing_mm is None:
        spacing = float((job or Job()).motion.point_spacing_mm)
    else:
        try:
            spacing = float(spacing_mm)
        except (TypeError, ValueError):
            spacing = math.nan
        if not (math.isfinite(spacing) and spacing > 0.0):
            raise IcefabError(f"constant_spacing: spacing_mm must be a positive number of mm, "
                              f"got {spacing_mm!r}")
    xy = traj.xy
    if len(xy) < 2:
        return xy.copy(), np.zeros(0)
    d = np.hypot(*np.diff(xy, axis=0).T)
    s = arc_lengths(d)
    n = max(1, int(math.ceil(s[-1] / spacing - 1e-9)))
    sq = np.linspace(0.0, s[-1], n + 1)
    t = traj.t
    # time at each arc length: s(t) is non-decreasing; rest samples repeat s
    uniq = np.concatenate([[True], np.diff(s) > 0])
    tq = np.interp(sq, s[uniq], t[uniq])
    pts = np.stack([np.interp(sq, s, xy[:, 0]), np.interp(sq, s, xy[:, 1])], axis=1)
    return pts, np.diff(tq)


def gcode_moves(traj: Trajectory, *, decimals: int = 3, power: np.ndarray | None = None,
                dwell: bool = False, rapid_mm_min: float | None = None) -> list[str]:
    """G-code-style moves for gantry machines: ``G0`` to the first sample, then ``G1 X.. Y..
    F..`` per sample, the feedrate (mm/min) being the average speed over the step to that
    sample (each move lasts one time step, thesis 4.3).

    power: (n - 1,) int, 0..255, per step: appended as ``S..`` to each step's move (Marlin's
    inline cutter power, :mod:`icefab.export`). dwell: a step that does not move becomes
    ``G4 P<ms>`` (consecutive ones merged) so the timing holds; without it such steps are
    left out. rapid_mm_min: the ``G0``'s own ``F``, mm/min (F is modal in G-code: without
    one the G0 ran at the feedrate of the move before it, a path's last slowing step).
    """
    xy = traj.xy
    if len(xy) == 0:
        return []
    feed0 = "" if rapid_mm_min is None else f" F{rapid_mm_min:.1f}"
    lines = [f"G0 X{xy[0, 0]:.{decimals}f} Y{xy[0, 1]:.{decimals}f}{feed0}"]
    d = np.hypot(*np.diff(xy, axis=0).T)
    feed = d / traj.dt * 60.0
    rest = 0
    for i, ((x, y), f) in enumerate(zip(xy[1:], feed)):
        if f <= 0.0:
            rest += 1
            continue
        if rest and dwell:
            lines.append(f"G4 P{rest * traj.dt * 1000:.0f}")
        rest = 0
        s = "" if power is None else f" S{int(power[i])}"
        lines.append(f"G1 X{x:.{decimals}f} Y{y:.{decimals}f} F{f:.1f}{s}")
    if rest and dwell:
        lines.append(f"G4 P{rest * traj.dt * 1000:.0f}")
    return lines




def save_constant_spacing(motion: BuildMotion, spacing_mm: float,
                          path: str | os.PathLike) -> None:
    """The optional output with constant point spacing and variable duration
    (:func:`constant_spacing`), ``.npz`` written atomically: ``format`` =
    "icefab-constant-spacing", ``version`` = 1, ``spacing_mm`` (the asked spacing; each path
    uses the largest spacing <= it that divides its length), ``xy`` (N, 2) float64 mm
    (robot base frame), ``duration`` (N,) float64 s from each point to the next (0 on each
    path's last point), ``path_start`` (T + 1,) int64 (path i is rows
    ``path_start[i]:path_start[i+1]``), and per path ``layer``, ``path_index``,
    ``material``, ``role`` as in ``trajectories.npz``, in its order."""
    xy, dur = [], []
    for lm in motion.layers:
        for tr in lm.trajectories:
            pts, d = constant_spacing(tr, spacing_mm)
            xy.append(pts)
            dur.append(np.append(d, 0.0) if len(pts) else d)
    data = {"format": np.array("icefab-constant-spacing"), "version": np.array(1),
            "spacing_mm": np.array(float(spacing_mm)),
            "xy": np.concatenate(xy) if xy else np.zeros((0, 2)),
            "duration": np.concatenate(dur) if dur else np.zeros(0),
            "path_start": offsets([len(p) for p in xy]),
            **owner_arrays(motion)}
    with atomic_path(path, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **data)


# --------------------------------------------------------------------------- reference shapes


def _arc(center: tuple[float, float], r: float, a0_deg: float, a1_deg: float,
         step_mm: float) -> np.ndarray:
    n = max(2, int(math.ceil(abs(math.radians(a1_deg - a0_deg)) * r / step_mm)) + 1)
    t = np.radians(np.linspace(a0_deg, a1_deg, n))
    return np.stack([center[0] + r * np.cos(t), center[1] + r * np.sin(t)], axis=1)


def thesis_test_path(offset_mm: tuple[float, float] = (0.0, 0.0), *,
                     step_mm: float = 0.05) -> np.ndarray:
    """A test path in the spirit of thesis Fig. 4-2: straight sides, rounds of radii 20,
    10 and 5 mm and one sharp 90-degree corner (where PATHSPLIT splits it in two).

    The outline is a 100 x 60 mm rectangle run counter-clockwise from the middle of its
    bottom side: round r = 20 (bottom right), r = 10 (top right), the sharp corner (top
    left), r = 5 (bottom left), ending 5 mm before the start. Returns (k, 2) float64 mm,
    arcs sampled every ``step_mm``, translated by ``offset_mm``.
    """
    parts = [np.array([[50.0, 0.0]]),
             _arc((80.0, 20.0), 20.0, -90.0, 0.0, step_mm),
             _arc((90.0, 50.0), 10.0, 0.0, 90.0, step_mm),
             np.array([[0.0, 60.0]]),
             _arc((5.0, 5.0), 5.0, 180.0, 270.0, step_mm),
             np.array([[45.0, 0.0]])]
    pts = np.concatenate(parts)
    return pts + np.asarray(offset_mm, dtype=np.float64)
