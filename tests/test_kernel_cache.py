"""numba's cache of the kernels follows their sources (icefab._kernel_cache): a kernel
compiled with another module's kernel inside it kept that module's old code after an edit
of it alone (found changing _smooth.smooth_pieces: _mtts.smooth_followed ran the old)."""

import os
import subprocess
import sys
from pathlib import Path

from icefab import _kernel_cache


def _tree(root: Path) -> dict[str, Path]:
    (root / "sub" / "__pycache__").mkdir(parents=True)
    (root / "__pycache__").mkdir()
    files = {"callee": root / "callee.py", "caller": root / "sub" / "caller.py",
             "plain": root / "plain.py"}
    files["callee"].write_text("@njit(cache=True)\ndef f(x):\n    return x\n")
    files["caller"].write_text("@njit(cache=True)\ndef g(x):\n    return f(x)\n")
    files["plain"].write_text("def h():\n    pass\n")
    return files


def _cached(root: Path) -> list[str]:
    return sorted(p.name for p in root.rglob("*.nb[ic]"))


def _fill_cache(root: Path) -> None:
    for name in ("callee.f-1.py311.nbi", "callee.f-1.py311.1.nbc"):
        (root / "__pycache__" / name).write_bytes(b"x")
    (root / "sub" / "__pycache__" / "caller.g-1.py311.nbi").write_bytes(b"x")
    (root / "__pycache__" / "plain.cpython-311.pyc").write_bytes(b"x")


def test_an_edited_kernel_module_clears_every_cached_kernel(tmp_path):
    files = _tree(tmp_path)
    _fill_cache(tmp_path)
    assert _kernel_cache.check(tmp_path)            # no stamp yet: the cache is unknown
    assert _cached(tmp_path) == []
    assert (tmp_path / "__pycache__" / "plain.cpython-311.pyc").exists()   # not numba's
    _fill_cache(tmp_path)
    assert not _kernel_cache.check(tmp_path)        # nothing changed
    assert len(_cached(tmp_path)) == 3
    # a module without a cached kernel, touched or edited: the cache stays
    files["plain"].write_text("def h():\n    return 1\n")
    assert not _kernel_cache.check(tmp_path)
    assert len(_cached(tmp_path)) == 3
    # touched with the same content (a checkout): the cache stays
    os.utime(files["callee"], ns=(1, 1))
    assert not _kernel_cache.check(tmp_path)
    assert len(_cached(tmp_path)) == 3
    # the callee edited alone: the caller's cache (in another folder) goes too
    files["callee"].write_text("@njit(cache=True)\ndef f(x):\n    return 2 * x\n")
    assert _kernel_cache.check(tmp_path)
    assert _cached(tmp_path) == []
    # a new kernel module
    _fill_cache(tmp_path)
    (tmp_path / "new.py").write_text("@njit(cache=True)\ndef k():\n    pass\n")
    assert _kernel_cache.check(tmp_path)
    assert _cached(tmp_path) == []


def test_an_unwritable_cache_is_left_to_numba(tmp_path):
    _tree(tmp_path)
    (tmp_path / "__pycache__").rmdir()
    (tmp_path / "__pycache__").write_text("not a folder")
    assert not _kernel_cache.check(tmp_path)        # no exception


def test_import_icefab_keeps_the_stamp_of_its_own_kernels():
    root = Path(_kernel_cache.__file__).resolve().parent
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    subprocess.run([sys.executable, "-c", "import icefab"], check=True, env=env)
    stamp = (root / "__pycache__" / _kernel_cache.STAMP).read_text().split()
    assert stamp[0] == _kernel_cache.sources_digest(root)
