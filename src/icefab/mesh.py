"""Mesh import, diagnostics and part set-up (thesis 3.1, Table 3-1).

This is the only module of icefab that parses mesh files. Everything returns an indexed
:class:`~icefab.types.Mesh` (``vertices (n, 3) float64 mm``, ``faces (m, 3) int64``).

Formats (detected by content; the file extension is only a hint):

* binary STL — one ``np.frombuffer`` with a structured dtype (thesis 3.1.1: "one FREAD
  statement"). A binary STL whose 80-byte header begins with ``solid`` is recognised by its
  size (``84 + 50 n`` bytes) or, when the size does not fit, by non-text bytes after the
  header.
* ASCII STL — parsed in bulk (keywords blanked, all numbers converted in one call).
* PLY, binary (little/big endian) and ASCII — every element is read with one structured
  dtype; extra properties are skipped; faces with any list count type; polygons are
  fan-triangulated; a ``tristrips`` element (``-1`` restarts) is decoded vectorised.
* OBJ — ``v`` and ``f`` lines (``f 1/2/3 4//5 -1``), negative indices, polygons
  fan-triangulated, parsed in bulk.

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
face (duplicates, in either orientation) are removed; a closed mesh with negative signed
volume (inside out) has all faces flipped. Open and non-manifold edges are reported,
never "repaired" here (the slicer closes gaps per layer and reports them).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Iterable, Sequence

import numpy as np
from numba import njit

from icefab.errors import MeshError
from icefab.types import Mesh

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job, PartSetup

log = logging.getLogger(__name__)

__all__ = ["MeshReport", "load_mesh", "read_mesh", "load_meshes", "check_mesh",
           "weld_vertices", "clean_mesh", "transform", "prepare_parts",
           "part_fraction_range", "merge_meshes", "mesh_volume", "write_stl"]

# --------------------------------------------------------------------------- hashing


@njit(cache=True)
def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Exact unique rows of an (n, k) integer array with an open-addressing hash table.

    Returns ``first`` (u,) int64, the index of the first occurrence of every distinct row
    in order of appearance, and ``inverse`` (n,) int64 with ``rows[first][inverse] == rows``.
    Expected O(n); used for vertex welding (float bit patterns), edges and duplicate faces.
    """
    n, k = rows.shape
    cap = 16
    while cap < 2 * n + 1:
        cap *= 2
    mask = np.uint64(cap - 1)
    table = np.full(cap, -1, np.int64)
    first = np.empty(n, np.int64)
    inverse = np.empty(n, np.int64)
    nu = 0
    for i in range(n):
        h = np.uint64(0xCBF29CE484222325)
        for c in range(k):
            h = (h ^ np.uint64(rows[i, c])) * np.uint64(0x100000001B3)
            h ^= h >> np.uint64(31)
        s = h & mask
        while True:
            slot = table[s]
            if slot < 0:
                table[s] = nu
                first[nu] = i
                inverse[i] = nu
                nu += 1
                break
            j = first[slot]
            same = True
            for c in range(k):
                if rows[j, c] != rows[i, c]:
                    same = False
                    break
            if same:
                inverse[i] = slot
                break
            s = (s + np.uint64(1)) & mask
    return first[:nu].copy(), inverse


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
            w.append(f"{n}: {self.open_edges} open edges (the surface has holes)")
        if self.non_manifold_edges:
            w.append(f"{n}: {self.non_manifold_edges} non-manifold edges (shared by more "
                     "than two faces)")
        if self.misoriented_edges:
            w.append(f"{n}: {self.misoriented_edges} edges between faces of inconsistent "
                     "orientation")
        if self.inverted and not self.flipped:
            w.append(f"{n}: inverted orientation (negative volume {self.volume:.6g} mm^3)")
        return w


def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (mm^3) enclosed by the faces (divergence theorem); > 0 when outward."""
    if len(faces) == 0:
        return 0.0
    # shift to the centroid of the bounding box for accuracy
    c = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    v = vertices - c
    a, b, d = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(np.einsum("ij,ij->", a, np.cross(b, d)) / 6.0)


def _edge_stats(faces: np.ndarray, n_vertices: int) -> tuple[int, int, int]:
    """(open, non-manifold, misoriented) undirected edge counts of non-degenerate faces."""
    if len(faces) == 0:
        return 0, 0, 0
    e = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    lo = np.minimum(e[:, 0], e[:, 1])
    hi = np.maximum(e[:, 0], e[:, 1])
    direction = np.where(e[:, 0] < e[:, 1], 1, -1)
    _, inv = _unique_rows(np.stack([lo, hi], axis=1))
    counts = np.bincount(inv)
    dsum = np.bincount(inv, weights=direction)
    open_ = int(np.count_nonzero(counts == 1))
    nonman = int(np.count_nonzero(counts > 2))
    misor = int(np.count_nonzero((counts == 2) & (dsum != 0)))
    return open_, nonman, misor


def _degenerate_mask(faces: np.ndarray) -> np.ndarray:
    return ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2])
            | (faces[:, 0] == faces[:, 2]))


def _duplicate_mask(faces: np.ndarray) -> np.ndarray:
    """(m,) bool: face has the same vertex set as an earlier face."""
    if len(faces) == 0:
        return np.zeros(0, bool)
    first, _ = _unique_rows(np.sort(faces, axis=1))
    keep = np.zeros(len(faces), bool)
    keep[first] = True
    return ~keep


def check_mesh(mesh: Mesh) -> MeshReport:
    """Diagnose a mesh: edge topology, degenerate/duplicate faces, orientation.

    Vectorised: edges are keyed by their sorted vertex pair and counted with a hash table.
    """
    v, f = mesh.vertices, np.asarray(mesh.faces, dtype=np.int64)
    nonfinite = int(np.count_nonzero(~np.isfinite(v).all(axis=1))) if len(v) else 0
    degen = _degenerate_mask(f)
    good = f[~degen]
    dup = _duplicate_mask(good)
    open_, nonman, misor = _edge_stats(good, len(v))
    if nonfinite == 0 and len(good):
        tri = v[good]
        area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        scale = float(np.abs(v).max()) or 1.0
        zero_area = int(np.count_nonzero(area2 <= (1e-12 * scale) ** 2))
        volume = mesh_volume(v, good)
    else:
        zero_area, volume = 0, float("nan")
    closed = open_ == 0 and nonman == 0 and len(good) > 0
    return MeshReport(name=mesh.name, n_vertices=int(len(v)), n_faces=int(len(f)),
                      open_edges=open_, non_manifold_edges=nonman, misoriented_edges=misor,
                      degenerate_faces=int(degen.sum()), zero_area_faces=zero_area,
                      duplicate_faces=int(dup.sum()), nonfinite_vertices=nonfinite,
                      volume=volume, inverted=bool(closed and misor == 0 and volume < 0))


def clean_mesh(mesh: Mesh) -> tuple[Mesh, MeshReport]:
    """Remove degenerate and duplicate faces, flip an inside-out closed mesh.

    Returns the cleaned mesh and the report of the cleaned mesh with the ``removed_*`` and
    ``flipped`` fields telling what was changed.
    """
    f = np.asarray(mesh.faces, dtype=np.int64)
    degen = _degenerate_mask(f)
    f = f[~degen]
    dup = _duplicate_mask(f)
    f = f[~dup]
    cleaned = Mesh(mesh.vertices, f, mesh.name)
    report = check_mesh(cleaned)
    flipped = False
    if report.inverted:
        cleaned = Mesh(mesh.vertices, np.ascontiguousarray(f[:, ::-1]), mesh.name)
        report = dataclasses.replace(report, volume=-report.volume, inverted=False)
        flipped = True
    report = dataclasses.replace(report, removed_degenerate=int(degen.sum()),
                                 removed_duplicate=int(dup.sum()), flipped=flipped)
    return cleaned, report


# --------------------------------------------------------------------------- reading


_STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)),
                       ("attr", "<u2")])
_TEXT_BYTES = np.zeros(256, bool)
_TEXT_BYTES[[9, 10, 11, 12, 13]] = True
_TEXT_BYTES[32:127] = True


def _is_text(data: bytes | memoryview) -> bool:
    """True when every byte is printable ASCII or whitespace."""
    return bool(_TEXT_BYTES[np.frombuffer(data, np.uint8)].all())


def _sniff(data: bytes, path: FsPath) -> str:
    """The format of ``data``: 'stl', 'stl-ascii', 'ply' or 'obj' (content first)."""
    ext = path.suffix.lower()
    head = data[:5].lower()
    if data[:3] == b"ply" and data[3:4] in (b"\n", b"\r", b" "):
        return "ply"
    if len(data) >= 84:
        n = int.from_bytes(data[80:84], "little")
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


def _corners_to_mesh(corners: np.ndarray, path: FsPath, inexact: bool,
                     tolerance: float) -> tuple[Mesh, int]:
    """Weld (3 m, 3) corners into an indexed mesh; returns the mesh and merged count."""
    _check_finite(corners, path)
    vertices, index = weld_vertices(corners, inexact=inexact, tolerance=tolerance)
    return Mesh(vertices, index.reshape(-1, 3), path.name), 0


def _check_finite(points: np.ndarray, path: FsPath) -> None:
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise MeshError(f"{path}: {int(bad.sum())} vertices with NaN/Inf coordinates "
                        f"(first: vertex {k} = {points[k].tolist()}); expected finite numbers")


def read_mesh(path: str | os.PathLike[str], *, inexact: bool = False,
              tolerance: float = 1e-4) -> tuple[Mesh, MeshReport]:
    """Load a mesh file and return it with its diagnostics (see :func:`load_mesh`)."""
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
    if len(data.strip()) == 0:
        raise MeshError(f"{p}: empty file, expected a mesh (STL, PLY or OBJ)")
    fmt = _sniff(data, p)
    try:
        if fmt == "stl":
            corners = _read_stl_binary(data, p)
            _check_finite(corners, p)
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
    for w in report.warnings():
        log.warning("%s", w)
    return mesh, report


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


def _read_stl_ascii(data: bytes, path: FsPath) -> np.ndarray:
    raise MeshError(f"{path}: ASCII STL not supported yet")


def _read_ply(data: bytes, path: FsPath) -> tuple[np.ndarray, np.ndarray]:
    raise MeshError(f"{path}: PLY not supported yet")


def _read_obj(data: bytes, path: FsPath) -> tuple[np.ndarray, np.ndarray]:
    raise MeshError(f"{path}: OBJ not supported yet")


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
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(header[:80].ljust(80, b" "))
        fh.write(np.uint32(len(tri)).tobytes())
        fh.write(rec.tobytes())
    os.replace(tmp, p)
