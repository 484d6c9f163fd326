"""What smooth contours buy the motion (issue 16): MTTS build time with the slicer's path
filter (the default) against local cubic B-spline contours (``slicing.fit_contours``), on
a faceted CAD part and the 300 mm bunny. One command:

    python3 bench/bench_fitting.py [--bunny-every K] [--meshes fandisk,bunny]

* fandisk (tests/data/meshes/fandisk.obj.gz, 12 946 facets, scaled x20: a 97 x 105 x 54 mm
  CAD part with sharp edges and large flat facets), every layer;
* the 1 M-facet bunny at 300 mm (``bench/meshes.py``; end-effector origin (340, 0) as in
  bench_motion.py; ``cell.stroke_mm`` 400: it is taller than the Cobra's 210 mm), every K-th layer of the full stack and scaffold (paths and MTTS of
  those layers; the whole build's time is K times theirs, an estimate said as such).

Per case: MTTS time (jerk on, default limits) in total and on boundary paths, the
speed-bound floor (path length / speed, thesis 4.2, the same paths), contour points per
layer, and the largest distance of the contours from the exact section (the unfiltered
slice, by shapely's Hausdorff distance) over a sample of layers. CPU time and the load
average are printed: the machine is shared.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "src"))

import shapely  # noqa: E402

from icefab.config import job_from_dict  # noqa: E402
from icefab.core import Stack  # noqa: E402
from icefab.mesh import prepare_parts  # noqa: E402
from icefab.motion import plan_toolpaths  # noqa: E402
from icefab.paths import estimate_build_time, plan_paths  # noqa: E402
from icefab.regions import add_scaffold  # noqa: E402
from icefab.slicing import slice_mesh  # noqa: E402

MESHES = HERE.parent / "tests" / "data" / "meshes"


def case_job(mesh: str, fit: bool, extra: dict | None = None, smoothing: float | None = None):
    if mesh == "fandisk":
        parts = {"files": [str(MESHES / "fandisk.obj.gz")], "scale": [20.0, 20.0, 20.0]}
        cell = {}
    else:
        from meshes import big_mesh
        parts = {"files": [str(big_mesh("bunny"))]}
        # 300 mm is taller than the Cobra's 210 mm stroke: a taller cell of the same robot
        cell = {"ee_origin_mm": [340.0, 0.0], "stroke_mm": 400.0}
    data = {"parts": parts, "cell": cell,
            "slicing": {"fit_contours": fit, **(extra or {})}}
    if smoothing is not None:
        data["motion"] = {"smoothing_tolerance_mm": smoothing}
    return job_from_dict(data)


def deviation(stack: Stack, exact: Stack, every: int) -> float:
    """Largest Hausdorff distance (mm) between a layer's contours and the exact section's,
    over every ``every``-th layer (shapely)."""
    worst = 0.0
    for k in range(0, len(stack), every):
        a = shapely.MultiLineString([np.vstack([r, r[:1]]) for r in stack[k].part.rings])
        b = shapely.MultiLineString([np.vstack([r, r[:1]]) for r in exact[k].part.rings])
        if a.is_empty or b.is_empty:
            continue
        worst = max(worst, shapely.hausdorff_distance(a, b, densify=0.05))
    return worst


def run_case(mesh: str, every: int, smoothing: float | None) -> list[dict]:
    rows = []
    exact_job = case_job(mesh, False, {"min_point_spacing_mm": 0.0})
    placed = prepare_parts(exact_job)
    exact = slice_mesh(placed, exact_job)
    for fit in (False, True):
        job = case_job(mesh, fit, smoothing=smoothing)
        c0, t0 = time.process_time(), time.perf_counter()
        stack = slice_mesh(placed, job)
        t_slice = time.perf_counter() - t0
        dev = deviation(stack, exact, max(1, len(stack) // 40))
        full = add_scaffold(stack, job)
        ks = list(range(0, len(full), every))
        sub = dataclasses.replace(full, layers=tuple(full.layers[k] for k in ks))
        tp = plan_paths(sub, job)
        motion = plan_toolpaths(tp, job)
        _, floor = estimate_build_time(tp, job)
        boundary = sum(t.duration for lm in motion.layers for t in lm.trajectories
                       if t.path is not None and t.path.role == "boundary")
        rows.append({
            "mesh": mesh, "contours": "B-spline fit" if fit else "path filter",
            "layers": f"{len(ks)} of {len(full)}", "scale": every,
            "points/layer": sum(L.part.n_points for L in stack) / max(len(stack), 1),
            "deviation": dev, "slice_s": t_slice,
            "mtts_h": motion.duration * every / 3600.0,
            "boundary_h": boundary * every / 3600.0,
            "floor_h": floor * every / 3600.0,
            "cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--meshes", default="fandisk,bunny")
    ap.add_argument("--bunny-every", type=int, default=20)
    ap.add_argument("--motion-smoothing", type=float, default=None, metavar="MM",
                    help="motion.smoothing_tolerance_mm for both cases (default: the job's "
                         "0.02 mm; 0 shows what the fit does where the paths are not "
                         "smoothed again)")
    args = ap.parse_args()
    print(f"# {platform.node()} {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, {time.strftime('%Y-%m-%d %H:%M')}, load "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    rows = []
    for mesh in args.meshes.split(","):
        rows += run_case(mesh, args.bunny_every if mesh == "bunny" else 1,
                         args.motion_smoothing)
    if args.motion_smoothing is not None:
        print(f"# motion.smoothing_tolerance_mm = {args.motion_smoothing:g}")
    print("| part | contours | layers planned | points/layer | deviation from exact (mm) | "
          "MTTS build (h) | of which boundaries (h) | length/speed floor (h) | "
          "CPU s | wall s |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        est = " (x%d)" % r["scale"] if r["scale"] > 1 else ""
        print(f"| {r['mesh']} | {r['contours']} | {r['layers']} | {r['points/layer']:.0f} | "
              f"{r['deviation']:.3f} | {r['mtts_h']:.3f}{est} | {r['boundary_h']:.3f} | "
              f"{r['floor_h']:.3f} | {r['cpu_s']:.0f} | {r['wall_s']:.0f} |")
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        a, b = [r for r in rows if r["mesh"] == mesh]
        print(f"{mesh}: MTTS with fitted contours {b['mtts_h'] / a['mtts_h']:.3f} x the "
              f"filter's ({(1 - b['mtts_h'] / a['mtts_h']) * 100:+.1f} % time saved), "
              f"boundaries {b['boundary_h'] / a['boundary_h']:.3f} x")
    print(f"# load after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
