"""Reading a mesh file: format sniffing, the loader table, welding and clean-up.

The format is detected by content (the file extension is only a hint) and read by the
format's module through :data:`LOADERS`; every loader returns points and faces (or a
corner soup for STL), which are checked for NaN/Inf, welded
(:func:`icefab.mesh.topology.weld_vertices`) and cleaned
(:func:`icefab.mesh.repair.clean_mesh`).

A gzip-, xz- or bzip2-compressed file of any of these formats is read too (recognised by
content, :mod:`icefab.mesh.compressed`, with a bound on the decompressed size), and text in
UTF-16 with its byte order mark is read as the UTF-8 text it holds.

Errors (:class:`~icefab.errors.MeshError`, the message names the file): missing or empty
file, corrupt or oversized compressed data, a zip archive, unknown format, truncated binary
STL or PLY, NaN/Inf coordinates, text that cannot be read (with its line number), face
index out of range, nothing but degenerate faces.
"""

from __future__ import annotations

import dataclasses
import io
import logging
import math
import os
import re
import zipfile
from pathlib import Path
from typing import Callable, Iterable, NamedTuple, Sequence

import numpy as np

from icefab.core import Mesh
from icefab.errors import MeshError
from icefab.inputs import read_input
from icefab.mesh import compressed, obj, ply, stl
from icefab.mesh.repair import MeshReport, clean_mesh
from icefab.mesh.topology import weld_vertices

log = logging.getLogger(__name__)


_TEXT_BYTES = np.zeros(256, bool)
_TEXT_BYTES[[9, 10, 11, 12, 13]] = True
_TEXT_BYTES[32:256] = True  # bytes >= 128: UTF-8 in names and comments


def _is_text(data: bytes | memoryview) -> bool:
    """True when no byte is a control character other than whitespace."""
    return bool(_TEXT_BYTES[np.frombuffer(data, np.uint8)].all())


def _is_text_head(head: bytes) -> bool:
    """Whether the first bytes of a file, ``head``, are text: :func:`_is_text`, or NUL or
    Ctrl-Z padding after its last line end (DOS-era and fixed-block writers pad ASCII STLs
    so, stl.read_ascii; a binary STL's text header is followed by NULs with no line end)."""
    if _is_text(head):
        return True
    kept = head.rstrip(b"\0\x1a")
    return len(kept) < len(head) and kept[-1:] in (b"\n", b"\r") and _is_text(kept)


def _is_stl_text(head: bytes) -> bool:
    """Whether the text ``head`` holds the lines of ASCII STL facets ('facet normal' and
    'vertex' lines): an ASCII STL some exporters write without its 'solid' line, or with
    a comment before it (read from its first 'solid' or 'facet' keyword)."""
    return bool(re.search(rb"(?im)^[ \t]*facet[ \t]+normal[ \t]", head)
                and re.search(rb"(?im)^[ \t]*vertex[ \t]", head))


def _sniff(data: bytes, path: Path) -> str:
    """The format of ``data``: 'stl', 'stl-ascii', 'ply' or 'obj' (content first)."""
    ext = path.suffix.lower()
    if ext in compressed.SUFFIXES:  # part.obj.gz: the hint is the extension under it
        ext = Path(path.stem).suffix.lower()
    head = data[:5].lower()
    text = _is_text_head(data[:4096])
    if data[:3] == b"ply" and data[3:4] in (b"\n", b"\r", b" "):
        return "ply"
    if len(data) >= 84:
        n = int.from_bytes(data[80:84], "little") or (len(data) - 84) // 50
        if 84 + 50 * n == len(data) and n > 0:
            # a valid binary STL size; an ASCII STL exactly matching by chance would
            # need its header bytes to encode its own length and is not text after byte 84
            if not (data[:256].lstrip()[:5].lower() == b"solid" and _is_text(data[84:4180])):
                return "stl"
    if len(data) == 84 and data[80:84] == bytes(4) and (
            ext == ".stl" or data[:256].lstrip()[:5].lower() == b"solid"):
        # a binary STL of 0 facets, its header text ending in a line end ('ASCII STL
        # without facets'); an OBJ padded to 84 bytes is read as before
        return "stl"
    if data[:256].lstrip()[:5].lower() == b"solid":
        if text:
            return "stl-ascii"
        return "stl"  # a binary STL with a "solid" header (size checked by the reader)
    if text and re.search(rb"(?m)^[ \t]*(v|f|vn|vt|o|g|mtllib|usemtl)[ \t]",
                                           data[:65536]):
        return "obj"
    if text and _is_stl_text(data[:65536]):
        return "stl-ascii"  # without its 'solid' line, or after a comment (stl.read_ascii)
    if data[:4] == b"PK\x03\x04":   # a zip: icefab's result files are .npz archives
        # (before the .stl fallback: a zip named .stl was a 'truncated binary STL')
        raise MeshError(_zip_message(data, path, ext))
    if ext == ".stl" and len(data) >= 84:
        if text:
            # its first bytes read as a facet count of hundreds of millions: "truncated
            # binary STL ... declares 775041312 facets" (a tester's)
            raise MeshError(f"{path}: ASCII text that does not start with 'solid' and holds "
                            "no 'facet normal'/'vertex' lines: neither an ASCII nor a binary "
                            "STL")
        return "stl"
    if ext == ".obj" and text:
        return "obj"
    if head == b"ply":
        return "ply"
    raise MeshError(f"{path}: unknown mesh format (not binary/ASCII STL, PLY or OBJ by its "
                    f"content; extension {ext or 'none'!r})")


def _zip_members(data: bytes) -> list[str]:
    """The names of the files in the zip archive ``data`` (none when it cannot be read)."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as z:
            return z.namelist()
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return []


def _zip_message(data: bytes, path: Path, ext: str) -> str:
    """Why a zip archive is refused, and what to do: icefab's result files are numpy .npz
    archives (every member a .npy); any other zip (a mesh packed by a web site) was told
    to take the .npz extension, wrong advice: it must be extracted."""
    names = _zip_members(data)
    if names and all(n.endswith(".npy") for n in names):
        if ext == ".npz":   # it said to give the file the extension it had (hunt P)
            return (f"{path}: one of icefab's result files, not a mesh: this needs a mesh "
                    "(STL, PLY, OBJ), or the command that reads this file")
        return (f"{path}: not a mesh but a zip archive, like icefab's result files (stack, "
                "toolpaths, trajectories): give such a file its .npz extension, or a mesh "
                "(STL, PLY, OBJ)")
    shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
    held = f" holding {shown}" if names else ""
    return (f"{path}: a zip archive{held}, not a mesh: extract the mesh (STL, PLY, OBJ) "
            "from it and give that file")


_UTF16_BOMS = {b"\xff\xfe": "utf-16-le", b"\xfe\xff": "utf-16-be"}


def _from_utf16(data: bytes, path: Path) -> bytes:
    """``data`` as UTF-8 when it is UTF-16 text with its byte order mark (Windows' "Unicode"
    text: every other byte NUL, it was 'unknown mesh format' or 'truncated binary STL');
    else ``data`` itself. UTF-16 text that does not decode is refused."""
    codec = _UTF16_BOMS.get(data[:2])
    if codec is None:
        return data
    high = data[3:258:2] if codec == "utf-16-le" else data[2:258:2]  # 0 for ASCII text
    if not high or high.count(0) < 0.9 * len(high):
        return data  # not text: a binary STL's free header may start with these bytes
    try:
        return data[2:].decode(codec).encode("utf-8")
    except UnicodeDecodeError as exc:
        raise MeshError(f"{path}: UTF-16 text that cannot be decoded ({exc.reason} at byte "
                        f"{exc.start + 2}); save it as ASCII or UTF-8") from None


def _check_finite(points: np.ndarray, path: Path, corners: bool = False) -> None:
    """MeshError naming the first non-finite vertex; ``corners``: the points are the
    facet corners of an STL (3 per facet), so name the facet (0-based) instead."""
    if np.isfinite(points).all():
        return
    bad = ~np.isfinite(points).all(axis=1)
    k = int(np.flatnonzero(bad)[0])
    first = f"facet {k // 3}, corner {k % 3 + 1}" if corners else f"vertex {k}"
    raise MeshError(f"{path}: {int(bad.sum())} vertices with NaN/Inf coordinates "
                    f"(first: {first} = {points[k].tolist()}); expected finite numbers")


class Loader(NamedTuple):
    """One mesh format's reader.

    read: ``read(data, path)``; ``soup``: it returns the (3 m, 3) corners of m facets
        (STL), otherwise ``(vertices (n, 3), faces (m, 3) int64)``. Raises MeshError
        naming ``path``.
    """

    read: Callable
    soup: bool


#: Readers by the format :func:`_sniff` finds (content first, extension as a hint).
LOADERS: dict[str, Loader] = {
    "stl": Loader(stl.read_binary, soup=True),
    "stl-ascii": Loader(stl.read_ascii, soup=True),
    "ply": Loader(ply.read, soup=False),
    "obj": Loader(obj.read, soup=False),
}


def read_mesh(path: str | os.PathLike[str], *, inexact: bool = False,
              tolerance: float = 1e-4) -> tuple[Mesh, MeshReport]:
    """Load a mesh file and return it with its diagnostics.

    Same as :func:`load_mesh`, and also returns the :class:`MeshReport` of the cleaned
    mesh: what was fixed (``removed_degenerate``, ``removed_duplicate``, ``flipped``,
    ``merged_vertices``) and what remains (open / non-manifold / misoriented edges,
    zero-area faces, volume). Every finding is also logged as a warning.
    """
    p = Path(path)
    if tolerance <= 0 or not math.isfinite(tolerance):
        raise MeshError(f"{p}: weld tolerance {tolerance!r} must be a positive number (mm)")
    data = read_input(p, "mesh", MeshError, "mesh file")  # regular, <= 1 GiB; no FIFO wait
    data = compressed.unpack(data, p)  # gzip, xz or bzip2 by its magic; else unchanged
    data = _from_utf16(data, p)
    if not data[:4096].strip() and not data.strip():
        raise MeshError(f"{p}: empty file, expected a mesh (STL, PLY or OBJ)")
    if data[:3] == b"\xef\xbb\xbf" and _is_text(data[3:4099]):
        data = data[3:]  # UTF-8 byte order mark of a text file
    fmt = _sniff(data, p)
    loader = LOADERS[fmt]
    try:
        if loader.soup:
            corners = loader.read(data, p)
            _check_finite(corners, p, corners=fmt == "stl")
            vertices, index = weld_vertices(corners, inexact=inexact, tolerance=tolerance)
            faces = index.reshape(-1, 3)
            n_in = len(corners)
        else:
            raw_v, faces = loader.read(data, p)
            _check_finite(raw_v, p)
            if len(faces) and (faces.min() < 0 or faces.max() >= len(raw_v)):
                bad = int(np.flatnonzero((faces < 0).any(axis=1)
                                         | (faces >= len(raw_v)).any(axis=1))[0])
                raise MeshError(f"{p}: face {bad} has vertex index "
                                f"{faces[bad].tolist()} out of range: the file has "
                                f"{len(raw_v)} vertices")
            vertices, index = weld_vertices(raw_v, inexact=inexact, tolerance=tolerance)
            faces = index[faces] if len(faces) else faces.reshape(0, 3)
            n_in = len(raw_v)
    except (ValueError, IndexError, OverflowError, TypeError) as exc:
        if isinstance(exc, MeshError):
            raise
        raise MeshError(f"{p}: malformed {fmt.upper()} data ({exc})") from None
    if len(faces) == 0:
        raise MeshError(f"{p}: the mesh has no faces")
    mesh = Mesh(vertices, np.ascontiguousarray(faces, dtype=np.int64), p.name)
    mesh, report = clean_mesh(mesh)
    report = dataclasses.replace(report, merged_vertices=int(n_in - len(vertices)))
    if len(mesh.faces) == 0:
        raise MeshError(f"{p}: every face is degenerate; nothing left to slice")
    if not _any_area(mesh):
        # corners on one line: no surface to slice (it was blamed on the units, "set
        # parts.scale", a hunt's)
        raise MeshError(f"{p}: every face has zero area (its corners lie on one line); "
                        "nothing to slice")
    found = tuple(report.warnings())
    for w in found:
        log.warning("%s", w)
    return dataclasses.replace(mesh, warnings=found), report


def _any_area(mesh: Mesh) -> bool:
    """Whether any face's corners are off one line: twice its area above 1e-9 of the sum
    of its two edges' squares (each face by its own size: a stray vertex 1e20 mm away
    leaves the others their area)."""
    v = mesh.vertices
    for faces in (mesh.faces[:1024], mesh.faces):   # a real mesh answers in its first faces
        a, b, c = (v[faces[:, i]] for i in range(3))
        u, w = b - a, c - a
        twice = np.sqrt(np.sum(np.cross(u, w) ** 2, axis=1))
        if (twice > 1e-9 * (np.sum(u * u, axis=1) + np.sum(w * w, axis=1))).any():
            return True
    return False


def load_mesh(path: str | os.PathLike[str], *, inexact: bool = False,
              tolerance: float = 1e-4) -> Mesh:
    """Load an STL (binary/ASCII), PLY (binary/ASCII, faces or tristrips) or OBJ file.

    path: the mesh file; its format is detected by content.
    inexact: weld vertices within ``tolerance`` mm instead of exactly (thesis option).
    Returns an indexed, cleaned :class:`Mesh` (vertices float64 mm, faces int64).
    Raises :class:`MeshError` naming the file for missing, empty, truncated or malformed
    files, NaN/Inf coordinates and out-of-range face indices. Fixable defects are fixed
    and logged as warnings with counts (see :func:`read_mesh` for the report).
    """
    return read_mesh(path, inexact=inexact, tolerance=tolerance)[0]


def merge_meshes(meshes: Sequence[Mesh], name: str = "") -> Mesh:
    """One mesh holding all faces of ``meshes`` (vertex indices offset; no welding)."""
    if not meshes:
        raise MeshError("no meshes to merge")
    if len(meshes) == 1:
        return meshes[0] if not name else dataclasses.replace(meshes[0], name=name)
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    vertices = np.concatenate([m.vertices for m in meshes])
    faces = np.concatenate([m.faces + o for m, o in zip(meshes, offsets)])
    return Mesh(vertices, faces, name or "+".join(m.name for m in meshes),
                tuple(w for m in meshes for w in m.warnings))


def load_meshes(paths: Iterable[str | os.PathLike[str]], *, inexact: bool = False,
                tolerance: float = 1e-4) -> Mesh:
    """Load several mesh files and merge them into one build (thesis Table 3-1, CAD PARTS).

    The parts keep their coordinates relative to each other; see :func:`load_mesh`.
    """
    meshes = [load_mesh(p, inexact=inexact, tolerance=tolerance) for p in paths]
    if not meshes:
        raise MeshError("no mesh files given")
    return merge_meshes(meshes)
