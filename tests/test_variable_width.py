"""Variable-width paths (issue 15): a width per point of a Toolpath, carried by the motion
stage to every sample, through both result files, into the valve programs (eq. 6.2 with
w(s)), the feedback headroom, the speed controller's re-timing and the simulator."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from icefab import Job, flow
from icefab.core import LayerMotion, LayerPaths, Toolpath, Toolpaths, widths_problem
from icefab.errors import FlowError, IcefabError, SimulationError, StackFileError
from icefab.feedback import retime_trajectory
from icefab.headroom import feedback_headroom
from icefab.motion import plan_motion, plan_paths_motion, plan_toolpaths
from icefab.resultfiles import (WIDTH_RESOLUTION_MM, load_toolpaths, load_trajectories,
                                save_toolpaths, save_trajectories)
from icefab.sim import deposit_pulses, empty_surface, pulse_drops
from icefab.sim.plans import plan_layer, plan_layer_motion

DH = 0.25


def _line(widths=(1.0, 3.0), length=60.0, **kw) -> Toolpath:
    """A straight fill line along x (part frame), its width linear from end to end."""
    pts = np.column_stack([np.linspace(-length / 2, length / 2, len(widths)),
                           np.zeros(len(widths))])
    w = np.asarray(widths, dtype=np.float64)
    return Toolpath(points=pts, z=DH, material="part", role="fill", width=float(w.mean()),
                    layer=0, widths=w, **kw)


def _square(widths=(1.0, 2.0, 3.0, 4.0)) -> Toolpath:
    pts = np.array([[-15.0, -15.0], [15.0, -15.0], [15.0, 15.0], [-15.0, 15.0]])
    return Toolpath(points=pts, z=DH, material="scaffold", role="fill", closed=True,
                    width=2.5, layer=0, widths=np.asarray(widths, dtype=np.float64))


def test_a_paths_widths_close_with_it_and_bad_ones_are_named():
    sq = _square()
    assert sq.polyline_widths().tolist() == [1.0, 2.0, 3.0, 4.0, 1.0]
    assert Toolpath(points=np.zeros((3, 2)), width=0.7).polyline_widths().tolist() == [0.7] * 3
    assert widths_problem(sq) == ""
    assert "one per point" in widths_problem(Toolpath(points=np.zeros((3, 2)),
                                                      widths=np.ones(2)))
    for bad in ([1.0, np.nan], [1.0, -0.1]):
        assert ">= 0" in widths_problem(Toolpath(points=np.zeros((2, 2)),
                                                 widths=np.array(bad)))


def test_every_sample_gets_the_width_of_its_place_along_the_path():
    job = Job()
    tr = plan_motion(_line((1.0, 3.0)), job)
    assert tr.widths is not None and tr.widths.shape == (len(tr.xy),)
    s = np.linalg.norm(tr.xy - tr.xy[0], axis=1)        # a straight line: s = |x - x0|
    np.testing.assert_allclose(tr.widths, 1.0 + 2.0 * s / 60.0, atol=1e-9)
    # a closed path: linear along each side, back to the first point's width
    sq = plan_motion(_square(), job)
    assert sq.widths[0] == pytest.approx(1.0) and sq.widths[-1] == pytest.approx(1.0)
    corners = sq.pieces[1:]          # the robot rests at the three corners
    np.testing.assert_allclose(sq.widths[corners], [2.0, 3.0, 4.0], atol=1e-9)
    # the same in a batch of paths, and a constant-width path keeps none
    plain = Toolpath(points=np.array([[0.0, 0.0], [10.0, 0.0]]), width=1.0, role="fill")
    got = plan_paths_motion([_line((1.0, 3.0)), plain, _square()], job)
    assert got[1].widths is None
    # (the batch's arc lengths run on from path to path: equal to float rounding)
    np.testing.assert_allclose(got[0].widths, tr.widths, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[2].widths, sq.widths, rtol=0, atol=1e-12)


def test_a_path_with_bad_widths_is_refused_by_name():
    bad = Toolpath(points=np.array([[0.0, 0.0], [10.0, 0.0]]), role="fill", width=1.0,
                   layer=3, widths=np.array([1.0, np.inf]))
    with pytest.raises(IcefabError, match="layer 3, path 1: widths must be finite"):
        plan_paths_motion([Toolpath(points=np.array([[0.0, 0.0], [5.0, 0.0]]), width=1.0),
                           bad], Job())
    # the widths of a layer are checked at once: still the first bad path is named
    good = dataclasses.replace(bad, widths=np.array([1.0, 2.0]))
    short = dataclasses.replace(bad, widths=np.array([1.0]))
    negative = dataclasses.replace(bad, widths=np.array([1.0, -0.5]))
    with pytest.raises(IcefabError, match=r"layer 3, path 1: widths have shape \(1,\)"):
        plan_paths_motion([good, short, negative, bad], Job())
    with pytest.raises(IcefabError, match="layer 3, path 2: widths must be finite"):
        plan_paths_motion([good, good, negative, short], Job())


def _build(paths) -> Toolpaths:
    return Toolpaths((LayerPaths(0, DH, tuple(paths), (0.0, 0.0)),), Job())


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.lists(st.floats(0.0, 5.0), min_size=2, max_size=6), min_size=1,
                max_size=4), st.booleans())
def test_toolpath_files_keep_every_width(rows, closed):
    paths = [Toolpath(points=np.column_stack([np.arange(len(w)) * 3.0, np.full(len(w), k)]),
                      role="fill", width=1.0, closed=closed, layer=0, z=DH,
                      widths=np.array(w)) for k, w in enumerate(rows)]
    paths.insert(1, Toolpath(points=np.array([[0.0, 9.0], [4.0, 9.0]]), role="boundary",
                             width=0.8, layer=0, z=DH))
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        save_toolpaths(_build(paths), f"{d}/t.npz")
        back = load_toolpaths(f"{d}/t.npz").layers[0].paths
    assert back[1].widths is None
    for p, q in zip(paths, back):
        if p.widths is not None:
            assert np.array_equal(p.widths, q.widths)


def test_a_toolpath_file_with_half_the_width_members_is_refused(tmp_path):
    save_toolpaths(_build([_line()]), tmp_path / "t.npz")
    with np.load(tmp_path / "t.npz") as z:
        data = {k: z[k] for k in z.files if k != "point_width"}
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(StackFileError, match="bad.npz: members 'variable' and 'point_width' come together"):
        load_toolpaths(tmp_path / "bad.npz")


def test_trajectory_files_keep_the_widths_within_their_resolution(tmp_path):
    job = Job()
    tp = _build([_line((1.0, 2.5, 0.5)), Toolpath(points=np.array([[0.0, 5.0], [9.0, 5.0]]),
                                                  role="boundary", width=1.0, layer=0, z=DH),
                 _square()])
    motion = plan_toolpaths(tp, job.replace(**{"cell.cpus": 1}))
    save_trajectories(motion, tmp_path / "t.npz", block_samples=40)   # several blocks
    back = load_trajectories(tmp_path / "t.npz")
    for a, b in zip(motion.layers[0].trajectories, back.layers[0].trajectories):
        assert (a.widths is None) == (b.widths is None)
        if a.widths is not None:
            assert np.abs(a.widths - b.widths).max() <= WIDTH_RESOLUTION_MM / 2 + 1e-12
            assert len(b.path.widths) == len(b.path.points)
    # a damaged width block is named
    with np.load(tmp_path / "t.npz") as z:
        data = {k: z[k] for k in z.files}
    data["width_counts_0"] = data["width_counts_0"][:, :, :-1]
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(StackFileError, match="bad.npz: member width_counts_0"):
        load_trajectories(tmp_path / "bad.npz")


def _linear_table_job(tmp_path) -> Job:
    """A linear calibration table: every pulse, at any frequency, drops 0.25 mm^3."""
    table = tmp_path / "linear.csv"
    table.write_text("frequency_hz,flow_mm3_s\n0,0\n1000,250\n")
    return Job().replace(**{"materials.part.calibration_file": str(table)})


def test_the_valve_deposits_the_width_along_the_path(tmp_path):
    job = _linear_table_job(tmp_path)
    tr = plan_motion(_line((1.0, 3.0)), job)
    prog = flow.plan_valves(tr, "part", job)
    # eq. 6.2 with w(s): the volume of a trapezoid, 60 mm * mean width 2 mm * dh
    want = 60.0 * 2.0 * DH
    assert abs(flow.n_pulses(prog) * 0.25 - want) <= 0.25
    # three times the flow per mm at the wide end: count the pulses per half
    t = flow.pulse_times(prog)
    x = np.interp(t, tr.t, tr.xy[:, 0]) - tr.xy[0, 0]
    first, second = np.count_nonzero(x < 30.0), np.count_nonzero(x >= 30.0)
    assert second / first == pytest.approx(2.5 / 1.5, rel=0.05)   # mean widths 1.5 and 2.5
    # a variable path of one width all along is the constant-width path, bit for bit
    same = plan_motion(_line((2.0, 2.0)), job)
    const = plan_motion(Toolpath(points=_line((2.0, 2.0)).points, z=DH, material="part",
                                 role="fill", width=2.0, layer=0), job)
    a, b = flow.plan_valves(same, "part", job), flow.plan_valves(const, "part", job)
    assert np.array_equal(a.ticks, b.ticks) and a.duration == b.duration
    # a layer's programs made at once equal plan_valves' for variable paths too
    layer = LayerMotion(index=0, z=DH, trajectories=(tr, const, same))
    for lp in flow.plan_layer_valves(layer, job):
        want_prog = flow.plan_valves(layer.trajectories[lp.path], "part", job)
        assert np.array_equal(lp.program.ticks, want_prog.ticks)
        assert lp.program.warnings == want_prog.warnings


def test_trajectory_widths_that_do_not_match_the_samples_are_refused():
    import dataclasses

    tr = plan_motion(_line((1.0, 3.0)), Job())
    bad = dataclasses.replace(tr, widths=tr.widths[:-1])
    with pytest.raises(FlowError, match="one per sample"):
        flow.plan_valves(bad, "part", Job())


def test_the_headroom_takes_the_largest_width_times_speed():
    job = Job()
    wide_end = plan_motion(_line((0.5, 4.0)), job)
    constant = plan_motion(Toolpath(points=_line().points, z=DH, material="part",
                                    role="fill", width=2.0, layer=0), job)
    (room,) = feedback_headroom([(0, constant), (0, wide_end)], job)
    i = int(np.argmax(wide_end.widths * wide_end.speed))
    assert room.nominal_mm3_s == pytest.approx(wide_end.widths[i] * wide_end.speed[i] * DH)
    assert room.width_mm == pytest.approx(wide_end.widths[i]) and room.width_mm > 3.0


def test_the_speed_controller_resamples_the_widths():
    tr = plan_motion(_line((1.0, 3.0)), Job())
    slow = retime_trajectory(tr, np.full(len(tr.xy), 0.25))    # 20 % slower
    assert len(slow.xy) > len(tr.xy) and slow.widths.shape == (len(slow.xy),)
    s = np.linalg.norm(slow.xy - slow.xy[0], axis=1)
    np.testing.assert_allclose(slow.widths, 1.0 + 2.0 * s / 60.0, atol=0.01)


def _strip_widths(hm) -> tuple[float, float]:
    """How wide the deposit is (mm, cells above a tenth of the peak) at x = -25 and +25."""
    xs, ys = hm.grid()
    out = []
    for x in (-25.0, 25.0):
        col = hm.z[:, np.argmin(np.abs(xs - x))]
        out.append(np.count_nonzero(col > 0.1 * col.max()) * hm.spacing)
    return out[0], out[1]


def test_the_simulator_lays_a_strip_as_wide_as_the_path(tmp_path):
    job = _linear_table_job(tmp_path)
    tr = plan_motion(_line((1.0, 3.0)), job)
    xy = flow.trajectory_part_xy(tr, "part", job)
    prog = flow.plan_valves(tr, "part", job)
    t, drops = pulse_drops(prog, flow.valve_frequency(tr, "part", job), "part", job)
    surf = empty_surface(np.array([-35.0, -5.0]), np.array([35.0, 5.0]), 0.1)
    out = deposit_pulses(surf, xy, tr.dt, t, drops, flow.sample_widths(tr, "part", job))
    assert out.z.sum() * 0.01 == pytest.approx(len(t) * 0.25, rel=1e-9)
    narrow, wide = _strip_widths(out)
    assert narrow == pytest.approx(1.0 + 2.0 * 5 / 60, abs=0.15)
    assert wide == pytest.approx(1.0 + 2.0 * 55 / 60, abs=0.15)
    with pytest.raises(SimulationError, match="one per sample"):
        deposit_pulses(surf, xy, tr.dt, t, drops, np.ones(3))


def test_the_simulators_layer_plans_carry_the_widths():
    job = Job()
    path = _line((1.0, 3.0))
    for lp in (plan_layer(0, [path], job),
               plan_layer_motion(LayerMotion(0, DH, (plan_motion(path, job),)), job)):
        mid = lp.midpoints[:, 0]
        want = 1.0 + 2.0 * (mid - mid.min()) / (mid.max() - mid.min())
        # widths at the segments' middles, linear along the line
        np.testing.assert_allclose(2.0 * lp.half_width, want, atol=0.1)
        assert lp.volume.sum() == pytest.approx(60.0 * 2.0 * DH, rel=0.01)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(1, 5),
                          st.sampled_from(["good", "short", "nan", "negative", "inf", "text"])),
                max_size=8))
def test_widths_checked_at_once_agree_with_each_paths_check(cases):
    """core.checked_widths (the layer-at-once check of the planning, the valves and the
    headroom) says of each path what widths_problem says of it alone, and gives the good
    paths' widths, concatenated in order."""
    from icefab.core import checked_widths
    paths = []
    for n, kind in cases:
        w = np.linspace(0.5, 2.0, n)
        if kind == "short":
            w = w[:-1] if n > 1 else np.zeros(2)
        elif kind == "nan":
            w[-1] = np.nan
        elif kind == "negative":
            w[0] = -0.1
        elif kind == "inf":
            w[0] = np.inf
        elif kind == "text":
            w = np.array(["1"] * n)
        paths.append(Toolpath(points=np.zeros((n, 2)), role="fill", width=1.0, widths=w))
    ok, W = checked_widths([p.widths for p in paths], [len(p.points) for p in paths])
    assert ok.tolist() == [widths_problem(p) == "" for p in paths]
    good = [np.asarray(p.widths, np.float64) for p, k in zip(paths, ok) if k]
    np.testing.assert_array_equal(W, np.concatenate(good) if good else np.zeros(0))
