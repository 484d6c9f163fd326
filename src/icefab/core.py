"""Core data types: the contract between pipeline stages.

All types are frozen dataclasses holding numpy arrays; stages are pure functions over
them. Units: millimetres and seconds; angles in radians inside arrays (degrees only at the
interface: config, CLI, files).

Ring convention (icefab): a ring is an ``(k, 2) float64`` array of distinct points, the
closing edge from the last point back to the first is implied (the first point is NOT
repeated). Outer rings are counter-clockwise (positive signed area), holes are clockwise
(negative signed area), so the signed areas of a region's rings add up to its area.
The thesis (Ch. 3.2) uses the opposite orientation; convert where thesis data is read.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
import itertools
import math
import operator
import typing
from typing import TYPE_CHECKING, Iterator, Literal, Sequence

import numpy as np

from icefab.errors import GeometryError

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job

Material = Literal["part", "scaffold"]
Role = Literal["boundary", "fill", "measure", "travel"]
Frame = Literal["part", "base"]
#: Miter limit of every offset (multiples of the offset distance) before a corner is
#: squared off (:mod:`icefab.geometry`'s offsets; the placement checks of
#: :mod:`icefab.workload` follow the scaffold's mitred wall with it).
MITER_LIMIT = 2.0

#: The tool a path is given for; "" means derived from role and material (Toolpath.tool_name).
Tool = Literal["", "part", "scaffold", "laser"]

MATERIALS: tuple[str, ...] = typing.get_args(Material)
ROLES: tuple[str, ...] = typing.get_args(Role)
FRAMES: tuple[str, ...] = typing.get_args(Frame)
TOOLS: tuple[str, ...] = typing.get_args(Tool)
#: The roles along which material flows (:attr:`Toolpath.depositing`), and their indices
#: in ``ROLES`` (the codes of packed paths).
DEPOSITING_ROLES: tuple[str, ...] = ("boundary", "fill")
DEPOSITING_CODES: tuple[int, ...] = tuple(ROLES.index(r) for r in DEPOSITING_ROLES)


def offsets(counts) -> np.ndarray:
    """(n + 1,) int64 start offsets of ``n`` items of ``counts`` rows each: ``[0, cumsum]``
    (item i is rows ``offsets[i]:offsets[i + 1]`` of the items concatenated). The one
    encoding of ragged arrays (``icefab.resultfiles`` stores them so)."""
    if isinstance(counts, list) and len(counts) < 256:
        # a few rings' lengths (the paths stage packs ring lists some 240 times a bunny
        # layer): numpy's cumsum costs 5 us a call however short, this 1.5 us
        return np.fromiter(itertools.accumulate(counts, operator.add, initial=0),
                           dtype=np.int64, count=len(counts) + 1)
    counts = np.asarray(counts, dtype=np.int64).reshape(-1)
    out = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=out[1:])
    return out


def split_rows(a: np.ndarray, cuts) -> list[np.ndarray]:
    """``np.split(a, cuts)``: views of ``a``'s rows between the row indices ``cuts`` (and
    before the first, after the last), without ``np.split``'s cost per piece (two
    ``swapaxes`` each: 2 % of the paths stage, which cuts thousands of centre lines, disk
    hulls and tour curves a layer)."""
    c = np.asarray(cuts, dtype=np.int64).tolist()
    return [a[s:e] for s, e in zip([0, *c], [*c, len(a)])]


def subdivide_segments(a: np.ndarray, b: np.ndarray, step: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points along the segments ``a[i] -> b[i]`` ((n, 2) each, mm) at most ``step`` apart:
    each segment's start and ``ceil(length / step) - 1`` evenly spaced inner points (its
    end is the next segment's start, or not included). Returns (points (s, 2), segment of
    each point (s,), fraction along it (s,))."""
    seg = np.linalg.norm(b - a, axis=1)
    n = np.maximum(1, np.ceil(seg / step).astype(np.int64))
    i = np.repeat(np.arange(len(seg)), n)
    t = (np.arange(len(i)) - np.repeat(np.cumsum(n) - n, n)) / n[i]
    return a[i] + t[:, None] * (b - a)[i], i, t


def arc_lengths(seg: np.ndarray) -> np.ndarray:
    """(k + 1,) float64 distance along a polyline at each of its points, from its
    segments' lengths ``seg`` (k,) mm: ``[0, cumsum(seg)]``."""
    return np.concatenate([[0.0], np.cumsum(seg)])


def closed_polyline(points: np.ndarray, closed: bool = True) -> np.ndarray:
    """The polyline of a ring (first point not repeated) with its closing edge: the first
    point appended, when ``closed`` and the ring has more than one point; else the points
    as they are. The one place a ring is closed."""
    if closed and len(points) > 1:
        return np.concatenate([points, points[:1]])
    return points


def signed_area(ring: np.ndarray) -> float:
    """Signed area (mm^2) of a ring ``(k, 2)``: positive when counter-clockwise (the
    shoelace formula, the closing edge's term added apart so no array is copied; the one
    definition, ``icefab.geometry`` re-exports it)."""
    x = ring[:, 0]
    y = ring[:, 1]
    return 0.5 * float(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])
                       + x[-1] * y[0] - x[0] * y[-1])


# --------------------------------------------------------------------------- mesh


@dataclass(frozen=True, eq=False)
class Mesh:
    """An indexed triangle mesh.

    vertices: (n, 3) float64, mm.
    faces: (m, 3) int64, indices into ``vertices``; counter-clockwise seen from outside.
    name: where it came from (file name or generator), used in messages.
    warnings: what loading found and fixed (counts per defect, see ``MeshReport``); the
        slicer passes them on to ``Stack.warnings``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    name: str = ""
    warnings: tuple[str, ...] = ()

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64: minimum and maximum corner, mm."""
        if len(self.vertices) == 0:
            return np.zeros((2, 3))
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    @property
    def n_faces(self) -> int:
        return int(len(self.faces))

    def triangles(self) -> np.ndarray:
        """(m, 3, 3) float64: the corner coordinates of every face, mm."""
        return self.vertices[self.faces]


# --------------------------------------------------------------------------- regions


@dataclass(frozen=True, eq=False)
class Region:
    """A planar area bounded by closed rings (see the module docstring for orientation).

    rings: tuple of (k_i, 2) float64 arrays, mm, first point not repeated.
    parent: (r,) int64; ``parent[i]`` is the index of the ring directly enclosing ring i,
        or -1 for a top-level outer ring. Holes have an outer ring as parent; an island
        inside a hole has that hole as parent (the thesis' hierarchy array q, Ch. 3.2).
        Depth parity tells outer (even) from hole (odd).
    """

    rings: tuple[np.ndarray, ...] = ()
    parent: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        # a Region a program built with a parent index past its rings was an IndexError in
        # depth(), (k, 3) rings numpy's broadcast error in the first area
        parent = self.parent
        if not (type(parent) is np.ndarray and parent.dtype == np.int64):
            try:
                parent = np.asarray(parent, dtype=np.int64)
            except (TypeError, ValueError):
                parent = np.zeros(0, dtype=np.int64) - 2
            object.__setattr__(self, "parent", parent)
        n = len(self.rings)
        if parent.shape != (n,) or (n and (parent.min() < -1 or parent.max() >= n)):
            raise GeometryError(f"Region: parent {np.asarray(self.parent).tolist()!r} for {n} "
                                f"rings: expected one index per ring, each -1 (top level) or "
                                f"another ring's index below {n}")
        for i, r in enumerate(self.rings):
            if not (type(r) is np.ndarray and r.ndim == 2 and r.shape[1] == 2):
                raise GeometryError(f"Region: ring {i} of shape {np.shape(r)}: expected a "
                                    "(k, 2) array of x, y in mm")

    @staticmethod
    def empty() -> "Region":
        return Region()

    def __len__(self) -> int:
        return len(self.rings)

    @property
    def is_empty(self) -> bool:
        return len(self.rings) == 0

    @property
    def area(self) -> float:
        """Area in mm^2 (sum of signed ring areas)."""
        return float(sum(signed_area(r) for r in self.rings))

    def ring_areas(self) -> np.ndarray:
        """(r,) float64 signed areas, mm^2."""
        return np.array([signed_area(r) for r in self.rings], dtype=np.float64)

    def depth(self) -> np.ndarray:
        """(r,) int64 nesting depth of every ring (0 = top-level outer ring); GeometryError
        when ``parent`` runs in a circle (a Region a program built: it looped for ever)."""
        parent = np.asarray(self.parent, dtype=np.int64)
        d = np.zeros(len(parent), dtype=np.int64)
        up = parent.copy()
        for _ in range(len(parent) + 1):      # every step climbs one level for all rings
            inside = up >= 0
            if not inside.any():
                return d
            d[inside] += 1
            up[inside] = parent[up[inside]]
        raise GeometryError(f"Region: parent {parent.tolist()} runs in a circle")

    def polygons(self) -> list[list[np.ndarray]]:
        """The region as polygons ``[outer, hole, hole, ...]`` (the thesis' contour groups A)."""
        depth = self.depth()
        groups: dict[int, list[np.ndarray]] = {}
        order: list[int] = []
        for i, ring in enumerate(self.rings):
            if depth[i] % 2 == 0:
                groups[i] = [ring]
                order.append(i)
        for i, ring in enumerate(self.rings):
            if depth[i] % 2 == 1:
                groups[int(self.parent[i])].append(ring)
        return [groups[i] for i in order]

    def bounds(self) -> np.ndarray:
        """(2, 2) float64 min and max corner, mm; zeros when empty."""
        if self.is_empty:
            return np.zeros((2, 2))
        pts = np.concatenate(self.rings)
        return np.stack([pts.min(axis=0), pts.max(axis=0)])

    @property
    def n_points(self) -> int:
        return int(sum(len(r) for r in self.rings))


# --------------------------------------------------------------------------- layers


@dataclass(frozen=True, eq=False)
class Layer:
    """One layer of the build.

    index: 0 for the bottom layer.
    z: height of the cutting plane actually used, mm (see ``icefab.slicing`` for where
        inside the layer it lies); the layer's top surface is at ``top_z``.
    top_z: height of the layer's top surface, mm.
    part: the part-material (water) region.
    scaffold: the scaffold-material region (empty until ``add_scaffold``).
    thickness: the layer's own thickness, mm, when layers differ (adaptive slicing,
        ``slicing.cusp_height_mm``); NaN: the stack's ``layer_thickness``.
    """

    index: int
    z: float
    part: Region
    scaffold: Region = field(default_factory=Region)
    top_z: float = float("nan")
    thickness: float = float("nan")


@dataclass(frozen=True, eq=False)
class Stack:
    """All layers of a build, bottom first, with the job they were made with.

    warnings: human-readable findings made while slicing (open contours closed, thin
        features, ...), each naming its layer.
    """

    layers: tuple[Layer, ...]
    job: "Job"
    layer_thickness: float
    warnings: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.layers)

    def __iter__(self) -> Iterator[Layer]:
        return iter(self.layers)

    def __getitem__(self, i: int) -> Layer:
        return self.layers[i]

    @property
    def thicknesses(self) -> np.ndarray:
        """(n,) float64 mm: every layer's thickness (its own, else ``layer_thickness``)."""
        t = np.array([L.thickness for L in self.layers], dtype=np.float64)
        return np.where(np.isfinite(t), t, self.layer_thickness)


@dataclass(frozen=True, eq=False)
class RuledEdges:
    """The generators from every part contour point of layer k to layer k+1.

    Per contour point (n,), in the order of the stack's layers, rings and points:
    layer: int64 index (in the stack) of the lower layer; ring: int64 ring index within
    its region; point: (n, 2) float64 mm, the contour point; z: float64 mm, its layer's
    cutting height; match: (n, 2) float64 mm, the matched point on the next layer's
    contour (NaN when none); match_ring: int64 ring index in the next layer (-1 none);
    dz: float64 mm, the height to the next layer's cutting plane (NaN when none);
    tilt: float64 rad in (-pi/2, pi/2), the generator's angle from vertical, positive
    leaning out of the material (NaN when no match).
    Made by :func:`icefab.ruled.ruled_edges`; the top layer has no match anywhere.
    """

    layer: np.ndarray
    ring: np.ndarray
    point: np.ndarray
    z: np.ndarray
    match: np.ndarray
    match_ring: np.ndarray
    dz: np.ndarray
    tilt: np.ndarray

    def __len__(self) -> int:
        return len(self.layer)

    @property
    def matched(self) -> np.ndarray:
        """(n,) bool: points with a generator."""
        return self.match_ring >= 0


# --------------------------------------------------------------------------- paths


@dataclass(frozen=True, eq=False)
class Toolpath:
    """One deposition, measurement or travel path.

    points: (k, 2) float64, mm, in the part (building) frame unless ``frame`` says else.
    z: height, mm.
    material: "part" or "scaffold" (the tool: water or scaffold nozzle; measure paths
        carry the material whose surface they measure).
    role: "boundary", "fill", "measure" or "travel".
    closed: a closed path returns to its first point (the point is not repeated).
    width: deposition width, mm (0 for travel and measure; a deposition path given 0 is
        laid at its material's width, the fill width for fill and the path width
        otherwise, by the valve programs and the simulator alike); for a variable-width
        path its nominal width: the mean of ``widths`` over the length.
    layer: index of the layer it belongs to (-1 when not part of a stack).
    frame: "part" (building frame) or "base" (robot base frame).
    tool: whose frame the points are given for: "part" (water nozzle), "scaffold"
        (scaffold nozzle) or "laser"; "" means derived (see ``tool_name``).
    widths: None (the path is ``width`` wide all along) or (k,) float64 mm, the deposition
        width at each point of a variable-width path (issue 15; the idea of Arachne): it
        varies linearly along every segment (a closed path's last segment from the last
        point's width back to the first's) and the valve deposits ``w(s) dh c(s)``.
    off: None (a depositing path deposits all along) or (k,) bool: True where the segment
        leaving the point deposits nothing (the valve is OFF: Ossino's state OFF). A
        continuous tour (issue 15, :func:`icefab.paths.join_tours`) is one open path of
        several deposition paths and the travel between them, which the robot follows
        without stopping; its travel segments are off. The last point of an open path
        leaves no segment (its entry is ignored).
    """

    points: np.ndarray
    z: float = 0.0
    material: Material = "part"
    role: Role = "boundary"
    closed: bool = False
    width: float = 0.0
    layer: int = -1
    frame: Frame = "part"
    tool: Tool = ""
    widths: np.ndarray | None = None
    off: np.ndarray | None = None

    def __post_init__(self) -> None:
        # the names a program can mistype (a tester's role "fil" planned and got no pulse,
        # frame "world" was taken as the part frame, a width of -1.5 as the fill width)
        if self.material not in MATERIALS or self.role not in ROLES \
                or self.frame not in FRAMES or self.tool not in TOOLS:
            raise GeometryError(f"Toolpath: material {self.material!r}, role {self.role!r}, "
                                f"frame {self.frame!r}, tool {self.tool!r}: expected material "
                                f"in {MATERIALS}, role in {ROLES}, frame in {FRAMES}, tool in "
                                f"{TOOLS}")
        if not self.width >= 0.0 or self.width == float("inf"):
            raise GeometryError(f"Toolpath: width {self.width!r}: expected a finite width >= 0 "
                                "mm")
        try:
            z_ok = math.isfinite(self.z)
        except TypeError:
            z_ok = False
        if not z_ok:
            # a NaN z planned a trajectory and sent it (the robot's z is the layer's)
            raise GeometryError(f"Toolpath: z {self.z!r}: expected a finite height, mm")
        pts = self.points
        if not (type(pts) is np.ndarray and pts.dtype == np.float64 and pts.ndim == 2
                and pts.shape[1] == 2):
            # (k, 3) points were numpy's broadcast error deep in the motion stage; a list
            # is taken as the array it spells (the stages' own checks name NaN points)
            try:
                arr = np.asarray(pts, dtype=np.float64)
            except (TypeError, ValueError):
                arr = None
            if arr is None or arr.ndim != 2 or arr.shape[1] != 2:
                what = (f"of shape {arr.shape}" if arr is not None
                        else f"{type(pts).__name__} {pts!r:.40}")
                raise GeometryError(f"Toolpath: points {what}: expected a (k, 2) array of "
                                    "x, y in mm")
            object.__setattr__(self, "points", arr)

    @property
    def tool_name(self) -> str:
        """The tool that follows the path: ``tool`` if set, else "laser" for measure
        paths and the material's nozzle otherwise."""
        if self.tool:
            return self.tool
        return "laser" if self.role == "measure" else self.material

    @property
    def depositing(self) -> bool:
        """True when material flows along this path (Ossino's ON1/ON2 vs OFF)."""
        return self.role in DEPOSITING_ROLES

    def polyline(self) -> np.ndarray:
        """(k or k+1, 2) points with the first point repeated at the end when closed."""
        return closed_polyline(self.points, self.closed)

    def polyline_widths(self) -> np.ndarray:
        """(k or k+1,) float64 mm: the width at every point of :meth:`polyline` (``width``
        everywhere for a constant-width path)."""
        if self.widths is None:
            return np.full(len(self.polyline()), float(self.width))
        return closed_polyline(np.asarray(self.widths, dtype=np.float64), self.closed)

    def segment_on(self) -> np.ndarray:
        """(k - 1 or k,) bool: which segments of :meth:`polyline` deposit (all of a
        depositing path without ``off``, none of a travel or measurement path)."""
        n = max(len(self.polyline()) - 1, 0)
        if not self.depositing:
            return np.zeros(n, dtype=bool)
        if self.off is None:
            return np.ones(n, dtype=bool)
        return ~np.asarray(self.off, dtype=bool)[:n]

    def deposited_runs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The stretches of :meth:`polyline` that deposit, as ``(points (m >= 2, 2) mm,
        widths (m,) mm)`` pairs in path order: the whole polyline of a depositing path
        without ``off``, a tour's deposition paths without its travel, nothing for travel
        and measurement paths."""
        on = self.segment_on()
        if not on.any():
            return []
        poly, w = self.polyline(), self.polyline_widths()
        return [(poly[a:b + 1], w[a:b + 1]) for a, b in true_runs(on)]

    @property
    def length(self) -> float:
        """Length along the path, mm (including the closing segment when closed)."""
        p = self.polyline()
        if len(p) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def widths_problem(path: Toolpath) -> str:
    """What is wrong with a path's per-point widths ('' when nothing: None, or (k,) finite
    and >= 0 with the points' k)."""
    if path.widths is None:
        return ""
    w = np.asarray(path.widths)
    if w.shape != (len(path.points),):
        return f"widths have shape {w.shape}, expected ({len(path.points)},): one per point"
    if w.dtype.kind not in "fiu" or not np.all(np.isfinite(w)) or np.any(w < 0):
        return "widths must be finite numbers >= 0 mm"
    return ""


def tour_members(path: Toolpath) -> list[Toolpath]:
    """The deposition paths a continuous tour joins (its :meth:`Toolpath.deposited_runs`
    as paths of its material, role and layer: closed where a run returns to its first
    point, with widths per point when the tour has them); ``[path]`` for any other path.
    What the coverage and shape checks look at: a tour's travel deposits nothing."""
    if path.off is None:
        return [path]
    out = []
    for pts, w in path.deposited_runs():
        closed = len(pts) > 3 and bool(np.all(pts[-1] == pts[0]))
        if closed:
            pts, w = pts[:-1], w[:-1]
        if path.widths is None or np.ptp(w) == 0:   # a path of one width
            out.append(replace(path, points=np.ascontiguousarray(pts), closed=closed,
                               widths=None, width=float(w[0]), off=None))
            continue
        out.append(replace(path, points=np.ascontiguousarray(pts), closed=closed,
                           widths=np.ascontiguousarray(w), off=None,
                           width=mean_width(closed_polyline(pts, closed),
                                            closed_polyline(w, closed))))
    return out


def true_runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of True in a bool array as ``(first, end)`` index pairs (``end``
    exclusive), in order: a path's depositing or travel stretches by segment."""
    edge = np.diff(np.r_[0, np.asarray(mask, dtype=np.int8), 0])
    return list(zip(np.flatnonzero(edge == 1).tolist(), np.flatnonzero(edge == -1).tolist()))


def mean_width(poly: np.ndarray, w: np.ndarray, on: np.ndarray | None = None) -> float:
    """Length-weighted mean of widths ``w`` (per point, linear along each segment) over a
    polyline's segments, or those of them ``on`` (bool per segment), mm; with no length
    there, the plain mean of the widths at the points of those segments (0 with none)."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    on = np.ones(len(seg), dtype=bool) if on is None else np.asarray(on, dtype=bool)
    total = float(seg[on].sum())
    if total > 0:
        return float((seg[on] * 0.5 * (w[:-1] + w[1:])[on]).sum() / total)
    at = np.zeros(len(w), dtype=bool)
    at[:-1] |= on
    at[1:] |= on
    return float(w[at].mean()) if at.any() else (float(w[0]) if len(w) else 0.0)


def off_problem(path: Toolpath) -> str:
    """What is wrong with a path's ``off`` mask ('' when nothing: None, or (k,) booleans
    on a depositing path that leave some segment depositing)."""
    if path.off is None:
        return ""
    off = np.asarray(path.off)
    if off.shape != (len(path.points),) or off.dtype.kind != "b":
        return (f"off has shape {off.shape} and dtype {off.dtype}, expected "
                f"({len(path.points)},) bool: one per point")
    if not path.depositing:
        return f"off is given on a {path.role} path, which deposits nothing anyway"
    if not path.segment_on().any():
        return "off leaves no segment depositing: a travel move is a path of role 'travel'"
    return ""


def checked_widths(widths: "Sequence[np.ndarray]", counts: "Sequence[int]"
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Many paths' per-point widths checked at once, as :func:`widths_problem` checks one
    (a bunny layer has hundreds: one by one they cost the planning and the valves
    seconds): ``(ok (m,) bool`` - ``counts[i]`` finite numbers >= 0 -, ``the ok ones
    concatenated, float64 mm)``."""
    ws = [np.asarray(w) for w in widths]
    ok = np.array([w.shape == (int(n),) and w.dtype.kind in "fiu"
                   for w, n in zip(ws, counts)], dtype=bool)
    good = [w for w, k in zip(ws, ok) if k]
    if not good:
        return ok, np.zeros(0)
    W = np.concatenate(good).astype(np.float64, copy=False)
    fine = np.isfinite(W) & (W >= 0)
    if not fine.all():
        owner = np.repeat(np.arange(len(good)), [len(w) for w in good])
        clean = np.bincount(owner[~fine], minlength=len(good)) == 0
        ok[np.flatnonzero(ok)[~clean]] = False
        W = W[clean[owner]]
    return ok, W


def path_lengths(paths: "Sequence[Toolpath]") -> np.ndarray:
    """(P,) float64 mm: :attr:`Toolpath.length` of each path, in a few array operations
    over all their points (a layer has thousands of paths, the bunny 0.5 M; the sums agree
    with ``length`` to float rounding)."""
    if not paths:
        return np.zeros(0)
    polys = [p.polyline() for p in paths]
    counts = np.array([len(q) for q in polys], dtype=np.int64)
    return polyline_lengths(np.concatenate([np.asarray(q, dtype=np.float64) for q in polys]),
                            counts)


def polyline_lengths(pts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(P,) float64 mm: the length of each of P polylines concatenated in ``pts`` (N, 2),
    ``counts`` (P,) points each."""
    if len(pts) < 2:
        return np.zeros(len(counts))
    # column by column: np.linalg.norm's sum of squares, bit for bit, without its cost
    # (the bunny's 17 M points are summed as icefab paths gets them)
    x, y = pts[:, 0], pts[:, 1]
    dx, dy = x[1:] - x[:-1], y[1:] - y[:-1]
    step = np.sqrt(dx * dx + dy * dy)
    inside = np.ones(len(step), dtype=bool)
    ends = np.cumsum(counts)[:-1]
    # from one path to the next (empty paths before the first point or after the last
    # have no step there)
    inside[ends[(ends > 0) & (ends < len(pts))] - 1] = False
    owner = np.repeat(np.arange(len(counts)), counts)[1:]
    out = np.bincount(owner[inside], weights=step[inside], minlength=len(counts))
    return out.astype(np.float64, copy=False)   # bincount of nothing counts in integers


#: The name before 0.2 (it shadowed ``pathlib.Path`` in every module using both).
Path = Toolpath


#: Ossino's deposition states (Ossino 6): nothing flows, part (water) valve, scaffold valve.
OFF, ON1, ON2 = 0, 1, 2


def deposition_state(path: Toolpath) -> int:
    """Ossino's state of a path's deposition: ON1 (1, part), ON2 (2, scaffold), OFF (0)."""
    if not path.depositing:
        return OFF
    return ON1 if path.material == "part" else ON2


def point_states(path: Toolpath) -> np.ndarray:
    """(k,) int8: Ossino's state of every point of a path (Ossino 6), the state of the
    segment that leaves the point along the path: :func:`deposition_state` at every point
    of a depositing path but the last point of an open one (OFF: nothing follows on the
    path) and the points whose segment is ``off`` (a tour's travel); a closed path's last
    point leads back to its first (its closing edge deposits). Travel and measurement
    paths: OFF throughout."""
    out = np.full(len(path.points), deposition_state(path), dtype=np.int8)
    if path.off is not None and len(out):
        out[np.asarray(path.off, dtype=bool)] = OFF
    if len(out) and not path.closed:
        out[-1] = OFF
    return out


@dataclass(frozen=True, eq=False)
class LayerPaths:
    """The ordered paths of one layer, travel moves included, in deposition order."""

    index: int
    z: float
    paths: tuple[Toolpath, ...]
    #: (part, scaffold) area of the regions left uncovered by the deposition paths, mm^2.
    unfilled_mm2: tuple[float, float] = (0.0, 0.0)
    #: The layer's own thickness, mm (adaptive slicing); NaN: the job's layer thickness.
    thickness: float = float("nan")
    #: The layer's top surface, mm (the stack's ``Layer.top_z``); NaN: not known (a
    #: toolpath file written before it was stored; :meth:`LayerMotion.top` then derives it).
    top_z: float = float("nan")


@dataclass(frozen=True, eq=False)
class Toolpaths:
    """Ordered paths of every layer of a build."""

    layers: tuple[LayerPaths, ...]
    job: "Job"
    warnings: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.layers)

    def __iter__(self) -> Iterator[LayerPaths]:
        return iter(self.layers)


# --------------------------------------------------------------------------- motion


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A path followed in time, sampled at a constant time step.

    dt: time step, s (default 0.016); the speed lives in the point spacing.
    xy: (n, 2) float64, mm, sampled points in the robot base frame.
    joints: (n, j) float64, rad (or mm for prismatic axes), joint positions.
    speed: (n,) float64, mm/s, speed along the path at each sample.
    duration: s, ``(n - 1) * dt`` for a single piece.
    path: the Toolpath it follows (None for a plain point array).
    pieces: (p,) int64 sample index where each piece (PATHSPLIT sub-path, thesis 4.1.1)
        starts; the robot is at rest at every one of them and at the last sample. Empty
        means a single piece starting at sample 0.
    widths: None (the path's ``width`` all along) or (n,) float64 mm, the deposition width
        at every sample of a variable-width path (:attr:`Toolpath.widths` at the sample's
        place along the path).
    on_spans: None (the valve follows the path all along) or (m, 2) float64 s, from the
        trajectory's start: the spans over which a continuous tour's valve is on (its
        paths; between them it is off, over the travel), in order, each ``[start, end]``
        with ``0 <= start <= end <= duration``. The instants are where the samples pass
        the path's switch points (linear between samples, as the samples are followed), so
        the valve switches exactly there rather than at the nearest sample (issue 15: the
        ON1/ON2/OFF states stay exact). Trajectory files before version 6 have none.
    """

    dt: float
    xy: np.ndarray
    joints: np.ndarray
    speed: np.ndarray
    duration: float
    path: Toolpath | None = None
    pieces: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    widths: np.ndarray | None = None
    on_spans: np.ndarray | None = None

    @property
    def t(self) -> np.ndarray:
        """(n,) float64 sample times, s."""
        return np.arange(len(self.xy)) * self.dt


def _span_faults(spans: np.ndarray, owner: np.ndarray, durations: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per span of ``spans (S, 2)`` float64 s, each of trajectory ``owner (S,)``
    (ascending) lasting ``durations (T,)`` s: ``(out (S,) bool`` - not finite, or outside
    ``[0, duration]`` by more than a rounding -, ``disorder (S,) bool`` - its end before its
    start, or its start before the end of the span before it in its trajectory``)``."""
    dur = np.asarray(durations, dtype=np.float64)[owner]
    tol = 1e-9 * np.maximum(1.0, np.abs(dur))
    with np.errstate(invalid="ignore"):
        out = ~np.isfinite(spans).all(axis=1) | (spans[:, 0] < -tol) | (spans[:, 1] > dur + tol)
        disorder = spans[:, 1] < spans[:, 0]
        disorder[1:] |= (spans[1:, 0] < spans[:-1, 1]) & (owner[1:] == owner[:-1])
    return out, disorder


def spans_problem(spans: np.ndarray | None, duration: float) -> str:
    """What is wrong with a trajectory's ``on_spans`` ('' when nothing: None, or (m, 2)
    finite instants, s, in ``[0, duration]``, each span's end not before its start, and
    every span starting where the one before ended or later)."""
    if spans is None:
        return ""
    s = np.asarray(spans)
    if s.ndim != 2 or s.shape[1:] != (2,) or s.dtype.kind not in "fiu":
        return f"on_spans has shape {s.shape}, expected (m, 2) numbers: [start, end] in s"
    out, disorder = _span_faults(s.astype(np.float64), np.zeros(len(s), dtype=np.int64),
                                 np.array([duration], dtype=np.float64))
    if out.any():
        return f"on_spans must be finite instants within [0, {duration:.6g}] s"
    if disorder.any():
        return "on_spans must be in order: each span's end >= its start >= the end before"
    return ""


def spans_fine(owner: np.ndarray, spans: np.ndarray, durations: np.ndarray) -> np.ndarray:
    """(T,) bool: :func:`spans_problem` finds nothing in any trajectory's spans, for many
    at once (a bunny layer has dozens of tours, its file 50 000): ``spans (S, 2)`` float
    s, each of trajectory ``owner (S,)`` (ascending), ``durations (T,)`` s. Shapes are
    the caller's to check."""
    owner = np.asarray(owner, dtype=np.int64)
    out, disorder = _span_faults(np.asarray(spans, dtype=np.float64).reshape(-1, 2), owner,
                                 durations)
    fine = np.ones(len(durations), dtype=bool)
    fine[owner[out | disorder]] = False
    return fine


@dataclass(frozen=True, eq=False)
class LayerMotion:
    """The trajectories of one layer, in deposition order (travel moves included)."""

    index: int
    z: float
    trajectories: tuple[Trajectory, ...]
    #: The layer's own thickness, mm (adaptive slicing); NaN: the job's layer thickness.
    thickness: float = float("nan")
    #: The layer's top surface, mm (the stack's ``Layer.top_z``, carried by the toolpath and
    #: trajectory files); NaN: not known (files written before they stored it).
    top_z: float = float("nan")

    @property
    def durations(self) -> np.ndarray:
        """(t,) float64 s, per trajectory."""
        return np.array([t.duration for t in self.trajectories], dtype=np.float64)

    @property
    def duration(self) -> float:
        return float(self.durations.sum())

    @property
    def n_points(self) -> int:
        return int(sum(len(t.xy) for t in self.trajectories))

    def top(self, job) -> float:
        """The layer's nominal top, mm above the platform: where the valves' full layer
        thickness (``flow``'s dh) ends, the stack's ``top_z``.

        Without ``top_z`` (older files) it is derived from the cutting plane ``z``,
        ``slicing.cut_fraction`` of the thickness above the bottom: exact but for a top
        layer the part does not fill (its plane is cut inside the part's share,
        :func:`icefab.slicing.layer_planes`), which it puts too low by ``cut_fraction``
        times the unfilled height."""
        if math.isfinite(self.top_z):
            return float(self.top_z)
        t = self.thickness if math.isfinite(self.thickness) else job.slicing.layer_thickness_mm
        return float(self.z + (1.0 - job.slicing.cut_fraction) * t)


@dataclass(frozen=True, eq=False)
class BuildMotion:
    """Trajectories of every layer of a build."""

    layers: tuple[LayerMotion, ...]
    job: "Job"
    robot: str = "scara"
    joint_names: tuple[str, ...] = ()

    @property
    def layer_durations(self) -> np.ndarray:
        """(L,) float64 s."""
        return np.array([lm.duration for lm in self.layers], dtype=np.float64)

    @property
    def duration(self) -> float:
        """Whole-build motion time, s."""
        return float(self.layer_durations.sum())

    @property
    def n_points(self) -> int:
        return int(sum(lm.n_points for lm in self.layers))

    def __len__(self) -> int:
        return len(self.layers)



# --------------------------------------------------------------------------- valves


@dataclass(frozen=True, eq=False)
class ValveProgram:
    """Pulse instants for one valve along one trajectory piece (thesis Ch. 6, 2.3.1).

    ticks: (p,) uint16, pulse instants in ticks of ``tick_s`` from the piece start.
    tick_s: tick length, s (0.002 on the Cobra 600 microcontroller).
    duration: s, length of the trajectory piece the pulses belong to.
    pieces: further pieces when the program was split (131.071 s / 16384 pulses at a 2 ms
        tick: :func:`icefab.flow.piece_max_s`).
    widths_us: (p,) uint16 pulse widths in microseconds (PWM mode; None in FM mode, where
        every pulse has the valve's fixed pulse width).
    warnings: valve limits reached while planning (clamped flow, too few drops per mm),
        each naming the setting; kept on the first piece.
    commanded_mm3, laid_mm3: the volume the path's flow commands where its valve is on and
        the volume its pulses lay, mm^3, over all pieces (kept on the first piece; NaN when
        unknown, e.g. a program read from a file): they differ by the valve's limits and
        by the rounding to whole pulses (a short FM path may get none, eq. 6.6).
    """

    ticks: np.ndarray
    tick_s: float = 0.002
    duration: float = 0.0
    pieces: tuple["ValveProgram", ...] = ()
    widths_us: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    commanded_mm3: float = float("nan")
    laid_mm3: float = float("nan")


# --------------------------------------------------------------------------- surfaces


@dataclass(frozen=True, eq=False)
class HeightMap:
    """A surface on a regular grid.

    origin: (2,) float64, mm, x and y of grid node (0, 0).
    spacing: grid pitch, mm.
    z: (ny, nx) float64, mm; NaN outside the footprint. Row i is y = origin[1] + i*spacing.
    """

    origin: np.ndarray
    spacing: float
    z: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.z.shape  # type: ignore[return-value]

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(nx,), (ny,) float64 node coordinates, mm."""
        ny, nx = self.z.shape
        return (
            self.origin[0] + self.spacing * np.arange(nx),
            self.origin[1] + self.spacing * np.arange(ny),
        )


def layer_runs(layers: Sequence[int]) -> str:
    """Every layer of a sorted list, consecutive ones as runs: "0-9, 12, 14-20" (a warning
    that listed ten and "..." left the rest out of the warnings file, which holds every
    warning)."""
    out: list[str] = []
    i = 0
    ks = [int(k) for k in layers]
    while i < len(ks):
        j = i
        while j + 1 < len(ks) and ks[j + 1] == ks[j] + 1:
            j += 1
        out.append(str(ks[i]) if j == i else f"{ks[i]}-{ks[j]}")
        i = j + 1
    return ", ".join(out)


def area_text(mm2: float) -> str:
    """An area in mm^2 to three significant digits without an exponent ("0.244", "12.5",
    "1234"): the paths summary printed ".0f", so 0.244 mm^2 read "0" beside the warning's
    0.244, and the warning's ".3g" read "1.02e+03" (reviews'); exactly 0 stays "0"."""
    a = float(mm2)
    if a == 0.0 or not math.isfinite(a):
        return f"{a:g}"
    return f"{a:.{max(0, 2 - math.floor(math.log10(abs(a))))}f}"
