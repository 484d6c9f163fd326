"""Benchmark: scaffold regions, boundaries and concentric fill of a 1 M-facet part.

One command: ``python3 bench/bench_paths.py [--no-peers] [--no-write] [--layers N]``.

The bunny of ``bench/meshes.py`` (1.1 M facets, 300 mm tall) is sliced once with the
default job (0.25 mm layers, 1200 layers; the stack is cached in ``bench/.cache/``, slicing
is not timed here). Then, on ``job.cell.cpus = 2`` (both cores):

* ``add_scaffold``: merged-region scan (sequential), buffer, difference, thin-piece filter
  and the thin-part report (parallel over layers);
* boundaries + concentric fill of both materials (parallel over layers) — with the
  scaffold this is the issue's target (<= 30 s);
* boundaries + concentric fill + gap fill of both materials (``material_paths``: the
  paths the issue's 97 % coverage needs);
* the whole ``plan_paths`` (gap accounting and gap fill, nearest-neighbour order, travel
  and measurement paths).

Peers in the same run, one core each, on the same regions (geometry only, Python loops
alike): the concentric fill chain (boundary + rings until empty, miter joins, 0.05 mm point
filter) and the scaffold Booleans (merged scan, 3.3 mm buffer, difference) with Clipper2
(pyclipr, icefab's choice), Clipper 1 (pyclipper) and GEOS (shapely).

Results are printed and written into the "Scaffold regions, boundaries and fill" section of
BENCHMARKS.md (unless ``--no-write``).
"""
from __future__ import annotations

import argparse
import datetime as dt
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from _cache import SLICING_MODULES, cache_path, drop_stale, job_key  # noqa: E402
from _report import write_section  # noqa: E402
from meshes import big_mesh  # noqa: E402

SECTION = "## Scaffold regions, boundaries and fill (issue 3)"
FILT = 0.05
BUFFER = 3.3


def _stack(name: str):
    from icefab.config import Job
    from icefab.mesh import prepare_parts
    from icefab.slicing import load_stack, save_stack, slice_mesh

    mesh_path = big_mesh(name)
    job = Job()
    cache = cache_path(f"{name}-stack-0.25", SLICING_MODULES, mesh_path, job_key(job, "slice"))
    if cache.exists():
        try:
            return load_stack(cache), None
        except Exception as exc:  # noqa: BLE001 - an unreadable cache is rebuilt
            print(f"rebuilding the stack cache ({exc})")
    # as 'icefab slice' prepares it: placed, and the scan's holes closed in 3D (issue 11;
    # slicing the open scan as it is refuses its open contours)
    # (the placement checks against a cell the 300 mm part fits: taller than the Cobra's
    # 210 mm stroke, and outside joint 1's range at the default origin)
    mesh = prepare_parts(job.replace(**{"parts.files": [str(mesh_path)], "cell.stroke_mm": 400.0,
                                        "cell.ee_origin_mm": (340.0, 0.0)}))
    stack = slice_mesh(mesh, job)
    save_stack(stack, cache)
    drop_stale(cache)
    return stack, mesh.n_faces


def _bounds_and_fill(args):
    """Boundaries + concentric fill of both materials of one layer (the issue's target)."""
    from icefab.paths import boundary_rings, fill_levels

    layer, job = args
    n = 0
    for material, region in (("part", layer.part), ("scaffold", layer.scaffold)):
        mat = job.materials[material]
        b = boundary_rings(region, mat, FILT)
        levels = fill_levels(region, mat, job).levels
        n += sum(len(lv) for lv in b) + sum(len(lv) for lv in levels)
    return n


def _bounds_fill_gaps(args):
    """Boundaries, concentric fill and gap fill of both materials of one layer: the paths
    the issue's 97 % coverage needs (no ordering, travel or measurement paths)."""
    from icefab.paths import material_paths

    layer, job = args
    n = 0
    for material, region in (("part", layer.part), ("scaffold", layer.scaffold)):
        sets, _hook, _gap = material_paths(region, job.materials[material], job, 0, layer.part)
        n += len(sets["boundary"]) + len(sets["fill"])
    return n


# ----------------------------------------------------------------------------- peers


def fill_pyclipr(regions):
    from icefab import geometry as geo
    n = 0
    for reg in regions:
        rings = geo.offset_rings(list(reg.rings), -0.6, FILT)
        n += len(rings)
        rings = geo.offset_rings(rings, -(0.75 + 1.5), FILT)
        while rings:
            n += len(rings)
            rings = geo.offset_rings(rings, -3.0, FILT)
    return n


def fill_pyclipper(regions):
    import pyclipper
    from icefab import geometry as geo
    S = geo.SCALE

    def off(rings, d):
        o = pyclipper.PyclipperOffset(miter_limit=2.0)
        o.AddPaths([np.rint(r * S).astype(np.int64) for r in rings], pyclipper.JT_MITER,
                   pyclipper.ET_CLOSEDPOLYGON)
        out = o.Execute(d * S)
        return geo.simplify([np.asarray(p, dtype=np.float64) / S for p in out], FILT)

    n = 0
    for reg in regions:
        rings = off(list(reg.rings), -0.6)
        n += len(rings)
        rings = off(rings, -(0.75 + 1.5))
        while rings:
            n += len(rings)
            rings = off(rings, -3.0)
    return n


def _shapely_geoms(regions):
    import shapely
    from shapely.geometry import Polygon
    out = []
    for reg in regions:
        polys = [Polygon(p[0], p[1:]) for p in reg.polygons()]
        polys = [q if q.is_valid else shapely.make_valid(q) for q in polys]
        g = shapely.union_all(polys) if polys else Polygon()
        out.append(g)
    return out


def fill_shapely(geoms):
    n = 0
    for g in geoms:
        cur = g.buffer(-0.6, join_style="mitre", mitre_limit=2.0).simplify(FILT)
        n += 1
        cur = cur.buffer(-(0.75 + 1.5), join_style="mitre", mitre_limit=2.0).simplify(FILT)
        while not cur.is_empty:
            n += 1
            cur = cur.buffer(-3.0, join_style="mitre", mitre_limit=2.0).simplify(FILT)
    return n


def scaffold_pyclipr(regions):
    from icefab import geometry as geo
    from icefab.regions import merged_regions
    merged = merged_regions(regions)
    return sum(len(geo.difference(geo.expand(m, BUFFER, FILT), p)) for m, p in zip(merged, regions))


def scaffold_pyclipper(regions):
    import pyclipper
    from icefab import geometry as geo
    S = geo.SCALE
    ints = [[np.rint(r * S).astype(np.int64) for r in reg.rings] for reg in regions]
    merged = [None] * len(ints)
    above: list = []
    for k in range(len(ints) - 1, -1, -1):
        if above and ints[k]:
            c = pyclipper.Pyclipper()
            c.AddPaths(above, pyclipper.PT_SUBJECT, True)
            c.AddPaths(ints[k], pyclipper.PT_CLIP, True)
            above = c.Execute(pyclipper.CT_UNION, pyclipper.PFT_NONZERO, pyclipper.PFT_NONZERO)
        elif ints[k]:
            above = ints[k]
        merged[k] = above
    n = 0
    for m, p in zip(merged, ints):
        if not m:
            continue
        filt = geo.simplify([np.asarray(r, dtype=np.float64) / S for r in m], FILT)
        o = pyclipper.PyclipperOffset(miter_limit=2.0)
        o.AddPaths([np.rint(r * S).astype(np.int64) for r in filt], pyclipper.JT_MITER,
                   pyclipper.ET_CLOSEDPOLYGON)
        grown = geo.simplify([np.asarray(r, dtype=np.float64) / S
                              for r in o.Execute(BUFFER * S)], FILT)
        c = pyclipper.Pyclipper()
        c.AddPaths([np.rint(r * S).astype(np.int64) for r in grown], pyclipper.PT_SUBJECT, True)
        if p:
            c.AddPaths(p, pyclipper.PT_CLIP, True)
        n += len(c.Execute2(pyclipper.CT_DIFFERENCE, pyclipper.PFT_NONZERO,
                            pyclipper.PFT_NONZERO).Childs)
    return n


def scaffold_shapely(geoms):
    from shapely.geometry import Polygon
    merged = [None] * len(geoms)
    above = Polygon()
    for k in range(len(geoms) - 1, -1, -1):
        above = above.union(geoms[k]) if not geoms[k].is_empty else above
        merged[k] = above
    n = 0
    for m, g in zip(merged, geoms):
        grown = m.simplify(FILT).buffer(BUFFER, join_style="mitre", mitre_limit=2.0).simplify(FILT)
        n += not grown.difference(g).is_empty
    return n


# ----------------------------------------------------------------------------- main


def _cpu() -> float:
    """CPU seconds of this process and its (finished) worker processes."""
    import resource
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + c.ru_utime + c.ru_stime


def _timed(fn, *args):
    t0 = time.perf_counter()
    r = fn(*args)
    return time.perf_counter() - t0, r


def _timed_cpu(fn, *args):
    c0 = _cpu()
    t0 = time.perf_counter()
    r = fn(*args)
    return time.perf_counter() - t0, _cpu() - c0, r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-peers", action="store_true", help="skip the peer comparison")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    ap.add_argument("--mesh", default="bunny", help="benchmark mesh (bench/meshes.py)")
    ap.add_argument("--layers", type=int, default=0, help="use only the first N layers")
    args = ap.parse_args()

    from icefab.config import Job
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold, parallel_map
    from icefab.core import Stack

    stack, _ = _stack(args.mesh)
    if args.layers:
        stack = Stack(stack.layers[:args.layers], stack.job, stack.layer_thickness)
    n = len(stack)
    job = Job().replace(**{"cell.cpus": 2})
    # warm up numba caches and the pool machinery on a few layers
    small = Stack(stack.layers[-30:], stack.job, stack.layer_thickness)
    plan_paths(add_scaffold(small, job), job)

    load0 = os.getloadavg()[0]
    t_scaf, c_scaf, scaffolded = _timed_cpu(add_scaffold, stack, job)
    print(f"add_scaffold (2 cores): {t_scaf:.2f} s ({c_scaf:.1f} CPU s)", flush=True)
    t_fill, c_fill, _ = _timed_cpu(parallel_map, _bounds_and_fill,
                                   [(layer, job) for layer in scaffolded.layers], job)
    print(f"boundaries + concentric fill, both materials (2 cores): {t_fill:.2f} s "
          f"({c_fill:.1f} CPU s)", flush=True)
    t_gaps, c_gaps, _ = _timed_cpu(parallel_map, _bounds_fill_gaps,
                                   [(layer, job) for layer in scaffolded.layers], job)
    print(f"boundaries + concentric fill + gap fill, both materials (2 cores): {t_gaps:.2f} s "
          f"({c_gaps:.1f} CPU s)", flush=True)
    t_plan, c_plan, tp = _timed_cpu(plan_paths, scaffolded, job)
    n_paths = sum(len(lp.paths) for lp in tp)
    unf = np.array([lp.unfilled_mm2 for lp in tp]).sum(axis=0)
    print(f"plan_paths (2 cores): {t_plan:.2f} s ({c_plan:.1f} CPU s), {n_paths} paths",
          flush=True)
    load1 = os.getloadavg()[0]
    res = {"layers": n, "scaffold_s": t_scaf, "fill_s": t_fill, "plan_s": t_plan,
           "scaffold_cpu": c_scaf, "fill_cpu": c_fill, "plan_cpu": c_plan,
           "gaps_s": t_gaps, "gaps_cpu": c_gaps,
           "paths": n_paths, "unfilled": unf,
           "points": sum(L.part.n_points for L in stack),
           "scaffold_area": sum(L.scaffold.area for L in scaffolded),
           "load": (load0, load1)}

    peers = {}
    if not args.no_peers:
        parts = [L.part for L in stack]
        geoms = _shapely_geoms(parts)
        for label, fn, data in (("fill", fill_pyclipr, parts), ("fill", fill_pyclipper, parts),
                                ("fill", fill_shapely, geoms),
                                ("scaffold", scaffold_pyclipr, parts),
                                ("scaffold", scaffold_pyclipper, parts),
                                ("scaffold", scaffold_shapely, geoms)):
            t, _ = _timed(fn, data)
            lib = fn.__name__.split("_")[1]
            peers[(label, lib)] = t
            print(f"peer {label} {lib} (1 core): {t:.2f} s", flush=True)
    res["peers"] = peers

    machine = (f"2-core {platform.processor() or platform.machine()}, Python "
               f"{platform.python_version()}")
    text = _markdown(res, machine, dt.date.today().isoformat(), args.mesh)
    print(text)
    if not args.no_write and not args.layers:
        write_section(SECTION, text)
        print(f"updated {ROOT / 'BENCHMARKS.md'}")
    return 0


def _markdown(r: dict, machine: str, date: str, mesh: str) -> str:
    target = r["scaffold_s"] + r["fill_s"]
    lines = [SECTION, "",
             f"`python3 bench/bench_paths.py` — {machine}; {date}; load average "
             f"{r['load'][0]:.1f} → {r['load'][1]:.1f} during the run (the machine is "
             f"shared; wall-clock times grow with the load). Mesh: {mesh} from "
             f"`bench/meshes.py`, 1.1 M facets, 300 mm tall, sliced at 0.25 mm "
             f"({r['layers']} layers, {r['points']:,} contour points; slicing not timed). "
             "Default job: buffer 3.3 mm, path width 1.5 mm, fill width 3.0 mm, initial "
             "offsets 0.6/1.2 mm, 0.05 mm point filter, `cell.cpus = 2`.", "",
             "| stage (both cores) | wall (s) | CPU (s, all processes) |", "|---|---|---|",
             f"| `add_scaffold`: merged scan, buffer, difference, thin-piece filter, thin-part "
             f"report | {r['scaffold_s']:.1f} | {r['scaffold_cpu']:.1f} |",
             f"| boundaries + concentric fill of part and scaffold | {r['fill_s']:.1f} | "
             f"{r['fill_cpu']:.1f} |",
             f"| **target: scaffold + boundaries + concentric fill** (≤ 30 s) | "
             f"**{target:.1f}** | {r['scaffold_cpu'] + r['fill_cpu']:.1f} |",
             f"| boundaries + concentric fill + gap fill of part and scaffold (the paths "
             f"the 97 % coverage needs) | {r['gaps_s']:.1f} | {r['gaps_cpu']:.1f} |",
             f"| scaffold + boundaries + concentric fill + gap fill | "
             f"{r['scaffold_s'] + r['gaps_s']:.1f} | "
             f"{r['scaffold_cpu'] + r['gaps_cpu']:.1f} |",
             f"| whole `plan_paths` (also gap accounting and gap fill, order, travel, "
             f"measurement paths; {r['paths']:,} paths) | {r['plan_s']:.1f} | "
             f"{r['plan_cpu']:.1f} |", "",
             "CPU seconds do not depend on the other jobs on the machine: on two free cores "
             "the wall time is about half of them (plus the sequential merged scan).", "",
             "Gap fill (rings with room, pockets, centre lines of the strips left, as wide as "
             "the strip) is most of `plan_paths`' time and paths: before it (thin-gap rings "
             "only, this benchmark on 2026-11-22 before commit 7546cfb) the unfilled area "
             "was part 5,388 + scaffold 20,693 mm².", "",
             f"Unfilled area reported: part {r['unfilled'][0]:.0f} mm², scaffold "
             f"{r['unfilled'][1]:.0f} mm² over all layers. The thesis needed 244 + 192 + 832 s "
             "(RPSCAF + BUFFERF bounds + BUFFERF fill) on 4 cores for a comparable 1 M-facet "
             "statue (Table 3-5).", ""]
    p = r.get("peers") or {}
    if p:
        lines += ["Polygon libraries on the same regions, one core each, same run (the "
                  "choice for `icefab.geometry`):", "",
                  "| task | Clipper2 (`pyclipr`, used) | Clipper 1 (`pyclipper`) | GEOS "
                  "(`shapely`) |", "|---|---|---|---|"]
        for task, label in (("fill", "part boundary + concentric rings until empty"),
                            ("scaffold", "merged scan + 3.3 mm buffer + difference")):
            a, b, c = p[(task, "pyclipr")], p[(task, "pyclipper")], p[(task, "shapely")]
            lines.append(f"| {label} | {a:.1f} | {b:.1f} ({b / a:.1f}×) | {c:.1f} "
                         f"({c / a:.1f}×) |")
        lines += ["", "Ratios are peer / Clipper2. All three use miter joins (limit 2) and "
                  "filter ring points (0.05 mm) after each offset; pyclipper needs integer "
                  "lists in and out, which is part of its cost from numpy. Round joins "
                  "multiply vertex counts and time many-fold, so they are never used.", ""]
    return "\n".join(lines)



if __name__ == "__main__":
    sys.exit(main())
