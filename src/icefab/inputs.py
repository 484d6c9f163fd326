"""Reading an input file safely: a regular file of bounded size, or one line saying why not.

Every file a user names (meshes, job files, calibration tables) is read through
:func:`read_input`, which refuses before reading anything:

* a path that is not a regular file: a folder, ``/dev/zero`` (endless bytes), a FIFO
  (would block forever waiting for a writer), a socket or other device;
* a file larger than the limit for its kind (:data:`MAX_BYTES`), since every loader holds
  the whole file in memory and derives arrays several times its size from it.

The FIFO case needs care: ``open()`` on a FIFO blocks until a writer appears, so the file
is checked with ``os.stat`` first and opened with ``O_NONBLOCK``, then checked again on
the open descriptor (``fstat``), which also closes the gap where the path is swapped
between the two checks.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from icefab.errors import IcefabError

#: Largest file, bytes, each kind of input may be. A binary STL of 1 GiB holds 21 million
#: facets (20 times the largest test mesh); a job or control file is a page of text; a
#: valve calibration table or a jig a few hundred rows; the laser's calibration scans
#: (``icefab calibrate laser``: a row per sample, ~40 bytes) a few hundred thousand.
MAX_BYTES: dict[str, int] = {
    "mesh": 1 << 30,
    "job": 1 << 20,
    "calibration": 1 << 20,
    "scans": 64 << 20,
}


def _describe(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def _mib(n: int) -> str:
    return f"{n / (1 << 20):.0f} MiB" if n >= 1 << 20 else f"{n} bytes"


def check_input(path: str | os.PathLike, kind: str, error: type[IcefabError],
                what: str | None = None) -> int:
    """The size, bytes, of the regular file ``path``; ``error`` naming the file otherwise.

    kind: a key of :data:`MAX_BYTES`; what: how the message names the file (default
    ``kind + " file"``).
    """
    what = what or f"{kind} file"
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise error(f"{p}: {what} not found") from None
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    return _check_stat(st, p, kind, error, what)


def _check_stat(st: os.stat_result, p: Path, kind: str, error: type[IcefabError],
                what: str) -> int:
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{p}: {what} is {_describe(st.st_mode)}, not a regular file")
    limit = MAX_BYTES[kind]
    if st.st_size > limit:
        # in bytes when that is what tells them apart ("1 MiB, larger than the 1 MiB")
        size = (_mib(st.st_size) if _mib(st.st_size) != _mib(limit)
                else f"{st.st_size} bytes")
        exact = f" ({limit} bytes)" if limit >= 1 << 20 else ""
        raise error(f"{p}: {what} is {size}, larger than the {_mib(limit)}{exact} limit for "
                    f"{kind} files (icefab.inputs.MAX_BYTES)")
    return int(st.st_size)


def read_input(path: str | os.PathLike, kind: str, error: type[IcefabError],
               what: str | None = None) -> bytes:
    """The bytes of the regular file ``path`` (at most ``MAX_BYTES[kind]``).

    Raises ``error`` (an :class:`IcefabError` subclass) with one line naming the file when
    it is missing, unreadable, not a regular file or too large.
    """
    what = what or f"{kind} file"
    p = Path(path)
    check_input(p, kind, error, what)
    try:
        fd = os.open(p, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        size = _check_stat(os.fstat(fd), p, kind, error, what)
        with os.fdopen(fd, "rb", closefd=False) as fh:
            data = fh.read(size + 1)
    except OSError as exc:
        raise error(f"{p}: cannot read {what} ({exc.strerror or exc})") from None
    finally:
        os.close(fd)
    if len(data) > MAX_BYTES[kind]:  # grew while being read
        raise error(f"{p}: {what} grew past the {_mib(MAX_BYTES[kind])} limit while read")
    return data


def read_input_text(path: str | os.PathLike, kind: str, error: type[IcefabError],
                    what: str | None = None) -> str:
    """:func:`read_input` decoded as UTF-8 (``error`` naming the file when it is not)."""
    data = read_input(path, kind, error, what)
    try:
        # a byte-order mark (Windows editors write one) is not part of the text: with it a
        # control file's first entry read as no number and a TOML file as invalid
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: {what or kind + ' file'} is not UTF-8 text (byte "
                    f"{exc.start})") from None
