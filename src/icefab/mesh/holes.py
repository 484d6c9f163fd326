"""Closing the holes of an open surface in 3D, once, before slicing (issue 11).

A scan is rarely closed: it is open at its base, where the scanner could not see, and has
holes of all sizes. The slicer used to close each layer's open chains with straight chords,
layer by layer (thesis 3.2 keeps only closed contours; RPSLICE's SEGMERGE leaves open ones
to the user). Chords chosen per layer do not agree from one layer to the next and can cut
across the part (a 156 mm "gap" closed across a beetle scan). Here every hole is closed
once, as a surface -- what PrusaSlicer/admesh do when they "fill holes" -- so every layer
through the hole sees the same patch and the per-layer chord is left as a bounded last
resort (``slicing.max_gap_mm``, ``slicing.open_contours``).

Method, chosen by benchmark (BENCHMARKS.md, "3D hole closing"): the boundary edges (used
by exactly one face) are walked into loops; each loop is projected on its least-squares
plane (SVD of its points) and triangulated there by ``manifold3d.triangulate`` (the
maintained triangulator of the Manifold library, already a dependency), which always
returns triangles that use exactly the loop's edges in the loop's direction -- a
topologically valid patch even when the projection of a warped loop crosses itself. The
patch's triangles reference the loop's own vertices: no vertex is added or moved, and the
faces of the input come first, unchanged. The patch faces traverse each boundary edge
opposite to the face already there, so orientation stays consistent.

Peers measured on the 1.1 M-facet open bunny: ``pymeshfix`` (MeshFix)
``PyTMesh.fill_small_boundaries`` closes the same holes (refined, smooth patches) but takes
~30 s, most of it loading the mesh, prints progress to the console and renumbers the
vertices; ``MeshFix.repair`` also removes self-intersections (changing the surface) and
takes ~140 s; ``trimesh``'s ``fill_holes`` closes only three- and four-edge holes (the
bunny stays open).

Degenerate cases, decided here: a boundary vertex with several outgoing boundary edges
(two holes touching at a vertex) is left by the first unused edge, so each hole is still
walked as one loop; a walk that cannot return to its start (edges of inconsistent
orientation) is not closed and is reported (``HoleReport.unclosed_edges``): the slicer's
per-layer rule then applies there. Loops of fewer than three edges cannot be capped and
count as unclosed too.

May import: ``icefab.core``, ``icefab.mesh.topology``, ``icefab.mesh.repair``, numpy,
manifold3d.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from icefab.core import Mesh
from icefab.mesh.repair import check_mesh, point_text
from icefab.mesh.topology import edge_buckets

if TYPE_CHECKING:
    from icefab.config import Job

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Hole:
    """One closed hole: its boundary ``edges`` (count), ``perimeter_mm``, ``span_mm`` (the
    largest distance between two of its boundary vertices), ``centre_mm`` (x, y, z: the mean
    of its boundary vertices, in the coordinates of the mesh given -- the build's, mm, when
    called after placement), ``warp_mm`` (largest distance of a boundary vertex from the
    loop's least-squares plane) and ``faces`` added."""

    edges: int
    perimeter_mm: float
    span_mm: float
    centre_mm: tuple[float, float, float]
    warp_mm: float
    faces: int


@dataclass(frozen=True)
class HoleReport:
    """What :func:`close_holes` did: the holes closed (largest first) and the boundary
    edges left open (walks that could not close), with one of them located (mm)."""

    holes: tuple[Hole, ...] = ()
    unclosed_edges: int = 0
    unclosed_at: tuple[float, float, float] | None = None
    faces_added: int = field(default=0)

    def warnings(self, name: str = "mesh") -> list[str]:
        """One line per finding (counts, sizes and positions in mm)."""
        out: list[str] = []
        if self.holes:
            big = self.holes[0]
            sizes = ", ".join(f"{h.span_mm:.3g}" for h in self.holes[:8])
            more = f" and {len(self.holes) - 8} more" if len(self.holes) > 8 else ""
            out.append(f"{name}: {len(self.holes)} holes closed in 3D before slicing "
                       f"({self.faces_added} faces added; spans {sizes}{more} mm; the "
                       f"largest centred at {point_text(big.centre_mm)} mm)")
        if self.unclosed_edges:
            where = ("" if self.unclosed_at is None else
                     f" e.g. at {point_text(self.unclosed_at)} mm")
            out.append(f"{name}: {self.unclosed_edges} open edges could not be closed in 3D "
                       f"(inconsistent orientation){where}; the slicer closes those "
                       "contours per layer within slicing.max_gap_mm")
        return out


@njit(cache=True)
def _boundary_half_edges(faces: np.ndarray, nv: int) -> np.ndarray:  # pragma: no cover
    """Ids ``3 f + k`` of the half-edges whose undirected edge no other face uses, O(m):
    the vertex buckets of :func:`icefab.mesh.topology.edge_buckets`, each sorted by upper vertex."""
    start, half, hi = edge_buckets(faces, nv)
    out = np.empty(half.size, np.int64)
    n = 0
    for v in range(nv):
        s = start[v]
        e = start[v + 1]
        for i in range(s + 1, e):  # insertion sort of the (small) bucket
            x = hi[i]
            h = half[i]
            j = i - 1
            while j >= s and hi[j] > x:
                hi[j + 1] = hi[j]
                half[j + 1] = half[j]
                j -= 1
            hi[j + 1] = x
            half[j + 1] = h
        i = s
        while i < e:
            j = i + 1
            while j < e and hi[j] == hi[i]:
                j += 1
            if j - i == 1:
                out[n] = half[i]
                n += 1
            i = j
    return out[:n]


def boundary_edges(faces: np.ndarray, n_vertices: int | None = None) -> np.ndarray:
    """(b, 2) int64: the directed boundary edges (a, b) as their one face runs them.

    faces: (m, 3) int vertex indices; n_vertices: at least ``faces.max() + 1``. An edge is
    a boundary edge when exactly one face uses it (in either direction); edges of three or
    more faces (non-manifold) are not. Faces with a repeated vertex are ignored.
    """
    f = np.ascontiguousarray(faces, dtype=np.int64)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(f) == 0:
        return np.zeros((0, 2), np.int64)
    nv = int(f.max()) + 1 if n_vertices is None else int(n_vertices)
    h = np.sort(_boundary_half_edges(np.ascontiguousarray(f), nv))
    fi, k = h // 3, h % 3
    return np.stack([f[fi, k], f[fi, (k + 1) % 3]], axis=1)


def _loops(edges: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """Walk the cap direction of boundary ``edges`` (a, b) into loops.

    The cap runs every boundary edge backwards (b -> a). Returns the loops (vertex index
    arrays, cap order) and a mask of the edges not on any closed loop.
    """
    nxt: dict[int, list[int]] = {}
    for k, b in enumerate(edges[:, 1].tolist()):
        nxt.setdefault(b, []).append(k)           # cap edge k: b -> a
    used = np.zeros(len(edges), bool)
    open_mask = np.zeros(len(edges), bool)
    loops: list[np.ndarray] = []
    a_of = edges[:, 0].tolist()
    b_of = edges[:, 1].tolist()
    for k0 in range(len(edges)):
        if used[k0]:
            continue
        start = b_of[k0]
        path_edges = [k0]
        used[k0] = True
        cur = a_of[k0]
        ok = True
        while cur != start:
            cand = nxt.get(cur)
            while cand and used[cand[-1]]:
                cand.pop()
            if not cand:
                ok = False
                break
            k = cand.pop()
            used[k] = True
            path_edges.append(k)
            cur = a_of[k]
        if ok and len(path_edges) >= 3:
            loops.append(np.array([b_of[k] for k in path_edges], dtype=np.int64))
        else:                                   # left open (never walked again), reported
            open_mask[path_edges] = True
    return loops, open_mask


def _cap(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Triangles (t, 3) (indices into ``points``) spanning one loop, and its warp (mm).

    points: (k, 3) float64 mm, the loop in cap order. Projected on the least-squares
    plane, wound counter-clockwise there (by mirroring the projection, never by reordering
    the points) and triangulated by manifold3d: the triangles run the loop's edges in the
    loop's direction.
    """
    import manifold3d

    k = len(points)
    if k == 3:
        return np.array([[0, 1, 2]], np.int64), 0.0
    c = points.mean(axis=0)
    d = points - c
    _, _, vt = np.linalg.svd(d, full_matrices=False)
    uv = d @ vt[:2].T
    warp = float(np.abs(d @ vt[2]).max())
    x, y = uv[:, 0], uv[:, 1]
    area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    if area2 < 0:
        uv[:, 1] = -uv[:, 1]
    tri = np.asarray(manifold3d.triangulate([np.ascontiguousarray(uv)]), dtype=np.int64)
    return tri.reshape(-1, 3), warp


def close_holes(mesh: Mesh) -> tuple[Mesh, HoleReport]:
    """Close every hole of ``mesh`` with a triangulated patch (module docstring).

    mesh: vertices (n, 3) float64 mm, faces (m, 3) int. Returns the mesh with the patch
    faces appended (vertices unchanged; ``faces[:m]`` are the input's) and the report.
    A closed mesh is returned as it is.
    """
    faces = np.asarray(mesh.faces, dtype=np.int64)
    edges = boundary_edges(faces, len(mesh.vertices))
    if len(edges) == 0:
        return mesh, HoleReport()
    v = np.asarray(mesh.vertices, dtype=np.float64)
    loops, open_mask = _loops(edges)
    new: list[np.ndarray] = []
    holes: list[Hole] = []
    for loop in loops:
        p = v[loop]
        tri, warp = _cap(p)
        new.append(loop[tri])
        seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
        if len(p) <= 2000:
            span = float(np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)).max())
        else:                                   # bounded work: the extent's diagonal
            span = float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))
        holes.append(Hole(edges=len(loop), perimeter_mm=float(seg.sum()), span_mm=span,
                          centre_mm=tuple(float(t) for t in p.mean(axis=0)),  # type: ignore
                          warp_mm=warp, faces=len(tri)))
    holes.sort(key=lambda h: -h.span_mm)
    added = np.concatenate(new) if new else np.zeros((0, 3), np.int64)
    n_open = int(open_mask.sum())
    at = None
    if n_open:
        e = edges[np.flatnonzero(open_mask)[0]]
        at = tuple(float(t) for t in 0.5 * (v[e[0]] + v[e[1]]))
    report = HoleReport(holes=tuple(holes), unclosed_edges=n_open, unclosed_at=at,  # type: ignore
                        faces_added=len(added))
    out = dataclasses.replace(mesh, faces=np.ascontiguousarray(
        np.concatenate([faces, added]).astype(np.int64)))
    for w in report.warnings(mesh.name or "mesh"):
        log.info("%s", w)
    return out, report


#: The mesh loader's located findings (``icefab.mesh.MeshReport.warnings``), given in the
#: file's coordinates; :func:`prepare_closed` replaces them by findings in the build's.
_LOCATED = ("open edges (the surface has holes)", "non-manifold edges (shared by more")


def prepare_closed(mesh: Mesh, job: "Job") -> Mesh:
    """The build mesh as the slicer gets it: placed ``mesh`` with its holes closed.

    mesh: the merged parts after ``icefab.mesh.transform`` (vertices in the build's
    coordinates, mm). With ``job.parts.close_holes`` the holes are closed
    (:func:`close_holes`). Either way, the loader's open and non-manifold edge findings,
    located in the file's coordinates, are replaced by the same findings located in the
    build's coordinates (after scale, rotation and translation), mm.
    """
    name = mesh.name or "mesh"
    kept = tuple(w for w in mesh.warnings if not any(k in w for k in _LOCATED))
    found: list[str] = []
    if job.parts.close_holes:
        mesh, holes = close_holes(mesh)
        found += holes.warnings(name)
    if len(kept) != len(mesh.warnings) or found:
        report = check_mesh(mesh)
        found += [w for w in report.warnings() if any(k in w for k in _LOCATED)]
    # check_mesh locates in the coordinates it is given: these are the build's
    found = [w.replace(") in the file's coordinates", ") mm", 1)
             .replace(") mm", ") mm (build coordinates)", 1) if "e.g. at (" in w else w
             for w in found]
    return dataclasses.replace(mesh, warnings=kept + tuple(found))
