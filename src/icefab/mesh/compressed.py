"""Compressed mesh files (``bunny.obj.gz``, ``part.stl.xz``, ``part.ply.bz2``) by content.

A file that starts with the magic bytes of gzip (``1f 8b``), xz (``fd 37 7a 58 5a 00``) or
bzip2 (``BZh`` and a block size digit) is decompressed (:func:`unpack`) before its format is
sniffed, so every format :mod:`icefab.mesh.load` reads can also be read compressed, with the
compressors of Python's standard library. The decompressed size is bounded
(:data:`MAX_DECOMPRESSED_BYTES`): a few kilobytes of compressed data can expand to gigabytes
(a "zip bomb"), so decompression stops, and the file is refused, as soon as the output passes
the limit, before it is held in memory. Concatenated members or streams (``cat a.gz b.gz``,
parallel compressors' output) are read as one file, as ``gunzip``, ``xz -d`` and ``bunzip2``
do. A zip archive is not unpacked (it may hold several files): :mod:`icefab.mesh.load` says
what it is.
"""

from __future__ import annotations

import zlib
from pathlib import Path

from icefab.errors import MeshError

# A Python built without liblzma or libbz2 (pyenv on a machine without their headers) has
# no lzma or bz2 module: every mesh still loads, and only an xz or bzip2 file is refused.
try:
    import lzma
except ImportError:   # pragma: no cover - depends on how Python was built
    lzma = None       # type: ignore[assignment]
try:
    import bz2
except ImportError:   # pragma: no cover
    bz2 = None        # type: ignore[assignment]

#: Largest decompressed mesh, bytes: the same bound as an uncompressed mesh file (a binary
#: STL of 1 GiB holds 21 million facets, 20 times the largest test mesh).
MAX_DECOMPRESSED_BYTES = 1 << 30

GZIP_MAGIC = b"\x1f\x8b"
XZ_MAGIC = b"\xfd7zXZ\x00"
BZIP2_MAGIC = b"BZh"
#: what follows a bzip2 stream's header: a block's magic (pi) or, empty, the end's (sqrt(pi))
_BZIP2_NEXT = (b"1AY&SY", b"\x17rE8P\x90")

#: Largest memory the xz decoder may take, bytes: ``xz -9`` needs 65 MiB; a crafted header
#: could ask for 1.5 GiB before any data is decoded.
XZ_MEMLIMIT = 256 << 20

#: Extensions of the compressed files read; the format hint is the extension under them.
SUFFIXES = (".gz", ".xz", ".bz2")

_CHUNK = 1 << 20


def is_gzip(data: bytes) -> bool:
    """True when ``data`` starts with the gzip magic bytes."""
    return data[:2] == GZIP_MAGIC


def gunzip(data: bytes, path: Path, limit: int | None = None) -> bytes:
    """The decompressed bytes of the gzip file ``data`` (read from ``path``).

    limit: largest decompressed size, bytes (default :data:`MAX_DECOMPRESSED_BYTES`).
    Raises :class:`MeshError` naming ``path`` for a corrupt or truncated gzip stream and
    for output larger than ``limit`` (checked while decompressing, in 1 MiB steps, so a
    bomb never reaches memory).
    """
    limit = MAX_DECOMPRESSED_BYTES if limit is None else limit
    out: list[bytes] = []
    size = 0
    rest = data
    while rest:
        d = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)  # gzip header and trailer
        buf = rest
        try:
            while True:
                chunk = d.decompress(buf, _CHUNK)
                size += len(chunk)
                if size > limit:
                    raise MeshError(_too_large(path, "gzip", limit))
                out.append(chunk)
                buf = d.unconsumed_tail
                if d.eof or not (buf or chunk):
                    break
        except zlib.error as exc:
            raise MeshError(f"{path}: corrupt gzip data ({exc}); expected a gzip-compressed "
                            f"STL, PLY or OBJ file") from None
        if not d.eof:
            raise MeshError(f"{path}: truncated gzip data (the stream ends before its "
                            f"end marker, after {size} decompressed bytes)")
        rest = d.unused_data.lstrip(b"\0")  # padding between members, as gunzip allows
        if rest and not is_gzip(rest):
            raise MeshError(f"{path}: {len(rest)} bytes of trailing garbage after the gzip "
                            f"data")
    return b"".join(out)


def _too_large(path: Path, kind: str, limit: int) -> str:
    """The message for a compressed file whose output passes ``limit`` bytes."""
    return (f"{path}: {kind}-compressed mesh expands to more than {limit / (1 << 20):.0f} MiB "
            "(the limit for mesh files, icefab.mesh.compressed.MAX_DECOMPRESSED_BYTES)")


def is_bzip2(data: bytes) -> bool:
    """True when ``data`` starts with a bzip2 stream: ``BZh``, a block size digit and a block
    or end magic (10 bytes: ``BZh`` alone could start a binary STL's free header)."""
    return (data[:3] == BZIP2_MAGIC and b"1" <= data[3:4] <= b"9"
            and data[4:10] in _BZIP2_NEXT)


def _new_xz():
    return lzma.LZMADecompressor(lzma.FORMAT_XZ, memlimit=XZ_MEMLIMIT)


def _new_bzip2():
    return bz2.BZ2Decompressor()


#: kind -> (magic test, new decompressor, standard-library module, command that unpacks)
#: of the compressors sharing the ``decompress(data, max_length)`` / ``needs_input`` /
#: ``eof`` interface
_STREAMS = {"xz": (lambda d: d[:6] == XZ_MAGIC, _new_xz, "lzma", "xz -d"),
            "bzip2": (is_bzip2, _new_bzip2, "bz2", "bunzip2")}


def _decompressor(kind: str, path: Path):
    """A new decompressor for ``kind``; MeshError when this Python lacks its module."""
    _, new, module, command = _STREAMS[kind]
    if globals()[module] is None:
        raise MeshError(f"{path}: {kind}-compressed, and this Python was built without its "
                        f"{module} module: decompress the file first ({command})")
    return new()


def kind(data: bytes) -> str | None:
    """The compression of ``data`` by its magic bytes: 'gzip', 'xz', 'bzip2' or None."""
    if is_gzip(data):
        return "gzip"
    return next((k for k, (magic, *_) in _STREAMS.items() if magic(data)), None)


def unpack(data: bytes, path: Path, limit: int | None = None) -> bytes:
    """``data`` decompressed when it is gzip, xz or bzip2 data (by its magic bytes), else
    ``data`` itself. Errors as :func:`gunzip`."""
    found = kind(data)
    if found is None:
        return data
    if found == "gzip":
        return gunzip(data, path, limit)
    return _inflate(data, path, found, MAX_DECOMPRESSED_BYTES if limit is None else limit)


def _inflate(data: bytes, path: Path, kind: str, limit: int) -> bytes:
    """The decompressed bytes of the xz or bzip2 file ``data``, streams concatenated (what
    :func:`gunzip` does for gzip, through the interface lzma and bz2 share)."""
    magic = _STREAMS[kind][0]
    broken = (OSError, EOFError, ValueError) + ((lzma.LZMAError,) if lzma else ())
    out: list[bytes] = []
    size = 0
    rest = data
    while rest:
        d = _decompressor(kind, path)
        buf = rest
        try:
            while not d.eof:
                chunk = d.decompress(buf, _CHUNK)  # at most 1 MiB: a bomb never reaches memory
                buf = b""
                size += len(chunk)
                if size > limit:
                    raise MeshError(_too_large(path, kind, limit))
                out.append(chunk)
                if d.needs_input and not d.eof:
                    break  # all input read, no end of stream
        except MeshError:
            raise     # too large: a ValueError too, and it was called corrupt (a tester's)
        except broken as exc:
            raise MeshError(f"{path}: corrupt {kind} data ({exc}); expected a "
                            f"{kind}-compressed STL, PLY or OBJ file") from None
        if not d.eof:
            raise MeshError(f"{path}: truncated {kind} data (the stream ends before its "
                            f"end marker, after {size} decompressed bytes)")
        rest = d.unused_data.lstrip(b"\0")  # xz's stream padding is zero bytes
        if rest and not magic(rest):
            raise MeshError(f"{path}: {len(rest)} bytes of trailing garbage after the {kind} "
                            "data")
    return b"".join(out)
