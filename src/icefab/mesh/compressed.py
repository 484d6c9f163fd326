"""Gzip-compressed mesh files (``bunny.obj.gz``, ``part.stl.gz``), recognised by content.

A file whose first two bytes are the gzip magic ``1f 8b`` is decompressed before its format
is sniffed, so every format :mod:`icefab.mesh.load` reads can also be read compressed. The
decompressed size is bounded (:data:`MAX_DECOMPRESSED_BYTES`): a few kilobytes of gzip can
expand to gigabytes (a "zip bomb"), so decompression stops, and the file is refused, as soon
as the output passes the limit, before it is held in memory. Concatenated gzip members
(``cat a.gz b.gz``) are read as one stream, as ``gunzip`` does.
"""

from __future__ import annotations

import zlib
from pathlib import Path

from icefab.errors import MeshError

#: Largest decompressed mesh, bytes: the same bound as an uncompressed mesh file (a binary
#: STL of 1 GiB holds 21 million facets, 20 times the largest test mesh).
MAX_DECOMPRESSED_BYTES = 1 << 30

GZIP_MAGIC = b"\x1f\x8b"
_CHUNK = 1 << 20


def is_gzip(data: bytes) -> bool:
    """True when ``data`` starts with the gzip magic bytes."""
    return data[:2] == GZIP_MAGIC


def gunzip(data: bytes, path: Path, limit: int | None = None) -> bytes:
    """The decompressed bytes of the gzip file ``data`` (read from ``path``).

    limit: largest decompressed size, bytes (default :data:`MAX_DECOMPRESSED_BYTES`). Raises :class:`MeshError` naming ``path`` for a
    corrupt or truncated gzip stream and for output larger than ``limit`` (checked while
    decompressing, in 1 MiB steps, so a bomb never reaches memory).
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
                    raise MeshError(f"{path}: gzip-compressed mesh expands to more than "
                                    f"{limit / (1 << 20):.0f} MiB (the limit for mesh "
                                    f"files, icefab.mesh.compressed.MAX_DECOMPRESSED_BYTES)")
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
