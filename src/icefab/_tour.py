"""Shorter travel between a layer's paths: 2-opt on the nearest-neighbour order (numba).

The paths of one set (one material and role of a layer) are visited in some order, each
entered at a point and left at a point: an open path at either end (entered at one end,
left at the other), a closed path at one of its candidate vertices (left where it was
entered). The travel of an order is the sum of the straight moves from the start to the
first entry and from each exit to the next entry; the tour ends at the last exit.

:func:`improve` takes the nearest-neighbour order (:func:`icefab.paths.order_nearest`) and
alternates two local moves until neither shortens the travel (or ``max_rounds``):

* **2-opt**: reverse a run of consecutive paths; each open path in it is then run the
  other way, each closed path keeps its vertex. Only the two moves at the run's ends
  change: the moves inside it are the same segments walked backwards.
* **closed-path vertex**: each closed path takes the candidate vertex that makes the move
  in plus the move out shortest.

Both only ever shorten the travel, so the result is never longer than the
nearest-neighbour order (the usual bar for tour improvement; cf. Lin and Kernighan's
family of k-opt moves, of which 2-opt is the simplest).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numba import njit

from icefab.geometry import _turn_mask


@njit(cache=True, error_model="numpy")
def _dist(a0: float, a1: float, b0: float, b1: float) -> float:
    return np.sqrt((a0 - b0) ** 2 + (a1 - b1) ** 2)


@njit(cache=True, error_model="numpy")
def entry_candidates(pts: np.ndarray, starts: np.ndarray, closed: np.ndarray,
                     cos_limit: float, use_corners: bool, max_c: int
                     ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Candidate entry vertices of paths packed as ``pts (v, 2)`` with path ``r`` at rows
    ``starts[r]:starts[r + 1]``: an open path's first and last point; a closed path's
    corners (vertices whose segments turn by more than the angle of ``cos_limit``, the
    closing segment included, repeated points never turning; only with ``use_corners``
    and at least 3 points) when it has any, else all its vertices; at most ``max_c`` of
    them, evenly spread as ``idx[np.linspace(0, len(idx) - 1, max_c).astype(int)]``.
    Returns (vertex index within its path (m,) int64, each path's rows (n + 1,) int64)."""
    n = len(starts) - 1
    bound = 0
    longest = 0
    for r in range(n):
        k = starts[r + 1] - starts[r]
        bound += 2 if not closed[r] else min(k, max_c)
        longest = max(longest, k)
    index = np.empty(bound, dtype=np.int64)
    rows = np.zeros(n + 1, dtype=np.int64)
    buf = np.empty(longest, dtype=np.int64)
    m = 0
    for r in range(n):
        a = starts[r]
        k = starts[r + 1] - a
        if not closed[r]:
            index[m] = 0
            index[m + 1] = k - 1
            m += 2
            rows[r + 1] = m
            continue
        c = 0
        if use_corners and k >= 3:   # geometry.corner_vertices' test
            turns = _turn_mask(pts[a:a + k], cos_limit)
            for i in range(k):
                if turns[i]:
                    buf[c] = i
                    c += 1
        if c == 0:
            for i in range(k):
                buf[i] = i
            c = k
        if c <= max_c:
            for j in range(c):
                index[m + j] = buf[j]
            m += c
        else:
            step = (c - 1) / (max_c - 1)
            for j in range(max_c - 1):
                index[m + j] = buf[int(j * step)]
            index[m + max_c - 1] = buf[c - 1]
            m += max_c
        rows[r + 1] = m
    return index[:m].copy(), rows


@njit(cache=True, error_model="numpy")
def nearest_order(P: np.ndarray, owner: np.ndarray, bounds: np.ndarray, closed: np.ndarray,
                  sx: float, sy: float) -> np.ndarray:
    """Nearest-neighbour order of paths given by their candidate entry points.

    P (m, 2): every path's candidate entries (a closed path's candidate vertices, an open
    path's first and last point), path i's being rows ``bounds[i]:bounds[i + 1]``;
    owner (m,): the path of each row. From (sx, sy), repeatedly the nearest candidate of a
    path not yet visited (the first one on a tie); leaving a closed path where it was
    entered, an open one at its other end. Returns (n,) int64: the chosen row per step.
    """
    m = P.shape[0]
    n = bounds.shape[0] - 1
    alive = np.ones(m, dtype=np.bool_)
    out = np.empty(n, dtype=np.int64)
    cx, cy = sx, sy
    for t in range(n):
        best = np.inf
        kb = -1
        for k in range(m):
            if alive[k]:
                dx = P[k, 0] - cx
                dy = P[k, 1] - cy
                d = dx * dx + dy * dy
                if d < best:
                    best = d
                    kb = k
        i = owner[kb]
        out[t] = kb
        for k in range(bounds[i], bounds[i + 1]):
            alive[k] = False
        if closed[i]:
            cx, cy = P[kb, 0], P[kb, 1]
        else:   # the other end
            o = bounds[i] + 1 if kb == bounds[i] else bounds[i]
            cx, cy = P[o, 0], P[o, 1]
    return out


@njit(cache=True, error_model="numpy")
def _two_opt(en: np.ndarray, ex: np.ndarray, perm: np.ndarray, flip: np.ndarray,
             sx: float, sy: float, max_passes: int) -> bool:
    """2-opt passes in place over entries ``en`` / exits ``ex`` (n, 2) in visiting order;
    ``perm`` (which path), ``flip`` (an open path run backwards) follow the moves.
    Returns whether anything changed."""
    n = en.shape[0]
    changed = False
    for _ in range(max_passes):
        improved = False
        for i in range(n - 1):
            if i == 0:
                px, py = sx, sy
            else:
                px, py = ex[i - 1, 0], ex[i - 1, 1]
            d_in = _dist(px, py, en[i, 0], en[i, 1])
            for j in range(i + 1, n):
                before = d_in
                after = _dist(px, py, ex[j, 0], ex[j, 1])
                if j + 1 < n:
                    before += _dist(ex[j, 0], ex[j, 1], en[j + 1, 0], en[j + 1, 1])
                    after += _dist(en[i, 0], en[i, 1], en[j + 1, 0], en[j + 1, 1])
                if after < before - 1e-9:
                    # reverse i..j: order reversed, each path's entry and exit swapped
                    a, b = i, j
                    while a < b:
                        for c in range(2):
                            ea, xa = en[a, c], ex[a, c]
                            en[a, c] = ex[b, c]
                            ex[a, c] = en[b, c]
                            en[b, c] = xa
                            ex[b, c] = ea
                        tp = perm[a]
                        perm[a] = perm[b]
                        perm[b] = tp
                        tf = flip[a]
                        flip[a] = not flip[b]
                        flip[b] = not tf
                        a += 1
                        b -= 1
                    if a == b:
                        for c in range(2):
                            t0 = en[a, c]
                            en[a, c] = ex[a, c]
                            ex[a, c] = t0
                        flip[a] = not flip[a]
                    improved = True
                    changed = True
                    d_in = _dist(px, py, en[i, 0], en[i, 1])
        if not improved:
            break
    return changed


@njit(cache=True, error_model="numpy")
def _closed_vertices(en: np.ndarray, ex: np.ndarray, perm: np.ndarray, closed: np.ndarray,
                     cand: np.ndarray, cand_start: np.ndarray, choice: np.ndarray,
                     sx: float, sy: float) -> bool:
    """Each closed path (in visiting order) takes its candidate vertex that minimises
    move in + move out; ``choice[path]`` is its index into ``cand``. In place."""
    n = en.shape[0]
    changed = False
    for k in range(n):
        p = perm[k]
        if not closed[p]:
            continue
        if k == 0:
            px, py = sx, sy
        else:
            px, py = ex[k - 1, 0], ex[k - 1, 1]
        best = _dist(px, py, en[k, 0], en[k, 1])
        if k + 1 < n:
            best += _dist(ex[k, 0], ex[k, 1], en[k + 1, 0], en[k + 1, 1])
        for q in range(cand_start[p], cand_start[p + 1]):
            d = _dist(px, py, cand[q, 0], cand[q, 1])
            if k + 1 < n:
                d += _dist(cand[q, 0], cand[q, 1], en[k + 1, 0], en[k + 1, 1])
            if d < best - 1e-9:
                best = d
                choice[p] = q
                en[k, 0] = cand[q, 0]
                en[k, 1] = cand[q, 1]
                ex[k, 0] = cand[q, 0]
                ex[k, 1] = cand[q, 1]
                changed = True
    return changed


def entry_points(items: Sequence[tuple], index: np.ndarray, rows: np.ndarray
                 ) -> np.ndarray:
    """(m, 2) float64 mm: the points of ``items`` (``(points (k, 2), closed, ...)``) at
    their candidate entries ``index[rows[i]:rows[i + 1]]`` (:func:`entry_candidates`)."""
    owner = np.repeat(np.arange(len(items)), np.diff(rows))
    first = np.concatenate([[0], np.cumsum([len(it[0]) for it in items])]).astype(np.int64)
    pts = np.concatenate([it[0] for it in items]).astype(np.float64).reshape(-1, 2)
    return pts[first[owner] + index]


def travel_length(items, start) -> float:
    """Travel of visiting ``items`` ((points, closed, ...) as entered: a closed path at
    its first point, an open path from first to last point) in order from ``start``."""
    cur = np.asarray(start, dtype=np.float64)
    total = 0.0
    for it in items:
        pts = it[0]
        total += float(np.hypot(*(pts[0] - cur)))
        cur = pts[0] if it[1] else pts[-1]
    return total


def moved(item: tuple, roll: int = 0, flip: bool = False) -> tuple:
    """An ordering item ``(points (k, 2), closed, width, ...)`` entered at vertex ``roll``
    (a closed path, rotated to start there) or run backwards (``flip``, an open path); a
    width given per point ((k,) array: a variable-width path) moves with its points."""
    pts, closed, *rest = item
    per_point = bool(rest) and isinstance(rest[0], np.ndarray)
    if roll:
        # np.roll's result, without its general-axis overhead (a layer rotates thousands)
        pts = np.concatenate((pts[roll:], pts[:roll]))
        if per_point:
            rest[0] = np.concatenate((rest[0][roll:], rest[0][:roll]))
    if flip:
        pts = pts[::-1]
        if per_point:
            rest[0] = rest[0][::-1]
    return (pts, closed, *rest)


def improve(items: list[tuple], start, candidates: tuple[np.ndarray, np.ndarray],
            max_rounds: int = 4, max_passes: int = 50) -> tuple[list[tuple], np.ndarray]:
    """Shorten the travel of an order (module docstring).

    items: the order to improve, each ``(points (k, 2) mm, closed, ...)`` as entered (a
    closed path starts at its entry vertex); candidates: ``(index (m,), rows (n + 1,))``,
    the vertex indices of item i that may become its entry at ``index[rows[i]:rows[i +
    1]]`` (closed paths; ignored for open ones), as :func:`entry_candidates` gives them.
    Returns the new order (closed paths rotated, open paths reversed as run) and the final
    position.
    """
    start = np.asarray(start, dtype=np.float64)
    n = len(items)
    if n < 2:
        end = start if not items else (items[0][0][0] if items[0][1] else items[0][0][-1])
        return list(items), np.asarray(end, dtype=np.float64)
    closed = np.array([bool(it[1]) for it in items])
    en = np.array([it[0][0] for it in items], dtype=np.float64)
    ex = np.array([it[0][0] if it[1] else it[0][-1] for it in items], dtype=np.float64)
    # every item's rows (_closed_vertices looks at the closed ones' only)
    cand_idx, cand_start = (np.asarray(a, dtype=np.int64) for a in candidates)
    cand = entry_points(items, cand_idx, cand_start)
    choice = np.full(n, -1, dtype=np.int64)   # -1: the vertex it was entered at
    perm = np.arange(n, dtype=np.int64)
    flip = np.zeros(n, dtype=np.bool_)
    sx, sy = float(start[0]), float(start[1])
    for _ in range(max_rounds):
        a = _two_opt(en, ex, perm, flip, sx, sy, max_passes)
        b = _closed_vertices(en, ex, perm, closed, cand, cand_start, choice, sx, sy)
        if not (a or b):
            break
    out = []
    for k in range(n):
        i = int(perm[k])
        if closed[i]:
            j = int(cand_idx[choice[i]]) if choice[i] >= 0 else 0
            out.append(moved(items[i], roll=j))
        else:
            out.append(moved(items[i], flip=bool(flip[k])))
    last = out[-1]
    return out, np.asarray(last[0][0] if last[1] else last[0][-1], dtype=np.float64)
