"""Mesh diagnostics and clean-up: :class:`MeshReport`, :func:`check_mesh`, :func:`clean_mesh`.

Clean-up after welding (each reported as a warning with its count): faces with a repeated
vertex index (degenerate) are removed; faces with the same three vertices as an earlier
face (duplicates, in either orientation) are removed (searched for only when a
non-manifold or misoriented edge shows one may exist); vertices no face uses are dropped;
a closed mesh with negative signed volume (inside out) has all faces flipped. Vertices of
open edges within rounding noise of each other are welded (one vertex written twice,
:func:`weld_noise_at_open_edges`). Other open and non-manifold edges are reported with
their count and the location of one of them, never "repaired" here
(:mod:`icefab.mesh.holes` closes holes in 3D, the slicer gaps per layer). Faces with distinct
but collinear corners (zero area) are counted, not removed: removing them would open the
surface.

May import: ``icefab.mesh.topology``, ``icefab.core``, ``icefab.errors``.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np

from icefab.core import Mesh
from icefab.errors import MeshError
from icefab.mesh.topology import _duplicate_faces, _edge_topology, _face_measures

log = logging.getLogger(__name__)


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
    removed_degenerate, removed_duplicate, merged_vertices, flipped: what loading fixed;
    welded_noise: vertices of open edges welded to a neighbour within rounding noise
        (:func:`weld_noise_at_open_edges`).
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
    welded_noise: int = 0
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
        if self.welded_noise:
            w.append(f"{n}: {self.welded_noise} vertices of open edges welded to a "
                     "neighbour within rounding noise (one vertex written twice)")
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
    # the file as read, before parts.scale and parts.translation place it
    return f", e.g. at {point_text(point)} in the file's coordinates"


def point_text(point) -> str:
    """``(x, y, z)`` to 4 significant digits, what rounding leaves of zero as 0 (a hole's
    centre printed as 5.329e-16)."""
    return "({:.4g}, {:.4g}, {:.4g})".format(*(np.round(np.asarray(point, dtype=np.float64), 9)
                                              + 0.0))


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
    return _edge_stats_and_open(faces, n_vertices)[0]


def _edge_stats_and_open(faces: np.ndarray, n_vertices: int) -> tuple[tuple, np.ndarray]:
    """:func:`_edge_stats` and (n_vertices,) bool: the vertices of the open edges."""
    if len(faces) == 0:
        none = np.full(2, -1, np.int64)
        return (0, 0, 0, none, none), np.zeros(int(n_vertices), bool)
    o, n, m, ex_o, ex_n, open_v = _edge_topology(faces, int(n_vertices))
    return (int(o), int(n), int(m), ex_o, ex_n), open_v


#: Two vertices of open edges closer than this, relative to their largest coordinate's
#: size (at least the median edge's), are one vertex written twice with rounding noise: a
#: few float32 steps (a binary STL's), 0.3 um at 300 mm ...
NOISE_WELD_REL = 1e-6
#: ... and never farther apart than this share of the mesh's median edge (a stray
#: vertex at 1e20 mm, or a part far from the origin, does not widen it).
NOISE_WELD_OF_EDGE = 1e-3


def noise_weld_tolerance(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The farthest (mm) :func:`weld_noise_at_open_edges` welds: NOISE_WELD_OF_EDGE of the
    median edge length (over up to 10 000 faces spread over the mesh: 60 ms for 100 000)."""
    if len(faces) == 0:
        return 0.0
    f = faces[::max(1, len(faces) // 10_000)]
    edge = vertices[f] - vertices[np.roll(f, 1, axis=1)]
    return NOISE_WELD_OF_EDGE * float(np.median(np.sqrt(np.sum(edge ** 2, axis=2))))


def weld_noise_at_open_edges(vertices: np.ndarray, faces: np.ndarray,
                             open_v: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Faces with the vertices of open edges that lie within rounding noise of each other
    welded (each to the lowest-numbered of its group), and how many were: closer than
    :data:`NOISE_WELD_REL` of their largest coordinate's size and than
    :func:`noise_weld_tolerance`.

    A CAD export wrote one vertex as (2.46875, 1.135, 5.1e-16) and as (2.46875, 1.135, 0):
    the exact weld kept both, the seam between their faces was 44 open edges, and the
    holes closed in 3D spanned 55 mm across surface that was there, doubling two layers'
    area (a tester's idler_riser.STL). Only open edges' vertices are looked at: a closed
    mesh costs nothing, and no vertex of a closed part of the surface moves.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    nv = len(vertices)
    if open_v is None:
        open_v = _edge_stats_and_open(faces, nv)[1]
    ids = np.flatnonzero(open_v)
    tol = noise_weld_tolerance(vertices, faces)
    if len(ids) < 2 or not tol > 0:
        return faces, 0
    at = vertices[ids]
    pairs = cKDTree(at).query_pairs(tol, output_type="ndarray")
    if len(pairs):   # ... and within rounding noise of their own size, or of an edge's
        # (1e-16 next to 0 is the noise of a sum of millimetres: a corner at the origin)
        a, b = at[pairs[:, 0]], at[pairs[:, 1]]
        size = np.maximum(np.maximum(np.abs(a).max(axis=1), np.abs(b).max(axis=1)),
                          tol / NOISE_WELD_OF_EDGE)
        pairs = pairs[np.sqrt(np.sum((a - b) ** 2, axis=1)) <= NOISE_WELD_REL * size]
    if not len(pairs):
        return faces, 0
    k = len(ids)
    graph = coo_matrix((np.ones(len(pairs), np.int8), (pairs[:, 0], pairs[:, 1])),
                       shape=(k, k))
    n_groups, label = connected_components(graph, directed=False)
    lowest = np.full(n_groups, nv, np.int64)
    np.minimum.at(lowest, label, ids)        # ids ascend: the group's lowest vertex
    to = np.arange(nv, dtype=np.int64)
    to[ids] = lowest[label]
    return to[faces], int(k - n_groups)


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
    edges, open_v = _edge_stats_and_open(f, nv)
    n_noise = 0
    if edges[0]:
        f, n_noise = weld_noise_at_open_edges(mesh.vertices, f, open_v)
        if n_noise:
            more = _degenerate_mask(f)
            f = f[~more]
            degen = np.concatenate([degen, more])
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
                                 removed_duplicate=n_dup, flipped=flipped,
                                 welded_noise=n_noise)
    return cleaned, report
