"""Work estimates: refuse a build the cell cannot make, or absurd work, before it starts.

Ranges on single settings (:mod:`icefab.config`) cannot catch work that depends on the
part and several settings together: a vertex at z = 1e9 mm makes four billion layers at
any layer thickness; a fine simulation grid is fine on a mug and 40 GB on a part as wide
as the workspace. Each stage that allocates in proportion to such work asks this module
first; every check is a few arithmetic operations on bounds and settings, never the work
itself, and raises one line naming the settings to change.

Two kinds of checks:

* the placed part against the machine (:func:`check_placed_part`, before slicing): it
  must fit the vertical stroke (``cell.stroke_mm``, Cobra 600: 210 mm, thesis Table
  2-1) and the reach of the robot (SCARA annulus ``cell.reach_mm`` around the base, or
  the gantry's travel box) where the water nozzle must go, and must not be implausibly
  small for the path width (a file in metres read as millimetres);
* the work of a stage against fixed budgets (:data:`MAX_LAYERS`, :data:`MAX_GRID_CELLS`,
  :data:`MAX_SAMPLES`), each sized so the stage stays well under 2 GB.
"""

from __future__ import annotations

import math

import numpy as np

from icefab.config import Job
from icefab.core import MITER_LIMIT, subdivide_segments
from icefab.errors import ConfigError, SimulationError, WorkspaceError
from icefab.frames import to_base_frame, to_part_frame

#: Most layers a build may have: the tallest stroke a job may describe (5 m,
#: ``cell.stroke_mm``'s upper bound) in the thinnest layers (0.01 mm) would be 500 000;
#: a real build within the Cobra 600's 210 mm stroke has at most 21 000.
MAX_LAYERS = 500_000

#: Most nodes of one height-map or error-surface grid (float64: 8 bytes each, and the
#: simulator keeps a few copies): 25 million is 200 MB per copy, a 500 mm square at
#: 0.1 mm.
MAX_GRID_CELLS = 25_000_000

#: Most trajectory samples (or resampled path points) of a build: each sample carries
#: about 10 float64 (position, joints, speed, flow), so 40 million are about 3 GB spread
#: over the layers; the demo mug at the defaults has under a million.
MAX_SAMPLES = 40_000_000

#: Most trajectory samples of a build planned as a stream (``icefab plan``, the
#: constant-speed comparison: one layer's samples in memory at a time, each layer within
#: :data:`MAX_SAMPLES`): the trajectory file stores about 5 bytes a sample, so 200 million
#: are about 1 GB on disk, within the 2 GB a result file may have
#: (``icefab.resultfiles.MAX_FILE_BYTES``); the 300 mm bunny has 36 million.
MAX_STREAMED_SAMPLES = 200_000_000

#: Most valve pulses of one depositing path (its program's instants are float64 while it
#: is planned: 20 million are 160 MB) and of a whole build (2 bytes a pulse on disk, more
#: with PWM widths: 500 million are 1-2 GB of programs). The demo mug has about 3 million.
MAX_PATH_PULSES = 20_000_000
MAX_BUILD_PULSES = 500_000_000

#: A placed part whose largest horizontal extent is under this many path widths cannot
#: hold a boundary path on each side: almost surely a file in other units.
MIN_WIDTHS_ACROSS = 2.0


def _fmt(v: float) -> str:
    return f"{v:.4g}"


def thinnest_layer(job: Job) -> tuple[str, float]:
    """(setting name in ``slicing``, mm) of the thinnest layer the job slices: the adaptive
    minimum with adaptive layers on (``slicing.cusp_height_mm`` > 0), else the one layer
    thickness (an adaptive job's 0.2 mm plate was refused as under one 0.25 mm layer)."""
    sl = job.slicing
    if sl.cusp_height_mm > 0:
        return "min_layer_thickness_mm", sl.min_layer_thickness_mm
    return "layer_thickness_mm", sl.layer_thickness_mm


def check_layers(z_min: float, z_max: float, job: Job) -> int:
    """The number of layers of a part spanning ``z_min``-``z_max`` mm (after
    ``parts.part_fraction``); ConfigError when it exceeds :data:`MAX_LAYERS` or the
    height is not finite."""
    f0, f1 = job.parts.part_fraction
    height = (float(z_max) - float(z_min)) * (f1 - f0)
    name, t = thinnest_layer(job)
    if not math.isfinite(height):
        raise ConfigError(f"part height {height} mm is not finite: check the mesh "
                          "coordinates and parts.scale")
    n = height / t
    if n > MAX_LAYERS:
        raise ConfigError(f"slicing.{name} = {t:g}: a part {_fmt(height)} mm tall "
                          f"would make {n:.3g} layers, more than {MAX_LAYERS} "
                          "(icefab.workload.MAX_LAYERS); check the part's size (parts.scale, "
                          "a stray vertex) or use thicker layers")
    return max(1, int(round(n)))


def check_placed_part(vertices: np.ndarray, job: Job, faces: np.ndarray | None = None
                      ) -> None:
    """Refuse a placed part that cannot be built by this cell, before slicing.

    vertices: (n, 3) float64, mm, the placed part (after ``parts`` scale, rotation,
    copies and translation), in the part frame; faces: its (m, 3) vertex indices, when
    given the edges are checked against the SCARA's minimum reach too (an edge passes
    nearer the base than its ends: a hunt's triangle with every vertex outside the 163
    mm passed an edge 127 mm from the base, and only 'icefab paths' refused it).
    Raises WorkspaceError naming the settings to change when the part (the slice of it
    ``parts.part_fraction`` selects) is taller than ``cell.stroke_mm``, when a surface
    point lies outside the robot's reach where the water nozzle must put it (with a
    slack of the boundary path's inset, since the paths lie inside the surface), the
    scaffold nozzle the scaffold around it or, with ``feedback.enabled``, the laser
    either, and
    ConfigError when it is under :data:`MIN_WIDTHS_ACROSS` path widths across.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) == 0:
        return
    lo, hi = v.min(axis=0), v.max(axis=0)
    size = hi - lo
    if not np.all(np.isfinite(size)):
        raise WorkspaceError("the placed part has non-finite size: check parts.scale and "
                             "parts.translation")
    f0, f1 = job.parts.part_fraction
    height = size[2] * (f1 - f0)
    stroke = job.cell.stroke_mm
    if height > stroke:
        raise WorkspaceError(
            f"the placed part is {_fmt(height)} mm tall (z {_fmt(lo[2])} to {_fmt(hi[2])} mm: "
            "a stray vertex?), more than the vertical stroke "
            f"cell.stroke_mm = {stroke:g} mm: scale it down (parts.scale = "
            f"{list(job.parts.scale)}), slice part of it (parts.part_fraction) or rotate it "
            "(parts.rotation_deg)")
    check_layers(lo[2], hi[2], job)
    # where it is, not only how tall: the layers keep the part frame's z, which is the
    # robot's above the build plate (z = 0); a part placed at z = 180 mm passed the
    # check above and stopped at 'icefab build', one placed below the plate nowhere
    bottom, top = lo[2] + f0 * size[2], lo[2] + f1 * size[2]
    if bottom < -1e-9 or top > stroke:
        where = "below the build plate (z = 0)" if bottom < -1e-9 else \
            f"above the vertical stroke cell.stroke_mm = {stroke:g} mm"
        raise WorkspaceError(
            f"the placed part spans z {_fmt(bottom)} to {_fmt(top)} mm, {where}: place its "
            f"bottom on the plate (parts.translation = {list(job.parts.translation)}; a "
            "number as the z entry is the part's lowest z, 0 by default)")
    width = job.materials.part.path_width_mm
    across = float(max(size[0], size[1]))
    if across < MIN_WIDTHS_ACROSS * width:
        raise ConfigError(
            f"the placed part is {_fmt(size[0])} x {_fmt(size[1])} x {_fmt(size[2])} mm, "
            f"under {MIN_WIDTHS_ACROSS:g} path widths (materials.part.path_width_mm = "
            f"{width:g}) across: is the file in metres or inches? set parts.scale (e.g. "
            "[1000, 1000, 1000] for metres, [25.4, 25.4, 25.4] for inches)")
    name, t = thinnest_layer(job)
    if height < t:
        if (f0, f1) != (0.0, 1.0):   # the fraction, not the scale (a tester's 3 mm box)
            raise ConfigError(
                f"parts.part_fraction = {list(job.parts.part_fraction)}: the slice of the "
                f"{_fmt(size[2])} mm tall part to build is {_fmt(height)} mm tall, less than "
                f"one layer (slicing.{name} = {t:g})")
        raise ConfigError(
            f"the placed part is {_fmt(height)} mm tall, less than one layer "
            f"(slicing.{name} = {t:g}): check parts.scale = "
            f"{list(job.parts.scale)} (a file in metres needs [1000, 1000, 1000])")
    z0, z1 = lo[2] + f0 * size[2], lo[2] + f1 * size[2]
    xy = v[(v[:, 2] >= z0) & (v[:, 2] <= z1), :2]
    if len(xy) == 0:
        return
    cell = job.cell
    where = ("move or scale it (parts.translation, parts.scale) or the part origin "
             f"(cell.ee_origin_mm = {list(cell.ee_origin_mm)})")
    # the part under the water nozzle; with a surrounding scaffold also the scaffold, which
    # reaches scaffold.buffer_mm beyond the part, under the scaffold nozzle
    checks = [("part", "part", 0.0, "")]
    sc = job.scaffold
    around = sc.enabled and sc.mode == "surround" and sc.buffer_mm > 0
    if around:
        checks.append(("scaffold", "scaffold", sc.buffer_mm,
                       f" with the scaffold around it (scaffold.buffer_mm = {sc.buffer_mm:g})"))
    if job.feedback.enabled:
        # the laser maps the part and its scaffold from its own offset (a tester's part
        # passed here and the paths stage refused its measurement path after the scaffold
        # of every layer, naming no laser)
        grow = sc.buffer_mm if around else 0.0
        checks.append(("laser", "scaffold" if around else "part", grow,
                       f"{' with the scaffold around it' if around else ''} under the laser "
                       f"(cell.laser_offset_mm = {list(cell.laser_offset_mm)}; "
                       "feedback.enabled measures it)"))
    tris = None
    if faces is not None and len(faces) and cell.robot == "scara":
        tris = np.asarray(faces, dtype=np.int64)
        if (f0, f1) != (0.0, 1.0):
            tris = tris[((v[tris, 2] >= z0) & (v[tris, 2] <= z1)).any(axis=1)]
    for tool, material, grow, what in checks:
        mat = job.materials[material]
        slack = mat.initial_offset_mm + mat.path_width_mm - grow
        base = to_base_frame(xy, tool, job)
        if cell.robot == "scara":
            r = np.hypot(base[:, 0], base[:, 1])
            rmin, rmax = cell.reach_mm
            k = int(np.argmax(r))
            if r[k] > rmax + slack:
                raise WorkspaceError(
                    f"the placed part{what} reaches {_fmt(r[k] + grow)} mm from the robot "
                    f"base at part point ({_fmt(xy[k, 0])}, {_fmt(xy[k, 1])}) mm, beyond the "
                    f"reach cell.reach_mm = {list(cell.reach_mm)} (part {_fmt(size[0])} x "
                    f"{_fmt(size[1])} mm across): " + where)
            k = int(np.argmin(r))
            if r[k] < rmin - slack:
                raise WorkspaceError(
                    f"the placed part{what} comes within {_fmt(max(r[k] - grow, 0.0))} mm of "
                    f"the robot base at part point ({_fmt(xy[k, 0])}, {_fmt(xy[k, 1])}) mm, "
                    f"inside the minimum reach cell.reach_mm = {list(cell.reach_mm)}: "
                    + where)
            _check_joint1(xy, base, r, slack, tris if len(xy) == len(v) else None, what,
                          where, job)
            if tris is not None:
                # every corner of the faces (xy holds the slab's vertices, all of them
                # unless parts.part_fraction cuts the part)
                corners = base if len(xy) == len(v) else to_base_frame(v[:, :2], tool, job)
                _check_edges_reach(v[:, :2], corners, tris, slack, grow, what, where, job)
                _check_over_base(corners, tris, tool, what, where, job)
        else:
            travel = np.asarray(cell.gantry_travel_mm, dtype=np.float64)
            out = (base < -slack) | (base > travel + slack)
            if out.any():
                k = int(np.flatnonzero(out.any(axis=1))[0])
                # with the scaffold, the part's point may lie inside the travel and the
                # scaffold around it not: say so (a tester read "(7.539, 0.0244) mm on
                # the gantry, outside its travel [60, 60]")
                beyond = (f" and the scaffold reaches {_fmt(grow)} mm beyond it" if grow > 0
                          else "")
                raise WorkspaceError(
                    f"the placed part{what}: part point ({_fmt(xy[k, 0])}, {_fmt(xy[k, 1])}) "
                    f"mm is at ({_fmt(base[k, 0])}, {_fmt(base[k, 1])}) mm on the "
                    f"gantry{beyond}, outside its travel cell.gantry_travel_mm = "
                    f"{list(cell.gantry_travel_mm)} (0 to {_fmt(travel[0])} x 0 to "
                    f"{_fmt(travel[1])} mm; part {_fmt(size[0])} x {_fmt(size[1])} mm "
                    "across): " + where)


#: Directions sampled on the circle a scaffold reaches around each part point
#: (:func:`_check_joint1`): a point of the circle between two of them lies at most
#: radius (1 - cos(pi / 16)), 2 %, outside the sampled polygon, so the circles can only
#: pass too much, never refuse a scaffold the paths stage takes.
CIRCLE_DIRECTIONS = 16


def _check_joint1(xy: np.ndarray, base: np.ndarray, r: np.ndarray, slack: float,
                  tris: np.ndarray | None, what: str, where: str, job: Job) -> None:
    """WorkspaceError when a point of the placed part needs joint 1 beyond its range by
    more than the slack (as an angle at the point's radius): a part behind the robot passed
    the reach checks and only 'icefab paths' refused it (a hunt's).

    A negative slack is a scaffold reaching ``-slack`` mm beyond the part: its points are
    the circles of that radius around the part's points and along its faces' edges
    (``tris``, indices into ``xy``). Joint 1's angle has no extreme inside a region (its
    rate across the radius, 1 / r, never vanishes), so a disk's extremes lie on its circle;
    an angle of -slack / r at the part's vertices missed a box's edges nearer the base
    (hunt Q)."""
    from icefab.robots import get_robot

    robot = get_robot(job)
    rmin, rmax = job.cell.reach_mm
    ok = (r >= rmin) & (r <= rmax)
    if not ok.any():
        return
    lim = float(robot.joint_range[0])
    if slack < 0.0:
        _check_joint1_around(xy, base, -slack, tris, robot, lim, what, where, job)
        return
    q1 = robot.ik(base[ok])[:, 0]
    over = np.abs(q1) - lim - slack / np.maximum(r[ok], 1.0)
    k = int(np.argmax(over))
    if over[k] > 0:
        i = int(np.flatnonzero(ok)[k])
        raise WorkspaceError(
            f"the placed part{what} needs joint 1 at {math.degrees(q1[k]):.2f} deg at part "
            f"point ({_fmt(xy[i, 0])}, {_fmt(xy[i, 1])}) mm, beyond its range +/-"
            f"{math.degrees(lim):g} deg (cell.joint_range_deg): " + where)


def _check_joint1_around(xy: np.ndarray, base: np.ndarray, rho: float,
                         tris: np.ndarray | None, robot, lim: float, what: str, where: str,
                         job: Job) -> None:
    """:func:`_check_joint1` for a scaffold reaching ``rho`` mm beyond the part: the
    circles of that radius around the part's points and points along its faces' edges
    (at most rho / 2 apart), and the mitred corners of the part's hull.

    First the superset: the hull grown by twice rho (a mitre reaches at most
    ``core.MITER_LIMIT`` times the offset), sampled with a margin of joint 1's rate;
    when it stays within range (the usual case: 1.1 M facets in ~0.1 s) nothing else is
    needed."""
    from scipy.ndimage import maximum_filter1d

    rmin, rmax = job.cell.reach_mm
    # joint 1's rate of change (rad/mm) within rho of each radius, to bound its angle
    # between samples: |grad q1|^2 = 1 / r^2 + f'(r)^2, f(r) joint 1 at (r, 0)
    grid = np.linspace(rmin, rmax, 2049)
    f = robot.ik(np.stack([grid, np.zeros_like(grid)], axis=1))[:, 0]
    cell = (rmax - rmin) / (len(grid) - 1)
    worst = maximum_filter1d(np.hypot(1.0 / np.maximum(grid, 1.0), np.gradient(f, grid)),
                             2 * (int(MITER_LIMIT * rho / cell) + 3) + 1, mode="nearest")

    def rate(p: np.ndarray) -> np.ndarray:
        r = np.hypot(p[:, 0], p[:, 1])
        return worst[np.clip(np.rint((r - rmin) / cell).astype(np.int64), 0, len(grid) - 1)]

    def within(p: np.ndarray, margin: np.ndarray) -> bool:
        r = np.hypot(p[:, 0], p[:, 1])
        ok = (r >= rmin) & (r <= rmax)   # the reach checks judge the others
        return not ok.any() or bool((np.abs(robot.ik(p[ok])[:, 0]) + margin[ok]
                                     < lim).all())

    hv = _hull(base)
    ang = np.linspace(0.0, 2.0 * np.pi, CIRCLE_DIRECTIONS, endpoint=False)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    if len(hv) >= 3:
        grow = MITER_LIMIT * rho
        v = base[hv]
        step = max(0.25 * grow, 1.0)
        along = subdivide_segments(v, np.roll(v, -1, axis=0), step)[0]
        # every point of the grown hull lies within grow (1 - cos(pi / 16)) + step of
        # a sample of a circle around a vertex or an edge point
        sample = (along[:, None, :] + grow * ring[None]).reshape(-1, 2)
        slack = grow * (1.0 - math.cos(math.pi / CIRCLE_DIRECTIONS)) + step
        if within(sample, 1.1 * slack * rate(sample)):
            return
    pts, part = base, xy
    if tris is not None and len(tris):
        edges = np.concatenate([tris[:, :2], tris[:, 1:], tris[:, ::2]])
        a, b = base[edges[:, 0]], base[edges[:, 1]]
        step = max(0.5 * rho, 1.0)
        long = np.flatnonzero(np.hypot(*(b - a).T) > step)
        if len(long):   # the inner points of the edges longer than a step
            inner, i, t = subdivide_segments(a[long], b[long], step)
            keep = t > 0   # the edges' starts are the part's points already
            e, t = long[i[keep]], t[keep][:, None]
            pts = np.concatenate([base, inner[keep]])
            pa, pb = xy[edges[e, 0]], xy[edges[e, 1]]
            part = np.concatenate([xy, pa + t * (pb - pa)])
    # only the points whose circle may need joint 1 beyond its range
    q1 = robot.ik(pts)[:, 0]
    near = np.flatnonzero(np.abs(q1) + 1.1 * rho * rate(pts) >= lim)
    circ = (pts[near][:, None, :] + rho * ring[None]).reshape(-1, 2)
    owner = np.repeat(near, CIRCLE_DIRECTIONS)
    # the scaffold's wall is a mitred offset (geometry.expand): at the outline's convex
    # corners it reaches beyond the circles, up to twice the buffer
    corner, at = _mitred_corners(base, hv, rho)
    circ, owner = np.concatenate([circ, corner]), np.concatenate([owner, at])
    rc = np.hypot(circ[:, 0], circ[:, 1])
    inside = (rc >= rmin) & (rc <= rmax)   # the reach checks judge the others
    if not inside.any():
        return
    idx = np.flatnonzero(inside)
    qc = robot.ik(circ[idx])[:, 0]
    k = int(np.argmax(np.abs(qc)))
    if abs(qc[k]) > lim:
        i = int(owner[idx[k]])
        raise WorkspaceError(
            f"the placed part{what} needs joint 1 at {math.degrees(qc[k]):.2f} deg "
            f"{_fmt(rho)} mm or more beyond part point ({_fmt(part[i, 0])}, "
            f"{_fmt(part[i, 1])}) mm, beyond its range +/-{math.degrees(lim):g} deg "
            "(cell.joint_range_deg): " + where)


def _hull(pts: np.ndarray) -> np.ndarray:
    """Indices of the convex hull's vertices of ``pts`` (n, 2), counter-clockwise; empty
    for fewer than 3 points or all on a line."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return ConvexHull(pts).vertices
    except (QhullError, ValueError):
        return np.zeros(0, dtype=np.int64)


def _mitred_corners(pts: np.ndarray, hv: np.ndarray, rho: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The corners of the convex hull (vertices ``hv``, counter-clockwise, indices into
    ``pts`` (n, 2) mm) offset outward by ``rho`` mm as Clipper2 joins them under
    ``core.MITER_LIMIT``: a mitre point, or where the mitre would reach further, the
    two ends of the square cut across the bisector rho out; and the index of each
    one's vertex. On a convex outline these are its wall's own corners; a sharper corner
    of another outline at a hull vertex is joined its own way, within about rho of them
    (the check is early, the paths stage's is exact)."""
    if len(hv) < 3:
        return np.zeros((0, 2)), np.zeros(0, dtype=np.int64)
    v = pts[hv]
    e = np.roll(v, -1, axis=0) - v                     # edge i: vertex i -> i + 1
    e /= np.maximum(np.hypot(e[:, 0], e[:, 1]), 1e-300)[:, None]
    nrm = np.stack([e[:, 1], -e[:, 0]], axis=1)       # outward normals of a CCW ring
    n1, n2 = np.roll(nrm, 1, axis=0), nrm             # the edges before and after
    cos = np.einsum("ij,ij->i", n1, n2)
    mitred = cos > 2.0 / MITER_LIMIT ** 2 - 1.0        # Clipper2's test for a mitre
    tip = v + rho * (n1 + n2) / np.maximum(1.0 + cos, 1e-12)[:, None]
    # a square join: the line rho out along the bisector bs meets each edge's offset
    # line (p - v) . n = rho at p = v + rho (bs + t bs_perp), t = (1 - bs.n) / (bs_perp.n)
    bs = n1 + n2
    bs /= np.maximum(np.hypot(bs[:, 0], bs[:, 1]), 1e-300)[:, None]
    bp = np.stack([-bs[:, 1], bs[:, 0]], axis=1)
    ends = []
    for nn in (n1, n2):
        den = np.einsum("ij,ij->i", bp, nn)
        t = (1.0 - np.einsum("ij,ij->i", bs, nn)) / np.where(np.abs(den) > 1e-12, den, 1.0)
        ends.append(v + rho * (bs + t[:, None] * bp))
    sq = ~mitred
    return (np.concatenate([tip[mitred], ends[0][sq], ends[1][sq]]),
            np.concatenate([hv[mitred], hv[sq], hv[sq]]))


def _check_edges_reach(xy: np.ndarray, vb: np.ndarray, tris: np.ndarray, slack: float,
                       grow: float, what: str, where: str, job: Job) -> None:
    """WorkspaceError when an edge of a face (``tris (m, 3)`` indices into the part points
    ``xy``, ``vb`` the same in the robot base frame) of the placed part passes inside the
    SCARA's minimum reach (less the slack) between ends that lie outside it."""
    rmin = job.cell.reach_mm[0]
    x, y = vb[:, 0], vb[:, 1]
    # only the edges whose box meets the minimum reach's (1.1 M facets: 2.4 -> 0.3 s)
    reach = rmin - slack
    if x.min() > reach or x.max() < -reach or y.min() > reach or y.max() < -reach:
        return   # the part's box stays clear of the minimum reach's (the usual case)
    edges = np.concatenate([tris[:, :2], tris[:, 1:], tris[:, ::2]])
    ea, eb = edges[:, 0], edges[:, 1]
    xa, xb, ya, yb = x[ea], x[eb], y[ea], y[eb]
    near = ((np.minimum(xa, xb) <= reach) & (np.maximum(xa, xb) >= -reach)
            & (np.minimum(ya, yb) <= reach) & (np.maximum(ya, yb) >= -reach))
    if not near.any():
        return
    edges = edges[near]
    a, b = vb[edges[:, 0]], vb[edges[:, 1]]
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(-np.einsum("ij,ij->i", a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    near = a + t[:, None] * d
    r = np.hypot(near[:, 0], near[:, 1])
    k = int(np.argmin(r))
    if r[k] < reach:
        p = xy[edges[k, 0]] + t[k] * (xy[edges[k, 1]] - xy[edges[k, 0]])
        raise WorkspaceError(
            f"the placed part{what} comes within {_fmt(max(r[k] - grow, 0.0))} mm of the "
            f"robot base along an edge through part point ({_fmt(p[0])}, {_fmt(p[1])}) mm, "
            f"inside the minimum reach cell.reach_mm = {list(job.cell.reach_mm)}: " + where)


def _check_over_base(vb: np.ndarray, tris: np.ndarray, tool: str, what: str, where: str,
                     job: Job) -> None:
    """WorkspaceError when a face (``tris (m, 3)`` indices into the part points in the
    robot base frame ``vb``) of the placed part lies over the SCARA's base axis: its
    section there holds points at radius 0, though every vertex and edge may lie beyond
    the minimum reach (a plate around the base; only 'icefab paths' refused it)."""
    x, y = vb[:, 0], vb[:, 1]
    if x.min() > 0 or x.max() < 0 or y.min() > 0 or y.max() < 0:
        return   # the part's box does not hold the base axis (the usual case: at once)
    xs, ys = x[tris], y[tris]                       # (m, 3) corners
    over = ((xs.min(axis=1) <= 0) & (xs.max(axis=1) >= 0)
            & (ys.min(axis=1) <= 0) & (ys.max(axis=1) >= 0))
    if not over.any():
        return
    xs, ys = xs[over], ys[over]
    # the origin's side of each edge: inside a triangle when all three agree
    c = [xs[:, i] * ys[:, (i + 1) % 3] - ys[:, i] * xs[:, (i + 1) % 3] for i in range(3)]
    inside = ((c[0] >= 0) & (c[1] >= 0) & (c[2] >= 0)) | ((c[0] <= 0) & (c[1] <= 0)
                                                          & (c[2] <= 0))
    # a face seen edge-on (zero area in plan) holds no section
    area = np.abs((xs[:, 1] - xs[:, 0]) * (ys[:, 2] - ys[:, 0])
                  - (xs[:, 2] - xs[:, 0]) * (ys[:, 1] - ys[:, 0]))
    if (inside & (area > 1e-12)).any():
        base = to_part_frame(np.zeros((1, 2)), tool, job)[0]
        raise WorkspaceError(
            f"the placed part{what} lies over the robot base (the base axis at part point "
            f"({_fmt(base[0])}, {_fmt(base[1])}) mm is under it), inside the minimum reach "
            f"cell.reach_mm = {list(job.cell.reach_mm)}: " + where)


def check_copies(extent_mm: np.ndarray, job: Job) -> None:
    """Refuse ``parts.copies`` whose grid is wider than any workspace of this cell before
    the copies are made (a 100 x 100 grid of a large part would allocate gigabytes).

    extent_mm: (3,) float64, the size of one placed copy before translation.
    """
    p1, p2, p3 = job.parts.copies
    if p3 <= 1:
        return
    cols, rows = min(p1, p3), math.ceil(p3 / p1)
    gap = job.parts.copy_gap_mm
    wide = cols * float(extent_mm[0]) + (cols - 1) * gap
    deep = rows * float(extent_mm[1]) + (rows - 1) * gap
    cell = job.cell
    room = (2.0 * cell.reach_mm[1] if cell.robot == "scara"
            else float(max(cell.gantry_travel_mm)))
    if max(wide, deep) > room:
        raise WorkspaceError(
            f"parts.copies = {list(job.parts.copies)}: the grid of copies is "
            f"{_fmt(wide)} x {_fmt(deep)} mm, wider than the {_fmt(room)} mm the robot can "
            "reach; make fewer copies or a smaller gap (parts.copy_gap_mm)")


def check_grid(lo: np.ndarray, hi: np.ndarray, spacing: float, setting: str) -> None:
    """Refuse a grid over the box ``lo``-``hi`` (mm, (2,)) at ``spacing`` mm with more than
    :data:`MAX_GRID_CELLS` nodes; the message names ``setting`` (the pitch's setting)."""
    span = np.asarray(hi, dtype=np.float64) - np.asarray(lo, dtype=np.float64)
    if not (spacing > 0 and np.all(np.isfinite(span))):
        raise SimulationError(f"{setting} = {spacing!r}: grid over {span.tolist()} mm "
                              "cannot be made")
    cells = (span[0] / spacing + 2.0) * (span[1] / spacing + 2.0)
    if cells > MAX_GRID_CELLS:
        raise SimulationError(
            f"{setting} = {spacing:g}: a {_fmt(span[0])} x {_fmt(span[1])} mm grid would have "
            f"{cells:.3g} nodes, more than {MAX_GRID_CELLS} (icefab.workload.MAX_GRID_CELLS); "
            "use a coarser pitch")


def check_samples(length_mm: float, spacing_mm: float, setting: str, *,
                  streamed: bool = False, what: str = "the build") -> None:
    """Refuse resampling ``length_mm`` of paths every ``spacing_mm`` when that makes more
    samples than :data:`MAX_SAMPLES` (``streamed``: :data:`MAX_STREAMED_SAMPLES`); the
    message names ``setting`` and ``what``."""
    limit, budget = ((MAX_STREAMED_SAMPLES, "MAX_STREAMED_SAMPLES") if streamed
                     else (MAX_SAMPLES, "MAX_SAMPLES"))
    n = float(length_mm) / spacing_mm
    if not math.isfinite(n) or n > limit:
        raise ConfigError(
            f"{setting}: {what} would need {n:.3g} samples, more than {limit} "
            f"(icefab.workload.{budget})")


def check_paths(areas_mm2: tuple[float, float], job: Job) -> None:
    """Refuse path planning whose fill alone exceeds the sample budget.

    areas_mm2: total (part, scaffold) area over all layers, mm^2. A region of area A
    filled at ``fill_width_mm`` w holds about A / w mm of fill paths; the trajectories
    resample them every ``motion.point_spacing_mm``, so a build over
    :data:`MAX_SAMPLES` x that spacing of fill would be refused there after the whole
    path planning: refuse it here, before.
    """
    mats = job.materials
    length = areas_mm2[0] / mats.part.fill_width_mm + areas_mm2[1] / mats.scaffold.fill_width_mm
    spacing = job.motion.point_spacing_mm
    if not math.isfinite(length) or length / spacing > MAX_SAMPLES:
        raise ConfigError(
            f"materials.*.fill_width_mm = {mats.part.fill_width_mm:g} / "
            f"{mats.scaffold.fill_width_mm:g}: {_fmt(sum(areas_mm2) / 100.0)} cm^2 of layers "
            f"would need about {_fmt(length / 1000.0)} m of fill paths, {length / spacing:.3g} "
            f"samples at motion.point_spacing_mm = {spacing:g}, more than {MAX_SAMPLES} "
            "(icefab.workload.MAX_SAMPLES)")


def check_motion(deposit_mm: float, other_mm: float, job: Job, *,
                 streamed: bool = False, what: str = "the build") -> None:
    """Refuse trajectory planning whose samples alone exceed the budget (``streamed``,
    ``what``: as :func:`check_samples`'s).

    deposit_mm, other_mm: total length of the depositing paths and of the rest (travel,
    measurement), mm. Counted: every path resampled every ``motion.point_spacing_mm``,
    and sampled every ``motion.dt_s`` at no more than its speed bound (depositing paths
    ``motion.speed_mm_s``, the rest the fastest of the travel and measurement speeds), a
    lower bound of the samples the planner makes.
    """
    m = job.motion
    check_samples(deposit_mm + other_mm, m.point_spacing_mm,
                  f"motion.point_spacing_mm = {m.point_spacing_mm:g}", streamed=streamed, what=what)
    fast = max(m.travel_speed_mm_s, m.measure_speed_mm_s)
    n_mm = deposit_mm / m.speed_mm_s + other_mm / fast  # seconds: samples x dt
    check_samples(n_mm, m.dt_s, f"motion.dt_s = {m.dt_s:g} with motion.speed_mm_s = "
                                f"{m.speed_mm_s:g}", streamed=streamed, what=what)


def check_pulses(layers, job: Job) -> None:
    """Refuse valve programs whose pulses would exceed :data:`MAX_PATH_PULSES` on one path
    or :data:`MAX_BUILD_PULSES` in all, before any is planned.

    layers: the ``LayerMotion`` whose depositing trajectories get programs
    (:func:`check_pulse_durations` of their durations).
    """
    check_pulse_durations(np.array([t.duration for lm in layers for t in lm.trajectories
                                    if t.path is None or t.path.depositing],
                                   dtype=np.float64), job)


def check_pulse_durations(durations: np.ndarray, job: Job) -> None:
    """:func:`check_pulses` from the durations (s) of the depositing trajectories, e.g. a
    trajectory file's per-trajectory members, before any sample is read. They are counted
    at the highest rate the valve is driven: in FM ``min(flow.max_frequency_hz, 1 /
    flow.tick_s, 1000 / flow.calibration_pulse_ms)``, in PWM ``flow.pwm_frequency_hz`` (an
    upper bound: FM pulses follow the flow).
    """
    fl = job.flow
    if fl.mode == "fm":
        rate = min(fl.max_frequency_hz, 1.0 / fl.tick_s, 1000.0 / fl.calibration_pulse_ms)
        name = f"flow.max_frequency_hz = {fl.max_frequency_hz:g}"
    else:
        rate = fl.pwm_frequency_hz
        name = f"flow.pwm_frequency_hz = {fl.pwm_frequency_hz:g}"
    d = np.asarray(durations, dtype=np.float64)
    if not d.size:
        return
    longest, total = float(d.max()) * rate, float(d.sum()) * rate
    if longest > MAX_PATH_PULSES:
        raise ConfigError(f"{name}: the longest depositing path ({_fmt(float(d.max()))} s) "
                          f"would take up to {longest:.3g} valve pulses, more than "
                          f"{MAX_PATH_PULSES} (icefab.workload.MAX_PATH_PULSES): a lower "
                          "valve frequency, or shorter paths")
    if total > MAX_BUILD_PULSES:
        raise ConfigError(f"{name}: the build's depositing paths ({_fmt(float(d.sum()))} s) "
                          f"would take up to {total:.3g} valve pulses, more than "
                          f"{MAX_BUILD_PULSES} (icefab.workload.MAX_BUILD_PULSES): a lower "
                          "valve frequency, or fewer layers at a time (--layers)")
