"""STL, binary and ASCII: reading (corner soup, welded by the loader) and writing.

* binary STL — one ``np.frombuffer`` with a structured dtype (thesis 3.1.1: "one FREAD
  statement"). A binary STL whose 80-byte header begins with ``solid`` is recognised by its
  size (``84 + 50 n`` bytes) or, when the size does not fit, by non-text bytes after the
  header (``icefab.mesh.load._sniff``).
* ASCII STL — one compiled pass (numba) over the bytes checks the grammar (errors give
  the line) and converts the coordinates (an exact fast path; ``strtod`` via
  ``np.fromstring`` in one call for the long mantissas it leaves), no per-line Python.
  Lines before the first 'solid' or 'facet' line (a comment, or a file without its
  'solid' line) are skipped with a warning.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
from numba import njit

from icefab.atomic import write_atomic
from icefab.core import Mesh
from icefab.errors import MeshError
from icefab.mesh._text import (_E_EOF, _E_NUMBER, _E_TOKEN, _E_VCOUNT, _check_finite_lines,
                               _finish_numbers, _is_number, _line_text, _next_token,
                               _store_number, _tok_eq, lf_line_ends)

log = logging.getLogger(__name__)


STL_DTYPE = np.dtype([("normal", "<f4", (3,)), ("corners", "<f4", (3, 3)),
                       ("attr", "<u2")])


def read_binary(data: bytes, path: Path) -> np.ndarray:
    """Corner coordinates (3 n, 3) float32 of a binary STL, one vectorised read."""
    if len(data) < 84:
        raise MeshError(f"{path}: binary STL shorter than its 84-byte header "
                        f"({len(data)} bytes)")
    n = int.from_bytes(data[80:84], "little")
    if n == 0 and len(data) > 84 and (len(data) - 84) % 50 == 0:
        # some streaming exporters never fill in the count: the size tells it
        n = (len(data) - 84) // 50
        log.warning("%s: binary STL header declares 0 facets; the file size gives %d, "
                    "read those", path, n)
    need = 84 + 50 * n
    if need > len(data):
        raise MeshError(f"{path}: truncated binary STL: the header declares {n} facets "
                        f"({need} bytes) but the file has {len(data)} bytes")
    if need < len(data):
        log.warning("%s: %d bytes after the %d facets declared in the binary STL header "
                    "were ignored", path, len(data) - need, n)
    if n == 0:
        raise MeshError(f"{path}: binary STL with 0 facets")
    rec = np.frombuffer(data, dtype=STL_DTYPE, count=n, offset=84)
    return np.ascontiguousarray(rec["corners"]).reshape(-1, 3)



_KW_SOLID = np.frombuffer(b"solid", np.uint8)
_KW_ENDSOLID = np.frombuffer(b"endsolid", np.uint8)
_KW_FACET = np.frombuffer(b"facet", np.uint8)
_KW_NORMAL = np.frombuffer(b"normal", np.uint8)
_KW_OUTER = np.frombuffer(b"outer", np.uint8)
_KW_LOOP = np.frombuffer(b"loop", np.uint8)
_KW_VERTEX = np.frombuffer(b"vertex", np.uint8)
_KW_ENDLOOP = np.frombuffer(b"endloop", np.uint8)
_KW_ENDFACET = np.frombuffer(b"endfacet", np.uint8)


@njit(cache=True)
def _skip_name(b, i):  # pragma: no cover
    """Index of the end of the 'solid'/'endsolid' line from i: its LF or CR (a name line
    ended by a CR alone swallowed the first facet's line)."""
    n = b.size
    while i < n and b[i] != 10 and b[i] != 13:
        i += 1
    return i


@njit(cache=True)
def _scan_stl_ascii(b):  # pragma: no cover
    """Check the ASCII STL grammar and collect the vertex coordinate tokens.

    Returns (slow_text, values, slow, vlines, err, err_line): ``values`` (3 v,) float64
    coordinates, exact where :func:`_fast_float` could compute them; the other tokens are
    copied to ``slow_text`` (uint8, space separated) and their slots listed in ``slow``;
    ``vlines`` (v,) int64 line of each vertex; an error code with its 1-based line.
    """
    n = b.size
    out = np.empty(n + 1, np.uint8)
    vlines = np.empty(n // 13 + 1, np.int64)
    values = np.empty(3 * (n // 13 + 1), np.float64)
    slow = np.empty(3 * (n // 13 + 1), np.int64)
    ns = 0
    o = 0
    nv = 0
    line = 1
    i = 0
    in_facet = False
    in_loop = False
    fv = 0
    err = 0
    while True:
        s, e, line = _next_token(b, i, line)
        i = e
        if s >= n:
            break
        if _tok_eq(b, s, e, _KW_SOLID) or _tok_eq(b, s, e, _KW_ENDSOLID):
            if in_facet:
                err = _E_TOKEN
                break
            i = _skip_name(b, e)
        elif _tok_eq(b, s, e, _KW_FACET):
            if in_facet:
                err = _E_TOKEN
                break
            s, e, line = _next_token(b, e, line)
            if not _tok_eq(b, s, e, _KW_NORMAL):
                err = _E_TOKEN
                break
            fline = line
            for _ in range(3):
                # any three tokens on the facet's line: the normal is never used, and
                # MSVC-built exporters write a NaN one as -nan(ind) or 1.#QNAN0
                s, e, line = _next_token(b, e, line)
                if s >= n or line != fline:
                    err = _E_NUMBER
                    line = fline  # the facet's line, not the next one's
                    break
            if err:
                break
            i = e
            in_facet = True
            fv = 0
        elif _tok_eq(b, s, e, _KW_OUTER):
            s, e, line = _next_token(b, e, line)
            if not in_facet or in_loop or not _tok_eq(b, s, e, _KW_LOOP):
                err = _E_TOKEN
                break
            in_loop = True
            i = e
        elif _tok_eq(b, s, e, _KW_VERTEX):
            if not in_loop:
                err = _E_TOKEN
                break
            if fv == 3:  # a fourth vertex: report its own line
                err = _E_VCOUNT
                break
            vline = line
            for q3 in range(3):
                s, e, line = _next_token(b, e, line)
                if not _is_number(b, s, e) or line != vline:
                    err = _E_NUMBER
                    break
                ns, o = _store_number(b, s, e, values, 3 * nv + q3, slow, ns, out, o)
            if err:
                break
            vlines[nv] = vline
            nv += 1
            fv += 1
            i = e
        elif _tok_eq(b, s, e, _KW_ENDLOOP):
            if not in_loop:
                err = _E_TOKEN
                break
            in_loop = False
        elif _tok_eq(b, s, e, _KW_ENDFACET):
            if not in_facet or in_loop:
                err = _E_TOKEN
                break
            if fv != 3:
                err = _E_VCOUNT
                break
            in_facet = False
        else:
            err = _E_TOKEN
            break
    if err == 0 and in_facet:
        err = _E_EOF
    return out[:o], values[:3 * nv], slow[:ns], vlines[:nv], err, line if err else 0



_FIRST_KEYWORD = re.compile(rb"(?im)^[ \t]*(solid|facet)\b")
_NOT_NEWLINE = bytes(10 if c == 10 else 32 for c in range(256))  # bytes.translate table


def _skip_preamble(data: bytes, path: Path) -> bytes:
    """``data`` with the lines before its first 'solid' or 'facet' line blanked (their
    newlines kept, so error messages count lines as an editor does).

    Some exporters write a comment line before 'solid', or no 'solid' line at all; the
    grammar has no comments, and the first word of a line that is none of its keywords
    was 'unexpected token'. The skipped lines are logged as a warning."""
    head = data[:64].lstrip()[:5].lower()
    if head in (b"solid", b"facet"):
        return data
    m = _FIRST_KEYWORD.search(data)
    if m is None:
        return data  # the scanner names the first line
    skipped = data[:m.start()]
    first = skipped.strip().split(b"\n", 1)[0][:60].decode("ascii", "replace").strip()
    log.warning("%s: ASCII STL: skipped %d lines before its first 'solid'/'facet' line "
                "(the first reads %r)", path, skipped.count(b"\n"), first)
    return skipped.translate(_NOT_NEWLINE) + data[m.start():]


def _content_end(data: bytes) -> int:
    """Length of ``data`` without its padding: NUL or Ctrl-Z bytes (among whitespace) at
    its end, which some DOS-era and fixed-block writers append after 'endsolid' (they
    were 'unexpected token')."""
    tail = data[-65536:]
    kept = tail.rstrip(b" \t\r\n\0\x1a")
    cut = tail[len(kept):]
    if b"\0" in cut or b"\x1a" in cut:
        return len(data) - len(cut)
    return len(data)


def read_ascii(data: bytes, path: Path) -> np.ndarray:
    """Corner coordinates (3 m, 3) float64 of an ASCII STL (one scan, one conversion).

    Lines end in LF, CRLF or CR alone (classic Mac OS: a CR-only file was 'without
    facets', its lines counted as one)."""
    data = _skip_preamble(lf_line_ends(data), path)
    b = np.frombuffer(data, np.uint8)[:_content_end(data)]
    buf, values, slow, vlines, err, line = _scan_stl_ascii(b)
    if err:
        what = {_E_TOKEN: "unexpected token", _E_NUMBER: "expected three numbers",
                _E_VCOUNT: "a facet must have exactly 3 vertices",
                _E_EOF: "file ends inside a facet (truncated?)"}[err]
        raise MeshError(f"{path}: ASCII STL line {line}: {what} "
                        f"(line reads {_line_text(data, line)!r})")
    if len(vlines) == 0:
        raise MeshError(f"{path}: ASCII STL without facets")
    values = _finish_numbers(buf, values, slow, vlines, 3, path, "ASCII STL")
    corners = values.reshape(-1, 3)
    _check_finite_lines(corners, vlines, path, "ASCII STL")
    return corners



def write_stl(mesh: Mesh, path: str | os.PathLike[str]) -> None:
    """Write a binary STL (float32; via a temporary file renamed into place)."""
    p = Path(path)
    tri = mesh.triangles().astype(np.float32)
    rec = np.zeros(len(tri), dtype=STL_DTYPE)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    rec["normal"] = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    rec["corners"] = tri
    header = (b"binary STL written by icefab " + mesh.name.encode("ascii", "replace"))
    write_atomic(p, header[:80].ljust(80, b" ") + np.uint32(len(tri)).tobytes()
                 + rec.tobytes())
