"""Mesh topology: exact vertex welding, edges and their facets, duplicate faces, facet
measures, fan triangulation (compiled with numba; no file formats here).

Welding: STL stores every facet corner separately; corners are merged into shared
vertices. Exact welding (default) merges corners whose coordinates are bit-identical
(``-0.0 == 0.0``), with a hash table compiled by numba. The thesis' *inexact* option
(paper Table 1) merges vertices closer than ``tolerance`` (mm): after the exact weld, all
vertex pairs within the tolerance are found with a k-d tree (scipy ``cKDTree``) and merged
transitively (connected components), so a chain of close vertices collapses to one vertex
even if its ends are farther apart than the tolerance; the merged vertex takes the
position of the lowest-indexed member.

:func:`edge_buckets` (facets grouped by undirected edge) also serves the slicer's facet
adjacency. May import: ``icefab.core``, ``icefab.errors``.
"""

from __future__ import annotations

import logging

import numpy as np
from numba import njit


log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- hashing


#: Buckets (half-edges or faces sharing a lowest vertex) up to this size are sorted or
#: scanned pairwise (fast for the usual valence of 6); larger ones by a merge sort, so a
#: mesh with a vertex of huge valence loads in O(m log m), not O(m^2).
_SMALL_BUCKET = 32


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
    the two vertices of one open and one non-manifold edge (-1 when there is none), and
    (nv,) bool: the vertices of the open edges.

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
    open_v = np.zeros(nv, np.bool_)
    for v in range(nv):
        s = start[v]
        e = start[v + 1]
        if e - s > _SMALL_BUCKET:  # a vertex of huge valence (e.g. thousands of copies
            # of one facet, issue 10): a merge sort keeps the whole pass O(m log m)
            perm = np.argsort(hi[s:e], kind="mergesort")
            hi[s:e] = hi[s:e][perm]
            dr[s:e] = dr[s:e][perm]
        else:
            for i in range(s + 1, e):  # insertion sort of the small bucket by upper vertex
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
                open_v[v] = True
                open_v[hi[i]] = True
            elif c > 2:
                if n_nonman == 0:
                    ex_nonman[0], ex_nonman[1] = v, hi[i]
                n_nonman += 1
            elif dsum != 0:
                n_misor += 1
            i = j
    return n_open, n_nonman, n_misor, ex_open, ex_nonman, open_v


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
        s = start[v]
        e = start[v + 1]
        if e - s > _SMALL_BUCKET:  # e.g. the fan of one OBJ face with 200 000 corners:
            # sort the bucket by (b, c), stably (faces stay in file order within a run);
            # every face of a run after its first is a duplicate
            fs = order[s:e]
            key = srt[fs, 1] * (nv + 1) + srt[fs, 2]
            perm = np.argsort(key, kind="mergesort")
            for r in range(1, e - s):
                if key[perm[r]] == key[perm[r - 1]]:
                    dup[fs[perm[r]]] = True
            continue
        for i in range(s + 1, e):
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


def polygon_triangles(vertices: np.ndarray, flat: np.ndarray, counts: np.ndarray
                      ) -> np.ndarray:
    """Triangles of polygon faces (OBJ, PLY), concatenated corner indices ``flat`` with
    ``counts`` corners each (>= 3): a fan (:func:`_fan`) for every convex polygon, ear
    clipping (``manifold3d.triangulate``, in the polygon's plane) for a concave one, whose
    fan lays triangles outside it (a tester's concave n-gons came out as overlapping
    shells, and every layer was 'made as the union of their contours'). Polygon order
    kept; indices out of range, or polygons without an area, are left to the fan (the
    loaders' checks name them).

    vertices: (n, 3) float64 mm. Returns (sum(counts - 2), 3) int64.
    """
    tris = _fan(flat, counts)
    big = np.flatnonzero(counts > 3)
    if not len(big) or len(flat) == 0 or flat.min() < 0 or flat.max() >= len(vertices):
        return tris
    starts = np.cumsum(counts) - counts
    # the corners of the polygons with more than 3, each with its neighbours in its ring
    c = counts[big]
    owner = np.repeat(np.arange(len(big)), c)
    k = np.arange(int(c.sum())) - np.repeat(np.cumsum(c) - c, c)
    base = np.repeat(starts[big], c)
    at = vertices[flat[base + k]]
    nxt = vertices[flat[base + (k + 1) % np.repeat(c, c)]]
    prv = vertices[flat[base + (k - 1) % np.repeat(c, c)]]
    # Newell's normal of each polygon, then the turn at each corner against it
    normal = np.zeros((len(big), 3))
    np.add.at(normal, owner, np.cross(at, nxt))
    turn = np.einsum("ij,ij->i", np.cross(at - prv, nxt - at), normal[owner])
    size = np.linalg.norm(normal, axis=1)
    scale = np.maximum.reduceat(np.abs(turn), np.cumsum(c) - c)
    concave = np.zeros(len(big), bool)
    np.logical_or.at(concave, owner, turn < -1e-9 * scale[owner])
    concave &= size > 0
    if not concave.any():
        return tris
    import manifold3d

    tstart = np.cumsum(counts - 2) - (counts - 2)
    for j in np.flatnonzero(concave):
        p = big[j]
        idx = flat[starts[p]:starts[p] + counts[p]]
        pts = vertices[idx]
        n = normal[j] / size[j]
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        local = np.asarray(manifold3d.triangulate([np.column_stack([pts @ u, pts @ v])]))
        if local.shape == (counts[p] - 2, 3):   # a simple polygon: its ears
            tris[tstart[p]:tstart[p] + counts[p] - 2] = idx[local]
    return tris


# --------------------------------------------------------------------------- shells

#: Shells (connected sets of faces) looked at by :func:`nested_same_way`, the largest
#: first: a mesh of thousands of loose parts is not searched pair by pair.
NESTED_SHELLS_LOOKED_AT = 64
#: Points of a shell tested inside another: face centres first (a box bridging a U's
#: arms has its corners inside them and its middle outside), then corners.
NESTED_TEST_POINTS = 6
#: Shells named at most (the slice summary shows three).
NESTED_NAMED = 3
#: Face-and-point evaluations :func:`nested_same_way` spends at most (a few seconds): 64
#: small shells inside one of 1.3 M facets took over 150 s (a tester's).
NESTED_WORK = 2e7


def winding_number(point: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> float:
    """How many times the faces wind around ``point`` (mm): their solid angles summed over
    4 pi (Van Oosterom and Strackee's formula), +1 inside a closed outward surface, -1
    inside an inward one, 0 outside."""
    return _winding(point, vertices[faces])


def _winding(point: np.ndarray, tri: np.ndarray) -> float:
    """:func:`winding_number` of the triangles ``tri`` (m, 3, 3), their corners gathered."""
    a, b, c = (tri[:, i] - point for i in range(3))
    la, lb, lc = (np.sqrt(np.sum(x * x, axis=1)) for x in (a, b, c))
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    div = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc
           + np.einsum("ij,ij->i", b, c) * la + np.einsum("ij,ij->i", c, a) * lb)
    return float(2.0 * np.arctan2(det, div).sum() / (4.0 * np.pi))


def nested_same_way(vertices: np.ndarray, faces: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Shells that lie inside another shell and face the same way: (its face count, one of
    its points) for each, at most :data:`NESTED_NAMED`. Either a cavity whose facets are
    wound inside out or a solid inside a solid; both slice as solid (the union of the
    shells), which hollows nothing: a tester's hollow part with its cavity inside out
    came out solid, said only as "contours ran against the facet orientation". A shell's
    way is the sign of its volume; inside, a box within the other's and
    :data:`NESTED_TEST_POINTS` of its points at a winding number of one half or more.
    Gives up quietly after :data:`NESTED_WORK` evaluations (a note, not a check)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nv = len(vertices)
    if len(faces) < 8:
        return []
    graph = coo_matrix((np.ones(2 * len(faces), np.int8),
                        (np.concatenate([faces[:, 0], faces[:, 1]]),
                         np.concatenate([faces[:, 1], faces[:, 2]]))), shape=(nv, nv))
    n, label = connected_components(graph, directed=False)
    if n < 2:
        return []
    shell = label[faces[:, 0]]
    order = np.argsort(shell, kind="stable")
    by_shell = np.split(faces[order], np.cumsum(np.bincount(shell, minlength=n))[:-1])
    size = np.array([len(f) for f in by_shell])
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    volume = np.bincount(shell, weights=np.einsum("ij,ij->i", a, np.cross(b, c)),
                         minlength=n) / 6.0
    looked = [int(s) for s in np.argsort(-size, kind="stable")[:NESTED_SHELLS_LOOKED_AT]
              if size[s] >= 4 and volume[s] != 0.0]
    lo = {s: vertices[by_shell[s]].reshape(-1, 3).min(axis=0) for s in looked}
    hi = {s: vertices[by_shell[s]].reshape(-1, 3).max(axis=0) for s in looked}
    found: list[tuple[int, np.ndarray]] = []
    work = 0.0
    for i in looked:
        mine = by_shell[i]
        pick = mine[np.linspace(0, len(mine) - 1, NESTED_TEST_POINTS // 2).astype(np.int64)]
        points = np.concatenate([vertices[pick].mean(axis=1), vertices[pick[:, 0]]])
        for j in looked:
            if j == i or np.sign(volume[j]) != np.sign(volume[i]) \
                    or (lo[i] < lo[j]).any() or (hi[i] > hi[j]).any():
                continue
            tri = vertices[by_shell[j]]
            inside = True
            for p in points:              # the first point outside ends it
                work += len(tri)
                if abs(_winding(p, tri)) < 0.5:
                    inside = False
                    break
            if inside:
                found.append((int(size[i]), points[-1].copy()))
                break
            if work > NESTED_WORK:
                return found
        if len(found) == NESTED_NAMED or work > NESTED_WORK:
            break
    return found
