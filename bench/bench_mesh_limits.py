"""Mesh loading of pathological but valid files (issue 10): time must grow linearly.

    python3 bench/bench_mesh_limits.py [--sizes 100000,400000] [--corners 200000]

* a binary STL of N copies of one facet (a vertex of valence 3 N: the edge and duplicate
  passes bucket half-edges by vertex; an insertion sort per bucket made them O(N^2));
* an OBJ with one face of K corners (its fan triangulation shares one vertex among K
  triangles) closed by a cone of K triangles.

Prints seconds per file (the compiled kernels are warmed first on a small file, so the
figures are the loading, not numba's compilation). Run with ``PYTHONPATH`` pointing at
another checkout's ``src`` to measure that version.
"""
from __future__ import annotations

import argparse
import struct
import tempfile
import time
from pathlib import Path

import numpy as np


def identical_facets(path: Path, n: int) -> None:
    rec = np.zeros(n, [("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["v"] = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 5]], np.float32)
    path.write_bytes(b"\0" * 80 + struct.pack("<I", n) + rec.tobytes())


def big_face(path: Path, k: int) -> None:
    t = np.linspace(0, 2 * np.pi, k, endpoint=False)
    ring = np.column_stack([50 * np.cos(t), 50 * np.sin(t), np.zeros(k)])
    lines = [f"v {x:.6f} {y:.6f} {z:g}" for x, y, z in ring] + ["v 0 0 20"]
    # corners listed from vertex 1, so the fan shares the file's lowest vertex index (the
    # one buckets are keyed by): every fan triangle lands in one bucket
    lines.append("f " + " ".join(str(i + 1) for i in range(k)))
    lines += [f"f {(i + 1) % k + 1} {i + 1} {k + 1}" for i in range(k)]
    path.write_text("\n".join(lines) + "\n")


def timed(path: Path) -> tuple[float, int]:
    from icefab.mesh import load_mesh
    t0 = time.perf_counter()
    mesh = load_mesh(path)
    return time.perf_counter() - t0, mesh.n_faces


def main() -> None:
    import logging
    logging.disable(logging.WARNING)  # the duplicate-facet warnings are expected
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="25000,100000,400000")
    ap.add_argument("--corners", default="50000,200000")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        identical_facets(d / "warm.stl", 100)
        big_face(d / "warm.obj", 100)
        timed(d / "warm.stl")
        timed(d / "warm.obj")
        for n in map(int, args.sizes.split(",")):
            identical_facets(d / f"dup{n}.stl", n)
            s, faces = timed(d / f"dup{n}.stl")
            print(f"binary STL, {n} identical facets: {s:.2f} s ({faces} face kept)",
                  flush=True)
        for k in map(int, args.corners.split(",")):
            big_face(d / f"face{k}.obj", k)
            s, faces = timed(d / f"face{k}.obj")
            print(f"OBJ, one face of {k} corners + cone: {s:.2f} s ({faces} faces)",
                  flush=True)


if __name__ == "__main__":
    main()
