"""Mesh import, diagnostics and part set-up (thesis 3.1, Table 3-1).

This is the only module of icefab that parses mesh files. Everything returns an indexed
:class:`~icefab.types.Mesh` (``vertices (n, 3) float64 mm``, ``faces (m, 3) int64``).

Formats (detected by content; the file extension is only a hint):

* binary STL — one ``np.frombuffer`` with a structured dtype (thesis 3.1.1: "one FREAD
  statement"). A binary STL whose 80-byte header begins with ``solid`` is recognised by its
  size (``84 + 50 n`` bytes) or, when the size does not fit, by non-text bytes after the
  header.
* ASCII STL — one compiled pass (numba) over the bytes checks the grammar (errors give
  the line) and converts the coordinates (an exact fast path; ``strtod`` via
  ``np.fromstring`` in one call for the long mantissas it leaves), no per-line Python.
* PLY, binary (little/big endian) and ASCII — every element is read with one structured
  dtype; extra properties are skipped; faces with any list count type; polygons are
  fan-triangulated; a ``tristrips`` element (``-1`` restarts) is decoded vectorised.
* OBJ — ``v`` and ``f`` lines (``f 1/2/3 4//5 -1``), negative indices, polygons
  fan-triangulated, scanned in one compiled pass like ASCII STL; other lines ignored.

Welding: STL stores every facet corner separately; corners are merged into shared
vertices. Exact welding (default) merges corners whose coordinates are bit-identical
(``-0.0 == 0.0``), with a hash table compiled by numba. The thesis' *inexact* option
(paper Table 1) merges vertices closer than ``tolerance`` (mm): after the exact weld, all
vertex pairs within the tolerance are found with a k-d tree (scipy ``cKDTree``) and merged
transitively (connected components), so a chain of close vertices collapses to one vertex
even if its ends are farther apart than the tolerance; the merged vertex takes the
position of the lowest-indexed member.

Clean-up after welding (each reported as a warning with its count): faces with a repeated
vertex index (degenerate) are removed; faces with the same three vertices as an earlier
face (duplicates, in either orientation) are removed (searched for only when a
non-manifold or misoriented edge shows one may exist); vertices no face uses are dropped;
a closed mesh with negative signed volume (inside out) has all faces flipped. Open and
non-manifold edges are reported with their count and the location of one of them, never
"repaired" here (the slicer closes gaps per layer and reports them). Faces with distinct
but collinear corners (zero area) are counted, not removed: removing them would open the
surface.

Errors (:class:`~icefab.errors.MeshError`, the message names the file): missing or empty
file, unknown format, truncated binary STL or PLY, NaN/Inf coordinates, text that cannot
be read (with its line number), face index out of range, nothing but degenerate faces.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np
from numba import njit

from icefab.atomic import write_atomic
from icefab.errors import MeshError
from icefab.types import Mesh

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job, PartSetup

log = logging.getLogger(__name__)

__all__ = ["MeshReport", "load_mesh", "read_mesh", "load_meshes", "check_mesh",
           "weld_vertices", "clean_mesh", "transform", "prepare_parts",
           "part_fraction_range", "merge_meshes", "mesh_volume", "write_stl",
           "rotation_matrix"]

# --------------------------------------------------------------------------- hashing


@njit(cache=True)
def _hash3(a, b, c):  # pragma: no cover
    h = ((np.uint64(a) * np.uint64(0x9E3779B97F4A7C15))
         ^ (np.uint64(b) * np.uint64(0xC2B2AE3D27D4EB4F))
         ^ (np.uint64(c) * np.uint64(0x165667B19E3779F9)))
    return h ^ (h >> np.uint64(32))


@njit(cache=True)
def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Exact unique rows of an (n, 3) unsigned-int array (open-addressing hash table).

    Returns ``first`` (u,) int64, the index of the first occurrence of every distinct row
    in order of appearance, and ``inverse`` (n,) int64 with ``rows[first][inverse] == rows``.
    Keys are stored in the table itself (one memory access per probe); the table starts
    at n/2 slots (STL corners repeat ~6 times) and doubles when half full. Expected O(n).
    """
    n = rows.shape[0]
    cap = 1024
    while cap < n // 2:
        cap *= 2
    keys = np.empty((cap, 3), rows.dtype)
    ids = np.full(cap, -1, np.int32)
    first = np.empty(n, np.int64)
    inverse = np.empty(n, np.int64)
    nu = 0
    for i in range(n):
        a = rows[i, 0]
        b = rows[i, 1]
        c = rows[i, 2]
        mask = np.uint64(cap - 1)
        s = _hash3(a, b, c) & mask
        while True:
            slot = ids[s]
            if slot < 0:
                ids[s] = nu
                keys[s, 0] = a
                keys[s, 1] = b
                keys[s, 2] = c
                first[nu] = i
                inverse[i] = nu
                nu += 1
                break
            if keys[s, 0] == a and keys[s, 1] == b and keys[s, 2] == c:
                inverse[i] = slot
                break
            s = (s + np.uint64(1)) & mask
        if 2 * nu > cap:  # grow and re-insert every distinct row
            cap *= 2
            keys = np.empty((cap, 3), rows.dtype)
            ids = np.full(cap, -1, np.int32)
            mask = np.uint64(cap - 1)
            for u in range(nu):
                j = first[u]
                s = _hash3(rows[j, 0], rows[j, 1], rows[j, 2]) & mask
                while ids[s] >= 0:
                    s = (s + np.uint64(1)) & mask
                ids[s] = u
                keys[s, 0] = rows[j, 0]
                keys[s, 1] = rows[j, 1]
                keys[s, 2] = rows[j, 2]
    return first[:nu].copy(), inverse


@njit(cache=True)
def edge_buckets(faces: np.ndarray, nv: int):  # pragma: no cover
    """Half-edges of a triangle mesh bucketed by their lower vertex: a counting sort, O(m).

    Local edge k of facet f joins its corners k and (k + 1) % 3 and has the id 3 f + k.
    Returns (start, half, upper): the half-edges of lower vertex v are
    ``half[start[v]:start[v + 1]]`` (in facet order), ``upper`` their other vertex. The
    buckets are as small as the vertex valence, so matching inside them is cheap; mesh
    diagnostics and the slicer's facet adjacency both start here.
    """
    m = faces.shape[0]
    start = np.zeros(nv + 1, np.int64)
    for f in range(m):
        for k in range(3):
            start[min(faces[f, k], faces[f, (k + 1) % 3]) + 1] += 1
    for i in range(nv):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    half = np.empty(3 * m, np.int64)
    upper = np.empty(3 * m, np.int64)
    for f in range(m):
        for k in range(3):
            a = faces[f, k]
            b = faces[f, (k + 1) % 3]
            lo = min(a, b)
            pos = fill[lo]
            half[pos] = 3 * f + k
            upper[pos] = max(a, b)
            fill[lo] += 1
    return start, half, upper


@njit(cache=True)
def _edge_topology(faces: np.ndarray, nv: int):  # pragma: no cover
    """(open, non-manifold, misoriented) undirected edge counts, O(m) with vertex buckets,
    and the two vertices of one open and one non-manifold edge (-1 when there is none).

    Each bucket of :func:`edge_buckets` is sorted by the upper vertex and runs of equal
    edges are counted: 1 use = open edge, > 2 = non-manifold, 2 uses in the same
    direction = misoriented.
    """
    start, half, hi = edge_buckets(faces, nv)
    dr = np.empty(half.size, np.int8)
    for pos in range(half.size):
        f = half[pos] // 3
        k = half[pos] % 3
        dr[pos] = 1 if faces[f, k] < faces[f, (k + 1) % 3] else -1
    n_open = 0
    n_nonman = 0
    n_misor = 0
    ex_open = np.full(2, -1, np.int64)
    ex_nonman = np.full(2, -1, np.int64)
    for v in range(nv):
        s = start[v]
        e = start[v + 1]
        for i in range(s + 1, e):  # insertion sort of the bucket by upper vertex
            x = hi[i]
            d = dr[i]
            j = i - 1
            while j >= s and hi[j] > x:
                hi[j + 1] = hi[j]
                dr[j + 1] = dr[j]
                j -= 1
            hi[j + 1] = x
            dr[j + 1] = d
        i = s
        while i < e:
            j = i
            dsum = 0
            while j < e and hi[j] == hi[i]:
                dsum += dr[j]
                j += 1
            c = j - i
            if c == 1:
                if n_open == 0:
                    ex_open[0], ex_open[1] = v, hi[i]
                n_open += 1
            elif c > 2:
                if n_nonman == 0:
                    ex_nonman[0], ex_nonman[1] = v, hi[i]
                n_nonman += 1
            elif dsum != 0:
                n_misor += 1
            i = j
    return n_open, n_nonman, n_misor, ex_open, ex_nonman


@njit(cache=True)
def _duplicate_faces(faces: np.ndarray, nv: int) -> np.ndarray:  # pragma: no cover
    """(m,) bool: the face has the same vertex set as an earlier face (O(m), buckets)."""
    m = faces.shape[0]
    srt = np.empty((m, 3), np.int64)
    start = np.zeros(nv + 1, np.int64)
    for f in range(m):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        if a > b:
            a, b = b, a
        if b > c:
            b, c = c, b
        if a > b:
            a, b = b, a
        srt[f, 0], srt[f, 1], srt[f, 2] = a, b, c
        start[a + 1] += 1
    for i in range(nv):
        start[i + 1] += start[i]
    fill = start[:-1].copy()
    order = np.empty(m, np.int64)
    for f in range(m):
        a = srt[f, 0]
        order[fill[a]] = f
        fill[a] += 1
    dup = np.zeros(m, np.bool_)
    for v in range(nv):
        for i in range(start[v] + 1, start[v + 1]):
            fi = order[i]
            for j in range(start[v], i):
                fj = order[j]
                if srt[fj, 1] == srt[fi, 1] and srt[fj, 2] == srt[fi, 2] and not dup[fj]:
                    dup[fi] = True
                    break
    return dup


@njit(cache=True)
def _face_measures(vertices: np.ndarray, faces: np.ndarray,
                   eps2: float) -> tuple[int, float]:  # pragma: no cover
    """(zero-area face count, signed volume mm^3) in one pass over the faces.

    The volume is taken about the bounding-box centre (divergence theorem):
    V = sum(a . ((b - a) x (c - a))) / 6.
    """
    m = faces.shape[0]
    cx = 0.0
    cy = 0.0
    cz = 0.0
    if vertices.shape[0] > 0:
        mn = vertices[0].copy()
        mx = vertices[0].copy()
        for i in range(vertices.shape[0]):
            for k in range(3):
                mn[k] = min(mn[k], vertices[i, k])
                mx[k] = max(mx[k], vertices[i, k])
        cx, cy, cz = 0.5 * (mn[0] + mx[0]), 0.5 * (mn[1] + mx[1]), 0.5 * (mn[2] + mx[2])
    n_zero = 0
    vol = 0.0
    for f in range(m):
        a = faces[f, 0]
        b = faces[f, 1]
        c = faces[f, 2]
        ax, ay, az = vertices[a, 0] - cx, vertices[a, 1] - cy, vertices[a, 2] - cz
        ux, uy, uz = vertices[b, 0] - cx - ax, vertices[b, 1] - cy - ay, vertices[b, 2] - cz - az
        wx, wy, wz = vertices[c, 0] - cx - ax, vertices[c, 1] - cy - ay, vertices[c, 2] - cz - az
        nx = uy * wz - uz * wy
        ny = uz * wx - ux * wz
        nz = ux * wy - uy * wx
        if nx * nx + ny * ny + nz * nz <= eps2:
            n_zero += 1
        vol += ax * nx + ay * ny + az * nz
    return n_zero, vol / 6.0


def _float_bits(points: np.ndarray) -> np.ndarray:
    """(n, 3) unsigned-int view of the bit patterns of float32/float64 points (-0.0 -> 0.0)."""
    p = np.ascontiguousarray(points)
    p = p + p.dtype.type(0.0)  # turns -0.0 into +0.0 so they weld
    return p.view(np.uint32 if p.dtype == np.float32 else np.uint64)


def weld_vertices(points: np.ndarray, *, inexact: bool = False,
                  tolerance: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Merge equal (or, with ``inexact``, close) points into shared vertices.

    points: (n, 3) float32/float64, mm (finite).
    Returns ``vertices`` (u, 3) float64 mm and ``index`` (n,) int64 with
    ``vertices[index] ~= points``. Exact: bit-identical coordinates (``-0.0 == 0.0``).
    Inexact: vertices within ``tolerance`` mm merged transitively (see module docstring).
    """
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    first, index = _unique_rows(_float_bits(points))
    vertices = np.asarray(points[first], dtype=np.float64)
    if inexact and len(vertices) > 1:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        pairs = cKDTree(vertices).query_pairs(float(tolerance), output_type="ndarray")
        if len(pairs):
            nv = len(vertices)
            graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])),
                               shape=(nv, nv))
            _, labels = connected_components(graph, directed=False)
            # renumber components in order of their lowest vertex index
            uniq, rep = np.unique(labels, return_index=True)
            order = np.argsort(rep, kind="stable")
            relabel = np.empty(len(uniq), np.int64)
            relabel[order] = np.arange(len(uniq))
            labels = relabel[labels]
            vertices = vertices[np.sort(rep)]
            index = labels[index]
    return vertices, index


# --------------------------------------------------------------------------- report


@dataclass(frozen=True)
class MeshReport:
    """Diagnostics of a mesh (counts; see :func:`check_mesh`).

    open_edges: edges used by exactly one face (holes in the surface).
    non_manifold_edges: edges used by more than two faces.
    misoriented_edges: edges shared by two faces that traverse them in the same direction
        (inconsistent face orientation).
    degenerate_faces: faces with a repeated vertex index.
    zero_area_faces: faces with three distinct vertices but (numerically) zero area.
    duplicate_faces: faces with the same three vertices as an earlier face.
    nonfinite_vertices: vertices with a NaN or infinite coordinate.
    volume: signed enclosed volume, mm^3 (meaningful for closed meshes).
    inverted: closed mesh with negative volume (faces point inwards).
    removed_degenerate, removed_duplicate, merged_vertices, flipped: what loading fixed.
    open_edge_at, non_manifold_edge_at: midpoint (mm) of one such edge, to find it.
    """

    name: str
    n_vertices: int
    n_faces: int
    open_edges: int
    non_manifold_edges: int
    misoriented_edges: int
    degenerate_faces: int
    zero_area_faces: int
    duplicate_faces: int
    nonfinite_vertices: int
    volume: float
    inverted: bool
    removed_degenerate: int = 0
    removed_duplicate: int = 0
    merged_vertices: int = 0
    flipped: bool = False
    open_edge_at: tuple[float, float, float] | None = None
    non_manifold_edge_at: tuple[float, float, float] | None = None

    @property
    def closed(self) -> bool:
        """No open and no non-manifold edges."""
        return self.open_edges == 0 and self.non_manifold_edges == 0 and self.n_faces > 0

    @property
    def watertight(self) -> bool:
        """Closed, consistently oriented, without degenerate faces."""
        return (self.closed and self.misoriented_edges == 0 and self.degenerate_faces == 0
                and self.nonfinite_vertices == 0)

    def warnings(self) -> list[str]:
        """Human-readable findings, each with its count and the mesh name."""
        w: list[str] = []
        n = self.name or "mesh"
        if self.removed_degenerate:
            w.append(f"{n}: removed {self.removed_degenerate} degenerate faces "
                     "(repeated vertex)")
        if self.removed_duplicate:
            w.append(f"{n}: removed {self.removed_duplicate} duplicate faces")
        if self.flipped:
            w.append(f"{n}: the closed mesh was inside out (volume < 0); all faces flipped")
        if self.nonfinite_vertices:
            w.append(f"{n}: {self.nonfinite_vertices} vertices with NaN/Inf coordinates")
        if self.degenerate_faces:
            w.append(f"{n}: {self.degenerate_faces} degenerate faces (repeated vertex)")
        if self.duplicate_faces:
            w.append(f"{n}: {self.duplicate_faces} duplicate faces")
        if self.zero_area_faces:
            w.append(f"{n}: {self.zero_area_faces} zero-area faces")
        if self.open_edges:
            w.append(f"{n}: {self.open_edges} open edges (the surface has holes)"
                     + _at(self.open_edge_at))
        if self.non_manifold_edges:
            w.append(f"{n}: {self.non_manifold_edges} non-manifold edges (shared by more "
                     "than two faces)" + _at(self.non_manifold_edge_at))
        if self.misoriented_edges:
            w.append(f"{n}: {self.misoriented_edges} edges between faces of inconsistent "
                     "orientation")
        if self.inverted and not self.flipped:
            w.append(f"{n}: inverted orientation (negative volume {self.volume:.6g} mm^3)")
        return w


def _at(point: tuple[float, float, float] | None) -> str:
    if point is None:
        return ""
    return ", e.g. at ({:.4g}, {:.4g}, {:.4g}) mm".format(*point)


def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (mm^3) enclosed by the faces (divergence theorem); > 0 when outward."""
    if len(faces) == 0:
        return 0.0
    # shift to the centroid of the bounding box for accuracy
    c = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    v = vertices - c
    a, b, d = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, d)) / 6.0)


def _edge_stats(faces: np.ndarray, n_vertices: int) -> tuple[int, int, int, np.ndarray,
                                                             np.ndarray]:
    """(open, non-manifold, misoriented) undirected edge counts of non-degenerate faces,
    and the vertex pair of one open and one non-manifold edge ((-1, -1) when none)."""
    if len(faces) == 0:
        none = np.full(2, -1, np.int64)
        return 0, 0, 0, none, none
    o, n, m, ex_o, ex_n = _edge_topology(faces, int(n_vertices))
    return int(o), int(n), int(m), ex_o, ex_n


def _degenerate_mask(faces: np.ndarray) -> np.ndarray:
    return ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
            | (faces[:, 0] == faces[:, 2]))


def _duplicate_mask(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(m,) bool: face has the same vertex set as an earlier face (either orientation)."""
    if len(faces) == 0:
        return np.zeros(0, bool)
    return _duplicate_faces(faces, int(n_vertices))


def check_mesh(mesh: Mesh) -> MeshReport:
    """Diagnose a mesh: edge topology, degenerate/duplicate faces, orientation.

    Compiled O(m) passes: edges are bucketed by their lower vertex and counted, duplicate
    faces found the same way; volume and zero-area faces in one pass over the faces.
    """
    return _diagnose(mesh, known_clean=False)


def _diagnose(mesh: Mesh, known_clean: bool,
              edges: tuple | None = None) -> MeshReport:
    """check_mesh; ``known_clean`` skips the degenerate/duplicate search (just removed),
    ``edges`` are the (open, non-manifold, misoriented) counts when already known."""
    v, f = mesh.vertices, np.ascontiguousarray(mesh.faces, dtype=np.int64)
    if f.ndim != 2 or (len(f) and f.shape[1] != 3) or (v.ndim != 2 or v.shape[1] != 3):
        raise MeshError(f"{mesh.name or 'mesh'}: expected vertices (n, 3) and faces (m, 3), "
                        f"got {v.shape} and {f.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise MeshError(f"{mesh.name or 'mesh'}: face index out of range [0, {len(v)})")
    v = np.ascontiguousarray(v, dtype=np.float64)
    nonfinite = 0 if np.isfinite(v).all() else int(np.count_nonzero(
        ~np.isfinite(v).all(axis=1)))
    if known_clean:
        good, degen, dup = f, np.zeros(0, bool), np.zeros(0, bool)
    else:
        degen = _degenerate_mask(f)
        good = f[~degen] if degen.any() else f
        dup = _duplicate_mask(good, len(v))
    open_, nonman, misor, ex_open, ex_nonman = (edges if edges is not None
                                                else _edge_stats(good, len(v)))
    if nonfinite == 0 and len(good):
        scale = float(np.abs(v).max()) or 1.0
        zero_area, volume = _face_measures(v, good, (1e-12 * scale) ** 2)
        zero_area, volume = int(zero_area), float(volume)
    else:
        zero_area, volume = 0, float("nan")
    closed = open_ == 0 and nonman == 0 and len(good) > 0
    return MeshReport(name=mesh.name, n_vertices=int(len(v)), n_faces=int(len(f)),
                      open_edges=open_, non_manifold_edges=nonman, misoriented_edges=misor,
                      degenerate_faces=int(degen.sum()), zero_area_faces=zero_area,
                      duplicate_faces=int(dup.sum()), nonfinite_vertices=nonfinite,
                      volume=volume, inverted=bool(closed and misor == 0 and volume < 0),
                      open_edge_at=_midpoint(v, ex_open),
                      non_manifold_edge_at=_midpoint(v, ex_nonman))


def _midpoint(v: np.ndarray, edge: np.ndarray) -> tuple[float, float, float] | None:
    if edge[0] < 0:
        return None
    return tuple(float(x) for x in 0.5 * (v[edge[0]] + v[edge[1]]))  # type: ignore


def clean_mesh(mesh: Mesh) -> tuple[Mesh, MeshReport]:
    """Remove degenerate and duplicate faces, flip an inside-out closed mesh.

    Returns the cleaned mesh and the report of the cleaned mesh with the ``removed_*`` and
    ``flipped`` fields telling what was changed.
    """
    f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    nv = len(mesh.vertices)
    degen = _degenerate_mask(f)
    if degen.any():
        f = f[~degen]
    edges = _edge_stats(f, nv)
    n_dup = 0
    # A duplicate face always leaves a non-manifold or misoriented edge (except a lone
    # two-sided pair, which encloses nothing), so clean meshes skip the search.
    if edges[1] or edges[2]:
        dup = _duplicate_mask(f, nv)
        n_dup = int(dup.sum())
        if n_dup:
            f = f[~dup]
            edges = _edge_stats(f, nv)
    vertices = mesh.vertices
    if len(f):
        used = np.zeros(len(vertices), bool)
        used[f] = True
        if not used.all():  # drop vertices no face refers to (renumbered, order kept)
            remap = np.cumsum(used) - 1
            f = remap[f]
            vertices = vertices[used]
            ex_open, ex_nonman = (np.where(e >= 0, remap[np.maximum(e, 0)], -1)
                                  for e in edges[3:])
            edges = (*edges[:3], ex_open, ex_nonman)
    cleaned = dataclasses.replace(mesh, vertices=vertices, faces=f)
    report = _diagnose(cleaned, known_clean=True, edges=edges)
    flipped = False
    if report.inverted:
        cleaned = dataclasses.replace(cleaned, faces=np.ascontiguousarray(f[:, ::-1]))
        report = dataclasses.replace(report, volume=-report.volume, inverted=False)
        flipped = True
    report = dataclasses.replace(report, removed_degenerate=int(degen.sum()),
                                 removed_duplicate=n_dup, flipped=flipped)
    return cleaned, report


# --------------------------------------------------------------------------- reading


_STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)),
                       ("attr", "<u2")])
_TEXT_BYTES = np.zeros(256, bool)
_TEXT_BYTES[[9, 10, 11, 12, 13]] = True
_TEXT_BYTES[32:256] = True  # bytes >= 128: UTF-8 in names and comments


def _is_text(data: bytes | memoryview) -> bool:
    """True when no byte is a control character other than whitespace."""
    return bool(_TEXT_BYTES[np.frombuffer(data, np.uint8)].all())


def _sniff(data: bytes, path: FsPath) -> str:
    """The format of ``data``: 'stl', 'stl-ascii', 'ply' or 'obj' (content first)."""
    ext = path.suffix.lower()
    head = data[:5].lower()
    if data[:3] == b"ply" and data[3:4] in (b"\n", b"\r", b" "):
        return "ply"
    if len(data) >= 84:
        n = int.from_bytes(data[80:84], "little") or (len(data) - 84) // 50
        if 84 + 50 * n == len(data) and n > 0:
            # a valid binary STL size; an ASCII STL exactly matching by chance would
            # need its header bytes to encode its own length and is not text after byte 84
            if not (data[:256].lstrip()[:5].lower() == b"solid" and _is_text(data[84:4180])):
                return "stl"
    if data[:256].lstrip()[:5].lower() == b"solid":
        if _is_text(data[:4096]):
            return "stl-ascii"
        return "stl"  # a binary STL with a "solid" header (size checked by the reader)
    if _is_text(data[:4096]) and re.search(rb"(?m)^[ \t]*(v|f|vn|vt|o|g|mtllib|usemtl)[ \t]",
                                           data[:65536]):
        return "obj"
    if ext == ".stl" and len(data) >= 84:
        return "stl"
    if ext == ".obj" and _is_text(data[:4096]):
        return "obj"
    if head == b"ply":
        return "ply"
    raise MeshError(f"{path}: unknown mesh format (not binary/ASCII STL, PLY or OBJ by its "
                    f"content; extension {ext or 'none'!r})")


def _read_stl_binary(data: bytes, path: FsPath) -> np.ndarray:
    """Corner coordinates (3 n, 3) float32 of a binary STL, one vectorised read."""
    if len(data) < 84:
        raise MeshError(f"{path}: binary STL shorter than its 84-byte header "
                        f"({len(data)} bytes)")
    n = int.from_bytes(data[80:84], "little")
    if n == 0 and len(data) > 84 and (len(data) - 84) % 50 == 0:
        # some streaming exporters never fill in the count: the size tells it
        n = (len(data) - 84) // 50
        log.warning("%s: binary STL header declares 0 facets; the file size gives %d, "
                    "read those", path, n)
    need = 84 + 50 * n
    if need > len(data):
        raise MeshError(f"{path}: truncated binary STL: the header declares {n} facets "
                        f"({need} bytes) but the file has {len(data)} bytes")
    if need < len(data):
        log.warning("%s: %d bytes after the %d facets declared in the binary STL header "
                    "were ignored", path, len(data) - need, n)
    if n == 0:
        raise MeshError(f"{path}: binary STL with 0 facets")
    rec = np.frombuffer(data, dtype=_STL_DTYPE, count=n, offset=84)
    return np.ascontiguousarray(rec["corners"]).reshape(-1, 3)


def _check_finite(points: np.ndarray, path: FsPath, corners: bool = False) -> None:
    """MeshError naming the first non-finite vertex; ``corners``: the points are the
    facet corners of an STL (3 per facet), so name the facet (0-based) instead."""
    if np.isfinite(points).all():
        return
    bad = ~np.isfinite(points).all(axis=1)
    k = int(np.flatnonzero(bad)[0])
    first = f"facet {k // 3}, corner {k % 3 + 1}" if corners else f"vertex {k}"
    raise MeshError(f"{path}: {int(bad.sum())} vertices with NaN/Inf coordinates "
                    f"(first: {first} = {points[k].tolist()}); expected finite numbers")


def read_mesh(path: str | os.PathLike[str], *, inexact: bool = False,
              tolerance: float = 1e-4) -> tuple[Mesh, MeshReport]:
    """Load a mesh file and return it with its diagnostics.

    Same as :func:`load_mesh`, and also returns the :class:`MeshReport` of the cleaned
    mesh: what was fixed (``removed_degenerate``, ``removed_duplicate``, ``flipped``,
    ``merged_vertices``) and what remains (open / non-manifold / misoriented edges,
    zero-area faces, volume). Every finding is also logged as a warning.
    """
    p = FsPath(path)
    if tolerance <= 0 or not math.isfinite(tolerance):
        raise MeshError(f"{p}: weld tolerance {tolerance!r} must be a positive number (mm)")
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise MeshError(f"{p}: mesh file not found") from None
    except IsADirectoryError:
        raise MeshError(f"{p}: is a directory, expected a mesh file") from None
    except OSError as exc:
        raise MeshError(f"{p}: cannot read mesh file ({exc.strerror or exc})") from None
    if not data[:4096].strip() and not data.strip():
        raise MeshError(f"{p}: empty file, expected a mesh (STL, PLY or OBJ)")
    if data[:3] == b"\xef\xbb\xbf" and _is_text(data[3:4099]):
        data = data[3:]  # UTF-8 byte order mark of a text file
    fmt = _sniff(data, p)
    try:
        if fmt == "stl":
            corners = _read_stl_binary(data, p)
            _check_finite(corners, p, corners=True)
            vertices, index = weld_vertices(corners, inexact=inexact, tolerance=tolerance)
            faces = index.reshape(-1, 3)
            n_in = len(corners)
        elif fmt == "stl-ascii":
            corners = _read_stl_ascii(data, p)
            _check_finite(corners, p)
            vertices, index = weld_vertices(corners, inexact=inexact, tolerance=tolerance)
            faces = index.reshape(-1, 3)
            n_in = len(corners)
        else:
            reader = _read_ply if fmt == "ply" else _read_obj
            raw_v, faces = reader(data, p)
            _check_finite(raw_v, p)
            if len(faces) and (faces.min() < 0 or faces.max() >= len(raw_v)):
                bad = int(np.flatnonzero((faces < 0).any(axis=1)
                                         | (faces >= len(raw_v)).any(axis=1))[0])
                raise MeshError(f"{p}: face {bad} has vertex index "
                                f"{faces[bad].tolist()} out of range: the file has "
                                f"{len(raw_v)} vertices")
            vertices, index = weld_vertices(raw_v, inexact=inexact, tolerance=tolerance)
            faces = index[faces] if len(faces) else faces.reshape(0, 3)
            n_in = len(raw_v)
    except (ValueError, IndexError, OverflowError, TypeError) as exc:
        if isinstance(exc, MeshError):
            raise
        raise MeshError(f"{p}: malformed {fmt.upper()} data ({exc})") from None
    if len(faces) == 0:
        raise MeshError(f"{p}: the mesh has no faces")
    mesh = Mesh(vertices, np.ascontiguousarray(faces, dtype=np.int64), p.name)
    mesh, report = clean_mesh(mesh)
    report = dataclasses.replace(report, merged_vertices=int(n_in - len(vertices)))
    if len(mesh.faces) == 0:
        raise MeshError(f"{p}: every face is degenerate; nothing left to slice")
    found = tuple(report.warnings())
    for w in found:
        log.warning("%s", w)
    return dataclasses.replace(mesh, warnings=found), report


def load_mesh(path: str | os.PathLike[str], *, inexact: bool = False,
              tolerance: float = 1e-4) -> Mesh:
    """Load an STL (binary/ASCII), PLY (binary/ASCII, faces or tristrips) or OBJ file.

    path: the mesh file; its format is detected by content.
    inexact: weld vertices within ``tolerance`` mm instead of exactly (thesis option).
    Returns an indexed, cleaned :class:`Mesh` (vertices float64 mm, faces int64).
    Raises :class:`MeshError` naming the file for missing, empty, truncated or malformed
    files, NaN/Inf coordinates and out-of-range face indices. Fixable defects are fixed
    and logged as warnings with counts (see :func:`read_mesh` for the report).
    """
    return read_mesh(path, inexact=inexact, tolerance=tolerance)[0]


# --------------------------------------------------------------------------- text scanning
#
# ASCII formats are scanned in one compiled pass over the bytes (numba): the pass checks
# the grammar (with line numbers for errors), copies the coordinate tokens into one
# compact buffer and parses integer indices itself; the coordinates are then converted
# in one call (``np.fromstring``, C ``strtod``, correctly rounded).

_WS = np.zeros(256, np.bool_)
_WS[[9, 10, 11, 12, 13, 32]] = True
_KW_SOLID = np.frombuffer(b"solid", np.uint8)
_KW_ENDSOLID = np.frombuffer(b"endsolid", np.uint8)
_KW_FACET = np.frombuffer(b"facet", np.uint8)
_KW_NORMAL = np.frombuffer(b"normal", np.uint8)
_KW_OUTER = np.frombuffer(b"outer", np.uint8)
_KW_LOOP = np.frombuffer(b"loop", np.uint8)
_KW_VERTEX = np.frombuffer(b"vertex", np.uint8)
_KW_ENDLOOP = np.frombuffer(b"endloop", np.uint8)
_KW_ENDFACET = np.frombuffer(b"endfacet", np.uint8)

# error codes of the scanners
_E_TOKEN, _E_NUMBER, _E_VCOUNT, _E_EOF, _E_INDEX, _E_FEW = 1, 2, 3, 4, 5, 6


@njit(cache=True)
def _is_ws(c):  # pragma: no cover
    return c == 32 or (9 <= c <= 13)


@njit(cache=True)
def _tok_eq(b, s, e, kw):  # pragma: no cover
    """Token b[s:e] equals keyword kw (ASCII, case-insensitive)."""
    if e - s != kw.size:
        return False
    for i in range(kw.size):
        c = b[s + i]
        if 65 <= c <= 90:
            c += 32
        if c != kw[i]:
            return False
    return True


@njit(cache=True)
def _is_number(b, s, e):  # pragma: no cover
    """Token b[s:e] is a decimal floating-point number, nan or inf[inity]."""
    i = s
    if i < e and (b[i] == 43 or b[i] == 45):
        i += 1
    if i >= e:
        return False
    c = b[i] | 32
    if c == 110 or c == 105:  # nan / inf / infinity
        n = e - i
        if n == 3:
            w0, w1, w2 = b[i] | 32, b[i + 1] | 32, b[i + 2] | 32
            return (w0 == 110 and w1 == 97 and w2 == 110) or (
                w0 == 105 and w1 == 110 and w2 == 102)
        if n == 8:
            ok = True
            word = "infinity"
            for k in range(8):
                if (b[i + k] | 32) != ord(word[k]):
                    ok = False
            return ok
        return False
    digits = 0
    while i < e and 48 <= b[i] <= 57:
        i += 1
        digits += 1
    if i < e and b[i] == 46:
        i += 1
        while i < e and 48 <= b[i] <= 57:
            i += 1
            digits += 1
    if digits == 0:
        return False
    if i < e and (b[i] == 101 or b[i] == 69):
        i += 1
        if i < e and (b[i] == 43 or b[i] == 45):
            i += 1
        ed = 0
        while i < e and 48 <= b[i] <= 57:
            i += 1
            ed += 1
        if ed == 0:
            return False
    return i == e


_POW10 = np.array([10.0 ** k for k in range(23)])


@njit(cache=True)
def _fast_float(b, s, e):  # pragma: no cover
    """Value of a validated decimal token when exactly computable, else (False, 0.0).

    Clinger's fast path: with at most 19 digits, a mantissa w <= 2^53 and a decimal
    exponent |q| <= 22, ``w * 10^q`` (or ``w / 10^-q``) is one correctly rounded IEEE
    operation, the same result as ``strtod``. Anything else (long mantissas, nan, inf)
    is left to ``np.fromstring``.
    """
    i = s
    neg = False
    if b[i] == 45:
        neg = True
        i += 1
    elif b[i] == 43:
        i += 1
    if (b[i] | 32) == 110 or (b[i] | 32) == 105:
        return False, 0.0
    w = np.uint64(0)
    nd = 0
    q = 0
    while i < e and 48 <= b[i] <= 57:
        if nd > 0 or b[i] != 48:
            nd += 1
        if nd > 19:
            return False, 0.0
        w = w * np.uint64(10) + np.uint64(b[i] - 48)
        i += 1
    if i < e and b[i] == 46:
        i += 1
        while i < e and 48 <= b[i] <= 57:
            if nd > 0 or b[i] != 48:
                nd += 1
            if nd > 19:
                return False, 0.0
            w = w * np.uint64(10) + np.uint64(b[i] - 48)
            q -= 1
            i += 1
    if i < e:  # exponent
        i += 1
        eneg = False
        if b[i] == 45:
            eneg = True
            i += 1
        elif b[i] == 43:
            i += 1
        x = 0
        while i < e:
            if x < 100000:
                x = x * 10 + (b[i] - 48)
            i += 1
        q += -x if eneg else x
    if w > np.uint64(9007199254740992):
        return False, 0.0
    v = float(w)
    if w == np.uint64(0):
        v = 0.0
    elif 0 <= q <= 22:
        v = v * _POW10[q]
    elif -22 <= q < 0:
        v = v / _POW10[-q]
    else:
        return False, 0.0
    return True, -v if neg else v


@njit(cache=True)
def _next_token(b, i, line):  # pragma: no cover
    """Skip whitespace from i; returns (start, end, line) of the next token (start == n at EOF)."""
    n = b.size
    while i < n and _is_ws(b[i]):
        if b[i] == 10:
            line += 1
        i += 1
    s = i
    while i < n and not _is_ws(b[i]):
        i += 1
    return s, i, line


@njit(cache=True)
def _skip_line(b, i):  # pragma: no cover
    n = b.size
    while i < n and b[i] != 10:
        i += 1
    return i


@njit(cache=True)
def _store_number(b, s, e, values, slot, slow, ns, out, o):  # pragma: no cover
    """Put the number token b[s:e] into ``values[slot]``.

    Exact values come from :func:`_fast_float`; a token it cannot convert exactly is
    copied to ``out`` (space separated) and its slot listed in ``slow`` for strtod.
    Returns the new (ns, o) fill counts of ``slow`` and ``out``.
    """
    ok, val = _fast_float(b, s, e)
    values[slot] = val
    if not ok:
        slow[ns] = slot
        ns += 1
        for k in range(s, e):
            out[o] = b[k]
            o += 1
        out[o] = 32
        o += 1
    return ns, o


@njit(cache=True)
def _scan_stl_ascii(b):  # pragma: no cover
    """Check the ASCII STL grammar and collect the vertex coordinate tokens.

    Returns (slow_text, values, slow, vlines, err, err_line): ``values`` (3 v,) float64
    coordinates, exact where :func:`_fast_float` could compute them; the other tokens are
    copied to ``slow_text`` (uint8, space separated) and their slots listed in ``slow``;
    ``vlines`` (v,) int64 line of each vertex; an error code with its 1-based line.
    """
    n = b.size
    out = np.empty(n + 1, np.uint8)
    vlines = np.empty(n // 13 + 1, np.int64)
    values = np.empty(3 * (n // 13 + 1), np.float64)
    slow = np.empty(3 * (n // 13 + 1), np.int64)
    ns = 0
    o = 0
    nv = 0
    line = 1
    i = 0
    in_facet = False
    in_loop = False
    fv = 0
    err = 0
    while True:
        s, e, line = _next_token(b, i, line)
        i = e
        if s >= n:
            break
        if _tok_eq(b, s, e, _KW_SOLID) or _tok_eq(b, s, e, _KW_ENDSOLID):
            if in_facet:
                err = _E_TOKEN
                break
            i = _skip_line(b, e)
        elif _tok_eq(b, s, e, _KW_FACET):
            if in_facet:
                err = _E_TOKEN
                break
            s, e, line = _next_token(b, e, line)
            if not _tok_eq(b, s, e, _KW_NORMAL):
                err = _E_TOKEN
                break
            for _ in range(3):
                s, e, line = _next_token(b, e, line)
                if not _is_number(b, s, e):
                    err = _E_NUMBER
                    break
            if err:
                break
            i = e
            in_facet = True
            fv = 0
        elif _tok_eq(b, s, e, _KW_OUTER):
            s, e, line = _next_token(b, e, line)
            if not in_facet or in_loop or not _tok_eq(b, s, e, _KW_LOOP):
                err = _E_TOKEN
                break
            in_loop = True
            i = e
        elif _tok_eq(b, s, e, _KW_VERTEX):
            if not in_loop:
                err = _E_TOKEN
                break
            if fv == 3:  # a fourth vertex: report its own line
                err = _E_VCOUNT
                break
            vline = line
            for q3 in range(3):
                s, e, line = _next_token(b, e, line)
                if not _is_number(b, s, e) or line != vline:
                    err = _E_NUMBER
                    break
                ns, o = _store_number(b, s, e, values, 3 * nv + q3, slow, ns, out, o)
            if err:
                break
            vlines[nv] = vline
            nv += 1
            fv += 1
            i = e
        elif _tok_eq(b, s, e, _KW_ENDLOOP):
            if not in_loop:
                err = _E_TOKEN
                break
            in_loop = False
        elif _tok_eq(b, s, e, _KW_ENDFACET):
            if not in_facet or in_loop:
                err = _E_TOKEN
                break
            if fv != 3:
                err = _E_VCOUNT
                break
            in_facet = False
        else:
            err = _E_TOKEN
            break
    if err == 0 and in_facet:
        err = _E_EOF
    return out[:o], values[:3 * nv], slow[:ns], vlines[:nv], err, line if err else 0


@njit(cache=True)
def _scan_numbers(b, start, line):  # pragma: no cover
    """All whitespace-separated numbers of b[start:] (the body of an ASCII PLY).

    Returns (slow_text, values, slow, err, err_line) as :func:`_scan_stl_ascii`.
    """
    n = b.size
    out = np.empty(n - start + 1, np.uint8)
    values = np.empty((n - start) // 2 + 1, np.float64)
    slow = np.empty((n - start) // 2 + 1, np.int64)
    nvals = 0
    ns = 0
    o = 0
    i = start
    while True:
        s, e, line = _next_token(b, i, line)
        i = e
        if s >= n:
            break
        if not _is_number(b, s, e):
            return out[:o], values[:nvals], slow[:ns], _E_NUMBER, line
        ns, o = _store_number(b, s, e, values, nvals, slow, ns, out, o)
        nvals += 1
    return out[:o], values[:nvals], slow[:ns], 0, 0


def _line_text(data: bytes, line: int) -> str:
    """The text of 1-based line ``line`` (shortened), for error messages."""
    lines = data.split(b"\n", line)
    text = lines[line - 1] if 0 < line <= len(lines) else b""
    return text[:60].decode("ascii", "replace").strip()


def _finish_numbers(text_buf: np.ndarray, values: np.ndarray, slow: np.ndarray,
                    lines: np.ndarray, per: int, path: FsPath, fmt: str) -> np.ndarray:
    """Fill the slots the compiled scan left (long mantissas, nan, inf) with ``strtod``.

    text_buf: uint8 tokens separated by spaces, one per entry of ``slow`` (slot indices
    into ``values``). Errors name the line (``lines[slot // per]``).
    """
    if len(slow) == 0:
        return values
    text = text_buf.tobytes()
    parsed = None
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        try:
            parsed = np.fromstring(text, dtype=np.float64, sep=" ")
        except (ValueError, DeprecationWarning):
            parsed = None
    if parsed is None or len(parsed) != len(slow):
        for k, tok in enumerate(text.split()):
            try:
                float(tok)
            except ValueError:
                line = int(lines[int(slow[k]) // per]) if len(lines) else -1
                raise MeshError(f"{path}: {fmt} line {line}: cannot read number "
                                f"{tok[:30].decode('ascii', 'replace')!r}") from None
        raise MeshError(f"{path}: {fmt}: expected {len(slow)} numbers, read "
                        f"{0 if parsed is None else len(parsed)}")
    values[slow] = parsed
    return values


def _check_finite_lines(points: np.ndarray, lines: np.ndarray, path: FsPath,
                        fmt: str) -> None:
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise MeshError(f"{path}: {int(bad.sum())} vertices with NaN/Inf coordinates "
                        f"(first on {fmt} line {int(lines[k])}: {points[k].tolist()}); "
                        "expected finite numbers")


def _read_stl_ascii(data: bytes, path: FsPath) -> np.ndarray:
    """Corner coordinates (3 m, 3) float64 of an ASCII STL (one scan, one conversion)."""
    b = np.frombuffer(data, np.uint8)
    buf, values, slow, vlines, err, line = _scan_stl_ascii(b)
    if err:
        what = {_E_TOKEN: "unexpected token", _E_NUMBER: "expected three numbers",
                _E_VCOUNT: "a facet must have exactly 3 vertices",
                _E_EOF: "file ends inside a facet (truncated?)"}[err]
        raise MeshError(f"{path}: ASCII STL line {line}: {what} "
                        f"(line reads {_line_text(data, line)!r})")
    if len(vlines) == 0:
        raise MeshError(f"{path}: ASCII STL without facets")
    values = _finish_numbers(buf, values, slow, vlines, 3, path, "ASCII STL")
    corners = values.reshape(-1, 3)
    _check_finite_lines(corners, vlines, path, "ASCII STL")
    return corners


# --------------------------------------------------------------------------- OBJ


@njit(cache=True)
def _scan_obj(b):  # pragma: no cover
    """Scan an OBJ: vertex coordinate tokens and face indices.

    Returns (slow_text, values, slow, vlines, fidx, fcount, flines, n_short, err,
    err_line): ``values`` the first three numbers of every ``v`` line (slots in ``slow``
    still to be converted from ``slow_text``, see :func:`_finish_numbers`); ``fidx``
    (k,) int64 0-based vertex indices of all faces (negative indices resolved against
    the vertices read so far), ``fcount`` (f,) corners per face, ``flines`` (f,) line of each face; ``n_short``
    faces with fewer than 3 corners were skipped.
    """
    n = b.size
    out = np.empty(n + 1, np.uint8)
    vlines = np.empty(n // 6 + 1, np.int64)
    values = np.empty(3 * (n // 6 + 1), np.float64)
    slow = np.empty(3 * (n // 6 + 1), np.int64)
    ns = 0
    fidx = np.empty(n // 2 + 1, np.int64)
    fcount = np.empty(n // 6 + 1, np.int64)
    flines = np.empty(n // 6 + 1, np.int64)
    o = 0
    nv = 0
    nk = 0
    nf = 0
    n_short = 0
    err = 0
    i = 0
    line = 1
    while i < n:
        # start of a line: skip blanks (not newlines)
        while i < n and (b[i] == 32 or b[i] == 9 or b[i] == 13):
            i += 1
        if i >= n:
            break
        if b[i] == 10:
            line += 1
            i += 1
            continue
        s = i
        while i < n and not _is_ws(b[i]):
            i += 1
        e = i
        if e - s == 1 and b[s] == 118:  # 'v'
            k = 0
            while True:
                while i < n and (b[i] == 32 or b[i] == 9 or b[i] == 13):
                    i += 1
                if i >= n or b[i] == 10 or b[i] == 35:
                    break
                s = i
                while i < n and not _is_ws(b[i]):
                    i += 1
                if k < 3:
                    if not _is_number(b, s, i):
                        err = _E_NUMBER
                        break
                    ns, o = _store_number(b, s, i, values, 3 * nv + k, slow, ns, out, o)
                k += 1
            if err == 0 and k < 3:
                err = _E_FEW
            if err:
                break
            vlines[nv] = line
            nv += 1
        elif e - s == 1 and b[s] == 102:  # 'f'
            k = 0
            while True:
                while i < n and (b[i] == 32 or b[i] == 9 or b[i] == 13):
                    i += 1
                if i >= n or b[i] == 10 or b[i] == 35:
                    break
                neg = False
                if b[i] == 45:
                    neg = True
                    i += 1
                elif b[i] == 43:
                    i += 1
                val = 0
                nd = 0
                while i < n and 48 <= b[i] <= 57 and nd < 18:
                    val = val * 10 + (b[i] - 48)
                    i += 1
                    nd += 1
                if nd == 0 or (i < n and not _is_ws(b[i]) and b[i] != 47):
                    err = _E_NUMBER
                    break
                while i < n and not _is_ws(b[i]):  # '/vt/vn' part
                    i += 1
                idx = nv - val if neg else val - 1
                if val == 0 or idx < 0:
                    err = _E_INDEX
                    break
                fidx[nk] = idx
                nk += 1
                k += 1
            if err:
                break
            if k < 3:
                nk -= k
                n_short += 1
            else:
                fcount[nf] = k
                flines[nf] = line
                nf += 1
        else:
            pass  # vt, vn, o, g, s, usemtl, comments...: not needed
        while i < n and b[i] != 10:  # rest of the line
            i += 1
    return (out[:o], values[:3 * nv], slow[:ns], vlines[:nv], fidx[:nk], fcount[:nf],
            flines[:nf], n_short, err, line if err else 0)


def _fan(flat: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given as concatenated corner indices, vectorised.

    flat: (sum(counts),) int64; counts: (p,) int64, each >= 3.
    Returns (sum(counts - 2), 3) int64, polygon order kept: (c0, c_j+1, c_j+2).
    """
    if len(counts) == 0:
        return np.zeros((0, 3), np.int64)
    if np.all(counts == 3):
        return flat.reshape(-1, 3)
    starts = np.cumsum(counts) - counts
    ntri = counts - 2
    poly = np.repeat(np.arange(len(counts)), ntri)
    j = np.arange(int(ntri.sum())) - np.repeat(np.cumsum(ntri) - ntri, ntri)
    base = starts[poly]
    return np.stack([flat[base], flat[base + j + 1], flat[base + j + 2]], axis=1)


def _read_obj(data: bytes, path: FsPath) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and triangles (m, 3) int64 of an OBJ file."""
    b = np.frombuffer(data, np.uint8)
    buf, values, slow, vlines, fidx, fcount, flines, n_short, err, line = _scan_obj(b)
    if err:
        what = {_E_NUMBER: "cannot read a number", _E_FEW: "a vertex needs 3 coordinates",
                _E_INDEX: "face index 0 or before the first vertex"}[err]
        raise MeshError(f"{path}: OBJ line {line}: {what} "
                        f"(line reads {_line_text(data, line)!r})")
    if len(vlines) == 0:
        raise MeshError(f"{path}: OBJ without vertices ('v' lines)")
    values = _finish_numbers(buf, values, slow, vlines, 3, path, "OBJ")
    vertices = values.reshape(-1, 3)
    _check_finite_lines(vertices, vlines, path, "OBJ")
    if len(fidx) and fidx.max() >= len(vertices):
        k = int(np.searchsorted(np.cumsum(fcount), int(np.argmax(fidx >= len(vertices))),
                                side="right"))
        raise MeshError(f"{path}: OBJ line {int(flines[k])}: face index out of range: the "
                        f"file has {len(vertices)} vertices")
    if n_short:
        log.warning("%s: skipped %d OBJ faces with fewer than 3 corners", path, n_short)
    return vertices, _fan(fidx, fcount)


# --------------------------------------------------------------------------- PLY

_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}


@dataclass
class _PlyProp:
    name: str
    dtype: str                 # value type code, e.g. 'f4'
    count: str | None = None   # list count type code, None for a scalar


@dataclass
class _PlyElement:
    name: str
    n: int
    props: list[_PlyProp]
    line: int


def _ply_header(data: bytes, path: FsPath) -> tuple[str, list[_PlyElement], int, int]:
    """Parse the header: (format, elements, byte offset of the body, header line count)."""
    end = data.find(b"end_header")
    if end < 0:
        raise MeshError(f"{path}: PLY header without 'end_header'")
    body = data.find(b"\n", end)
    body = len(data) if body < 0 else body + 1
    try:
        text = data[:end].decode("ascii")
    except UnicodeDecodeError:
        raise MeshError(f"{path}: PLY header is not ASCII text") from None
    fmt = ""
    elements: list[_PlyElement] = []
    lines = text.replace("\r", "").split("\n")
    for ln, raw in enumerate(lines, start=1):
        words = raw.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        where = f"{path}: PLY header line {ln}"
        if words[0] == "format":
            if len(words) < 2 or words[1] not in ("ascii", "binary_little_endian",
                                                  "binary_big_endian"):
                raise MeshError(f"{where}: unknown format {raw.strip()!r}; expected ascii, "
                                "binary_little_endian or binary_big_endian")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise MeshError(f"{where}: expected 'element <name> <count>', got "
                                f"{raw.strip()!r}")
            elements.append(_PlyElement(words[1], int(words[2]), [], ln))
        elif words[0] == "property":
            if not elements:
                raise MeshError(f"{where}: property before any element")
            if len(words) == 5 and words[1] == "list":
                ct, vt = _PLY_TYPES.get(words[2]), _PLY_TYPES.get(words[3])
                if ct is None or vt is None or ct[0] == "f":
                    raise MeshError(f"{where}: bad list types in {raw.strip()!r}")
                elements[-1].props.append(_PlyProp(words[4], vt, ct))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].props.append(_PlyProp(words[2], _PLY_TYPES[words[1]]))
            else:
                raise MeshError(f"{where}: cannot read property {raw.strip()!r}")
        else:
            raise MeshError(f"{where}: unknown header keyword {words[0]!r}")
    if not fmt:
        raise MeshError(f"{path}: PLY header without a 'format' line")
    return fmt, elements, body, len(lines)


@njit(cache=True)
def _scan_ply_binary(b, start, n, is_list, vsize, csize, csigned, big):  # pragma: no cover
    """Byte offset of every property of every record of a PLY element with list properties.

    Returns (offsets (n, p) int64, end, ok); ``ok`` is False when the data run out or a
    count is negative.
    """
    p = is_list.size
    offsets = np.empty((n, p), np.int64)
    pos = start
    size = b.size
    for r in range(n):
        for q in range(p):
            offsets[r, q] = pos
            if not is_list[q]:
                pos += vsize[q]
                continue
            cs = csize[q]
            if pos + cs > size:
                return offsets, pos, False
            c = 0
            for k in range(cs):
                byte = b[pos + (cs - 1 - k if not big else k)]
                c = c * 256 + byte
            if csigned[q] and c >= (1 << (8 * cs - 1)):
                return offsets, pos, False  # negative count
            pos += cs + c * vsize[q]
        if pos > size:
            return offsets, pos, False
    return offsets, pos, True


@njit(cache=True)
def _scan_ply_ascii(t, start, n, is_list):  # pragma: no cover
    """Token index of every property of every record (ASCII PLY); see _scan_ply_binary."""
    p = is_list.size
    offsets = np.empty((n, p), np.int64)
    pos = start
    size = t.size
    for r in range(n):
        for q in range(p):
            offsets[r, q] = pos
            if not is_list[q]:
                pos += 1
                continue
            if pos >= size:
                return offsets, pos, False
            c = t[pos]
            if not (c >= 0 and c == np.floor(c) and c < 2**31):
                return offsets, pos, False
            pos += 1 + int(c)
        if pos > size:
            return offsets, pos, False
    return offsets, pos, True


class _PlyData:
    """Property values of one element: ``scalars[name]`` (n,) and
    ``lists[name] = (flat values, counts (n,))``."""

    def __init__(self, scalars: dict[str, np.ndarray],
                 lists: dict[str, tuple[np.ndarray, np.ndarray]]):
        self.scalars = scalars
        self.lists = lists  # name -> (flat values, counts)


def _ply_element_binary(b: np.ndarray, pos: int, el: _PlyElement, endian: str,
                        path: FsPath) -> tuple[_PlyData, int]:
    """Read one element of a binary PLY starting at byte ``pos``; returns data and end."""
    remaining = len(b) - pos
    # guess a fixed layout from the first record's list counts (exact by induction when
    # every record's counts agree with it); fall back to a compiled scan otherwise.
    fields = []
    at = pos
    guess: dict[str, int] = {}
    for q in el.props:
        if q.count is None:
            fields.append((q.name, endian + q.dtype))
            at += np.dtype(q.dtype).itemsize
        else:
            csz = np.dtype(q.count).itemsize
            if el.n == 0 or at + csz > len(b):
                c = 0
            else:
                c = int(b[at:at + csz].view(endian + q.count)[0])
            if c < 0:
                raise MeshError(f"{path}: PLY element {el.name!r}: negative list count {c}")
            guess[q.name] = c
            fields.append(("__n_" + q.name, endian + q.count))
            fields.append((q.name, endian + q.dtype, (c,)))
            at += csz + c * np.dtype(q.dtype).itemsize
    dt = np.dtype(fields)
    if el.n == 0:
        return _PlyData({q.name: np.zeros(0) for q in el.props if q.count is None},
                        {q.name: (np.zeros(0, np.int64), np.zeros(0, np.int64))
                         for q in el.props if q.count is not None}), pos
    if not guess:
        if el.n * dt.itemsize > remaining:
            raise MeshError(f"{path}: truncated PLY: element {el.name!r} declares {el.n} "
                            f"records ({el.n * dt.itemsize} bytes) but {remaining} bytes "
                            "remain")
        rec = np.frombuffer(b, dt, count=el.n, offset=pos)
        return _PlyData({q.name: rec[q.name] for q in el.props}, {}), \
            pos + el.n * dt.itemsize
    if dt.itemsize > 0 and el.n * dt.itemsize <= remaining:
        rec = np.frombuffer(b, dt, count=el.n, offset=pos)
        if all(np.all(rec["__n_" + k] == c) for k, c in guess.items()):
            scal = {q.name: rec[q.name] for q in el.props if q.count is None}
            lists = {k: (rec[k].reshape(-1).astype(np.int64),
                         np.full(el.n, c, np.int64)) for k, c in guess.items()}
            return _PlyData(scal, lists), pos + el.n * dt.itemsize
    # variable layout: every record is at least its count fields and scalars long
    min_size = sum(np.dtype(q.count or q.dtype).itemsize for q in el.props)
    if el.n * max(min_size, 1) > remaining:
        raise MeshError(f"{path}: truncated PLY: element {el.name!r} declares {el.n} "
                        f"records but only {remaining} bytes remain")
    is_list = np.array([q.count is not None for q in el.props])
    vsize = np.array([np.dtype(q.dtype).itemsize for q in el.props], np.int64)
    csize = np.array([np.dtype(q.count).itemsize if q.count else 0 for q in el.props],
                     np.int64)
    csigned = np.array([bool(q.count and q.count[0] == "i") for q in el.props])
    offsets, end, ok = _scan_ply_binary(b, pos, el.n, is_list, vsize, csize, csigned,
                                        endian == ">")
    if not ok:
        raise MeshError(f"{path}: truncated or corrupt PLY element {el.name!r} (record data "
                        f"runs past the end of the file or has a negative list count)")
    scal: dict[str, np.ndarray] = {}
    lists: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for qi, q in enumerate(el.props):
        if q.count is None:
            scal[q.name] = _gather(b, offsets[:, qi], endian + q.dtype)
        else:
            cdt = endian + q.count
            counts = _gather(b, offsets[:, qi], cdt).astype(np.int64)
            vdt = np.dtype(endian + q.dtype)
            total = int(counts.sum())
            rec_of = np.repeat(np.arange(el.n), counts)
            j = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
            starts = offsets[rec_of, qi] + np.dtype(cdt).itemsize + j * vdt.itemsize
            lists[q.name] = (_gather(b, starts, vdt).astype(np.int64), counts)
    return _PlyData(scal, lists), int(end)


def _gather(b: np.ndarray, starts: np.ndarray, dtype: str | np.dtype) -> np.ndarray:
    """Values of ``dtype`` stored at byte offsets ``starts`` of ``b`` (vectorised)."""
    dt = np.dtype(dtype)
    idx = starts[:, None] + np.arange(dt.itemsize)
    return np.ascontiguousarray(b[idx]).view(dt).reshape(-1)


def _ply_element_ascii(t: np.ndarray, pos: int, el: _PlyElement,
                       path: FsPath) -> tuple[_PlyData, int]:
    """Read one element from the token array ``t`` (ASCII PLY) starting at token ``pos``."""
    remaining = len(t) - pos
    kinds = [q.count is not None for q in el.props]
    if el.n == 0:
        return _PlyData({}, {}), pos
    if el.n * max(len(kinds), 1) > remaining:
        raise MeshError(f"{path}: truncated ASCII PLY: element {el.name!r} declares {el.n} "
                        f"records but only {remaining} numbers remain")
    # fixed layout guess from the first record
    width = 0
    guess = []
    for q in el.props:
        if q.count is None:
            width += 1
        else:
            c = t[pos + width] if pos + width < len(t) else -1
            if not (c >= 0 and c == np.floor(c)):
                raise MeshError(f"{path}: ASCII PLY element {el.name!r}: bad list count "
                                f"{c!r}")
            guess.append((width, int(c)))
            width += 1 + int(c)
    if el.n * width <= remaining:
        table = t[pos:pos + el.n * width].reshape(el.n, width)
        if all(np.all(table[:, w] == c) for w, c in guess):
            scal, lists, col = {}, {}, 0
            for q in el.props:
                if q.count is None:
                    scal[q.name] = table[:, col]
                    col += 1
                else:
                    c = int(table[0, col])
                    lists[q.name] = (table[:, col + 1:col + 1 + c].reshape(-1),
                                     np.full(el.n, c, np.int64))
                    col += 1 + c
            return _PlyData(scal, lists), pos + el.n * width
    offsets, end, ok = _scan_ply_ascii(t, pos, el.n, np.array(kinds))
    if not ok:
        raise MeshError(f"{path}: truncated or corrupt ASCII PLY element {el.name!r} (data "
                        "run out or a list count is not a non-negative integer)")
    scal, lists = {}, {}
    for qi, q in enumerate(el.props):
        if q.count is None:
            scal[q.name] = t[offsets[:, qi]]
        else:
            counts = t[offsets[:, qi]].astype(np.int64)
            total = int(counts.sum())
            rec_of = np.repeat(np.arange(el.n), counts)
            j = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts)
            lists[q.name] = (t[offsets[rec_of, qi] + 1 + j], counts)
    return _PlyData(scal, lists), int(end)


def _tristrips(strip: np.ndarray) -> np.ndarray:
    """Triangles (m, 3) of a triangle strip with -1 restarts, vectorised.

    Triangle i of a strip is (s_i, s_i+1, s_i+2) with the first two swapped for odd i
    (alternating winding, counted from the start of each strip); triangles spanning a -1
    and degenerate ones (repeated index, used by strippers to turn corners) are dropped.
    """
    s = np.asarray(strip, np.int64)
    if len(s) < 3:
        return np.zeros((0, 3), np.int64)
    a, b_, c = s[:-2], s[1:-1], s[2:]
    i = np.arange(len(s) - 2)
    restart = np.flatnonzero(s < 0)
    last = np.full(len(s), -1, np.int64)
    last[restart] = restart
    last = np.maximum.accumulate(last)
    k = i - last[:-2] - 1  # position inside the current strip
    odd = (k % 2) == 1
    tri = np.stack([np.where(odd, b_, a), np.where(odd, a, b_), c], axis=1)
    valid = (a >= 0) & (b_ >= 0) & (c >= 0) & (a != b_) & (b_ != c) & (a != c)
    return tri[valid]


def _read_ply(data: bytes, path: FsPath) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and triangles (m, 3) int64 of a binary or ASCII PLY."""
    fmt, elements, body, _ = _ply_header(data, path)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise MeshError(f"{path}: PLY without a 'vertex' element")
    vel = elements[names.index("vertex")]
    missing = [a for a in "xyz" if a not in [q.name for q in vel.props if q.count is None]]
    if missing:
        raise MeshError(f"{path}: PLY vertex element lacks scalar properties "
                        f"{', '.join(missing)}")
    wanted = {"vertex", "face", "tristrips"}
    last = max(i for i, e in enumerate(elements) if e.name in wanted)
    got: dict[str, _PlyData] = {}
    if fmt == "ascii":
        header_lines = data[:body].count(b"\n") + 1
        buf, t, slow, err, line = _scan_numbers(np.frombuffer(data, np.uint8), body,
                                                header_lines)
        if err:
            raise MeshError(f"{path}: ASCII PLY line {line}: cannot read number "
                            f"(line reads {_line_text(data, line)!r})")
        t = _finish_numbers(buf, t, slow, np.zeros(0, np.int64), 1, path, "ASCII PLY")
        pos = 0
        for el in elements[:last + 1]:
            d, pos = _ply_element_ascii(t, pos, el, path)
            got[el.name] = d
    else:
        b = np.frombuffer(data, np.uint8)
        endian = "<" if fmt == "binary_little_endian" else ">"
        pos = body
        for el in elements[:last + 1]:
            d, pos = _ply_element_binary(b, pos, el, endian, path)
            got[el.name] = d
    v = got["vertex"].scalars
    vertices = np.stack([np.asarray(v[a], np.float64) for a in "xyz"], axis=1) \
        if vel.n else np.zeros((0, 3))
    tris = []
    for name in ("face", "tristrips"):
        if name not in got:
            continue
        lists = got[name].lists
        key = next((k for k in ("vertex_indices", "vertex_index") if k in lists),
                   next(iter(lists), None))
        if key is None:
            raise MeshError(f"{path}: PLY element {name!r} has no vertex index list")
        flat, counts = lists[key]
        flat = np.asarray(flat)
        if not np.all(flat == np.floor(flat)):
            raise MeshError(f"{path}: PLY {name} indices are not integers")
        flat = flat.astype(np.int64)
        if name == "face":
            short = counts < 3
            if short.any():
                log.warning("%s: skipped %d PLY faces with fewer than 3 corners", path,
                            int(short.sum()))
                keep = np.repeat(~short, counts)
                flat, counts = flat[keep], counts[~short]
            tris.append(_fan(flat, counts))
        else:
            # every record is a strip set of its own: join them with -1 restarts
            joined = np.full(len(flat) + len(counts), -1, np.int64)
            rec_of = np.repeat(np.arange(len(counts)), counts)
            joined[np.arange(len(flat)) + rec_of] = flat
            tris.append(_tristrips(joined))
    if not tris:
        raise MeshError(f"{path}: PLY without a 'face' or 'tristrips' element (a point "
                        "cloud?)")
    faces = np.concatenate(tris) if len(tris) > 1 else tris[0]
    return vertices, faces


# --------------------------------------------------------------------------- writing


def write_stl(mesh: Mesh, path: str | os.PathLike[str]) -> None:
    """Write a binary STL (float32; via a temporary file renamed into place)."""
    p = FsPath(path)
    tri = mesh.triangles().astype(np.float32)
    rec = np.zeros(len(tri), dtype=_STL_DTYPE)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    rec["normal"] = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    rec["corners"] = tri
    header = (b"binary STL written by icefab " + mesh.name.encode("ascii", "replace"))
    write_atomic(p, header[:80].ljust(80, b" ") + np.uint32(len(tri)).tobytes()
                 + rec.tobytes())


# --------------------------------------------------------------------------- part set-up


def merge_meshes(meshes: Sequence[Mesh], name: str = "") -> Mesh:
    """One mesh holding all faces of ``meshes`` (vertex indices offset; no welding)."""
    if not meshes:
        raise MeshError("no meshes to merge")
    if len(meshes) == 1:
        return meshes[0] if not name else dataclasses.replace(meshes[0], name=name)
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)])
    return Mesh(vertices, faces, name or "+".join(m.name for m in meshes),
                tuple(w for m in meshes for w in m.warnings))


def load_meshes(paths: Iterable[str | os.PathLike[str]], *, inexact: bool = False,
                tolerance: float = 1e-4) -> Mesh:
    """Load several mesh files and merge them into one build (thesis Table 3-1, CAD PARTS).

    The parts keep their coordinates relative to each other; see :func:`load_mesh`.
    """
    meshes = [load_mesh(p, inexact=inexact, tolerance=tolerance) for p in paths]
    if not meshes:
        raise MeshError("no mesh files given")
    return merge_meshes(meshes)


def _rotation_matrix(axis: int, angle_deg: float) -> np.ndarray:
    """(3, 3) right-handed rotation about space-fixed axis 1 (x), 2 (y) or 3 (z)."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis - 1]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def rotation_matrix(rotation_deg: Sequence[float], order: Sequence[int]) -> np.ndarray:
    """(3, 3) rotation: about the space-fixed axes in ``order`` (1 = x, 2 = y, 3 = z).

    rotation_deg: angles about x, y, z, degrees. The first axis in ``order`` is applied
    first; space-fixed (extrinsic) rotations compose by left multiplication:
    ``R = R[order[2]] @ R[order[1]] @ R[order[0]]`` (thesis 3.1.2).
    """
    from icefab.errors import ConfigError

    if sorted(int(o) for o in order) != [1, 2, 3]:
        raise ConfigError(f"parts.rotation_order = {tuple(order)!r}: must be a permutation "
                          "of 1, 2, 3")
    r = np.eye(3)
    for axis in order:
        r = _rotation_matrix(int(axis), float(rotation_deg[int(axis) - 1])) @ r
    return r


def transform(mesh: Mesh, parts: "PartSetup") -> Mesh:
    """Place a build as the part set-up asks (thesis 3.1.2, Table 3-1, paper Table 1).

    Steps, in this order:

    1. If any rotation or scaling is asked, the mesh is first moved so that its minimum
       coordinate on every axis is zero (thesis 3.1.2).
    2. Rotations about the space-fixed x, y, z axes by ``rotation_deg``, one axis at a
       time in ``rotation_order`` (see :func:`rotation_matrix`).
    3. Scaling by ``scale`` along the space-fixed axes (after rotation, as the paper's
       "rotated, scaled, and translated").
    4. Copies: ``copies = (p1, p2, p3)`` lays ``p3`` copies out row by row in a grid of
       ``p1`` columns (x) by ``p2`` rows (y), spaced by the part's extent plus
       ``copy_gap_mm``; ``p3`` must not exceed ``p1 * p2``.
    5. Translation of the whole build per axis: a number is the build's minimum
       coordinate on that axis (mm); ``'cent'`` centres its bounding box on 0; ``'orig'``
       keeps the bounding-box centre where the original model's was.

    Returns a new Mesh (faces of copies appended after the original's).
    """
    from icefab.errors import ConfigError

    v = np.array(mesh.vertices, dtype=np.float64)
    if len(v) == 0:
        raise MeshError(f"{mesh.name or 'mesh'}: nothing to transform (no vertices)")
    lo0, hi0 = v.min(axis=0), v.max(axis=0)
    centre0 = 0.5 * (lo0 + hi0)
    scale = np.asarray(parts.scale, dtype=np.float64)
    rot = np.asarray(parts.rotation_deg, dtype=np.float64)
    if np.any(scale != 1.0) or np.any(rot % 360.0 != 0.0):
        v -= lo0  # thesis 3.1.2: minimum at zero before rotating or scaling
        v = v @ rotation_matrix(rot, parts.rotation_order).T
        v *= scale
    p1, p2, p3 = (int(c) for c in parts.copies)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if p3 > p1 * p2:
        raise ConfigError(f"parts.copies = {tuple(parts.copies)!r}: {p3} copies do not fit "
                          f"a {p1} x {p2} grid")
    if p3 > 1:
        lo, hi = v.min(axis=0), v.max(axis=0)
        pitch = (hi - lo)[:2] + float(parts.copy_gap_mm)
        k = np.arange(p3)
        shift = np.zeros((p3, 3))
        shift[:, 0] = (k % p1) * pitch[0]
        shift[:, 1] = (k // p1) * pitch[1]
        v = (v[None, :, :] + shift[:, None, :]).reshape(-1, 3)
        faces = (faces[None, :, :] + (np.arange(p3) * len(mesh.vertices))[:, None, None]
                 ).reshape(-1, 3)
    lo, hi = v.min(axis=0), v.max(axis=0)
    for axis, t in enumerate(parts.translation):
        if isinstance(t, str):
            if t == "cent":
                v[:, axis] -= 0.5 * (lo[axis] + hi[axis])
            elif t == "orig":
                v[:, axis] += centre0[axis] - 0.5 * (lo[axis] + hi[axis])
            else:
                raise ConfigError(f"parts.translation = {tuple(parts.translation)!r}: the "
                                  f"{'xyz'[axis]} entry must be a number, 'cent' or 'orig'")
        else:
            v[:, axis] += float(t) - lo[axis]
    return dataclasses.replace(mesh, vertices=v, faces=faces)


def part_fraction_range(mesh: Mesh, parts: "PartSetup") -> tuple[float, float]:
    """(zmin, zmax) mm of the slice of the build height to make (``parts.part_fraction``).

    ``[0, 1]`` is the whole part; fractions are of the height between the lowest and
    highest vertex.
    """
    lo, hi = mesh.bounds[:, 2]
    f0, f1 = parts.part_fraction
    h = float(hi - lo)
    return float(lo + f0 * h), float(lo + f1 * h)


def prepare_parts(job: "Job", base_dir: str | os.PathLike[str] | None = None) -> Mesh:
    """Load ``job.parts.files`` (relative to ``base_dir``), merge and place them.

    Welding follows ``job.parts.inexact`` / ``weld_tolerance_mm``; placement follows
    :func:`transform`; then holes are closed in 3D (``job.parts.close_holes``) and defects
    located in the build's coordinates (:func:`icefab.holes.prepare_closed`). Raises
    :class:`MeshError` when the job names no file.
    """
    parts = job.parts
    if not parts.files:
        raise MeshError("parts.files is empty: the job names no mesh file to build")
    base = FsPath(base_dir) if base_dir is not None else None
    paths = [FsPath(f) if base is None or FsPath(f).is_absolute() else base / f
             for f in parts.files]
    mesh = load_meshes(paths, inexact=parts.inexact, tolerance=parts.weld_tolerance_mm)
    from icefab.holes import prepare_closed  # holes closed in 3D, defects located in mm

    return prepare_closed(transform(mesh, parts), job)
