"""Build time of the 300 mm bunny and a rounded box like Fig. 4-15 (issue 15), beside a
peer job and the speed-bound floor.

    python3 bench/bench_build_time.py [--layers-every K] [--peer SETTING=VALUE ...]

Both parts are planned twice in one run, the default job and the peer (by default the
default job with ``materials.*.variable_width = false``: gap fill in constant-width runs,
icefab before variable-width paths):
``plan_paths`` (timed, 2 workers), then MTTS of every layer (``iter_plan_toolpaths``,
jerk on, default limits) summed without keeping the samples. Per variant:

* MTTS build time, and by role (boundary, fill rings of the fill width or widened from
  it, gap paths of other or variable widths, travel, measurement);
* the speed-bound floor: every path's length over the speed bound MTTS plans it under
  (``motion.path_limits``), i.e. no acceleration at all;
* rest stops per layer by cause: travel moves, path starts, PATHSPLIT corners inside
  paths (every trajectory and every split piece starts and ends at rest, thesis 4.1.1),
  and the joins of continuous tours (``paths.join_tours``: stops not made); tours are
  timed as "boundary tour" / "fill tour"; the corner stops by material and kind of path
  (why they remain: a fill ring's corners over ``motion.smooth_angle_deg`` that its
  smoothing keeps, the tips of the rings of a wedge-shaped pocket);
* unfilled area (the paths stage's own measure, ``LayerPaths.unfilled_mm2``) and the
  lowest coverage of any layer's material region of at least 100 mm^2;
* paths and the ``plan_paths`` wall time;
* on ``--toppra-layers`` evenly spread layers, the whole layer tours (every path and
  travel move, each PATHSPLIT piece from rest to rest) timed by TOPP-RA without jerk (the
  independent planner of ``tests/test_motion_toppra.py``: joint speed and acceleration,
  Cartesian speed and a 64-gon total acceleration bound) beside MTTS with jerk off and on
  on the same layers: how much of the gap to the floor is the jerk bound.

The bunny is sliced as ``icefab slice`` does (origin (340, 0), stroke 400 mm; the stack
cached in ``bench/.cache/``), the box as ``bench_motion.py`` builds it.
"""
from __future__ import annotations

import argparse
import json
from collections import Counter
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parent.parent))  # tests.test_motion_toppra

from _report import evenly_spread, parse_settings, rest_stops  # noqa: E402

BUNNY_EE = (340.0, 0.0)


def _bunny_stack(job, every: int):
    from bench_paths import _stack

    from icefab.core import Stack
    from icefab.regions import add_scaffold

    stack, _ = _stack("bunny")
    stack = add_scaffold(stack, job)
    if every > 1:
        stack = Stack(layers=stack.layers[::every], job=stack.job,
                      layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    return stack


def _is_fill_ring(p, width: float) -> bool:
    """A fill ring of the fill width (constant, or widened where smoothing moved it
    inward: never narrower), not a gap path (centre lines, gap and pocket rings)."""
    if p.widths is None:
        return abs(p.width - width) < 1e-9
    return bool(p.closed and p.widths.min() >= width - 1e-9)


def _coverage(stack, tp) -> float:
    """The lowest 1 - unfilled / region area over every layer's part and scaffold region of
    at least 100 mm^2."""
    from icefab import geometry as geo

    worst = 1.0
    for layer, lp in zip(stack.layers, tp.layers):
        for k, region in enumerate((layer.part, layer.scaffold)):
            a = geo.area(region)
            if a >= 100.0:
                worst = min(worst, 1.0 - lp.unfilled_mm2[k] / a)
    return worst


def _toppra_tours(tp, job, picks) -> dict:
    """TOPP-RA (no jerk) and MTTS (jerk off, on) times of the picked layers' whole tours."""
    from tests.test_motion_toppra import toppra_duration

    from icefab.frames import to_base_frame
    from icefab.motion import path_limits, pathsplit, plan_paths_motion
    from icefab.robots import get_robot

    robot = get_robot(job)
    off = job.replace(**{"motion.jerk_limited": False})
    out = {"toppra_s": 0.0, "mtts_nojerk_s": 0.0, "mtts_s": 0.0, "failed": 0}
    for k in picks:
        lp = tp.layers[k]
        out["mtts_s"] += sum(t.duration for t in plan_paths_motion(lp.paths, job))
        out["mtts_nojerk_s"] += sum(t.duration for t in plan_paths_motion(lp.paths, off))
        for p in lp.paths:
            pts = to_base_frame(p.polyline(), p.tool_name, job)
            if len(pts) < 2:
                continue
            jb = off.replace(**{"motion.speed_mm_s": path_limits(p, off)})
            for piece in pathsplit(pts, jb):
                try:
                    out["toppra_s"] += toppra_duration(piece, jb, robot)
                except Exception:  # noqa: BLE001 - counted and reported
                    out["failed"] += 1
    return out


def measure(stack, job, toppra_layers: int = 0) -> dict:
    from icefab.core import tour_members
    from icefab.motion import iter_plan_toolpaths, path_limits
    from icefab.paths import plan_paths

    plan_paths(type(stack)(layers=stack.layers[:2], job=stack.job,
                           layer_thickness=stack.layer_thickness), job)  # kernels loaded
    t0 = time.perf_counter()
    tp = plan_paths(stack, job)
    t_paths = time.perf_counter() - t0
    by_role: dict[str, float] = {}
    floor = 0.0
    stops: Counter = Counter()
    fill_width = {"part": job.materials.part.fill_width_mm,
                  "scaffold": job.materials.scaffold.fill_width_mm}
    joins = 0
    corners: Counter = Counter()   # why the robot stops: PATHSPLIT corners by kind of path
    for lm in iter_plan_toolpaths(tp, job):
        stops.update(rest_stops(lm.trajectories))
        for t in lm.trajectories:
            p = t.path
            role = "travel" if p is None else p.role
            if p is not None and p.off is not None:   # a continuous tour
                joins += len(tour_members(p)) - 1
                role = f"{role} tour"
            elif role == "fill":
                role = "fill" if _is_fill_ring(p, fill_width[p.material]) else "gap"
            by_role[role] = by_role.get(role, 0.0) + float(t.duration)
            if p is not None:
                floor += p.length / path_limits(p, job)
                if p.role != "travel":
                    corners[f"{p.material} {role}"] += max(len(t.pieces) - 1, 0)
    n = len(tp.layers)
    unfilled = np.array([lp.unfilled_mm2 for lp in tp.layers]).sum(axis=0)
    picks = evenly_spread(n, toppra_layers) if toppra_layers else []
    tours = _toppra_tours(tp, job, picks) if picks else None
    return {"mtts_h": sum(by_role.values()) / 3600.0, "floor_h": floor / 3600.0,
            "by_role_h": {k: v / 3600.0 for k, v in sorted(by_role.items())},
            "stops_per_layer": {k: v / n for k, v in stops.items()},
            "corners_per_layer": {k: v / n for k, v in corners.most_common()},
            "joins_per_layer": joins / n,
            "unfilled_mm2": [float(unfilled[0]), float(unfilled[1])],
            "min_coverage": _coverage(stack, tp), "paths": stops["path starts"], "layers": n,
            "plan_paths_s": t_paths, "toppra_layers": picks, "tours": tours}


def _rows(a: dict, b: dict) -> list[tuple[str, float, float]]:
    rows = [("MTTS build time (h)", a["mtts_h"], b["mtts_h"]),
            ("speed-bound floor (h)", a["floor_h"], b["floor_h"])]
    for k in sorted(set(a["by_role_h"]) | set(b["by_role_h"])):
        rows.append((f"  MTTS of {k} paths (h)", a["by_role_h"].get(k, 0.0),
                     b["by_role_h"].get(k, 0.0)))
    for k in a["stops_per_layer"]:
        rows.append((f"rest stops per layer: {k}", a["stops_per_layer"][k],
                     b["stops_per_layer"][k]))
    ca, cb = a["corners_per_layer"], b["corners_per_layer"]
    for k in sorted(set(ca) | set(cb), key=lambda k: -max(ca.get(k, 0.0), cb.get(k, 0.0))):
        rows.append((f"  corner stops per layer in {k} paths", ca.get(k, 0.0), cb.get(k, 0.0)))
    rows.append(("paths joined into tours per layer (stops saved)", a["joins_per_layer"],
                 b["joins_per_layer"]))
    rows += [("unfilled part / scaffold (mm^2)", a["unfilled_mm2"][0], b["unfilled_mm2"][0]),
             ("", a["unfilled_mm2"][1], b["unfilled_mm2"][1]),
             ("lowest coverage of a region", a["min_coverage"], b["min_coverage"]),
             ("paths (deposition and measurement)", a["paths"], b["paths"]),
             ("plan_paths wall time (s)", a["plan_paths_s"], b["plan_paths_s"])]
    if a["tours"] and b["tours"]:
        where = ", ".join(str(k) for k in b["toppra_layers"])
        for key, label in (("toppra_s", "TOPP-RA, no jerk"), ("mtts_nojerk_s", "MTTS, jerk off"),
                           ("mtts_s", "MTTS, jerk on")):
            rows.append((f"layers {where}: {label} (s)", a["tours"][key], b["tours"][key]))
        rows.append(("  TOPP-RA pieces without a solution", a["tours"]["failed"],
                     b["tours"]["failed"]))
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers-every", type=int, default=1,
                    help="the bunny's every K-th layer only (default: all 1 200)")
    ap.add_argument("--box-height", type=float, default=20.0, help="rounded box height, mm")
    ap.add_argument("--peer", nargs="*", default=None, metavar="SETTING=VALUE",
                    help="the peer job's settings (JSON values); default: "
                         "materials.part.variable_width=false "
                         "materials.scaffold.variable_width=false")
    ap.add_argument("--skip-bunny", action="store_true")
    ap.add_argument("--toppra-layers", type=int, default=1,
                    help="layers of each part whose whole tours TOPP-RA times (0: none)")
    args = ap.parse_args()
    from icefab.config import Job

    peer_settings = parse_settings(args.peer) if args.peer is not None else {
        "materials.part.variable_width": False, "materials.scaffold.variable_width": False}
    print(f"machine: {os.cpu_count()}-core {platform.machine()}, Python "
          f"{platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print(f"peer: {peer_settings}")
    results = {}
    from bench_motion import rounded_box_stack

    parts = [("rounded box like Fig. 4-15", Job(),
              lambda j: rounded_box_stack(j, args.box_height))]
    if not args.skip_bunny:
        bjob = Job().replace(**{"cell.ee_origin_mm": BUNNY_EE, "cell.stroke_mm": 400.0})
        parts.append(("bunny, 300 mm", bjob, lambda j: _bunny_stack(j, args.layers_every)))
    for name, job, make in parts:
        stack = make(job)
        peer = measure(stack, job.replace(**peer_settings), args.toppra_layers)
        mine = measure(stack, job, args.toppra_layers)
        results[name] = {"peer": peer, "default": mine}
        print(f"\n{name}: {mine['layers']} layers")
        print("| figure | peer | default job | ratio |")
        print("| --- | ---: | ---: | ---: |")
        for label, a, b in _rows(peer, mine):
            ratio = f"{b / a:.3f}" if a else ""
            print(f"| {label} | {a:,.3f} | {b:,.3f} | {ratio} |", flush=True)
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
