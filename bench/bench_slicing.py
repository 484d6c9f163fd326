"""Benchmark: mesh import and slicing of two ~1 M-facet parts, 300 mm tall, at 0.25 mm.

One command: ``python3 bench/bench_slicing.py [--no-trimesh] [--no-write]``.

For each mesh of ``bench/meshes.py`` ("bunny": open scan, 1.1 M facets; "rocker-arm":
closed, 1.3 M facets) it measures, each in a fresh child process (so the peak memory is
that of the measured work alone):

* binary STL import (``icefab.load_mesh``), best of 3;
* import + slice + link + filter + nesting (``load_mesh`` + ``slice_mesh`` with the default
  job, 0.25 mm layers), best of 3, with the peak resident memory (``ru_maxrss``) and the
  number of layers lost (empty although the part is there);
* the peers in the same run: trimesh's ``section_multiplane`` on the same cutting heights
  (time, empty layers, and the largest relative area difference of the layers both have),
  and manifold3d's ``slice`` (watertight meshes only).

Results are printed and written into the "Mesh import and slicing" section of
BENCHMARKS.md (unless ``--no-write``).
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from _report import write_section  # noqa: E402
from meshes import big_mesh  # noqa: E402

NAMES = ("bunny", "rocker-arm")
SECTION = "## Mesh import and slicing (issue 2)"


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# --------------------------------------------------------------------------- children


def child_icefab(name: str) -> dict:
    import numpy as np

    import icefab
    from icefab.slicing import slice_report

    path = big_mesh(name)
    # the slicer alone, as measured since issue 2: the bunny's holes closed per layer
    # (consent to long chords); the 3D hole closing before slicing is bench_repair.py's
    job = icefab.Job().replace(**{"slicing.open_contours": "close"})
    # warm up: numba compilation cache, file cache
    tiny = icefab.Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]),
                       np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]), "warm")
    icefab.slice_mesh(tiny, job)
    path.read_bytes()
    t_import = []
    for _ in range(3):
        t0 = time.perf_counter()
        mesh = icefab.load_mesh(path)
        t_import.append(time.perf_counter() - t0)
        del mesh
    t_total = []
    for _ in range(3):
        t0 = time.perf_counter()
        mesh = icefab.load_mesh(path)
        stack = icefab.slice_mesh(mesh, job)
        t_total.append(time.perf_counter() - t0)
    t_slices = []
    for _ in range(3):
        t0 = time.perf_counter()
        icefab.slice_mesh(mesh, job)
        t_slices.append(time.perf_counter() - t0)
    t_slice = min(t_slices)
    rep = slice_report(stack)
    z = [L.z for L in stack]
    # areas without the path filter, to compare with the peers' exact sections
    exact = job.replace(**{"slicing.min_point_spacing_mm": 0.0,
                           "slicing.max_filter_deviation_mm": 0.0})
    areas = [L.part.area for L in icefab.slice_mesh(mesh, exact)]
    return {
        "facets": int(len(mesh.faces)),
        "import_s": min(t_import), "total_s": min(t_total), "slice_s": t_slice,
        "peak_mb": _peak_mb(), "layers": len(stack), "lost": len(rep.empty_layers),
        "segments": rep.segments, "contours": rep.rings, "points": rep.points_after_filter,
        "open_chains": rep.open_chains, "large_gaps": rep.large_gaps_closed,
        "warnings": len(stack.warnings), "z": z, "areas": areas,
        "gap_layers": sorted({int(w.split()[1]) for w in stack.warnings
                              if w.startswith("layer ") and "gap" in w}),
        "threads": int(__import__("numba").get_num_threads()),
    }


def _even_odd_area(rings) -> float:
    import shapely

    region = shapely.Polygon()
    for ring in rings:
        if len(ring) >= 3:
            region = region.symmetric_difference(shapely.Polygon(ring[:, :2]).buffer(0))
    return float(region.area)


def child_trimesh(name: str, z: list[float]) -> dict:
    import numpy as np
    import trimesh

    tm = trimesh.load(big_mesh(name), force="mesh")
    t0 = time.perf_counter()
    secs = tm.section_multiplane(plane_origin=[0, 0, 0], plane_normal=[0, 0, 1], heights=z)
    t = time.perf_counter() - t0
    areas = []
    for s in secs:
        if s is None or len(s.entities) == 0:
            areas.append(0.0)
        else:
            areas.append(_even_odd_area([np.asarray(d) for d in s.discrete]))
    return {"section_s": t, "areas": areas, "empty": int(sum(a <= 0 for a in areas)),
            "peak_mb": _peak_mb()}


def child_manifold(name: str, z: list[float]) -> dict:
    import manifold3d as m3d
    import numpy as np

    import icefab

    mesh = icefab.load_mesh(big_mesh(name))
    t0 = time.perf_counter()
    man = m3d.Manifold(m3d.Mesh(vert_properties=np.asarray(mesh.vertices, np.float32),
                                tri_verts=np.asarray(mesh.faces, np.uint32)))
    if man.status() != m3d.Error.NoError:
        return {"error": str(man.status())}
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    areas = [man.slice(h).area() for h in z]
    t = time.perf_counter() - t0
    return {"build_s": t_build, "slice_s": t, "areas": areas,
            "empty": int(sum(a <= 0 for a in areas))}


def _run_child(kind: str, name: str, z: list[float] | None = None) -> dict:
    cmd = [sys.executable, __file__, "--child", kind, name]
    env = dict(os.environ)
    inp = json.dumps(z) if z is not None else ""
    out = subprocess.run(cmd, input=inp, capture_output=True, text=True, env=env,
                         check=False)
    if out.returncode != 0:
        raise RuntimeError(f"{kind} {name} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------- main


def _max_rel_diff(a: list[float], b: list[float], skip: list[int] = ()) -> float:
    """Largest relative area difference over the layers both have (minus ``skip``)."""
    skip = set(skip)
    pairs = [(x, y) for k, (x, y) in enumerate(zip(a, b)) if x > 0 and y > 0
             and k not in skip]
    if not pairs:
        return float("nan")
    return max(abs(x - y) / y for x, y in pairs)


def _compare(ice: dict, peer: dict) -> str:
    """Layer areas of icefab (unfiltered) against a peer's, in words."""
    a, b, gaps = ice["areas"], peer["areas"], set(ice["gap_layers"])
    diff = [k for k, (x, y) in enumerate(zip(a, b)) if abs(x - y) > 1e-6 * max(x, y, 1e-9)]
    at_gap = [k for k in diff if k in gaps]
    peer_empty = [k for k in diff if k not in gaps and b[k] <= 0 < a[k]]
    other = [k for k in diff if k not in gaps and k not in peer_empty]
    parts = [f"{len(diff)} of {len(a)} layers differ by > 1e-6"]
    if diff:
        parts.append(f"{len(at_gap)} where icefab closed a reported gap, "
                     f"{len(peer_empty)} the peer leaves empty, {len(other)} other")
    parts.append(f"largest difference elsewhere "
                 f"{_max_rel_diff(a, b, sorted(gaps | set(peer_empty))):.1e}")
    return "; ".join(parts)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--no-trimesh", action="store_true", help="skip the slow trimesh peer")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    args = ap.parse_args()
    if args.child:
        kind, name = args.child
        z = json.loads(sys.stdin.read() or "null")
        res = {"icefab": lambda: child_icefab(name), "trimesh": lambda: child_trimesh(name, z),
               "manifold": lambda: child_manifold(name, z)}[kind]()
        print(json.dumps(res))
        return 0

    machine = (f"{os.cpu_count()}-core {platform.processor() or platform.machine()}, "
               f"Python {platform.python_version()}, load average at start "
               f"{os.getloadavg()[0]:.1f} (machine shared with other jobs)")
    date = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    rows = []
    for name in NAMES:
        print(f"[{name}] building/finding the mesh ...", flush=True)
        big_mesh(name)
        print(f"[{name}] icefab import + slice ...", flush=True)
        ice = _run_child("icefab", name)
        print(f"[{name}] {ice['facets']} facets: import {ice['import_s']:.2f} s, import+slice "
              f"{ice['total_s']:.2f} s (slice alone {ice['slice_s']:.2f} s, "
              f"{ice['threads']} threads), peak {ice['peak_mb']:.0f} MB, {ice['layers']} "
              f"layers, lost {ice['lost']}, {ice['contours']} contours, "
              f"{ice['open_chains']} open chains ({ice['large_gaps']} gaps > max_gap_mm "
              f"closed, reported)", flush=True)
        row = {"name": name, "ice": ice}
        print(f"[{name}] manifold3d slice ...", flush=True)
        try:
            man = _run_child("manifold", name, ice["z"])
        except RuntimeError as exc:
            man = {"error": str(exc).splitlines()[0]}
        if "error" in man:
            print(f"[{name}] manifold3d: cannot build a manifold ({man['error']})")
        else:
            print(f"[{name}] manifold3d: {man['slice_s']:.2f} s slicing (+{man['build_s']:.2f} s "
                  f"to build), empty layers {man['empty']}; {_compare(ice, man)}")
        row["man"] = man
        if not args.no_trimesh:
            print(f"[{name}] trimesh section_multiplane (slow) ...", flush=True)
            tri = _run_child("trimesh", name, ice["z"])
            row["tri"] = tri
            print(f"[{name}] trimesh: {tri['section_s']:.1f} s, empty layers {tri['empty']}, "
                  f"ratio trimesh/icefab-slice {tri['section_s'] / ice['slice_s']:.0f}x; "
                  f"{_compare(ice, tri)}", flush=True)
        rows.append(row)
    text = _markdown(rows, machine, date)
    print()
    print(text)
    if not args.no_write:
        write_section(SECTION, text)
        print(f"updated {ROOT / 'BENCHMARKS.md'}")
    return 0


def _markdown(rows: list[dict], machine: str, date: str) -> str:
    lines = [SECTION, "",
             f"`python3 bench/bench_slicing.py` — {machine}; {date}. Meshes from "
             "`bench/meshes.py` (300 mm tall, binary STL), default job (0.25 mm layers, "
             "cut at mid-layer, filter 0.4 mm / 0.05 mm). Times are the best of 3; peak "
             "memory is the child process' maximum resident set. Area differences compare "
             "icefab's unfiltered contours (filter off) with the peer's section.", "",
             "| mesh | facets | import (s) | import + slice + link + filter (s) | slice "
             "alone (s) | peak memory (MB) | layers | lost | contours | open chains "
             "closed (reported) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        i = r["ice"]
        lines.append(f"| {r['name']} | {i['facets']:,} | {i['import_s']:.2f} | "
                     f"{i['total_s']:.2f} | {i['slice_s']:.2f} | {i['peak_mb']:.0f} | "
                     f"{i['layers']} | {i['lost']} | {i['contours']} | {i['open_chains']} |")
    lines += ["", "Peers on the same cutting heights, same run:", "",
              "| mesh | peer | time (s) | ratio peer / icefab slice | empty layers | layer "
              "areas vs icefab (unfiltered) |", "|---|---|---|---|---|---|"]
    for r in rows:
        i = r["ice"]
        m = r.get("man", {})
        if "error" in m:
            lines.append(f"| {r['name']} | manifold3d `slice` | — | — | — | not a manifold "
                         f"({m['error']}) |")
        elif m:
            lines.append(f"| {r['name']} | manifold3d `slice` (+{m['build_s']:.2f} s build) | "
                         f"{m['slice_s']:.2f} | {m['slice_s'] / i['slice_s']:.1f} | "
                         f"{m['empty']} | {_compare(i, m)} |")
        t = r.get("tri")
        if t:
            lines.append(f"| {r['name']} | trimesh `section_multiplane` | "
                         f"{t['section_s']:.1f} | {t['section_s'] / i['slice_s']:.0f} | "
                         f"{t['empty']} | {_compare(i, t)} |")
    lines += ["", "Targets (issue 2): import ≤ 0.5 s, import + slice ≤ 3 s, peak ≤ 2 GB, no "
              "layer lost. For scale (issue 2, same machine): PrusaSlicer's slicing phase "
              "≈ 1.6 s for the bunny (drops 26 of 1200 layers), manifold3d 1.5 s, trimesh "
              "28–32 s (30 layers empty); the thesis needed 13 s for 691 layers on 4 cores.",
              ""]
    return "\n".join(lines)



if __name__ == "__main__":
    sys.exit(main())
