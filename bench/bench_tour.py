"""Travel between a layer's paths: nearest neighbour against nearest neighbour + 2-opt
(``icefab._tour``), on the 300 mm bunny (issue 15).

    python3 bench/bench_tour.py [--layers 24]

Slices the bunny as ``icefab slice`` does (origin (340, 0), stroke 400 mm), adds the
scaffold, and plans the paths of ``--layers`` evenly spread layers twice: with the
nearest-neighbour order alone (the peer: today's order before this change) and with 2-opt
after it. Per variant: travel length, the MTTS time of the travel moves and of the whole
layers (``icefab.motion.plan_toolpaths``, jerk on, default limits), the time to plan the
paths; the robot's rest stops per layer (where every trajectory and every PATHSPLIT
piece starts: travel moves, path starts, corner splits inside paths); and a lower bound
of the travel (in every set of one material and role, every
path but one is entered at best from the nearest other path's end or start vertex).
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).parent))

from _report import evenly_spread, rest_stops  # noqa: E402


def _stack():
    from meshes import big_mesh

    from icefab.config import Job
    from icefab.mesh import prepare_parts
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh

    job = Job().replace(**{"cell.ee_origin_mm": (340.0, 0.0), "cell.stroke_mm": 400.0})
    mesh = prepare_parts(job.replace(**{"parts.files": [str(big_mesh("bunny"))]}))
    return add_scaffold(slice_mesh(mesh, job), job), job


def _lower_bound(lp) -> float:
    """Sum over the layer's sets (consecutive paths of one material and role) of: every
    path but the one entered first is entered at best from the nearest other path."""
    total = 0.0
    groups: dict = {}
    for p in lp.paths:
        if p.role != "travel":
            groups.setdefault((p.material, p.role), []).append(p)
    for paths in groups.values():
        if len(paths) < 2:
            continue
        pts, owner = [], []
        for k, p in enumerate(paths):
            # a closed path may be entered at any vertex here (a superset of the
            # planner's candidates, so the bound stays a bound)
            q = p.points if p.closed else p.points[[0, -1]]
            pts.append(q)
            owner.append(np.full(len(q), k))
        P, O = np.concatenate(pts), np.concatenate(owner)
        tree = cKDTree(P)
        best = np.full(len(paths), np.inf)
        k = min(len(P), 32)
        while True:
            d, idx = tree.query(P, k=k)
            other = O[idx] != O[:, None]
            dd = np.where(other, d, np.inf).min(axis=1)
            np.minimum.at(best, O, dd)
            if np.isfinite(best).all() or k >= len(P):
                break
            k = min(len(P), 4 * k)
        total += float(best.sum() - best.max())
    return total


def _run(stack, job, picks, improve: bool) -> dict:
    from icefab import _tour
    from icefab import paths as paths_mod
    from icefab.core import Stack
    from icefab.motion import plan_toolpaths

    saved = _tour.improve
    if not improve:
        _tour.improve = lambda items, start, candidates, **kw: (list(items), start)
    try:
        sub = Stack(layers=tuple(stack.layers[i] for i in picks), job=stack.job,
                    layer_thickness=stack.layer_thickness, warnings=stack.warnings)
        t0 = time.perf_counter()
        tp = paths_mod.plan_paths(sub, job)
        t_paths = time.perf_counter() - t0
    finally:
        _tour.improve = saved
    motion = plan_toolpaths(tp, job)
    travel_s = sum(float(t.duration) for lm in motion.layers for t in lm.trajectories
                   if t.path is None or t.path.role == "travel")
    stops = rest_stops(t for lm in motion.layers for t in lm.trajectories)
    return {"travel_mm": sum(p.length for lp in tp.layers for p in lp.paths
                             if p.role == "travel"),
            "travel_moves": sum(1 for lp in tp.layers for p in lp.paths
                                if p.role == "travel"),
            "travel_s": travel_s, "layers_s": float(motion.duration),
            "paths_s": t_paths, "bound_mm": sum(_lower_bound(lp) for lp in tp.layers),
            "stops_per_layer": {k: v / len(picks) for k, v in stops.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=24)
    args = ap.parse_args()
    t0 = time.perf_counter()
    stack, job = _stack()
    n = len(stack.layers)
    picks = evenly_spread(n, args.layers)
    print(f"bunny: {n} layers, {len(picks)} picked; sliced in "
          f"{time.perf_counter() - t0:.0f} s", flush=True)
    nn = _run(stack, job, picks, improve=False)
    opt = _run(stack, job, picks, improve=True)
    rows = [("travel length (m)", nn["travel_mm"] / 1000, opt["travel_mm"] / 1000),
            ("lower bound of the travel (m)", nn["bound_mm"] / 1000, opt["bound_mm"] / 1000),
            ("travel moves", nn["travel_moves"], opt["travel_moves"]),
            ("MTTS time of the travel moves (h)", nn["travel_s"] / 3600,
             opt["travel_s"] / 3600),
            ("MTTS time of the layers (h)", nn["layers_s"] / 3600, opt["layers_s"] / 3600),
            ("plan_paths wall time (s)", nn["paths_s"], opt["paths_s"])]
    rows += [(f"rest stops per layer: {k}", nn["stops_per_layer"][k],
              opt["stops_per_layer"][k]) for k in nn["stops_per_layer"]]
    print(f"{platform.machine()}, Python {platform.python_version()}; layers {picks}")
    print("| figure | nearest neighbour | + 2-opt | ratio |")
    print("| --- | --- | --- | --- |")
    for name, a, b in rows:
        print(f"| {name} | {a:,.3f} | {b:,.3f} | {b / a if a else float('nan'):.3f} |")
    print(json.dumps({"nn": nn, "opt": opt, "layers": picks}))


if __name__ == "__main__":
    main()
