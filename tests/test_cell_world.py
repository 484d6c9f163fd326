"""The virtual cell's surface model: the simulator's layer step, persisted.

Ground truth: ``icefab.sim.simulate_build`` in valves mode on the same trajectories (the
cell must give the same surface bit for bit when its valves drop what the simulator's
do: PWM), determinism across restarts (a new World read from the state folder between
every step), and the layout of surface.npz.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_build import annulus_toolpaths  # noqa: E402

from icefab import Job, flow  # noqa: E402
from icefab.cell import robot_protocol as rp  # noqa: E402
from icefab.cell.robot import as_received, robot_paths  # noqa: E402
from icefab.cell.world import World, grid_for  # noqa: E402
from icefab.errors import CellError  # noqa: E402
from icefab.motion import plan_toolpaths  # noqa: E402
from icefab.sim import layer_valves, plan_layer_motion, simulate_build  # noqa: E402


def _job(mode):
    return Job().replace(**{"simulation.deposition": "valves", "flow.mode": mode,
                            "cell.cpus": 1, "feedback.interval_layers": 2})


@pytest.fixture(scope="module", params=["pwm", "fm"])
def build(request):
    job = _job(request.param)
    motion = as_received(plan_toolpaths(annulus_toolpaths(job, 2), job))
    return job, motion, simulate_build(motion, job, closed_loop=False)


def _run(world_factory, motion, job):
    """Every layer through a World as the cell runs it: each deposition path's pulses
    (the programs the host would upload, played from t = 0), laser paths read, layer end.
    world_factory() gives the World to use for each step (the same, or re-read)."""
    values = []
    for lm in motion.layers:
        progs = iter(layer_valves(plan_layer_motion(lm, job), job).programs)
        for p in robot_paths(lm, job):
            w = world_factory()
            if p.flags & rp.FLAG_VALVE:
                prog = next(progs)
                t = flow.pulse_times(prog)
                widths = prog.widths_us if prog.widths_us is not None else np.full(len(t), 500)
                valve = 0 if p.tool == "part" else 1
                w.deposit_path(lm.index, p.xy, p.dt_s, p.width_mm, p.tool,
                               [(valve, ti, wi) for ti, wi in zip(t, widths)])
            elif p.flags & rp.FLAG_LASER:
                values.append(w.laser_values(p.xy, p.dt_s, p.z_mm))
            w.save()
        w = world_factory()
        w.freeze()
        w.save()
    return world_factory(), values


def test_pwm_cell_surface_is_the_simulators_bit_for_bit(build, tmp_path):
    job, motion, res = build
    world = World(tmp_path, job, *(), **dict(zip(("origin", "shape", "spacing"),
                                                 grid_for(motion, job))))
    world, _ = _run(lambda: world, motion, job)
    got = world.height_map()
    np.testing.assert_array_equal(got.origin, res.height.origin)
    if job.flow.mode == "pwm":
        np.testing.assert_array_equal(got.z, res.height.z)       # NaN where never deposited
    else:
        # FM: the cell's valve drops Q(nu)/nu at the rate it actually pulses at, the
        # simulator at the commanded frequency; the same footprint, heights within 1 %
        assert np.array_equal(np.isnan(got.z), np.isnan(res.height.z))
        ok = np.isfinite(got.z)
        rel = np.abs(got.z[ok] - res.height.z[ok]).max() / np.nanmax(res.height.z)
        assert 0 < rel < 0.01


def test_same_steps_give_the_same_surface_across_restarts(build, tmp_path):
    job, motion, _ = build
    grid = dict(zip(("origin", "shape", "spacing"), grid_for(motion, job)))
    sub = motion
    a = World(tmp_path / "a", job, **grid)
    a, va = _run(lambda: a, sub, job)
    World(tmp_path / "b", job, **grid)
    b, vb = _run(lambda: World(tmp_path / "b", job), sub, job)   # re-read at every step
    np.testing.assert_array_equal(a.z, b.z)
    assert len(va) == len(vb) > 0
    for x, y in zip(va, vb):
        np.testing.assert_array_equal(x, y)


def test_surface_file_layout(tmp_path):
    job = _job("fm")
    w = World(tmp_path, job, origin=(-5.0, -3.0), shape=(7, 11), spacing=0.5)
    with np.load(tmp_path / "surface.npz") as d:
        assert str(d["format"]) == "icefab-cell-surface" and int(d["version"]) == 1
        np.testing.assert_array_equal(d["origin"], [-5.0, -3.0])
        assert float(d["spacing"]) == 0.5 and d["z"].shape == (7, 11)
    assert np.isnan(w.height_map().z).all()


def test_a_new_state_needs_a_grid_and_a_corrupt_one_is_named(tmp_path):
    with pytest.raises(CellError, match="no surface yet"):
        World(tmp_path / "none", _job("fm"))
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "surface.npz").write_bytes(b"garbage")
    with pytest.raises(CellError, match="surface.npz: cannot read the cell surface"):
        World(tmp_path / "bad", _job("fm"))


def _deposit_first_paths(world, motion, job, n):
    """The first ``n`` deposition paths of the first layer into ``world``, each saved."""
    lm = motion.layers[0]
    progs = iter(layer_valves(plan_layer_motion(lm, job), job).programs)
    done = 0
    for p in robot_paths(lm, job):
        if not p.flags & rp.FLAG_VALVE:
            continue
        prog = next(progs)
        t = flow.pulse_times(prog)
        widths = prog.widths_us if prog.widths_us is not None else np.full(len(t), 500)
        world.deposit_path(lm.index, p.xy, p.dt_s, p.width_mm, p.tool,
                           [(0 if p.tool == "part" else 1, ti, wi) for ti, wi in zip(t, widths)])
        world.last_done += 1
        world.save()
        done += 1
        if done == n:
            return
    raise AssertionError(f"the first layer has only {done} deposition paths")


def _same_state(a, b):
    np.testing.assert_array_equal(a.z, b.z)
    np.testing.assert_array_equal(a.ever, b.ever)
    assert (a.last_done, a.cut, a.layers_frozen) == (b.last_done, b.cut, b.layers_frozen)
    pa, pb = a.pending.arrays(), b.pending.arrays()
    assert pa.keys() == pb.keys()
    for key in pa:
        np.testing.assert_array_equal(pa[key], pb[key])


def test_a_path_saves_only_its_own_liquid_and_a_freeze_the_whole_surface(build, tmp_path):
    """A path's save leaves surface.npz alone and writes a piece of its own drops, as
    small on a grid 40 times larger (the whole surface and the layer's liquid were
    rewritten after every path: ~5 MB a path on a 300 mm part, growing along the layer);
    a freeze writes the surface whole and the pieces go."""
    job, motion, _ = build
    origin, shape, spacing = grid_for(motion, job)
    sizes = []
    for scale in (1, 40):
        d = tmp_path / f"x{scale}"
        w = World(d, job, origin=origin, shape=(shape[0] * scale, shape[1]), spacing=spacing)
        before = (d / "surface.npz").stat()
        _deposit_first_paths(w, motion, job, 3)
        after = (d / "surface.npz").stat()
        assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)
        pieces = sorted(d.glob("liquid-*.npz"))
        assert [f.name for f in pieces] == ["liquid-1-0.npz", "liquid-1-1.npz",
                                             "liquid-1-2.npz"]
        sizes.append([f.stat().st_size for f in pieces])
        assert max(sizes[-1]) < after.st_size / 2
        _same_state(w, World(d, job))
        w.freeze()
        w.save()
        assert not list(d.glob("liquid-*.npz"))
        with np.load(d / "surface.npz") as s:
            assert int(s["generation"]) == 2 and len(s["pend_a"]) == 0
        _same_state(w, World(d, job))
    assert sizes[0] == sizes[1]


def test_a_crash_between_a_surface_and_its_pieces_removal_is_harmless(build, tmp_path):
    """Pieces of an older generation (the process died after writing the next surface,
    before deleting them) are the next surface's already: a read ignores and removes
    them. A missing piece in the middle is named."""
    job, motion, _ = build
    d = tmp_path / "cell"
    w = World(d, job, **dict(zip(("origin", "shape", "spacing"), grid_for(motion, job))))
    _deposit_first_paths(w, motion, job, 2)
    old = {f.name: f.read_bytes() for f in d.glob("liquid-*.npz")}
    w.freeze()
    w.save()
    for name, data in old.items():
        (d / name).write_bytes(data)
    again = World(d, job)
    _same_state(w, again)
    assert not list(d.glob("liquid-*.npz"))
    _deposit_first_paths(again, motion, job, 3)
    (d / "liquid-2-1.npz").unlink()
    with pytest.raises(CellError, match=r"liquid-2-2.npz: liquid piece 2 .* piece 1 should"):
        World(d, job)


def test_a_new_surface_takes_no_piece_of_the_part_it_replaces(build, tmp_path):
    """A folder whose surface.npz went (a new part) but whose pieces stayed: the new
    surface started at generation 1 too and took them for its own (a tester's fresh cell
    reported 3 paths done and 388 segments it never deposited)."""
    job, motion, _ = build
    grid = dict(zip(("origin", "shape", "spacing"), grid_for(motion, job)))
    d = tmp_path / "cell"
    _deposit_first_paths(World(d, job, **grid), motion, job, 3)
    assert len(list(d.glob("liquid-1-*.npz"))) == 3
    (d / "surface.npz").unlink()
    fresh = World(d, job, **grid)
    assert not list(d.glob("liquid-*.npz"))
    again = World(d, job)
    assert again.last_done == 0 and again.pending.empty()
    _same_state(fresh, again)


@pytest.mark.parametrize("damage", [lambda b: b[: len(b) // 2], lambda b: b"",
                                    lambda b: b[:40] + bytes([b[40] ^ 0xFF]) + b[41:]])
def test_a_damaged_piece_is_named_in_one_line(build, tmp_path, damage):
    job, motion, _ = build
    d = tmp_path / "cell"
    w = World(d, job, **dict(zip(("origin", "shape", "spacing"), grid_for(motion, job))))
    _deposit_first_paths(w, motion, job, 2)
    piece = d / "liquid-1-1.npz"
    piece.write_bytes(damage(piece.read_bytes()))
    with pytest.raises(CellError, match=r"liquid-1-1.npz: cannot read a liquid piece"):
        World(d, job)


def test_a_killed_cells_temporary_files_go_when_old(build, tmp_path):
    import os
    import time

    job, motion, _ = build
    d = tmp_path / "cell"
    World(d, job, **dict(zip(("origin", "shape", "spacing"), grid_for(motion, job))))
    old, new = d / ".liquid-1-10.npz.3fa4920a.npz", d / ".surface.npz.0badcafe.npz"
    for f in (old, new):
        f.write_bytes(b"half a save")
    os.utime(old, (time.time() - 120, time.time() - 120))
    World(d, job)
    assert not old.exists() and new.exists()   # a save in flight is left alone


def test_robot_paths_run_at_the_top_of_the_layer_being_deposited():
    """The robot paths of a layer (what ``cell.links.run_layer`` sends) were at its
    cutting plane ``layer.z``, inside the layer, while the build runner sends the layer's
    top: now both send the top."""
    job = _job("fm")
    motion = as_received(plan_toolpaths(annulus_toolpaths(job, 2), job))
    for lm in motion.layers:
        zs = [p.z_mm for p in robot_paths(lm, job)]
        assert zs and zs == pytest.approx([lm.top(job)] * len(zs))
        assert lm.top(job) > lm.z + 1e-6
