"""OBJ: ``v`` and ``f`` lines (``f 1/2/3 4//5 -1``), negative indices, polygons
fan-triangulated, scanned in one compiled pass like ASCII STL; other lines ignored.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
from numba import njit

from icefab.errors import MeshError
from icefab.mesh._text import (_E_FEW, _E_INDEX, _E_NUMBER, _check_finite_lines, _finish_numbers,
                               _is_number, _is_ws, _line_text, _store_number,
                               lf_line_ends)
from icefab.mesh.topology import polygon_triangles

log = logging.getLogger(__name__)


@njit(cache=True)
def _is_blank(c):  # pragma: no cover
    """Whitespace within a line: every byte :func:`_is_ws` stops a token at except the
    newline (a vertical tab or form feed between numbers used to stop the token scan
    without being skipped: an endless loop, found by bench/fuzz_inputs.py mesh:2338)."""
    return c == 32 or (9 <= c <= 13 and c != 10)


@njit(cache=True)
def _scan_obj(b):  # pragma: no cover
    """Scan an OBJ: vertex coordinate tokens and face indices.

    Returns (slow_text, values, slow, vlines, fidx, fcount, flines, n_short, err,
    err_line): ``values`` the first three numbers of every ``v`` line (slots in ``slow``
    still to be converted from ``slow_text``, see :func:`_finish_numbers`); ``fidx``
    (k,) int64 0-based vertex indices of all faces (negative indices resolved against
    the vertices read so far), ``fcount`` (f,) corners per face, ``flines`` (f,) line of each face; ``n_short``
    faces with fewer than 3 corners were skipped.
    """
    n = b.size
    out = np.empty(n + 1, np.uint8)
    vlines = np.empty(n // 6 + 1, np.int64)
    values = np.empty(3 * (n // 6 + 1), np.float64)
    slow = np.empty(3 * (n // 6 + 1), np.int64)
    ns = 0
    fidx = np.empty(n // 2 + 1, np.int64)
    fcount = np.empty(n // 6 + 1, np.int64)
    flines = np.empty(n // 6 + 1, np.int64)
    o = 0
    nv = 0
    nk = 0
    nf = 0
    n_short = 0
    err = 0
    i = 0
    line = 1
    while i < n:
        # start of a line: skip blanks (not newlines)
        while i < n and _is_blank(b[i]):
            i += 1
        if i >= n:
            break
        if b[i] == 10:
            line += 1
            i += 1
            continue
        s = i
        while i < n and not _is_ws(b[i]):
            i += 1
        e = i
        if e - s == 1 and b[s] == 118:  # 'v'
            k = 0
            while True:
                while i < n and _is_blank(b[i]):
                    i += 1
                if i >= n or b[i] == 10 or b[i] == 35:
                    break
                s = i
                while i < n and not _is_ws(b[i]):
                    i += 1
                if k < 3:
                    if not _is_number(b, s, i):
                        err = _E_NUMBER
                        break
                    ns, o = _store_number(b, s, i, values, 3 * nv + k, slow, ns, out, o)
                k += 1
            if err == 0 and k < 3:
                err = _E_FEW
            if err:
                break
            vlines[nv] = line
            nv += 1
        elif e - s == 1 and b[s] == 102:  # 'f'
            k = 0
            while True:
                while i < n and _is_blank(b[i]):
                    i += 1
                if i >= n or b[i] == 10 or b[i] == 35:
                    break
                neg = False
                if b[i] == 45:
                    neg = True
                    i += 1
                elif b[i] == 43:
                    i += 1
                val = 0
                nd = 0
                while i < n and 48 <= b[i] <= 57 and nd < 18:
                    val = val * 10 + (b[i] - 48)
                    i += 1
                    nd += 1
                if nd == 0 or (i < n and not _is_ws(b[i]) and b[i] != 47):
                    err = _E_NUMBER
                    break
                while i < n and not _is_ws(b[i]):  # '/vt/vn' part
                    i += 1
                idx = nv - val if neg else val - 1
                if val == 0 or idx < 0:
                    err = _E_INDEX
                    break
                fidx[nk] = idx
                nk += 1
                k += 1
            if err:
                break
            if k < 3:
                nk -= k
                n_short += 1
            else:
                fcount[nf] = k
                flines[nf] = line
                nf += 1
        else:
            pass  # vt, vn, o, g, s, usemtl, comments...: not needed
        while i < n and b[i] != 10:  # rest of the line
            i += 1
    return (out[:o], values[:3 * nv], slow[:ns], vlines[:nv], fidx[:nk], fcount[:nf],
            flines[:nf], n_short, err, line if err else 0)


#: What an error on the line a file ends inside adds: the file looks cut short (as an
#: ASCII STL that ends inside a facet, a PLY short of its elements).
_CUT = ", and the file ends inside this line (truncated?)"


def _cut_line(data: bytes) -> int:
    """The 1-based number of the last line when the file ends inside it, an element's
    line (not blank, not a comment) without its line end; 0 otherwise. A file need not
    end in a line end: an error there, or a face too short, says it may be truncated."""
    tail = data[data.rfind(b"\n") + 1:]
    if not tail.strip() or tail.lstrip().startswith(b"#"):
        return 0
    return data.count(b"\n") + 1


def _is_short_face(data: bytes, line: int) -> bool:
    """Whether 1-based ``line`` of ``data`` is an 'f' line of fewer than 3 corners (the
    scan skips such faces)."""
    words = data.split(b"\n")[line - 1].split(b"#", 1)[0].split()
    return bool(words) and words[0] == b"f" and len(words) < 4


def read(data: bytes, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and triangles (m, 3) int64 of an OBJ file.

    Lines end in LF, CRLF or CR alone (classic Mac OS: read as 'no faces'); a backslash at
    a line's end continues it on the next (the OBJ specification's continuation: a
    tester's 'f 1 4 \\' was 'cannot read a number'; after one, error messages count
    the joined lines)."""
    data = lf_line_ends(data)
    if b"\\" in data:
        data = re.sub(rb"\\[ \t]*\r?\n", b" ", data)
    b = np.frombuffer(data, np.uint8)
    buf, values, slow, vlines, fidx, fcount, flines, n_short, err, line = _scan_obj(b)
    cut = _cut_line(data)
    if err:
        what = {_E_NUMBER: "cannot read a number", _E_FEW: "a vertex needs 3 coordinates",
                _E_INDEX: "face index 0 or before the first vertex"}[err]
        raise MeshError(f"{path}: OBJ line {line}: {what}{_CUT if line == cut else ''} "
                        f"(line reads {_line_text(data, line)!r})")
    if cut and _is_short_face(data, cut):
        # skipped as a face of fewer than 3 corners: a truncated file lost its last face
        # without a word, or was 'no faces' when it had been its first (a review's)
        raise MeshError(f"{path}: OBJ line {cut}: a face needs 3 corners{_CUT} (line reads "
                        f"{_line_text(data, cut)!r})")
    if len(vlines) == 0:
        raise MeshError(f"{path}: OBJ without vertices ('v' lines)")
    if len(fcount) == 0:
        if cut:
            raise MeshError(f"{path}: OBJ without faces ('f' lines), and the file ends inside "
                            f"line {cut} (truncated?) (line reads {_line_text(data, cut)!r})")
        raise MeshError(f"{path}: OBJ without faces ('f' lines) after its {len(vlines)} "
                        "vertices" + (f" (its {n_short} 'f' lines have fewer than 3 corners)"
                                      if n_short else ""))
    values = _finish_numbers(buf, values, slow, vlines, 3, path, "OBJ")
    vertices = values.reshape(-1, 3)
    _check_finite_lines(vertices, vlines, path, "OBJ")
    if len(fidx) and fidx.max() >= len(vertices):
        k = int(np.searchsorted(np.cumsum(fcount), int(np.argmax(fidx >= len(vertices))),
                                side="right"))
        raise MeshError(f"{path}: OBJ line {int(flines[k])}: face index out of range: the "
                        f"file has {len(vertices)} vertices")
    if n_short:
        log.warning("%s: skipped %d OBJ faces with fewer than 3 corners", path, n_short)
    return vertices, polygon_triangles(vertices, fidx, fcount)
