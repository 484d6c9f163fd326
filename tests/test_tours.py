"""Continuous tours (issue 15): consecutive paths joined through travel the robot does not
stop for, the valve off over it (icefab.paths.join_tours, Toolpath.off)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import shapely
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from icefab import Job, flow
from icefab.core import (OFF, ON1, LayerMotion, LayerPaths, Toolpath, Toolpaths,
                         point_states, tour_members)
from icefab.errors import IcefabError, StackFileError
from icefab.motion import _base_points, plan_motion, plan_paths_durations
from icefab.paths import (RING_TO_RING_MAX_TURN_DEG, TOUR_MIN_MEMBER_MM, join_tours,
                          tour_turn_deg)
from icefab.resultfiles import load_toolpaths, save_toolpaths
from icefab.sim.plans import layer_valves, plan_layer, plan_layer_motion, valve_segments
from test_variable_width import _linear_table_job  # every pulse drops 0.25 mm^3

DH = 0.25


def _fill(points, width=1.5, closed=False, material="part", **kw) -> Toolpath:
    return Toolpath(points=np.asarray(points, dtype=np.float64), z=DH, material=material,
                    role="fill", closed=closed, width=width, layer=0, **kw)


def _in_line(gap=10.0, length=40.0):
    """Two fill lines along x, the second starting ``gap`` mm past the first's end."""
    return [_fill([[0.0, 0.0], [length, 0.0]]),
            _fill([[length + gap, 0.0], [2 * length + gap, 0.0]])]


def _travel(a: Toolpath, b: Toolpath) -> Toolpath:
    return Toolpath(points=np.array([a.polyline()[-1], b.points[0]]), z=DH, material="part",
                    role="travel", layer=0)


def _lines_distance(lines, xy):
    geoms = shapely.union_all([shapely.LineString(p.polyline()) for p in lines])
    return shapely.distance(geoms, shapely.points(xy))


def test_paths_in_line_become_one_tour_whose_travel_is_off():
    a, b = _in_line()
    (tour,) = join_tours([a, b], 240.0)
    assert not tour.closed and tour.depositing and tour.off is not None
    n_a = len(a.points)
    # off exactly from the first path's end to the second's start
    on = tour.segment_on()
    assert on[:n_a - 1].all() and on[-(len(b.points) - 1):].all()
    assert not on[n_a - 1:len(tour.points) - len(b.points)].any()
    st_ = point_states(tour)
    assert (st_[:n_a - 1] == ON1).all() and (st_[n_a - 1:-len(b.points)] == OFF).all()
    assert st_[-1] == OFF
    # the members come back as they were
    back = tour_members(tour)
    assert len(back) == 2
    for m, p in zip(back, (a, b)):
        np.testing.assert_array_equal(m.points, p.points)
        assert m.width == p.width and m.widths is None and m.off is None
    # G1 where the travel curve meets the paths: it leaves and arrives along them
    pts = tour.points
    leave = pts[n_a] - pts[n_a - 1]
    arrive = pts[-len(b.points)] - pts[-len(b.points) - 1]
    assert abs(np.arctan2(leave[1], leave[0])) < 1e-9
    assert abs(np.arctan2(arrive[1], arrive[0])) < 1e-9


def test_a_join_is_made_by_the_turn_it_needs():
    a, b = _in_line()
    assert tour_turn_deg(a.points[-1], np.array([1.0, 0]), b.points[0],
                         np.array([1.0, 0])) == pytest.approx(0.0)
    # a path that starts 10 mm behind the end of the last: the robot turns back and
    # round again (354 deg), joined only when allowed
    behind = _fill([[30.0, 0.5], [70.0, 0.5]])
    assert tour_turn_deg(a.points[-1], np.array([1.0, 0]), behind.points[0],
                         np.array([1.0, 0])) > 350.0
    assert len(join_tours([a, behind], 240.0)) == 2
    assert len(join_tours([a, behind], 360.0)) == 1
    # 0: no tours at all
    assert len(join_tours([a, b], 0.0)) == 2
    # other material, role or a measurement path: never joined
    assert len(join_tours([a, _fill(b.points, material="scaffold")], 360.0)) == 2
    meas = Toolpath(points=b.points, z=DH, material="part", role="measure", layer=0)
    assert len(join_tours([a, meas], 360.0)) == 2
    # ring to ring: a turn of 180 deg is too much between closed paths, not between open
    sq1 = _fill([[0, 0], [10, 0], [10, 10], [0, 10]], closed=True)
    sq2 = _fill([[2, 2], [8, 2], [8, 8], [2, 8]], closed=True)
    turn = tour_turn_deg(np.zeros(2), np.array([0, -1.0]), np.array([2.0, 2.0]),
                         np.array([1.0, 0]))
    assert RING_TO_RING_MAX_TURN_DEG < turn <= 240.0
    assert len(join_tours([sq1, sq2], 240.0)) == 2
    open1 = _fill([[0, 10], [0, 0]])
    assert len(join_tours([open1, _fill(sq2.points)], 240.0)) == 1


def test_a_path_too_short_to_be_sampled_ends_its_tour():
    a, b = _in_line(gap=3.0)
    tiny = _fill([[43.0 + 2.0, 0.0], [45.0 + TOUR_MIN_MEMBER_MM / 2, 0.0]])
    c = _fill([[b.points[-1, 0] + 3.0, 0.0], [b.points[-1, 0] + 40.0, 0.0]])
    tours = join_tours([a, tiny, b, c], 240.0)
    assert len(tours) == 2 and len(tour_members(tours[0])) == 2
    assert len(tour_members(tours[1])) == 2


def test_a_tours_trajectory_is_off_over_its_travel_and_faster_than_its_paths_apart():
    job = Job()
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    tr = plan_motion(tour, job)
    assert tr.widths is not None and tr.widths.shape == (len(tr.xy),)
    d = _lines_distance([a, b], flow.trajectory_part_xy(tr, "part", job))
    # on the lines: the path's width; on the travel curve: nothing
    assert np.all(tr.widths[d > 1e-6] == 0.0)
    assert np.all(tr.widths[tr.widths > 0] == 1.5)
    assert np.count_nonzero(tr.widths == 0) >= 3
    # no rest stop between the two paths: one piece, and faster than A, travel, B apart
    assert len(tr.pieces) <= 1
    apart = plan_paths_durations([a, _travel(a, b), b], job, layer=0).sum()
    assert tr.duration < apart - 0.1


def test_the_valve_switches_exactly_where_the_tours_paths_end_and_start():
    job = Job()
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    tr = plan_motion(tour, job)
    assert tr.on_spans.shape == (2, 2) and tr.on_spans[0, 0] == 0.0
    assert tr.on_spans[-1, 1] == tr.duration
    # the nozzle (the samples, linear between them) is at the paths' ends at the switches
    x = np.interp(tr.on_spans.ravel(), tr.t, tr.xy[:, 0]) - tr.xy[0, 0]
    np.testing.assert_allclose(x, [0.0, 40.0, 50.0, 90.0], atol=1e-9)
    # between two samples, not on one: the old valve switched at the sample after
    assert np.all(np.abs(tr.on_spans[0, 1] / tr.dt - np.rint(tr.on_spans[0, 1] / tr.dt)) > 1e-3)


def test_the_valve_pulses_only_over_the_tours_paths_each_its_own(tmp_path):
    job = _linear_table_job(tmp_path)
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    tr = plan_motion(tour, job)
    for mode in ("fm", "pwm"):
        jm = job.replace(**{"flow.mode": mode})
        prog = flow.plan_valves(tr, "part", jm)
        t = flow.pulse_times(prog)
        x = np.interp(t, tr.t, tr.xy[:, 0]) - tr.xy[0, 0]
        # no pulse over the travel, not even within a sample step of the paths' ends
        assert np.all((x <= 40.0 + 1e-9) | (x >= 50.0 - 1e-9)), mode
        assert np.all(t >= tr.on_spans[0, 0]) and np.all(t <= tr.on_spans[-1, 1])
        # each path lays its own volume, 40 mm x 1.5 mm x dh = 15 mm^3, and PWM starts its
        # periods afresh on each
        if mode == "fm":
            assert np.count_nonzero(x < 45.0) * 0.25 == pytest.approx(15.0, abs=0.25)
            assert np.count_nonzero(x > 45.0) * 0.25 == pytest.approx(15.0, abs=0.25)
        else:
            period = 1.0 / jm.flow.pwm_frequency_hz
            second = t[x > 45.0]
            # (instants on the controller's ticks)
            assert second[0] - tr.on_spans[1, 0] == pytest.approx(
                0.5 * period, abs=0.5 * jm.flow.tick_s + 1e-9)


def test_a_tours_speed_controlled_valve_still_switches_at_the_paths_ends(tmp_path):
    job = _linear_table_job(tmp_path).replace(**{"feedback.controller": "speed"})
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    tr = plan_motion(tour, job)
    (slow,), (prog,) = flow.replan_valves([tr], job, action=lambda xy: np.full(len(xy), 0.2))
    assert slow.duration > tr.duration
    x = np.interp(slow.on_spans.ravel(), slow.t, slow.xy[:, 0]) - slow.xy[0, 0]
    np.testing.assert_allclose(x, [0.0, 40.0, 50.0, 90.0], atol=1e-6)
    xp = np.interp(flow.pulse_times(prog), slow.t, slow.xy[:, 0]) - slow.xy[0, 0]
    assert np.all((xp <= 40.0 + 1e-6) | (xp >= 50.0 - 1e-6))


def test_the_simulator_lays_nothing_over_a_tours_travel(tmp_path):
    job = _linear_table_job(tmp_path)
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    from_paths = plan_layer(0, [tour], job)
    layer = LayerMotion(0, DH, (plan_motion(tour, job),))
    from_motion = plan_layer_motion(layer, job)
    for plan in (from_paths, from_motion):
        # the segments end exactly at the paths' ends
        ends = np.concatenate([plan.a[:, 0], plan.b[:, 0]])      # the part frame's x
        assert not np.any((ends > 40.0 + 1e-6) & (ends < 50.0 - 1e-6))
    assert from_paths.volume.sum() == pytest.approx(80.0 * 1.5 * DH, rel=1e-9)
    # the samples' speed integrates to their path within the motion's tolerance
    assert from_motion.volume.sum() == pytest.approx(80.0 * 1.5 * DH, rel=1e-3)
    # the valves' drops: a drop's strip does not reach over the travel either
    a_, b_, vol, *_rest = valve_segments(layer_valves(from_motion, job), job)
    assert len(vol) and vol.sum() == pytest.approx(80.0 * 1.5 * DH, abs=2 * 0.25)
    x0 = from_paths.a[0, 0]
    for p in (a_, b_):
        assert not np.any((p[:, 0] - x0 > 40.0 + 1e-6) & (p[:, 0] - x0 < 50.0 - 1e-6))


def test_toolpath_files_keep_the_tours(tmp_path):
    a, b = _in_line()
    (tour,) = join_tours([a, b], 240.0)
    other = _fill([[0, 5.0], [30, 5.0]], width=2.0)
    tp = Toolpaths((LayerPaths(0, DH, (tour, other), (0.0, 0.0)),), Job())
    save_toolpaths(tp, tmp_path / "tp.npz")
    (got, plain) = load_toolpaths(tmp_path / "tp.npz").layers[0].paths
    np.testing.assert_array_equal(got.off, tour.off)
    np.testing.assert_array_equal(point_states(got), point_states(tour))
    assert plain.off is None
    # off segments on a path that deposits nothing: a corrupt file
    with np.load(tmp_path / "tp.npz") as d:
        data = {k: d[k] for k in d.files}
    data["role"] = np.array([1, 3], dtype=np.int8)       # the tour made a travel move
    data["point_off"] = np.ones_like(data["point_off"])
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(StackFileError, match="point_off"):
        load_toolpaths(tmp_path / "bad.npz")


def test_trajectory_files_keep_the_valves_switches(tmp_path):
    from icefab.core import BuildMotion
    from icefab.resultfiles import load_trajectories, save_trajectories
    job = Job()
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    other = _fill([[0, 5.0], [30, 5.0]], width=2.0)
    trs = (plan_motion(other, job), plan_motion(tour, job), plan_motion(other, job))
    motion = BuildMotion(layers=(LayerMotion(0, DH, trs), LayerMotion(1, 2 * DH, trs[1:2])),
                         job=job, robot="scara", joint_names=("j1", "j2", "j3"))
    f = tmp_path / "t.npz"
    save_trajectories(motion, f, block_samples=1)
    back = load_trajectories(f)
    for layer in back.layers:
        for got, want in zip(layer.trajectories, trs if layer.index == 0 else trs[1:2]):
            if want.on_spans is None:
                assert got.on_spans is None
            else:
                np.testing.assert_array_equal(got.on_spans, want.on_spans)
    # and the valve follows them as it did before the file
    prog = flow.plan_valves(back.layers[1].trajectories[0], "part", job)
    np.testing.assert_array_equal(prog.ticks, flow.plan_valves(trs[1], "part", job).ticks)
    with np.load(f) as z:
        data = {k: z[k] for k in z.files}
    for bad in (data["on_spans"][::-1], data["on_spans"] + 100.0):
        np.savez(tmp_path / "bad.npz", **{**data, "on_spans": bad})
        with pytest.raises(StackFileError, match="bad.npz.*on_spans"):
            load_trajectories(tmp_path / "bad.npz")
    # a version 5 file has no spans: its tours' valves switch at the samples, as they did
    old = {k: v for k, v in data.items() if k not in ("span_owner", "on_spans")}
    np.savez(tmp_path / "v5.npz", **{**old, "version": np.array(5)})
    assert load_trajectories(tmp_path / "v5.npz").layers[1].trajectories[0].on_spans is None


def test_spans_out_of_order_are_refused_by_name():
    job = Job()
    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    tr = plan_motion(tour, job)
    bad = dataclasses.replace(tr, on_spans=tr.on_spans[::-1].copy())
    with pytest.raises(IcefabError, match="on_spans must be in order"):
        flow.plan_valves(bad, "part", job)
    with pytest.raises(IcefabError, match="on_spans must be finite instants"):
        flow.plan_valves(dataclasses.replace(tr, on_spans=tr.on_spans + tr.duration), "part",
                         job)


def test_an_off_mask_that_is_not_one_bool_per_point_is_refused():
    a, b = _in_line()
    bad = _fill(a.points, off=np.array([True]))
    with pytest.raises(IcefabError, match="one per point"):
        plan_motion(bad, Job())
    all_off = _fill(a.points, off=np.array([True, False]))
    with pytest.raises(IcefabError, match="no segment depositing"):
        plan_motion(all_off, Job())


@st.composite
def _open_paths(draw):
    """Open fill paths of 2-5 points, each starting a little beyond the last one's end."""
    n = draw(st.integers(1, 6))
    out, cur = [], np.zeros(2)
    for _ in range(n):
        k = draw(st.integers(2, 5))
        steps = np.array(draw(st.lists(st.tuples(st.floats(-20, 20), st.floats(-20, 20)),
                                       min_size=k, max_size=k)))
        pts = cur + np.cumsum(steps, axis=0)
        if np.any(np.linalg.norm(np.diff(pts, axis=0), axis=1) < 1e-3):
            continue
        out.append(_fill(pts, width=draw(st.sampled_from([1.5, 3.0]))))
        cur = pts[-1]
    return out


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_open_paths(), st.sampled_from([0.0, 60.0, 240.0, 360.0]))
def test_tours_give_back_their_paths_in_order(paths, max_turn):
    tours = join_tours(paths, max_turn)
    members = [m for t in tours for m in tour_members(t)]
    assert len(members) == len(paths)
    for m, p in zip(members, paths):
        np.testing.assert_array_equal(m.points, p.points)
        assert m.width == pytest.approx(p.width)
    for t in tours:
        if t.off is not None:
            # what deposits is exactly its members' length; states OFF over the travel
            on = t.segment_on()
            seg = np.linalg.norm(np.diff(t.polyline(), axis=0), axis=1)
            assert seg[on].sum() == pytest.approx(sum(m.length for m in tour_members(t)))
            assert np.array_equal(point_states(t)[:-1] == OFF, ~on)


def test_every_path_of_the_demo_mugs_tours_is_deposited():
    """On the demo mug's layers (default job): every path a tour joins gets samples of its
    own width (none falls between two samples, ``TOUR_MIN_MEMBER_MM``), and the valve's
    width x speed integrates to the paths' area within half a sample step per switch."""
    from icefab.demo import demo_mug
    from icefab.motion import plan_paths_motion
    from icefab.paths import plan_layer
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh

    job = Job().replace(**{"cell.cpus": 1})
    stack = add_scaffold(slice_mesh(demo_mug(), job), job)
    tours = 0
    for k in (3, 40, 90, 130, 170):
        lp = plan_layer(stack.layers[k], job)
        for p, tr in zip(lp.paths, plan_paths_motion(lp.paths, job, layer=k)):
            if p.off is None:
                continue
            tours += 1
            on = p.segment_on()
            runs = np.diff(np.r_[0, on.astype(np.int8), 0])
            sampled = np.diff(np.r_[0, (tr.widths > 0).astype(np.int8), 0])
            assert np.count_nonzero(sampled == 1) == np.count_nonzero(runs == 1), (k, p.role)
            # the valve switches where the nozzle passes each path's ends: within the
            # smoothing of the followed path and the chord of one sample step (2 mm at 125
            # mm/s) across a travel curve's bend, 0.03 mm on these layers; switching at a
            # sample is up to a whole step off
            first, end = np.flatnonzero(runs == 1), np.flatnonzero(runs == -1)
            switch_points = _base_points(p, job)[np.column_stack([first, end]).ravel()]
            at = np.column_stack([np.interp(tr.on_spans.ravel(), tr.t, tr.xy[:, j])
                                  for j in (0, 1)])
            assert np.linalg.norm(at - switch_points, axis=1).max() <= 0.05, (k, p.role)
            poly, w = p.polyline(), p.polyline_widths()
            seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
            area = float(np.sum(seg[on] * 0.5 * (w[:-1] + w[1:])[on]))
            got = float(np.trapezoid(tr.widths * tr.speed, dx=tr.dt))
            step = float(tr.speed.max()) * tr.dt
            switches = 2 * np.count_nonzero(runs == 1) - 2
            assert abs(got - area) <= switches * 0.5 * step * w.max() + 1e-3 * area, (k, got,
                                                                                   area)
    assert tours > 10


def test_the_paths_summary_counts_the_tours_and_their_travel():
    from icefab.cli.paths_cmd import PathTally
    from icefab.resultfiles import pack_paths

    a, b = _in_line(gap=10.0)
    (tour,) = join_tours([a, b], 240.0)
    tally = PathTally(Job())
    tally.add_packed(pack_paths([tour, _fill([[0, 5.0], [30, 5.0]])]))
    n, joined, curve = tally.tours["part fill"]
    on = tour.segment_on()
    seg = np.linalg.norm(np.diff(tour.points, axis=0), axis=1)
    assert (n, joined) == (1, 2) and curve == pytest.approx(seg[~on].sum())
    assert curve == pytest.approx(10.0) and tally.counts["part fill"] == 2   # in line


def test_the_simulator_lays_a_tours_paths_as_it_lays_them_apart():
    # a closed ring keeps the mitred joint where it closes inside a tour
    ring = _fill([[0.0, 0.0], [20.0, 0.0], [20.0, 20.0], [0.0, 20.0]], closed=True)
    line = _fill([[-3.0, -2.0], [-3.0, 30.0]])
    (tour,) = join_tours([ring, line], 240.0)
    job = Job()
    joined, apart = plan_layer(0, [tour], job), plan_layer(0, [ring, line], job)
    for field in ("a", "b", "volume", "half_width", "n0", "n1", "ext"):
        np.testing.assert_allclose(getattr(joined, field), getattr(apart, field),
                                   err_msg=field)


def test_a_tour_ends_where_it_would_grow_too_long():
    a, b = _in_line(gap=10.0)
    c = _fill([[b.points[-1, 0] + 10.0, 0.0], [b.points[-1, 0] + 50.0, 0.0]])
    tours = join_tours([a, b, c], 240.0, max_length_mm=100.0)   # 40 + 10 + 40, then no
    assert [len(tour_members(t)) for t in tours] == [2, 1]
    assert len(join_tours([a, b, c], 240.0)) == 1


def test_long_paths_fit_the_robot_controllers_store():
    """A measured layer of a 260 mm square: every measurement path and tour is planned
    within the samples the robot controller stores of one path (before, the bunny's
    measurement spirals took up to 14 318 of its 8 192 and the build was refused)."""
    from icefab import geometry as geo
    from icefab.core import Layer
    from icefab.motion import plan_paths_motion
    from icefab.paths import plan_layer
    from icefab.robots import CONTROLLER_PATH_POINTS

    job = Job().replace(**{"cell.ee_origin_mm": [340.0, 0.0], "materials.part.fill_pattern":
                           "zigzag", "materials.part.gap_fill": False})
    sq = np.array([[-130.0, -130.0], [130.0, -130.0], [130.0, 130.0], [-130.0, 130.0]])
    lp = plan_layer(Layer(3, 1.0, geo.region_from_rings([sq])), job, measured=True)
    meas = [p for p in lp.paths if p.role == "measure"]
    assert sum(p.length for p in meas) > 20_000.0        # more than one store's worth
    longest = max(len(t.xy) for t in plan_paths_motion(meas, job, layer=3))
    assert longest <= CONTROLLER_PATH_POINTS


def test_a_tour_of_two_widths_is_as_wide_as_what_it_deposits_on_average():
    a, b = _in_line(gap=10.0)
    wide = _fill(b.points, width=3.0)
    (tour,) = join_tours([a, wide], 240.0)
    # 40 mm at 1.5 and 40 mm at 3.0; the 10 mm of travel (0 wide) does not count
    assert tour.width == pytest.approx(2.25)
    assert [m.width for m in tour_members(tour)] == [1.5, 3.0]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(0.5, 20.0),
                          st.lists(st.floats(-1.0, 21.0) | st.just(float("nan")),
                                   max_size=8)),
                min_size=1, max_size=6))
def test_spans_are_checked_at_once_as_one_by_one(trajs):
    """core.spans_fine (many trajectories' spans at once, as the valves and the trajectory
    file check them) agrees with core.spans_problem trajectory by trajectory."""
    from icefab.core import spans_fine, spans_problem
    durations = np.array([d for d, _ in trajs])
    spans = [np.sort(np.asarray(e[:len(e) // 2 * 2], dtype=np.float64)).reshape(-1, 2)
             if k % 2 else np.asarray(e[:len(e) // 2 * 2], dtype=np.float64).reshape(-1, 2)
             for k, (_, e) in enumerate(trajs)]
    owner = np.repeat(np.arange(len(trajs)), [len(x) for x in spans])
    got = spans_fine(owner, np.concatenate(spans), durations)
    want = [spans_problem(x, d) == "" for x, d in zip(spans, durations)]
    assert got.tolist() == want


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.floats(2.0, 15.0), st.floats(-150.0, 150.0), st.booleans()),
                min_size=2, max_size=9))
def test_a_path_switched_anywhere_opens_and_closes_its_valve_where_it_switches(legs):
    """Random open paths (legs of 2-15 mm turning up to 150 deg, centred on the part's
    origin, in the default cell's reach), each segment on or off
    (the path may start or end off): one span per run of on segments, and at each span's
    ends the nozzle is at the run's first and last point (within the followed path's
    smoothing and the chord of a sample step across a bend)."""
    job = Job()
    heading, pts = 0.0, [np.zeros(2)]
    for length, turn, _ in legs:
        heading += np.radians(turn)
        pts.append(pts[-1] + length * np.array([np.cos(heading), np.sin(heading)]))
    off = np.array([o for _, _, o in legs] + [False])
    if off[:-1].all():
        off[0] = False
    pts = np.array(pts)
    path = _fill(pts - 0.5 * (pts.min(axis=0) + pts.max(axis=0)), off=off)
    tr = plan_motion(path, job)
    on = path.segment_on()
    runs = [(a, b) for a, b in zip(np.flatnonzero(np.diff(np.r_[0, on.astype(np.int8)]) == 1),
                                   np.flatnonzero(np.diff(np.r_[on.astype(np.int8), 0]) == -1))]
    assert tr.on_spans.shape == (len(runs), 2)
    want = _base_points(path, job)[np.array(runs).ravel() + np.array([0, 1] * len(runs))]
    at = np.column_stack([np.interp(tr.on_spans.ravel(), tr.t, tr.xy[:, j]) for j in (0, 1)])
    assert np.linalg.norm(at - want, axis=1).max() <= 0.1
    # the valve lays no pulse outside the spans (a tick on a span's end is inside: its
    # instant, ticks x tick_s, may be a rounding above the end's)
    t = flow.pulse_times(flow.plan_valves(tr, "part", job.replace(
        **{"flow.out_of_range": "clamp"})))
    inside = np.zeros(len(t), dtype=bool)
    for a, b in tr.on_spans:
        inside |= (t >= a - 1e-12) & (t <= b + 1e-12)
    assert inside.all()


def test_pulses_at_the_valves_top_rate_keep_their_own_ticks_at_a_span_end():
    """Kept half a tick inside its span, the first pulse of a span that opens on a tick
    (at 1 / tick_s) took the tick of the next one: 'pulses share a 2 ms tick' with the
    valve at 500 Hz, not above it (a tester's 2 mm bunny layers, clamped)."""
    tick = 0.002
    ends = np.array([[0.0, 0.05], [0.06, 0.0695]])
    first = np.arange(0.0, 0.0105, tick)                 # 500 Hz from the span's start
    second = 0.0695 - tick * np.arange(4)[::-1]          # 500 Hz up to the span's end
    times = np.concatenate([first, second])
    per = np.array([len(first), len(second)])
    kept = flow._kept_in_spans(times, per, ends, tick)
    ticks = np.floor(kept / tick + (0.5 + 1e-9))
    for part, (a, b) in zip(np.split(ticks, [len(first)]), ends):
        assert np.all(np.diff(part) >= 1)                       # one pulse per tick
        assert np.all((part * tick >= a) & (part * tick <= b))  # its tick inside the span
    assert np.abs(kept - times).max() <= tick / 2 + 1e-15
