"""Large benchmark meshes (~1 M facets, 300 mm tall), built once and cached.

``big_mesh(name) -> pathlib.Path`` returns a binary STL in ``bench/.cache/`` (gitignored):

* ``"rocker-arm"``: tests/data/meshes/rocker-arm.obj.gz (closed, with holes), midpoint-
  subdivided three times (20 088 -> 1 285 632 facets; midpoint subdivision keeps a closed
  mesh closed), scaled to 300 mm tall.
* ``"bunny"``: tests/data/meshes/stanford-bunny.obj.gz (a scan, open at its base, with
  holes), turned so its up axis (y) is z, subdivided twice (69 451 -> 1 111 216 facets),
  scaled to 300 mm tall.

Both stand on z = 0, centred on x = y = 0. Built with trimesh (only here, not in icefab)
from the gzip-compressed meshes that ship with the repository (tests/data/meshes/README.md).
Run ``python3 bench/meshes.py`` to build both and print their sizes.
"""
from __future__ import annotations

import gzip
import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache"
SOURCE_DIR = HERE.parent / "tests" / "data" / "meshes"
HEIGHT_MM = 300.0

# name -> (source file, subdivisions, rotation taking the source's up axis to z)
SOURCES = {
    "rocker-arm": ("rocker-arm.obj.gz", 3, None),
    "bunny": ("stanford-bunny.obj.gz", 2, "y-up"),
}


def _build(name: str, path: Path) -> None:
    import trimesh

    src, n_sub, up = SOURCES[name]
    with gzip.open(SOURCE_DIR / src) as f:
        tm = trimesh.load(f, file_type="obj", force="mesh", process=True)
    if up == "y-up":
        tm.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    for _ in range(n_sub):
        tm = tm.subdivide()
    lo, hi = tm.bounds
    tm.apply_translation(-np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]))
    tm.apply_scale(HEIGHT_MM / (hi[2] - lo[2]))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(trimesh.exchange.stl.export_stl(tm))
    os.replace(tmp, path)


def big_mesh(name: str) -> Path:
    """Path to the cached binary STL of benchmark mesh ``name`` ("bunny", "rocker-arm")."""
    if name not in SOURCES:
        raise KeyError(f"unknown benchmark mesh {name!r}: expected one of {', '.join(SOURCES)}")
    path = CACHE / f"{name}-{HEIGHT_MM:.0f}mm.stl"
    if not path.exists():
        _build(name, path)
    return path


if __name__ == "__main__":
    for n in (sys.argv[1:] or SOURCES):
        p = big_mesh(n)
        n_facets = (p.stat().st_size - 84) // 50
        print(f"{n}: {p} ({n_facets} facets, {p.stat().st_size / 1e6:.1f} MB)")
