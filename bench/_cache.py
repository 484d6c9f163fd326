"""Derived benchmark inputs (stacks, toolpaths) cached in ``bench/.cache/`` under a key of
the code and mesh that made them.

Building the bunny's stack and toolpaths takes minutes, so the benchmarks keep them. A
cache named by its contents only went stale silently whenever the slicing or paths code
changed, and the figures of a benchmark then described the paths of older code. Here the
file name carries a digest of the icefab modules the stage depends on, of the mesh file
(size and modification time) and of any extra text the caller passes (e.g. the job), so a
change to any of them builds anew; older files of the same stem are removed on writing.
"""
from __future__ import annotations

import hashlib
from pathlib import Path

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache"
SRC = HERE.parent / "src" / "icefab"

# the modules (or packages) whose code decides a stack (slicing) and toolpaths (scaffold +
# paths); tests/test_architecture.py's STAGES says what each may import
SLICING_MODULES = ("config", "core", "stages", "resultfiles", "mesh", "geometry", "slicing")
PATHS_MODULES = SLICING_MODULES + ("parallel", "frames", "regions", "paths", "robots")


def job_key(job, step: str) -> str:
    """The settings of ``job`` that ``step`` and the steps before it read
    (``icefab.stages``): two jobs give the same cache file exactly when they agree there."""
    from icefab.stages import digest
    return digest(job, step)


def cache_path(stem: str, modules: tuple[str, ...], mesh: Path | None = None,
               extra: str = "") -> Path:
    """``bench/.cache/<stem>-<digest>.npz`` for the given icefab modules, mesh and extra."""
    h = hashlib.sha1()
    for name in modules:
        files = (sorted((SRC / name).rglob("*.py")) if (SRC / name).is_dir()
                 else [SRC / f"{name}.py"])
        for f in files:
            h.update(f.read_bytes())
    if mesh is not None:
        st = Path(mesh).stat()
        h.update(f"{Path(mesh).name}:{st.st_size}:{st.st_mtime_ns}".encode())
    h.update(extra.encode())
    return CACHE / f"{stem}-{h.hexdigest()[:12]}.npz"


def drop_stale(path: Path) -> None:
    """Remove the other cache files of ``path``'s stem (made by other code)."""
    stem = path.stem.rsplit("-", 1)[0]
    for old in path.parent.glob(f"{stem}-*.npz"):
        if old != path and old.stem.rsplit("-", 1)[0] == stem:
            old.unlink(missing_ok=True)
