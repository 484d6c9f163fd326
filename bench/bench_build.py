"""Build runner benchmarks (issue 14), on the cell's links (``icefab build --virtual``:
``icefab cell serve``): SIGKILL the build at random moments and resume (final surface
bit-identical to an uninterrupted build's, every path executed once); SIGKILL the cell
mid-path (the build completes, final RMS against the uninterrupted build's); where the
robot waits for the PC on the 300 mm bunny.

    python3 bench/bench_build.py kills [--layers 60] [--kills 30] [--seed 0]
    python3 bench/bench_build.py cellkills [--layers 60] [--kills 5] [--time-factor 100]
    python3 bench/bench_build.py overhead [--first 301] [--layers 4] [--interval N]

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


def cell_kills(args: argparse.Namespace) -> None:
    """SIGKILL the virtual cell's process (``icefab cell serve``) mid-path a few times
    during a build; the build reconnects (restarting the cell), the path cut short is
    journaled and the surface measured at once; the final RMS against the uninterrupted
    build's."""
    from icefab.journal import Journal

    d = Path(tempfile.mkdtemp(prefix="bench_cellkills."))
    traj = _plan_demo(d, args.layers)
    cmd = [sys.executable, "-m", "icefab", "build", str(traj), "--virtual",
           "--cell-time-factor", str(args.time_factor)]
    subprocess.run(cmd + ["-o", "ref"], cwd=d, check=True, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd + ["-o", "f"], cwd=d, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    n = 0
    while n < args.kills and proc.poll() is None:
        start = _done(d / "f")
        while proc.poll() is None and _done(d / "f") <= start + args.gap:
            time.sleep(0.05)
        time.sleep(float(rng.uniform(0.0, 0.5)))
        if proc.poll() is not None:
            break
        _kill_cell(d / "f")
        n += 1
    proc.wait()
    wall = time.perf_counter() - t0
    _kill_cell(d / "f")
    _kill_cell(d / "ref")
    j = Journal.open(d / "f" / "journal.sqlite")
    ref = Journal.open(d / "ref" / "journal.sqlite")
    ex = [int(x) for x in (d / "f" / "cell" / "executed.log").read_text().split()]
    print(json.dumps({
        "layers": args.layers, "cell_kills": n, "exit": proc.returncode,
        "wall_s": round(wall, 1), "cut_paths": sum(1 for c in j.commands() if c["cut"]),
        "fault_measurements": sum(1 for e in j.events() if e["kind"] == "fault-measure"),
        "max_executions_per_command": Counter(ex).most_common(1)[0][1],
        "final_rms_mm": j.measurements()[-1]["rms_measured"],
        "uninterrupted_final_rms_mm": ref.measurements()[-1]["rms_measured"],
        "dir": str(d)}))


def _bunny_layers(first: int, count: int, **changes):
    """Trajectories of the 300 mm bunny's layers ``first`` .. ``first + count - 1``
    (prepared as ``icefab slice`` does: origin (340, 0), stroke 400 mm; scaffold and
    paths of the whole stack, trajectories of those layers), and the job."""
    sys.path.insert(0, str(Path(__file__).parent))
    from meshes import big_mesh

    from icefab.config import Job
    from icefab.core import Stack
    from icefab.mesh import prepare_parts
    from icefab.motion import plan_toolpaths
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh

    job = Job().replace(**{"cell.ee_origin_mm": (340.0, 0.0), "cell.stroke_mm": 400.0,
                           **changes})
    mesh = prepare_parts(job.replace(**{"parts.files": [str(big_mesh("bunny"))]}))
    stack = add_scaffold(slice_mesh(mesh, job), job)
    sub = Stack(layers=stack.layers[first:first + count], job=stack.job,
                layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    return plan_toolpaths(plan_paths(sub, job), job), job


def overhead(args: argparse.Namespace) -> None:
    """Where the robot waits for the PC: the runner on the cell's links (LinkedCell) and
    the virtual cell in its own process (``icefab cell serve``), as fast as it goes.

    Per path the robot waits when the PC is not ready for the next GO at the end of the
    current motion: ready = (its preload after this GO) + (the PC's work between this
    DN and the next GO); wait = max(0, ready - motion of this path). A layer's first path
    waits for everything between the last DN of the layer before (its end, measurement,
    SMF) and its GO: there the robot stands (it has nothing stored)."""
    from icefab import build as bmod
    from icefab.config import to_toml
    from icefab.journal import Journal
    from icefab.linkedcell import (LinkedCell, load_endpoints, shutdown_virtual_cell,
                                   start_virtual_cell)
    from icefab.motion import save_trajectories

    t0 = time.perf_counter()
    motion, job = _bunny_layers(args.first, args.layers, **(
        {"feedback.interval_layers": args.interval} if args.interval else {}))
    t_plan = time.perf_counter() - t0
    d = Path(tempfile.mkdtemp(prefix="bench_overhead."))
    rec: list = []           # (kind, seq, time, layer, motion s)

    class Timed(LinkedCell):
        def hello(self):
            out = super().hello()
            robot = self.links.robot
            go, wait = robot.go, robot.wait_done

            def timed_go(seq):
                t = time.perf_counter()
                go(seq)
                rec.append(("go", seq, time.perf_counter(), time.perf_counter() - t))

            def timed_wait(seq, timeout_s=None):
                out = wait(seq, timeout_s)
                rec.append(("dn", seq, time.perf_counter()))
                return out
            robot.go, robot.wait_done = timed_go, timed_wait
            return out

        def run_path(self, seq, path, upcoming=None):
            pre = self._preloaded is not None and self._preloaded[0] == seq
            rec.append(("path", seq, path.layer, path.duration_s, pre))
            return super().run_path(seq, path, upcoming)

        def _preload(self, upcoming, *, streaming=False):
            super()._preload(upcoming, streaming=streaming)
            rec.append(("preloaded", None, time.perf_counter()))

    # the cell in its own process, as icefab build --virtual runs it (in this process its
    # physics would hold the runner's GIL)
    save_trajectories(motion, d / "t.npz")
    (d / "job.toml").write_text(to_toml(job), encoding="utf-8")
    start_virtual_cell(d / "cell", d / "job.toml", d / "t.npz")
    journal = Journal.create(d / "journal.sqlite", {"digests": {}})
    try:
        endpoints = load_endpoints(d / "cell")
        t1 = time.perf_counter()
        bmod.Runner(d, motion, job, journal, lambda: Timed(endpoints, job)).run()
        wall = time.perf_counter() - t1
    finally:
        shutdown_virtual_cell(d / "cell")
    # one row per path: layer, motion, GO time, preload end (None), DN time
    paths, cur = [], None
    for r in rec:
        if r[0] == "path":
            cur = {"seq": r[1], "layer": r[2], "motion": r[3], "pre": None,
                   "preloaded": r[4]}
            paths.append(cur)
        elif r[0] == "go":
            cur["go"], cur["go_s"] = r[2], r[3]
        elif r[0] == "preloaded":
            cur["pre"] = r[2]
        elif r[0] == "dn":
            cur["dn"] = r[2]
    waits_in, waits_first, first_pre, go_first = [], [], [], []
    for a, b in zip(paths, paths[1:]):
        if b["layer"] == a["layer"] and a["pre"] is not None:
            ready = (a["pre"] - a["go"]) + (b["go"] - a["dn"])
            waits_in.append(max(0.0, ready - a["motion"]))
        else:
            waits_first.append(b["go"] - a["dn"])
            first_pre.append(b["preloaded"])
            go_first.append(b["go_s"])
    motion_s = float(sum(p["motion"] for p in paths))
    w_in, w_first = float(sum(waits_in)), float(sum(waits_first))
    print(json.dumps({
        "layers": [int(lm.index) for lm in motion.layers], "paths": len(paths),
        "planning_s": round(t_plan, 1), "build_wall_s": round(wall, 1),
        "motion_s": round(motion_s, 1),
        "robot_waits_within_layers_s": round(w_in, 3),
        "paths_that_wait": int(sum(1 for w in waits_in if w > 0)),
        "largest_wait_within_s": round(max(waits_in, default=0.0), 3),
        "robot_waits_at_layer_starts_s": [round(w, 2) for w in waits_first],
        "layer_first_path_sent_ahead": first_pre,
        # the GO's own round trip: the virtual cell answers it after freezing the layer
        # (the GIL), which a real controller does not do
        "layer_first_go_round_trip_s": [round(w, 2) for w in go_first],
        "robot_wait_fraction_of_motion": round((w_in + w_first) / motion_s, 5),
        "measurement_layers": sorted({m["layer"] for m in journal.measurements()})}))


def main() -> None:
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="what", required=True)
    k = sub.add_parser("kills")
    k.add_argument("--layers", type=int, default=60)
    k.add_argument("--kills", type=int, default=30)
    k.add_argument("--seed", type=int, default=0)
    c = sub.add_parser("cellkills")
    c.add_argument("--layers", type=int, default=60)
    c.add_argument("--kills", type=int, default=5)
    c.add_argument("--gap", type=int, default=200, help="commands done between kills")
    c.add_argument("--time-factor", type=float, default=100.0)
    c.add_argument("--seed", type=int, default=0)
    o = sub.add_parser("overhead")
    o.add_argument("--first", type=int, default=301, help="first bunny layer (0-based)")
    o.add_argument("--layers", type=int, default=4)
    o.add_argument("--interval", type=int, default=0,
                   help="feedback.interval_layers (0: the job's)")
    args = p.parse_args()
    {"kills": kills, "cellkills": cell_kills, "overhead": overhead}[args.what](args)


if __name__ == "__main__":
    main()
