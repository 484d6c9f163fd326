"""Robot kinematics and limits: a small ``Robot`` protocol plus a registry by name.

The motion planner (:mod:`icefab.motion`) never imports a robot class: it asks
:func:`get_robot` for the robot the job names and only uses the protocol below. A robot
can only *tighten* the Cartesian limits of a move (the Klipper rule): it supplies its
joints as a function of the tool position (inverse kinematics, vectorised) and a speed,
acceleration and jerk bound per joint; the planner turns those into per-point bounds on
the speed along the path (thesis 4.1.2, eqs. 4.3-4.4).

Implementations
---------------
``scara``  Adept Cobra 600 (thesis 2.1, 4.2): links l1, l2; joints 1 and 2 revolute,
           joint 3 the vertical stroke (not moved while depositing, not modelled), joint 4
           keeping the end-effector orientation fixed, ``theta4 = phi - theta1 - theta2``
           (eq. 4.11). Joints reported: (theta1, theta2, theta4) in rad; joint 4 has no
           kinematic limits (thesis 4.2.1).
           Elbow ``"right"`` means theta2 >= 0 (the elbow lies to the right of the line
           from the shoulder to the wrist, the forearm turns counter-clockwise);
           ``"left"`` means theta2 <= 0.
``gantry`` Cartesian gantry: identity kinematics, joints (x, y) in mm, per-axis speed,
           acceleration and jerk limits; travel [0, gantry_travel_mm] per axis.

Points handed to a robot are positions of its controlled point (the joint-4 axis for the
SCARA) in the robot base frame, mm; the tool offsets (nozzles, laser) are applied
before that by ``icefab.frames.to_base_frame``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable, Protocol, runtime_checkable

import numpy as np

from icefab.errors import ConfigError, WorkspaceError

log = logging.getLogger(__name__)

#: Samples of one path the robot controller stores (the V+ server's default
#: ``icefab.cell.vplus.VplusSettings.max_points``; the virtual C40's too): 131 s at 16 ms.
#: A path is uploaded whole before it runs, so the paths stage keeps its long paths (a
#: measurement spiral, a tour) well inside it.
CONTROLLER_PATH_POINTS = 8192

__all__ = ["Robot", "Scara", "Gantry", "get_robot", "register_robot", "check_workspace",
           "points_box", "ROBOTS"]


@runtime_checkable
class Robot(Protocol):
    """What the planner needs from a robot.

    Attributes
    ----------
    name: registry name (``"scara"``, ``"gantry"``).
    joint_names: one name per joint column returned by :meth:`ik`.
    joint_speed_max, joint_accel_max, joint_jerk_max: (j,) float64 bounds per joint in
        joint units per s, s^2, s^3 (rad or mm); ``inf`` for an unconstrained joint.

    Optional: ``joint_resolution`` (j,) float64, the encoder resolution per joint in joint
    units (0 or absent: not considered); AREST makes the first and last step of every
    piece turn some joint by at least that much (thesis 4.2.6). ``box_reachable(lo, hi)
    -> bool``: whether every point of an axis-aligned box (and so every chord within it)
    is surely reachable; :meth:`workspace_violations` and the paths stage's reach check
    skip their point-by-point work for such a box. ``jacobian(xy, joints=None) -> (n, j,
    2)``: d joints / d (x, y) at the points (joint units per mm; ``joints``: their ``ik``
    when at hand); the planner's vertex bounds take it (else central differences of
    :meth:`ik`).
    """

    name: str
    joint_names: tuple[str, ...]
    joint_speed_max: np.ndarray
    joint_accel_max: np.ndarray
    joint_jerk_max: np.ndarray

    def ik(self, xy: np.ndarray) -> np.ndarray:
        """Joint positions ``(n, j)`` float64 for tool points ``xy (n, 2)`` mm (no checks)."""
        ...

    def fk(self, joints: np.ndarray) -> np.ndarray:
        """Tool points ``(n, 2)`` float64 mm for joint positions ``(n, j)``."""
        ...

    def workspace_violations(self, xy: np.ndarray, joints: np.ndarray | None = None
                             ) -> tuple[np.ndarray, list[str]]:
        """Indices of the points of ``xy (n, 2)`` that cannot be reached, and one reason
        (naming the quantity, its value and the allowed range) per such point (at most the
        first 10). ``joints``: ``ik(xy)`` when the caller has it already."""
        ...


def points_box(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box (lo, hi) ((2,) each, NaN if any coordinate is) of points ``xy (n >= 1, 2)``.
    Column by column: numpy's ``min(axis=0)`` of an (n, 2) array walks it 20 times
    slower (1.1 ms against 0.05 ms for 14 000 points, a bunny layer)."""
    x, y = xy[:, 0], xy[:, 1]
    return np.array([x.min(), y.min()]), np.array([x.max(), y.max()])


# --------------------------------------------------------------------------- SCARA

#: How far inside every limit (mm of reach, rad of joint) a box must lie for
#: :meth:`Scara.box_reachable` to pass it: far beyond the per-point checks' tolerances
#: (1e-9 mm, 1e-12 rad) and the rounding of the inverse kinematics (~1e-15 rad).
BOX_MARGIN = 1e-6


@dataclass(frozen=True, eq=False)
class Scara:
    """A two-link SCARA with an orientation-keeping joint 4 (Cobra 600 defaults).

    l1, l2: link lengths, mm. reach: [min, max] radial reach, mm. joint_range: (2,) rad,
    symmetric range of joints 1 and 2. elbow: "right" (theta2 >= 0) or "left".
    phi: end-effector orientation kept by joint 4, rad (eq. 4.11; the cell's phi is not a
    job setting and stays 0). joint_resolution: (3,) rad encoder resolution of joints 1,
    2 and 4 (default 0.001 deg for joints 1 and 2, ``cell.encoder_resolution_deg``; the
    Cobra 600 has 0.00045 and 0.00072 deg, thesis 4.2.6; joint 4 not considered).
    """

    l1: float = 325.0
    l2: float = 275.0
    reach: tuple[float, float] = (163.0, 600.0)
    joint_range: tuple[float, float] = (np.radians(105.0), np.radians(150.0))
    elbow: str = "right"
    phi: float = 0.0
    joint_speed_max: np.ndarray = None  # type: ignore[assignment]
    joint_accel_max: np.ndarray = None  # type: ignore[assignment]
    joint_jerk_max: np.ndarray = None  # type: ignore[assignment]
    joint_resolution: np.ndarray = None  # type: ignore[assignment]
    name: str = "scara"
    joint_names: tuple[str, ...] = ("theta1", "theta2", "theta4")

    def __post_init__(self) -> None:
        # thesis eq. 4.10 defaults and the 0.001 deg encoders (cell.encoder_resolution_deg);
        # joint 4 unconstrained (thesis 4.2.1): no limit, no resolution
        defaults = {"joint_speed_max": ((33.0, 39.0), np.inf),
                    "joint_accel_max": ((165.0, 195.0), np.inf),
                    "joint_jerk_max": ((1320.0, 1560.0), np.inf),
                    "joint_resolution": (0.001, 0.0)}
        for attr, (deg, joint4) in defaults.items():
            value = getattr(self, attr)
            value = np.radians(deg) if value is None else value
            value = np.asarray(value, dtype=np.float64)
            if value.ndim == 0:  # one value for joints 1 and 2
                value = np.full(2, float(value))
            if value.shape == (2,):
                value = np.append(value, joint4)
            object.__setattr__(self, attr, value)

    @property
    def _sign(self) -> float:
        return 1.0 if self.elbow == "right" else -1.0

    def ik(self, xy: np.ndarray) -> np.ndarray:
        """(n, 3) float64 rad: theta1, theta2, theta4 for points ``xy (n, 2)`` mm.

        Points beyond reach are clipped to the nearest reachable radius (use
        :meth:`workspace_violations` first).
        """
        xy = np.asarray(xy, dtype=np.float64)
        x, y = xy[:, 0], xy[:, 1]
        l1, l2 = self.l1, self.l2
        r2 = x * x + y * y
        c2 = np.clip((r2 - l1 * l1 - l2 * l2) / (2.0 * l1 * l2), -1.0, 1.0)
        t2 = self._sign * np.arccos(c2)
        t1 = np.arctan2(y, x) - np.arctan2(l2 * np.sin(t2), l1 + l2 * c2)
        t1 = (t1 + np.pi) % (2.0 * np.pi) - np.pi
        t4 = self.phi - t1 - t2  # thesis eq. 4.11
        return np.stack([t1, t2, t4], axis=1)

    #: |sin theta2| below which :meth:`jacobian` takes this value (the arm stretched out or
    #: folded: no inverse there; 1e-6 gives ~11 rad/mm, a joint that cannot turn a path).
    SINGULAR_SIN = 1e-6

    def jacobian(self, xy: np.ndarray, joints: np.ndarray | None = None) -> np.ndarray:
        """(n, 3, 2) rad/mm: d (theta1, theta2, theta4) / d (x, y) at points ``xy (n, 2)``
        mm (``joints``: their ``ik`` when at hand), the inverse of the arm's Jacobian
        (x = l1 cos t1 + l2 cos(t1 + t2), y likewise; determinant l1 l2 sin t2); joint 4
        keeps phi, so its row is minus the sum."""
        q = self.ik(xy) if joints is None else joints
        t1, t12 = q[:, 0], q[:, 0] + q[:, 1]
        s2 = np.sin(q[:, 1])
        s2 = np.where(np.abs(s2) < self.SINGULAR_SIN,
                      np.where(s2 < 0.0, -self.SINGULAR_SIN, self.SINGULAR_SIN), s2)
        det = self.l1 * self.l2 * s2
        out = np.empty((len(q), 3, 2))
        out[:, 0, 0] = self.l2 * np.cos(t12) / det
        out[:, 0, 1] = self.l2 * np.sin(t12) / det
        out[:, 1, 0] = -(self.l1 * np.cos(t1) + self.l2 * np.cos(t12)) / det
        out[:, 1, 1] = -(self.l1 * np.sin(t1) + self.l2 * np.sin(t12)) / det
        out[:, 2] = -(out[:, 0] + out[:, 1])
        return out

    def fk(self, joints: np.ndarray) -> np.ndarray:
        """(n, 2) float64 mm: the tool points of joint positions ``(n, >=2)`` rad."""
        joints = np.asarray(joints, dtype=np.float64)
        t1, t12 = joints[:, 0], joints[:, 0] + joints[:, 1]
        return np.stack([self.l1 * np.cos(t1) + self.l2 * np.cos(t12),
                         self.l1 * np.sin(t1) + self.l2 * np.sin(t12)], axis=1)

    def box_reachable(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether every point of the box ``[lo, hi]`` ((2,) mm each, base frame) lies
        ``BOX_MARGIN`` inside the reach and both joint ranges: then no point in it fails
        :meth:`workspace_violations`, nor a chord between two of them. False when unsure
        (a box near a limit, around the base, or not finite): check point by point.

        Why: the paths stage checks each layer's points as the workers send them, the
        motion stage every input point; on the 300 mm bunny that is 17 M inverse
        kinematics of points in the middle of the workspace (issue 17). The box's radii
        span ``[r_near, r_far]`` and its polar angles an interval (it does not hold the
        base). |theta2| = acos(c2(r)) falls as r grows, and theta1 is the polar angle less
        the shoulder's angle beta(r) of the triangle (l1, l2, r) (:meth:`ik`'s second atan2), which
        rises up to r = sqrt(l1^2 - l2^2) and falls after it (law of cosines), so the
        extremes of both lie at the interval's ends or at that radius."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all()):
            return False
        m = BOX_MARGIN
        corners = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])
        r_near = float(np.hypot(*np.clip(0.0, lo, hi)))
        r_far = float(np.hypot(corners[:, 0], corners[:, 1]).max())
        rmin, rmax = self.reach
        if r_near < rmin + m or r_far > rmax - m or r_near <= 0.0:
            return False
        l1, l2 = self.l1, self.l2
        j1, j2 = self.joint_range

        def shoulder(r: float) -> float:  # beta(r) >= 0, as ik computes it
            c2 = min(max((r * r - l1 * l1 - l2 * l2) / (2.0 * l1 * l2), -1.0), 1.0)
            return float(np.arctan2(l2 * np.sin(np.arccos(c2)), l1 + l2 * c2))

        c2_near = (r_near * r_near - l1 * l1 - l2 * l2) / (2.0 * l1 * l2)
        if not -1.0 < c2_near < 1.0 or float(np.arccos(c2_near)) > j2 - m:
            return False
        betas = [shoulder(r_near), shoulder(r_far)]
        if l1 > l2 and r_near < np.sqrt(l1 * l1 - l2 * l2) < r_far:
            betas.append(shoulder(float(np.sqrt(l1 * l1 - l2 * l2))))
        b_lo, b_hi = min(betas), max(betas)
        if self._sign < 0:
            b_lo, b_hi = -b_hi, -b_lo
        centre = 0.5 * (lo + hi)
        tc = float(np.arctan2(centre[1], centre[0]))
        rel = (np.arctan2(corners[:, 1], corners[:, 0]) - tc + np.pi) % (2.0 * np.pi) - np.pi
        t_lo, t_hi = tc + float(rel.min()) - b_hi, tc + float(rel.max()) - b_lo
        shift = 2.0 * np.pi * np.round(0.5 * (t_lo + t_hi) / (2.0 * np.pi))
        return bool(t_lo - shift >= -(j1 - m) and t_hi - shift <= j1 - m)

    def workspace_violations(self, xy: np.ndarray, joints: np.ndarray | None = None
                             ) -> tuple[np.ndarray, list[str]]:
        xy = np.asarray(xy, dtype=np.float64)
        if len(xy) and self.box_reachable(*points_box(xy)):
            return np.zeros(0, dtype=np.intp), []
        return self._point_violations(xy, joints)

    def _point_violations(self, xy: np.ndarray, joints: np.ndarray | None = None
                          ) -> tuple[np.ndarray, list[str]]:
        """:meth:`workspace_violations` point by point."""
        r2 = xy[:, 0] * xy[:, 0] + xy[:, 1] * xy[:, 1]
        rmin, rmax = self.reach
        eps = 1e-9
        q = self.ik(xy) if joints is None else joints
        j1, j2 = self.joint_range
        bad_r = (r2 < (rmin - eps) ** 2) | (r2 > (rmax + eps) ** 2) | ~np.isfinite(r2)
        bad_1 = np.abs(q[:, 0]) > j1 + 1e-12
        bad_2 = np.abs(q[:, 1]) > j2 + 1e-12
        bad = np.flatnonzero(bad_r | bad_1 | bad_2)
        r = np.sqrt(r2)
        reasons = []
        for i in bad[:10]:
            if bad_r[i]:
                reasons.append(f"radius {r[i]:.3f} mm outside the reach "
                               f"[{rmin:g}, {rmax:g}] mm")
            elif bad_1[i]:
                reasons.append(f"joint 1 at {np.degrees(q[i, 0]):.2f} deg beyond its range "
                               f"+/-{np.degrees(j1):g} deg")
            else:
                reasons.append(f"joint 2 at {np.degrees(q[i, 1]):.2f} deg beyond its range "
                               f"+/-{np.degrees(j2):g} deg")
        return bad, reasons


# --------------------------------------------------------------------------- gantry


@dataclass(frozen=True, eq=False)
class Gantry:
    """A Cartesian x-y gantry: identity kinematics, per-axis limits.

    travel: (2,) mm, the axes run from 0 to travel. Limits (2,) in mm/s, mm/s^2, mm/s^3.
    """

    travel: tuple[float, float] = (300.0, 300.0)
    joint_speed_max: np.ndarray = None  # type: ignore[assignment]
    joint_accel_max: np.ndarray = None  # type: ignore[assignment]
    joint_jerk_max: np.ndarray = None  # type: ignore[assignment]
    name: str = "gantry"
    joint_names: tuple[str, ...] = ("x", "y")

    def __post_init__(self) -> None:
        defaults = {"joint_speed_max": (250.0, 250.0), "joint_accel_max": (2000.0, 2000.0),
                    "joint_jerk_max": (20000.0, 20000.0)}
        for attr, d in defaults.items():
            value = getattr(self, attr)
            object.__setattr__(self, attr, np.asarray(d if value is None else value,
                                                      dtype=np.float64))

    def ik(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) float64 mm: the axis positions are the tool point."""
        return np.array(xy, dtype=np.float64, copy=True)

    def fk(self, joints: np.ndarray) -> np.ndarray:
        """(n, 2) float64 mm."""
        return np.array(joints[:, :2], dtype=np.float64, copy=True)

    def jacobian(self, xy: np.ndarray, joints: np.ndarray | None = None) -> np.ndarray:
        """(n, 2, 2): the identity (each axis follows its coordinate)."""
        return np.broadcast_to(np.eye(2), (len(xy), 2, 2)).copy()

    def box_reachable(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether the box ``[lo, hi]`` ((2,) mm each) lies within the travel (and so does
        every chord between its points: a box is convex)."""
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        return bool(np.isfinite(lo).all() and np.isfinite(hi).all() and (lo >= 0.0).all()
                    and (hi <= np.asarray(self.travel, dtype=np.float64)).all())

    def workspace_violations(self, xy: np.ndarray, joints: np.ndarray | None = None
                             ) -> tuple[np.ndarray, list[str]]:
        xy = np.asarray(xy, dtype=np.float64)
        if len(xy) and self.box_reachable(*points_box(xy)):
            return np.zeros(0, dtype=np.intp), []
        return self._point_violations(xy, joints)

    def _point_violations(self, xy: np.ndarray, joints: np.ndarray | None = None
                          ) -> tuple[np.ndarray, list[str]]:
        """:meth:`workspace_violations` point by point."""
        tr = np.asarray(self.travel)
        out = (xy < -1e-9) | (xy > tr + 1e-9) | ~np.isfinite(xy)
        bad = np.flatnonzero(out.any(axis=1))
        reasons = []
        for i in bad[:10]:
            ax = int(np.flatnonzero(out[i])[0])
            reasons.append(f"{'xy'[ax]} = {xy[i, ax]:.3f} mm outside the travel "
                           f"[0, {tr[ax]:g}] mm (cell.gantry_travel_mm)")
        return bad, reasons


# --------------------------------------------------------------------------- registry


def _scara_from_job(job) -> Scara:
    c, m = job.cell, job.motion
    return Scara(l1=c.l1_mm, l2=c.l2_mm, reach=tuple(c.reach_mm),
                 joint_range=tuple(np.radians(c.joint_range_deg)), elbow=c.elbow,
                 joint_speed_max=np.radians(m.joint_speed_deg_s),
                 joint_accel_max=np.radians(m.joint_accel_deg_s2),
                 joint_jerk_max=np.radians(m.joint_jerk_deg_s3),
                 joint_resolution=np.radians(c.encoder_resolution_deg))


def _gantry_from_job(job) -> Gantry:
    m = job.motion
    return Gantry(travel=tuple(job.cell.gantry_travel_mm),
                  joint_speed_max=np.asarray(m.gantry_speed_mm_s),
                  joint_accel_max=np.asarray(m.gantry_accel_mm_s2),
                  joint_jerk_max=np.asarray(m.gantry_jerk_mm_s3))


ROBOTS: dict[str, Callable[..., Robot]] = {"scara": _scara_from_job, "gantry": _gantry_from_job}


def register_robot(name: str, factory: Callable[..., Robot]) -> None:
    """Add a robot kind: ``factory(job) -> Robot`` is used when ``job.cell.robot == name``."""
    ROBOTS[name] = factory


def get_robot(job) -> Robot:
    """The robot the job names (``job.cell.robot``), built from ``job.cell``/``job.motion``."""
    name = job.cell.robot
    factory = ROBOTS.get(name)
    if factory is None:
        raise ConfigError(f"cell.robot = {name!r}: expected one of {', '.join(sorted(ROBOTS))}")
    return factory(job)


def check_workspace(points: np.ndarray, robot: Robot, *, layer: int = -1, path: int = -1,
                    what: str = "") -> None:
    """Raise :class:`WorkspaceError` if any point of ``points (n, 2)`` mm (robot base frame)
    is unreachable or needs a joint beyond its range.

    The message names the layer and path (when given, ``-1`` = not part of a build), the
    first offending point's index and coordinates, why it fails, and how many points fail.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise WorkspaceError(f"path points must be an (n, 2) array in mm, got shape {pts.shape}")
    if len(pts) == 0:
        return
    bad, reasons = robot.workspace_violations(pts)
    if len(bad) == 0:
        return
    i = int(bad[0])
    where = []
    if layer >= 0:
        where.append(f"layer {layer}")
    if path >= 0:
        where.append(f"path {path}")
    if what:
        where.append(what)
    prefix = (", ".join(where) + ": ") if where else ""
    more = f" ({len(bad)} of {len(pts)} points fail)" if len(bad) > 1 else ""
    raise WorkspaceError(f"{prefix}point {i} at ({pts[i, 0]:.3f}, {pts[i, 1]:.3f}) mm is out of "
                         f"the {robot.name} workspace: {reasons[0]}{more}")
