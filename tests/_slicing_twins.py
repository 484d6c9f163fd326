"""Numpy twins of the slicer's compiled kernels, used only to test them: the sorting
facet adjacency and the vectorised facet-plane expansion (thesis 3.2 INTERSECTFACET),
written the straightforward way; the tests demand bit-identical results."""

from __future__ import annotations

import numpy as np

from icefab.slicing import _ramp, _Segments


def _facet_adjacency_numpy(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Neighbour across every facet edge (sorting version; see :func:`_facet_adjacency`).

    faces: (m, 3) int64. Local edge j of a facet joins its corners j and (j+1) % 3.
    Returns (m, 3) int64: ``3*g + j'`` (facet g, its local edge j') of the facet across
    that edge, -1 for a boundary edge (one facet), -2 for a non-manifold edge (> 2 facets).
    """
    m = len(faces)
    a = faces
    b = np.roll(faces, -1, axis=1)
    lo = np.minimum(a, b).ravel()
    hi = np.maximum(a, b).ravel()
    key = lo.astype(np.int64) * np.int64(n_vertices) + hi
    order = np.argsort(key, kind="stable")
    ks = key[order]
    nbr = np.full(3 * m, -1, dtype=np.int64)
    if len(ks) == 0:
        return nbr.reshape(m, 3)
    start = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    count = np.diff(np.r_[start, len(ks)])
    two = start[count == 2]
    h0, h1 = order[two], order[two + 1]
    nbr[h0] = h1
    nbr[h1] = h0
    many = count > 2
    if many.any():
        idx = np.repeat(start[many], count[many]) + _ramp(count[many])
        nbr[order[idx]] = -2
    return nbr.reshape(m, 3)


def _intersect_numpy(vertices: np.ndarray, faces: np.ndarray, fz: np.ndarray,
                     q: np.ndarray, lo: np.ndarray, hi: np.ndarray, k0: int, k1: int,
                     nbr: np.ndarray) -> _Segments:
    """Cut every facet with the planes k0..k1-1 (thesis 3.2 INTERSECTFACET, Ossino eq. 1).

    vertices (n, 3) float64 mm; faces (m, 3) int64; fz (m, 3) float64 corner heights;
    q (L,) float64 classification heights; lo/hi (m,) int64 first plane above the lowest
    corner / first plane above the highest corner (facet f is cut by planes lo..hi-1).
    """
    a = np.clip(lo, k0, k1)
    b = np.clip(hi, k0, k1)
    cnt = b - a
    fsel = np.flatnonzero(cnt > 0)
    cnt = cnt[fsel]
    seg_f = np.repeat(fsel, cnt)
    seg_k = np.repeat(a[fsel], cnt) + _ramp(cnt)
    n_seg = len(seg_f)
    qs = q[seg_k]
    zc = fz[seg_f]                                   # (S, 3)
    above = zc >= qs[:, None]
    n_above = above.sum(axis=1)
    lone = above ^ (n_above == 2)[:, None]           # the vertex alone on its side
    i = np.argmax(lone, axis=1).astype(np.int8)
    ip = (i + 2) % 3                                  # edge (i-1, i) has local index i-1
    # Segment direction follows the facet orientation (material on the left, thesis 3.2):
    # a lone vertex above runs from edge (i, i+1) to edge (i-1, i); below: the reverse.
    lone_above = n_above == 1
    e_start = np.where(lone_above, i, ip).astype(np.int8)
    e_end = np.where(lone_above, ip, i).astype(np.int8)
    edge = np.stack([e_start, e_end], axis=1)         # (S, 2)
    # Crossing points, computed from the edge's corners in vertex-index order so that
    # both facets sharing an edge produce bit-identical points.
    fe = np.repeat(seg_f, 2)
    le = edge.ravel().astype(np.int64)
    va = faces[fe, le]
    vb = faces[fe, (le + 1) % 3]
    v0 = np.minimum(va, vb)
    v1 = np.maximum(va, vb)
    p0 = vertices[v0]
    p1 = vertices[v1]
    qe = np.repeat(qs, 2)
    t = (qe - p0[:, 2]) / (p1[:, 2] - p0[:, 2])
    pts = p0[:, :2] + t[:, None] * (p1[:, :2] - p0[:, :2])
    # Partner of every end: the same layer's segment in the facet across the edge.
    nb = nbr[fe, le]
    partner = np.full(2 * n_seg, -1, dtype=np.int64)
    ok = nb >= 0
    if ok.any():
        g = nb[ok] // 3
        jg = nb[ok] % 3
        kk = np.repeat(seg_k, 2)[ok]
        base = np.zeros(len(lo), dtype=np.int64)
        base[fsel] = np.cumsum(cnt) - cnt
        inside = (kk >= a[g]) & (kk < b[g])
        s2 = base[g] + kk - a[g]
        s2 = np.where(inside, s2, 0)
        which = (edge[s2, 1] == jg).astype(np.int64)
        good = inside & ((edge[s2, 0] == jg) | (edge[s2, 1] == jg))
        idx = np.flatnonzero(ok)
        partner[idx[good]] = 2 * s2[good] + which[good]
    return _Segments(layer=seg_k, facet=seg_f, edge=edge, points=pts, partner=partner)
