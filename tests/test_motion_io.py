"""Build-wide planning (layer-parallel), trajectory files, and the ``icefab plan`` command."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from icefab import Job, LayerPaths, Toolpath, Toolpaths
from icefab.errors import StackFileError, WorkspaceError
from icefab.motion import load_trajectories, plan_toolpaths, save_trajectories
from icefab.resultfiles import (JOINT_RESOLUTION, SPEED_RESOLUTION_MM_S, XY_RESOLUTION_MM,
                                pack_trajectories)


def _toolpaths(job, n_layers=4):
    layers = []
    th = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    for k in range(n_layers):
        r = 20.0 + 5 * k
        ring = Toolpath(points=np.c_[r * np.cos(th), r * np.sin(th)], z=0.25 * (k + 1),
                    material="part", role="boundary", closed=True, width=1.5, layer=k)
        sq = np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]])
        fill = Toolpath(points=sq, z=0.25 * (k + 1), material="scaffold", role="fill",
                    closed=True, width=3.0, layer=k)
        travel = Toolpath(points=np.array([[r, 0.0], [-10.0, -10.0]]), z=0.25 * (k + 1),
                      role="travel", layer=k)
        layers.append(LayerPaths(index=k, z=0.25 * (k + 1), paths=(ring, travel, fill)))
    return Toolpaths(layers=tuple(layers), job=job)


def test_parallel_equals_serial_and_progress():
    job = Job()
    tp = _toolpaths(job)
    calls = []
    serial = plan_toolpaths(tp, job.replace(**{"cell.cpus": 1}),
                            progress=lambda d, t: calls.append((d, t)))
    par = plan_toolpaths(tp, job.replace(**{"cell.cpus": 2}))
    assert calls[-1] == (4, 4) and len(calls) == 4
    for a, b in zip(serial.layers, par.layers):
        assert a.index == b.index
        for ta, tb in zip(a.trajectories, b.trajectories):
            np.testing.assert_array_equal(ta.xy, tb.xy)
            np.testing.assert_array_equal(ta.joints, tb.joints)
    assert serial.duration == pytest.approx(sum(lm.duration for lm in serial.layers))
    assert serial.layers[0].durations.shape == (3,)
    # the square fill stops at its four corners (and at the start)
    sq = serial.layers[0].trajectories[2]
    assert len(sq.pieces) == 4
    assert (sq.speed[sq.pieces] == 0).all()


def test_save_load_round_trip(tmp_path):
    job = Job()
    motion = plan_toolpaths(_toolpaths(job, 2), job.replace(**{"cell.cpus": 1}))
    f = tmp_path / "traj.npz"
    save_trajectories(motion, f)
    back = load_trajectories(f)
    assert back.robot == "scara" and back.joint_names == ("theta1", "theta2", "theta4")
    assert back.duration == pytest.approx(motion.duration)
    for a, b in zip(motion.layers, back.layers):
        assert a.index == b.index and a.z == b.z
        for ta, tb in zip(a.trajectories, b.trajectories):
            # the samples within half the file's resolution (issue 17), the rest exactly
            np.testing.assert_allclose(tb.xy, ta.xy, rtol=0, atol=XY_RESOLUTION_MM / 2)
            np.testing.assert_allclose(tb.joints, ta.joints, rtol=0,
                                       atol=JOINT_RESOLUTION / 2)
            np.testing.assert_allclose(tb.speed, ta.speed, rtol=0,
                                       atol=SPEED_RESOLUTION_MM_S / 2)
            np.testing.assert_array_equal(ta.pieces, tb.pieces)
            assert tb.path.role == ta.path.role and tb.path.material == ta.path.material
            assert tb.dt == ta.dt


def _narrow_layers(job):
    """Toolpaths whose paths carry non-default widths (a narrow gap-fill ring), tools
    and closed flags, as the paths stage makes them."""
    th = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    ring = Toolpath(points=np.c_[25 * np.cos(th), 25 * np.sin(th)], z=0.25, material="part",
                role="fill", closed=True, width=0.6, layer=0)
    laser = Toolpath(points=np.c_[30 * np.cos(th), 30 * np.sin(th)], z=0.25, material="part",
                 role="measure", closed=True, width=0.0, layer=0, tool="laser")
    line = Toolpath(points=np.array([[-20.0, 0.0], [20.0, 5.0]]), z=0.25, material="scaffold",
                role="boundary", closed=False, width=2.2, layer=0)
    return Toolpaths(layers=(LayerPaths(index=0, z=0.25, paths=(ring, laser, line)),),
                     job=job)


def test_round_trip_keeps_path_widths_tools_closed_and_dt(tmp_path):
    import dataclasses

    from icefab.motion import BuildMotion
    job = Job()
    tp = _narrow_layers(job)
    motion = plan_toolpaths(tp, job.replace(**{"cell.cpus": 1}))
    # a trajectory sampled at another dt (e.g. merged from another plan) keeps its dt
    lm = motion.layers[0]
    odd = dataclasses.replace(lm.trajectories[2], dt=0.008)
    motion = BuildMotion(layers=(dataclasses.replace(
        lm, trajectories=lm.trajectories[:2] + (odd,)),), job=motion.job,
        robot=motion.robot, joint_names=motion.joint_names)
    f = tmp_path / "t.npz"
    save_trajectories(motion, f)
    back = load_trajectories(f)
    for p, tr, tb in zip(tp.layers[0].paths, motion.layers[0].trajectories,
                         back.layers[0].trajectories):
        q = tb.path
        assert (q.width, q.closed, q.tool, q.material, q.role, q.layer, q.z) == \
            (p.width, p.closed, p.tool, p.material, p.role, p.layer, p.z)
        assert q.tool_name == p.tool_name
        assert tb.dt == tr.dt
        # the samples, closed or not (within the file's resolution)
        np.testing.assert_allclose(q.polyline(), tr.xy, rtol=0, atol=XY_RESOLUTION_MM / 2)
    assert [t.dt for t in back.layers[0].trajectories] == [0.016, 0.016, 0.008]
    # the valve stage uses the stored widths: the 0.6 mm ring gets a fifth of the drops
    # the job's 3 mm fill width would give it
    from icefab import plan_valves
    narrow = back.layers[0].trajectories[0]
    wide = dataclasses.replace(narrow, path=dataclasses.replace(narrow.path, width=0.0))
    n_narrow = len(plan_valves(narrow, "part", job).ticks)
    n_wide = len(plan_valves(wide, "part", job).ticks)
    assert job.materials.part.fill_width_mm == 3.0
    assert n_narrow == pytest.approx(0.2 * n_wide, rel=0.05)


def test_version_1_files_still_load_with_a_warning(tmp_path, caplog):
    job = Job()
    motion = plan_toolpaths(_narrow_layers(job), job.replace(**{"cell.cpus": 1}))
    f = tmp_path / "t.npz"
    save_trajectories(motion, f)
    with np.load(f) as z:
        data = {k: z[k] for k in z.files
                if k not in ("traj_dt", "width", "closed", "tool", "path_z", "variable",
                             "block_layer_start") + _V6
                and "_counts" not in k and not k.endswith("_resolution")}
    # version 1 stored the samples as float64
    packed = pack_trajectories([t for lm in motion.layers for t in lm.trajectories], 3)
    data.update({k: packed[k] for k in ("xy", "joints", "speed")})
    data["version"] = np.array(1)
    old = tmp_path / "v1.npz"
    np.savez(old, **data)
    with caplog.at_level("WARNING", logger="icefab.motion"):
        back = load_trajectories(old)
    assert "version 1" in caplog.text and "widths" in caplog.text
    trs = back.layers[0].trajectories
    assert [t.path.width for t in trs] == [0.0, 0.0, 0.0]
    assert all(t.dt == 0.016 for t in trs) and trs[0].path.z == 0.25
    np.testing.assert_array_equal(trs[0].xy, motion.layers[0].trajectories[0].xy)


def test_load_rejects_bad_files(tmp_path):
    with pytest.raises(StackFileError, match="not found"):
        load_trajectories(tmp_path / "missing.npz")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04garbage")
    with pytest.raises(StackFileError):
        load_trajectories(bad)
    other = tmp_path / "other.npz"
    np.savez(other, format=np.array("something-else"))
    with pytest.raises(StackFileError, match="not an icefab trajectory file"):
        load_trajectories(other)


def test_workspace_error_names_layer_in_build():
    job = Job().replace(**{"cell.ee_origin_mm": [590.0, 0.0]})
    with pytest.raises(WorkspaceError, match=r"layer 0, path 0: point \d+ at"):
        plan_toolpaths(_toolpaths(job, 2), job.replace(**{"cell.cpus": 1}))
    # a bad point in the last layer is found before the first layer is planned
    job = Job()
    tp = _toolpaths(job, 3)
    last = tp.layers[-1]
    far = Toolpath(points=np.array([[0.0, 0.0], [400.0, 0.0]]), role="travel", layer=2)
    tp = Toolpaths(layers=tp.layers[:-1] + (LayerPaths(index=2, z=last.z,
                                                        paths=last.paths + (far,)),),
                   job=job)
    calls = []
    with pytest.raises(WorkspaceError, match=r"layer 2, path 3: point 1 at \(660.100, -99.700\)"):
        plan_toolpaths(tp, job.replace(**{"cell.cpus": 1}),
                       progress=lambda d, t: calls.append(d))
    assert calls == []


def test_version_2_files_with_float_samples_still_load_exactly(tmp_path):
    job = Job()
    motion = plan_toolpaths(_narrow_layers(job), job.replace(**{"cell.cpus": 1}))
    f = tmp_path / "t.npz"
    save_trajectories(motion, f)
    with np.load(f) as z:
        data = {k: z[k] for k in z.files if "_counts" not in k and k != "block_layer_start"
                and not k.endswith("_resolution") and k != "variable" and k not in _V6}
    packed = pack_trajectories([t for lm in motion.layers for t in lm.trajectories], 3)
    data.update({k: packed[k] for k in ("xy", "joints", "speed")}, version=np.array(2))
    np.savez(tmp_path / "v2.npz", **data)
    back = load_trajectories(tmp_path / "v2.npz")
    for ta, tb in zip(motion.layers[0].trajectories, back.layers[0].trajectories):
        np.testing.assert_array_equal(ta.xy, tb.xy)
        np.testing.assert_array_equal(ta.speed, tb.speed)
        assert tb.path.width == ta.path.width and tb.dt == ta.dt


def test_constant_speed_time_is_the_constant_speed_motions_duration():
    from icefab.motion import constant_speed_motion, constant_speed_time
    job = Job()
    tp = _toolpaths(job, 3)
    for cpus in (1, 2):
        j = job.replace(**{"cell.cpus": cpus})
        full = constant_speed_motion(tp, j, fill_mm_s=60.0)
        assert constant_speed_time(tp, j, fill_mm_s=60.0) == pytest.approx(full.duration,
                                                                           rel=1e-12)
    # and it is not the minimum-time plan's (slower fill)
    assert constant_speed_time(tp, job) > plan_toolpaths(tp, job).duration


def test_trajectories_without_joint_names_keep_their_joints(tmp_path):
    """A BuildMotion whose joints carry no names (as version 2 read it: any columns)."""
    import dataclasses
    job = Job()
    motion = plan_toolpaths(_toolpaths(job, 1), job.replace(**{"cell.cpus": 1}))
    unnamed = dataclasses.replace(motion, joint_names=())
    save_trajectories(unnamed, tmp_path / "t.npz")
    back = load_trajectories(tmp_path / "t.npz")
    for ta, tb in zip(motion.layers[0].trajectories, back.layers[0].trajectories):
        assert tb.joints.shape == ta.joints.shape == (len(ta.xy), 3)
        np.testing.assert_allclose(tb.joints, ta.joints, rtol=0, atol=JOINT_RESOLUTION / 2)


def _same_samples(a, b):
    """Two BuildMotions' layers agree: samples within half the file's resolution, the rest
    exactly."""
    assert [lm.index for lm in a.layers] == [lm.index for lm in b.layers]
    for la, lb in zip(a.layers, b.layers):
        assert la.z == lb.z and len(la.trajectories) == len(lb.trajectories)
        for ta, tb in zip(la.trajectories, lb.trajectories):
            np.testing.assert_allclose(tb.xy, ta.xy, rtol=0, atol=XY_RESOLUTION_MM / 2)
            np.testing.assert_allclose(tb.joints, ta.joints, rtol=0, atol=JOINT_RESOLUTION / 2)
            np.testing.assert_allclose(tb.speed, ta.speed, rtol=0,
                                       atol=SPEED_RESOLUTION_MM_S / 2)
            np.testing.assert_array_equal(ta.pieces, tb.pieces)
            assert (tb.dt, tb.duration, tb.path.role, tb.path.material, tb.path.width) == \
                (ta.dt, ta.duration, ta.path.role, ta.path.material, ta.path.width)


@pytest.fixture(scope="module")
def four_layers():
    job = Job()
    return plan_toolpaths(_toolpaths(job, 4), job.replace(**{"cell.cpus": 1}))


@pytest.mark.parametrize("block_samples", [1, 700, 10**9])
def test_blocks_read_back_the_same_build_and_any_layers_of_it(tmp_path, four_layers,
                                                              block_samples):
    from icefab.resultfiles import TrajectoryFile
    motion = four_layers
    f = tmp_path / "t.npz"
    save_trajectories(motion, f, block_samples=block_samples)
    with np.load(f) as z:
        blocks = z["block_layer_start"].tolist()
    # one layer a block, a few layers a block, the whole build in one
    assert {1: [0, 1, 2, 3, 4], 10**9: [0, 4]}.get(block_samples, blocks) == blocks
    assert 2 < len(blocks) < 5 or block_samples != 700
    _same_samples(motion, load_trajectories(f))
    with TrajectoryFile(f) as tf:
        assert tf.n_layers == 4 and tf.n_points == motion.n_points
        assert tf.duration == pytest.approx(motion.duration)
        picked = list(tf.iter_layers({1, 3}))
        assert [lm.index for lm in picked] == [1, 3]
        for lm, want in zip(picked, (motion.layers[1], motion.layers[3])):
            _same_samples(type(motion)(layers=(want,), job=motion.job),
                          type(motion)(layers=(lm,), job=motion.job))
        assert list(tf.iter_layers(set())) == []
        assert [lm.index for lm in tf.layers] == [0, 1, 2, 3]


def test_version_3_files_one_block_still_load(tmp_path, four_layers):
    f = tmp_path / "t.npz"
    save_trajectories(four_layers, f)
    with np.load(f) as z:
        data = {k.replace("_counts_0", "_counts"): z[k] for k in z.files
                if k != "block_layer_start" and k not in _V5 + _V6 and not k.startswith("width_")}
    data["version"] = np.array(3)
    np.savez(tmp_path / "v3.npz", **data)
    _same_samples(four_layers, load_trajectories(tmp_path / "v3.npz"))


#: What version 5 added to version 4: per-sample widths of variable-width paths.
_V5 = ("variable", "width_resolution")
#: What version 6 added to version 5: the spans over which continuous tours' valves are on.
_V6 = ("span_owner", "on_spans")


def test_version_4_files_without_widths_still_load(tmp_path, four_layers):
    f = tmp_path / "t.npz"
    save_trajectories(four_layers, f, block_samples=1)
    with np.load(f) as z:
        data = {k: z[k] for k in z.files if k not in _V5 + _V6 and not k.startswith("width_")}
    data["version"] = np.array(4)
    np.savez(tmp_path / "v4.npz", **data)
    back = load_trajectories(tmp_path / "v4.npz")
    _same_samples(four_layers, back)
    assert all(t.widths is None for lm in back.layers for t in lm.trajectories)


def test_a_bad_block_table_or_block_is_named(tmp_path, four_layers):
    f = tmp_path / "t.npz"
    save_trajectories(four_layers, f, block_samples=1)
    with np.load(f) as z:
        data = {k: z[k] for k in z.files}
    for change, member in (({"block_layer_start": np.array([0, 2, 1, 3, 4])},
                            "block_layer_start"),
                           ({"block_layer_start": np.array([0, 2, 5])}, None),
                           ({"joint_counts_2": data["joint_counts_1"]}, "joint_counts_2")):
        bad = {**data, **change}
        if member is None:  # blocks 2 and 3 are not named by the table: unexpected members
            member = "unexpected members"
        np.savez(tmp_path / "bad.npz", **bad)
        with pytest.raises(StackFileError, match=f"bad.npz: .*{member}"):
            load_trajectories(tmp_path / "bad.npz")


def test_a_failed_write_leaves_no_file(tmp_path, four_layers):
    from icefab.resultfiles import TrajectoryWriter
    f = tmp_path / "t.npz"
    with pytest.raises(RuntimeError):
        with TrajectoryWriter(f, four_layers.job, "scara", four_layers.joint_names,
                              block_samples=1) as w:
            w.add(four_layers.layers[0])   # a block is written
            raise RuntimeError("planning failed")
    assert list(tmp_path.iterdir()) == []


def test_streamed_plan_gives_the_same_layers_in_order(four_layers):
    from icefab.motion import iter_plan_toolpaths
    job = Job().replace(**{"cell.cpus": 2})
    calls = []
    streamed = list(iter_plan_toolpaths(_toolpaths(job, 4), job,
                                        progress=lambda d, t: calls.append(d)))
    assert [lm.index for lm in streamed] == [0, 1, 2, 3] and calls[-1] == 4
    for a, b in zip(four_layers.layers, streamed):
        for ta, tb in zip(a.trajectories, b.trajectories):
            np.testing.assert_array_equal(ta.xy, tb.xy)
            np.testing.assert_array_equal(ta.joints, tb.joints)
            np.testing.assert_array_equal(ta.pieces, tb.pieces)
            assert (ta.path.role, ta.path.layer) == (tb.path.role, tb.path.layer)
            np.testing.assert_array_equal(ta.path.points, tb.path.points)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 9), st.booleans()), min_size=0, max_size=12),
       st.integers(0, 2**32 - 1))
def test_path_lengths_at_once_equal_each_paths_length(shapes, seed):
    from icefab.core import path_lengths
    rng = np.random.default_rng(seed)
    paths = [Toolpath(points=rng.uniform(-50, 50, (max(k, 1), 2)), closed=c)
             for k, c in shapes]
    np.testing.assert_allclose(path_lengths(paths), [p.length for p in paths], rtol=1e-12,
                               atol=1e-9)


def test_plan_and_compare_in_one_pass_gives_both_figures(four_layers):
    from icefab.motion import constant_speed_time, iter_plan_and_compare
    job = Job().replace(**{"cell.cpus": 2})
    tp = _toolpaths(job, 4)
    pairs = list(iter_plan_and_compare(tp, job))
    assert sum(t for _, t in pairs) == pytest.approx(constant_speed_time(tp, job), rel=1e-12)
    for (lm, _), want in zip(pairs, four_layers.layers):
        assert lm.duration == want.duration


def test_open_trajectories_reads_layers_as_asked_for(tmp_path, four_layers):
    import threading

    from icefab.motion import open_trajectories
    f = tmp_path / "t.npz"
    save_trajectories(four_layers, f, block_samples=700)   # a few blocks
    lazy = open_trajectories(f)
    whole = load_trajectories(f)
    assert len(lazy.layers) == 4 and lazy.job == whole.job and lazy.robot == whole.robot
    _same_samples(whole, type(whole)(layers=tuple(lazy.layers), job=whole.job))
    assert [lm.index for lm in lazy.layers[1:3]] == [1, 2] and lazy.layers[-1].index == 3
    assert [lm.index for lm in lazy.layers[::-2]] == [3, 1] and len(lazy.layers[2:]) == 2
    with pytest.raises(IndexError):
        lazy.layers[4]
    # the build runner's planning thread reads ahead while the main thread reads
    rng = np.random.default_rng(5)
    picks = rng.integers(0, 4, size=(2, 200))
    wrong = []

    def read(order):
        for k in order:
            lm = lazy.layers[int(k)]
            if lm.index != k or len(lm.trajectories) != len(whole.layers[k].trajectories):
                wrong.append(k)
    threads = [threading.Thread(target=read, args=(p,)) for p in picks]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not wrong


def test_a_layer_shipped_to_a_worker_arrives_whole():
    """The planning's work items pickle a layer as a few packed arrays (icefab plan sent
    the bunny's 432 k Toolpath objects one by one): every field of every path, the
    per-point widths of a variable-width path and the layer's own fields come back."""
    import pickle

    from icefab.motion import _ShippedLayer
    base = _toolpaths(Job()).layers[1]
    var = Toolpath(points=np.array([[0.0, 0.0], [1.0, 0.5], [2.0, 0.25]]), z=0.5,
                   material="scaffold", role="fill", width=1.2, layer=1,
                   widths=np.array([0.9, 1.4, 1.3]))
    laser = Toolpath(points=np.array([[5.0, 5.0], [6.0, 5.0], [6.0, 6.0]]), z=0.5,
                     role="measure", closed=True, layer=1, frame="base", tool="laser")
    lp = LayerPaths(index=1, z=0.5, paths=base.paths + (var, laser), unfilled_mm2=(1.5, 2.5),
                    thickness=0.3)
    got = pickle.loads(pickle.dumps(_ShippedLayer(lp))).lp
    assert (got.index, got.z, got.unfilled_mm2, got.thickness) == (1, 0.5, (1.5, 2.5), 0.3)
    assert len(got.paths) == len(lp.paths)
    for a, b in zip(lp.paths, got.paths):
        np.testing.assert_array_equal(a.points, b.points)
        assert (a.z, a.material, a.role, a.closed, a.width, a.layer, a.frame, a.tool) == \
            (b.z, b.material, b.role, b.closed, b.width, b.layer, b.frame, b.tool)
        assert (a.widths is None) == (b.widths is None)
        if a.widths is not None:
            np.testing.assert_array_equal(a.widths, b.widths)
    # a serial run does not pickle: the layer itself is the item's
    assert _ShippedLayer(lp).lp is lp


def _count_samples(layer, job):
    """per_layer of the test below (module level: it reaches the workers by name)."""
    return layer.index, layer.n_points


@pytest.mark.parametrize("cpus", [1, 2])
def test_packed_planning_gives_the_same_layers_and_the_workers_results(cpus, tmp_path):
    """iter_plan_packed: the trajectories as the workers pack them, the constant-speed time
    and per_layer's result on each layer; unpacked, the layers iter_plan_and_compare
    gives; written, the file TrajectoryWriter.add writes of those layers."""
    import zipfile

    from icefab.motion import (iter_plan_and_compare, iter_plan_packed,
                               unpack_layer_motion)
    from icefab.resultfiles import TrajectoryWriter
    job = Job().replace(**{"cell.cpus": cpus})
    tp = _toolpaths(job, n_layers=5)
    packed = list(iter_plan_packed(tp, job, per_layer=_count_samples))
    whole = list(iter_plan_and_compare(tp, job))
    assert [pl.paths.index for pl in packed] == [lm.index for lm, _ in whole] == list(range(5))
    for pl, (lm, t) in zip(packed, whole):
        assert pl.const_s == t and pl.extra == (lm.index, lm.n_points)
        got = unpack_layer_motion(pl.paths, pl.packed)
        for a, b in zip(got.trajectories, lm.trajectories):
            np.testing.assert_array_equal(a.xy, b.xy)
            np.testing.assert_array_equal(a.pieces, b.pieces)
            assert a.path is b.path and a.duration == b.duration
    files = {}
    for how in ("add", "add_packed"):
        path = tmp_path / f"{how}.npz"
        with TrajectoryWriter(path, job, "scara", ("theta1", "theta2", "theta4"),
                              block_samples=300) as w:
            for pl, (lm, _) in zip(packed, whole):
                if how == "add":
                    w.add(lm)
                else:
                    w.add_packed(pl.paths.index, pl.paths.z, pl.paths.thickness,
                                 pl.paths.paths, pl.packed, top_z=pl.paths.top_z)
        with zipfile.ZipFile(path) as z:
            files[how] = {n: z.read(n) for n in z.namelist()}
    assert files["add"] == files["add_packed"] and len(files["add"]) > 20


@pytest.mark.parametrize("cpus", [1, 2])
def test_a_build_loaded_as_arrays_plans_and_writes_as_its_toolpaths(cpus, tmp_path):
    """icefab plan loads its toolpath file as arrays (load_packed_toolpaths: no Toolpath
    made) and iter_plan_packed checks and ships them as they are: the same trajectories,
    times and per_layer results as the Toolpaths loaded from that file, each layer with
    its path arrays, and written by TrajectoryWriter.add_packed from those arrays the
    same file byte for byte; the constant-speed estimate is the same too."""
    import zipfile

    from icefab.motion import iter_plan_packed
    from icefab.paths import estimate_build_time
    from icefab.resultfiles import (LayerHead, TrajectoryWriter, load_packed_toolpaths,
                                    load_toolpaths, save_toolpaths)
    job = Job().replace(**{"cell.cpus": cpus})
    f = tmp_path / "tp.npz"
    save_toolpaths(_toolpaths(job, n_layers=5), f)
    whole, arrays = load_toolpaths(f), load_packed_toolpaths(f)
    (per_a, sum_a), (per_w, sum_w) = (estimate_build_time(tp, job) for tp in (arrays, whole))
    assert per_a.tolist() == per_w.tolist() and sum_a == sum_w > 0
    got = list(iter_plan_packed(arrays, job, per_layer=_count_samples))
    want = list(iter_plan_packed(whole, job, per_layer=_count_samples))
    files = []
    for planned, kind in ((got, "arrays"), (want, "paths")):
        path = tmp_path / f"{kind}.npz"
        with TrajectoryWriter(path, job, "scara", ("theta1", "theta2", "theta4"),
                              block_samples=300) as w:
            for pl in planned:
                w.add_packed(pl.paths.index, pl.paths.z, pl.paths.thickness,
                             pl.path_arrays if kind == "arrays" else pl.paths.paths,
                             pl.packed, top_z=pl.paths.top_z)
        with zipfile.ZipFile(path) as z:
            files.append({n: z.read(n) for n in z.namelist()})
    assert files[0] == files[1]
    for a, b in zip(got, want):
        assert isinstance(a.paths, LayerHead) and a.path_arrays is not None
        assert b.path_arrays is None and a.paths.index == b.paths.index
        assert a.const_s == b.const_s and a.extra == b.extra
        for key in b.packed:
            np.testing.assert_array_equal(a.packed[key], b.packed[key], err_msg=key)


def test_unreachable_builds_loaded_as_arrays_are_refused_before_planning(monkeypatch, tmp_path):
    """The up-front checks of a build loaded as arrays: the reach of every layer (the
    same message as its Toolpaths get) before any layer is planned."""
    import icefab.motion as motion
    from icefab.errors import WorkspaceError
    from icefab.resultfiles import load_packed_toolpaths, load_toolpaths, save_toolpaths
    job = Job().replace(**{"cell.cpus": 1, "cell.ee_origin_mm": (560.0, 0.0)})
    f = tmp_path / "tp.npz"
    save_toolpaths(_toolpaths(job, n_layers=5), f)
    monkeypatch.setattr(motion, "_plan_packed_task",
                        lambda args: pytest.fail("planned an unreachable build"))
    messages = []
    for tp in (load_packed_toolpaths(f), load_toolpaths(f)):
        with pytest.raises(WorkspaceError) as e:
            next(motion.iter_plan_packed(tp, job))
        messages.append(str(e.value))
    assert messages[0] == messages[1] and "layer 4, path 0: point 0" in messages[0]
