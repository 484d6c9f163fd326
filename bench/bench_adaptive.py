"""Adaptive layers (issue 16): layers saved against uniform slicing of the same cusp bound,
and the cusp height kept. One command:

    python3 bench/bench_adaptive.py [--cusp MM] [--min MM] [--max MM] [--plan]

For a sphere (R 15 mm, 256 segments: the analytic case), the fandisk (x20, a CAD part:
97 x 105 x 54 mm) and the 300 mm bunny (``bench/meshes.py``; stroke 400 mm): adaptive
slicing (``slicing.cusp_height_mm``) against uniform layers thin enough for the same bound
everywhere (C_max / max |n_z| over the part, within the range: C_max wherever a part has a
flat or a near-horizontal wall); layer counts, the largest cusp t_k max|n_z| of any layer,
slicing time. ``--plan``: also scaffold, paths and MTTS build time of the fandisk both ways
(a paste cell's case: the thickness range defaults to 0.1-1.0 mm).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "src"))

from icefab.config import job_from_dict  # noqa: E402
from icefab.core import Mesh  # noqa: E402
from icefab.mesh import prepare_parts  # noqa: E402
from icefab.motion import plan_toolpaths  # noqa: E402
from icefab.paths import plan_paths  # noqa: E402
from icefab.regions import add_scaffold  # noqa: E402
from icefab.slicing import slice_mesh, slice_report  # noqa: E402

MESHES = HERE.parent / "tests" / "data" / "meshes"


def sphere() -> Mesh:
    import manifold3d as m3
    m = m3.Manifold.sphere(15.0, 256).translate([0.0, 0.0, 15.0]).to_mesh()
    return Mesh(np.asarray(m.vert_properties)[:, :3].astype(np.float64),
                np.asarray(m.tri_verts).astype(np.int64), "sphere R15")


def part(name: str, slicing: dict):
    cell: dict = {}
    if name == "fandisk":
        parts = {"files": [str(MESHES / "fandisk.obj.gz")], "scale": [20.0, 20.0, 20.0]}
    elif name == "bunny":
        from meshes import big_mesh
        parts = {"files": [str(big_mesh("bunny"))]}
        cell = {"ee_origin_mm": [340.0, 0.0], "stroke_mm": 400.0}
    else:
        parts = {}
    job = job_from_dict({"parts": parts, "cell": cell, "slicing": slicing})
    mesh = sphere() if name == "sphere" else prepare_parts(job)
    return mesh, job


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cusp", type=float, default=0.1)
    ap.add_argument("--min", type=float, default=0.05)
    ap.add_argument("--max", type=float, default=1.0)
    ap.add_argument("--parts", default="sphere,fandisk,bunny")
    ap.add_argument("--plan", action="store_true")
    args = ap.parse_args()
    print(f"# {platform.node()} {platform.machine()}, {os.cpu_count()} cores, "
          f"{time.strftime('%Y-%m-%d %H:%M')}, load "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}; cusp {args.cusp} mm, "
          f"thickness {args.min}-{args.max} mm")
    print("| part | adaptive layers | uniform layers, same bound | saved | largest cusp (mm) "
          "| thickness range (mm) | slicing s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    plan_rows = []
    for name in args.parts.split(","):
        adaptive = {"cusp_height_mm": args.cusp, "min_layer_thickness_mm": args.min,
                    "max_layer_thickness_mm": args.max}
        mesh, job = part(name, adaptive)
        t0 = time.perf_counter()
        stack = slice_mesh(mesh, job)
        dt = time.perf_counter() - t0
        rep = slice_report(stack)
        t = stack.thicknesses
        print(f"| {name} | {len(stack)} | {rep.uniform_layers} | "
              f"{100 * (1 - len(stack) / rep.uniform_layers):.0f} % | {rep.max_cusp_mm:.4f} | "
              f"{t.min():.3f}-{t.max():.3f} | {dt:.1f} |")
        if args.plan and name == "fandisk":
            for label, sl in (("adaptive", adaptive),
                              ("uniform", {"layer_thickness_mm": (
                                  mesh.bounds[1, 2] - mesh.bounds[0, 2]) / rep.uniform_layers})):
                _, jb = part(name, sl)
                st = add_scaffold(slice_mesh(mesh, jb), jb)
                mo = plan_toolpaths(plan_paths(st, jb), jb)
                plan_rows.append((name, label, len(st), mo.duration / 3600.0))
    for name, label, n, hours in plan_rows:
        print(f"{name} {label}: {n} layers, MTTS build {hours:.3f} h")
    print(f"# load after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
