"""End to end on the virtual cell (issue 13's must-show): the first N layers of the demo
mug deposited through the three links -- trajectories to the virtual robot over TCP,
valve programs uploaded to the firmware's host build over its pty, laser samples read
back from the LK-G emulator -- against ``icefab simulate`` (valves mode, open loop, same
seed) on the same trajectories as the controller holds them (micrometre wire rounding).

    python3 bench/bench_cell.py [--layers 60] [--mode fm|pwm] [--work DIR]

Prints the figures for BENCHMARKS.md: wall time of each side, paths and pulses through
the links, and how the two surfaces compare (bit-identical cells, largest difference).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def mug_motion(n_layers: int, job, cache: Path):
    from icefab.demo import demo_mug
    from icefab.motion import load_trajectories, plan_toolpaths, save_trajectories
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh

    from icefab.core import Toolpaths

    f = cache / f"mug_{n_layers}_trajectories.npz"
    if f.exists():
        return load_trajectories(f)
    stack = add_scaffold(slice_mesh(demo_mug(), job), job)
    tp = plan_paths(stack, job)
    motion = plan_toolpaths(Toolpaths(layers=tp.layers[:n_layers], job=tp.job), job)
    save_trajectories(motion, f)
    return load_trajectories(f)


def run(n_layers: int, mode: str, work: Path, out=print) -> dict:
    from icefab import Job
    from icefab.cell.links import CellLinks, run_layer
    from icefab.cell.robot import as_received
    from icefab.cell.virtual import read_endpoints
    from icefab.config import to_toml
    from icefab.motion import save_trajectories
    from icefab.sim import simulate_build

    work.mkdir(parents=True, exist_ok=True)
    job = Job().replace(**{"simulation.deposition": "valves", "flow.mode": mode})
    motion = mug_motion(n_layers, job.replace(**{"flow.mode": "fm"}), work)
    motion = as_received(motion)
    traj = work / "as_received.npz"
    save_trajectories(motion, traj)
    (work / "job.toml").write_text(to_toml(job), encoding="utf-8")

    t0 = time.perf_counter()
    res = simulate_build(motion, job, closed_loop=False)
    t_sim = time.perf_counter() - t0

    state = work / "state"
    if state.exists():
        import shutil
        shutil.rmtree(state)
    env = dict(os.environ)
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "cell", "serve", "--state",
                             str(state), "-c", str(work / "job.toml"), "--grid-for", str(traj),
                             "--port", "0"], env=env, stdout=subprocess.PIPE, text=True)
    try:
        ends = read_endpoints(state, timeout_s=120)
        t0 = time.perf_counter()
        samples = []
        pulses = [0, 0]
        paths = 0
        with CellLinks.open(ends) as links:
            for lm in motion.layers:
                r = run_layer(links, lm, job)
                samples.append(r.samples)
                pulses[0] += r.pulses[0]
                pulses[1] += r.pulses[1]
                paths += r.paths
        t_cell = time.perf_counter() - t0
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
    with np.load(state / "surface.npz") as d:
        z = np.where(d["ever"], d["z"], np.nan)
    ref = res.height.z
    same_nan = bool(np.array_equal(np.isnan(z), np.isnan(ref)))
    ok = np.isfinite(z) & np.isfinite(ref)
    diff = np.abs(z[ok] - ref[ok])
    dh = job.slicing.layer_thickness_mm
    rms_cell = {motion.layers[j].index: float(np.sqrt(np.mean((s[:, 2] - (j + 1) * dh) ** 2)))
                for j, s in enumerate(samples) if len(s)}
    rms_sim = dict(zip(res.layers.tolist(), res.rms_measured.tolist()))
    laser_diff = max((abs(rms_cell[k] - rms_sim[k]) for k in rms_cell), default=float("nan"))
    fig = {"layers": n_layers, "mode": mode, "paths": paths, "pulses": pulses,
           "sim_pulses": res.pulses, "simulate_s": round(t_sim, 1),
           "cell_s": round(t_cell, 1), "cells": int(ok.sum()),
           "bit_identical": bool(same_nan and np.array_equal(z[ok], ref[ok])),
           "identical_cells": int((diff == 0).sum()), "max_abs_diff_mm": float(diff.max()),
           "rms_diff_mm": float(np.sqrt(np.mean(diff ** 2))),
           "max_height_mm": float(np.nanmax(ref)),
           "laser_samples": int(sum(len(s) for s in samples)),
           "measured_layers_cell": sorted(rms_cell), "measured_layers_sim": sorted(rms_sim),
           "laser_rms_max_diff_mm": laser_diff}
    out(json.dumps(fig))
    return fig


HEADING = "## The cell's links end to end (issue 13)"


def section(figs: list[dict], when: str, commit: str) -> str:
    """The BENCHMARKS.md section for the figures of :func:`run` (one dict per mode)."""
    rows = []
    for f in figs:
        same = ("**bit-identical** (all {cells:,} cells)".format(**f) if f["bit_identical"]
                else "{identical_cells:,} of {cells:,} cells identical; largest difference "
                     "{max_abs_diff_mm:.4f} mm, RMS {rms_diff_mm:.4f} mm (top {max_height_mm:.1f} mm)"
                     .format(**f))
        rows.append(f"| {f['mode'].upper()} | {f['paths']:,} | {sum(f['pulses']):,} "
                    f"({f['sim_pulses']:,} in simulate) | {f['laser_samples']:,} "
                    f"({len(f['measured_layers_cell'])} layers; RMS vs simulate within "
                    f"{f['laser_rms_max_diff_mm']:.1e} mm) | {f['cell_s']:.0f} s | "
                    f"{f['simulate_s']:.0f} s | {same} |")
    n = figs[0]["layers"]
    return f"""{HEADING}

Command: `python3 bench/bench_cell.py --layers {n}` (both valve modes). Machine: 2-core
x86_64 shared with six other jobs, {when}, code of commit {commit}. The first {n} layers of
the demo mug (default job: flow error, drift, noise, debris, edge loss, liquid flow,
laser noise and latency), open loop, through the three links of a running
`icefab cell serve`: every trajectory to the virtual C40 over TCP, every deposition
path's valve program uploaded, verified and armed on the firmware's host build (the C
core) over its pty and triggered by the robot's GO, every measurement path's laser values
stored by the LK-G emulator and read back over its pty. The peer is `icefab simulate`
(valves mode, same seed) on the same trajectories as the controller holds them
(micrometre wire rounding: `icefab.cell.robot.as_received`).

| valves | robot paths | pulses through the firmware | laser samples read back | cell (links) | simulate | surface vs simulate |
| --- | --- | --- | --- | --- | --- | --- |
{chr(10).join(rows)}

PWM: the firmware emits the programs' pulses at their ticks with their widths, and the
cell's valve drops what the simulator's does, so the surfaces agree bit for bit; the
laser values differ only by the LK-G format's 0.1 um. FM: the valve's drop volume depends
on its frequency (the calibration table is not proportional); the simulator takes the
commanded frequency, which the cell cannot know, and the cell's valve the rate it is
actually pulsed at (the mean interval to its neighbouring pulses, ticks of 2 ms): that is
the whole difference (same pulses, same places). The suite runs the same comparison on a
4-layer two-material build (`tests/test_cell_virtual.py`, about 25 s); the {n}-layer run
is here because it takes minutes.
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--layers", type=int, default=60)
    ap.add_argument("--mode", choices=("fm", "pwm", "both"), default="both")
    ap.add_argument("--work", default=None)
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    a = ap.parse_args()
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="icefab-bench-cell-"))
    modes = ("pwm", "fm") if a.mode == "both" else (a.mode,)
    figs = [run(a.layers, m, work) for m in modes]
    if not a.no_write and a.mode == "both":
        sys.path.insert(0, str(Path(__file__).parent))
        from _report import write_section

        commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                                capture_output=True, text=True).stdout.strip()
        write_section(HEADING, section(figs, time.strftime("%Y-%m-%d %H:%M UTC",
                                                           time.gmtime()), commit))


if __name__ == "__main__":
    main()
