"""Benchmark: closing the open bunny's holes in 3D before slicing (issue 11).

One command: ``python3 bench/bench_repair.py [--no-write] [--meshfix-repair]``.

On the 1.1 M-facet open bunny of ``bench/meshes.py`` (300 mm tall) it measures, in this
process, after a warm-up:

* ``icefab.mesh.holes.close_holes`` (boundary loops triangulated by manifold3d), best of 3;
* the peers on the same mesh: pymeshfix (MeshFix) ``PyTMesh.fill_small_boundaries`` (all
  boundaries, refined patches; load + fill + return), trimesh's ``fill_holes``, and with
  ``--meshfix-repair`` ``MeshFix.repair`` (also removes self-intersections; ~2 min);
* slicing at 0.25 mm (default job, filter off for the areas): the open mesh with its chains
  closed per layer (``slicing.open_contours = "close"``, as before issue 11), the mesh
  closed by icefab, the mesh filled by pymeshfix: time, layers lost, open chains, and the
  area effect layer by layer (the "hidden layers": those that cut a hole's patch).

Results are printed and written into the "3D hole closing" section of BENCHMARKS.md
(unless ``--no-write``).
"""
from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _report import write_section  # noqa: E402
from meshes import big_mesh  # noqa: E402

SECTION = "## 3D hole closing before slicing (issue 11)"


@contextlib.contextmanager
def _quiet_fds():
    """MeshFix prints progress from C++: silence fds 1 and 2 while it runs."""
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(null, 1)
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)


def _best(fn, n=3):
    out, times = None, []
    for _ in range(n):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, min(times)


def _slice(mesh, job):
    from icefab.slicing import slice_mesh, slice_report

    t0 = time.perf_counter()
    stack = slice_mesh(mesh, job)
    t = time.perf_counter() - t0
    rep = slice_report(stack)
    return stack, rep, t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--meshfix-repair", action="store_true")
    args = ap.parse_args()

    import icefab
    from icefab.core import Mesh
    from icefab.mesh import check_mesh
    from icefab.mesh.holes import close_holes

    load0 = os.getloadavg()[0]
    mesh = icefab.load_mesh(big_mesh("bunny"))
    before = check_mesh(mesh)
    close_holes(mesh)                                          # warm-up (numba cache)
    (closed, report), t_close = _best(lambda: close_holes(mesh))
    after = check_mesh(closed)

    import pymeshfix
    import trimesh

    def meshfix_fill():
        pt = pymeshfix.PyTMesh()
        with _quiet_fds():
            pt.load_array(mesh.vertices, mesh.faces.astype(np.int32))
            pt.fill_small_boundaries(nbe=0, refine=True)
            v, f = pt.return_arrays()
        return Mesh(v, f.astype(np.int64), "meshfix")

    t0 = time.perf_counter()
    filled = meshfix_fill()
    t_meshfix = time.perf_counter() - t0
    mf_check = check_mesh(filled)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    t0 = time.perf_counter()
    tm.fill_holes()
    t_trimesh = time.perf_counter() - t0
    tm_open = int(check_mesh(Mesh(np.asarray(tm.vertices), np.asarray(tm.faces, np.int64),
                                  "t")).open_edges)
    t_repair = None
    if args.meshfix_repair:
        mf = pymeshfix.MeshFix(mesh.vertices, mesh.faces.astype(np.int32))
        t0 = time.perf_counter()
        with _quiet_fds():
            mf.repair(joincomp=False, remove_smallest_components=False)
        t_repair = time.perf_counter() - t0

    exact = icefab.Job().replace(**{"slicing.min_point_spacing_mm": 0.0,
                                    "slicing.max_filter_deviation_mm": 0.0})
    chord = exact.replace(**{"slicing.open_contours": "close"})
    s_open, r_open, t_open = _slice(mesh, chord)
    s_closed, r_closed, t_sliced = _slice(closed, exact)
    s_mf, r_mf, _ = _slice(filled, exact)
    a_open = np.array([L.part.area for L in s_open])
    a_closed = np.array([L.part.area for L in s_closed])
    a_mf = np.array([L.part.area for L in s_mf])
    d = a_closed - a_open
    rel = np.abs(d) / np.maximum(np.abs(a_open), 1e-9)
    changed = np.flatnonzero(rel > 1e-6)
    d_mf = np.abs(a_closed - a_mf) / np.maximum(np.abs(a_mf), 1e-9)
    mf_changed = np.flatnonzero(d_mf > 1e-6)
    chord_layers = sorted({int(w.split()[1]) for w in s_open.warnings
                           if w.startswith("layer ") and "gap" in w})
    spans = ", ".join(f"{h.span_mm:.1f}" for h in report.holes)
    load1 = os.getloadavg()[0]
    when = dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        SECTION, "",
        f"`python3 bench/bench_repair.py` — {os.cpu_count()}-core {platform.machine()}, "
        f"Python {platform.python_version()}, {when}; load average {load0:.1f} at start, "
        f"{load1:.1f} at the end (the machine is shared: wall-clock times grow with the "
        "load). Mesh: the open bunny of `bench/meshes.py`, "
        f"{len(mesh.faces):,} facets, {before.open_edges} open edges; sliced at 0.25 mm, "
        "filter off.", "",
        "| hole closing | time (s) | result |", "|---|---|---|",
        f"| icefab `close_holes` (boundary loops, manifold3d `triangulate`), best of 3 | "
        f"{t_close:.2f} | {len(report.holes)} holes closed (spans {spans} mm), "
        f"{report.faces_added} faces added, {after.open_edges} open / "
        f"{after.non_manifold_edges} non-manifold / {after.misoriented_edges} misoriented "
        "edges left; vertices unchanged |",
        f"| pymeshfix {pymeshfix.__version__} `PyTMesh.fill_small_boundaries` (load + fill + "
        f"return) | {t_meshfix:.1f} | {mf_check.open_edges} open edges left, "
        f"{len(filled.faces) - len(mesh.faces):+,} faces (refined patches), vertices "
        "renumbered; prints progress on the console |",
        f"| trimesh {trimesh.__version__} `fill_holes` | {t_trimesh:.1f} | {tm_open} open "
        "edges left (fills 3- and 4-edge holes only) |",
    ]
    if t_repair is not None:
        lines.append(f"| pymeshfix `MeshFix.repair` | {t_repair:.1f} | also removes "
                     "self-intersections (changes the surface) |")
    lines += [
        "", "| slicing | slice (s) | layers | lost | open chains | chords > max_gap_mm |",
        "|---|---|---|---|---|---|",
        f"| open, chains closed per layer (`open_contours = \"close\"`, before issue 11) | "
        f"{t_open:.2f} | {len(s_open)} | {len(r_open.empty_layers)} | {r_open.open_chains} | "
        f"{r_open.large_gaps_closed} |",
        f"| closed in 3D first (default) | {t_close:.2f} + {t_sliced:.2f} | {len(s_closed)} | "
        f"{len(r_closed.empty_layers)} | {r_closed.open_chains} | "
        f"{r_closed.large_gaps_closed} |",
        "",
        f"Area effect of the 3D closing against the per-layer chords: {len(changed)} of "
        f"{len(s_open)} layers differ by more than 1e-6 (relative) — the layers that cut a "
        f"hole's patch; the per-layer chords were in {len(chord_layers)} layers. Largest "
        f"difference {np.abs(d).max():.2f} mm² ({100 * rel.max():.2f} % of that layer), "
        f"total {d.sum():+.1f} mm² over the build ({100 * d.sum() / a_open.sum():+.4f} % of "
        f"the summed layer areas). Against the pymeshfix-filled mesh (smooth refined "
        f"patches instead of flat ones): {len(mf_changed)} layers differ by more than 1e-6, "
        f"at most {100 * d_mf.max():.2f} %; elsewhere the two agree to 1e-6.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if not args.no_write:
        write_section(SECTION, text)


if __name__ == "__main__":
    main()
