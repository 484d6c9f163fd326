"""The virtual cell as its own process, driven through the three links (issue 13).

Ground truth: ``icefab.sim.simulate_build`` (valves mode, open loop, same seed) on the
same trajectories as the controller holds them. With PWM valves the cell's valve drops
what the simulator's does, so the surfaces must agree bit for bit; with FM the cell's
valve drops Q(nu)/nu at the rate it actually pulses at (the simulator: the commanded
rate), which moves heights by a fraction of a percent (BENCHMARKS.md).

The suite runs a 4-layer annulus build (two materials, measurement paths on layers 1 and
3); the 60-layer demo mug is ``bench/bench_cell.py`` (BENCHMARKS.md: about 3 minutes).
Needs a C compiler and make for the firmware's host build (``.ci/run`` installs them).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_build import annulus_toolpaths  # noqa: E402

from icefab import Job  # noqa: E402
from icefab.cell.links import CellLinks, run_layer  # noqa: E402
from icefab.cell.robot import as_received  # noqa: E402
from icefab.cell.virtual import read_endpoints  # noqa: E402
from icefab.config import to_toml  # noqa: E402
from icefab.errors import CellError  # noqa: E402
from icefab.motion import plan_toolpaths, save_trajectories  # noqa: E402
from icefab.sim import simulate_build  # noqa: E402


def _job(mode):
    return Job().replace(**{"simulation.deposition": "valves", "flow.mode": mode,
                            "cell.cpus": 1, "feedback.interval_layers": 2})


_BUILDS: dict = {}


def _build(mode, tmp_path_factory):
    if mode not in _BUILDS:
        job = _job(mode)
        motion = as_received(plan_toolpaths(annulus_toolpaths(job, 4), job))
        work = tmp_path_factory.mktemp(f"build-{mode}")
        save_trajectories(motion, work / "t.npz")
        (work / "job.toml").write_text(to_toml(job))
        _BUILDS[mode] = job, motion, simulate_build(motion, job, closed_loop=False), work
    return _BUILDS[mode]


@pytest.fixture(scope="module", params=["pwm", "fm"])
def build(request, tmp_path_factory):
    return _build(request.param, tmp_path_factory)


class Cell:
    """``icefab cell serve`` in its own process."""

    def __init__(self, state, work, exe, *extra, layers=0):
        args = [sys.executable, "-m", "icefab", "cell", "serve", "--state", str(state),
                "--port", "0", "--firmware", str(exe), *extra]
        if not (Path(state) / "surface.npz").exists():
            args += ["-c", str(work / "job.toml"), "--grid-for", str(work / "t.npz"),
                     "--layers", str(layers)]
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=dict(os.environ))
        try:
            self.endpoints = read_endpoints(state, timeout_s=60)
        except CellError:
            self.proc.kill()
            raise AssertionError(self.proc.communicate()[1])

    def stop(self):
        self.proc.send_signal(signal.SIGTERM)
        out, err = self.proc.communicate(timeout=60)
        assert self.proc.returncode == 0, err
        return out


def _surface(state):
    with np.load(Path(state) / "surface.npz") as d:
        return np.where(d["ever"], d["z"], np.nan)


def _run(cell, layers, job):
    with CellLinks.open(cell.endpoints) as links:
        return [run_layer(links, lm, job) for lm in layers]


def test_links_through_the_cell_give_the_simulators_surface(build, firmware_exe, tmp_path):
    job, motion, res, work = build
    cell = Cell(tmp_path / "st", work, firmware_exe)
    try:
        runs = _run(cell, motion.layers, job)
    finally:
        out = cell.stop()
    assert "stopped after" in out
    z = _surface(tmp_path / "st")
    assert sum(r.pulses[0] + r.pulses[1] for r in runs) == res.pulses
    # the pulse log starts again at each trigger, and no pulse was lost for it (the
    # surface below): it holds the last play only (it grew 2-3 KB a path, 1.5 GB over a
    # 300 mm part)
    log = (tmp_path / "st" / "valve-pulses.log").read_text().splitlines()
    assert sum(ln.startswith("start ") for ln in log) == 1 and log[-1] == "exit"
    assert np.array_equal(np.isnan(z), np.isnan(res.height.z))
    if job.flow.mode == "pwm":
        np.testing.assert_array_equal(z, res.height.z)
    else:
        ok = np.isfinite(z)
        assert np.abs(z[ok] - res.height.z[ok]).max() < 0.01 * np.nanmax(res.height.z)
    # the laser samples read back: the simulator's to the LK-G's 0.1 um (open loop)
    dh = job.slicing.layer_thickness_mm
    measured = [(j, r.samples) for j, r in enumerate(runs) if len(r.samples)]
    assert [motion.layers[j].index for j, _ in measured] == res.layers.tolist()
    for (j, s), rms in zip(measured, res.rms_measured):
        got = np.sqrt(np.mean((s[:, 2] - (j + 1) * dh) ** 2))
        if job.flow.mode == "pwm":
            assert got == pytest.approx(rms, abs=1e-4)


def test_a_restarted_cell_carries_on_with_the_same_surface(firmware_exe, tmp_path,
                                                           tmp_path_factory):
    """One layer, the cell stopped, started again on the same state folder (this time at
    200 x real time, the firmware on its real clock), the next layer (with measurement
    paths): the simulator's surface of both, bit for bit (PWM)."""
    job, motion, _, work = _build("pwm", tmp_path_factory)
    res = simulate_build(motion, job, layers=2, closed_loop=False)
    state = tmp_path / "st"
    cell = Cell(state, work, firmware_exe, layers=2)
    try:
        _run(cell, motion.layers[:1], job)
    finally:
        cell.stop()
    cell = Cell(state, work, firmware_exe, "--time-factor", "200")  # restarted, real clock
    try:
        runs = _run(cell, motion.layers[1:2], job)
    finally:
        cell.stop()
    assert len(runs[0].samples)
    np.testing.assert_array_equal(_surface(state), res.height.z)
