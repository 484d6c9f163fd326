"""The build runner: journal, exactly-once resume after crashes of the control PC and
faults of the cell, refusals before anything moves, status/stop, the report in a browser.

A crash of the control PC is injected in-process (an exception that is not a cell error,
at a random command, before or after the cell ran it) and, end to end, by SIGKILL of the
``icefab build`` process; the virtual cell keeps its state in its folder."""
from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import io
import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from icefab.errors import CellError, ConfigError, WorkspaceError

from icefab import build as bmod
from icefab.config import Job, to_toml
from icefab.journal import Journal, JournalError
from icefab.runcell import VirtualCell

LAYERS = 5          # the demo mug's first 5 layers: 4 and 8 hold measurement paths (n_d = 4)


def _plan_mug(n_layers: int, folder: Path) -> Path:
    """The demo mug's first ``n_layers`` layers, trajectories planned (trajectories.npz)."""
    from icefab.demo import demo_mug
    from icefab.mesh import transform
    from icefab.motion import plan_toolpaths, save_trajectories
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh
    from icefab.core import Stack

    # The default job: it leaves the part valve no room for SMF's full correction at
    # 125 mm/s (121.9 mm^3/s needed, 115.3 given: icefab.headroom), so the valve
    # saturates the correction there (thesis 5.2.2) -- a resumed build, whose surface and
    # correction differ from the uninterrupted one's, must not stop on it
    job = Job()
    stack = add_scaffold(slice_mesh(transform(demo_mug(), job.parts), job), job)
    stack = Stack(layers=stack.layers[:n_layers], job=stack.job,
                  layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    motion = plan_toolpaths(plan_paths(stack, job), job)
    save_trajectories(motion, folder / f"mug{n_layers}.npz")
    return folder / f"mug{n_layers}.npz"


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """The demo mug's first LAYERS layers, trajectories planned once (trajectories.npz)."""
    return _plan_mug(LAYERS, tmp_path_factory.mktemp("plan"))


def test_journal_answers_a_bunny_sized_build_by_index_and_keeps_two_smf_states(tmp_path):
    """A 1 200-layer build's journal (555 000 commands): what the runner asks per layer or
    per reconnection scanned every command (a resume near the end waited 5 minutes before
    its first path, deaf to --stop; a reconnection read 3 s and 360 MB), the report read
    every measurement's samples for the last one, and every SMF state was kept (0.7 of a
    1 GB journal; only the last is read). A hunt's measurements."""
    j = Journal.create(tmp_path / "j.sqlite", {"digests": {}})
    n = 460 * 1200
    with j._tx() as db:
        db.executemany("INSERT INTO commands (seq, kind, layer, item, digest, created, done) "
                       "VALUES (?, 'path', ?, ?, 'd', 0, 1)",
                       [(i + 1, i // 460, i % 460) for i in range(n)])
        db.execute("UPDATE commands SET done = NULL WHERE seq > ?", (n - 3,))
    for q, a, index in (
            ("SELECT seq FROM commands WHERE done IS NULL ORDER BY seq", (), "commands_open"),
            ("SELECT item FROM commands WHERE layer=? AND kind='path' AND done IS NOT NULL",
             (5,), "sqlite_autoindex_commands_1"),   # UNIQUE (kind, layer, item)
            ("SELECT DISTINCT layer FROM commands WHERE cut", (), "commands_cut")):
        plan = " ".join(r[3] for r in j._db.execute("EXPLAIN QUERY PLAN " + q, a))
        assert f"USING INDEX {index}" in plan, (q, plan)   # its rows only, not every one
    assert [c["seq"] for c in j.commands(open_only=True)] == [n - 2, n - 1, n]
    assert j.done_items(1199)[-3:] == [454, 455, 456]
    assert j.numbered_after(n - 1, 1199) is False and j.numbered_after(5, 0) is True
    # the cut layers: read once, then kept by done()
    assert j.cut_layers() == set()
    j.done(n - 1, cut=True)
    assert j.cut_layers() == {1199}
    j.done(n - 1)                     # reported whole after all
    assert j.cut_layers() == set()
    # measurements without their samples, the last with them; two SMF states kept
    for k in range(1, 6):
        j.measurement(k, 4 * k, 0.25 * k, np.full((3, 3), float(k)), 0.1 * k,
                      smf_state=bytes([k]) * 10)
    assert [m["layer"] for m in j.measurements(samples=False)] == [4, 8, 12, 16, 20]
    assert "samples" not in j.measurements(samples=False)[0]
    (last,) = j.measurements(last=True)
    assert last["k"] == 5 and last["samples"][0, 0] == 5.0
    assert [r[0] for r in j._db.execute("SELECT k FROM smf ORDER BY k")] == [4, 5]
    assert j.last_smf() == (5, 20, bytes([5]) * 10)
    # a journal made before the indexes gets them when a resume opens it
    for index in ("commands_open", "commands_cut"):
        j._db.execute(f"DROP INDEX {index}")
    j.add_indexes()
    assert {r[0] for r in j._db.execute("SELECT name FROM sqlite_master WHERE type='index'")
            } >= {"commands_open", "commands_cut"}
    j.close()


def test_the_runner_counts_a_files_layers_without_decoding_them(planned):
    """A trajectory file's per-layer motion time and path count, from its per-trajectory
    arrays: the runner decoded every layer for them at each start and resume."""
    from icefab.motion import open_trajectories

    motion = open_trajectories(planned)
    want = [(lm.duration, len(bmod._items(lm)[0]) + len(bmod._items(lm)[1]))
            for lm in motion.layers]
    for layers, rows in ((motion.layers, want), (motion.layers[1:4], want[1:4])):
        durations, paths = layers.summary()
        np.testing.assert_allclose(durations, [d for d, _ in rows], rtol=1e-12)
        assert list(paths) == [n for _, n in rows]


def test_journal_is_wal_full_and_keeps_sequence_numbers(tmp_path):
    j = Journal.create(tmp_path / "j.sqlite", {"digests": {"job": "a"}})
    assert j._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert j._db.execute("PRAGMA synchronous").fetchone()[0] == 2      # FULL
    s1, new1 = j.command("path", 0, 0, "d0")
    s2, new2 = j.command("path", 0, 1, "d1")
    assert (s1, s2, new1, new2) == (1, 2, True, True)
    j.close()
    j = Journal.open(tmp_path / "j.sqlite")
    assert j.command("path", 0, 0, "d0") == (1, False)     # the repeat keeps its number
    with pytest.raises(JournalError, match="other content"):
        j.command("path", 0, 1, "changed")
    with pytest.raises(JournalError, match="job changed"):
        j.check_digests({"job": "b"})
    j.check_digests({"job": "a"})
    with pytest.raises(JournalError, match="exists already"):
        Journal.create(tmp_path / "j.sqlite", {})
    (tmp_path / "x.sqlite").write_bytes(b"not a database at all" * 50)
    with pytest.raises(JournalError, match="not a build journal"):
        Journal.open(tmp_path / "x.sqlite")


def test_stroke_is_checked_before_anything_moves(planned):
    from icefab.motion import BuildMotion, LayerMotion, load_trajectories

    m = load_trajectories(planned)
    tall = BuildMotion(layers=(LayerMotion(index=0, z=230.0, trajectories=()),), job=m.job)
    with pytest.raises(WorkspaceError, match="vertical stroke cell.stroke_mm = 210 mm"):
        bmod.check_build(tall, m.job, 1)
    bmod.check_build(m, m.job, len(m.layers))
    # the cell's own stroke, not the Cobra's constant: a taller cell takes it
    bmod.check_build(tall, m.job.replace(**{"cell.stroke_mm": 300.0}), 1)
    with pytest.raises(WorkspaceError, match="cell.stroke_mm = 200 mm"):
        bmod.check_build(tall, m.job.replace(**{"cell.stroke_mm": 200.0}), 1)


def _layer(index: int, xy, role: str = "fill", dt: float = 0.016, top_z: float = float("nan")):
    """A layer of one trajectory through the points ``xy`` (mm, base frame), ``dt`` s
    apart."""
    from icefab.core import LayerMotion, Toolpath, Trajectory

    xy = np.asarray(xy, np.float64)
    path = Toolpath(points=xy, z=0.25 * index, material="part", role=role, closed=False)
    t = Trajectory(dt=dt, xy=xy, joints=np.zeros((len(xy), 2)), speed=np.ones(len(xy)),
                   duration=(len(xy) - 1) * dt, path=path)
    return LayerMotion(index=index, z=0.25 * index, trajectories=(t,), top_z=top_z)


def test_a_gantrys_stroke_and_travel_refusals_name_the_gantrys_settings():
    # a gantry hunt's: the stroke refusal quoted "(Cobra 600: 210 mm, ...)" and the reach
    # refusal named cell.reach_mm and cell.joint_range_deg, SCARA settings; the gantry's
    # travel is cell.gantry_travel_mm (check_build refuses a gantry job first, so its
    # checks are called here as a G-code job would need them)
    from icefab.motion import BuildMotion

    job = Job().replace(**{"cell.robot": "gantry", "cell.stroke_mm": 100.0})
    ok = [[150.0, 150.0], [151.0, 150.0]]
    tall = BuildMotion(layers=(_layer(0, ok, top_z=50.0), _layer(1, ok, top_z=120.0)),
                       job=job)
    with pytest.raises(WorkspaceError, match=r"cell.stroke_mm = 100 mm from layer 1") as ei:
        bmod._check_stroke(tall, job, 2)
    assert "Cobra" not in str(ei.value)
    far = BuildMotion(layers=(_layer(0, ok + [[350.0, 150.0]]),), job=job)
    with pytest.raises(WorkspaceError, match=r"x = 350.000 mm outside the travel \[0, 300\] "
                                             r"mm \(cell.gantry_travel_mm\)") as ei:
        bmod._check_reach(far, job, 1)
    assert "reach_mm" not in str(ei.value) and "joint_range" not in str(ei.value)


def test_a_refused_build_names_its_first_offending_layer_and_counts_them():
    """A build refused for its reach, stroke or laser storage names the first layer in
    build order, as a user fixing the file needs it, and how many offend (a review's: the
    headroom refusal named the tightest; the others named no count, the stroke no layer,
    and the laser's rate fitted only the first path)."""
    from icefab.cell.lkg import STORAGE_CAPACITY
    from icefab.motion import BuildMotion

    job = Job()
    ok = [[300.0, -100.0], [301.0, -100.0]]
    far = BuildMotion(layers=(_layer(0, ok), _layer(1, ok + [[700.0, 0.0]]), _layer(2, ok),
                              _layer(3, ok + [[900.0, 0.0]])), job=job)
    with pytest.raises(WorkspaceError) as ei:
        bmod.check_build(far, job, 4)
    text = str(ei.value)
    assert text.startswith("layer 1, path 0, before anything moves")
    assert "point 2 at (700.000, 0.000) mm" in text
    assert "(the first of 2 layers with points out of reach); move the part" in text
    assert "layer 3" not in text
    tall = BuildMotion(layers=tuple(_layer(k, ok, top_z=z) for k, z in
                                    enumerate((100.0, 215.0, 209.0, 230.0, 240.0))), job=job)
    with pytest.raises(WorkspaceError, match=r"beyond the robot's vertical stroke "
                                             r"cell.stroke_mm = 210 mm \(Cobra 600: 210 mm, "
                                             r"thesis Table 2-1\) from layer 1 on, its top at "
                                             r"215.0 mm \(the first of 3 layers above it\)$"):
        bmod.check_build(tall, job, 5)
    rate = job.simulation.laser_rate_hz
    long_s = [1.5 * STORAGE_CAPACITY / rate, 3.0 * STORAGE_CAPACITY / rate]
    rings = BuildMotion(layers=tuple(
        _layer(k, np.c_[np.linspace(300, 301, 11), np.full(11, -100.0)], role="measure",
               dt=d / 10) for k, d in ((2, long_s[0]), (5, long_s[1]))), job=job)
    with pytest.raises(ConfigError) as ei:
        bmod.check_build(rings, job, 2)
    text = str(ei.value)
    assert text.startswith("layer 2, measurement path 0: ")
    assert "(the first of 2 such measurement paths); lower simulation.laser_rate_hz to " \
           f"at most {(STORAGE_CAPACITY - 1) / long_s[1]:.0f} Hz" in text


def test_reach_of_the_builds_cell_is_checked_before_anything_moves(planned):
    """Trajectories planned for one cell, built with a job whose reach is shorter: refused
    before anything moves, naming the layer, path, point and the reach."""
    from icefab.motion import load_trajectories

    m = load_trajectories(planned)
    r = max(float(np.hypot(*t.xy.T).max()) for lm in m.layers for t in lm.trajectories
            if len(t.xy))
    short = m.job.replace(**{"cell.reach_mm": [163.0, r - 5.0]})
    with pytest.raises(WorkspaceError, match=r"layer \d+, path \d+, before anything moves"):
        bmod.check_build(m, short, len(m.layers))
    bmod.check_build(m, m.job.replace(**{"cell.reach_mm": [163.0, r + 1.0]}), len(m.layers))


def test_a_measurement_path_the_laser_cannot_store_is_refused_before_anything_moves(planned):
    """The LK-G3001P stores 65 536 values and the cell reads them after each measurement
    path: at a sampling rate that would overflow it on the longest measurement path, the
    build is refused before anything moves, naming the layer, the path and the highest
    rate that fits; at that rate it starts."""
    from icefab.cell.lkg import STORAGE_CAPACITY
    from icefab.motion import load_trajectories

    m = load_trajectories(planned)
    longest = max(tr.duration for lm in m.layers for _i, tr in bmod._items(lm)[1])
    assert longest > 0.0
    fits = (STORAGE_CAPACITY - 1) / longest
    bmod.check_build(m, m.job.replace(**{"simulation.laser_rate_hz": fits}), len(m.layers))
    with pytest.raises(ConfigError, match=r"layer \d+, measurement path \d+: .* lower "
                                          r"simulation.laser_rate_hz to at most"):
        bmod.check_build(m, m.job.replace(**{"simulation.laser_rate_hz": 1.01 * fits}),
                         len(m.layers))


def test_gains_that_make_smf_unstable_are_refused_before_anything_moves(planned, tmp_path):
    """The thesis' own unstable example (Kp 1, Ki* 0.33, Kd* 0.45: pole 1.048, Fig.
    5-12) ran a build without a word: refused now, naming the gains and the pole, with
    nothing left behind; gains with a pole on the unit circle only warn; feedback off
    checks nothing."""
    from icefab.motion import load_trajectories

    m = load_trajectories(planned)
    bad = m.job.replace(**{"feedback.kp": 1.0, "feedback.ki": 0.33, "feedback.kd": 0.45})
    with pytest.raises(ConfigError, match=r"feedback.kp, ki, kd = 1, 0.33, 0.45 make the "
                                          r"SMF loop unstable \(largest pole modulus 1.048"):
        bmod.check_build(m, bad, len(m.layers))
    bmod.check_build(m, bad.replace(**{"feedback.enabled": False}), len(m.layers))
    bmod.check_build(m, m.job.replace(**{"feedback.ki": 0.0, "feedback.kd": 0.0}),
                     len(m.layers))   # Kp alone: a pole at 1, the error stays
    (tmp_path / "wild.toml").write_text("[feedback]\nkp = 1.0\nki = 0.33\nkd = 0.45\n")
    r = _icefab("build", str(planned), "-o", "u", "--virtual", "-c", "wild.toml",
                cwd=tmp_path)
    assert r.returncode == 2 and "make the SMF loop unstable" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1 and not (tmp_path / "u").exists()


def test_unstable_gains_are_refused_before_the_part_is_sliced(tmp_path, monkeypatch, capsys):
    """'icefab build MESH -c unstable.toml' sliced, scaffolded and planned the part before
    check_build refused the gains (the demo mug: 500 layers; a reviewer's)."""
    import icefab.cli as cli
    import icefab.cli.simulate_cmd as simulate_cmd

    def sliced(*args, **kwargs):
        raise AssertionError("the part was loaded and sliced before the gains were checked")

    monkeypatch.setattr(simulate_cmd, "load_build", sliced)
    (tmp_path / "wild.toml").write_text("[feedback]\nkp = 1.0\nki = 0.33\nkd = 0.45\n")
    assert cli.main(["build", "demo", "-o", str(tmp_path / "u"), "--virtual", "-c",
                     str(tmp_path / "wild.toml")]) == 2
    err = capsys.readouterr().err
    assert "make the SMF loop unstable" in err and err.count("\n") == 1
    assert not (tmp_path / "u").exists()


class Crash(BaseException):
    """The control PC dies (not an error the runner handles)."""


class CrashingCell:
    """A cell that makes the control PC 'die' at call ``at``: before the cell gets the
    command, or after it ran it (the reply lost)."""

    def __init__(self, cell: VirtualCell, at: int, after: bool) -> None:
        self.cell, self.at, self.after, self.n = cell, at, after, 0

    def __getattr__(self, name):
        fn = getattr(self.cell, name)
        if name not in ("run_path", "end_layer"):
            return fn

        def call(*a):
            self.n += 1
            if self.n == self.at and not self.after:
                raise Crash()
            out = fn(*a)
            if self.n == self.at:
                raise Crash()
            return out
        return call


def _inprocess(build: Path, motion, job, crash_at=None, after=False):
    jpath = build / bmod.JOURNAL
    if jpath.exists():
        journal, cell = Journal.open(jpath), VirtualCell(build / "cell")
    else:
        cell = _prepared(build, motion, job)
        journal = Journal.create(jpath, {"digests": {}})
    c = cell if crash_at is None else CrashingCell(cell, crash_at, after)
    runner = bmod.Runner(build, motion, job, journal, lambda: c)
    try:
        return runner.run()
    finally:
        journal.close()


class FaultingCell:
    """A cell that faults at the start of the first deposition path of ``layer``: the link
    drops and, reconnected, the cell reports that path as cut (nothing of it deposited)."""

    def __init__(self, cell: VirtualCell, layer: int) -> None:
        self.cell, self.layer, self.cut = cell, layer, 0

    def __getattr__(self, name):
        return getattr(self.cell, name)

    def status(self):
        st = self.cell.status()
        return dataclasses.replace(st, cut=self.cut) if self.cut else st

    def run_path(self, seq, path, upcoming=None):
        if not self.cut and path.layer == self.layer and path.role != "measure":
            self.cut = seq
            raise CellError("link lost (cell fault)")
        return self.cell.run_path(seq, path, upcoming)


def _prepared(build: Path, motion, job) -> VirtualCell:
    """A model cell in ``build/cell`` holding a new build of these trajectories."""
    from icefab.cli.build_cmd import _box

    build.mkdir(exist_ok=True)
    cell = VirtualCell(build / "cell")
    lo, hi = _box(motion, job)
    cell.prepare(to_toml(job), tuple(lo), tuple(hi))
    return cell


def test_a_cell_fault_is_measured_before_the_next_layer(planned, tmp_path):
    """Layer 1 (not a measurement layer: every 4th is) has a path cut by a cell fault: it
    is journaled as cut, never re-run, and the surface is measured at the layer's end with
    the nearest measurement layer's paths, an SMF update made there."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    faulty = FaultingCell(cell, layer=1)
    etas = []
    runner = bmod.Runner(build, motion, job, journal, lambda: faulty,
                         on_progress=lambda p: etas.append(p.remaining_s))
    runner.run()
    # the fault's measurement was never in the planned time: taken off, the ETA fell
    # below the truth and jumped back at the next layer (hunt Z)
    assert all(b <= a + 1e-9 for a, b in zip(etas, etas[1:]))
    cut = [c for c in journal.commands() if c["cut"]]
    assert len(cut) == 1 and cut[0]["seq"] == faulty.cut and cut[0]["layer"] == 1
    assert faulty.cut not in _executed(build)  # never run again
    measured = [m["layer"] for m in journal.measurements()]
    assert measured[0] == 1  # before any regular measurement (layer 3)
    assert [e["layer"] for e in journal.events() if e["kind"] == "fault-measure"] == [1]
    assert any(c["kind"] == "fault_measure" and c["layer"] == 1 for c in journal.commands())
    journal.close()


def test_the_valve_saturates_a_correction_it_cannot_give_and_the_build_goes_on(planned,
                                                                                tmp_path):
    """The virtual cell lays 30 % too little (simulation.flow_error): after the
    measurement of layer 3, SMF asks for about +30 % on layer 4, more than the part valve
    gives along the mug's widest fill at 125 mm/s (+23 %: icefab.headroom). The valve
    saturates it (thesis 5.2.2): the build completes, and the layer's journal says how
    much volume it gave of what SMF asked. Under the default flow.out_of_range = "error"
    this build used to stop there with a valve frequency above 500 Hz."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job.replace(**{"simulation.flow_error": -0.3})
    assert job.flow.out_of_range == "error"
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    bmod.Runner(build, motion, job, journal, lambda: cell).run()
    said = [e for e in journal.events() if e["kind"] == "saturation"]
    assert said and all(e["layer"] == 4 for e in said), said
    assert "the valve saturated SMF's correction on" in said[0]["text"]
    got, asked = (float(x) for x in re.search(r"([0-9.]+) of the ([0-9.]+) mm\^3",
                                              said[0]["text"]).groups())
    assert 0 < got < asked
    assert len(journal.measurements()) >= 1
    journal.close()


class CrashInLayer:
    """A cell whose control PC 'dies' right after the first path of ``layer`` ran."""

    def __init__(self, cell: VirtualCell, layer: int) -> None:
        self.cell, self.layer, self.crashed = cell, layer, False

    def __getattr__(self, name):
        return getattr(self.cell, name)

    def run_path(self, seq, path, upcoming=None):
        out = self.cell.run_path(seq, path, upcoming)
        if path.layer == self.layer and not self.crashed:
            self.crashed = True
            raise Crash()
        return out


def test_a_resumed_build_journals_its_findings_once(planned, tmp_path):
    """The saturation build above, its PC killed in layer 4 after the layer's finding was
    journaled: the resumed build plans the layer's programs again, finds the same, and
    does not journal it twice (it did: the findings said were kept in memory only)."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job.replace(**{"simulation.flow_error": -0.3})
    build = tmp_path / "b"
    cell = CrashInLayer(_prepared(build, motion, job), layer=4)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    with pytest.raises(Crash):
        bmod.Runner(build, motion, job, journal, lambda: cell).run()
    journal.close()
    assert cell.crashed
    _inprocess(build, motion, job)
    journal = Journal.open(build / bmod.JOURNAL)
    said = [e["layer"] for e in journal.events() if e["kind"] == "saturation"]
    journal.close()
    assert said == [4]


def test_the_build_says_it_runs_before_its_first_path(planned, tmp_path):
    """status.json shows the build running, with its process, before the first path
    runs: 'icefab build --stop' asked then stops the build (a stop asked before it found
    no status and went to the cell alone)."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    seen, closed = [], []

    class Watching:
        def __getattr__(self, name):
            return getattr(cell, name)

        def run_path(self, seq, path, upcoming=None):
            if not seen:
                seen.append(json.loads((build / bmod.STATUS).read_text()))
            return cell.run_path(seq, path, upcoming)

        def close(self):
            closed.append(True)

    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    runner = bmod.Runner(build, motion, job, journal, lambda: Watching())
    runner.run()
    journal.close()
    assert seen[0]["state"] == "running" and seen[0]["pid"] == os.getpid()
    assert seen[0]["paths_done"] == 0
    # the runner closed the link it opened (left open, a real link's socket closed
    # whenever the runner was collected)
    assert closed == [True] and runner.cell is None


def _executed(build: Path) -> list[int]:
    return [int(x) for x in (build / "cell" / "executed.log").read_text().split()]


def test_exactly_once_after_crashes_in_process(planned, tmp_path):
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    ref = tmp_path / "ref"
    _inprocess(ref, motion, job)
    n_cmds = len(_executed(ref))
    rng = np.random.default_rng(3)
    crashed = tmp_path / "crashed"
    done = False
    kills = 0
    while not done:
        at = int(rng.integers(1, max(2, n_cmds // 3)))
        try:
            _inprocess(crashed, motion, job, crash_at=at, after=bool(rng.integers(0, 2)))
            done = True
        except Crash:
            kills += 1
    assert kills >= 3
    a = np.load(ref / "cell" / "surface.npz")
    b = np.load(crashed / "cell" / "surface.npz")
    assert np.array_equal(a["z"], b["z"], equal_nan=True)       # bit-identical
    ex = _executed(crashed)
    assert Counter(ex).most_common(1)[0][1] == 1 and len(ex) == n_cmds
    j = Journal.open(crashed / bmod.JOURNAL)
    cmds = j.commands()
    assert all(c["done"] is not None and not c["cut"] for c in cmds)
    assert sorted(ex) == [c["seq"] for c in cmds]
    assert len({(c["kind"], c["layer"], c["item"]) for c in cmds}) == len(cmds)


def test_a_cell_that_lost_its_record_is_named_on_resume(planned, tmp_path):
    # a tester resumed on a fresh cell (its state folder moved away): a path the old cell
    # had run was run again and the build was 'complete' over a part missing its first
    # layers. Now refused; with --cell-lost-record the journal's record stands and the
    # path in flight counts as cut
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    with pytest.raises(Crash):
        _inprocess(build, motion, job, crash_at=40, after=True)   # ran, reply lost
    journal = Journal.open(build / bmod.JOURNAL)
    in_flight = [c["seq"] for c in journal.commands() if c["sent"] and c["done"] is None]
    assert in_flight
    journal.close()
    shutil.move(build / "cell", tmp_path / "old-cell")
    fresh = _prepared(build, motion, job)       # a new state: its record starts at 0
    journal = Journal.open(build / bmod.JOURNAL)
    try:
        with pytest.raises(JournalError, match=r"record of completed paths ends at number "
                                               r"0, but this build's journal has path \d+ "
                                               r"done: the cell lost its record"):
            bmod.Runner(build, motion, job, journal, lambda: fresh).run()
        p = bmod.Runner(build, motion, job, journal, lambda: fresh,
                        accept_cell_reset=True).run()
        assert p.state == "complete"
        # the first command in flight may have run: cut; a path after it was only
        # uploaded ahead (its GO waits for the one before): run on the new cell (it was
        # cut too and the part missed it, a hunt's)
        kinds = {c["seq"]: c["kind"] for c in journal.commands()}
        assert journal.is_cut(in_flight[0])
        ahead = [s for s in in_flight[1:] if kinds[s] == "path"]
        assert ahead        # the crash left one uploaded ahead
        assert all(not journal.is_cut(s) and journal.is_done(s) for s in ahead)
        assert set(ahead) <= set(_executed(build))
        assert any(e["kind"] == "cell-reset" for e in journal.events())
    finally:
        journal.close()
    old = {int(x) for x in (tmp_path / "old-cell" / "executed.log").read_text().split()}
    assert old and not old & set(_executed(build))     # no path ran on both cells


class OutageCell:
    """A cell whose link is down (every call a CellError) for ``length`` calls at a time
    before paths ``at``."""

    def __init__(self, cell: VirtualCell, at: set, length: int) -> None:
        self.cell, self.at, self.length, self.down, self.n = cell, set(at), length, 0, 0

    def __getattr__(self, name):
        fn = getattr(self.cell, name)
        if name not in ("run_path", "status"):
            return fn

        def call(*a, **k):
            if name == "run_path":
                self.n += 1
                if self.n in self.at:
                    self.at.discard(self.n)
                    self.down = self.length
            if self.down:
                self.down -= 1
                raise CellError("no reply within 10 s")
            return fn(*a, **k)
        return call


def test_link_faults_count_in_a_row_and_the_status_says_the_build_waits(planned, tmp_path,
                                                                         monkeypatch):
    # a tester's three outages of a valve controller each came back, but the limit counted
    # every fault of the run (20) and the third ended the build; a stalled cell left the
    # console and the status silent
    from icefab.motion import load_trajectories

    monkeypatch.setattr(bmod.Runner, "FAULT_BACKOFF_S", (0.0, 0.0))
    motion = load_trajectories(planned)
    build = tmp_path / "b"
    cell = OutageCell(_prepared(build, motion, motion.job), at={5, 30, 60}, length=8)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    lines = []
    try:
        p = bmod.Runner(build, motion, motion.job, journal, lambda: cell, max_faults=10,
                        on_progress=lambda p: lines.append(bmod.progress_line(p))).run()
        assert p.state == "complete"    # 24 faults, never more than 10 in a row
        assert sum("waiting for the cell (link fault 1: no reply within 10 s)" in x
                   for x in lines) == 3
        assert not lines[-1].count("waiting")
        # one outage longer than the limit ends it, saying so
        build2 = tmp_path / "c"
        cell2 = OutageCell(_prepared(build2, motion, motion.job), at={5}, length=11)
        j2 = Journal.create(build2 / bmod.JOURNAL, {"digests": {}})
        with pytest.raises(CellError, match=r"gave up after 11 link faults in a row"):
            bmod.Runner(build2, motion, motion.job, j2, lambda: cell2, max_faults=10).run()
        j2.close()
    finally:
        journal.close()
    assert Counter(_executed(build)).most_common(1)[0][1] == 1


def test_a_stop_asked_while_the_build_waits_for_the_cell_ends_the_wait(planned, tmp_path):
    """'icefab build --stop' and Ctrl-C were polled between paths only: while the build
    waited out a silent valve link they went unheard for the 137 s of its faults (a
    hunt's). The wait now ends at the stop, journaled as one."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    build = tmp_path / "b"
    cell = OutageCell(_prepared(build, motion, motion.job), at={5}, length=100)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    asked = []
    runner = bmod.Runner(build, motion, motion.job, journal, lambda: cell, max_faults=20,
                         should_stop=lambda: bool(asked))
    real_report = runner._report

    def report(*a, **k):      # the stop is asked once the build says it waits
        if runner.progress.waiting:
            asked.append(True)
        return real_report(*a, **k)

    runner._report = report
    t0 = time.monotonic()
    try:
        with pytest.raises(bmod.BuildStopped, match="stopped at layer"):
            runner.run()
        assert time.monotonic() - t0 < 30.0
        texts = [e["text"] for e in journal.events() if e["kind"] == "stop"]
        assert any("while the build waited for the cell's link" in t for t in texts)
    finally:
        journal.close()


def test_a_second_build_on_the_same_cell_runs_every_path(planned, tmp_path):
    """The cell keeps its last completed number across builds and answers any number at
    or below it "done": a second build numbered from 1 was "complete" at once with nothing
    deposited (a tester's). It numbers after the cell's, runs every command once, and
    journals the earlier build; a crash of the second build still resumes exactly once.
    (Its platform is said cleared, though the virtual cell keeps the first part: else it
    is refused, below.)"""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    first = tmp_path / "first"
    _inprocess(first, motion, job)
    n_cmds = len(_executed(first))
    z_first = np.load(first / "cell" / "surface.npz")["z"]
    second = tmp_path / "second"
    second.mkdir()
    jpath = second / bmod.JOURNAL
    rng = np.random.default_rng(5)
    while True:  # the second build, on the first one's cell, crashed and resumed
        journal = Journal.open(jpath) if jpath.exists() else Journal.create(jpath, {})
        cell = CrashingCell(VirtualCell(first / "cell"), int(rng.integers(1, 20)), True)
        try:
            bmod.Runner(second, motion, job, journal, lambda: cell,
                        platform_cleared=True).run()
            break
        except Crash:
            pass
        finally:
            journal.close()
    ex = _executed(first)
    assert len(ex) == 2 * n_cmds and len(set(ex)) == len(ex)
    assert ex[n_cmds:] == list(range(n_cmds + 1, 2 * n_cmds + 1))
    j = Journal.open(jpath)
    assert j.first_seq() == n_cmds + 1
    assert all(c["done"] is not None and not c["cut"] for c in j.commands())
    assert [e["text"] for e in j.events() if e["kind"] == "cell-numbers"] == [
        f"the cell has completed commands up to number {n_cmds} (an earlier build; its "
        f"platform was said cleared): this build numbers from {n_cmds + 1}"]
    j.close()
    z = np.load(first / "cell" / "surface.npz")["z"]
    assert np.nanmax(z) > np.nanmax(z_first) + 0.5   # the second mug's layers on the first's
    with pytest.raises(JournalError, match="journaled already"):
        Journal.open(jpath).number_from(1)


def test_a_second_build_on_a_cell_whose_platform_may_hold_ice_is_refused(planned,
                                                                        tmp_path):
    """A cell that completed commands since its program started ran an earlier build,
    whose ice its platform may hold: a new build there put its first layers' nozzle into
    that part with a note only (a review's). It is refused before anything is sent, the
    refusal says how to go on, and the cell is as it was."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    first = tmp_path / "first"
    _inprocess(first, motion, motion.job)
    done = _executed(first)
    z_first = np.load(first / "cell" / "surface.npz")["z"]
    second = tmp_path / "second"
    second.mkdir()
    journal = Journal.create(second / bmod.JOURNAL, {})
    try:
        with pytest.raises(CellError, match=r"(?s)completed commands up to number "
                           rf"{done[-1]}.*nothing was sent.*--platform-cleared"):
            bmod.Runner(second, motion, motion.job, journal,
                        lambda: VirtualCell(first / "cell")).run()
        assert not journal.commands()
    finally:
        journal.close()
    assert _executed(first) == done
    np.testing.assert_array_equal(np.load(first / "cell" / "surface.npz")["z"], z_first)


def test_a_journal_that_lost_its_records_is_refused_before_anything_is_sent(planned,
                                                                          tmp_path):
    """A crash, then the journal's -wal file deleted (or the folder copied without it):
    the journal held only what it was created with, and the resume took the cell's done
    commands for another build's, numbered after them and built the whole part again on
    top of the first, 'complete' (a hunt's). The cell's count at the start, kept in the
    journal's first write, tells the loss: refused, nothing sent."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    jpath = build / bmod.JOURNAL
    cell = _prepared(build, motion, job)
    journal = Journal.create(jpath, {"digests": {}, bmod.CELL_DONE_AT_START: 0})
    with pytest.raises(Crash):
        bmod.Runner(build, motion, job, journal, lambda: CrashingCell(cell, 6, True)).run()
    journal.close()
    done = _executed(build)
    assert done
    for f in build.glob(bmod.JOURNAL + "*"):      # the -wal lost: what create wrote stays
        f.unlink()
    journal = Journal.create(jpath, {"digests": {}, bmod.CELL_DONE_AT_START: 0})
    with pytest.raises(JournalError, match=r"holds no command of this build, but the cell "
                       rf"has completed commands up to number {max(done)} since it started "
                       r"\(up to 0 before\): the journal lost its records"):
        bmod.Runner(build, motion, job, journal, lambda: VirtualCell(build / "cell")).run()
    journal.close()
    assert _executed(build) == done
    # a journal of an earlier icefab (no such record) numbers after the cell as before
    second = tmp_path / "second"
    second.mkdir()
    j2 = Journal.create(second / bmod.JOURNAL, {"digests": {}})
    bmod.Runner(second, motion, job, j2, lambda: VirtualCell(build / "cell"),
                platform_cleared=True).run()
    assert j2.first_seq() == max(done) + 1
    j2.close()


def _icefab(*args, cwd, **kw):
    return subprocess.run([sys.executable, "-m", "icefab", *args], cwd=cwd,
                          capture_output=True, text=True, **kw)


def _kill_cell(build: Path) -> None:
    ep = build / "cell" / "endpoints.json"
    if ep.is_file():
        pid = json.loads(ep.read_text())["pid"]
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass


def done_commands(build: Path) -> int:
    """Commands the journal shows done (read-only; -1 before the journal exists)."""
    f = build / bmod.JOURNAL
    if not f.exists():
        return -1
    try:
        db = sqlite3.connect(f"{f.as_uri()}?mode=ro", uri=True, timeout=5)
        try:
            return int(db.execute("SELECT COUNT(*) FROM commands WHERE done IS NOT NULL"
                                  ).fetchone()[0])
        finally:
            db.close()
    except sqlite3.OperationalError:
        return -1


def _paths_done(build: Path) -> int:
    db = sqlite3.connect(f"{(build / bmod.JOURNAL).as_uri()}?mode=ro", uri=True, timeout=5)
    try:
        return int(db.execute("SELECT COUNT(*) FROM commands WHERE kind='path' AND done IS "
                              "NOT NULL").fetchone()[0])
    finally:
        db.close()


def _wait_progress(build: Path, proc, timeout_s: float = 300.0) -> int | None:
    """Wait until the journal shows one more command done than when called; None when
    the process ended first."""
    start = done_commands(build)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            return None
        n = done_commands(build)
        if n > start:
            return n
        time.sleep(0.05)
    raise AssertionError(f"{build}: no progress within {timeout_s:g} s")


@pytest.mark.parametrize("when", ["at once", "in the paths stage"])
def test_stop_reaches_a_build_that_is_still_planning(tmp_path, when):
    # 'icefab build --stop B' while B was planning said "no build journal here" and the
    # build went on to deposit (a tester's, 12 s after the start); stopped while a process
    # pool planned, it first ran the rest of the stage (over 60 s in a CI rehearsal)
    log = tmp_path / "build.log"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", "demo", "-o", "b",
                                 "--virtual"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                                stderr=err, text=True)
    marker = tmp_path / ".b.icefab-build"
    try:
        deadline = time.monotonic() + 120
        while not (marker.exists() and (when == "at once" or "paths: " in log.read_text())):
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        assert int(marker.read_text()) == proc.pid
        if when != "at once":   # --status said "no build journal here" (hunt X)
            r = _icefab("build", "--status", "b", cwd=tmp_path)
            assert r.returncode == 0 and f"being prepared (process {proc.pid})" in r.stdout
            # the keys of every other state (hunt Z: a program's d["paths_done"] failed)
            r = _icefab("build", "--status", "b", "--json", cwd=tmp_path)
            st = json.loads(r.stdout)
            assert tuple(st) == bmod.STATUS_KEYS and st["state"] == "preparing"
            assert st["pid"] == proc.pid and st["paths_done"] is None
        t0 = time.monotonic()
        r = _icefab("build", "--stop", "b", cwd=tmp_path)
        assert r.returncode == 0, r.stderr + log.read_text()   # where the build was
        assert "stopped while it was being prepared" in r.stdout
        assert proc.wait(timeout=60) == 143 and "terminated" in log.read_text(), \
            log.read_text()
        assert time.monotonic() - t0 < 30.0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["build.log"]  # no folder, marker
    # a marker left by a killed build (its process gone) is not a build
    marker.write_text("999999999\n")
    r = _icefab("build", "--stop", "b", cwd=tmp_path)
    assert r.returncode == 2 and "no build journal here" in r.stderr
    assert not marker.exists()


def test_stop_reaches_a_build_into_a_folder_whose_parent_is_missing(tmp_path):
    """``-o new/sub/b`` with ``new`` missing: the build had nowhere to put its marker, and
    a --stop during its planning was lost: the build ran to its end (hunt X). The
    parent is made with the marker, and goes again with a stopped build."""
    log = tmp_path / "build.log"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", "demo", "-o",
                                 "new/sub/b", "--virtual"], cwd=tmp_path,
                                stdout=subprocess.DEVNULL, stderr=err, text=True)
    marker = tmp_path / "new" / "sub" / ".b.icefab-build"
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        r = _icefab("build", "--stop", "new/sub/b", cwd=tmp_path)
        assert r.returncode == 0 and "stopped while it was being prepared" in r.stdout, \
            r.stderr
        assert proc.wait(timeout=60) == 143, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["build.log"]


def test_a_stop_sent_as_a_resume_starts_is_not_lost(firmware_tools, planned, tmp_path):
    """--stop while --resume started read the stopped run's status, said no build was
    running, told the cell to stop, and the resume deleted the request and built to its
    end (hunt X: lost in 2 of 4 tries). The resume's marker comes first: the stop ends it,
    and the next resume still runs every path exactly once."""
    # 10 times real time: 24 s of paths, so that the resume has most of them left when the
    # stop comes (at 20 a CI run's resume completed before its stop: the first stop, a
    # second process under load, had let the first run deposit most of the build)
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o", "b",
                             "--virtual", "--cell-time-factor", "10"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_progress(tmp_path / "b", proc) is not None
        # the runner's own request (what --stop writes first; --stop itself is below)
        (tmp_path / "b" / bmod.STOP_REQUEST).write_text("stop\n")
        assert proc.wait(timeout=60) == 143
        j = Journal.open(tmp_path / "b" / bmod.JOURNAL)
        done = j.paths_done()
        j.close()
        proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", "--resume", "b"],
                                cwd=tmp_path, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)
        marker = tmp_path / ".b.icefab-build"
        deadline = time.monotonic() + 60
        while not marker.exists():
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.01)
        t0 = time.monotonic()
        r = _icefab("build", "--stop", "b", cwd=tmp_path)
        took = time.monotonic() - t0
        assert r.returncode == 0, r.stderr
        # a lost stop waits for the resume's end and reads "completed" too: the time says
        # which it was
        assert "no build was running" not in r.stdout and "stopped" in r.stdout, \
            (r.stdout, f"--stop took {took:.1f} s; the first run did {done} paths",
             [e["text"] for e in Journal.open(tmp_path / "b" / bmod.JOURNAL).events()][-6:])
        assert proc.wait(timeout=60) == 143, proc.stderr.read()
        r = _icefab("build", "--resume", "b", cwd=tmp_path)
        assert r.returncode == 0 and "build complete" in r.stdout, r.stderr
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_cell(tmp_path / "b")
    ex = _executed(tmp_path / "b")
    assert Counter(ex).most_common(1)[0][1] == 1
    j = Journal.open(tmp_path / "b" / bmod.JOURNAL)
    assert ex == [c["seq"] for c in j.commands() if c["kind"] != "layer_end"]
    j.close()
    # a stop to the complete build has nothing to stop (it wrote a request into the
    # finished folder and journaled "no build was running"); a virtual cell still up
    # (the build killed as it ended) is ended
    r = _icefab("build", "--stop", "b", cwd=tmp_path)
    assert r.returncode == 0 and "the build is complete: nothing to stop" in r.stdout
    assert not (tmp_path / "b" / bmod.STOP_REQUEST).exists()
    from icefab.linkedcell import cell_alive, start_virtual_cell

    cdir = tmp_path / "b" / bmod.CELL_DIR
    try:
        start_virtual_cell(cdir, tmp_path / "b" / "job.toml",
                           tmp_path / "b" / bmod.TRAJECTORIES)
        r = _icefab("build", "--stop", "b", cwd=tmp_path)
        assert r.returncode == 0 and "its virtual cell was still running" in r.stdout
        assert not cell_alive(cdir)
    finally:
        _kill_cell(tmp_path / "b")


def test_a_second_build_command_leaves_the_running_builds_marker(firmware_tools, planned,
                                                                    tmp_path):
    """A second 'icefab build -o B' or '--resume B' while B built wrote its own id into
    B's marker, was refused, and removed the marker as it left: --stop then said no build
    was running and told the cell to stop with the tool down (hunt Y). Both are refused
    at once now, and the marker stays the running build's."""
    # 5 times real time (48 s of paths): three commands of a loaded machine, each a new
    # Python process, come before the build ends
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o", "b",
                             "--virtual", "--cell-time-factor", "5"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    marker = tmp_path / ".b.icefab-build"
    try:
        assert _wait_progress(tmp_path / "b", proc) is not None
        for argv in ((str(planned), "-o", "b", "--virtual"), ("--resume", "b")):
            r = _icefab("build", *argv, cwd=tmp_path)
            assert r.returncode == 2, r.stderr
            assert f"a build is running for this folder already (process {proc.pid}" \
                in r.stderr
            assert int(marker.read_text()) == proc.pid
        r = _icefab("build", "--stop", "b", cwd=tmp_path)
        assert r.returncode == 0 and "stopped (" in r.stdout, r.stdout + r.stderr
        assert proc.wait(timeout=60) == 143
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_cell(tmp_path / "b")


def test_a_stop_as_the_journal_is_made_leaves_nothing(firmware_tools, planned, tmp_path,
                                                     monkeypatch, capsys):
    """SIGTERM just after the new journal was renamed into place, before the build left
    its preparation: the clean-up took everything but the journal, which then refused
    every command (--resume: no job.toml; a new build: "holds a build journal", hunt Y).
    The journal goes with the rest."""
    from icefab.cli import main
    from icefab.cli.common import Terminated

    real = Journal.create

    def create_then_stopped(path, meta):
        real(path, meta).close()
        raise Terminated()

    monkeypatch.setattr(Journal, "create", staticmethod(create_then_stopped))
    monkeypatch.chdir(tmp_path)
    assert main(["build", str(planned), "-o", "b", "--virtual"]) == 143
    assert "terminated" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_a_journal_is_whole_or_absent(tmp_path, monkeypatch):
    """A build killed while its journal was created left a file with no tables, which
    every later command called damaged (hunt X): the journal is made under another name
    and renamed into place."""
    import icefab.journal as jmod

    def interrupted(src, dst):
        raise KeyboardInterrupt

    monkeypatch.setattr(jmod, "replace_durably", interrupted)
    with pytest.raises(KeyboardInterrupt):
        Journal.create(tmp_path / bmod.JOURNAL, {"layers": 1})
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    # what a build killed (-9) as it made its journal leaves goes with the next one
    (tmp_path / f".{bmod.JOURNAL}.999999.new").write_bytes(b"x")
    (tmp_path / f".{bmod.JOURNAL}.999999.new-journal").write_bytes(b"x")
    j = Journal.create(tmp_path / bmod.JOURNAL, {"layers": 1})
    assert j.meta()["layers"] == 1
    j.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == [bmod.JOURNAL]


def test_a_resume_refused_for_a_lost_record_leaves_no_cell_behind(firmware_tools, planned,
                                                                   tmp_path):
    # the refusal left the new virtual cell running on a new, empty BUILD/cell, in the way
    # of moving the old cell back (a tester's)
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o", "b",
                             "--virtual", "--cell-time-factor", "20"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 300
        while done_commands(tmp_path / "b") < 10 and time.monotonic() < deadline:
            assert proc.poll() is None, proc.stderr.read().decode()
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_cell(tmp_path / "b")
    time.sleep(0.5)
    shutil.move(tmp_path / "b" / "cell", tmp_path / "old-cell")
    r = _icefab("build", "--resume", "b", cwd=tmp_path)
    assert r.returncode == 2 and "the cell lost its record" in r.stderr, r.stderr
    assert not (tmp_path / "b" / "cell").exists()
    shutil.move(tmp_path / "old-cell", tmp_path / "b" / "cell")
    r = _icefab("build", "--resume", "b", cwd=tmp_path)
    _kill_cell(tmp_path / "b")
    assert r.returncode == 0, r.stderr
    assert Counter(_executed(tmp_path / "b")).most_common(1)[0][1] == 1


def test_stop_ends_the_cell_of_a_build_killed_while_starting(firmware_tools, planned,
                                                              tmp_path):
    # killed (-9) after it started its virtual cell, before its journal existed: --stop
    # said "no build journal here" and the cell with its firmware ran on (hunt I)
    from icefab.linkedcell import cell_alive, start_virtual_cell

    build = tmp_path / "b"
    build.mkdir()
    (build / "job.toml").write_text(to_toml(Job()), encoding="utf-8")
    shutil.copy(planned, build / bmod.TRAJECTORIES)
    try:
        start_virtual_cell(build / bmod.CELL_DIR, build / "job.toml",
                           build / bmod.TRAJECTORIES)
        assert cell_alive(build / bmod.CELL_DIR)
        r = _icefab("build", "--stop", "b", cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        assert "left its virtual cell running: stopped it" in r.stdout
        assert not cell_alive(build / bmod.CELL_DIR)
        # and a new build with the same -o starts afresh
        assert _icefab("build", "--stop", "b", cwd=tmp_path).returncode == 2
    finally:
        _kill_cell(build)


def test_sigkill_the_build_and_resume(firmware_tools, planned, tmp_path):
    r = _icefab("build", str(planned), "-o", "ref", "--virtual", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "build complete" in r.stdout
    rng = np.random.default_rng(11)
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o", "k",
                             "--virtual"], cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    kills = 0
    try:
        while kills < 4 and proc.poll() is None:
            # a random moment after the (resumed) build made progress, so every run
            # gets somewhere however slowly this machine starts a Python process
            done = _wait_progress(tmp_path / "k", proc)
            if done is None:
                break
            time.sleep(float(rng.uniform(0.0, 1.5)))
            if proc.poll() is not None:
                break
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            kills += 1
            if kills == 1:
                # the status of a killed build counts from the journal (status.json, written
                # at most once a second, said 38 paths where 66 were done: a tester's)
                st = _icefab("build", "--status", "k", "--json", cwd=tmp_path)
                if st.returncode == 0:    # no status before the first layer's start
                    st = json.loads(st.stdout)
                    assert st["state"] == "interrupted"   # a token (hunt Z)
                    assert st["paths_done"] == _paths_done(tmp_path / "k")
            proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", "--resume", "k"],
                                    cwd=tmp_path, stdout=subprocess.DEVNULL,
                                    stderr=subprocess.PIPE)
        proc.wait(timeout=600)
        assert proc.returncode == 0, proc.stderr.read().decode()
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_cell(tmp_path / "k")
        _kill_cell(tmp_path / "ref")
    assert kills >= 1
    a = np.load(tmp_path / "ref" / "cell" / "surface.npz")
    b = np.load(tmp_path / "k" / "cell" / "surface.npz")
    assert np.array_equal(a["z"], b["z"], equal_nan=True)
    ex = _executed(tmp_path / "k")
    assert Counter(ex).most_common(1)[0][1] == 1
    assert ex == _executed(tmp_path / "ref")
    st = _icefab("build", "--status", "k", "--json", cwd=tmp_path)
    assert json.loads(st.stdout)["state"] == "complete"


def _one_demo_layer(cwd: Path, job_text: str, out: str):
    """``icefab build demo`` of one layer with the job ``job_text`` on a fast virtual cell,
    which is then stopped; the finished run (exit 0 asserted)."""
    (cwd / f"{out}.toml").write_text(job_text)
    r = _icefab("build", "demo", "-c", f"{out}.toml", "-o", out, "--virtual", "--layers", "1",
                "--cell-time-factor", "50", cwd=cwd)
    _kill_cell(cwd / out)
    assert r.returncode == 0, r.stderr
    return r


def test_what_the_valve_cannot_give_is_refused_before_anything_moves(firmware_tools,
                                                                     planned, tmp_path):
    # a tester's: the build stopped at a layer whose nominal flow is beyond the valve after
    # depositing the layers before it, status.json said "running", and every resume
    # stopped there again
    (tmp_path / "thick.toml").write_text("[slicing]\nlayer_thickness_mm = 1.0\n")
    r = _icefab("build", "demo", "-c", "thick.toml", "-o", "b", "--virtual", "--layers", "2",
                cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    err = r.stderr.strip().splitlines()[-1]
    assert "layer 0 part fill path: its nominal flow" in err and "out_of_range" in err
    assert not (tmp_path / "b").exists()
    # clamped instead: journaled, said at the end and in the status (it was unsaid)
    r = _one_demo_layer(tmp_path, "[slicing]\nlayer_thickness_mm = 1.0\n"
                                  "[flow]\nout_of_range = \"clamp\"\n", "c")
    assert "warning: layer 0: the flow of" in r.stderr and "was clamped" in r.stderr
    j = Journal.open(tmp_path / "c" / bmod.JOURNAL)
    assert "clamp" in [e["kind"] for e in j.events()]
    j.close()
    # trajectories keep the motion they were planned with: a -c job's other speed was
    # recorded in the build's job.toml and had no effect
    (tmp_path / "slow.toml").write_text("[motion]\nspeed_mm_s = 30.0\n")
    r = _icefab("build", str(planned), "-c", "slow.toml", "-o", "d", "--virtual",
                cwd=tmp_path)
    assert r.returncode == 2 and "were made with motion.speed_mm_s = 125.0, the job has " \
        "30.0" in r.stderr, r.stderr
    assert not (tmp_path / "d").exists()


def test_a_changed_calibration_table_is_named_on_resume(firmware_tools, tmp_path):
    # a table changed between a crash and the resume was refused as "the build's plan is
    # not deterministic, or another icefab version started the build"
    r = _icefab("calibrate", "synthetic", "-o", "syn", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    r = _icefab("calibrate", "valve", "syn/masses_part.csv", "-o", "cal", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _one_demo_layer(tmp_path, '[materials.part]\ncalibration_file = '
                              '"cal/calibration_part.csv"\n', "b")
    table = tmp_path / "cal" / "calibration_part.csv"
    table.write_text(table.read_text() + "\n")
    r = _icefab("build", "--resume", "b", cwd=tmp_path)
    _kill_cell(tmp_path / "b")
    assert r.returncode == 2 and "the calibration tables (materials.*.calibration_file) " \
        "changed since the build started" in r.stderr, r.stderr


def test_refusals(firmware_tools, planned, tmp_path):
    r = _icefab("build", str(planned), "-o", "b", "--virtual", "--layers", "1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _kill_cell(tmp_path / "b")
    # the feedback's headroom, said and journaled once the build starts: the default fill
    # at 125 mm/s leaves the part valve no room for SMF's 30 % (icefab.headroom), and the
    # valve saturates the correction there
    assert "warning: feedback headroom" in r.stderr
    assert "the valve saturates SMF's correction at +" in r.stderr
    j = Journal.open(tmp_path / "b" / bmod.JOURNAL)
    assert [e["kind"] for e in j.events()][:2] == ["start", "headroom"]
    j.close()
    # a second start in the same folder
    r = _icefab("build", str(planned), "-o", "b", "--virtual", cwd=tmp_path)
    assert r.returncode == 2 and "--resume" in r.stderr
    # the job changed since the journal
    (tmp_path / "other.toml").write_text("[feedback]\nkp = 0.5\n")
    r = _icefab("build", "--resume", "b", "-c", "other.toml", cwd=tmp_path)
    assert r.returncode == 2 and "job changed since the build started" in r.stderr
    assert r.stderr.count("\n") == 1
    with open(tmp_path / "b" / "job.toml", "a") as f:
        f.write("\n# edited\n")
    r = _icefab("build", "--resume", "b", cwd=tmp_path)
    assert r.returncode == 2 and "job changed" in r.stderr
    r = _icefab("build", "--resume", "b", "--layers", "3", cwd=tmp_path)
    assert r.returncode == 2 and "a resumed build keeps its layers" in r.stderr
    # not an endpoints file
    (tmp_path / "old.json").write_text(json.dumps({"host": "127.0.0.1", "port": 9}))
    r = _icefab("build", str(planned), "-o", "c", "--cell", "old.json", cwd=tmp_path)
    assert r.returncode == 2 and "old.json: not a cell's endpoints file" in r.stderr
    assert not (tmp_path / "c").exists()   # no folder of a build that never started
    # a cell that does not answer its handshake: nothing journaled
    (tmp_path / "ep.json").write_text(json.dumps({
        "robot": {"host": "127.0.0.1", "port": 9}, "valve": {"device": "/dev/null"},
        "laser": {"device": "/dev/null"}}))
    r = _icefab("build", str(planned), "-o", "c", "--cell", "ep.json", cwd=tmp_path)
    assert r.returncode == 2 and "robot at 127.0.0.1:9: cannot connect" in r.stderr
    assert r.stderr.count("\n") == 1
    assert not (tmp_path / "c").exists()
    # into a folder the user made: it stays, empty
    (tmp_path / "mine").mkdir()
    r = _icefab("build", str(planned), "-o", "mine", "--cell", "ep.json", cwd=tmp_path)
    assert r.returncode == 2 and list((tmp_path / "mine").iterdir()) == []


def test_a_new_build_takes_the_parts_its_job_names(tmp_path, capsys):
    # a legacy control file (or a TOML job) names its parts: 'icefab slice' took them,
    # 'icefab build' asked for an INPUT; now it plans them, up to the cell it is given
    import trimesh

    from icefab.cli import main

    trimesh.creation.box(extents=(20.0, 15.0, 1.0)).export(tmp_path / "box.stl")
    (tmp_path / "control.txt").write_text(
        "1	[int] Number of STL and/or PLY files to import\n"
        "box.stl	[char] STL and/or PLY file names\n")
    (tmp_path / "old.json").write_text(json.dumps({"host": "127.0.0.1", "port": 9}))
    assert main(["build", "-c", str(tmp_path / "control.txt"), "-o", str(tmp_path / "b"),
                 "--cell", str(tmp_path / "old.json"), "--layers", "1"]) == 2
    err = capsys.readouterr().err
    assert "old.json: not a cell's endpoints file" in err and "INPUT" not in err
    assert not (tmp_path / "b").exists()
    assert main(["build", "-o", str(tmp_path / "b"), "--virtual"]) == 2
    assert "no input: give mesh file(s), 'demo' or a result .npz" in capsys.readouterr().err
    # adaptive layers: refused from the job, before slicing (it came after planning)
    (tmp_path / "adapt.toml").write_text("[slicing]\ncusp_height_mm = 0.1\n")
    assert main(["build", str(tmp_path / "box.stl"), "-c", str(tmp_path / "adapt.toml"), "-o",
                 str(tmp_path / "b"), "--virtual"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("icefab build: error: slicing.cusp_height_mm = 0.1: adaptive layers")
    assert len(err.splitlines()) == 1   # no slicing progress before it
    assert not (tmp_path / "b").exists()
    # a gantry: the runner drives the Cobra's C40 link, and a gantry job went down it as
    # if its carriage positions were the SCARA's (a gantry hunt's); refused from the job
    # before slicing, and from a result file's job before planning
    (tmp_path / "gantry.toml").write_text('[cell]\nrobot = "gantry"\n')
    said = "icefab build: error: cell.robot = 'gantry': the build runner drives the Cobra 600"
    assert main(["build", str(tmp_path / "box.stl"), "-c", str(tmp_path / "gantry.toml"),
                 "-o", str(tmp_path / "b"), "--virtual"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(said) and "'icefab plan --gcode'" in err and \
        len(err.splitlines()) == 1
    assert main(["slice", str(tmp_path / "box.stl"), "-c", str(tmp_path / "gantry.toml"),
                 "-o", str(tmp_path / "s")]) == 0
    assert main(["paths", str(tmp_path / "s" / "stack.npz"), "-o", str(tmp_path / "p")]) == 0
    capsys.readouterr()
    assert main(["build", str(tmp_path / "p" / "toolpaths.npz"), "-o", str(tmp_path / "b"),
                 "--virtual"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(said) and "planning" not in err, err
    assert not (tmp_path / "b").exists()


def test_a_resumed_gantry_build_is_refused_before_its_cell_is_asked(tmp_path, capsys):
    """A gantry build started before 'icefab build' refused one (check_build_robot) has a
    journal: its resume went on driving the Cobra's C40 link with the gantry's carriage
    positions. The resume is refused from the build's job, before its cell is asked."""
    from icefab.cli import main

    b = tmp_path / "b"
    b.mkdir()
    (b / "job.toml").write_text(to_toml(Job().replace(**{"cell.robot": "gantry"})))
    (b / bmod.TRAJECTORIES).write_bytes(b"not read")
    Journal.create(b / bmod.JOURNAL, {"cell": "virtual", "digests": {}}).close()
    assert main(["build", "--resume", str(b)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("icefab build: error: cell.robot = 'gantry': the build runner "
                          "drives the Cobra 600") and len(err.splitlines()) == 1, err


def test_a_build_started_here_while_this_one_planned_is_left_alone(planned, tmp_path,
                                                                    capsys, monkeypatch):
    """Two builds into one folder: the second finished its planning after the first had
    started (and completed), deleted the first one's cell, wrote over its job and
    trajectories and only then failed at the journal (a hunt's: the first build could not
    be resumed, a cell ran on). It now looks again once it holds the folder's lock."""
    from icefab.cli import build_cmd, main

    b = tmp_path / "b"
    real = build_cmd._plan

    def plan_while_another_starts(args, out):
        got = real(args, out)
        (b / "cell").mkdir(parents=True)
        (b / "cell" / "surface.npz").write_bytes(b"the first build's")
        (b / "job.toml").write_text("# the first build's\n")
        Journal.create(b / bmod.JOURNAL, {"digests": {}}).close()
        return got

    monkeypatch.setattr(build_cmd, "_plan", plan_while_another_starts)
    assert main(["build", str(planned), "-o", str(b), "--virtual"]) == 2
    err = capsys.readouterr().err
    assert "another build started in this folder while this one was planning" in err
    assert (b / "cell" / "surface.npz").read_bytes() == b"the first build's"
    assert (b / "job.toml").read_text() == "# the first build's\n"
    assert not (b / bmod.TRAJECTORIES).exists()


def test_an_endpoints_file_that_is_no_file_is_refused_before_planning(tmp_path, capsys):
    # a tester's --cell /dev/zero ran out of memory, a FIFO hung with a build folder made
    import os

    from icefab.cli import main

    os.mkfifo(tmp_path / "cell.json")
    for cell, kind in ((tmp_path / "cell.json", "a FIFO"), ("/dev/zero", "a character device")):
        assert main(["build", "demo", "-o", str(tmp_path / "b"), "--cell", str(cell)]) == 2
        err = capsys.readouterr().err
        assert f"the cell endpoints file is {kind}" in err and "slicing" not in err, err
        assert not (tmp_path / "b").exists()


@pytest.mark.parametrize("argv", [["demo", "-o", "b", "--virtual"], ["--stop", "b"],
                                  ["--resume", "b"]])
def test_json_without_status_is_refused_before_anything_starts(tmp_path, capsys, monkeypatch,
                                                               argv):
    # a docs hunt's: --json without --status was ignored, as --cell-lost-record without
    # --resume is not
    from icefab.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["build", *argv, "--json"]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err == "icefab build: error: --json goes with --status BUILD\n"
    assert not (tmp_path / "b").exists()


def test_cell_killed_mid_path_build_completes(firmware_tools, planned, tmp_path):
    r = _icefab("build", str(planned), "-o", "ref", "--virtual", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o",
                             "f", "--virtual", "--cell-time-factor", "50"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    rng = np.random.default_rng(5)
    try:
        for _ in range(3):
            if _wait_progress(tmp_path / "f", proc) is None:
                break
            time.sleep(float(rng.uniform(0.0, 1.0)))
            if proc.poll() is not None:
                break
            _kill_cell(tmp_path / "f")
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_cell(tmp_path / "f")
        _kill_cell(tmp_path / "ref")
    assert proc.returncode == 0, err
    j = Journal.open(tmp_path / "f" / bmod.JOURNAL)
    faults = [e for e in j.events() if e["kind"] in ("cell-link", "cell-fault")]
    assert faults
    # every layer in which a fault cut a path short is measured at its end (its own
    # measurement paths, or the nearest layer's: a "fault-measure"), before the next layer,
    # unless the fault cut the layer's last path after the next layer's first had been
    # sent ahead: that one runs first, and the runner says the layer is not measured (a
    # CI rehearsal's kill hit that instant on layer 0)
    measured = {m["layer"] for m in j.measurements()}
    cut = {c["layer"] for c in j.commands() if c["cut"]}
    fault_measures = {e["layer"] for e in j.events() if e["kind"] == "fault-measure"}
    unmeasured = {e["layer"] for e in j.events() if e["kind"] == "fault-measure"
                  and "not measured after the cell fault" in e["text"]}
    assert cut - unmeasured <= measured, (cut, measured, unmeasured)
    assert fault_measures <= cut
    ref = Journal.open(tmp_path / "ref" / bmod.JOURNAL).measurements()[-1]["rms_measured"]
    got = j.measurements()[-1]["rms_measured"]
    assert got <= 2 * ref
    assert Counter(_executed(tmp_path / "f")).most_common(1)[0][1] == 1


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def test_a_valve_controller_killed_mid_play_cuts_its_path(firmware_tools, planned,
                                                          tmp_path):
    # a tester killed the virtual cell's valvectl while it played: the path (9 of its 617
    # pulses) was journaled done and never run again, the cell kept the dead firmware's pty
    # and every resume failed on it. Now the path is cut, the cell stops, and the build
    # starts it again and completes, every path once
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o",
                             "f", "--virtual", "--cell-time-factor", "20"], cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = None
    try:
        assert _wait_progress(tmp_path / "f", proc) is not None
        log = tmp_path / "f" / "cell" / "valve-pulses.log"
        deadline = time.monotonic() + 120
        while killed is None and time.monotonic() < deadline and proc.poll() is None:
            lines = log.read_text().splitlines() if log.exists() else []
            last = [ln for ln in lines if not ln.startswith("pulse")][-1:]
            if last and last[0].startswith("start") and lines[-1].startswith("pulse"):
                cell_pid = json.loads((tmp_path / "f" / "cell" / "endpoints.json")
                                      .read_text())["pid"]
                (killed,) = _children(cell_pid)
                os.kill(killed, signal.SIGKILL)
            time.sleep(0.005)
        out, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
        _kill_cell(tmp_path / "f")
    assert killed is not None, "no play was seen under way"
    assert proc.returncode == 0, err
    j = Journal.open(tmp_path / "f" / bmod.JOURNAL)
    cut = [c for c in j.commands() if c["cut"]]
    assert len(cut) == 1 and cut[0]["kind"] == "path"
    texts = " ".join(e["text"] for e in j.events())
    assert "was cut short by a cell fault" in texts
    # and the build's last lines say so (they said "N paths", the cut one among them)
    assert "warning: " in err and "was cut short by a cell fault" in err
    assert Counter(_executed(tmp_path / "f")).most_common(1)[0][1] == 1
    assert cut[0]["seq"] not in _executed(tmp_path / "f")


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def test_report_of_a_running_build_in_chromium(firmware_tools, tmp_path):
    browser = _chromium()
    if browser is None:
        pytest.skip("headless Chromium is not installed (Debian package 'chromium'; "
                    ".ci/run installs it): the report's browser check cannot run here")
    # 9 layers: the report first appears after layer 4's measurement, with layers 5-8 to go
    planned = _plan_mug(2 * 4 + 1, tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o",
                             "b", "--virtual", "--cell-time-factor", "100"], cwd=tmp_path,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    cell_pid = None
    try:
        report = tmp_path / "b" / bmod.REPORT
        deadline = time.monotonic() + 300
        while not report.exists() and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.02)
        assert report.exists(), proc.stderr.read() if proc.poll() is not None else "timeout"
        # freeze the cell (a robot still moving): the build waits on it, still running,
        # however slowly Chromium starts on a loaded machine
        cell_pid = json.loads((tmp_path / "b" / "cell" / "endpoints.json").read_text())["pid"]
        os.kill(cell_pid, signal.SIGSTOP)
        assert proc.poll() is None          # the build is still running
        snap = tmp_path / "snapshot.html"
        shutil.copy(report, snap)
        assert 'http-equiv="refresh"' in snap.read_text()   # a running build's reloads
        r = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu",
                            "--disable-background-networking", "--no-first-run",
                            f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr",
                            "--v=0", "--dump-dom", snap.as_uri()],
                           capture_output=True, text=True, timeout=120)
    finally:
        if cell_pid is not None:
            os.kill(cell_pid, signal.SIGCONT)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=120)
        _kill_cell(tmp_path / "b")
    dom = r.stdout
    assert 'id="rms-plot"' in dom and "<path" in dom       # the RMS plot rendered as SVG
    assert 'id="status"' in dom and "running" in dom
    console = [ln for ln in r.stderr.splitlines() if "CONSOLE" in ln or "Uncaught" in ln]
    assert not console, console
    # Ctrl-C stopped it: journaled, resumable
    st = json.loads((tmp_path / "b" / bmod.STATUS).read_text())
    assert st["state"] == "stopped"


def test_planning_ahead_sends_the_programs_of_planning_in_turn(planned, tmp_path,
                                                               monkeypatch):
    """The next layer's valve programs, planned on a thread while a layer runs, are the
    ones planned in turn (same digests of every command, same surface); they are planned
    ahead for the layers without measurement before them, the motion plan for all."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    used = []
    real = bmod.Runner._layer_valves

    def spy(self, j, action):
        a = self._ahead
        if a is not None and a[0] == j:
            used.append((j, "programs" if a[1].result()[1] is not None else "motion plan"))
        return real(self, j, action)
    monkeypatch.setattr(bmod.Runner, "_layer_valves", spy)
    _inprocess(tmp_path / "ahead", motion, job)
    # layer 3 measures: layer 4's programs wait for its SMF update, its motion plan not
    assert used == [(1, "programs"), (2, "programs"), (3, "programs"), (4, "motion plan")]
    monkeypatch.setattr(bmod.Runner, "_prefetch",
                        lambda self, j, action, plan_only=False: None)
    _inprocess(tmp_path / "in-turn", motion, job)
    a = Journal.open(tmp_path / "ahead" / bmod.JOURNAL).commands()
    b = Journal.open(tmp_path / "in-turn" / bmod.JOURNAL).commands()
    assert [c["digest"] for c in a] == [c["digest"] for c in b]
    za = np.load(tmp_path / "ahead" / "cell" / "surface.npz")["z"]
    zb = np.load(tmp_path / "in-turn" / "cell" / "surface.npz")["z"]
    assert np.array_equal(za, zb, equal_nan=True)


def test_a_fault_on_a_layers_last_path_after_the_next_layer_was_sent(planned, tmp_path,
                                                                     plan_ahead_at_once):
    """The next layer's first path is numbered (and may be uploaded) while a layer's last
    path moves. If a cell fault cuts that last path, a measurement now would be numbered
    after a path that must run first: the runner skips it, says so, and every other
    command runs exactly once, in number order."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    last_item = bmod._items(motion.layers[1])[0][-1][0]

    class LastPathFault(FaultingCell):
        def run_path(self, seq, path, upcoming=None):
            if not self.cut and path.layer == 1 and path.item == last_item:
                assert upcoming is not None and upcoming[1].layer == 2   # sent ahead
                self.cut = seq
                raise CellError("link lost (cell fault)")
            return self.cell.run_path(seq, path, upcoming)

    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    faulty = LastPathFault(cell, layer=1)
    bmod.Runner(build, motion, job, journal, lambda: faulty).run()
    cmds = journal.commands()
    cut = [c for c in cmds if c["cut"]]
    assert len(cut) == 1 and cut[0]["layer"] == 1 and cut[0]["item"] == last_item
    assert not any(c["kind"] == "fault_measure" for c in cmds)
    assert any("not measured after the cell fault" in e["text"] for e in journal.events())
    ex = _executed(build)
    assert Counter(ex).most_common(1)[0][1] == 1 and faulty.cut not in ex
    assert ex == sorted(ex)                                       # in number order
    assert sorted(ex + [faulty.cut]) == [c["seq"] for c in cmds]  # nothing skipped
    journal.close()


def test_a_crash_during_a_fault_measurement_resumes_it(planned, tmp_path):
    """The PC dies after the first path of the measurement that follows a cell fault;
    the resumed build finishes that measurement (its own numbers after the layer's end
    do not count as a later layer's) and makes the SMF update at that layer."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    faulty = FaultingCell(cell, layer=1)

    class DiesInTheMeasurement:
        def __getattr__(self, name):
            return getattr(faulty, name)

        def run_path(self, seq, path, upcoming=None):
            out = faulty.run_path(seq, path, upcoming)
            if path.layer == 1 and path.role == "measure":
                raise Crash()
            return out

    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    with pytest.raises(Crash):
        bmod.Runner(build, motion, job, journal, DiesInTheMeasurement).run()
    journal.close()
    journal = Journal.open(build / bmod.JOURNAL)
    bmod.Runner(build, motion, job, journal, lambda: faulty).run()
    fm = [c for c in journal.commands() if c["kind"] == "fault_measure"]
    assert len(fm) > 1 and all(c["done"] is not None for c in fm)
    assert [m["layer"] for m in journal.measurements()][0] == 1
    assert not any("not measured" in e["text"] for e in journal.events())
    journal.close()


def test_a_refused_command_stops_the_build_at_once(planned, tmp_path):
    """A refusal that sending again cannot change (here: the controller's "out of reach",
    error 8) ends the build with its message and a journal event, after one attempt; a
    lost link is retried instead."""
    from icefab.errors import CellRefused
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    calls = {"connect": 0, "run": 0, "close": 0}

    class Refusing:
        def __getattr__(self, name):
            return getattr(cell, name)

        def close(self):
            calls["close"] += 1

        def run_path(self, seq, path, upcoming=None):
            calls["run"] += 1
            if calls["run"] == 3:
                raise CellRefused("robot: command 3 refused: error 8 (a point is out of "
                                  "the robot's reach)")
            return cell.run_path(seq, path, upcoming)

    def connect():
        calls["connect"] += 1
        return Refusing()
    with pytest.raises(CellRefused, match="error 8"):
        bmod.Runner(build, motion, job, journal, connect).run()
    assert calls == {"connect": 1, "run": 3, "close": 1}    # closed on the way out too
    assert [e["kind"] for e in journal.events()].count("cell-refused") == 1
    journal.close()


def test_progress_names_a_layer_by_its_index_and_its_place(planned, tmp_path):
    # "layer 9 of 12" beside "stopped at layer 8" (an index) read as two layers; and
    # between layers the status named the finished layer beside the next one's place
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    build = tmp_path / "b"
    cell = _prepared(build, motion, motion.job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    lines = []
    bmod.Runner(build, motion, motion.job, journal, lambda: cell,
                on_progress=lambda p: lines.append(bmod.progress_line(p))).run()
    journal.close()
    seen = {m.group(0) for m in map(re.compile(r"layer (\d+) \((\d+) of 5\)").match, lines)
            if m}
    got = [tuple(map(int, re.match(r"layer (\d+) \((\d+)", x).groups())) for x in seen]
    assert sorted(got) == [(k, k + 1) for k in range(LAYERS)]
    assert all(x.startswith("layer ") for x in lines)
    # a finished build's report stays put (a tester's kept reloading every 30 s)
    page = (build / bmod.REPORT).read_text()
    assert "complete" in page and 'http-equiv="refresh"' not in page


def test_a_build_killed_with_its_pc_is_not_running_whatever_has_its_id_now(planned,
                                                                            tmp_path):
    """After a restart of the PC, the id in a crashed build's status.json and marker was
    another program's: --status said "running" (any live process), --status and --stop
    took a program with "build" in its command line for the build, and --stop sent it
    SIGTERM. A build holds its marker and its folder's lock (flock) while it runs; the
    kernel lets go of both when it ends, however it ends; a forked child keeps neither."""
    from icefab.cli import build_cmd
    from icefab.cli.build_cmd import (_build_pid, _build_process, _folder_locked, _lock,
                                      _process_marker, _status)
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    build = tmp_path / "b"
    cell = _prepared(build, motion, motion.job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    bmod.Runner(build, motion, motion.job, journal, lambda: cell).run()
    journal.close()
    # a program of the restarted PC, with the crashed build's id and "build" in its argv
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)", "build"])
    try:
        st = json.loads((build / bmod.STATUS).read_text())
        (build / bmod.STATUS).write_text(json.dumps(dict(st, state="running", pid=other.pid)))
        _process_marker(build).write_text(f"{other.pid}\n")
        assert _build_pid(build) is None and not _process_marker(build).exists()
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert _status(build, as_json=True) == 0
        got = json.loads(out.getvalue())
        assert got["state"] == "interrupted" and got["update_by"] is None
        assert other.poll() is None
    finally:
        other.kill()
        other.wait()
    # a marker being claimed in place (locked, its id not written yet) is no stale one:
    # a look then removed a live build's marker (a hunt's)
    claim = os.open(_process_marker(build), os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(claim, fcntl.LOCK_EX)
        assert _build_pid(build) is None and _process_marker(build).exists()
    finally:
        os.close(claim)
    assert _build_pid(build) is None and not _process_marker(build).exists()
    # a build whose process lives (its lock held) but wrote no status when it was due
    lock = _lock(build)
    try:
        st = json.loads((build / bmod.STATUS).read_text())
        (build / bmod.STATUS).write_text(json.dumps(dict(
            st, state="running", pid=os.getpid(), time=time.time() - 600,
            update_by=time.time() - 60)))
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert _status(build, as_json=False) == 0
        assert "running;" in out.getvalue() and "runs but does not report" in out.getvalue()
    finally:
        build_cmd._unlock(lock)
    # while a build runs: both held; when it ends (the kernel closes its files), a worker
    # it forked holds neither
    with _build_process(build, new=False):
        lock = _lock(build)
        assert _build_pid(build) == os.getpid() and _folder_locked(build) is True
        r, w = os.pipe()
        child = os.fork()
        if child == 0:    # a planning pool's worker, say: it runs on
            os.write(w, b"x")
            time.sleep(5)
            os._exit(0)
        try:
            assert os.read(r, 1) == b"x"
            build_cmd._unlock(lock)
            os.close(build_cmd._MARKER_FD)
            build_cmd._MARKER_FD = None
            assert _build_pid(build) is None and _folder_locked(build) is False
        finally:
            os.kill(child, signal.SIGKILL)
            os.waitpid(child, 0)
            os.close(r)
            os.close(w)
    assert not _process_marker(build).exists()
    # a file system without hard links: the marker written in place is locked too (it was
    # not, and the first look called it stale and removed it)
    real_link = os.link

    def no_links(*a, **k):
        raise PermissionError(1, "Operation not permitted")

    os.link = no_links
    second = ("import os, sys\nfrom pathlib import Path\nfrom icefab.cli import build_cmd as bc\n"
              "def no(*a, **k):\n    raise PermissionError(1, 'Operation not permitted')\n"
              "os.link = no\ntry:\n    with bc._build_process(Path(sys.argv[1]), new=False):\n"
              "        print('claimed')\nexcept Exception as exc:\n    print(exc)\n")
    try:
        with _build_process(build, new=False):
            assert _build_pid(build) == os.getpid() and _build_pid(build) == os.getpid()
            # a second build of the folder is refused and leaves the marker as it was (it
            # wrote its own id, took the lock's refusal for a file system without locks,
            # and removed the marker as it left: a hunt's)
            r = subprocess.run([sys.executable, "-c", second, str(build)],
                               capture_output=True, text=True)
            assert f"a build is running for this folder already (process {os.getpid()}" \
                in r.stdout, r.stdout + r.stderr
            assert _build_pid(build) == os.getpid()
    finally:
        os.link = real_link
    assert not _process_marker(build).exists()


def test_a_resumed_build_names_the_layer_it_goes_on_with_before_its_first_path(planned,
                                                                             tmp_path):
    """A build's PC dies in layer 2 (its third); resumed, the status written before the
    first path names layer 2, third of five, with the time left of it and the layers after
    (a hunt's kill at that moment left "layer 0 (3 of 3), ETA 0:00:00"). And a status that
    still names a layer the journal says is done (written up to a second before a kill)
    is read as the next one by 'icefab build --status'."""
    from icefab.cli.build_cmd import _status
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = CrashInLayer(_prepared(build, motion, job), layer=2)
    journal = Journal.create(build / bmod.JOURNAL, {
        "digests": {}, "layer_indices": [int(lm.index) for lm in motion.layers],
        "measured_layers": [int(lm.index) for lm in motion.layers if bmod.measures(lm)]})
    with pytest.raises(Crash):
        bmod.Runner(build, motion, job, journal, lambda: cell).run()
    first = motion.layers[2].trajectories[bmod._items(motion.layers[2])[0][0][0]]
    left = sum(lm.duration for lm in motion.layers[2:]) - first.duration
    # stopped before the resume's first path: the layer's loop set the whole layer's ETA
    # again (a hunt's: 0:03:04 before the resume, 0:03:22 after the stop)
    with pytest.raises(bmod.BuildStopped):
        bmod.Runner(build, motion, job, journal, lambda: cell.cell,
                    should_stop=lambda: True).run()
    assert json.loads((build / bmod.STATUS).read_text())["eta_s"] == pytest.approx(left)
    seen = []

    class Watching:
        def __getattr__(self, name):
            return getattr(cell.cell, name)

        def run_path(self, seq, path, upcoming=None):
            if not seen:
                seen.append(json.loads((build / bmod.STATUS).read_text()))
            return cell.cell.run_path(seq, path, upcoming)

    bmod.Runner(build, motion, job, journal, lambda: Watching()).run()
    journal.close()
    st = seen[0]
    assert (st["layer"], st["layers_done"], st["layers"]) == (2, 2, LAYERS)
    # less layer 2's first path, which ran before the crash (the ETA counted the whole
    # layer, hunt X)
    assert st["eta_s"] == pytest.approx(left)
    # a status of a killed build that names the layer it had just finished
    stale = dict(st, state="running", pid=2 ** 22 + 1, layer=1, layers_done=1)

    def status_after(edits: list[str], layer: int) -> dict:
        """'icefab build --status --json' after the journal ``edits`` (SQL) with a
        status.json of the killed build naming ``layer``."""
        j = Journal.open(build / bmod.JOURNAL)
        try:
            with j._tx() as db:
                for sql in edits:
                    db.execute(sql)
        finally:
            j.close()
        (build / bmod.STATUS).write_text(json.dumps(dict(stale, layer=layer)))
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert _status(build, as_json=True) == 0
        return json.loads(out.getvalue())

    # layers 2-4 not done: the build was killed after layer 1
    got = status_after(["UPDATE commands SET done=NULL WHERE layer >= 2"], 1)
    assert got["state"].startswith("interrupted")
    assert (got["layer"], got["layers_done"]) == (2, 2)
    # killed in layer 3's measurement (its end journaled, its measurement not): the build
    # goes on with layer 3, and so does the status (it named layer 4, a hunt's)
    j = Journal.open(build / bmod.JOURNAL)
    assert 3 in j.meta()["measured_layers"]
    j.close()
    got = status_after(["UPDATE commands SET done=1 WHERE layer <= 3 AND kind='layer_end'",
                        "DELETE FROM measurements WHERE layer = 3"], 3)
    assert (got["layer"], got["layers_done"]) == (3, 3)
    # a layer a fault cut a path of short is done once its fault measurement is in, for
    # the status as for the runner (bmod.layer_finished, one rule)
    got = status_after(["UPDATE commands SET cut=1 WHERE seq = (SELECT MIN(seq) FROM "
                        "commands WHERE layer = 2 AND kind = 'path')"], 2)
    assert (got["layer"], got["layers_done"]) == (2, 2)


def test_a_measurement_and_the_smf_state_it_led_to_are_one_transaction(tmp_path):
    """Written apart, a build killed between them resumed with the layer measured and its
    SMF update lost for good (a hunt's: final RMS 0.108 mm against 0.043 mm). One fails,
    neither is kept."""
    j = Journal.create(tmp_path / "j.sqlite", {"digests": {}})
    try:
        j.measurement(1, 3, 1.0, np.zeros((2, 3)), 0.05, smf_state=b"state 1")
        assert [m["layer"] for m in j.measurements()] == [3]
        assert j.last_smf() == (1, 3, b"state 1")
        j._db.execute("DROP TABLE smf")    # the second insert fails
        with pytest.raises(JournalError, match="j.sqlite: the journal cannot be written"):
            j.measurement(2, 7, 2.0, np.zeros((2, 3)), 0.04, smf_state=b"state 2")
        assert [m["layer"] for m in j.measurements()] == [3]
    finally:
        j.close()


def test_a_journal_that_cannot_be_written_is_named_in_one_line(tmp_path):
    """A full disk under the journal ended the build, and every resume, with sqlite3's
    traceback (a hunt's); any write the journal cannot make is one JournalError naming it
    (here a read-only connection: root writes through file modes)."""
    j = Journal.create(tmp_path / "j.sqlite", {"digests": {}})
    try:
        j._db.execute("PRAGMA query_only = 1")
        with pytest.raises(JournalError, match=r"j\.sqlite: the journal cannot be written "
                                               r"\(attempt to write a readonly database\)"):
            j.event("start", "a build")
        j._db.execute("PRAGMA query_only = 0")
        j.event("start", "a build")       # nothing was left half-done
        assert [e["text"] for e in j.events()] == ["a build"]
    finally:
        j.close()


def test_a_completed_build_ends_with_what_the_cell_did_not_do(tmp_path):
    """A laser that read nothing (the build ran open loop there and said 'build complete'
    with nothing else, a hunt's) and a path a cell fault cut short are warned of at the
    end."""
    from icefab.cli.build_cmd import _completion_notes

    j = Journal.create(tmp_path / "j.sqlite", {"digests": {}})
    try:
        j.measurement(1, 3, 1.0, np.zeros((0, 3)), float("nan"))
        j.event("measurement", "layer 3: measurement path 40 gave no laser samples", layer=3)
        j.event("measurement", "layer 3: measurement path 41 gave no laser samples", layer=3)
        j.event("cell-fault", "path 1/12 (seq 50) was cut short by a cell fault and is not "
                "run again", layer=1)
        j.event("clamp", "layer 2: 1 path clamped", layer=2)
        notes, warns = _completion_notes(j)
    finally:
        j.close()
    assert notes == []
    assert warns[0].startswith("path 1/12 (seq 50) was cut short") and "clamped" in warns[1]
    assert warns[2].startswith("1 of 1 measured layers had a measurement path the laser gave "
                               "no samples for (layers 3)")


def test_the_journal_counts_paths_done_as_a_query_would(tmp_path):
    j = Journal.create(tmp_path / "j.sqlite", {"digests": {}})
    seqs = [j.command("path", 0, i, f"d{i}")[0] for i in range(6)]
    le, _ = j.command("layer_end", 0, -1, "le")
    assert j.paths_done() == 0
    for s in (seqs[0], seqs[1], seqs[1], le, seqs[3]):   # a repeat and a layer end
        j.done(s)
    j.done(seqs[4], cut=True)
    assert j.paths_done() == 4
    j.close()
    assert Journal.open(tmp_path / "j.sqlite").paths_done() == 4     # counted afresh


def test_stop_and_resume_on_a_separately_started_cell(firmware_tools, planned, tmp_path):
    """``--cell ENDPOINTS`` on ``icefab cell serve`` started by hand (as a real cell would
    be): ``icefab build --stop`` stops the running build (valves off, robot lifted,
    journaled), ``--resume`` finishes it, every path runs once, and the cell, not the
    build's, keeps running."""
    from icefab.cell.virtual import read_endpoints
    from icefab.linkedcell import shutdown_virtual_cell

    state = tmp_path / "cell"
    serve = subprocess.Popen([sys.executable, "-m", "icefab", "cell", "serve", "--state",
                              str(state), "--port", "0", "--grid-for", str(planned),
                              "--time-factor", "50"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        read_endpoints(state, timeout_s=120)
        ep = str(state / "endpoints.json")
        proc = subprocess.Popen([sys.executable, "-m", "icefab", "build", str(planned), "-o",
                                 "b", "--cell", ep], cwd=tmp_path, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            assert _wait_progress(tmp_path / "b", proc) is not None
            r = _icefab("build", "--stop", "b", cwd=tmp_path)
            assert r.returncode == 0 and "stopped" in r.stdout, r.stderr
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
        assert proc.returncode == 143 and "stopped at layer" in err, err
        st = json.loads((tmp_path / "b" / bmod.STATUS).read_text())
        assert st["state"] == "stopped" and st["paths_done"] < st["paths"]
        # a second stop, with no build running, goes to the cell, which keeps running
        r = _icefab("build", "--stop", "b", cwd=tmp_path)
        assert r.returncode == 0 and "the cell was told to stop at once" in r.stdout
        assert "the tool was not lifted" in r.stdout
        assert "it keeps running for 'icefab build --resume b'" in r.stdout
        assert serve.poll() is None
        r = _icefab("build", "--resume", "b", cwd=tmp_path)
        assert r.returncode == 0 and "build complete" in r.stdout, r.stderr
        assert serve.poll() is None                      # the cell is not the build's
        ex = [int(x) for x in (state / "executed.log").read_text().split()]
        assert Counter(ex).most_common(1)[0][1] == 1
        j = Journal.open(tmp_path / "b" / bmod.JOURNAL)
        # every path ran (the cell's log lists paths; layer ends freeze, they do not run)
        assert ex == [c["seq"] for c in j.commands() if c["kind"] != "layer_end"]
        assert any(e["kind"] == "stop" for e in j.events())
        last = max(ex)   # the cell's last completed number (a layer's end is not one)
        j.close()
        # 'icefab cell check' tells it ran a build
        r = _icefab("cell", "check", "--state", str(state), cwd=tmp_path)
        assert r.returncode == 0 and f"commands completed up to number {last} (an earlier " \
            "build" in r.stdout, r.stdout + r.stderr
        # a second build on the same cell, whose platform holds the first's ice, is
        # refused before anything is sent or written; said cleared, it runs its paths,
        # numbered after the first's
        r = _icefab("build", str(planned), "-o", "b2", "--cell", ep, "--layers", "1",
                    cwd=tmp_path)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert f"completed commands up to number {last} since its program started" \
            in r.stderr and "--platform-cleared" in r.stderr
        assert not (tmp_path / "b2").exists()
        assert [int(x) for x in (state / "executed.log").read_text().split()] == ex
        r = _icefab("build", str(planned), "-o", "b2", "--cell", ep, "--layers", "1",
                    "--platform-cleared", cwd=tmp_path)
        assert r.returncode == 0 and "build complete" in r.stdout, r.stderr
        assert f"note: the cell has completed commands up to number {last}" in r.stdout
        ex2 = [int(x) for x in (state / "executed.log").read_text().split()]
        assert ex2[:len(ex)] == ex and len(ex2) > len(ex) and min(ex2[len(ex):]) > last
    finally:
        shutdown_virtual_cell(state)
        if serve.poll() is None:
            serve.kill()


def test_a_cell_whose_surface_is_elsewhere_refuses_the_first_path(firmware_tools, planned,
                                                                   tmp_path):
    """A virtual cell started over another place than the part: its drops fell nowhere and
    its laser read 0, and the build was 'complete'. The cell refuses the first path that
    leaves its surface (ER 10), and the build stops there with that reason."""
    from icefab.cell.virtual import read_endpoints
    from icefab.linkedcell import shutdown_virtual_cell

    state = tmp_path / "cell"
    serve = subprocess.Popen([sys.executable, "-m", "icefab", "cell", "serve", "--state",
                              str(state), "--port", "0", "--bounds=500,500,510,510"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        read_endpoints(state, timeout_s=120)
        r = _icefab("build", str(planned), "-o", "b", "--cell", str(state / "endpoints.json"),
                    "--layers", "1", cwd=tmp_path)
        assert r.returncode == 2, r.stderr
        assert "off the virtual cell's surface" in r.stderr
        assert not (state / "executed.log").exists() or \
            (state / "executed.log").read_text().split() == []
    finally:
        shutdown_virtual_cell(state)
        if serve.poll() is None:
            serve.kill()


def test_the_report_follows_the_status_and_a_measurement_is_not_silent(planned, tmp_path,
                                                                      monkeypatch):
    """report.html was written only at a measurement, a stop or the end: missing for the
    first layers, frozen between measurements; measurement paths wrote no status at all,
    so a long measurement looked like a hung build; a finished build that measured no
    layer said "no measurement yet"; the RMS plot's axis label was cut off (hunt Z)."""
    import re as re_

    from icefab.motion import load_trajectories

    monkeypatch.setattr(time, "monotonic", lambda c=iter(range(0, 10 ** 9, 2)): next(c))
    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    seen = []   # (layer, role, report's paths row, status' paths_done) before each path
    gaps = []   # (status' update_by - time, expected)

    class Watching:
        def __getattr__(self, name):
            return getattr(cell, name)

        def run_path(self, seq, path, upcoming=None):
            rep = build / bmod.REPORT
            row = (re_.search(r"<th>paths</th><td>(\d+) of", rep.read_text()).group(1)
                   if rep.exists() else None)
            st = json.loads((build / bmod.STATUS).read_text())
            seen.append((path.layer, path.role, row, st["paths_done"]))
            # when a reader may call a "running" status stale: within twice the layer's
            # longest path and the margin (a killed build's page said "running" for ever)
            longest = max(lm.durations.max() for lm in motion.layers
                          if lm.index == st["layer"])
            gaps.append((st["update_by"] - st["time"], 2 * longest + bmod.UPDATE_MARGIN_S))
            if row is not None:
                assert "<th>next update by</th>" in rep.read_text()
            return cell.run_path(seq, path, upcoming)

    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    bmod.Runner(build, motion, job, journal, lambda: Watching()).run()
    journal.close()
    first = motion.layers[0].index
    assert seen[0][2] is None                  # not drawn before the first GO
    assert all(r is not None for L, _, r, _ in seen[2:])
    done_before = [int(r) for _, _, r, _ in seen[2:]]
    assert done_before == sorted(done_before) and len(set(done_before)) > 10
    assert seen[1][0] == first and seen[-1][2] is not None
    measuring = [(r, d) for _, role, r, d in seen if role == "measure"]
    assert len(measuring) >= 2
    # each measurement path's status counts the one before it
    assert all(b[1] == a[1] + 1 for a, b in zip(measuring, measuring[1:]))
    assert tuple(json.loads((build / bmod.STATUS).read_text())) == bmod.STATUS_KEYS
    page = (build / bmod.REPORT).read_text()
    assert "<title>icefab build: complete</title>" in page and "refresh" not in page
    assert "next update by" not in page
    assert json.loads((build / bmod.STATUS).read_text())["update_by"] is None
    assert len({round(g, 6) for g, _ in gaps}) > 1     # the layers' longest paths differ
    assert all(g == pytest.approx(want) for g, want in gaps), \
        [x for x in gaps if x[0] != pytest.approx(x[1])]
    svg = page[page.index('<svg id="rms-plot"'):page.index("</svg>")]
    height = float(re_.search(r'height="([\d.]+)pt"', svg).group(1))
    # the x axis' label, baseline and descenders, inside the picture (246.5 of 244.8)
    base = float(re_.search(r"<!-- nominal height \(mm\) -->\s*<g transform=\"translate\("
                            r"[\d.]+ ([\d.]+)\)", svg).group(1))
    assert base + 3.0 <= height
    # a finished build that measured no layer does not promise a measurement
    one = tmp_path / "one"
    m1 = dataclasses.replace(motion, layers=motion.layers[:1])
    cell1 = _prepared(one, m1, job)
    j1 = Journal.create(one / bmod.JOURNAL, {"digests": {}})
    bmod.Runner(one, m1, job, j1, lambda: cell1).run()
    j1.close()
    page = (one / bmod.REPORT).read_text()
    assert "none: no layer of this build was measured" in page
    assert "no measurement yet" not in page


def test_a_progress_line_on_a_terminal_erases_the_rest_of_its_row():
    from icefab.cli.build_cmd import _console_line

    long = "layer 3 (4 of 6), paths 12/99; waiting for the cell (link fault 3: " + "x" * 200
    assert _console_line(long, 80) == "\r" + long[:79] + "\x1b[K"
    assert _console_line("short", 80) == "\rshort\x1b[K"


def test_a_sigterm_lost_as_the_journal_is_made_stops_the_runner(tmp_path):
    """A SIGTERM whose Terminated is raised inside a weakref callback is printed as
    "Exception ignored" and lost; lost as the build made its journal (after the last
    progress report), the build ran all its paths and exited 0 (a check's). The runner
    takes it over: it stops at once and says so (143)."""
    (tmp_path / "job.toml").write_text("[parts]\nscale = [0.4, 0.4, 0.4]\n[slicing]\n"
                                       "layer_thickness_mm = 1.0\n[motion]\nspeed_mm_s = 25.0\n")
    (tmp_path / "lost.py").write_text(
        "import gc, os, signal, sys, weakref\n"
        "import icefab.journal as J\n"
        "made = J.Journal.create.__func__\n"
        "def create(cls, *a, **k):\n"
        "    j = made(cls, *a, **k)\n"
        "    class Lock: pass\n"
        "    def callback(ref):\n"
        "        os.kill(os.getpid(), signal.SIGTERM)   # its handler runs in here\n"
        "        sum(range(1000))\n"
        "    lock = Lock(); ref = weakref.ref(lock, callback); del lock; gc.collect()\n"
        "    return j\n"
        "J.Journal.create = classmethod(create)\n"
        "from icefab.cli import main\n"
        "sys.exit(main(['build', 'demo', '-c', 'job.toml', '--layers', '2', '--virtual',\n"
        "               '-o', 'b']))\n")
    from icefab.linkedcell import shutdown_virtual_cell

    try:
        r = subprocess.run([sys.executable, "lost.py"], cwd=tmp_path, capture_output=True,
                           text=True, timeout=300)
        assert r.returncode == 143, r.stderr
        # no path ran on this link, so the cell had nowhere known to lift the tool from
        assert "Exception ignored" in r.stderr and "SIGTERM received; valves closed, robot " \
            "stopped where it was (the tool was not lifted)" in r.stderr, r.stderr
        st = json.loads(_icefab("build", "--status", "b", "--json", cwd=tmp_path).stdout)
        assert st["paths_done"] == 0 and st["state"] != "complete"
    finally:   # the stopped build's virtual cell runs on for a resume
        shutdown_virtual_cell(tmp_path / "b" / bmod.CELL_DIR)


def _completed_folder(planned, build: Path, cell: str, n_layers: int = 1) -> None:
    """A build folder as ``icefab build`` leaves it, built to its end on the model cell in
    ``build/cell``: job.toml, trajectories.npz (the first ``n_layers``), a journal whose
    meta names ``cell`` ("virtual" or an endpoints file) and the files' digests."""
    from icefab.journal import digest_file
    from icefab.motion import load_trajectories, open_trajectories, save_trajectories

    whole = load_trajectories(planned)
    build.mkdir()
    (build / "job.toml").write_text(to_toml(whole.job))
    save_trajectories(dataclasses.replace(whole, layers=whole.layers[:n_layers]),
                      build / bmod.TRAJECTORIES)
    motion = open_trajectories(build / bmod.TRAJECTORIES)
    model = _prepared(build, motion, whole.job)
    journal = Journal.create(build / bmod.JOURNAL, {
        "cell": cell, "layers": n_layers,
        "layer_indices": [int(lm.index) for lm in motion.layers],
        "measured_layers": [int(lm.index) for lm in motion.layers if bmod.measures(lm)],
        "digests": {"job": digest_file(build / "job.toml"),
                    "trajectories": digest_file(build / bmod.TRAJECTORIES)}})
    try:
        assert bmod.Runner(build, motion, whole.job, journal, lambda: model).run().state \
            == "complete"
    finally:
        journal.close()


def _no_cell(calls: list):
    """A connector for ``icefab build``'s _connector: every call is recorded, and the cell
    is gone (as after its process was stopped)."""
    def connector(*a, **k):
        def connect():
            calls.append(True)
            raise CellError("no cell endpoints file (the cell is gone)")
        return connect
    return connector


@pytest.mark.parametrize("last_done, cut, refused", [(0, 0, False), (0, 3, True),
                                                     (41, 0, True), (None, 0, False)])
def test_a_used_cell_is_refused_before_the_part_is_planned(tmp_path, capsys, monkeypatch,
                                                           last_done, cut, refused):
    """A cell that ran an earlier build is asked before the part is planned (minutes for a
    large part), by its robot link alone: refused at once, nothing written; a cell that
    ran nothing, or one that does not answer, is left to the build's own link."""
    from icefab.cell import robot
    from icefab.cli import build_cmd, main

    asked = []

    class Robot:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            asked.append("closed")

        def hello(self):
            asked.append("hello")

        def status(self):
            return {"state": "idle", "stored": 0, "last_done": last_done, "cut": cut}

    def connect(cls, *a, **k):
        if last_done is None:
            asked.extend(["hello", "closed"])   # as if it timed out after connecting
            raise CellError("robot at 127.0.0.1:7100: no answer")
        return Robot()

    planned = []
    monkeypatch.setattr(robot.RobotLink, "connect", classmethod(connect))
    monkeypatch.setattr(build_cmd, "_plan", lambda *a: planned.append(1) or 1 / 0)
    ep = tmp_path / "ep.json"
    ep.write_text(json.dumps({"robot": {"host": "127.0.0.1", "port": 7100},
                              "valve": {"device": "v"}, "laser": {"device": "l"}}))
    monkeypatch.chdir(tmp_path)
    argv = ["build", "demo", "-o", "b", "--cell", str(ep)]
    if refused:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and f"up to number {max(last_done, cut)} since its " \
            "program started" in err and "--platform-cleared" in err, err
        assert planned == [] and asked == ["hello", "closed"]
        assert not (tmp_path / "b").exists()
        # said cleared, the robot is not even asked (the build's link checks it again)
        asked.clear()
        with pytest.raises(ZeroDivisionError):
            main(argv + ["--platform-cleared"])
        assert asked == [] and planned == [1]
    else:
        with pytest.raises(ZeroDivisionError):   # asked, then on to the planning
            main(argv)
        assert asked == ["hello", "closed"] and planned == [1]


def test_a_resume_of_a_complete_build_has_nothing_to_do(planned, tmp_path, capsys,
                                                        monkeypatch):
    """A resume of a completed build, its cell gone: it waited out 20 link faults for that
    cell and, stopped, turned the status from "complete" into "stopped" (a reviewer's).
    It says the build is complete and leaves journal, status and report as they were,
    without a link to any cell."""
    from icefab.cli import build_cmd, main

    build = tmp_path / "b"
    _completed_folder(planned, build, str(tmp_path / "gone" / "endpoints.json"))
    before = {f: (build / f).read_bytes() for f in (bmod.STATUS, bmod.REPORT)}
    j = Journal.open(build / bmod.JOURNAL)
    events = j.events()
    j.close()
    calls: list = []
    monkeypatch.setattr(build_cmd, "_connector", _no_cell(calls))
    monkeypatch.setattr(bmod.Runner, "FAULT_BACKOFF_S", (0.0, 0.0))
    assert main(["build", "--resume", str(build)]) == 0
    out, err = capsys.readouterr()
    assert out == f"{build}: build complete, nothing to resume ('icefab build --status " \
        f"{build}')\n" and err == "", err
    assert calls == []
    assert {f: (build / f).read_bytes() for f in before} == before
    j = Journal.open(build / bmod.JOURNAL)
    assert j.events() == events
    j.close()


def test_a_runner_whose_journal_has_every_layer_finished_needs_no_cell(planned, tmp_path):
    """A build killed after its last layer, before it journaled "complete": the runner has
    nothing to send and completes without a link (it waited for a cell that may be gone)."""
    from icefab.motion import open_trajectories

    build = tmp_path / "b"
    _completed_folder(planned, build, "virtual")
    motion = open_trajectories(build / bmod.TRAJECTORIES)
    calls: list = []
    journal = Journal.open(build / bmod.JOURNAL)
    try:
        p = bmod.Runner(build, motion, motion.job, journal, _no_cell(calls)(),
                        max_faults=0).run()
    finally:
        journal.close()
    assert p.state == "complete" and calls == []


@pytest.mark.parametrize("argv, said", [
    (["--resume", "b", "--virtual"], "b was built on the cell of "),
    (["--status", "b", "--virtual"], "--status BUILD takes none of --virtual: "),
    (["--status", "b", "in.npz", "--layers", "2"], "--status BUILD takes none of INPUT, "
                                                    "--layers: "),
    (["--stop", "b", "--cell", "ep.json", "-o", "c"], "--stop BUILD takes none of -o, "
                                                      "--cell: "),
    (["--stop", "b", "-c", "job.toml"], "--stop BUILD takes none of -c: "),
    (["--status", "b", "--platform-cleared"], "--status BUILD takes none of "
                                              "--platform-cleared: "),
    (["in.npz", "-o", "c", "--virtual", "--platform-cleared"],
     "--platform-cleared goes with --cell ENDPOINTS: a new virtual cell's platform is "
     "empty"),
])
def test_options_a_resume_status_or_stop_would_ignore_are_refused(planned, tmp_path, capsys,
                                                                  monkeypatch, argv, said):
    """--virtual on the resume of a build on another cell, and a new build's options with
    --status and --stop, did nothing without a word (a reviewer's --resume --virtual went
    to the build's own cell): one line, exit 2, nothing sent, nothing written."""
    from icefab.cli import build_cmd, main

    _completed_folder(planned, tmp_path / "b", str(tmp_path / "gone" / "endpoints.json"))
    (tmp_path / "b" / bmod.STATUS).write_text(json.dumps(dict(json.loads(
        (tmp_path / "b" / bmod.STATUS).read_text()), state="stopped")))  # it would resume
    before = sorted(p.name for p in (tmp_path / "b").iterdir())
    calls: list = []
    monkeypatch.setattr(build_cmd, "_connector", _no_cell(calls))
    monkeypatch.setattr(bmod.Runner, "FAULT_BACKOFF_S", (0.0, 0.0))
    monkeypatch.chdir(tmp_path)
    assert main(["build", *argv]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.startswith(f"icefab build: error: {said}"), err
    assert err.count("\n") == 1 and calls == []
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == before


def test_a_stop_says_who_asked_for_it():
    """Ctrl-C, SIGTERM and 'icefab build --stop' (a request and SIGTERM) all read "a stop
    was asked for" (a reviewer's)."""
    from icefab.cli.build_cmd import stop_asked_by

    assert stop_asked_by(signal.SIGINT, False) == "Ctrl-C"
    assert stop_asked_by(signal.SIGTERM, False) == "SIGTERM received"
    assert stop_asked_by(signal.SIGTERM, True) == stop_asked_by(None, True) \
        == "'icefab build --stop' asked for it"
    assert stop_asked_by(None, False) is None


@pytest.mark.parametrize("answer, said", [
    (20.0, "valves closed, robot stopped, tool lifted 20 mm; resume with"),
    (0.0, "valves closed, robot stopped where it was (the tool was not lifted); resume"),
    (CellError("no reply"), "the cell did not answer the stop (no reply): check it; "),
])
def test_a_stop_says_what_the_cell_did(planned, tmp_path, answer, said):
    """The stop's message and journal said "a stop was asked for" and never whether the
    valves were closed or the tool lifted (a reviewer's): they say who asked and what the
    cell's stop did, no more."""
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    build = tmp_path / "b"
    model = _prepared(build, motion, motion.job)

    class Stopping:
        def __getattr__(self, name):
            return getattr(model, name)

        def stop(self):
            if isinstance(answer, Exception):
                raise answer
            return answer

    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    polls = iter(range(10 ** 6))
    runner = bmod.Runner(build, motion, motion.job, journal, lambda: Stopping(),
                         should_stop=lambda: next(polls) == 3 and "Ctrl-C")
    try:
        with pytest.raises(bmod.BuildStopped) as err:
            runner.run()
        texts = [e["text"] for e in journal.events() if e["kind"] == "stop"]
    finally:
        journal.close()
    assert re.fullmatch(rf"stopped at layer \d+: Ctrl-C; {re.escape(said)}.*", str(err.value))
    assert f"Ctrl-C; {said.split('; ')[0]}" in texts[-1]


def test_a_stop_while_the_link_is_down_says_the_cell_was_not_told(planned, tmp_path):
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    build = tmp_path / "b"
    cell = OutageCell(_prepared(build, motion, motion.job), at={5}, length=100)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    runner = bmod.Runner(build, motion, motion.job, journal, lambda: cell, max_faults=20,
                         should_stop=lambda: bool(runner.progress.waiting) and "Ctrl-C")
    try:
        with pytest.raises(bmod.BuildStopped) as err:
            runner.run()
    finally:
        journal.close()
    assert "Ctrl-C while the build waited for the cell's link; the cell was not told (no " \
           "link to it then): check it; resume with" in str(err.value)


def test_the_eta_is_labelled_and_follows_the_pace_so_far():
    """The ETA was the planned motion time left read as wall time: 0:40:00 for a
    virtual-cell build that took 92 s (a reviewer's). Labelled so until this run's pace
    (wall s per planned s) is known, then at that pace with the planned motion beside."""
    assert bmod.pace_eta_s(2400.0, 60.0, 3.0) == pytest.approx(120.0)
    assert bmod.pace_eta_s(2400.0, bmod.PACE_MIN_RAN_S / 2, 3.0) is None   # too early
    assert bmod.pace_eta_s(2400.0, float("nan"), float("nan")) is None     # not begun
    assert bmod.eta_text(2400.0, None) == "ETA 0:40:00 (planned motion)"
    assert bmod.eta_text(2400.0, 92.0) == "ETA 0:01:32 (pace so far; planned motion 0:40:00)"
    p = bmod.Progress(remaining_s=2400.0, pace_since=100.0, pace_left0_s=2460.0)
    assert p.eta_wall_s(now=103.0) == pytest.approx(120.0)
    p.state = "stopped"
    assert p.eta_wall_s(now=103.0) is None


def test_a_build_on_a_fast_cell_says_its_eta_at_its_pace(planned, tmp_path, capsys):
    """The model cell runs faster than real time: once 10 s of planned motion ran, the
    console line and status.json give the ETA at that pace, below the planned motion
    left; --status of the build, ended, labels the planned motion as such."""
    from icefab.cli.build_cmd import _status
    from icefab.motion import load_trajectories

    motion = load_trajectories(planned)
    build = tmp_path / "b"
    cell = _prepared(build, motion, motion.job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    lines, statuses = [], []

    def seen(p):
        lines.append(bmod.progress_line(p))
        if (build / bmod.STATUS).exists():
            statuses.append(json.loads((build / bmod.STATUS).read_text()))

    try:
        bmod.Runner(build, motion, motion.job, journal, lambda: cell, on_progress=seen).run()
    finally:
        journal.close()
    assert lines[0].endswith("(planned motion), last RMS -")
    paced = [s for s in statuses if s["state"] == "running" and s["eta_wall_s"] is not None]
    assert paced and all(s["eta_wall_s"] <= max(s["eta_s"], 0.0) for s in paced), [
        (s["eta_wall_s"], s["eta_s"]) for s in paced]
    assert any(s["eta_wall_s"] < 0.5 * s["eta_s"] for s in paced), paced
    assert tuple(statuses[-1]) == bmod.STATUS_KEYS
    assert any("(pace so far; planned motion " in line for line in lines)
    assert _status(build, as_json=False) == 0
    assert "ETA 0:00:00 (planned motion)" in capsys.readouterr().out


def test_a_measurement_without_a_surface_keeps_the_integral_term_acting():
    """A control review's: collinear laser samples (no surface) gave the runner no action
    (nominal flow for an interval) and the integral's bias of a lasting flow error was
    lost. The state is kept, the integral term alone acts, and the journal is told."""
    from icefab import feedback

    job = Job().replace(**{"feedback.kp": 0.0, "feedback.kd": 0.0})
    g = np.linspace(-10.0, 10.0, 21)
    X, Y = np.meshgrid(g, g)
    high = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, 1.1)])  # 0.1 mm high
    state, u, filled, rms, note = bmod.smf_from_samples(high, 1.0, feedback.SmfState(), job)
    assert note is None and rms == pytest.approx(0.1) and state.k == 1
    line = np.column_stack([g, np.zeros_like(g), np.full(g.size, 2.3)])   # collinear
    kept, held_u, held_filled, _, note = bmod.smf_from_samples(line, 2.0, state, job)
    assert kept is state
    assert held_u is not None and np.allclose(held_u.z[np.isfinite(u.z)],
                                              u.z[np.isfinite(u.z)], rtol=1e-12)
    assert np.nanmax(held_u.z) < -0.02      # less flow: the part stood high
    assert "integral term alone" in note
    # what the journal keeps restores the same action (a resumed build)
    _, sampler = bmod.unpack_smf(bmod.pack_smf(kept, held_u, held_filled))
    assert np.allclose(sampler(np.array([[0.0, 0.0], [5.0, -5.0]])), u.z[10, 10])
    # before any update there is nothing to hold: nominal flow
    _, none_u, _, _, note = bmod.smf_from_samples(line, 2.0, feedback.SmfState(), job)
    assert none_u is None and "none yet" in note


def test_the_runner_gives_smf_the_measured_layers_footprint(planned, tmp_path, monkeypatch):
    """The runner's SMF update gets the footprint of the layer just deposited (its plan,
    as the valve programs were made from), and the laser's samples lie on it."""
    from icefab.motion import load_trajectories
    from icefab.sim import commanded_footprint, plan_layer_motion

    motion = load_trajectories(planned)
    job = motion.job
    build = tmp_path / "b"
    cell = _prepared(build, motion, job)
    journal = Journal.create(build / bmod.JOURNAL, {"digests": {}})
    seen = []
    real = bmod.smf_from_samples

    def spy(samples, nominal, state, job, footprint=None):
        seen.append((samples, footprint))
        return real(samples, nominal, state, job, footprint)

    monkeypatch.setattr(bmod, "smf_from_samples", spy)
    bmod.Runner(build, motion, job, journal, lambda: cell).run()
    journal.close()
    assert len(seen) == 1                                  # layer 3 (n_d = 4)
    samples, (mask, grid) = seen[0]
    want, want_grid = commanded_footprint(plan_layer_motion(motion.layers[3], job), job)
    assert np.array_equal(mask, want) and np.array_equal(grid.origin, want_grid.origin)
    ix = np.rint((samples[:, 0] - grid.origin[0]) / grid.spacing).astype(int)
    iy = np.rint((samples[:, 1] - grid.origin[1]) / grid.spacing).astype(int)
    assert mask[iy, ix].mean() > 0.99


def test_the_runner_measures_a_two_island_layer_on_its_footprint_only():
    """A control review's: the runner formed the measured surface over the laser samples'
    convex hull, so the empty platform between two islands (or a part's arms) took heights
    interpolated across the gap, and they fed SMF (its integral there, and the action at
    the islands' facing edges). The surface is now restricted to the layer's footprint, as
    the simulator's is."""
    from icefab import feedback
    from icefab.core import Toolpath
    from icefab.sim import commanded_footprint, plan_layer

    job = Job()

    def square(cx, h):
        return np.array([[cx - h, -h], [cx + h, -h], [cx + h, h], [cx - h, h]])

    # two 20 mm squares, 10 mm apart (x in [-25, -5] and [5, 25]), filled by 1.5 mm rings
    paths = [Toolpath(points=square(cx, h), z=0.25, material="part", role="boundary",
                      closed=True, width=1.5, layer=0)
             for cx in (-15.0, 15.0) for h in np.arange(9.25, 0.0, -1.5)]
    mask, grid = commanded_footprint(plan_layer(0, paths, job), job)
    gx, gy = grid.grid()
    assert mask[np.searchsorted(gy, 0.0), np.searchsorted(gx, -15.0)]
    assert not mask[np.searchsorted(gy, 0.0), np.searchsorted(gx, 0.0)]     # the gap
    # the laser over both: the left island 0.2 mm high, the right one at its height
    s = np.arange(-9.5, 9.6, 1.0)
    X, Y = np.meshgrid(s, s)
    samples = np.concatenate([np.column_stack([X.ravel() + cx, Y.ravel(),
                                               np.full(X.size, z)])
                              for cx, z in ((-15.0, 1.2), (15.0, 1.0))])
    _, u_hull, *_ = bmod.smf_from_samples(samples, 1.0, feedback.SmfState(), job)
    state, u, *_ = bmod.smf_from_samples(samples, 1.0, feedback.SmfState(), job,
                                         (mask, grid))
    x, y = u.grid()
    rows = np.abs(y) < 9.0
    gap = np.ix_(rows, np.abs(x) < 4.5)
    assert np.isfinite(u_hull.z[gap]).all()         # the hull: the gap was controlled
    assert np.isnan(u.z[gap]).all() and np.isnan(state.integral.z[gap]).all()
    assert np.allclose(u.z[np.ix_(rows, x > 5.5)], 0.0)
    assert np.all(u.z[np.ix_(rows, x < -5.5)] < -0.1)
