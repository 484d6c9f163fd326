"""Mesh import: every format gives the same geometry, welding, diagnostics, errors.

Reference meshes are built here with trimesh.creation (box, tube, sphere) and written by
trimesh (STL) or by the small independent writers below (PLY in every variant, OBJ with
quads), so the expected geometry never comes from icefab itself.
"""
from __future__ import annotations

import gzip
import io
import logging
import re
import struct

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings, strategies as st

from icefab.errors import MeshError
from icefab.mesh import (check_mesh, load_mesh, load_meshes, merge_meshes, read_mesh,
                         weld_vertices)
from icefab.core import Mesh

# --------------------------------------------------------------------------- references


def _tm(kind: str) -> trimesh.Trimesh:
    if kind == "box":
        return trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    if kind == "tube":
        return trimesh.creation.annulus(r_min=5.0, r_max=8.0, height=12.0, sections=24)
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=2, radius=7.5)
    raise KeyError(kind)


KINDS = ("box", "tube", "sphere")


def _canonical(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 9) triangles, each rotated to start at its smallest corner, rows sorted.

    Equal for two meshes iff they have the same oriented triangles (any numbering).
    """
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    # rank of every corner inside its triangle by lexicographic order
    flat = tri.reshape(-1, 3)
    order = np.lexsort(flat.T[::-1])
    rank = np.empty(len(flat), np.int64)
    rank[order] = np.arange(len(flat))
    rank = rank.reshape(-1, 3)
    start = np.argmin(rank, axis=1)
    idx = (start[:, None] + np.arange(3)) % 3
    rot = np.take_along_axis(tri, idx[:, :, None], axis=1).reshape(-1, 9)
    return rot[np.lexsort(rot.T[::-1])]


def _same_geometry(mesh: Mesh, ref: trimesh.Trimesh, dtype=np.float64) -> None:
    ref_v = np.asarray(ref.vertices, dtype).astype(np.float64)
    assert len(mesh.vertices) == len(np.unique(ref_v, axis=0))
    np.testing.assert_array_equal(np.unique(mesh.vertices, axis=0), np.unique(ref_v, axis=0))
    np.testing.assert_array_equal(_canonical(mesh.vertices, mesh.faces),
                                  _canonical(ref_v, ref.faces))
    report = check_mesh(mesh)
    assert report.watertight
    assert report.volume == pytest.approx(
        trimesh.Trimesh(ref_v, ref.faces, process=False).volume, rel=1e-9)


# --------------------------------------------------------------------------- writers


def _ply_bytes(vertices, faces, *, fmt="binary_little_endian", count_type="uchar",
               index_type="int", extra=False, polygons=None) -> bytes:
    """A PLY file written independently of icefab (struct/numpy, any layout)."""
    endian = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "<"}[fmt]
    codes = {"uchar": "u1", "char": "i1", "ushort": "u2", "short": "i2", "int": "i4",
             "uint": "u4"}
    polys = [list(f) for f in faces] if polygons is None else polygons
    head = ["ply", f"format {fmt} 1.0", "comment written by the icefab tests",
            f"element vertex {len(vertices)}"]
    vfields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if extra:
        vfields = [("confidence", "f8"), ("x", "f4"), ("nx", "f4"), ("y", "f4"),
                   ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")]
    names = {"f4": "float", "f8": "double", "u1": "uchar"}
    head += [f"property {names[t]} {n}" for n, t in vfields]
    head += [f"element face {len(polys)}",
             f"property list {count_type} {index_type} vertex_indices"]
    if extra:
        head += ["property uchar flags"]
        head += ["element edge 1", "property int vertex1", "property int vertex2"]
    head += ["end_header"]
    out = io.BytesIO()
    out.write(("\n".join(head) + "\n").encode())
    vrec = np.zeros(len(vertices), [(n, endian + t) for n, t in vfields])
    for n, _ in vfields:
        if n in "xyz":
            vrec[n] = np.asarray(vertices)[:, "xyz".index(n)]
        elif n == "confidence":
            vrec[n] = 0.5
    if fmt == "ascii":
        for r in vrec:
            out.write((" ".join(repr(float(x)) if isinstance(x, np.floating) else str(x)
                                for x in r.tolist()) + "\n").encode())
        for f in polys:
            out.write((" ".join(str(i) for i in [len(f), *f])
                       + (" 7" if extra else "") + "\n").encode())
        if extra:
            out.write(b"0 1\n")
        return out.getvalue()
    out.write(vrec.tobytes())
    ct, it = np.dtype(endian + codes[count_type]), np.dtype(endian + codes[index_type])
    for f in polys:
        out.write(np.array([len(f)], ct).tobytes() + np.array(f, it).tobytes())
        if extra:
            out.write(b"\x07")
    if extra:
        out.write(np.array([0, 1], endian + "i4").tobytes())
    return out.getvalue()


def _obj_bytes(vertices, polygons, *, style="plain") -> bytes:
    lines = ["# written by the icefab tests", "o part", "mtllib none.mtl"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, float).tolist()]
    lines += ["vt 0 0", "vn 0 0 1", "usemtl x", "s off"]
    n = len(vertices)
    for poly in polygons:
        if style == "plain":
            toks = [str(i + 1) for i in poly]
        elif style == "slashes":
            toks = [f"{i + 1}/1/1" if k % 2 else f"{i + 1}//1" for k, i in enumerate(poly)]
        else:  # negative (relative) indices
            toks = [str(i - n) for i in poly]
        lines.append("f " + " ".join(toks))
    return ("\n".join(lines) + "\n").encode()


def _box_quads():
    """A 10 x 20 x 30 box as 8 vertices and 6 outward quads."""
    v = np.array([[x, y, z] for z in (0, 30) for y in (0, 20) for x in (0, 10)], float)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2],
             [1, 3, 7, 5]]
    return v, quads


# --------------------------------------------------------------------------- formats


@pytest.mark.parametrize("kind", KINDS)
def test_binary_stl(tmp_path, kind):
    ref = _tm(kind)
    p = tmp_path / f"{kind}.stl"
    p.write_bytes(trimesh.exchange.stl.export_stl(ref))
    _same_geometry(load_mesh(p), ref, np.float32)


@pytest.mark.parametrize("kind", KINDS)
def test_ascii_stl(tmp_path, kind):
    ref = _tm(kind)
    p = tmp_path / f"{kind}.stl"
    p.write_text(trimesh.exchange.stl.export_stl_ascii(ref))
    _same_geometry(load_mesh(p), ref)


def test_ascii_stl_uppercase_multisolid_and_crlf(tmp_path):
    ref = _tm("box")
    text = trimesh.exchange.stl.export_stl_ascii(ref)
    lines = text.splitlines()
    half = 1 + 7 * 6  # header + six facets
    two = lines[:half] + ["endsolid a", "solid b"] + lines[half:]
    p = tmp_path / "box.txt"
    p.write_bytes("\r\n".join(ln.upper() for ln in two).encode())
    _same_geometry(load_mesh(p), ref)


@pytest.mark.parametrize("edit", ["no solid line", "comment first"])
def test_ascii_stl_without_its_solid_line_first(tmp_path, caplog, edit):
    """Exporters that leave out 'solid', or write a comment before it: read from the first
    'solid'/'facet' line (both were 'truncated binary STL ... declares 775041312 facets',
    the first bytes read as a facet count)."""
    ref = _tm("box")
    lines = trimesh.exchange.stl.export_stl_ascii(ref).splitlines()
    lines = lines[1:] if edit == "no solid line" else ["# exported by foo", *lines]
    p = tmp_path / "box.stl"
    p.write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        _same_geometry(load_mesh(p), ref)
    assert ("skipped 1 lines" in caplog.text) == (edit == "comment first")


@pytest.mark.parametrize("edit", [
    lambda t: t.replace(b"\n", b"\r"),              # classic Mac OS line ends
    lambda t: t.replace(b"\n", b"\r", 1),           # a CR alone after the 'solid' line
    lambda t: t + b"\x1a",                          # DOS end-of-file mark
    lambda t: t + b"\0" * (-len(t) % 512),          # padded to a block, a small file
    lambda t: t + b"\r\n\x1a" + b"\0" * 5000,       # padding past the sniffed 4 kB
    lambda t: t.replace(b"normal 0", b"normal -nan(ind)"),   # MSVC's NaN normals
    lambda t: re.sub(rb"normal \S+ \S+ \S+", b"normal 1.#QNAN0 1.#QNAN0 1.#QNAN0", t),
], ids=["cr-only", "solid-cr", "ctrl-z", "nul-block", "nul-long", "nan-ind", "qnan"])
def test_ascii_stl_line_ends_padding_and_unreadable_normals(tmp_path, edit):
    """Were 'without facets' (CR-only), 'unexpected token' (after endsolid, a line ended by
    CR alone after 'solid') and 'expected three numbers' (normals, never used)."""
    ref = _tm("box")
    text = trimesh.exchange.stl.export_stl_ascii(ref).encode()
    assert b"normal 0" in text
    p = tmp_path / "box.stl"
    p.write_bytes(edit(text))
    _same_geometry(load_mesh(p), ref)


@pytest.mark.parametrize("header", [b"Exported from Blender-2.91.0", b"solid part",
                                    b"solid part\n"])
def test_error_binary_stl_of_no_facets_is_not_taken_for_padded_text(tmp_path, header):
    """A text header and a facet count of 0 end in NULs, as padded ASCII does: no line end
    before them tells it from text (Blender's empty export). A header ending in a line end
    was 'ASCII STL without facets'."""
    with pytest.raises(MeshError, match=r"e\.stl: binary STL with 0 facets"):
        load_mesh(_write(tmp_path, "e.stl", header.ljust(80, b"\0") + b"\0" * 4))
    # an OBJ padded with NULs to the same 84 bytes stays an OBJ (a check's)
    tet = b"v 0 0 0\nv 9 0 0\nv 0 9 0\nv 0 0 9\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
    assert load_mesh(_write(tmp_path, "t.obj", tet.ljust(84, b"\0"))).faces.shape == (4, 3)


def test_error_ascii_stl_normal_short_names_the_facet_line(tmp_path):
    text = trimesh.exchange.stl.export_stl_ascii(_tm("box")).splitlines()
    k = 1 + 7 * 2   # third facet's line
    assert text[k].strip().startswith("facet normal")
    text[k] = "facet normal 0 0"
    with pytest.raises(MeshError, match=rf"n\.stl: ASCII STL line {k + 1}: expected three"):
        load_mesh(_write(tmp_path, "n.stl", "\n".join(text).encode()))


def test_error_text_stl_without_facets_is_not_called_binary(tmp_path):
    p = tmp_path / "notes.stl"
    p.write_text("these are not the facets you are looking for\n" * 3)
    with pytest.raises(MeshError, match=r"notes\.stl: ASCII text that does not start with "
                                        r"'solid'") as info:
        load_mesh(p)
    assert "\n" not in str(info.value)
    # a real ASCII STL's bad line after a comment is still named by its own line number
    text = trimesh.exchange.stl.export_stl_ascii(_tm("box")).splitlines()
    text[4] = "vertx 1 2 3"
    q = tmp_path / "bad.stl"
    q.write_text("\n".join(["# a comment", *text]))
    with pytest.raises(MeshError, match=r"bad\.stl: ASCII STL line 6: unexpected token"):
        load_mesh(q)


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply(tmp_path, kind, fmt):
    ref = _tm(kind)
    v32 = np.asarray(ref.vertices, np.float32)
    p = tmp_path / f"{kind}.ply"
    p.write_bytes(_ply_bytes(v32, ref.faces, fmt=fmt))
    ref32 = trimesh.Trimesh(v32.astype(float), ref.faces, process=False)
    _same_geometry(load_mesh(p), ref32)


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("count_type,index_type", [("uchar", "int"), ("int", "int"),
                                                   ("ushort", "uint"), ("char", "short")])
def test_ply_extra_properties_and_count_types(tmp_path, fmt, count_type, index_type):
    ref = _tm("tube")
    v32 = np.asarray(ref.vertices, np.float32)
    p = tmp_path / "tube.dat"  # no telling extension: detected by content
    p.write_bytes(_ply_bytes(v32, ref.faces, fmt=fmt, count_type=count_type,
                             index_type=index_type, extra=True))
    _same_geometry(load_mesh(p), trimesh.Trimesh(v32.astype(float), ref.faces,
                                                 process=False))


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
def test_ply_mixed_polygons_fan_triangulated(tmp_path, fmt):
    v, quads = _box_quads()
    # split two quads into triangles so the file mixes 3- and 4-corner faces
    polys = quads[:4] + [quads[4][:3], [quads[4][0], quads[4][2], quads[4][3]]] + quads[5:]
    p = tmp_path / "box.ply"
    p.write_bytes(_ply_bytes(v, None, fmt=fmt, polygons=polys, extra=True))
    mesh = load_mesh(p)
    assert mesh.n_faces == 12
    report = check_mesh(mesh)
    assert report.watertight and report.volume == pytest.approx(6000.0, rel=1e-12)


@pytest.mark.parametrize("style", ["plain", "slashes", "negative"])
def test_obj_quads(tmp_path, style):
    v, quads = _box_quads()
    p = tmp_path / "box.obj"
    p.write_bytes(_obj_bytes(v, quads, style=style))
    mesh = load_mesh(p)
    assert mesh.n_faces == 12 and len(mesh.vertices) == 8
    ref = trimesh.creation.box(extents=(10, 20, 30))
    ref.apply_translation((5, 10, 15))
    assert check_mesh(mesh).watertight
    assert check_mesh(mesh).volume == pytest.approx(ref.volume, rel=1e-12)
    # the triangles cover exactly the box surface
    assert trimesh.Trimesh(mesh.vertices, mesh.faces).area == pytest.approx(ref.area)


@pytest.mark.parametrize("fmt", ["obj", "ply"])
@pytest.mark.parametrize("start", range(6))
def test_concave_polygons_are_triangulated_inside_themselves(tmp_path, fmt, start):
    # an L-shaped prism with its top and bottom as hexagons: a fan from a corner next to
    # the reflex one lays a triangle outside the L (a tester's concave n-gons sliced as
    # overlapping shells, 'made as the union of their contours' on every layer)
    L = np.array([[0, 0], [20, 0], [20, 10], [10, 10], [10, 20], [0, 20]], float)
    L = np.roll(L, start, axis=0)                     # the fan starts at every corner
    v = np.vstack([np.c_[L, np.zeros(6)], np.c_[L, np.full(6, 5.0)]])
    faces = [list(range(5, -1, -1)), list(range(6, 12))]
    faces += [[k, (k + 1) % 6, (k + 1) % 6 + 6, k + 6] for k in range(6)]
    if fmt == "obj":
        text = "".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in v)
        text += "".join("f " + " ".join(str(i + 1) for i in f) + "\n" for f in faces)
        data = text.encode()
    else:
        data = _ply_bytes(v, None, fmt="ascii", polygons=faces)
    mesh = load_mesh(_write(tmp_path, f"l.{fmt}", data))
    assert mesh.n_faces == 2 * 4 + 6 * 2
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert tm.area == pytest.approx(2 * 300.0 + 80.0 * 5.0)    # no triangle outside the L
    report = check_mesh(mesh)
    assert report.watertight and report.volume == pytest.approx(1500.0, rel=1e-12)


@pytest.mark.parametrize("form", ["continued", "cr"])
def test_obj_continued_lines_and_cr_line_ends(tmp_path, form):
    # the OBJ specification continues a line after a backslash at its end (a tester's
    # 'f 1 4 \\' was 'cannot read a number'); classic Mac OS ends lines with CR alone
    # (read as 'the mesh has no faces')
    v, quads = _box_quads()
    text = _obj_bytes(v, quads, style="plain").decode()
    if form == "continued":
        text = "\n".join(ln.replace(" ", " \\\n  ", 2) if ln.startswith("f ") else ln
                          for ln in text.splitlines()) + "\n"
        assert "\\\n" in text
    else:
        text = text.replace("\n", "\r")
    p = tmp_path / "box.obj"
    p.write_bytes(text.encode())
    mesh = load_mesh(p)
    assert mesh.n_faces == 12 and check_mesh(mesh).watertight
    assert check_mesh(mesh).volume == pytest.approx(6000.0, rel=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_obj_matches_trimesh(tmp_path, kind):
    ref = _tm(kind)
    p = tmp_path / f"{kind}.obj"
    p.write_bytes(_obj_bytes(ref.vertices, ref.faces, style="slashes"))
    _same_geometry(load_mesh(p), ref)


def test_same_result_from_every_format(tmp_path):
    ref = _tm("sphere")
    v32 = np.asarray(ref.vertices, np.float32).astype(float)
    ref32 = trimesh.Trimesh(v32, ref.faces, process=False)
    files = {
        "a.stl": trimesh.exchange.stl.export_stl(ref32),
        "b.stl": trimesh.exchange.stl.export_stl_ascii(ref32).encode(),
        "c.ply": _ply_bytes(v32, ref.faces),
        "d.ply": _ply_bytes(v32, ref.faces, fmt="ascii"),
        "e.obj": _obj_bytes(v32, ref.faces),
    }
    canon = []
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
        m = load_mesh(tmp_path / name)
        canon.append(_canonical(m.vertices, m.faces))
    for c in canon[1:]:
        np.testing.assert_array_equal(c, canon[0])


def test_binary_stl_with_solid_header(tmp_path):
    ref = _tm("tube")
    data = bytearray(trimesh.exchange.stl.export_stl(ref))
    data[:80] = b"solid exported by a CAD tool that writes binary with a solid header".ljust(80)
    p = tmp_path / "tube.stl"
    p.write_bytes(bytes(data))
    _same_geometry(load_mesh(p), ref, np.float32)


def test_binary_stl_with_solid_header_truncated(tmp_path):
    data = bytearray(trimesh.exchange.stl.export_stl(_tm("tube")))
    data[:80] = b"solid x".ljust(80)
    p = tmp_path / "tube.stl"
    p.write_bytes(bytes(data[:-70]))
    with pytest.raises(MeshError, match=r"tube\.stl.*truncated"):
        load_mesh(p)


def test_extension_is_only_a_hint(tmp_path):
    ref = _tm("box")
    p = tmp_path / "box.obj"  # actually a binary STL
    p.write_bytes(trimesh.exchange.stl.export_stl(ref))
    _same_geometry(load_mesh(p), ref, np.float32)
    q = tmp_path / "box.stl"  # actually a PLY
    q.write_bytes(_ply_bytes(np.asarray(ref.vertices, np.float32), ref.faces))
    assert load_mesh(q).n_faces == 12


# --------------------------------------------------------------------------- tristrips


def _tristrip_reference(strip: np.ndarray) -> np.ndarray:
    """Plain-Python strip decoder (independent of icefab): restarts, alternate winding."""
    tris, cur = [], []
    for idx in strip.tolist():
        if idx < 0:
            cur = []
            continue
        cur.append(idx)
        if len(cur) >= 3:
            a, b, c = cur[-3:]
            if (len(cur) - 3) % 2 == 1:
                a, b = b, a
            if len({a, b, c}) == 3:
                tris.append((a, b, c))
    return np.array(tris, np.int64)


def test_igea_tristrips(mesh_dir):
    path = mesh_dir / "igea.ply.gz"
    data = gzip.decompress(path.read_bytes())
    body = data.index(b"end_header\n") + len(b"end_header\n")
    nv = 134345
    vertices = np.frombuffer(data, "<f4", count=3 * nv, offset=body).reshape(-1, 3)
    at = body + 12 * nv
    n = struct.unpack_from("<i", data, at)[0]
    strip = np.frombuffer(data, "<i4", count=n, offset=at + 4)
    expected = _tristrip_reference(strip)
    mesh, report = read_mesh(path)
    assert mesh.n_faces == len(expected)
    ref = trimesh.Trimesh(vertices.astype(float), expected, process=False)
    got = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert got.area == pytest.approx(ref.area, rel=1e-12)
    assert report.volume == pytest.approx(ref.volume, rel=1e-9)
    assert report.volume > 0
    assert report.watertight, report.warnings()


def test_tristrips_small(tmp_path):
    # two strips in one record and one in another: a square strip and a fan-like strip
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0], [1, 2, 0]], float)
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 6\nproperty float x\n"
            "property float y\nproperty float z\nelement tristrips 2\n"
            "property list int int vertex_indices\nend_header\n").encode()
    s1 = np.array([0, 1, 2, 3, -1, 2, 3, 4], "<i4")
    s2 = np.array([3, 5, 4, 4], "<i4")
    body = (v.astype("<f4").tobytes() + np.int32(len(s1)).tobytes() + s1.tobytes()
            + np.int32(len(s2)).tobytes() + s2.tobytes())
    p = tmp_path / "strips.ply"
    p.write_bytes(head + body)
    mesh = read_mesh(p)[0]
    want = np.concatenate([_tristrip_reference(s1), _tristrip_reference(s2)])
    got_tri = mesh.vertices[mesh.faces]
    want_tri = v[want]
    np.testing.assert_array_equal(got_tri, want_tri)
    # every triangle faces +z (the alternating winding keeps the orientation)
    n = np.cross(got_tri[:, 1] - got_tri[:, 0], got_tri[:, 2] - got_tri[:, 0])
    assert np.all(n[:, 2] > 0)


# --------------------------------------------------------------------------- real meshes


@pytest.mark.parametrize("name", ["fandisk.obj.gz", "rocker-arm.obj.gz", "spot.obj.gz",
                                  "stanford-bunny.obj.gz", "teapot.obj.gz",
                                  "igea.ply.gz"])
def test_real_meshes_load(mesh_dir, name):
    mesh, report = read_mesh(mesh_dir / name)
    assert mesh.n_faces > 1000
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    tm = (trimesh.load(gzip.open(mesh_dir / name), file_type="obj", process=False)
          if name.endswith(".obj.gz") else None)
    if tm is not None:
        assert mesh.n_faces + report.removed_degenerate + report.removed_duplicate == \
            len(tm.faces)
    if name in ("teapot.obj.gz", "stanford-bunny.obj.gz"):
        assert report.open_edges > 0 and not report.watertight
        assert any("open edges" in w for w in report.warnings())
    else:
        assert report.watertight, report.warnings()
        assert report.volume > 0


def test_teapot_open_edges_match_trimesh(mesh_dir):
    mesh, report = read_mesh(mesh_dir / "teapot.obj.gz")
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    edges = np.sort(tm.edges, axis=1)
    _, c = np.unique(edges, axis=0, return_counts=True)
    assert report.open_edges == int(np.count_nonzero(c == 1)) > 0
    assert report.non_manifold_edges == int(np.count_nonzero(c > 2))


# --------------------------------------------------------------------------- welding


def test_exact_weld_merges_negative_zero():
    pts = np.array([[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [0.0, 1.0, 2.0 + 1e-12]])
    v, idx = weld_vertices(pts)
    assert len(v) == 2 and idx.tolist() == [0, 0, 1]


def test_inexact_weld_within_tolerance():
    rng = np.random.default_rng(1)
    base = rng.random((200, 3)) * 100.0
    noisy = np.concatenate([base, base + rng.uniform(-2e-5, 2e-5, base.shape)])
    v, idx = weld_vertices(noisy, inexact=True, tolerance=1e-4)
    assert len(v) == 200
    assert np.array_equal(idx[:200], idx[200:])
    np.testing.assert_allclose(v[idx], noisy, atol=1e-4)
    v2, _ = weld_vertices(noisy)  # exact: nothing merges
    assert len(v2) == 400


def test_inexact_option_closes_a_jittered_stl(tmp_path):
    ref = _tm("sphere")
    tri = np.asarray(ref.vertices)[ref.faces].reshape(-1, 3)
    tri = tri + np.random.default_rng(2).uniform(-1e-5, 1e-5, tri.shape)
    jit = trimesh.Trimesh(tri, np.arange(len(tri)).reshape(-1, 3), process=False)
    p = tmp_path / "jitter.stl"
    p.write_bytes(trimesh.exchange.stl.export_stl(jit))
    exact = read_mesh(p)[1]
    assert exact.open_edges > 0
    mesh, rep = read_mesh(p, inexact=True, tolerance=1e-4)
    assert rep.watertight and len(mesh.vertices) == len(ref.vertices)


def _noisy_soup(kind: str, ulps: int, share: float, seed: int, dtype) -> np.ndarray:
    """The triangle corners of a reference mesh, each corner in ``share`` of them moved
    by up to ``ulps`` steps of ``dtype`` per coordinate (one vertex written twice with
    rounding noise, as CAD exporters do)."""
    ref = _tm(kind)
    tri = np.asarray(ref.vertices, dtype=dtype)[ref.faces].reshape(-1, 3)
    rng = np.random.default_rng(seed)
    pick = rng.random(len(tri)) < share
    step = np.spacing(np.abs(tri[pick]).astype(dtype)).astype(dtype)
    tri[pick] += step * rng.integers(-ulps, ulps + 1, (int(pick.sum()), 3)).astype(dtype)
    return tri


@settings(max_examples=25, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(KINDS), ulps=st.integers(1, 4), share=st.floats(0.01, 0.5),
       seed=st.integers(0, 2 ** 16), binary=st.booleans())
def test_a_vertex_written_twice_with_rounding_noise_is_one(tmp_path, kind, ulps, share,
                                                           seed, binary):
    """A CAD export wrote one vertex as (2.46875, 1.135, 5.1e-16) and (2.46875, 1.135, 0):
    the exact weld left 44 open edges, and the holes closed in 3D spanned 55 mm across
    surface that was there (a tester's idler_riser.STL, two layers of twice the area).
    Corners moved by a few float32 (binary STL) or float64 (ASCII) steps weld back into
    the closed reference, its volume as trimesh gives it."""
    ref = _tm(kind)
    tri = _noisy_soup(kind, ulps, share, seed, np.float32 if binary else np.float64)
    soup = trimesh.Trimesh(tri.astype(np.float64), np.arange(len(tri)).reshape(-1, 3),
                           process=False)
    p = tmp_path / "noisy.stl"
    if binary:
        p.write_bytes(trimesh.exchange.stl.export_stl(soup))
    else:
        lines = ["solid noisy"]
        for corners in tri.reshape(-1, 3, 3).tolist():
            lines += ["facet normal 0 0 0", "outer loop",
                      *(f"vertex {x!r} {y!r} {z!r}" for x, y, z in corners),
                      "endloop", "endfacet"]
        p.write_text("\n".join(lines + ["endsolid noisy", ""]))
    mesh, rep = read_mesh(p)
    assert rep.watertight and rep.open_edges == 0
    assert len(mesh.vertices) == len(ref.vertices) and len(mesh.faces) == len(ref.faces)
    assert rep.volume == pytest.approx(ref.volume, rel=1e-6)


def test_rounding_noise_at_the_origin_is_welded(tmp_path):
    """A corner at the origin written as (1e-16, 0, -2e-16) and as (0, 0, 0): noise of a
    sum of millimetres, welded though it is 1e6 times its own coordinates (a tester's)."""
    ref = _tm("box")
    ref.apply_translation(-ref.bounds[0])          # a corner at the origin
    tri = np.asarray(ref.vertices)[ref.faces].reshape(-1, 3)
    at = np.flatnonzero((tri == 0).all(axis=1))
    tri[at[0]] = (1e-16, 0.0, -2e-16)
    p = tmp_path / "origin.stl"
    p.write_text("\n".join(["solid o"] + [
        f"facet normal 0 0 0\nouter loop\n" + "\n".join(
            f"vertex {x!r} {y!r} {z!r}" for x, y, z in corners) + "\nendloop\nendfacet"
        for corners in tri.reshape(-1, 3, 3).tolist()] + ["endsolid o", ""]))
    mesh, rep = read_mesh(p)
    assert rep.open_edges == 0 and rep.welded_noise == 1 and len(mesh.vertices) == 8


def test_a_real_gap_is_not_welded_as_noise(tmp_path):
    """Corners 1 um apart on a 20 mm box are a gap, not rounding noise: they stay open
    edges (the thesis' inexact weld, ``parts.inexact``, is the user's to choose)."""
    ref = _tm("box")
    tri = np.asarray(ref.vertices)[ref.faces].reshape(-1, 3)
    tri[0] += 1e-3
    p = tmp_path / "gap.stl"
    p.write_bytes(trimesh.exchange.stl.export_stl(
        trimesh.Trimesh(tri, np.arange(len(tri)).reshape(-1, 3), process=False)))
    rep = read_mesh(p)[1]
    assert rep.open_edges > 0 and rep.welded_noise == 0


# --------------------------------------------------------------------------- diagnostics


def test_defects_are_fixed_and_reported(tmp_path, caplog):
    ref = _tm("box")
    faces = np.asarray(ref.faces)
    bad = np.concatenate([faces, faces[:2], [[0, 0, 1], [2, 3, 3]]])  # 2 dup, 2 degenerate
    tri = np.asarray(ref.vertices)[bad]
    tm = trimesh.Trimesh(tri.reshape(-1, 3), np.arange(3 * len(bad)).reshape(-1, 3),
                         process=False)
    p = tmp_path / "bad.stl"
    p.write_bytes(trimesh.exchange.stl.export_stl(tm))
    with caplog.at_level(logging.WARNING, logger="icefab.mesh"):
        mesh, report = read_mesh(p)
    assert mesh.n_faces == 12
    assert report.removed_duplicate == 2 and report.removed_degenerate == 2
    assert report.watertight
    assert "removed 2 duplicate faces" in caplog.text
    assert "removed 2 degenerate faces" in caplog.text
    assert "bad.stl" in caplog.text


def test_inverted_mesh_is_flipped_and_reported(tmp_path):
    ref = _tm("box")
    inv = trimesh.Trimesh(ref.vertices, np.asarray(ref.faces)[:, ::-1], process=False)
    p = tmp_path / "inside_out.stl"
    p.write_bytes(trimesh.exchange.stl.export_stl(inv))
    raw = check_mesh(Mesh(np.asarray(inv.vertices, float), np.asarray(inv.faces), "x"))
    assert raw.inverted and raw.volume == pytest.approx(-6000.0)
    assert any("inverted" in w for w in raw.warnings())
    mesh, report = read_mesh(p)
    assert report.flipped and report.volume == pytest.approx(6000.0)
    assert any("flipped" in w for w in report.warnings())


def test_check_mesh_counts():
    ref = _tm("box")
    v, f = np.asarray(ref.vertices, float), np.asarray(ref.faces)
    open_box = check_mesh(Mesh(v, f[:-1], "open"))
    assert open_box.open_edges == 3 and not open_box.watertight
    # a fin: a third face on an existing edge -> non-manifold
    v2 = np.vstack([v, [[100.0, 100.0, 100.0]]])
    a, b = f[0, 0], f[0, 1]
    fin = check_mesh(Mesh(v2, np.vstack([f, [[a, b, 8]]]), "fin"))
    assert fin.non_manifold_edges == 1 and fin.open_edges == 2
    # one face flipped -> its three edges are misoriented
    f3 = f.copy()
    f3[0] = f3[0, ::-1]
    flip = check_mesh(Mesh(v, f3, "flip"))
    assert flip.misoriented_edges == 3 and not flip.watertight
    dup = check_mesh(Mesh(v, np.vstack([f, f[:1, ::-1]]), "dup"))
    assert dup.duplicate_faces == 1
    degen = check_mesh(Mesh(v, np.vstack([f, [[1, 1, 2]]]), "degen"))
    assert degen.degenerate_faces == 1 and not degen.watertight
    nan = check_mesh(Mesh(np.vstack([v, [[np.nan, 0, 0]]]), f, "nan"))
    assert nan.nonfinite_vertices == 1 and not nan.watertight


def test_load_meshes_merges(tmp_path):
    a, b = _tm("box"), _tm("sphere")
    b.apply_translation((50, 0, 0))
    pa, pb = tmp_path / "a.stl", tmp_path / "b.obj"
    pa.write_bytes(trimesh.exchange.stl.export_stl(a))
    pb.write_bytes(_obj_bytes(b.vertices, b.faces))
    merged = load_meshes([pa, pb])
    assert merged.n_faces == len(a.faces) + len(b.faces)
    rep = check_mesh(merged)
    assert rep.watertight
    assert rep.volume == pytest.approx(a.volume + b.volume, rel=1e-6)
    assert merge_meshes([load_mesh(pa)]).n_faces == 12


# --------------------------------------------------------------------------- errors


def _write(tmp_path, name, data: bytes):
    p = tmp_path / name
    p.write_bytes(data)
    return p


def test_error_missing_file(tmp_path):
    with pytest.raises(MeshError, match=r"nope\.stl.*not found"):
        load_mesh(tmp_path / "nope.stl")


@pytest.mark.parametrize("data", [b"", b"   \n\n "])
def test_error_empty_file(tmp_path, data):
    with pytest.raises(MeshError, match=r"empty\.stl.*empty"):
        load_mesh(_write(tmp_path, "empty.stl", data))


def test_error_truncated_binary_stl(tmp_path):
    data = trimesh.exchange.stl.export_stl(_tm("sphere"))
    p = _write(tmp_path, "cut.stl", data[:-120])
    with pytest.raises(MeshError, match=r"cut\.stl: truncated binary STL.*declares 320 facets"):
        load_mesh(p)


def test_error_nan_binary_stl(tmp_path):
    ref = _tm("box")
    v = np.asarray(ref.vertices, float).copy()
    v[3, 1] = np.nan
    data = trimesh.exchange.stl.export_stl(trimesh.Trimesh(v, ref.faces, process=False))
    facet = int(np.flatnonzero((ref.faces == 3).any(axis=1))[0])
    with pytest.raises(MeshError, match=rf"nan\.stl.*NaN/Inf.*first: facet {facet}, corner"):
        load_mesh(_write(tmp_path, "nan.stl", data))


def test_error_fourth_vertex_names_its_own_line(tmp_path):
    text = trimesh.exchange.stl.export_stl_ascii(_tm("box")).splitlines()
    k = 1 + 7 * 4 + 4  # third vertex of the fifth facet (0-based line index)
    assert text[k].strip().startswith("vertex")
    text.insert(k + 1, text[k])
    p = _write(tmp_path, "four.stl", "\n".join(text).encode())
    with pytest.raises(MeshError, match=rf"four\.stl: ASCII STL line {k + 2}: a facet must "
                                        "have exactly 3 vertices"):
        load_mesh(p)


@pytest.mark.parametrize("token", ["nan", "inf", "-Infinity"])
def test_error_nan_ascii_stl(tmp_path, token):
    text = trimesh.exchange.stl.export_stl_ascii(_tm("box")).splitlines()
    k = next(i for i, ln in enumerate(text) if ln.strip().startswith("vertex"))
    k += 7 * 3  # a vertex of the fourth facet
    text[k] = f"vertex 1.0 {token} 2.0"
    p = _write(tmp_path, "nan.stl", "\n".join(text).encode())
    with pytest.raises(MeshError, match=rf"nan\.stl.*NaN/Inf.*line {k + 1}"):
        load_mesh(p)


@pytest.mark.parametrize("bad,what", [("vertex 1.0 2.x 3.0", "expected three numbers"),
                                      ("vertex 1.0 2.0", "expected three numbers"),
                                      ("vertx 1 2 3", "unexpected token"),
                                      ("", "3 vertices")])
def test_error_unparseable_ascii_stl_names_line(tmp_path, bad, what):
    text = trimesh.exchange.stl.export_stl_ascii(_tm("box")).splitlines()
    k = 1 + 7 * 4 + 2  # first vertex of the fifth facet (0-based line index)
    assert text[k].strip().startswith("vertex")
    text[k] = bad
    p = _write(tmp_path, "bad.stl", "\n".join(text).encode())
    with pytest.raises(MeshError, match=rf"bad\.stl: ASCII STL line (\d+): .*{what}") as ei:
        load_mesh(p)
    line = int(__import__("re").search(r"line (\d+)", str(ei.value)).group(1))
    assert k + 1 <= line <= k + 5  # the bad line, or where the damage shows (endfacet)


def test_error_ascii_stl_truncated(tmp_path):
    text = trimesh.exchange.stl.export_stl_ascii(_tm("box"))
    p = _write(tmp_path, "cut.stl", text[: len(text) // 2].encode())
    with pytest.raises(MeshError, match=r"cut\.stl: ASCII STL line \d+"):
        load_mesh(p)


def _obj_cut(upto: str, keep: str) -> tuple[bytes, int]:
    """The box OBJ cut after ``keep`` on its first line starting ``upto``: the bytes and
    that line's number."""
    v, quads = _box_quads()
    lines = _obj_bytes(v, quads).decode().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith(upto))
    return ("\n".join(lines[:k] + [keep]).encode(), k + 1)


@pytest.mark.parametrize("upto,keep,what", [
    ("v ", "v 0.0 0", "OBJ line {k}: a vertex needs 3 coordinates, and the file ends inside "
                      "this line (truncated?) (line reads 'v 0.0 0')"),
    ("v 10.0 20.0 0.0", "v 10.0 20.0 0", "OBJ without faces ('f' lines), and the file ends "
                                         "inside line {k} (truncated?) (line reads 'v 10.0 "
                                         "20.0 0')"),
    ("f ", "f 1 3", "OBJ line {k}: a face needs 3 corners, and the file ends inside this "
                    "line (truncated?) (line reads 'f 1 3')"),
    ("f 5 6 8 7", "f 5 6", "OBJ line {k}: a face needs 3 corners, and the file ends inside "
                           "this line (truncated?) (line reads 'f 5 6')"),
    ("f 5 6 8 7", "f 5 6 8 -", "OBJ line {k}: cannot read a number, and the file ends inside "
                               "this line (truncated?) (line reads 'f 5 6 8 -')"),
])
def test_error_obj_truncated_names_its_last_line(tmp_path, upto, keep, what):
    """A truncated OBJ said 'the mesh has no faces', or lost its last face without a
    word (a review's): the line the file ends inside is named, as ASCII STL and PLY say
    'truncated'."""
    data, k = _obj_cut(upto, keep)
    with pytest.raises(MeshError) as ei:
        load_mesh(_write(tmp_path, "cut.obj", data))
    assert str(ei.value) == f"{tmp_path / 'cut.obj'}: " + what.format(k=k)


def test_error_obj_without_faces_counts_its_vertices(tmp_path):
    data, _ = _obj_cut("vt ", "")
    with pytest.raises(MeshError, match=r"cut\.obj: OBJ without faces \('f' lines\) after its "
                                        r"8 vertices$"):
        load_mesh(_write(tmp_path, "cut.obj", data))
    # a last line of a whole face needs no line end (and says nothing)
    v, quads = _box_quads()
    assert load_mesh(_write(tmp_path, "whole.obj", _obj_bytes(v, quads).rstrip())).n_faces \
        == 12


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(at=st.integers(0, 10_000), style=st.sampled_from(["plain", "slashes", "negative"]))
def test_obj_cut_anywhere_is_a_mesh_or_one_line_naming_the_file(tmp_path, at, style):
    """Cut at any byte, an OBJ loads, or is one MeshError naming the file; one that ends
    inside a vertex or face line too short, or before any face, says 'truncated?'."""
    v, quads = _box_quads()
    whole = _obj_bytes(v, quads, style=style)
    data = whole[:at % (len(whole) + 1)]
    p = _write(tmp_path, "cut.obj", data)
    last = data.rsplit(b"\n", 1)[-1].split()
    try:
        mesh = load_mesh(p)
    except MeshError as exc:
        text = str(exc)
        assert text.startswith(f"{p}: ") and "\n" not in text
        ends_inside = bool(last) and last[0] in (b"v", b"f")
        if ends_inside and (len(last) < 4 or b"\nf " not in data):
            assert "(truncated?)" in text
        return
    assert 0 < mesh.n_faces <= 12 and b"\nf " in data


def test_error_obj_bad_number_names_line(tmp_path):
    v, quads = _box_quads()
    lines = _obj_bytes(v, quads).decode().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("v ")) + 2
    lines[k] = "v 1.0 abc 2.0"
    with pytest.raises(MeshError, match=rf"box\.obj: OBJ line {k + 1}: cannot read"):
        load_mesh(_write(tmp_path, "box.obj", "\n".join(lines).encode()))


@pytest.mark.parametrize("index", ["9", "0", "-9"])
def test_error_obj_index_out_of_range(tmp_path, index):
    v, quads = _box_quads()
    data = _obj_bytes(v, quads) + f"f 1 2 {index}\n".encode()
    with pytest.raises(MeshError, match=r"box\.obj: OBJ line \d+: .*(out of range|index 0|"
                                        r"before the first)"):
        load_mesh(_write(tmp_path, "box.obj", data))


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_error_ply_index_out_of_range(tmp_path, fmt):
    v, quads = _box_quads()
    polys = quads[:-1] + [[1, 3, 7, 99]]
    data = _ply_bytes(v, None, fmt=fmt, polygons=polys)
    with pytest.raises(MeshError, match=r"box\.ply: face \d+ has vertex index .*out of "
                                        r"range: the file has 8 vertices"):
        load_mesh(_write(tmp_path, "box.ply", data))


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
@pytest.mark.parametrize("index,message", [
    (1e30, r"PLY face vertex index 1e\+30 out of range: the file has 8 vertices"),
    (-1e30, r"PLY face vertex index -1e\+30 out of range: the file has 8 vertices"),
    (np.inf, r"PLY face indices are not integers"),
    (2.5, r"PLY face indices are not integers")])
def test_error_ply_float_index_list_holding_no_vertex_index(tmp_path, fmt, index,
                                                            message):
    """A float-typed index list (legal PLY) holding a whole number beyond any integer or
    an infinity: one error naming the file and the value, no numpy cast warning (the
    loader said 'index [0, 1, -9223372036854775808] out of range' after a
    RuntimeWarning)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(MeshError, match=r"big\.ply: " + message):
            load_mesh(_write(tmp_path, "big.ply", _ply_float_index(fmt, index)))


def _ply_float_index(fmt: str, index: float) -> bytes:
    """The box's first two triangles in a PLY with a double-typed index list, the last
    index ``index``."""
    v, _quads = _box_quads()
    head = ["ply", f"format {fmt} 1.0", "element vertex 8"]
    head += [f"property float {a}" for a in "xyz"]
    head += ["element face 2", "property list uchar double vertex_indices", "end_header"]
    faces = [[0, 2, 3], [0, 1, index]]
    if fmt == "ascii":
        body = "".join(f"{x} {y} {z}\n" for x, y, z in v)
        body += "".join(" ".join(["3", *(repr(float(i)) for i in f)]) + "\n" for f in faces)
        return ("\n".join(head) + "\n" + body).encode()
    data = ("\n".join(head) + "\n").encode() + np.asarray(v, "<f4").tobytes()
    return data + b"".join(struct.pack("<B3d", 3, *map(float, f)) for f in faces)


@settings(max_examples=200, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(fmt=st.sampled_from(["binary_little_endian", "ascii"]),
       index=st.floats(allow_nan=True, allow_infinity=True))
def test_any_float_index_loads_or_is_refused_without_warning(tmp_path, fmt, index):
    """Whatever number a float-typed PLY index list holds: the mesh loads (a whole number
    naming one of the 8 vertices) or one MeshError naming the file, and no warning."""
    import warnings

    names_a_vertex = bool(np.isfinite(index) and float(index).is_integer() and 0 <= index < 8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            mesh = load_mesh(_write(tmp_path, "any.ply", _ply_float_index(fmt, index)))
        except MeshError as exc:
            assert "any.ply" in str(exc) and "\n" not in str(exc)
            assert not names_a_vertex
        else:
            assert names_a_vertex
            assert len(mesh.faces) == (1 if index in (0, 1) else 2)  # 0 1 0: degenerate


def test_error_ply_truncated(tmp_path):
    ref = _tm("sphere")
    data = _ply_bytes(np.asarray(ref.vertices, np.float32), ref.faces)
    with pytest.raises(MeshError, match=r"cut\.ply: truncated"):
        load_mesh(_write(tmp_path, "cut.ply", data[:-50]))
    with pytest.raises(MeshError, match=r"cut2\.ply: truncated"):
        load_mesh(_write(tmp_path, "cut2.ply", data[:300]))


def test_error_ply_ascii_garbage_names_line(tmp_path):
    v, quads = _box_quads()
    lines = _ply_bytes(v, None, fmt="ascii", polygons=quads).decode().splitlines()
    k = lines.index("end_header") + 3
    lines[k] = "1.0 oops 2.0"
    with pytest.raises(MeshError, match=rf"g\.ply: ASCII PLY line {k + 1}: cannot read"):
        load_mesh(_write(tmp_path, "g.ply", "\n".join(lines).encode()))


def _ascii_box(edit):
    v, quads = _box_quads()
    lines = _ply_bytes(v, None, fmt="ascii", polygons=quads).decode().splitlines()
    head = lines.index("end_header")
    return "\n".join(edit(lines, head)).encode() + b"\n"


def test_error_ascii_ply_counts_that_do_not_match_its_lines(tmp_path):
    # the numbers are read as one stream: a vertex count one too high took the first
    # face's numbers and read the faces shifted (a tester's box: 3 faces, volume -266.7,
    # the error came from slicing naming no file); a face count one too low dropped a face
    def more_vertices(lines, head):
        return [ln.replace("element vertex 8", "element vertex 9") for ln in lines]

    def fewer_faces(lines, head):
        return [ln.replace("element face 6", "element face 5") for ln in lines]

    def a_missing_number(lines, head):
        lines[head + 2] = " ".join(lines[head + 2].split()[:2])
        return lines

    with pytest.raises(MeshError, match=r"c\.ply: ASCII PLY header declares 13 records "
                                        r"\(8 vertex, 5 face\): 5 numbers are left after "
                                        r"them; the body has 14 lines, one record a line"):
        load_mesh(_write(tmp_path, "c.ply", _ascii_box(fewer_faces)))
    head = _ascii_box(lambda lines, head: lines).decode().splitlines().index("end_header")
    with pytest.raises(MeshError, match=rf"c\.ply: ASCII PLY line {head + 3} has 2 numbers; "
                                        r"a vertex record there needs 3 \(header: x, y, z\)"):
        load_mesh(_write(tmp_path, "c.ply", _ascii_box(a_missing_number)))
    with pytest.raises(MeshError, match=r"c\.ply: (ASCII PLY header declares 15 records|"
                                        r"truncated or corrupt ASCII PLY)"):
        load_mesh(_write(tmp_path, "c.ply", _ascii_box(more_vertices)))

    # the declared numbers over other lines (every vertex on one line) are taken as they are
    def one_line(lines, head):
        return lines[:head + 1] + [" ".join(lines[head + 1:head + 9])] + lines[head + 9:]

    mesh = load_mesh(_write(tmp_path, "one.ply", _ascii_box(one_line)))
    assert len(mesh.faces) == 12


def _ascii_tetra_ply(face_lines, head_faces="property list uchar int vertex_indices\n",
                     n_faces=None, before="") -> bytes:
    """A unit tetrahedron as ASCII PLY text, its face lines given."""
    n = len(face_lines) if n_faces is None else n_faces
    return (f"ply\nformat ascii 1.0\n{before}element vertex 4\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {n}\n{head_faces}"
            "end_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n"
            + "".join(f"{ln}\n" for ln in face_lines)).encode()


TETRA = ["3 0 2 1", "3 0 1 3", "3 0 3 2", "3 1 2 3"]


def test_ascii_ply_without_faces_says_so_as_binary_does(tmp_path):
    """An ASCII PLY declaring 0 faces was 'element face has no vertex index list'."""
    for fmt in ("ascii", "binary_little_endian"):
        data = _ply_bytes(np.eye(3), np.zeros((0, 3), int), fmt=fmt)
        with pytest.raises(MeshError, match=r"e\.ply: the mesh has no faces"):
            load_mesh(_write(tmp_path, "e.ply", data))


@pytest.mark.parametrize("faces", [1, 6])
def test_error_ascii_ply_face_lines_longer_than_their_header_name_the_line(tmp_path, faces):
    """Face lines holding a list the header does not declare (trimesh's fuze_ascii.ply):
    'truncated or corrupt' or 'numbers are left' named no line."""
    head = ("property list uchar int vertex_indices\nproperty list uchar float texcoord\n"
            "property uchar red\nproperty uchar green\nproperty uchar blue\n")
    lines = [f"{f} 6 .1 .2 .3 .4 .5 .6 9 1 1 1 1 1 1 1 1 1" for f in TETRA * faces]
    data = _ascii_tetra_ply(lines, head)
    with pytest.raises(MeshError, match=r"f\.ply: ASCII PLY line 18 has 21 numbers; a face "
                                        r"record there needs 14 \(header: vertex_indices, "
                                        r"texcoord, red, green, blue\)"):
        load_mesh(_write(tmp_path, "f.ply", data))


def test_ascii_ply_with_cr_only_line_ends(tmp_path):
    """A classic Mac OS file (CR alone) was 'unknown header keyword plyformat'; a bad
    body line is still named by its line."""
    data = _ascii_tetra_ply(TETRA)
    assert load_mesh(_write(tmp_path, "cr.ply", data.replace(b"\n", b"\r"))).n_faces == 4
    bad = data.replace(b"\n0 0 1\n", b"\n0 0 x\n").replace(b"\n", b"\r")
    with pytest.raises(MeshError, match=r"bad\.ply: ASCII PLY line 13: cannot read"):
        load_mesh(_write(tmp_path, "bad.ply", bad))


def test_binary_ply_with_cr_only_header(tmp_path):
    v, quads = _box_quads()
    data = _ply_bytes(v, None, polygons=quads)
    end = data.index(b"end_header\n") + 11
    cr = data[:end].replace(b"\n", b"\r") + data[end:]
    assert load_mesh(_write(tmp_path, "box.ply", cr)).n_faces == 12


def test_ply_free_header_line_before_the_elements_skipped_with_warning(tmp_path, caplog):
    """Old Blender wrote 'Created by Blender3D 247 ...' (assimp's Wuson.ply): skipped, named,
    before the first element; after it, a free line could be a misspelt declaration."""
    blender = "Created by Blender3D 247 - www.blender.org, source file: ''\n"
    with caplog.at_level(logging.WARNING):
        mesh = load_mesh(_write(tmp_path, "w.ply", _ascii_tetra_ply(TETRA, before=blender)))
    assert mesh.n_faces == 4
    assert "w.ply: PLY header line 3: skipped \"Created by Blender3D" in caplog.text
    late = _ascii_tetra_ply(TETRA, head_faces="proprety list uchar int vertex_indices\n")
    with pytest.raises(MeshError, match=r"l\.ply: PLY header line 8: unknown header keyword "
                                        r"'proprety'"):
        load_mesh(_write(tmp_path, "l.ply", late))
    typo = _ascii_tetra_ply(TETRA).replace(b"format ascii", b"fromat ascii")
    with pytest.raises(MeshError, match=r"t\.ply: PLY header without a 'format' line"):
        load_mesh(_write(tmp_path, "t.ply", typo))


def test_error_ply_point_cloud(tmp_path):
    data = (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n1 2 3\n")
    with pytest.raises(MeshError, match=r"pc\.ply: PLY without a 'face'"):
        load_mesh(_write(tmp_path, "pc.ply", data))


def test_error_unknown_format(tmp_path):
    with pytest.raises(MeshError, match=r"thing\.step: unknown mesh format"):
        load_mesh(_write(tmp_path, "thing.step", b"ISO-10303-21;\nHEADER;\n"))
    # an icefab result file renamed (a hunt's stack.dat): said what it looks like
    import io
    buf = io.BytesIO()
    np.savez_compressed(buf, format=np.array("icefab-stack"))
    with pytest.raises(MeshError, match=r"stack\.dat: not a mesh but a zip archive, like "
                                        r"icefab's result files"):
        load_mesh(_write(tmp_path, "stack.dat", buf.getvalue()))
    # with its .npz extension it was told to give it its .npz extension (hunt P)
    with pytest.raises(MeshError, match=r"stack\.npz: one of icefab's result files, not a "
                                        r"mesh: this needs a mesh \(STL, PLY, OBJ\)"):
        load_mesh(_write(tmp_path, "stack.npz", buf.getvalue()))


def test_error_only_degenerate_faces(tmp_path):
    data = b"v 0 0 0\nv 1 0 0\nf 1 2 2\n"
    with pytest.raises(MeshError, match=r"flat\.obj.*degenerate"):
        load_mesh(_write(tmp_path, "flat.obj", data))


def test_error_only_faces_of_zero_area(tmp_path):
    """Faces whose corners lie on one line (no repeated index) hold no surface: named as
    such, not blamed on the units ("set parts.scale", a hunt's). One real face among them
    is enough."""
    data = b"v 0 0 0\nv 0 0 5\nv 0 0 10\nv 30 0 0\nv 30 0 10\nf 1 2 3\nf 4 5 4\n"
    with pytest.raises(MeshError, match=r"line\.obj: every face has zero area"):
        load_mesh(_write(tmp_path, "line.obj", data))
    ok = data + b"v 0 30 0\nf 1 4 6\n"
    assert load_mesh(_write(tmp_path, "one.obj", ok)).n_faces >= 1


def test_text_files_with_bom_and_utf8_names(tmp_path):
    ref = _tm("box")
    text = trimesh.exchange.stl.export_stl_ascii(ref).replace("solid", "solid Würfel", 1)
    p = _write(tmp_path, "w.stl", b"\xef\xbb\xbf" + text.encode("utf-8"))
    _same_geometry(load_mesh(p), ref)
    v, quads = _box_quads()
    q = _write(tmp_path, "w.obj", b"\xef\xbb\xbfo W\xc3\xbcrfel\n" + _obj_bytes(v, quads))
    assert load_mesh(q).n_faces == 12


@pytest.mark.parametrize("codec,bom", [("utf-16-le", b"\xff\xfe"), ("utf-16-be", b"\xfe\xff")])
def test_utf16_text_meshes_with_byte_order_mark(tmp_path, codec, bom):
    """UTF-16 text (Windows' "Unicode" save) was 'unknown mesh format' (OBJ, PLY) or
    'truncated binary STL'; with its byte order mark it is decoded."""
    ref = _tm("box")
    stl_text = trimesh.exchange.stl.export_stl_ascii(ref).replace("solid", "solid Würfel", 1)
    _same_geometry(load_mesh(_write(tmp_path, "b.stl", bom + stl_text.encode(codec))), ref)
    obj_text = _obj_bytes(*_box_quads()).decode()
    assert load_mesh(_write(tmp_path, "b.obj", bom + obj_text.encode(codec))).n_faces == 12
    ply_text = _ascii_tetra_ply(TETRA).decode()
    assert load_mesh(_write(tmp_path, "t.ply", bom + ply_text.encode(codec))).n_faces == 4
    cut = bom + obj_text.encode(codec)[:-1]   # an odd number of bytes
    with pytest.raises(MeshError, match=r"c\.obj: UTF-16 text that cannot be decoded .*; "
                                        r"save it as ASCII or UTF-8"):
        load_mesh(_write(tmp_path, "c.obj", cut))


def test_binary_stl_without_facet_count(tmp_path, caplog):
    ref = _tm("box")
    data = bytearray(trimesh.exchange.stl.export_stl(ref))
    data[80:84] = b"\0\0\0\0"  # a streaming exporter that never wrote the count
    with caplog.at_level(logging.WARNING, logger="icefab.mesh"):
        mesh = load_mesh(_write(tmp_path, "nocount.stl", bytes(data)))
    _same_geometry(mesh, ref, np.float32)
    assert "declares 0 facets" in caplog.text


def test_open_and_non_manifold_edges_are_located():
    ref = _tm("box")
    v, f = np.asarray(ref.vertices, float), np.asarray(ref.faces)
    rep = check_mesh(Mesh(v, f[1:], "open"))
    a, b, c = v[f[0]]
    mids = [tuple((p + q) / 2) for p, q in ((a, b), (b, c), (c, a))]
    assert rep.open_edge_at in [pytest.approx(m) for m in mids]
    # where the file has it: parts.scale and parts.translation come later
    assert "e.g. at (" in " ".join(rep.warnings()) and "in the file's coordinates" in \
        " ".join(rep.warnings())
    from icefab.mesh.repair import point_text
    assert point_text((5.329e-16, -78.666, -1e-17)) == "(0, -78.67, 0)"
    v2 = np.vstack([v, [[100.0, 100.0, 100.0]]])
    fin = check_mesh(Mesh(v2, np.vstack([f, [[f[0, 0], f[0, 1], 8]]]), "fin"))
    assert fin.non_manifold_edge_at == pytest.approx(tuple((v[f[0, 0]] + v[f[0, 1]]) / 2))


def test_located_open_edge_after_unused_vertices_dropped(tmp_path):
    # unreferenced vertices first: the location must survive the renumbering
    ref = _tm("box")
    v = np.vstack([[[50.0, 50.0, 50.0]] * 3, np.asarray(ref.vertices)])
    f = np.asarray(ref.faces)[1:] + 3
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in v.tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f.tolist()]
    mesh, rep = read_mesh(_write(tmp_path, "o.obj", "\n".join(lines).encode()))
    a, b, c = np.asarray(ref.vertices)[ref.faces[0]]
    mids = [tuple((p + q) / 2) for p, q in ((a, b), (b, c), (c, a))]
    assert rep.open_edges == 3
    assert rep.open_edge_at in [pytest.approx(m) for m in mids]


def test_clean_mesh_keeps_name_and_earlier_warnings():
    from icefab.mesh import clean_mesh

    tm = trimesh.creation.box()
    inside_out = Mesh(np.asarray(tm.vertices, float), np.asarray(tm.faces)[:, ::-1].copy(),
                      "box.stl", warnings=("box.stl: 1 duplicate facet removed",))
    cleaned, report = clean_mesh(inside_out)
    assert report.flipped
    assert cleaned.name == "box.stl"
    assert cleaned.warnings == inside_out.warnings


@pytest.mark.parametrize("count", ["nan", "inf", "-3", "2.5"])
def test_ascii_ply_bad_list_count_is_one_clean_line(tmp_path, count):
    """A list count that is not a whole non-negative number: one MeshError naming the file,
    no numpy warning on the way (the cast of a NaN count warned before the error)."""
    import warnings

    path = tmp_path / "bad.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                    "property float y\nproperty float z\nelement face 1\n"
                    "property list uchar int vertex_indices\nend_header\n"
                    f"0 0 0\n1 0 0\n0 1 0\n{count} 0 1 2\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(MeshError, match="bad.ply") as err:
            load_mesh(path)
    assert "np." not in str(err.value) and "\n" not in str(err.value)
