"""The build runner on the cell's links (icefab.linkedcell): exactly once through the real
protocols when the control PC dies at any point of a path's exchange, and a cell whose
process dies mid-path reporting that path cut after its restart.

The cell is ``icefab.cell.virtual.VirtualCell`` (the virtual C40, the valve firmware's
host build, the laser emulator) in this process for the crash test, and ``icefab cell
serve`` in its own process for the kill test. The build is a 4-layer two-material
annulus with measurement paths on layers 1 and 3, the default disturbances (noise,
debris, laser noise: all drawn from the seed)."""
from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_build import annulus_toolpaths  # noqa: E402

from icefab import Job  # noqa: E402
from icefab import build as bmod  # noqa: E402
from icefab.cell import robot_protocol as rp  # noqa: E402
from icefab.cell.robot import RobotLink, RobotPath  # noqa: E402
from icefab.cell.virtual import VirtualCell, read_endpoints  # noqa: E402
from icefab.cell.world import grid_for  # noqa: E402
from icefab.config import to_toml  # noqa: E402
from icefab.journal import Journal  # noqa: E402
from icefab.linkedcell import LinkedCell, load_endpoints  # noqa: E402
from icefab.motion import plan_toolpaths, save_trajectories  # noqa: E402
from icefab.errors import CellError  # noqa: E402


@pytest.fixture(scope="module")
def planned():
    job = Job().replace(**{"cell.cpus": 1, "feedback.interval_layers": 2})
    return job, plan_toolpaths(annulus_toolpaths(job, 4), job)


class Crash(BaseException):
    """The control PC dies: its links close (as the OS closes a dead process's sockets
    and ports), nothing else happens."""


class CrashingLinkedCell(LinkedCell):
    """A LinkedCell whose PC dies at the ``at``-th robot upload or GO of the session,
    just before it is sent (``after`` False) or just after it was (the reply lost)."""

    def __init__(self, endpoints, job, at: int, after: bool):
        super().__init__(endpoints, job)
        self.at, self.after, self.n = at, after, 0

    def hello(self):
        out = super().hello()
        robot = self.links.robot
        for name in ("upload", "go"):
            setattr(robot, name, self._crashing(getattr(robot, name)))
        return out

    def _crashing(self, fn):
        def call(*a, **kw):
            self.n += 1
            if self.n == self.at and not self.after:
                self._die()
            out = fn(*a, **kw)
            if self.n == self.at:
                self._die()
            return out
        return call

    def _die(self):
        self.close()
        raise Crash()


def _build(build: Path, motion, job, endpoints, crash=None) -> None:
    jpath = build / bmod.JOURNAL
    build.mkdir(exist_ok=True)
    journal = Journal.open(jpath) if jpath.exists() else Journal.create(jpath, {"digests": {}})

    def connect():
        if crash is None:
            return LinkedCell(endpoints, job)
        return CrashingLinkedCell(endpoints, job, *crash)
    runner = bmod.Runner(build, motion, job, journal, connect)
    try:
        runner.run()
    finally:
        journal.close()
    assert runner.cell is None      # the runner closed its link


def _executed(state: Path) -> list[int]:
    return [int(x) for x in (state / "executed.log").read_text().split()]


@pytest.fixture(scope="module")
def reference(planned, firmware_exe, tmp_path_factory):
    """The uninterrupted build: its folder (``ref``: journal; ``ref-cell``: the cell)."""
    job, motion = planned
    d = tmp_path_factory.mktemp("reference")
    with VirtualCell(d / "ref-cell", job, grid=grid_for(motion, job),
                     firmware_exe=firmware_exe) as c:
        _build(d / "ref", motion, job, c.endpoints)
    return d


def test_exactly_once_through_the_links_when_the_pc_dies_anywhere(planned, firmware_exe,
                                                                   reference, tmp_path):
    job, motion = planned
    grid = grid_for(motion, job)
    ref = _executed(reference / "ref-cell")
    n_robot_calls = 2 * len(ref)           # an upload and a GO per path
    rng = np.random.default_rng(7)
    deaths = Counter()
    with VirtualCell(tmp_path / "cell", job, grid=grid, firmware_exe=firmware_exe) as c:
        while True:
            crash = (int(rng.integers(1, max(2, n_robot_calls // 4))),
                     bool(rng.integers(0, 2)))
            try:
                _build(tmp_path / "b", motion, job, c.endpoints, crash)
                break
            except Crash:
                deaths[crash[1]] += 1
    assert deaths[True] >= 2 and deaths[False] >= 2, deaths   # before and after sending
    with np.load(reference / "ref-cell" / "surface.npz") as a, \
            np.load(tmp_path / "cell" / "surface.npz") as b:
        assert np.array_equal(a["z"], b["z"]) and np.array_equal(a["ever"], b["ever"])
    ex = _executed(tmp_path / "cell")
    assert ex == ref                        # every path once, in the same order
    j = Journal.open(tmp_path / "b" / bmod.JOURNAL)
    cmds = j.commands()
    assert all(c["done"] is not None and not c["cut"] for c in cmds)
    ref_j = Journal.open(reference / "ref" / bmod.JOURNAL)
    # the same laser samples reached SMF, so its state is the uninterrupted build's
    got, want = j.measurements(), ref_j.measurements()
    assert len(got) == len(want) == 2
    for m, r in zip(got, want):
        np.testing.assert_array_equal(m["samples"], r["samples"])
    assert j.last_smf()[2] == ref_j.last_smf()[2]


def test_a_stop_lifts_the_tool_and_the_build_resumes_exactly_once(planned, firmware_exe,
                                                                   reference, tmp_path):
    """``--stop`` / Ctrl-C between paths: valves off, robot stopped, then a one-point
    park path 20 mm above where the last one ended, which the robot does not count as a
    path done (a path the PC had uploaded ahead and the stop discarded is sent again on
    resume); resumed, the build runs exactly the uninterrupted build's paths."""
    from icefab.linkedcell import SAFE_LIFT_MM

    job, motion = planned
    lifts = []

    class Watching(LinkedCell):
        def stop(self):
            self.links.robot.upload = _spy(self.links.robot.upload, lifts)
            return super().stop()

    with VirtualCell(tmp_path / "cell", job, grid=grid_for(motion, job),
                     firmware_exe=firmware_exe) as c:
        journal = Journal.create(tmp_path / bmod.JOURNAL, {"digests": {}})
        calls = iter(range(10 ** 6))
        runner = bmod.Runner(tmp_path, motion, job, journal, lambda: Watching(c.endpoints, job),
                             should_stop=lambda: next(calls) == 40 and "Ctrl-C")
        with pytest.raises(bmod.BuildStopped, match=f"Ctrl-C; valves closed, robot stopped, "
                           f"tool lifted {SAFE_LIFT_MM:g} mm; resume with"):
            runner.run()
        assert runner.cell is None
        (path, seq), = lifts
        assert seq is None and len(path.xy) == 1 and path.flags == rp.FLAG_PARK
        stopped_at = [e["layer"] for e in journal.events() if e["kind"] == "stop"]
        journal.close()
        _build(tmp_path, motion, job, c.endpoints)       # resume
    assert _executed(tmp_path / "cell") == _executed(reference / "ref-cell")
    with np.load(reference / "ref-cell" / "surface.npz") as a, \
            np.load(tmp_path / "cell" / "surface.npz") as b:
        assert np.array_equal(a["z"], b["z"])
    lm = next(lm for lm in motion.layers if lm.index == stopped_at[0])
    assert path.z_mm == pytest.approx(lm.top(job) + SAFE_LIFT_MM)


def _spy(fn, out):
    def upload(path, seq=None):
        out.append((path, seq))
        return fn(path, seq)
    return upload


class RecordingLinkedCell(LinkedCell):
    """Records the order of robot uploads and DN waits (and the valve uploads)."""

    events: list = []

    def hello(self):
        out = super().hello()
        robot, valves = self.links.robot, self.links.valves
        up, wait, vup = robot.upload, robot.wait_done, valves.upload

        def upload(path, seq=None):
            self.events.append(("upload", seq))
            return up(path, seq)

        def wait_done(seq, timeout_s=None):
            out = wait(seq, timeout_s)
            self.events.append(("done", seq))
            return out

        def valve_upload(valve, program, **kw):
            self.events.append(("valve", None))
            return vup(valve, program, **kw)
        robot.upload, robot.wait_done, valves.upload = upload, wait_done, valve_upload
        return out


def test_the_next_path_is_uploaded_while_one_moves(planned, firmware_exe, tmp_path,
                                                   plan_ahead_at_once):
    """Within a layer, path k+1 (robot path and valve program) is uploaded between the
    GO and the DN of path k: the robot never waits for the PC's data."""
    job, motion = planned
    RecordingLinkedCell.events = ev = []
    with VirtualCell(tmp_path / "cell", job, grid=grid_for(motion, job),
                     firmware_exe=firmware_exe) as c:
        journal = Journal.create(tmp_path / bmod.JOURNAL, {"digests": {}})
        bmod.Runner(tmp_path, motion, job, journal,
                    lambda: RecordingLinkedCell(c.endpoints, job)).run()
    cmds = journal.commands()
    journal.close()
    ends = {r["layer"]: r["seq"] for r in cmds if r["kind"] == "layer_end"}
    # deposition and travel (measurement paths come after the layer's end)
    paths = [r for r in cmds if r["kind"] == "path" and r["seq"] < ends[r["layer"]]]
    pos = {e: k for k, e in enumerate(ev)}
    pairs = [(a["seq"], b["seq"]) for a, b in zip(paths, paths[1:])
             if a["layer"] == b["layer"] and a["seq"] + 1 == b["seq"]]
    assert len(pairs) > 30
    depositing = {r["seq"] for r in paths if _traj(motion, r).path is not None
                  and _traj(motion, r).path.depositing}
    for a, b in pairs:
        assert pos[("upload", b)] < pos[("done", a)], (a, b)
        if b in depositing:   # its valve program too, before path a's DN
            assert any(e[0] == "valve" for e in ev[pos[("upload", b)]:pos[("done", a)]])
    # across a layer end without measurement (layers 0 -> 1, 2 -> 3): the next layer's
    # first path is uploaded during the last path of the layer, numbered after its LE
    measured = {lm.index for lm in motion.layers
                if any(t.path is not None and t.path.role == "measure" for t in lm.trajectories)}
    crossings = 0
    for L in sorted(ends)[:-1]:
        if L in measured:
            continue
        last = max(r["seq"] for r in paths if r["layer"] == L)
        first = min(r["seq"] for r in paths if r["layer"] == L + 1)
        assert last < ends[L] < first
        assert pos[("upload", first)] < pos[("done", last)]
        crossings += 1
    assert crossings == 2


def _traj(motion, row):
    lm = next(lm for lm in motion.layers if lm.index == row["layer"])
    return lm.trajectories[row["item"]]


def test_a_new_session_settles_what_a_dead_one_left(planned, firmware_exe, tmp_path):
    """A path uploaded (not started) by a session that died is discarded, so its number
    can be uploaded again; the laser values of a measurement path whose DN was lost are
    read from the laser's storage."""
    job, motion = planned
    with VirtualCell(tmp_path / "cell", job, grid=grid_for(motion, job),
                     firmware_exe=firmware_exe) as c:
        from icefab.frames import to_base_frame

        # the laser over the part (the cell refuses a path off its surface: ER 10)
        xy = to_base_frame(np.column_stack([10 * np.cos(np.linspace(0, 3, 50)),
                                            10 * np.sin(np.linspace(0, 3, 50))]), "laser", job)
        with RobotLink.connect("127.0.0.1", c.endpoints["robot"]["port"]) as dead:
            dead.hello()
            dead.upload(RobotPath(xy=xy, dt_s=0.02, z_mm=1.0, flags=0, tool="none",
                                  width_mm=0.0, layer=0, index=0), 5)
        cell = LinkedCell(c.endpoints, job)
        cell.hello()
        st = cell.links.robot.status()
        assert st["stored"] == 0 and st["last_done"] == 0
        from icefab.runcell import CellPath

        meas = CellPath(layer=0, item=1, role="measure", tool="laser", xy=xy, dt_s=0.02,
                        z_mm=1.0, width_mm=0.0)
        assert cell.run_path(5, meas) is True
        want = cell.laser_samples(5, meas)
        assert want.shape == (len(np.arange(0, 49 * 0.02 + 1e-9, 0.01)), 4)
        assert cell.status().last_done == 5
        assert cell.run_path(5, meas) is False        # done already: not run again
        cell.close()
        again = LinkedCell(c.endpoints, job)
        again.hello()
        np.testing.assert_array_equal(again.laser_samples(5, meas), want)
        again.close()
    assert _executed(tmp_path / "cell") == [5]


def test_stop_now_stops_a_motion_under_way_at_once(planned, firmware_exe, tmp_path):
    """'icefab build --stop' with no build running opened the cell with hello(), which lets
    a motion under way run to its end (a hunt's stop waited 7.4 s for a measurement path,
    a deposition path's valve dispensing meanwhile). stop_now() stops it at once: the
    path is cut."""
    job, motion = planned
    with VirtualCell(tmp_path / "cell", job, grid=grid_for(motion, job),
                     firmware_exe=firmware_exe, time_factor=1.0) as c:
        from icefab.frames import to_base_frame

        t = np.linspace(0, 3, 300)       # 6 s at 0.02 s a point, in real time
        xy = to_base_frame(np.column_stack([10 * np.cos(t), 10 * np.sin(t)]), "laser", job)
        with RobotLink.connect("127.0.0.1", c.endpoints["robot"]["port"]) as first:
            first.hello()
            seq = first.upload(RobotPath(xy=xy, dt_s=0.02, z_mm=1.0, flags=0, tool="none",
                                         width_mm=0.0, layer=0, index=0), 7)
            first.go(seq)
            time.sleep(0.3)
        t0 = time.monotonic()
        cell = LinkedCell(c.endpoints, job)
        try:
            cell.stop_now()
            assert time.monotonic() - t0 < 3.0
            st = cell.links.robot.status()
        finally:
            cell.close()
        assert st["state"] == "aborted" and st["cut"] == seq


def test_a_cell_killed_mid_path_reports_it_cut_after_its_restart(planned, firmware_tools,
                                                                 tmp_path):
    job, motion = planned
    save_trajectories(motion, tmp_path / "t.npz")
    (tmp_path / "job.toml").write_text(to_toml(job))
    state = tmp_path / "cell"

    def serve(factor):
        args = [sys.executable, "-m", "icefab", "cell", "serve", "--state", str(state),
                "--port", "0", "--time-factor", str(factor)]
        if not (state / "surface.npz").exists():
            args += ["-c", str(tmp_path / "job.toml"), "--grid-for", str(tmp_path / "t.npz")]
        (state / "endpoints.json").unlink(missing_ok=True)
        proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True)
        try:
            read_endpoints(state, timeout_s=120)
        except CellError:
            proc.kill()
            raise AssertionError(proc.communicate()[1])
        return proc

    xy = np.column_stack([340 + np.linspace(0, 20, 101), np.zeros(101)])
    travel = RobotPath(xy=xy, dt_s=0.02, z_mm=1.0, flags=0, tool="none", width_mm=0.0,
                       layer=0, index=0)
    proc = serve(1.0)          # real time: the 2 s path is under way when the cell dies
    try:
        ep = load_endpoints(state)
        with RobotLink.connect("127.0.0.1", ep["robot"]["port"]) as link:
            link.hello()
            link.upload(dataclasses.replace(travel, xy=xy[:3]), 1)
            link.go(1)
            link.wait_done(1)                  # path 1 done
            link.upload(travel, 2)
            link.go(2)
            time.sleep(0.3)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
    proc = serve(0.0)
    try:
        cell = LinkedCell(load_endpoints(state), job)
        cell.hello()
        st = cell.status()
        assert (st.last_done, st.cut) == (1, 2)
        cell.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    assert _executed(state) == [1]


def test_paths_longer_than_the_controller_stores_are_refused_before_anything_moves(planned):
    from types import SimpleNamespace

    from icefab.cell.robot import RobotInfo

    job, motion = planned
    longest = max(len(t.xy) for lm in motion.layers for t in lm.trajectories)
    cell = LinkedCell({}, job)
    cell.links = SimpleNamespace(robot=SimpleNamespace(info=RobotInfo(2, longest, 4)))
    cell.check_paths(motion)                                   # fits exactly
    cell.links.robot.info = RobotInfo(2, longest - 1, 4)
    with pytest.raises(CellError, match=rf"{longest} points, the robot controller stores "
                                        rf"{longest - 1} per path"):
        cell.check_paths(motion)


def test_a_cell_interrupted_while_it_starts_does_not_run_on(tmp_path, monkeypatch):
    # a build stopped (--stop, Ctrl-C) while its virtual cell started: the clean-up found no
    # endpoints (no pid), removed the folder, and the cell wrote its files again and ran on,
    # out of reach of --stop and --status (a tester's)
    from icefab import linkedcell

    started = []
    real_popen = subprocess.Popen

    def popen(args, **kw):
        # a stand-in that never writes its endpoints, in its own session as the cell is
        p = real_popen([sys.executable, "-c", "import time; time.sleep(60)"], **kw)
        started.append(p)
        return p

    sleeps = []

    def sleep(s):
        sleeps.append(s)
        if len(sleeps) == 3:
            raise KeyboardInterrupt

    monkeypatch.setattr(linkedcell.subprocess, "Popen", popen)
    monkeypatch.setattr(linkedcell.time, "sleep", sleep)
    with pytest.raises(KeyboardInterrupt):
        linkedcell.start_virtual_cell(tmp_path / "cell", tmp_path / "job.toml",
                                      tmp_path / "t.npz")
    (proc,) = started
    assert proc.poll() is not None      # killed and reaped, not left running


@pytest.mark.parametrize("damage", ["half", "empty"])
def test_a_cell_that_refuses_to_start_is_not_started_again(tmp_path, damage):
    """A damaged surface.npz: 'icefab cell serve' printed a BadZipFile / EOFError traceback
    (status 1), and the build started the cell 21 times over 100 s, then advised resuming
    when it answered (a hunt's). The cell now names the file (status 2, icefab's refusal),
    and its start is a refusal the build does not repeat (CellRefused)."""
    import numpy as np

    from icefab import linkedcell
    from icefab.config import Job, to_toml
    from icefab.errors import CellRefused

    state = tmp_path / "cell"
    state.mkdir()
    surface = state / "surface.npz"
    np.savez(surface, job=np.array(to_toml(Job())), z=np.zeros((4, 4)))
    size = surface.stat().st_size
    os.truncate(surface, size // 2 if damage == "half" else 0)
    with pytest.raises(CellRefused, match=r"exited at start \(status 2: icefab cell: error: "
                       r".*surface.npz: cannot read the cell's job .*the file is damaged"):
        linkedcell.start_virtual_cell(state, tmp_path / "job.toml", tmp_path / "t.npz",
                                      timeout_s=60)
