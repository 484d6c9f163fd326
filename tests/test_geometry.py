"""icefab.geometry against shapely (an independent polygon implementation) and analytic shapes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
from hypothesis import example, given, settings, strategies as st
from shapely.geometry import Polygon
from shapely.validation import explain_validity

from icefab import geometry as geo
from icefab.core import Region, signed_area

# ----------------------------------------------------------------------------- helpers


def rect(x0, y0, x1, y1):
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)


def circle(r, n=256, c=(0.0, 0.0), hole=False):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.c_[c[0] + r * np.cos(t), c[1] + r * np.sin(t)]
    return ring[::-1].copy() if hole else ring


def to_shapely(region: Region):
    """Region -> shapely (Multi)Polygon, built from the nesting tree."""
    polys = [Polygon(p[0], p[1:]) for p in region.polygons()]
    if not polys:
        return Polygon()
    # vertex-touching rings (see check_region_structure) are made valid without area change
    return shapely.union_all([p if p.is_valid else shapely.make_valid(p) for p in polys])


def check_region_structure(region: Region):
    """Orientation and parents follow the icefab convention; the polygons are valid."""
    depth = region.depth()
    for ring, d in zip(region.rings, depth):
        a = signed_area(ring)
        assert (a > 0) == (d % 2 == 0), "outer rings CCW, holes CW"
        assert len(ring) >= 3
    for p in region.polygons():
        poly = Polygon(p[0], p[1:])
        if not poly.is_valid:
            # Clipper may return pieces that touch at a vertex as one ring, or holes that
            # touch each other (GEOS: "Ring Self-intersection" / "Self-intersection"); no
            # edge crosses another, so make_valid keeps the signed area, which a crossing
            # (bow-tie) ring or overlapping holes would change.
            signed = sum(signed_area(r) for r in p)
            assert shapely.make_valid(poly).area == pytest.approx(signed, rel=1e-6, abs=1e-6), \
                explain_validity(poly)
            holes = [Polygon(h) for h in p[1:]]
            for i in range(len(holes)):
                for j in range(i + 1, len(holes)):
                    assert holes[i].intersection(holes[j]).area < 1e-4  # grid rounding


# ----------------------------------------------------------------------------- analytic


def test_region_from_rings_builds_tree_and_orientation():
    outer = rect(0, 0, 10, 10)[::-1]  # given clockwise on purpose, evenodd ignores it
    hole = rect(3, 3, 7, 7)
    island = rect(4, 4, 6, 6)
    r = geo.region_from_rings([outer, hole, island], fill="evenodd")
    assert r.area == pytest.approx(100 - 16 + 4)
    assert sorted(r.depth().tolist()) == [0, 1, 2]
    check_region_structure(r)
    # island's parent is the hole, whose parent is the outer ring
    d = r.depth()
    i_island = int(np.flatnonzero(d == 2)[0])
    i_hole = int(r.parent[i_island])
    assert d[i_hole] == 1 and d[int(r.parent[i_hole])] == 0


def test_offsets_of_square_with_hole_are_exact():
    r = geo.region_from_rings([rect(0, 0, 10, 10), rect(3, 3, 7, 7)[::-1]])
    assert r.area == pytest.approx(84)
    # miter joins keep square corners exact
    assert geo.shrink(r, 1).area == pytest.approx(8 * 8 - 6 * 6)
    assert geo.expand(r, 1).area == pytest.approx(12 * 12 - 2 * 2)
    assert geo.shrink(r, 1.6).is_empty  # walls 3 mm thick vanish
    assert geo.expand(r, 0) is r


def test_circle_offsets_match_shapely_within_filter():
    c = geo.region_from_rings([circle(20, 720)])
    for d in (0.5, 3.3, 7.0):
        # chords of the point filter cut at most filter_mm inside along the perimeter
        ours = geo.shrink(c, d)
        ref = to_shapely(c).buffer(-d, quad_segs=64)
        assert ours.area == pytest.approx(ref.area, abs=geo.FILTER_MM * ref.length)
        assert ours.area <= ref.area + 1e-6
        ours = geo.expand(c, d)
        ref = to_shapely(c).buffer(d, quad_segs=64)
        assert ours.area == pytest.approx(ref.area, abs=geo.FILTER_MM * ref.length)


def test_filter_reduces_points_of_fine_circle():
    c = geo.region_from_rings([circle(50, 5000)])
    out = geo.shrink(c, 1.0, filter_mm=0.05)
    # sagitta rule: spacing ~ sqrt(8 r eps) = 4.4 mm -> about 70 points, not 5000
    assert out.n_points < 200
    assert out.area == pytest.approx(math.pi * 49 ** 2, rel=2e-3)


def test_booleans_against_shapely():
    a = geo.region_from_rings([rect(0, 0, 10, 10)])
    b = geo.region_from_rings([circle(4, 200, c=(10, 5))])
    sa, sb = to_shapely(a), to_shapely(b)
    assert geo.union(a, b).area == pytest.approx(sa.union(sb).area, rel=1e-9)
    assert geo.difference(a, b).area == pytest.approx(sa.difference(sb).area, rel=1e-9)
    assert geo.intersection(a, b).area == pytest.approx(sa.intersection(sb).area, rel=1e-9)
    assert geo.intersection(a, Region()).is_empty
    assert geo.difference(Region(), a).is_empty


def test_opening_removes_thin_features_only():
    # a 20x20 block with a 1 mm wide, 10 mm long fin
    r = geo.union(geo.region_from_rings([rect(0, 0, 20, 20)]),
                  geo.region_from_rings([rect(20, 9.5, 30, 10.5)]))
    o = geo.opening(r, 0.75)
    assert o.area == pytest.approx(400, abs=0.5)


def test_clip_lines_and_sweep():
    r = geo.region_from_rings([rect(0, 0, 10, 10), rect(3, 3, 7, 7)[::-1]])
    pieces = geo.clip_lines([np.array([[-5.0, 5.0], [15.0, 5.0]])], r)
    lengths = sorted(np.linalg.norm(p[-1] - p[0]) for p in pieces)
    assert lengths == pytest.approx([3.0, 3.0])
    ring = rect(1, 1, 9, 9)
    s = geo.sweep([(ring, True, 2.0)])
    assert s.area == pytest.approx(10 * 10 - 6 * 6)  # band from 0 to 2 mm inside the 10 mm square
    check_region_structure(s)


# ----------------------------------------------------------------------------- property


@st.composite
def polygon_with_holes(draw):
    """A random star-shaped outer ring with up to 3 non-overlapping circular holes."""
    n = draw(st.integers(5, 40))
    radii = draw(st.lists(st.floats(8.0, 30.0), min_size=n, max_size=n))
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    outer = np.c_[np.array(radii) * np.cos(t), np.array(radii) * np.sin(t)]
    holes = []
    for k in range(draw(st.integers(0, 3))):
        ang = draw(st.floats(0, 2 * np.pi))
        rr = draw(st.floats(1.0, 3.0))
        c = (4.0 * math.cos(ang + k * 2.1), 4.0 * math.sin(ang + k * 2.1))
        if all(math.dist(c, h[0]) > h[1] + rr + 0.5 for h in holes) and math.hypot(*c) + rr < 7.5:
            holes.append((c, rr))
    rings = [outer] + [circle(rr, 24, c, hole=True) for c, rr in holes]
    return rings


@given(polygon_with_holes(), st.floats(0.1, 5.0))
def test_property_offsets_and_booleans_match_shapely(rings, d):
    r = geo.region_from_rings(rings)
    ref = Polygon(rings[0], rings[1:])
    assert ref.is_valid
    grid = 1.0 / geo.SCALE  # coordinates are rounded to Clipper's integer grid
    assert r.area == pytest.approx(ref.area, abs=grid * ref.length)
    check_region_structure(r)
    f = geo.FILTER_MM + 2 * grid
    # mitred offsets contain the round (Euclidean) offset, and no point is farther than
    # the miter limit times d from the original
    grown = geo.expand(r, d)
    check_region_structure(grown)
    g = to_shapely(grown)
    assert ref.buffer(d - f, quad_segs=16).difference(g).area < 1e-6
    assert g.difference(ref.buffer(geo.MITER_LIMIT * d + f, quad_segs=16)).area < 1e-6
    shrunk = geo.shrink(r, d)
    check_region_structure(shrunk)
    sh = to_shapely(shrunk)
    assert sh.difference(ref.buffer(-(d - f), quad_segs=16)).area < 1e-6
    inner = ref.buffer(-(d + f), join_style="mitre", mitre_limit=100)
    assert inner.difference(sh).area < 1e-6
    other = geo.region_from_rings([circle(10, 64, c=(5, 5))])
    so = to_shapely(other)
    tol = grid * (ref.length + so.length)
    assert geo.difference(r, other).area == pytest.approx(ref.difference(so).area, abs=tol)
    assert geo.union(r, other).area == pytest.approx(ref.union(so).area, abs=tol)


@given(polygon_with_holes(), st.integers(0, 2**31 - 1))
def test_property_points_inside_matches_shapely(rings, seed):
    r = geo.region_from_rings(rings)
    pts = np.random.default_rng(seed).uniform(-32, 32, size=(300, 2))
    ours = geo.points_inside(pts, r)
    poly = to_shapely(r)
    ref = shapely.contains_xy(poly, pts[:, 0], pts[:, 1])
    near = shapely.distance(poly.boundary, shapely.points(pts)) < 1e-6
    assert np.array_equal(ours[~near], ref[~near])


# ----------------------------------------------------------------------------- filter, medial


def _slivers(seed: int, count: int):
    """Thin wobbly rings (narrower than two point filters): where the chord filter, looking
    only along the ring, may cut across to the other side."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        n = int(rng.integers(5, 30))
        x = np.sort(rng.uniform(0, 3, n))
        y = 0.3 * np.sin(x * rng.uniform(0.5, 3))
        half = rng.uniform(0.0025, 0.04)
        ring = np.vstack([np.c_[x, y - half], np.c_[x[::-1], y[::-1] + half]])
        ring = np.round(ring + rng.uniform(-0.01, 0.01, ring.shape), 4)
        if shapely.LinearRing(ring).is_simple:
            out.append(ring)
    return out


def test_simplify_never_makes_a_ring_cross_itself():
    rings = _slivers(0, 400)
    raw = [r[geo._chord_keep(r, np.array([0, len(r)]), geo.FILTER_MM, closed=True)]
           for r in rings]
    # the plain chord filter does cross (the audit's bow-ties): the case is exercised
    assert sum(len(f) >= 3 and not shapely.LinearRing(f).is_simple for f in raw) > 50
    for ring in rings:
        out = geo.simplify([ring])
        for f in out:
            assert shapely.LinearRing(f).is_simple
            # points of the input, none moved; every input point within the filter of it
            assert all((ring == q).all(axis=1).any() for q in f)
        if out:
            d = shapely.distance(shapely.MultiLineString([np.vstack([f, f[:1]]) for f in out]),
                                 shapely.points(ring))
            assert d.max() <= geo.FILTER_MM + 1e-9


def test_simplify_cuts_a_ring_touching_itself_into_loops():
    # Clipper may return two lobes touching at a vertex as one ring (spot, 2 mm, layer 8)
    ring = np.array([[0, 0], [4, 0], [4, 4], [2, 2], [3, 6], [1, 6], [2, 2], [0, 4]], float)
    assert not shapely.LinearRing(ring).is_simple
    out = geo.simplify([ring], 0.01)
    assert len(out) == 2 and all(shapely.LinearRing(r).is_simple for r in out)
    assert sum(shapely.Polygon(r).area for r in out) == pytest.approx(shapely.Polygon(ring).area)


@given(st.integers(0, 2**31 - 1), st.booleans())
def test_property_simple_mask_matches_shapely(seed, closed):
    rng = np.random.default_rng(seed)
    lines = [np.round(rng.uniform(0, 4, (int(rng.integers(3, 9)), 2))) for _ in range(30)]
    lines = [ln for ln in lines if len(np.unique(ln, axis=0)) == len(ln)]
    ours = geo.simple_mask(lines, closed=closed)
    ref = [(shapely.LinearRing(ln) if closed else shapely.LineString(ln)).is_simple
           for ln in lines]
    if not closed:  # an open line ending on its start is a closed line for GEOS
        ref = [r and not (ln[0] == ln[-1]).all() for r, ln in zip(ref, lines)]
    assert ours.tolist() == ref


def test_medial_axis_of_strip_and_annulus():
    # a 0.5 x 20 mm strip: one centre line at y = 0.25, clearance 0.25, ends where the
    # clearance is reached (0.25 from the short sides)
    chains = geo.medial_axis([rect(0, 0, 20, 0.5)], 0.1, 0.05)
    long = max(chains, key=lambda c: np.ptp(c[0][:, 0]))
    pts, clear, closed = long
    assert not closed
    assert np.allclose(pts[:, 1], 0.25, atol=1e-3) and np.allclose(clear, 0.25, atol=1e-3)
    assert pts[:, 0].min() == pytest.approx(0.25, abs=0.05)
    assert pts[:, 0].max() == pytest.approx(19.75, abs=0.05)
    # an annulus 10 .. 10.4 mm: one closed centre line at 10.2 with clearance 0.2
    chains = geo.medial_axis([circle(10.4, 400), circle(10.0, 400, hole=True)], 0.05, 0.05)
    assert len(chains) == 1 and chains[0][2]
    r = np.hypot(*chains[0][0].T)
    assert r == pytest.approx(np.full_like(r, 10.2), abs=2e-3)
    assert chains[0][1] == pytest.approx(np.full_like(r, 0.2), abs=2e-3)
    # clearance is the true distance to the rings (shapely)
    ring = shapely.Polygon(circle(10.4, 400), [circle(10.0, 400, hole=True)]).boundary
    d = shapely.distance(ring, shapely.points(chains[0][0]))
    assert np.abs(d - chains[0][1]).max() < 1e-6


def _disks(chains) -> shapely.Geometry:
    """The union of the disks of every chain point's clearance."""
    pts = np.concatenate([c[0] for c in chains])
    r = np.concatenate([c[1] for c in chains])
    return shapely.union_all(shapely.buffer(shapely.points(pts), r, quad_segs=16))


@settings(max_examples=30, deadline=None)
@given(st.floats(0.8, 3.0), st.floats(6.0, 30.0), st.floats(0.0, 1.5))
def test_short_fork_arms_are_pruned_into_a_wider_junction(width, length, angle):
    # a strip's square ends fork the medial axis into a Y (arms to the two corners, about
    # width / sqrt(2) long): each arm was a gap path of its own (BENCHMARKS.md, issue 15).
    # Given max_radius, an arm shorter than its junction's width is pruned (every junction
    # keeps two branches) and the junction's clearance grows to hold the arm's disks: the
    # disks cover what they covered, with fewer chains
    c, s = math.cos(angle), math.sin(angle)
    ring = rect(0, 0, length, width) @ np.array([[c, s], [-s, c]])
    spacing = width / 6.0
    plain = geo.medial_axis([ring], spacing, 0.05)
    pruned = geo.medial_axis([ring], spacing, 0.05, 2.0 * width)
    assert len(plain) >= 3 and len(pruned) < len(plain)
    lost = _disks(plain).difference(_disks(pruned)).area
    assert lost <= 1e-3 * width * length, lost
    # the widened junctions stay within max_radius; without room to grow, no arm goes
    assert max(float(c_[1].max()) for c_ in pruned) <= 2.0 * width + 1e-9
    tight = geo.medial_axis([ring], spacing, 0.05, 0.5 * width)
    assert len(tight) == len(plain)


def test_width_runs_split_where_the_width_changes():
    x = np.linspace(0, 10, 101)
    w = np.where(x < 5, 1.0, 0.5)
    runs = geo.width_runs([(np.c_[x, 0 * x], w, False)], ratio=1.3)
    assert len(runs) == 2
    (p0, (lo0, _m0, hi0), _c0), (p1, (lo1, _m1, hi1), _c1) = runs
    assert (lo0, hi0) == (1.0, 1.0) and p0[-1, 0] == pytest.approx(4.9)
    assert lo1 == 0.5 and p1[0, 0] == pytest.approx(4.9)  # runs share their end vertex
    # never cut shorter than min_length: one run holding both widths
    assert len(geo.width_runs([(np.c_[x, 0 * x], w, False)], 1.3, min_length=20.0)) == 1
    # a closed chain of one width stays closed
    t = np.linspace(0, 2 * np.pi, 50, endpoint=False)
    (runs,) = geo.width_runs([(np.c_[np.cos(t), np.sin(t)], np.full(50, 0.3), True)], 1.3)
    assert runs[2] and runs[1] == (0.3, pytest.approx(0.3), 0.3)


@given(polygon_with_holes(), st.integers(0, 2**31 - 1))
def test_property_distance_to_rings_matches_shapely(rings, seed):
    pts = np.random.default_rng(seed).uniform(-32, 32, size=(200, 2))
    ours = geo.distance_to_rings(pts, rings)
    ref = shapely.distance(shapely.MultiLineString([np.vstack([r, r[:1]]) for r in rings]),
                           shapely.points(pts))
    assert ours == pytest.approx(ref, abs=1e-9)


# ----------------------------------------------------------------------- smooth_rings


def _noisy_ellipse(n: int = 300, noise: float = 0.05, seed: int = 1, a: float = 100.0,
                   b: float = 70.0) -> np.ndarray:
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rng = np.random.default_rng(seed)
    return np.c_[a * np.cos(th), b * np.sin(th)] + rng.normal(0.0, noise, (n, 2))


def _total_turn(ring: np.ndarray) -> float:
    d = np.diff(np.vstack([ring, ring[:1]]), axis=0)
    a = np.arctan2(d[:, 1], d[:, 0])
    t = np.diff(np.r_[a, a[0]])
    return float(np.abs((t + np.pi) % (2.0 * np.pi) - np.pi).sum())


def _farthest_from(ring_out: np.ndarray, ring_in: np.ndarray) -> float:
    """The largest distance of any point of ring_out (its edges sampled finely) to ring_in."""
    pts = shapely.LinearRing(ring_out).segmentize(0.01)
    return float(shapely.LinearRing(ring_in).distance(
        shapely.points(np.asarray(pts.coords))).max())


def _lobed_ring(seed: int, noise: float, hole: bool) -> np.ndarray:
    """A three-lobed ring of 12-400 random vertices, radius 30 +- 8 mm, each moved by
    ``noise`` mm (normal); clockwise for a hole."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(12, 400))
    th = np.sort(rng.uniform(0.0, 2.0 * np.pi, n))
    r = 30.0 + 8.0 * np.sin(3.0 * th + rng.uniform(0, 6)) + rng.normal(0.0, noise, n)
    ring = np.c_[r * np.cos(th), r * np.sin(th)]
    return ring[::-1] if hole else ring


@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 10_000), noise=st.floats(0.0, 0.3),
       tol=st.floats(0.01, 0.5), hole=st.booleans())
def test_smooth_rings_moved_bounds_how_far_each_point_went_into_the_area(seed, noise, tol,
                                                                         hole):
    """``smooth_rings_moved`` gives the rings ``smooth_rings`` gives and, per point, a
    move into the area that is at least the point's distance from the input ring when it
    lies inside the input's area (what a widened fill bead needs to reach back to the raw
    ring's band, paths.concentric_levels), and never more than the tolerance. A point
    is judged by the input segment it lay on: one that slid past a vertex may lie inside
    uncounted, by 0.06 x the tolerance at most over 300 seeds, 0.29 x in the worst case
    hypothesis found (a ring jagged by 0.16 mm at every vertex)."""
    ring = _lobed_ring(seed, noise, hole)
    if not shapely.LinearRing(ring).is_simple:
        return
    (out,), reach, (inward,) = geo.smooth_rings_moved([ring], tol, 5.0)
    (same,), same_reach = geo.smooth_rings([ring], tol, 5.0)
    np.testing.assert_array_equal(out, same)
    assert reach == same_reach
    assert inward.shape == (len(out),)
    assert (inward >= 0.0).all() and (inward <= tol + 1e-9).all()
    d = shapely.distance(shapely.LinearRing(ring), shapely.points(out))
    inside = shapely.contains_xy(Polygon(ring), out[:, 0], out[:, 1])
    into = inside ^ hole  # a hole's area lies outside its ring
    assert (inward[into] >= d[into] - tol / 2.0).all()
    # and nearly every point that lies inside is counted in full (Clipper's grid aside):
    # >= 98.9 % over 300 seeds
    grid = 2.0 / geo.SCALE
    deep = into & (d > grid)
    if deep.sum() >= 10:
        assert (inward[deep] >= d[deep] - grid).mean() >= 0.95


@settings(deadline=None, max_examples=40)
@given(seed=st.integers(0, 10_000), noise=st.floats(0.0, 0.3),
       tol=st.floats(0.01, 0.5), sigma=st.floats(0.5, 8.0), hole=st.booleans())
def test_smooth_rings_stays_within_the_tolerance_and_reach_covers_the_input(
        seed, noise, tol, sigma, hole):
    """Every point of a smoothed ring (vertices and chords) lies within the tolerance of
    the input ring; orientation is kept; the smoothed area grown by ``reach`` holds the
    input's area (what the fill's first ring relies on to leave no sliver)."""
    ring = _lobed_ring(seed, noise, hole)
    if not shapely.LinearRing(ring).is_simple:
        return
    (out,), reach = geo.smooth_rings([ring], tol, sigma)
    assert _farthest_from(out, ring) <= tol + 1e-9
    assert np.sign(signed_area(out)) == np.sign(signed_area(ring))
    assert 0.0 <= reach <= tol + 1e-9
    # the area each ring bounds (a hole's: the outside, here the ring's own disk turned)
    inside, smooth = Polygon(ring), Polygon(out)
    if hole:  # the area lies right of a CW ring's disk edge: the disk shrinks to hold it
        assert smooth.difference(inside.buffer(reach + 1e-6, join_style=2)).area < 1e-6
    else:
        assert inside.difference(smooth.buffer(reach + 1e-6, join_style=2)).area < 1e-6


def test_smooth_rings_takes_the_noise_off_a_scanned_contour():
    """A 200 x 140 mm ellipse with 0.05 mm vertex noise turns 2.8 times round in all; within
    0.25 mm it comes out turning once (as the clean ellipse), and a jerk-limited robot
    follows it about as fast as the clean one (the reason the fill is smoothed)."""
    from icefab.config import Job
    from icefab.core import Toolpath
    from icefab.motion import plan_motion

    noisy = _noisy_ellipse()
    (out,), _ = geo.smooth_rings([noisy], 0.25, 5.0)
    assert _total_turn(noisy) > 2.5 * 2.0 * np.pi
    assert _total_turn(out) == pytest.approx(2.0 * np.pi, rel=0.02)
    job = Job()
    ring = lambda p: Toolpath(points=p + [340.0, 0.0], closed=True, role="fill", width=3.0,
                              frame="base")
    t_noisy = plan_motion(ring(noisy), job).duration
    t_out = plan_motion(ring(out), job).duration
    t_clean = plan_motion(ring(_noisy_ellipse(noise=0.0)), job).duration
    assert t_out < 0.7 * t_noisy
    assert t_out < 1.15 * t_clean


def test_smooth_rings_keeps_clean_polygons_and_corners():
    """Straight edges and corners are not smoothed away: a square and an L-shaped ring come
    back as they were (reach 0); rings too short to smooth, tolerance 0 and no rings are
    returned as they are."""
    square = np.array([[0.0, 0.0], [50.0, 0.0], [50.0, 50.0], [0.0, 50.0]])
    ell = np.array([[0.0, 0.0], [40.0, 0.0], [40.0, 10.0], [10.0, 10.0], [10.0, 40.0],
                    [0.0, 40.0]])
    out, reach = geo.smooth_rings([square, ell], 0.3, 5.0)
    assert reach == 0.0
    for a, b in zip([square, ell], out):
        assert shapely.Polygon(a).symmetric_difference(shapely.Polygon(b)).area < 1e-9
    tiny = square * 0.02  # 4 mm round: fewer than 8 grid steps
    assert geo.smooth_rings([tiny], 0.3, 5.0)[0][0] is not None
    np.testing.assert_array_equal(geo.smooth_rings([tiny], 0.3, 5.0)[0][0], tiny)
    np.testing.assert_array_equal(geo.smooth_rings([square], 0.0, 5.0)[0][0], square)
    assert geo.smooth_rings([], 0.3, 5.0) == ([], 0.0)


def test_smooth_rings_takes_repeated_and_collinear_points():
    """Repeated vertices (zero-length edges), collinear runs and a ring of one repeated
    point do not upset the smoothing: the result stays within the tolerance, a point-ring
    comes back as it was."""
    noisy = _noisy_ellipse(n=120, noise=0.1)
    ring = np.repeat(noisy, 2, axis=0)                    # every vertex twice
    ring = np.insert(ring, 7, (ring[6] + ring[8]) / 2.0, axis=0)  # a collinear point
    (out,), reach = geo.smooth_rings([ring], 0.2, 5.0)
    assert _farthest_from(out, noisy) <= 0.2 + 1e-9
    assert 0.0 < reach <= 0.2 + 1e-9
    dot = np.zeros((4, 2))
    (same,), r = geo.smooth_rings([dot], 0.2, 5.0)
    np.testing.assert_array_equal(same, dot)
    assert r == 0.0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(-20, 20), st.floats(-20, 20), st.floats(0.05, 3.0)),
                min_size=2, max_size=7), st.booleans(), st.floats(0.0, 0.1))
def test_a_variable_width_sweep_is_the_hull_of_its_disks(pts, closed, grow):
    # against shapely: the union of the convex hulls of consecutive disks (fine arcs); the
    # inscribed 32-gons at the points may only fall short, by at most their 0.6 %
    xy = np.array([p[:2] for p in pts])
    w = np.array([p[2] for p in pts])
    if closed and len(xy) < 3:
        closed = False
    band = geo.union(geo.variable_sweep_rings([(xy, closed, w)], grow))
    poly = np.vstack([xy, xy[:1]]) if closed else xy
    r = (np.concatenate([w, w[:1]]) if closed else w) / 2.0 + grow
    disks = shapely.buffer(shapely.points(poly), r, quad_segs=64)
    exact = shapely.union_all(shapely.convex_hull(shapely.union(disks[:-1], disks[1:])))
    # Clipper's rings may touch themselves at a vertex (valid for Clipper, not for GEOS)
    def polys(sign):
        return shapely.union_all([shapely.make_valid(Polygon(q)) for q in band.rings
                                  if sign * signed_area(q) > 0])
    got = polys(1).difference(polys(-1))
    assert got.difference(exact.buffer(1e-3)).area <= 1e-6
    assert got.area >= 0.99 * exact.area
    # no part of any point's disk (inscribed 32-gon) is left out: the sweep only keeps
    # the pieces of them its quadrilaterals do not hold; what is missing may only be
    # Clipper's rounding to 1e-4 mm along the edges
    ang = 2.0 * np.pi * np.arange(32) / 32
    disks32 = shapely.union_all([Polygon(c + rc * np.stack([np.cos(ang), np.sin(ang)], 1))
                                 for c, rc in zip(poly, r)])
    assert disks32.difference(got).area <= 1e-4 * disks32.length


def test_a_smoothing_tolerance_within_the_grid_moves_nothing_and_a_lone_hole_is_dropped():
    """Smoothed within less than Clipper's grid, a ring was turned inside out (the cap on
    each point's move, the tolerance less the grid and the filter, was negative); the
    next offset of that lone clockwise ring was a square 1.8e15 mm wide, whose smoothing
    asked for more memory than there is (hypothesis found it: fill_smoothing_mm = 1e-96)."""
    ring = circle(8.0, 32)
    for tol in (1e-96, 1e-30, 1.0 / geo.SCALE, 2.0 / geo.SCALE):
        got, reach = geo.smooth_rings([ring], tol, 5.0)
        assert reach == 0.0 and np.array_equal(got[0], ring)
    moved, _reach = geo.smooth_rings([ring], 3.0 / geo.SCALE, 5.0)
    assert signed_area(moved[0]) > 0   # just above it: smoothed, orientation kept
    hole = circle(8.0, 32, hole=True)
    assert geo.without_orphan_holes([hole]) == []
    assert geo.offset_rings([hole], -1.0) == [] and geo.offset_rings([hole], 1.0) == []
    assert len(geo.without_orphan_holes([ring])) == 1


def test_level_gaps_are_the_area_less_every_band_when_the_levels_nest():
    """Square rings 3 mm apart, bands 1.6 mm half-wide (0.2 mm of overlap): the gaps are
    the corner tips the mitred bands miss, the centre and what lies outside the first
    band, as one Boolean of every band gives them. Levels that do not nest (a ring out of
    turn, inside the band two levels out) give other gaps: the precondition is real."""
    area = [rect(-20, -20, 20, 20)]
    nested = [([rect(-c, -c, c, c)], 1.6) for c in (18.0, 15.0, 12.0, 9.0)]
    nested.append(([circle(4.0, 64)], 1.6, [rect(-5, -5, 5, 5)]))  # with a held area
    def both(levels):
        fast = geo.union(geo.level_gaps(area, levels))
        ref = geo.union(geo.difference_rings(area, geo.level_bands(levels)))
        return fast, ref
    fast, ref = both(nested)
    assert ref.area > 1.0   # the centre at least
    assert to_shapely(fast).symmetric_difference(to_shapely(ref)).area < 1e-6
    out_of_turn = nested[:2] + [([rect(-17.5, -17.5, 17.5, 17.5)], 0.2)] + nested[2:]
    fast, ref = both(out_of_turn)
    assert to_shapely(fast).symmetric_difference(to_shapely(ref)).area > 1.0
    assert geo.level_gaps(area, []) and geo.union(geo.level_gaps(area, [])).area == 1600.0


@pytest.mark.parametrize("where", [(0.0, 40.0), (0.0, -40.0), (40.0, 0.0), (-40.0, 0.0)])
def test_an_orphan_hole_does_not_turn_an_offset_inside_out(where):
    """Clipper takes a whole set's orientation from its lowest ring: a stray clockwise
    sliver outside every outer ring (a bunny fill level had one) emptied the next fill
    level. offset_rings and level_bands drop such holes; the result is the outer's."""
    sq = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    tiny = np.array([[-0.7916, 2.1763], [0.0, 2.6829], [-1.5576, 1.6221]]) + where
    assert signed_area(tiny) < 0
    assert np.allclose(geo.ring_areas(geo.offset_rings([sq, tiny], -1.0, 0.0)), [64.0])
    assert np.allclose(sorted(geo.ring_areas(geo.level_bands([([tiny, sq], 0.5)]))),
                       [-81.0, 121.0])
    # a hole its outer holds stays
    hole = np.array([[4, 4], [4, 6], [6, 6], [6, 4]], float)
    assert np.allclose(sorted(geo.ring_areas(geo.offset_rings([sq, hole], -1.0, 0.0))),
                       [-16.0, 64.0])


@settings(deadline=None, max_examples=60)
@given(seed=st.integers(0, 10_000), angle=st.floats(1.0, 179.0))
def test_corner_vertices_are_the_turns_over_the_angle(seed, angle):
    """corner_vertices against the turn angle of every vertex (atan2 of the arriving and
    leaving segments, the closing one included); a repeated point turns by nothing."""
    rng = np.random.default_rng(seed)
    ring = rng.uniform(-10, 10, (int(rng.integers(3, 40)), 2))
    ring = np.vstack([ring, ring[-1:]]) if seed % 3 == 0 else ring  # a repeated point
    e = np.diff(ring, axis=0, append=ring[:1])
    f = np.roll(e, 1, axis=0)
    turn = np.degrees(np.abs(np.arctan2(f[:, 0] * e[:, 1] - f[:, 1] * e[:, 0],
                                        (f * e).sum(axis=1))))
    moving = (np.hypot(*e.T) > 0) & (np.hypot(*f.T) > 0)
    want = np.flatnonzero(moving & (turn > angle))
    got = geo.corner_vertices(ring, angle)
    near = np.abs(turn - angle) < 1e-6  # rounding at the threshold may go either way
    assert set(got.tolist()) ^ set(want.tolist()) <= set(np.flatnonzero(near).tolist())
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    assert geo.corner_vertices(square, 30.0).tolist() == [0, 1, 2, 3]
    assert geo.corner_vertices(square, 91.0).tolist() == []


@settings(max_examples=40, deadline=None)
@given(polygon_with_holes(), st.lists(st.tuples(st.floats(-40, 40), st.floats(-40, 40)),
                                      min_size=1, max_size=20))
def test_ring_nearest_is_shapelys_projection(rings, points):
    """:func:`icefab.geometry.ring_nearest` against shapely: the distance of every point
    to the ring's edges, and an arc length (from the ring's first point) whose point on
    the ring (shapely's interpolation) lies at that distance: a nearest point, whichever
    of several equally near ones."""
    ring = np.asarray(rings[0], dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    at, dist = geo.ring_nearest(pts, ring)
    line = shapely.LinearRing(ring)
    sp = shapely.points(pts)
    assert np.allclose(dist, shapely.distance(sp, line), atol=1e-9)
    foot = shapely.get_coordinates(shapely.line_interpolate_point(line, at))
    # the foot at the arc position given is that far from the point
    assert np.allclose(np.hypot(*(foot - pts).T), dist, atol=1e-7)
    assert np.all((at >= 0.0) & (at <= line.length + 1e-9))


def test_clipper_needles_are_dropped_from_regions_unless_they_hold_a_ring():
    """region_from_tree leaves out rings narrower on average than one grid unit (a spike
    Clipper2 returned as a ring of its own) unless another ring lies inside them; the
    parents of the rest follow."""
    class Node:
        def __init__(self, polygon, children=()):
            self.polygon, self.children = np.asarray(polygon, float), list(children)

    needle = np.array([[1.0, 1.0], [9.0, 1.00001], [1.0, 1.00002]])[::-1]   # CW, a "hole"
    assert 2 * abs(signed_area(needle)) * geo.SCALE < 16.0
    island = rect(4, 4, 6, 6)
    hole = rect(2, 2, 8, 8)[::-1]
    tree = Node(np.zeros((0, 2)), [Node(rect(0, 0, 10, 10), [Node(needle),
                                                              Node(hole, [Node(island)])])])
    r = geo.region_from_tree(tree)
    assert len(r.rings) == 3 and r.parent.tolist() == [-1, 0, 1]
    np.testing.assert_array_equal(r.rings[1], hole)
    check_region_structure(r)
    # a needle holding a ring stays (its child would lose its place in the tree)
    tree = Node(np.zeros((0, 2)), [Node(rect(0, 0, 10, 10), [Node(needle, [Node(island)])])])
    assert len(geo.region_from_tree(tree).rings) == 3


@settings(max_examples=60, deadline=None)
@given(polygon_with_holes(), st.lists(st.tuples(*[st.floats(-35.0, 35.0)] * 4), min_size=1,
                                      max_size=30),
       st.floats(0.05, 5.0), st.sampled_from([0.25, 1.0, 3.0]), st.booleans())
# crosses the closing edge 0.2 mm from its end vertex, which is sampled as the next edge's
# start: was 0.0276 mm (the closing edge's own last sample 2.9 mm away was not near)
@example(rings=[np.array([[8.75, 0.0], [6.73002826, 4.32512654], [3.3233201, 7.27705596],
                          [-1.13851871, 7.91857154], [-5.23888587, 6.04599659],
                          [-7.67594379, 2.25386045], [-7.67594379, -2.25386045],
                          [-5.23888587, -6.04599659], [-1.13851871, -7.91857154],
                          [3.3233201, -7.27705596], [15.14256359, -9.73153471]])],
         segs=[(0.0, -1.0, 9.0, 0.0)], upper=0.125, spacing=3.0, each=False)
def test_segment_distances_to_rings_are_shapelys(rings, segs, upper, spacing, each):
    """segments_to_rings_distance is GEOS' segment-to-boundary distance (0 where an edge
    crosses the segment) wherever that is within ``upper`` (one for all, or one per
    segment), and inf only beyond it, whatever the sampling that finds the edges."""
    s = np.array(segs, dtype=np.float64).reshape(-1, 4)
    a, b = s[:, :2], s[:, 2:]
    if each:
        upper = upper * (1.0 + np.sin(np.arange(len(a))))
    got = geo.segments_to_rings_distance(a, b, rings, upper, spacing)
    edge = shapely.MultiLineString([np.vstack([r, r[:1]]) for r in rings])
    want = np.array([shapely.LineString([p, q]).distance(edge) if np.any(p != q)
                     else shapely.Point(p).distance(edge) for p, q in zip(a, b)])
    near = want <= upper
    np.testing.assert_allclose(got[near], want[near], rtol=1e-9, atol=1e-9)
    assert np.all(np.isinf(got[~near]) | (np.abs(got[~near] - want[~near]) < 1e-9))


def test_a_segment_across_a_thin_spike_of_the_edge_is_at_distance_0():
    """The case sampled distances miss: a short segment whose ends lie well inside the
    area, crossing a spike of the edge whose tip and base lie far from it."""
    spike = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 4.0], [5.2, 4.0], [5.0, 9.0],
                      [4.99, 4.0], [0.0, 4.0]])
    a, b = np.array([[4.9, 6.0]]), np.array([[5.3, 6.0]])
    assert geo.segments_to_rings_distance(a, b, [spike], 1.0)[0] == 0.0
    # parallel beside it, 0.3 mm from the spike's nearer edge
    far = geo.segments_to_rings_distance(np.array([[5.5, 5.0]]), np.array([[5.5, 6.0]]),
                                         [spike], 1.0)[0]
    want = shapely.LineString([[5.5, 5.0], [5.5, 6.0]]).distance(
        shapely.LinearRing(spike))
    assert far == pytest.approx(want, abs=1e-12) and 0.2 < far < 0.4


@pytest.mark.parametrize("spacing", [0.5, 3.0, 10.0])
def test_an_edge_sampled_sparsely_is_still_found_near_a_short_segment(spacing):
    """A short segment beside the middle of a long edge, between its samples: within
    ``upper`` of the edge, farther than ``upper`` from every sample of it."""
    box = rect(-30.0, -20.0, 30.0, 0.0)
    for x in (0.25, 1.3, 4.9):
        a, b = np.array([[x, -0.9]]), np.array([[x + 0.01, -0.9]])
        assert geo.segments_to_rings_distance(a, b, [box], 1.0, spacing)[0] == \
            pytest.approx(0.9, abs=1e-12)
        assert np.isinf(geo.segments_to_rings_distance(a, b, [box], 0.8, spacing)[0])


@settings(max_examples=60, deadline=None)
@given(st.floats(5.0, 40.0), st.floats(0.002, 0.3), st.floats(0.01, 0.1),
       st.floats(0.0, 0.5), st.floats(0.5, 3.0))
def test_an_offset_drops_an_annulus_narrower_than_its_filter_keeps_apart(
        radius, width, filt, off_centre, d):
    """An annulus (a 360-gon and its hole) offset inward by ``d`` to a mean width under
    twice the filter is dropped whole (the filter moves each ring up to its tolerance on
    its own, so the two could cross); a wider one keeps both rings; a hole out of the ring
    is never dropped, and a region's own rings keep such an annulus."""
    def circle(r, c=(0.0, 0.0)):
        a = np.linspace(0, 2 * np.pi, 360, endpoint=False)
        return np.column_stack([c[0] + r * np.cos(a), c[1] + r * np.sin(a)])
    # the hole stays inside the outer ring, at least half the width from it (a hole that
    # touches it makes one ring of the two, a C that keeps its points when filtered)
    shift = off_centre * width
    outer, hole = circle(radius + d), circle(radius - width - d, (shift, 0.0))[::-1]
    out = geo.offset_rings([outer, hole], -d, filt)
    got = geo.offset_rings([outer, hole], -d, 0.0)       # unfiltered: its mean width
    mean = 2 * geo.ring_areas(got).sum() / geo.ring_perimeters(got).sum()
    if mean < 2 * filt * 0.99:
        assert out == []
    elif mean > 2 * filt * 1.01:
        assert len(out) == 2
    assert len(geo.simplify(got, filt)) == 2              # not by default
    # a ring of the same area elsewhere is no sliver of the outer one
    far = circle(radius - width, (5 * radius, 0.0))[::-1]
    assert len(geo.simplify([circle(radius), far], filt, slivers=True)) == 2


_COORD = st.floats(-300.0, 300.0, allow_nan=False, allow_infinity=False)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(_COORD, _COORD, _COORD, _COORD), min_size=0, max_size=30),
       st.sampled_from([0.25, 0.4, 3.0]), st.booleans())
def test_compiled_subdivision_is_core_subdivide_segments_to_the_last_bit(segs, step, zero):
    """geometry's compiled subdivision (the paths stage's hot loop) and its ring sampling
    are core.subdivide_segments and the numpy arc formula they replaced, bit for bit:
    the toolpaths were checked unchanged by it, and this keeps the two forms one."""
    from icefab.core import arc_lengths, subdivide_segments

    a = np.array([s[:2] for s in segs], dtype=np.float64).reshape(-1, 2)
    b = np.array([s[2:] for s in segs], dtype=np.float64).reshape(-1, 2)
    if zero and len(a):
        b[::3] = a[::3]                       # zero-length segments among them
    got = geo._subdivided(a, b, step)
    want = subdivide_segments(a, b, step)
    for g, w in zip(got, want):
        assert g.shape == w.shape and np.array_equal(g, w)
    # the rings' samples: ring of each sample and its arc position from the ring's start
    if len(a) >= 3:
        rings = [a[: len(a) // 2 + 1], a[len(a) // 2 + 1:]] if len(a) >= 6 else [a]
        P, edge, ea, eb, _prv, ring, arc, _ring_len = geo._sample_rings(rings, step * 10)
        seg = np.linalg.norm(eb - ea, axis=1)
        first = np.cumsum([0] + [len(r) for r in rings[:-1]])
        ring_of_edge = np.repeat(np.arange(len(rings)), [len(r) for r in rings])
        _, _, t = subdivide_segments(ea, eb, step * 10)
        cum = arc_lengths(seg)
        assert np.array_equal(ring, ring_of_edge[edge])
        assert np.array_equal(arc, cum[edge] - cum[first][ring_of_edge[edge]] + t * seg[edge])
