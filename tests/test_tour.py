"""Travel between a layer's paths: 2-opt after nearest neighbour (icefab._tour).

Invariants (hypothesis): the improved order visits the same paths (a closed path only
rotated to another start vertex among its candidates, an open one possibly reversed) and
its travel is never longer than the nearest-neighbour order's; on random layouts it is
clearly shorter, and never shorter than a lower bound (every path but the first is
entered from the nearest other path at best)."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from icefab._tour import improve, travel_length
from icefab.paths import _entry_candidates, _start_candidates, order_nearest


def _layout(seed: int, n: int) -> list[tuple]:
    rng = np.random.default_rng(seed)
    items = []
    for k in range(n):
        c = rng.uniform(0, 200, 2)
        if rng.random() < 0.5:
            t = np.linspace(0, 2 * np.pi, int(rng.integers(3, 90)), endpoint=False)
            r = rng.uniform(1, 5)
            items.append((c + np.column_stack([r * np.cos(t), r * np.sin(t)]), True, k))
        else:
            d = rng.normal(size=2)
            items.append((np.array([c, c + rng.uniform(1, 20) * d / np.linalg.norm(d)]),
                          False, k))
    return items


def _improved(items, start):
    nn, _ = order_nearest(items, start)
    out, end = improve(nn, start, _entry_candidates(nn))
    return nn, out, end


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 10 ** 6), st.integers(0, 60))
def test_the_same_paths_and_never_longer_than_nearest_neighbour(seed, n):
    items = _layout(seed, n)
    start = np.array([5.0, -3.0])
    nn, out, end = _improved(items, start)
    assert sorted(it[2] for it in out) == list(range(n))
    by_id = {it[2]: it for it in items}
    for pts, closed, k in out:
        orig = by_id[k][0]
        if closed:
            j = int(np.flatnonzero((orig == pts[0]).all(axis=1))[0])
            np.testing.assert_array_equal(pts, np.roll(orig, -j, axis=0))
        else:
            assert np.array_equal(pts, orig) or np.array_equal(pts, orig[::-1])
    assert travel_length(out, start) <= travel_length(nn, start) + 1e-9
    if out:
        last = out[-1]
        np.testing.assert_array_equal(end, last[0][0] if last[1] else last[0][-1])


def _lower_bound(items) -> float:
    """Every path but one is entered from another path's end or vertex, at best the
    nearest one (brute force: small layouts)."""
    ends = [it[0] if it[1] else it[0][[0, -1]] for it in items]
    near = []
    for i, a in enumerate(ends):
        near.append(min(float(np.min(np.linalg.norm(a[:, None] - b[None], axis=2)))
                        for j, b in enumerate(ends) if j != i))
    return float(sum(near) - max(near))


def test_clearly_shorter_on_a_random_layout_and_above_the_lower_bound():
    items = _layout(1, 150)
    start = np.zeros(2)
    nn, out, _ = _improved(items, start)
    a, b = travel_length(nn, start), travel_length(out, start)
    assert b < 0.93 * a, (a, b)
    assert b >= _lower_bound(items)


def _nearest_reference(items, start):
    """Nearest neighbour written plainly: every candidate entry of every unvisited path,
    the first nearest on a tie."""
    left = list(range(len(items)))
    cur = np.asarray(start, dtype=np.float64)
    out = []
    while left:
        best = None
        for i in left:
            pts, closed = items[i][0], items[i][1]
            idx = _start_candidates(pts) if closed else np.array([0, len(pts) - 1])
            for j in idx:
                d = float(((pts[j] - cur) ** 2).sum())
                if best is None or d < best[0]:
                    best = (d, i, int(j))
        _, i, j = best
        left.remove(i)
        pts, closed = items[i][0], items[i][1]
        pts = np.roll(pts, -j, axis=0) if closed else (pts[::-1] if j else pts)
        out.append(items[i][2])
        cur = pts[0] if closed else pts[-1]
    return out


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10 ** 6), st.integers(0, 40))
def test_nearest_neighbour_is_the_plain_algorithm(seed, n):
    items = _layout(seed, n)
    got, _ = order_nearest(items, np.array([1.0, 2.0]))
    assert [it[2] for it in got] == _nearest_reference(items, np.array([1.0, 2.0]))


def test_a_ring_with_corners_starts_at_one_and_stops_once_less():
    """A closed path with corners over the PATHSPLIT angle may start only at one of them
    (the robot stops there anyway: start, end and corner are one stop), one without may
    start anywhere. A square entered from beside the middle of an edge starts at a
    corner, and MTTS plans it as its 4 sides, not 5 pieces."""
    from icefab.config import Job
    from icefab.motion import plan_paths_motion
    from icefab.core import Toolpath
    job = Job()
    corner = job.motion.smooth_angle_deg
    t = np.linspace(0.0, 10.0, 21)[:-1]
    square = np.concatenate([np.c_[t, 0 * t], np.c_[10 + 0 * t, t],
                             np.c_[10 - t, 10 + 0 * t], np.c_[0 * t, 10 - t]])
    got = _start_candidates(square, corner)
    assert sorted(got.tolist()) == [0, 20, 40, 60]
    th = np.linspace(0.0, 2 * np.pi, 90, endpoint=False)
    circle = np.c_[np.cos(th), np.sin(th)] * 10.0
    assert len(_start_candidates(circle, corner)) == min(90, 64)
    assert len(_start_candidates(square)) == min(len(square), 64)  # no angle: every vertex
    (entered,), _ = order_nearest([(square, True, 0)], np.array([5.0, -1.0]), corner)
    assert tuple(entered[0][0]) in {(0.0, 0.0), (10.0, 0.0)}
    (plain,), _ = order_nearest([(square, True, 0)], np.array([5.0, -1.0]))
    assert tuple(plain[0][0]) == (5.0, 0.0)

    def pieces(pts):
        path = Toolpath(points=pts + [340.0, 0.0], closed=True, role="fill", width=3.0,
                        frame="base")
        return len(plan_paths_motion([path], job)[0].pieces)

    assert pieces(entered[0]) == 4 and pieces(plain[0]) == 5


def _plain_candidates(pts, closed, corner_deg):
    """The entry candidates written plainly (numpy over one path at a time)."""
    from icefab import geometry as geo
    from icefab.paths import MAX_START_CANDIDATES
    if not closed:
        return np.array([0, len(pts) - 1])
    idx = np.arange(len(pts))
    if corner_deg is not None:
        corners = geo.corner_vertices(pts, corner_deg)
        if len(corners):
            idx = corners
    if len(idx) <= MAX_START_CANDIDATES:
        return idx
    return idx[np.linspace(0, len(idx) - 1, MAX_START_CANDIDATES).astype(np.int64)]


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 10 ** 6), st.sampled_from([None, 10.0, 30.0, 90.0]))
def test_entry_candidates_of_a_set_are_each_paths_own(seed, corner_deg):
    """One compiled pass over a set gives every path the candidates it would get alone:
    corners or every vertex, at most 64 evenly spread, an open path's two ends; rings with
    repeated points, two points or jagged outlines of up to 300 vertices among them."""
    rng = np.random.default_rng(seed)
    items = []
    for _ in range(int(rng.integers(1, 12))):
        k = int(rng.integers(1, 300))
        pts = np.cumsum(rng.normal(size=(k, 2)), axis=0)
        if k > 3 and rng.random() < 0.3:
            pts[1] = pts[0]                                  # a repeated point
        if rng.random() < 0.3:                               # a smooth ring
            th = np.linspace(0, 2 * np.pi, k, endpoint=False)
            pts = np.c_[np.cos(th), np.sin(th)] * 20.0
        items.append((pts, bool(rng.random() < 0.7)))
    index, rows = _entry_candidates(items, corner_deg)
    assert rows[0] == 0 and rows[-1] == len(index)
    for i, (pts, closed) in enumerate(items):
        np.testing.assert_array_equal(index[rows[i]:rows[i + 1]],
                                      _plain_candidates(pts, closed, corner_deg))
