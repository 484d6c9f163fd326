"""numba's cache of icefab's compiled kernels, kept in step with their sources.

numba caches a kernel beside its source (``__pycache__/*.nbi``, ``*.nbc``) under a hash of
that one source file. A kernel that calls a kernel of another module (``_mtts``'s
``smooth_followed`` calls ``_smooth.smooth_pieces``; the mesh readers call ``mesh._text``)
is compiled with the callee's code inside it, so after an edit of the callee's module
alone (a ``git pull``, a developer's change) its cached code is the old one, and it runs
without a word: the paths stage then smoothed with the new kernel and the motion stage
with the old. :func:`check` removes every cached kernel of the package when any module
that defines one has changed since the cache was made (a stamp of their hashes), before
the first kernel is loaded. It runs at ``import icefab``; reading the sources takes a few
milliseconds. With ``NUMBA_CACHE_DIR`` set the cache is elsewhere and its owner's.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

#: The stamp file, in the package's own ``__pycache__``.
STAMP = "icefab-kernels.sha256"
_MARK = b"cache=True"


def _modules(root: Path) -> list[str]:
    """Every ``.py`` file under ``root``, as sorted paths."""
    found = []
    for folder, dirs, names in os.walk(root):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        found += [os.path.join(folder, n) for n in names if n.endswith(".py")]
    return sorted(found)


def _stats_digest(root: Path, modules: list[str]) -> str:
    """A digest of every module's path, size and modification time: when it is the
    stamp's, no source was touched and none need be read."""
    h = hashlib.sha256()
    for path in modules:
        st = os.stat(path)
        h.update(f"{os.path.relpath(path, root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def sources_digest(root: Path, modules: list[str] | None = None) -> str:
    """SHA-256 over the path and content of every module under ``root`` that caches a
    compiled kernel (its source holds ``cache=True``), in path order."""
    h = hashlib.sha256()
    for path in _modules(root) if modules is None else modules:
        data = Path(path).read_bytes()
        if _MARK in data:
            h.update(os.path.relpath(path, root).encode() + b"\0")
            h.update(hashlib.sha256(data).digest())
    return h.hexdigest()


def check(root: Path | None = None) -> bool:
    """Remove the cached kernels under ``root`` (default: this package) when the stamp in
    ``root/__pycache__`` differs from :func:`sources_digest`, and write the new stamp
    (with the modules' sizes and times, so that an untouched package is checked without
    reading its sources). Returns whether the cache was cleared. Never raises for the
    file system: a read-only installation keeps what numba does with it."""
    if root is None:
        if os.environ.get("NUMBA_CACHE_DIR"):
            return False
        root = Path(__file__).resolve().parent
    try:
        modules = _modules(root)
        stats = _stats_digest(root, modules)
        stamp = root / "__pycache__" / STAMP
        try:
            old = stamp.read_text(encoding="ascii").split()
        except (OSError, UnicodeDecodeError):
            old = []
        if old[1:2] == [stats]:
            return False
        digest = sources_digest(root, modules)
        cleared = old[:1] != [digest]
        if cleared:
            for folder, dirs, names in os.walk(root):
                if os.path.basename(folder) == "__pycache__":
                    for name in names:
                        if name.endswith((".nbi", ".nbc")):
                            Path(folder, name).unlink(missing_ok=True)
        stamp.parent.mkdir(exist_ok=True)
        tmp = stamp.with_name(f"{STAMP}.{os.getpid()}.tmp")
        tmp.write_text(f"{digest}\n{stats}\n", encoding="ascii")
        os.replace(tmp, stamp)
        return cleared
    except OSError:
        return False
