"""Atomic, durable file writing: a result file is either complete or absent.

Every writer of a result (stacks, toolpaths, trajectories, valve programs, pictures)
writes to a temporary file in the target's folder and renames it over the target, so an
interrupted or failed write never leaves a half-written file behind. The data are flushed
to disk (``fsync``) before the rename and the folder after it: without the first, a power
cut shortly after the rename can leave an empty file under the target's name (the rename
reaches the disk before the data on ext4/xfs with delayed allocation); without the second,
the rename itself may be lost.

Temporary files and folders are created with mode 0666 / 0777 and the process umask
applied by the kernel (as ``open()`` and ``mkdir()`` do), so results get the user's normal
modes; nothing here reads or changes the umask (``os.umask`` can only be read by setting
it, which races with other threads creating files).
"""

from __future__ import annotations

import os
import re
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

_ATTEMPTS = 100


def _temp_name(target: Path, suffix: str) -> Path:
    return target.parent / f".{target.name}.{secrets.token_hex(4)}{suffix}"


def remove_temps(folder: str | os.PathLike, suffix: str = ".tmp") -> int:
    """Remove the temporary files :func:`make_temp_file` left in ``folder`` (a process
    killed between writing one and renaming it into place); only for a folder whose
    writers are known to be gone (a build's, its lock held). Returns how many."""
    pattern = re.compile(rf"\..+\.[0-9a-f]{{8}}{re.escape(suffix)}")
    gone = 0
    for f in Path(folder).iterdir():
        if pattern.fullmatch(f.name) and f.is_file():
            f.unlink(missing_ok=True)
            gone += 1
    return gone


def make_temp_file(target: Path, suffix: str = ".tmp") -> Path:
    """A new, empty file beside ``target`` (hidden, random name), mode 0666 & ~umask."""
    for _ in range(_ATTEMPTS):
        tmp = _temp_name(target, suffix)
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return tmp
    raise FileExistsError(f"{target.parent}: no free temporary name for {target.name}")


def make_temp_dir(parent: Path, prefix: str) -> Path:
    """A new folder ``parent/PREFIX<random>``, mode 0777 & ~umask."""
    for _ in range(_ATTEMPTS):
        tmp = parent / f"{prefix}{secrets.token_hex(4)}"
        try:
            os.mkdir(tmp, 0o777)
        except FileExistsError:
            continue
        return tmp
    raise FileExistsError(f"{parent}: no free temporary folder name {prefix}*")


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's data, or a folder's entries, to disk. Folders on file systems that
    cannot sync a folder (EINVAL) are skipped; a file must sync."""
    p = Path(path)
    if p.is_dir():
        fd = os.open(p, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
        try:
            os.fsync(fd)
        except OSError as exc:  # pragma: no cover - e.g. some network file systems
            if exc.errno not in (22, 95):  # EINVAL, EOPNOTSUPP
                raise
        finally:
            os.close(fd)
        return
    fd = os.open(p, os.O_RDONLY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_tree(root: str | os.PathLike) -> None:
    """fsync every file and folder under ``root`` (children before their folder)."""
    for folder, dirs, files in os.walk(root, topdown=False):
        for name in files:
            p = os.path.join(folder, name)
            if not os.path.islink(p):
                fsync_path(p)
        fsync_path(folder)


def replace_durably(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """``os.replace(src, dst)`` with ``src``'s data on disk before and the folder's entry
    after the rename (the folder of ``dst``, and of ``src`` when it differs)."""
    fsync_tree(src) if os.path.isdir(src) else fsync_path(src)
    os.replace(src, dst)
    fsync_path(Path(dst).parent)
    if Path(src).parent.resolve() != Path(dst).parent.resolve():
        fsync_path(Path(src).parent)


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ".tmp") -> Iterator[Path]:
    """A temporary path to write to; it replaces ``path`` when the block succeeds.

    ``suffix`` keeps libraries that insist on an extension (``np.savez`` adds ``.npz``)
    writing exactly to the yielded path. The file is fsynced before the rename and the
    folder after it; on failure the temporary file goes and ``path`` is untouched.
    """
    target = Path(path)
    tmp = make_temp_file(target, suffix)
    try:
        yield tmp
        replace_durably(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


def write_atomic(path: str | os.PathLike, data: bytes | str) -> Path:
    """Write bytes (or UTF-8 text) to ``path`` atomically and durably."""
    with atomic_path(path) as tmp:
        if isinstance(data, str):
            tmp.write_text(data, encoding="utf-8")
        else:
            tmp.write_bytes(data)
    return Path(path)
