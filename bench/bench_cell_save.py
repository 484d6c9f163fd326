"""What the virtual cell writes after every path: its surface saved by pieces, beside the
whole surface rewritten after every path (the way before, run side by side as the peer).

    python3 bench/bench_cell_save.py [--paths 462] [--segments 92] [--grid 640x480]

One synthetic layer of the 300 mm bunny's size (the long-build soak's figures, BENCHMARKS
"Long builds": 462 paths a layer, 2-3 KB of pulse log a path, about 92 pulses each; the
surface at ``simulation.grid_mm`` = 0.5 mm over 320 x 240 mm): each path's drop segments
go into the layer's liquid as :meth:`icefab.cell.world.World.deposit_path` leaves them,
then the world is saved, as :class:`icefab.cell.virtual.VirtualCell` does after every
path; the layer then freezes. Prints the time a save takes at the layer's start, middle
and end, and the bytes written over the layer, for both ways, and their ratio.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _segments(rng: np.random.Generator, n: int) -> tuple:
    """One path's drop segments and chord midpoints, shaped as deposit_path makes them."""
    a = rng.uniform(0, 300, (n, 2))
    return (a, a + 0.4, rng.uniform(0.01, 0.1, n), np.full(n, 0.5), np.zeros(n, np.int8),
            rng.normal(size=(n, 2)), rng.normal(size=(n, 2)), np.zeros(n),
            rng.uniform(0, 300, (n // 3, 2)))


def run_layer(folder: Path, whole: bool, paths: int, segments: int,
              shape: tuple[int, int]) -> dict:
    """Save after each of ``paths`` paths; ``whole``: the surface rewritten every time."""
    from icefab import Job
    from icefab.cell.world import World

    w = World(folder, Job(), origin=(0.0, 0.0), shape=shape, spacing=0.5)
    rng = np.random.default_rng(0)
    p = w.pending
    p.layer = 0
    times, written = [], 0
    for _ in range(paths):
        a, b, vol, hw, mat, n0, n1, ext, mid = _segments(rng, segments)
        for lst, arr in zip((p.a, p.b, p.vol, p.hw, p.mat, p.n0, p.n1, p.ext, p.mid),
                            (a, b, vol, hw, mat, n0, n1, ext, mid)):
            lst.append(arr)
        w.last_done += 1
        if whole:
            w._surface_changed = True
        before = {f.name: f.stat().st_mtime_ns for f in folder.iterdir()}
        t0 = time.perf_counter()
        w.save()
        times.append(time.perf_counter() - t0)
        written += sum(f.stat().st_size for f in folder.iterdir()
                       if before.get(f.name) != f.stat().st_mtime_ns)
    t0 = time.perf_counter()
    w.freeze()
    w.save()
    freeze_s = time.perf_counter() - t0
    k = len(times)
    return {"start_ms": 1e3 * float(np.median(times[:10])),
            "middle_ms": 1e3 * float(np.median(times[k // 2 - 5:k // 2 + 5])),
            "end_ms": 1e3 * float(np.median(times[-10:])),
            "layer_s": float(sum(times)), "written_mb": written / 1e6,
            "freeze_s": freeze_s}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--paths", type=int, default=462)
    ap.add_argument("--segments", type=int, default=92)
    ap.add_argument("--grid", default="640x480", help="nodes, NXxNY (0.5 mm apart)")
    args = ap.parse_args(argv)
    nx, ny = (int(v) for v in args.grid.split("x"))
    print(f"{os.uname().machine}, {os.cpu_count()} cores, Python {sys.version.split()[0]}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"one layer: {args.paths} paths of {args.segments} drop segments, grid {nx} x {ny}")
    rows = {}
    for name, whole in (("pieces (icefab)", False), ("whole surface (peer)", True)):
        with tempfile.TemporaryDirectory(prefix="cellsave-") as tmp:
            rows[name] = run_layer(Path(tmp), whole, args.paths, args.segments, (ny, nx))
    print(f"{'':24} {'save at start':>14} {'middle':>9} {'end':>9} {'layer':>9} "
          f"{'written':>10}")
    for name, r in rows.items():
        print(f"{name:24} {r['start_ms']:11.1f} ms {r['middle_ms']:6.1f} ms "
              f"{r['end_ms']:6.1f} ms {r['layer_s']:7.2f} s {r['written_mb']:7.1f} MB")
    a, b = rows["pieces (icefab)"], rows["whole surface (peer)"]
    print(f"ratio icefab / peer: layer time {a['layer_s'] / b['layer_s']:.3f}, bytes "
          f"{a['written_mb'] / b['written_mb']:.4f}; the layer's freeze and its save "
          f"{a['freeze_s']:.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
