"""Virtual cell: deposition and the simulated laser (icefab.sim)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, strategies as st

from icefab.sim import (SimulationError, deposit, deposit_pulses, empty_surface,
                        laser_measure, laser_positions, sample_surface)
from icefab.core import HeightMap

G = 0.5


def _map(lo=(-20.0, -20.0), hi=(80.0, 80.0), g=G):
    return empty_surface(np.array(lo), np.array(hi), g)


def _line(p0, p1, speed, flow, dt=0.016):
    """Samples at constant speed from p0 to p1 with ``flow * dt`` mm^3 per step."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = np.linalg.norm(p1 - p0)
    n = int(round(length / (speed * dt)))
    t = np.linspace(0, 1, n + 1)[:, None]
    xy = p0 + t * (p1 - p0)
    vol = np.full(len(xy), flow * length / speed / n)
    vol[-1] = 0.0
    return xy, vol


@given(st.lists(st.tuples(st.floats(0, 60), st.floats(0, 60)), min_size=1, max_size=30),
       st.floats(0.3, 4.0), st.floats(0.0, 5.0))
def test_volume_is_conserved_away_from_the_edge(points, width, vol):
    xy = np.array(points, dtype=float)
    rng = np.random.default_rng(len(points))
    volume = rng.uniform(0, vol, len(xy))
    out = deposit(_map(), xy, volume, width)
    assert out.z.sum() * G * G == pytest.approx(volume.sum(), rel=1e-9, abs=1e-12)
    assert np.all(out.z >= 0)


def test_volume_is_conserved_with_several_paths_and_widths():
    xy = np.array([[0, 0], [10, 3], [20, 20], [5, 40], [30, 30], [30, 31.0]])
    volume = np.array([1.0, 2.0, 0.5, 3.0, 1.0, 0.2])
    width = np.array([1.5, 1.5, 3.0, 3.0, 0.4, 0.4])
    out = deposit(_map(), xy, volume, width, path_starts=[0, 3])
    assert out.z.sum() * G * G == pytest.approx(volume.sum(), rel=1e-9)


@pytest.mark.parametrize("speed,flow,width", [(25.0, 9.375, 1.5), (125.0, 93.75, 3.0),
                                               (50.0, 10.0, 2.0)])
def test_straight_path_leaves_a_strip_of_height_q_over_wv(speed, flow, width):
    # strip along x at y = 10.25 (not grid aligned)
    xy, vol = _line((0.0, 10.25), (60.0, 10.25), speed, flow)
    out = deposit(_map(), xy, vol, width)
    xs, ys = out.grid()
    h = flow / (width * speed)
    col = out.z[:, np.searchsorted(xs, 30.0)]
    # cross-section: area = h * w exactly, fully covered cells sit at h
    assert col.sum() * G == pytest.approx(h * width, rel=1e-9)
    inside = np.abs(ys - 10.25) <= width / 2 - G / 2
    assert np.allclose(col[inside], h, rtol=1e-9)
    outside = np.abs(ys - 10.25) >= width / 2 + G / 2
    assert np.all(col[outside] == 0)


def test_diagonal_path_strip_height_and_width():
    speed, flow, width = 40.0, 12.0, 3.0
    xy, vol = _line((0.0, 0.0), (50.0, 50.0), speed, flow)
    out = deposit(_map(), xy, vol, width)
    xs, ys = out.grid()
    X, Y = np.meshgrid(xs, ys)
    d = np.abs(X - Y) / np.sqrt(2)  # distance from the path's line
    mid = (X + Y > 20) & (X + Y < 80)
    h = flow / (width * speed)
    core = mid & (d < width / 2 - G)
    assert np.allclose(out.z[core], h, rtol=1e-9)
    assert np.all(out.z[mid & (d > width / 2 + G)] == 0)


def test_stationary_sample_covers_a_w_by_w_square():
    out = deposit(_map(), np.array([[10.0, 10.0]]), np.array([9.0]), 3.0)
    assert out.z.sum() * G * G == pytest.approx(9.0)
    assert out.z.max() == pytest.approx(1.0)  # 9 mm^3 over 3 x 3 mm
    assert np.count_nonzero(out.z) == 7 * 7  # [8.5, 11.5]^2: 5 x 5 full, half-covered rim


def test_volume_off_the_map_is_lost_not_moved():
    out = deposit(_map(), np.array([[-20.0, 30.0], [-20.0, 40.0]]), np.array([10.0, 0.0]), 2.0)
    assert 0 < out.z.sum() * G * G < 10.0


def test_deposit_rejects_bad_input():
    with pytest.raises(SimulationError, match="width"):
        deposit(_map(), np.zeros((2, 2)), np.ones(2), 0.0)
    with pytest.raises(SimulationError, match=r"\(n, 2\)"):
        deposit(_map(), np.zeros((2, 3)), np.ones(2), 1.0)
    with pytest.raises(SimulationError, match="finite"):
        deposit(_map(), np.array([[0, np.nan], [1, 1]]), np.ones(2), 1.0)


def test_evenly_spaced_drops_leave_a_strip_of_drop_over_width_times_spacing():
    # 40 mm at 50 mm/s sampled every 16 ms; a drop every 10 ms = every 0.5 mm
    n = 51
    xy = np.column_stack([np.linspace(0.0, 40.0, n), np.full(n, 10.0)])
    t = (np.arange(80) + 0.5) * 0.01
    out = deposit_pulses(_map(), xy, 0.8 / 50, t, 0.375, 1.5)
    assert out.z.sum() * G * G == pytest.approx(80 * 0.375, rel=1e-12)
    xs, ys = out.grid()
    inner = (xs > 2) & (xs < 38)
    # 0.375 mm^3 over 1.5 mm x 0.5 mm: 0.5 mm high, whatever the cells the drops straddle
    assert np.allclose(out.z[np.abs(ys - 10.0) < 0.5][:, inner], 0.5, rtol=1e-9)


def test_drops_crowded_where_the_nozzle_is_slow_pile_up():
    # the same 80 drops at a constant rate on a path whose second half is run twice as
    # slowly: the second half gets two thirds of the drops on the same length
    t_knots = np.array([0.0, 0.4, 1.2])
    s_knots = np.array([0.0, 20.0, 40.0])
    ts = np.arange(0.0, 1.2 + 1e-9, 0.016)
    xy = np.column_stack([np.interp(ts, t_knots, s_knots), np.full(len(ts), 10.0)])
    t = (np.arange(80) + 0.5) * (ts[-1] / 80)
    out = deposit_pulses(_map(), xy, 0.016, t, 0.375, 1.5)
    xs, ys = out.grid()
    row = out.z[np.argmin(np.abs(ys - 10.0))]
    fast, slow = row[(xs > 3) & (xs < 17)], row[(xs > 23) & (xs < 37)]
    assert slow.mean() == pytest.approx(2 * fast.mean(), rel=0.05)


def test_drops_at_a_stop_and_bad_input():
    xy = np.zeros((5, 2))  # the nozzle does not move: every drop on a w x w square
    out = deposit_pulses(_map(), xy, 0.016, np.array([0.01, 0.02, 0.03]), 0.5, 1.0)
    assert out.z.sum() * G * G == pytest.approx(1.5)
    # a 1 mm square centred on a node: 1.5 mm high, its rim on the 8 neighbours' halves
    assert out.z.max() == pytest.approx(1.5) and np.count_nonzero(out.z) == 9
    for args in [(np.zeros((3, 3)), 0.016, [0.0], 1.0, 1.0),
                 (xy, 0.0, [0.0], 1.0, 1.0),
                 (xy, 0.016, [0.02, 0.01], 1.0, 1.0),
                 (xy, 0.016, [0.0], np.nan, 1.0),
                 (xy, 0.016, [0.0], 1.0, 0.0)]:
        with pytest.raises(SimulationError, match="deposit_pulses"):
            deposit_pulses(_map(), *args)


# --------------------------------------------------------------------------- laser


def _plane(z0=0.0, slope=0.0):
    s = _map()
    xs, ys = s.grid()
    return HeightMap(origin=s.origin, spacing=s.spacing,
                     z=z0 + slope * np.broadcast_to(xs, s.z.shape).copy())


def test_laser_samples_every_speed_over_rate_with_the_configured_noise():
    path = np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 60.0], [0.0, 60.0]])
    tagged, true = laser_positions(path, True, speed_mm_s=50.0, rate_hz=100.0, latency_s=0.0)
    step = np.linalg.norm(np.diff(tagged, axis=0), axis=1)
    assert np.allclose(step, 0.5)
    assert len(tagged) == 480 + 1
    rng = np.random.default_rng(5)
    xyz = laser_measure(_plane(2.0), tagged, true, noise_mm=0.05, rng=rng)
    assert xyz.shape == (481, 3)
    assert np.array_equal(xyz[:, :2], tagged)
    # 481 samples: the std estimate is within ~10 % (3.3 sigma of its sampling error)
    assert np.std(xyz[:, 2]) == pytest.approx(0.05, rel=0.11)
    assert np.mean(xyz[:, 2]) == pytest.approx(2.0, abs=4 * 0.05 / np.sqrt(481))


def test_laser_without_noise_reads_the_surface():
    surf = _plane(1.0, 0.02)
    tagged, true = laser_positions(np.array([[0.0, 5.0], [40.0, 5.0]]), False,
                                   speed_mm_s=50.0, rate_hz=100.0, latency_s=0.0)
    xyz = laser_measure(surf, tagged, true, noise_mm=0.0, rng=np.random.default_rng(0))
    assert np.allclose(xyz[:, 2], 1.0 + 0.02 * tagged[:, 0])
    assert np.allclose(sample_surface(surf, tagged), xyz[:, 2])


@pytest.mark.parametrize("direction", [1, -1])
def test_laser_latency_lags_the_reading_along_the_path(direction):
    speed, latency, slope = 50.0, 0.004, 0.01  # lag 0.2 mm along the path
    surf = _plane(1.0, slope)
    ends = np.array([[5.0, 5.0], [45.0, 5.0]])[::direction]
    tagged, true = laser_positions(ends, False, speed_mm_s=speed, rate_hz=100.0,
                                   latency_s=latency)
    xyz = laser_measure(surf, tagged, true, noise_mm=0.0, rng=np.random.default_rng(0))
    later = slice(1, None)  # the first sample is clamped at the path start
    expected = 1.0 + slope * (tagged[:, 0] - direction * speed * latency)
    assert np.allclose(xyz[later, 2], expected[later])
    assert np.allclose(np.linalg.norm(tagged[later] - true[later], axis=1), speed * latency)


def _closed(points, speed, dt=0.016):
    """Resample a closed polygon at constant speed; the sample count sets the volume."""
    from icefab.sim import _resample
    xy, _ = _resample(np.asarray(points, float), True, speed * dt)
    return xy


@pytest.mark.parametrize("shape", ["square", "circle"])
def test_closed_path_leaves_an_even_strip_at_its_corners(shape):
    # mitre joins: no double deposit on the inside of a turn, no gap on the outside
    width, dh = 2.0, 0.25
    if shape == "square":
        ring = np.array([[10.0, 10.0], [40.0, 10.0], [40.0, 40.0], [10.0, 40.0]])
    else:
        t = np.linspace(0, 2 * np.pi, 400, endpoint=False)
        ring = 25.0 + 12.0 * np.column_stack([np.cos(t), np.sin(t)])
    xy = _closed(ring, 125.0)[:-1]  # closed: the first point is not repeated
    vol = width * dh * np.linalg.norm(np.roll(xy, -1, axis=0) - xy, axis=1)
    out = deposit(_map(), xy, vol, width, closed=True)
    assert out.z.sum() * G * G == pytest.approx(vol.sum(), rel=1e-9)
    xs, ys = out.grid()
    X, Y = np.meshgrid(xs, ys)
    pts = np.column_stack([X.ravel(), Y.ravel()])
    if shape == "square":
        d = np.abs(np.maximum(np.abs(X - 25.0), np.abs(Y - 25.0)) - 15.0)
    else:
        d = np.abs(np.hypot(X - 25.0, Y - 25.0) - 12.0)
    core = d < width / 2 - G
    assert np.allclose(out.z[core], dh, rtol=1e-9), (out.z[core].min(), out.z[core].max())
    assert np.all(out.z[d > width / 2 + G] == 0)
    assert len(pts) == out.z.size


# --------------------------------------------------------------------------- liquid flow


def _two_strips(gap):
    """Two parallel 1.5 mm strips 0.25 mm high along x, ``gap`` mm apart, on a flat base."""
    s = _map((-5.0, -5.0), (45.0, 15.0))
    out = s
    for y in (5.0, 5.0 + 1.5 + gap):
        xy, vol = _line((5.0, y), (35.0, y), 25.0, 25.0 * 1.5 * 0.25)
        out = deposit(out, xy, vol, 1.5)
    return s, out


def test_liquid_fills_a_narrow_gap_between_paths_and_keeps_its_volume():
    from icefab.sim import level_liquid
    base, wet = _two_strips(1.0)
    xs, ys = wet.grid()
    col = np.searchsorted(xs, 20.0)
    gap_rows = (ys > 5.75 + G) & (ys < 6.75 - G)
    assert np.all(wet.z[gap_rows, col] == 0)
    out = level_liquid(base.z, wet.z, G, 1.0)
    assert out.sum() == pytest.approx(wet.z.sum(), rel=1e-12)
    assert np.all(out >= 0)
    assert np.all(out[gap_rows, col] > 0.1)  # the gap got liquid from both sides
    # a gap wider than twice the spread stays dry
    base, wide = _two_strips(3.0)
    out = level_liquid(base.z, wide.z, G, 1.0)
    gap_rows = (ys > 5.75 + 1.0 + G) & (ys < 8.75 - 1.0 - G)
    assert np.all(out[gap_rows, col] == 0)


def test_liquid_on_a_level_layer_stays_put_and_fills_a_dent_below():
    from icefab.sim import level_liquid
    s = _map((0.0, 0.0), (20.0, 20.0))
    liquid = np.zeros_like(s.z)
    liquid[5:35, 5:35] = 0.25
    flat = level_liquid(s.z, liquid, G, 1.0)
    assert np.allclose(flat, liquid)
    below = np.zeros_like(s.z)
    below[18:22, 18:22] = -0.2  # a dent in the frozen surface
    out = level_liquid(below, liquid, G, 1.0)
    assert out.sum() == pytest.approx(liquid.sum(), rel=1e-12)
    assert out[18:22, 18:22].mean() > 0.25 + 0.05  # liquid ran into the dent
