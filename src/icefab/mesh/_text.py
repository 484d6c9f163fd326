"""Compiled scanning of ASCII mesh files (shared by ASCII STL, OBJ and ASCII PLY).

ASCII formats are scanned in one compiled pass over the bytes (numba): the pass checks
the grammar (with line numbers for errors), copies the coordinate tokens into one
compact buffer and parses integer indices itself; the coordinates are then converted
in one call (``np.fromstring``, C ``strtod``, correctly rounded). This module holds the
tokenizer, the exact fast float path and the number finishing; the per-format scanners
live in their format's module.
"""

from __future__ import annotations

import logging
import warnings
from pathlib import Path

import numpy as np
from numba import njit

from icefab.errors import MeshError

log = logging.getLogger(__name__)


# error codes of the scanners
_E_TOKEN, _E_NUMBER, _E_VCOUNT, _E_EOF, _E_INDEX, _E_FEW = 1, 2, 3, 4, 5, 6


@njit(cache=True)
def _is_ws(c):  # pragma: no cover
    return c == 32 or (9 <= c <= 13)


@njit(cache=True)
def _tok_eq(b, s, e, kw):  # pragma: no cover
    """Token b[s:e] equals keyword kw (ASCII, case-insensitive)."""
    if e - s != kw.size:
        return False
    for i in range(kw.size):
        c = b[s + i]
        if 65 <= c <= 90:
            c += 32
        if c != kw[i]:
            return False
    return True


@njit(cache=True)
def _is_number(b, s, e):  # pragma: no cover
    """Token b[s:e] is a decimal floating-point number, nan or inf[inity]."""
    i = s
    if i < e and (b[i] == 43 or b[i] == 45):
        i += 1
    if i >= e:
        return False
    c = b[i] | 32
    if c == 110 or c == 105:  # nan / inf / infinity
        n = e - i
        if n == 3:
            w0, w1, w2 = b[i] | 32, b[i + 1] | 32, b[i + 2] | 32
            return (w0 == 110 and w1 == 97 and w2 == 110) or (
                w0 == 105 and w1 == 110 and w2 == 102)
        if n == 8:
            ok = True
            word = "infinity"
            for k in range(8):
                if (b[i + k] | 32) != ord(word[k]):
                    ok = False
            return ok
        return False
    digits = 0
    while i < e and 48 <= b[i] <= 57:
        i += 1
        digits += 1
    if i < e and b[i] == 46:
        i += 1
        while i < e and 48 <= b[i] <= 57:
            i += 1
            digits += 1
    if digits == 0:
        return False
    if i < e and (b[i] == 101 or b[i] == 69):
        i += 1
        if i < e and (b[i] == 43 or b[i] == 45):
            i += 1
        ed = 0
        while i < e and 48 <= b[i] <= 57:
            i += 1
            ed += 1
        if ed == 0:
            return False
    return i == e


_POW10 = np.array([10.0 ** k for k in range(23)])


@njit(cache=True)
def _fast_float(b, s, e):  # pragma: no cover
    """Value of a validated decimal token when exactly computable, else (False, 0.0).

    Clinger's fast path: with at most 19 digits, a mantissa w <= 2^53 and a decimal
    exponent |q| <= 22, ``w * 10^q`` (or ``w / 10^-q``) is one correctly rounded IEEE
    operation, the same result as ``strtod``. Anything else (long mantissas, nan, inf)
    is left to ``np.fromstring``.
    """
    i = s
    neg = False
    if b[i] == 45:
        neg = True
        i += 1
    elif b[i] == 43:
        i += 1
    if (b[i] | 32) == 110 or (b[i] | 32) == 105:
        return False, 0.0
    w = np.uint64(0)
    nd = 0
    q = 0
    while i < e and 48 <= b[i] <= 57:
        if nd > 0 or b[i] != 48:
            nd += 1
        if nd > 19:
            return False, 0.0
        w = w * np.uint64(10) + np.uint64(b[i] - 48)
        i += 1
    if i < e and b[i] == 46:
        i += 1
        while i < e and 48 <= b[i] <= 57:
            if nd > 0 or b[i] != 48:
                nd += 1
            if nd > 19:
                return False, 0.0
            w = w * np.uint64(10) + np.uint64(b[i] - 48)
            q -= 1
            i += 1
    if i < e:  # exponent
        i += 1
        eneg = False
        if b[i] == 45:
            eneg = True
            i += 1
        elif b[i] == 43:
            i += 1
        x = 0
        while i < e:
            if x < 100000:
                x = x * 10 + (b[i] - 48)
            i += 1
        q += -x if eneg else x
    if w > np.uint64(9007199254740992):
        return False, 0.0
    v = float(w)
    if w == np.uint64(0):
        v = 0.0
    elif 0 <= q <= 22:
        v = v * _POW10[q]
    elif -22 <= q < 0:
        v = v / _POW10[-q]
    else:
        return False, 0.0
    return True, -v if neg else v


@njit(cache=True)
def _next_token(b, i, line):  # pragma: no cover
    """Skip whitespace from i; returns (start, end, line) of the next token (start == n at EOF)."""
    n = b.size
    while i < n and _is_ws(b[i]):
        if b[i] == 10:
            line += 1
        i += 1
    s = i
    while i < n and not _is_ws(b[i]):
        i += 1
    return s, i, line


@njit(cache=True)
def _store_number(b, s, e, values, slot, slow, ns, out, o):  # pragma: no cover
    """Put the number token b[s:e] into ``values[slot]``.

    Exact values come from :func:`_fast_float`; a token it cannot convert exactly is
    copied to ``out`` (space separated) and its slot listed in ``slow`` for strtod.
    Returns the new (ns, o) fill counts of ``slow`` and ``out``.
    """
    ok, val = _fast_float(b, s, e)
    values[slot] = val
    if not ok:
        slow[ns] = slot
        ns += 1
        for k in range(s, e):
            out[o] = b[k]
            o += 1
        out[o] = 32
        o += 1
    return ns, o


@njit(cache=True)
def _scan_numbers(b, start, line):  # pragma: no cover
    """All whitespace-separated numbers of b[start:] (the body of an ASCII PLY).

    Returns (slow_text, values, slow, err, err_line) as :func:`_scan_stl_ascii`.
    """
    n = b.size
    out = np.empty(n - start + 1, np.uint8)
    values = np.empty((n - start) // 2 + 1, np.float64)
    slow = np.empty((n - start) // 2 + 1, np.int64)
    nvals = 0
    ns = 0
    o = 0
    i = start
    while True:
        s, e, line = _next_token(b, i, line)
        i = e
        if s >= n:
            break
        if not _is_number(b, s, e):
            return out[:o], values[:nvals], slow[:ns], _E_NUMBER, line
        ns, o = _store_number(b, s, e, values, nvals, slow, ns, out, o)
        nvals += 1
    return out[:o], values[:nvals], slow[:ns], 0, 0


def lf_line_ends(data: bytes) -> bytes:
    """``data`` with CR-only line ends (classic Mac OS) as LF, byte offsets kept; text
    with any LF (LF or CRLF lines) as it is. The scanners count lines by LF: a CR-only
    file was one line ('without facets', 'no faces', 'unknown header keyword')."""
    if b"\r" in data and b"\n" not in data:
        return data.replace(b"\r", b"\n")
    return data


def _line_text(data: bytes, line: int) -> str:
    """The text of 1-based line ``line`` (shortened), for error messages."""
    lines = data.split(b"\n", line)
    text = lines[line - 1] if 0 < line <= len(lines) else b""
    return text[:60].decode("ascii", "replace").strip()


def _finish_numbers(text_buf: np.ndarray, values: np.ndarray, slow: np.ndarray,
                    lines: np.ndarray, per: int, path: Path, fmt: str) -> np.ndarray:
    """Fill the slots the compiled scan left (long mantissas, nan, inf) with ``strtod``.

    text_buf: uint8 tokens separated by spaces, one per entry of ``slow`` (slot indices
    into ``values``). Errors name the line (``lines[slot // per]``).
    """
    if len(slow) == 0:
        return values
    text = text_buf.tobytes()
    parsed = None
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        try:
            parsed = np.fromstring(text, dtype=np.float64, sep=" ")
        except (ValueError, DeprecationWarning):
            parsed = None
    if parsed is None or len(parsed) != len(slow):
        for k, tok in enumerate(text.split()):
            try:
                float(tok)
            except ValueError:
                line = int(lines[int(slow[k]) // per]) if len(lines) else -1
                raise MeshError(f"{path}: {fmt} line {line}: cannot read number "
                                f"{tok[:30].decode('ascii', 'replace')!r}") from None
        raise MeshError(f"{path}: {fmt}: expected {len(slow)} numbers, read "
                        f"{0 if parsed is None else len(parsed)}")
    values[slow] = parsed
    return values


def _check_finite_lines(points: np.ndarray, lines: np.ndarray, path: Path,
                        fmt: str) -> None:
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise MeshError(f"{path}: {int(bad.sum())} vertices with NaN/Inf coordinates "
                        f"(first on {fmt} line {int(lines[k])}: {points[k].tolist()}); "
                        "expected finite numbers")
