"""Surface mapping feedback: surfaces, the 3D spatial PID, applying the action (thesis 5.1-5.2)."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
from hypothesis import given, settings
from hypothesis import strategies as st

from icefab import Job
from icefab.errors import GeometryError
from icefab.feedback import (ControlAction, SmfState, _despike, _one_per_place, action_along,
                             error_surface, grid_over, region_mask, regrid,
                             retime_trajectory, saturation_limits, smf_update,
                             surface_from_samples)
from icefab.core import HeightMap, Toolpath, Region, Trajectory


def square(x0, y0, x1, y1, ccw=True):
    r = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
    return r if ccw else r[::-1]


def frame_region():
    """A 100 x 60 mm rectangle with a 20 x 20 hole."""
    return Region(rings=(square(0, 0, 100, 60), square(40, 20, 60, 40, ccw=False)),
                  parent=np.array([-1, 0]))


def samples_on(fn, n=4000, seed=0, box=(-2, -2, 102, 62)):
    rng = np.random.default_rng(seed)
    x = rng.uniform(box[0], box[2], n)
    y = rng.uniform(box[1], box[3], n)
    return np.column_stack([x, y, fn(x, y)])


def test_region_mask_matches_shapely():
    reg = frame_region()
    x = np.arange(-5, 106, 1.3)
    y = np.arange(-5, 66, 1.7)
    m = region_mask(reg, x, y)
    poly = shapely.Polygon(reg.rings[0], [reg.rings[1]])
    xx, yy = np.meshgrid(x, y)
    ref = shapely.contains_xy(poly, xx, yy)
    assert np.array_equal(m, ref)


def test_plane_is_reproduced_and_nan_outside_footprint():
    plane = lambda x, y: 10 + 0.01 * x - 0.02 * y  # noqa: E731
    reg = frame_region()
    hm = surface_from_samples(samples_on(plane), reg, spacing=1.0)
    x, y = hm.grid()
    xx, yy = np.meshgrid(x, y)
    inside = region_mask(reg, x, y)
    assert np.array_equal(np.isfinite(hm.z), inside)
    np.testing.assert_allclose(hm.z[inside], plane(xx, yy)[inside], atol=1e-9)
    assert hm.origin[0] % 1.0 == 0 and hm.origin[1] % 1.0 == 0  # lattice-aligned grid


def test_footprint_outside_hull_uses_nearest_sample():
    xyz = samples_on(lambda x, y: 5 + 0 * x, box=(10, 10, 90, 50))
    hm = surface_from_samples(xyz, frame_region(), spacing=2.0)
    inside = np.isfinite(hm.z)
    np.testing.assert_allclose(hm.z[inside], 5.0)


def test_smoothing_removes_spikes():
    xyz = samples_on(lambda x, y: 3 + 0 * x, n=6000)
    xyz[::97, 2] += 2.0  # laser drop-outs / reflections
    raw = surface_from_samples(xyz, frame_region(), 1.0, bin_mm=0)
    smooth = surface_from_samples(xyz, frame_region(), 1.0, smoothing=True, bin_mm=0)
    err = lambda h: np.nanmax(np.abs(h.z - 3))  # noqa: E731
    assert err(raw) > 0.5
    assert np.nanpercentile(np.abs(smooth.z - 3), 99) < 0.05 * err(raw)
    binned = surface_from_samples(xyz, frame_region(), 1.0, smoothing=True)
    assert np.nanpercentile(np.abs(binned.z - 3), 99) < 0.1 * err(raw)


def _rings(spacing_mm=3.0, along_mm=0.5, r_max=30.0):
    """Samples as the laser takes them: concentric measurement rings ``spacing_mm`` apart,
    one sample every ``along_mm`` along each (100 Hz at 50 mm/s)."""
    pts = []
    for r in np.arange(spacing_mm / 2, r_max, spacing_mm):
        t = np.arange(0, 2 * np.pi, along_mm / r)
        pts.append(np.column_stack([r * np.cos(t), r * np.sin(t)]))
    return np.vstack(pts)


@pytest.mark.parametrize("along_mm", [0.5, 1.25])   # the ice's 50 mm/s, the scaffold's 125
@pytest.mark.parametrize("pair", [False, True])
def test_spikes_on_measurement_rings_leave_no_node_off(along_mm, pair):
    """Spikes of one or two samples on rings 3 mm apart, with the default binning: the
    grid median alone left 23 nodes 0.1-0.27 mm off (the spike, averaged into its 1 mm
    cell, spread across to the next ring); a ripple 1.5 mm long along the ring stays."""
    rng = np.random.default_rng(3)
    xy = _rings(along_mm=along_mm)
    truth = 0.05 * np.sin(2 * np.pi * xy[:, 0] / 20)
    z = truth + rng.normal(0, 0.01, len(xy))
    hit = rng.choice(len(xy) - 1, 12, replace=False)
    z[hit] += 2.0
    if pair:
        z[hit + 1] += 2.0
    s = surface_from_samples(np.column_stack([xy, z]), None, 1.0, smoothing=True)
    x, y = s.grid()
    X, Y = np.meshgrid(x, y)
    inner = np.isfinite(s.z) & (X ** 2 + Y ** 2 < 25 ** 2)
    off = np.abs(s.z - 0.05 * np.sin(2 * np.pi * X / 20))[inner]
    assert off.max() < 0.05
    raw = surface_from_samples(np.column_stack([xy, z]), None, 1.0)
    assert np.nanmax(np.abs(raw.z)) > 1.0      # the spikes are there without smoothing


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 5), st.integers(0, 5), st.floats(-5, 5)),
                min_size=1, max_size=60))
def test_samples_at_one_place_become_one_at_their_median(rows):
    """The laser reading on while the robot stands (a dwell): one sample a place, its
    height the median of theirs (100 000 at one place slowed the k-d tree to 30 s)."""
    xyz = np.array(rows, dtype=np.float64)
    got = _one_per_place(xyz)
    places = {}
    for x, y, z in rows:
        places.setdefault((float(x), float(y)), []).append(z)
    assert len(got) == len(places)
    for x, y, z in got:
        assert z == pytest.approx(float(np.median(places[(x, y)])))


def test_despiking_keeps_a_feature_three_samples_long():
    xy = _rings()
    z = np.zeros(len(xy))
    ring = np.flatnonzero(np.hypot(*xy.T) > 20)[:1][0]   # a sample on an outer ring
    z[ring:ring + 3] = 1.0
    out = _despike(np.column_stack([xy, z]))
    np.testing.assert_array_equal(out[ring:ring + 3, 2], 1.0)
    z[ring + 2] = 0.0                             # two samples: a spike, removed
    assert not _despike(np.column_stack([xy, z]))[:, 2].any()


def test_bad_samples():
    with pytest.raises(GeometryError, match="need >= 3"):
        surface_from_samples(np.zeros((2, 3)), None, 1.0)
    with pytest.raises(GeometryError, match="shape"):
        surface_from_samples(np.zeros((5, 2)), None, 1.0)
    with pytest.raises(GeometryError, match="triangulate"):
        surface_from_samples(np.column_stack([np.arange(5.0), np.arange(5.0), np.ones(5)]),
                             None, 1.0)


def test_error_surface_normalised():
    hm = HeightMap(np.zeros(2), 1.0, np.array([[1.0, 0.8], [np.nan, 1.2]]))
    e = error_surface(hm, 1.0, 0.5)
    np.testing.assert_allclose(e.z, [[0.0, 0.4], [np.nan, -0.4]])


def _plant_run(reg, n_layers, job, disturbance, gains=None, integral_limit=None,
               spacing=2.0, dh_m=1.0):
    """A pixel-wise plant: each interval adds dh_m (1 + u)(1 + delta(x, y, k))."""
    origin, nx, ny = grid_over(reg.bounds(), spacing)
    x = origin[0] + spacing * np.arange(nx)
    y = origin[1] + spacing * np.arange(ny)
    mask = region_mask(reg, x, y)
    xx, yy = np.meshgrid(x, y)
    h = np.zeros((ny, nx))
    state = SmfState()
    rms = []
    u = np.zeros_like(h)
    us = []
    for k in range(1, n_layers + 1):
        h = h + dh_m * (1 + u) * (1 + disturbance(xx, yy, k))
        meas = HeightMap(origin, spacing, np.where(mask, h, np.nan))
        err = error_surface(meas, k * dh_m, dh_m)
        rms.append(float(np.sqrt(np.nanmean(err.z ** 2))))
        act, state = smf_update(state, err, job, gains=gains, integral_limit=integral_limit)
        u = np.nan_to_num(act.u.z)
        us.append(act)
    return np.array(rms), us, state


def test_pid_converges_on_tilted_surface():
    # a tilted flow error: +5 % at x = 0 rising to +25 % at x = 100 (and a tilted start)
    reg = Region(rings=(square(0, 0, 100, 60),), parent=np.array([-1]))
    tilt = lambda x, y, k: 0.05 + 0.2 * x / 100 + (0.5 * y / 60 if k == 1 else 0)  # noqa
    rms_cl, acts, _ = _plant_run(reg, 40, Job(), tilt)
    rms_ol, _, _ = _plant_run(reg, 40, Job(), tilt, gains=(0.0, 0.0, 0.0))
    assert rms_ol[-1] > 5.0  # open loop: error grows with height
    assert rms_cl[-1] < 1e-3  # closed loop converges to the nominal height
    assert rms_cl[-1] < rms_cl[0] / 100
    # the action settles on the inverse of the tilt: (1 + u)(1 + delta) = 1
    a = acts[-1]
    x, y = a.u.grid()
    xx, _ = np.meshgrid(x, y)
    ok = np.isfinite(a.u.z)
    assert ok.mean() > 0.9
    np.testing.assert_allclose(a.u.z[ok], (1 / (1 + 0.05 + 0.2 * xx / 100) - 1)[ok], atol=1e-3)


def test_saturation_of_output_and_integral():
    job = Job()
    err = HeightMap(np.zeros(2), 1.0, np.full((3, 4), 2.0))  # 2 intervals too low
    act, st1 = smf_update(SmfState(), err, job)
    assert np.allclose(act.u.z, 0.3) and act.saturated == 1.0
    np.testing.assert_allclose(act.unsaturated.z, 2.0 + 0.3)  # P = 2, I = min(0.66, 0.3)
    assert np.allclose(st1.integral.z, 0.3)  # integral term clamped (anti-windup)
    st = st1
    for _ in range(10):
        act, st = smf_update(st, err, job)
    assert np.allclose(st.integral.z, 0.3)
    # error gone: the controller output is only the (bounded) integral, not a wound-up sum
    zero = HeightMap(np.zeros(2), 1.0, np.zeros((3, 4)))
    act, st = smf_update(st, zero, job)
    np.testing.assert_allclose(act.u.z, 0.3 - 0.03 * 2.0, atol=1e-12)  # I + Kd*(0 - 2)
    lo, hi = saturation_limits(Job().replace(**{"feedback.controller": "speed"}))
    assert 1 / (1 + hi) == pytest.approx(0.7) and 1 / (1 + lo) == pytest.approx(1.3)
    # the c-controller's planes are uneven: its integral stays within them (it reached
    # -0.3 below the lower plane -0.23 and wound up there: a control review's)
    speed = Job().replace(**{"feedback.controller": "speed"})
    high = HeightMap(np.zeros(2), 1.0, np.full((3, 4), -2.0))   # 2 intervals too high
    st = SmfState()
    for _ in range(5):
        act, st = smf_update(st, high, speed)
    assert np.allclose(st.integral.z, lo) and np.allclose(act.u.z, lo)
    st = SmfState()
    for _ in range(5):
        act, st = smf_update(st, err, speed)
    assert np.allclose(st.integral.z, 0.3)       # the job's bound, inside the upper plane


def test_anti_windup_reduces_overshoot():
    # thesis 5.2.2: a fluid line blocked for 6 intervals (no deposition), then normal
    reg = Region(rings=(square(0, 0, 20, 20),), parent=np.array([-1]))
    blocked = lambda x, y, k: (-1.0 if 3 <= k <= 8 else 0.0) + 0 * x  # noqa: E731
    job = Job()
    rms_aw, acts_aw, _ = _plant_run(reg, 60, job, blocked)
    rms_wu, acts_wu, _ = _plant_run(reg, 60, job, blocked, integral_limit=np.inf)
    # With the wound-up integral the controller keeps the output saturated long after the
    # height is recovered and overshoots; anti-windup recovers sooner and overshoots less.
    over = lambda acts: max(-np.nanmin(a.p) for a in acts)  # noqa: E731  (p = Kp * E)
    assert over(acts_aw) < 0.5 * over(acts_wu)
    assert rms_aw[-1] < 1e-3
    assert np.sum(rms_aw) < np.sum(rms_wu)


def test_regrid_between_footprints():
    # layer k: 0..40 x 0..20; layer k+1: 10..60 x 0..20 (new area on the right)
    job = Job()
    e1 = HeightMap(np.array([0.0, 0.0]), 1.0, np.full((21, 41), 0.5))
    act1, st = smf_update(SmfState(), e1, job)
    e2 = HeightMap(np.array([10.0, 0.0]), 1.0, np.full((21, 51), 0.1))
    act2, st2 = smf_update(st, e2, job)
    x, _ = e2.grid()
    old = x <= 40
    # integral carried over where the grids overlap, 0 + Ki* E at new nodes
    np.testing.assert_allclose(st2.integral.z[:, old], min(0.33 * 0.5, 0.3) + 0.33 * 0.1)
    np.testing.assert_allclose(st2.integral.z[:, ~old], 0.33 * 0.1)
    # derivative only where the previous error is known
    np.testing.assert_allclose(act2.d[:, old], 0.03 * (0.1 - 0.5))
    np.testing.assert_allclose(act2.d[:, ~old], 0.0)
    # a differently pitched, shifted grid goes through interpolation: linear fields exact
    xs = np.arange(0, 41.0)
    ys = np.arange(0, 21.0)
    lin = HeightMap(np.zeros(2), 1.0, 0.01 * xs[None, :] + 0.02 * ys[:, None])
    tgt = HeightMap(np.array([0.25, 0.35]), 0.7, np.zeros((20, 40)))
    vals, known = regrid(lin, tgt)
    tx, ty = tgt.grid()
    ref = 0.01 * tx[None, :] + 0.02 * ty[:, None]
    inside = (tx[None, :] <= 40) & (ty[:, None] <= 20)
    assert np.array_equal(known, np.broadcast_to(inside, known.shape))
    np.testing.assert_allclose(vals[known], ref[known], atol=1e-12)
    assert np.all(vals[~known] == 0)


def test_hole_nodes_do_not_leak_into_new_grid():
    z = np.full((11, 11), 0.2)
    z[4:7, 4:7] = np.nan  # a hole in the previous footprint
    prev = HeightMap(np.zeros(2), 1.0, z)
    vals, known = regrid(prev, HeightMap(np.zeros(2), 1.0, np.zeros((11, 11))))
    assert not known[5, 5] and vals[5, 5] == 0
    assert np.all(vals[known] == 0.2)


def test_nodes_the_laser_missed_keep_their_integral_and_previous_error():
    """A laser drop-out (NaN nodes inside the footprint) or a layer it saw nothing of
    (all NaN) is not an error of 0: those nodes keep their integral and previous error for
    the next layer (a hunt's all-NaN update restarted the integral from 0: 0.066 where
    0.198 was due)."""
    job = Job()
    ki = job.feedback.ki
    E = HeightMap(np.zeros(2), 1.0, np.full((10, 12), 0.2))
    _, s = smf_update(SmfState(), E, job)
    _, s = smf_update(s, E, job)
    np.testing.assert_allclose(s.integral.z, 2 * ki * 0.2)
    _, blind = smf_update(s, HeightMap(np.zeros(2), 1.0, np.full((10, 12), np.nan)), job)
    np.testing.assert_allclose(blind.integral.z, 2 * ki * 0.2)
    np.testing.assert_allclose(blind.previous_error.z, 0.2)
    act, _ = smf_update(blind, E, job)
    np.testing.assert_allclose(act.i, 3 * ki * 0.2)
    holed = E.z.copy()
    holed[3:5, 4:8] = np.nan
    _, s_h = smf_update(s, HeightMap(np.zeros(2), 1.0, holed), job)
    act, _ = smf_update(s_h, E, job)
    assert act.i[4, 5] == pytest.approx(3 * ki * 0.2)     # missed one layer's increment
    assert act.i[0, 0] == pytest.approx(4 * ki * 0.2)


def test_action_along():
    z = np.array([[0.0, 0.1, 0.2], [0.0, 0.1, np.nan]])
    hm = HeightMap(np.array([10.0, 20.0]), 2.0, z)
    u = action_along(hm, np.array([[11.0, 20.0], [12.0, 21.0], [100.0, 0.0], [14.0, 22.0]]))
    np.testing.assert_allclose(u, [0.05, 0.1, 0.2, 0.1])  # NaN node: nearest footprint value
    # outside the grid: the value at the nearest point of its edge (thesis 5.1.2: the grid
    # spans the footprint, which reaches past the laser's samples; it was 0, no correction)
    out = np.array([[5.0, 20.0], [11.0, 10.0], [11.0, 30.0], [20.0, 19.0], [5.0, 40.0]])
    np.testing.assert_allclose(action_along(hm, out), [0.0, 0.05, 0.05, 0.2, 0.0])
    act, _ = smf_update(SmfState(), HeightMap(np.zeros(2), 1.0, np.full((3, 3), 0.1)), Job())
    assert isinstance(act, ControlAction)
    np.testing.assert_allclose(act.sample(np.array([[1.0, 1.0]])), act.u.z[1, 1])


def _line_traj(n=200, dt=0.016, v=50.0):
    t = np.arange(n) * dt
    xy = np.column_stack([v * t, 0 * t])
    return Trajectory(dt=dt, xy=xy, joints=np.column_stack([t, -t]), speed=np.full(n, v),
                      duration=(n - 1) * dt, path=Toolpath(points=xy[[0, -1]], width=1.5))


def test_retime_constant_action():
    tr = _line_traj()
    out = retime_trajectory(tr, np.full(len(tr.xy), 0.25))  # speed / 1.25 = 0.8 c_nom
    assert out.dt == tr.dt
    assert out.duration == pytest.approx(tr.duration / 0.8, abs=tr.dt)
    np.testing.assert_allclose(out.xy[[0, -1]], tr.xy[[0, -1]], atol=1e-9)
    spacing = np.linalg.norm(np.diff(out.xy, axis=0), axis=1)
    np.testing.assert_allclose(spacing, 0.8 * 50 * tr.dt, rtol=0.01)  # Fig. 5-6 spacing
    np.testing.assert_allclose(out.speed, 40.0, rtol=1e-9)
    assert np.allclose(out.xy[:, 1], 0)
    assert out.joints.shape == (len(out.xy), 2)


@given(st.floats(-0.9, 3.0))
def test_retime_speed_within_30_percent(uval):
    tr = _line_traj(n=50)
    u = np.full(50, uval)
    u[::7] = -uval / 2
    out = retime_trajectory(tr, u)
    assert np.all(out.speed >= 0.7 * 50 - 1e-9) and np.all(out.speed <= 1.3 * 50 + 1e-9)
    assert abs(out.duration - (len(out.xy) - 1) * out.dt) < 1e-12
    np.testing.assert_allclose(out.xy[-1], tr.xy[-1], atol=1e-9)


def test_speed_controller_end_to_end_volume_per_mm():
    # c-controller: volume per mm scales with (1 + u) when the flow is held constant
    tr = _line_traj()
    u = np.where(tr.xy[:, 0] < 80, 0.2, -0.1)
    out = retime_trajectory(tr, u)
    x = out.xy[:, 0]
    ds = np.gradient(x)
    # constant flow per sample => volume per mm ~ 1/spacing
    ratio = np.median(ds[x > 100]) / np.median(ds[(x > 10) & (x < 60)])
    assert ratio == pytest.approx(1.2 / 0.9, rel=0.02)


def test_footprint_as_union_of_part_and_scaffold():
    part = Region(rings=(square(20, 20, 80, 40),), parent=np.array([-1]))
    scaffold = Region(rings=(square(0, 0, 100, 60), square(20, 20, 80, 40, ccw=False)),
                      parent=np.array([-1, 0]))
    xyz = samples_on(lambda x, y: 1 + 0 * x)
    both = surface_from_samples(xyz, (part, scaffold), 1.0)
    x, y = both.grid()
    assert both.origin.tolist() == [0.0, 0.0] and (len(x), len(y)) == (101, 61)
    assert np.isfinite(both.z[30, 50]) and np.isfinite(both.z[10, 10])
    only = surface_from_samples(xyz, part, 1.0)
    assert only.origin.tolist() == [20.0, 20.0]


def test_grid_values_equal_linearndinterpolator():
    from scipy.interpolate import LinearNDInterpolator
    rng = np.random.default_rng(5)
    xyz = samples_on(lambda x, y: np.sin(x / 7) + np.cos(y / 5), n=3000, seed=4)
    xyz[:, :2] += rng.normal(0, 0.01, (len(xyz), 2))
    hm = surface_from_samples(xyz, None, 0.7, bin_mm=0)
    x, y = hm.grid()
    xx, yy = np.meshgrid(x, y)
    from scipy.spatial import Delaunay
    in_hull = Delaunay(xyz[:, :2]).find_simplex(np.column_stack([xx.ravel(), yy.ravel()]))
    in_hull = (in_hull >= 0).reshape(xx.shape)
    ours = np.isfinite(hm.z)
    assert np.count_nonzero(ours & ~in_hull) == 0
    assert ours.sum() > 0.99 * in_hull.sum()
    ref = LinearNDInterpolator(xyz[:, :2], xyz[:, 2])(xx[ours], yy[ours])
    np.testing.assert_allclose(hm.z[ours], ref, atol=1e-9)


def test_ring_samples_binned_keep_the_surface():
    # measurement rings 3 mm apart sampled every 0.25 mm (laser 200 Hz at 50 mm/s)
    t = np.arange(0, 2 * np.pi, 0.25 / 40)
    pts = [np.column_stack([50 + r * np.cos(t[: int(len(t) * r / 40)] * 40 / r),
                            30 + r * np.sin(t[: int(len(t) * r / 40)] * 40 / r)])
           for r in np.arange(1.5, 29, 3.0)]
    xy = np.vstack(pts)
    z = 2 + 0.01 * xy[:, 0] + np.random.default_rng(0).normal(0, 0.01, len(xy))
    reg = Region(rings=(np.column_stack([50 + 28 * np.cos(t[::40]), 30 + 28 * np.sin(t[::40])]),),
                 parent=np.array([-1]))
    hm = surface_from_samples(np.column_stack([xy, z]), reg, 1.0)
    gx, gy = hm.grid()
    ref = 2 + 0.01 * gx[None, :] + 0 * gy[:, None]
    ok = np.isfinite(hm.z)
    assert ok.sum() > 2000
    assert np.abs(hm.z[ok] - ref[ok]).max() < 0.04
    assert np.sqrt(np.mean((hm.z[ok] - ref[ok]) ** 2)) < 0.01  # below the laser noise


@given(st.integers(0, 2 ** 31 - 1), st.floats(0.05, 1.0), st.floats(0.05, 1.0))
def test_smf_update_respects_saturation_planes(seed, sat, isat):
    rng = np.random.default_rng(seed)
    job = Job().replace(**{"feedback.saturation": sat, "feedback.integral_saturation": isat})
    state = SmfState()
    for k in range(4):
        ny, nx = rng.integers(3, 12, 2)
        z = rng.normal(0, 2.0, (ny, nx))
        z[rng.random((ny, nx)) < 0.2] = np.nan
        origin = rng.integers(-3, 3, 2).astype(float)
        act, state = smf_update(state, HeightMap(origin, 1.0, z), job)
        ok = np.isfinite(z)
        assert np.array_equal(np.isfinite(act.u.z), ok)
        assert np.all(np.abs(act.u.z[ok]) <= sat + 1e-12)
        assert np.all(np.abs(state.integral.z[ok]) <= isat + 1e-12)
        np.testing.assert_allclose(act.u.z[ok], np.clip(act.unsaturated.z[ok], -sat, sat))
        assert state.k == k + 1


def test_retime_moves_piece_starts():
    tr = _line_traj(n=101)
    tr = Trajectory(dt=tr.dt, xy=tr.xy, joints=tr.joints, speed=tr.speed, duration=tr.duration,
                    path=tr.path, pieces=np.array([0, 50]))
    out = retime_trajectory(tr, np.full(101, 0.25))
    assert out.pieces.tolist() == [0, 62] or out.pieces.tolist() == [0, 63]


def test_smf_step_end_to_end():
    from icefab.feedback import smf_step
    job = Job()
    dh_m = 4 * 0.25
    reg = frame_region()
    # the part is 0.2 mm too low on the left half, 0.1 mm too high on the right
    xyz = samples_on(lambda x, y: 10 - np.where(x < 50, 0.2, -0.1), n=8000)
    act, st = smf_step(xyz, reg, 10.0, SmfState(), job)
    x, y = act.u.grid()
    left = np.isfinite(act.u.z) & (x[None, :] < 45)
    right = np.isfinite(act.u.z) & (x[None, :] > 55)
    # U = Kp E + Ki* E (k = 1, no derivative), E = 0.2 / dh_m and -0.1 / dh_m
    np.testing.assert_allclose(act.u.z[left], (1 + 0.33) * 0.2 / dh_m, atol=1e-9)
    np.testing.assert_allclose(act.u.z[right], -(1 + 0.33) * 0.1 / dh_m, atol=1e-9)
    assert st.k == 1


def test_smf_update_checks_its_overrides_and_keeps_its_own_state():
    # a tester's reversed limits or negative integral limit flipped the action's sign, a
    # NaN gain made it NaN, and a refilled error buffer zeroed the derivative term (the
    # state kept the caller's array)
    from icefab.errors import ConfigError, GeometryError

    E = HeightMap(np.zeros(2), 1.0, np.full((5, 6), 0.1))
    for kw in ({"limits": (0.3, -0.3)}, {"integral_limit": -1.0},
               {"gains": (float("nan"), 0.33, 0.03)}, {"gains": (1.0, 0.0)},
               {"limits": (float("nan"), 0.3)}):
        with pytest.raises(ConfigError):
            smf_update(SmfState(), E, Job(), **kw)
    smf_update(SmfState(), E, Job(), integral_limit=np.inf, limits=(-np.inf, np.inf))
    for bad in (HeightMap(np.zeros(2), 0.0, np.zeros((3, 3))),
                HeightMap(np.zeros(2), 1.0, np.zeros(3)), None):
        with pytest.raises(GeometryError, match="error surface"):
            smf_update(SmfState(), bad, Job())
    buf, fresh = np.empty((5, 6)), []
    s1 = s2 = SmfState()
    for e in (0.0, 0.1, 0.3):
        buf[:] = e
        u1, s1 = smf_update(s1, HeightMap(np.zeros(2), 1.0, buf), Job())
        u2, s2 = smf_update(s2, HeightMap(np.zeros(2), 1.0, np.full((5, 6), e)), Job())
        fresh.append(float(np.nanmax(u2.d)))
        assert float(np.nanmax(u1.d)) == fresh[-1]
    assert fresh[-1] > 0
