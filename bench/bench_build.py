"""Build runner benchmarks (issue 14): SIGKILL the build at random moments and resume
(final surface bit-identical to an uninterrupted build's, every path executed once), and
the host's overhead per layer against the layer's motion time.

    python3 bench/bench_build.py kills [--layers 60] [--kills 30] [--seed 0]
    python3 bench/bench_build.py overhead TRAJECTORIES.npz [--layers N]

Prints its figures; BENCHMARKS.md records them.
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
from collections import Counter
from pathlib import Path

import numpy as np


def _plan_demo(d: Path, layers: int) -> Path:
    from icefab.config import Job
    from icefab.demo import demo_mug
    from icefab.mesh import transform
    from icefab.motion import plan_toolpaths, save_trajectories
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh
    from icefab.core import Stack

    job = Job()
    stack = add_scaffold(slice_mesh(transform(demo_mug(), job.parts), job), job)
    stack = Stack(layers=stack.layers[:layers], job=stack.job,
                  layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    motion = plan_toolpaths(plan_paths(stack, job), job)
    save_trajectories(motion, d / "mug.npz")
    return d / "mug.npz"


def _kill_cell(build: Path) -> None:
    ep = build / "cell" / "endpoints.json"
    if ep.is_file():
        try:
            os.kill(json.loads(ep.read_text())["pid"], signal.SIGKILL)
        except OSError:
            pass


def _done(build: Path) -> int:
    import sqlite3

    f = build / "journal.sqlite"
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


def kills(args: argparse.Namespace) -> None:
    d = Path(tempfile.mkdtemp(prefix="bench_build."))
    traj = _plan_demo(d, args.layers)
    cmd = [sys.executable, "-m", "icefab", "build"]
    t0 = time.perf_counter()
    subprocess.run(cmd + [str(traj), "-o", "ref", "--virtual"], cwd=d, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_ref = time.perf_counter() - t0
    rng = np.random.default_rng(args.seed)
    proc = subprocess.Popen(cmd + [str(traj), "-o", "k", "--virtual"], cwd=d,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    n = 0
    # each kill: a random moment (up to the mean share of the uninterrupted build's time
    # per kill, so all kills fit in the build: up to twice that let the build finish
    # after 28 of 30) after the (resumed) build journaled one more command done, so that a
    # slow process start on a loaded machine cannot starve the build
    share = t_ref / args.kills
    while n < args.kills:
        start = _done(d / "k")
        while proc.poll() is None and _done(d / "k") <= start:
            time.sleep(0.02)
        if proc.poll() is not None:
            break
        time.sleep(float(rng.uniform(0.0, share)))
        if proc.poll() is not None:
            break
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        n += 1
        proc = subprocess.Popen(cmd + ["--resume", "k"], cwd=d, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
    proc.wait()
    _kill_cell(d / "k")
    _kill_cell(d / "ref")
    a = np.load(d / "ref" / "cell" / "surface.npz")
    b = np.load(d / "k" / "cell" / "surface.npz")
    ex = [int(x) for x in (d / "k" / "cell" / "executed.log").read_text().split()]
    ref_ex = [int(x) for x in (d / "ref" / "cell" / "executed.log").read_text().split()]
    print(json.dumps({"layers": args.layers, "kills": n, "exit": proc.returncode,
                      "uninterrupted_s": round(t_ref, 1),
                      "surface_bit_identical": bool(np.array_equal(a["z"], b["z"],
                                                                   equal_nan=True)),
                      "commands": len(ex), "max_executions_per_command":
                          Counter(ex).most_common(1)[0][1],
                      "same_commands_as_uninterrupted": ex == ref_ex, "dir": str(d)}))


def overhead(args: argparse.Namespace) -> None:
    """Host time per layer (valve planning, SMF, journal, cell calls) vs motion time."""
    from icefab import build as bmod
    from icefab.cli.build_cmd import _box
    from icefab.config import to_toml
    from icefab.journal import Journal
    from icefab.motion import BuildMotion, load_trajectories
    from icefab.runcell import VirtualCell

    m = load_trajectories(args.trajectories)
    layers = m.layers[:args.layers] if args.layers else m.layers
    motion = BuildMotion(layers=tuple(layers), job=m.job, robot=m.robot,
                         joint_names=m.joint_names)
    d = Path(tempfile.mkdtemp(prefix="bench_overhead."))
    journal = Journal.create(d / "journal.sqlite", {"digests": {}})
    cell = VirtualCell(d / "cell")
    lo, hi = _box(motion, m.job)
    cell.prepare(to_toml(m.job), tuple(lo), tuple(hi))
    times = {}

    class Timed:
        def __getattr__(self, name):
            fn = getattr(cell, name)

            def call(*a):
                t = time.perf_counter()
                try:
                    return fn(*a)
                finally:
                    times[name] = times.get(name, 0.0) + time.perf_counter() - t
            return call
    t0 = time.perf_counter()
    bmod.Runner(d, motion, m.job, journal, lambda: Timed()).run()
    total = time.perf_counter() - t0
    cell_s = sum(times.values())
    motion_s = motion.duration
    print(json.dumps({"layers": len(layers), "motion_s": round(motion_s, 1),
                      "host_s": round(total - cell_s, 2), "virtual_cell_s": round(cell_s, 2),
                      "host_fraction_of_motion": round((total - cell_s) / motion_s, 4)}))


def main() -> None:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="what", required=True)
    k = sub.add_parser("kills")
    k.add_argument("--layers", type=int, default=60)
    k.add_argument("--kills", type=int, default=30)
    k.add_argument("--seed", type=int, default=0)
    o = sub.add_parser("overhead")
    o.add_argument("trajectories")
    o.add_argument("--layers", type=int, default=0)
    args = p.parse_args()
    kills(args) if args.what == "kills" else overhead(args)


if __name__ == "__main__":
    main()
