"""Parsers on random and corrupted bytes: a Mesh or a MeshError, never anything else."""
from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from icefab.errors import MeshError
from icefab.mesh import load_mesh
from icefab.core import Mesh

_TMP = Path(tempfile.mkdtemp(prefix="icefab-fuzz-"))
atexit.register(shutil.rmtree, _TMP, True)


def _valid_files() -> dict[str, bytes]:
    box = trimesh.creation.box(extents=(3.0, 4.0, 5.0))
    v32 = np.asarray(box.vertices, np.float32)
    head = ["ply", "format {fmt} 1.0", f"element vertex {len(v32)}", "property float x",
            "property float y", "property float z", f"element face {len(box.faces)}",
            "property list uchar int vertex_indices", "end_header"]

    def ply(fmt: str) -> bytes:
        text = ("\n".join(head) + "\n").replace("{fmt}", fmt).encode()
        if fmt == "ascii":
            body = "".join(f"{x} {y} {z}\n" for x, y, z in v32.tolist())
            body += "".join(f"3 {a} {b} {c}\n" for a, b, c in box.faces.tolist())
            return text + body.encode()
        e = "<" if fmt == "binary_little_endian" else ">"
        faces = np.zeros(len(box.faces), [("n", "u1"), ("i", e + "i4", (3,))])
        faces["n"] = 3
        faces["i"] = box.faces
        return text + v32.astype(e + "f4").tobytes() + faces.tobytes()

    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in box.vertices.tolist())
    obj += "".join(f"f {a + 1}/1 {b + 1}//2 {c + 1}\n" for a, b, c in box.faces.tolist())
    return {
        "stl": trimesh.exchange.stl.export_stl(box),
        "stl-ascii": trimesh.exchange.stl.export_stl_ascii(box).encode(),
        "ply-le": ply("binary_little_endian"),
        "ply-be": ply("binary_big_endian"),
        "ply-ascii": ply("ascii"),
        "obj": obj.encode(),
    }


VALID = _valid_files()
EXTS = (".stl", ".ply", ".obj", ".bin")


def _load(data: bytes, ext: str) -> None:
    p = _TMP / f"fuzz{ext}"
    p.write_bytes(data)
    try:
        mesh = load_mesh(p)
    except MeshError as exc:
        assert "fuzz" in str(exc)  # the message names the file
        return
    assert isinstance(mesh, Mesh)
    assert mesh.faces.ndim == 2 and mesh.faces.shape[1] == 3
    assert mesh.n_faces > 0
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    assert np.isfinite(mesh.vertices).all()


def test_valid_files_load():
    for name, data in VALID.items():
        for ext in EXTS:
            p = _TMP / f"ok-{name}{ext}"
            p.write_bytes(data)
            assert load_mesh(p).n_faces == 12, (name, ext)


@settings(suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(data=st.binary(max_size=2048), ext=st.sampled_from(EXTS))
def test_random_bytes(data, ext):
    _load(data, ext)


@settings(suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(prefix=st.sampled_from([b"solid ", b"ply\n", b"ply\nformat ascii 1.0\n",
                               b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n",
                               b"v 1 2 3\n", b"f 1 2 3\n", b"solid x\nfacet normal 0 0 1\n"]),
       data=st.binary(max_size=512), ext=st.sampled_from(EXTS))
def test_random_bytes_after_magic(prefix, data, ext):
    _load(prefix + data, ext)


@settings(suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(name=st.sampled_from(sorted(VALID)), ext=st.sampled_from(EXTS),
       cut=st.floats(0.0, 1.0))
def test_truncated_valid_files(name, ext, cut):
    data = VALID[name]
    _load(data[: int(cut * len(data))], ext)


@settings(suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(name=st.sampled_from(sorted(VALID)), ext=st.sampled_from(EXTS),
       edits=st.lists(st.tuples(st.floats(0.0, 1.0, exclude_max=True),
                                st.integers(0, 255), st.sampled_from(["set", "ins", "del"])),
                      min_size=1, max_size=8))
def test_corrupted_valid_files(name, ext, edits):
    data = bytearray(VALID[name])
    for where, byte, how in edits:
        if not data:
            break
        i = int(where * len(data))
        if how == "set":
            data[i] = byte
        elif how == "ins":
            data.insert(i, byte)
        else:
            del data[i]
    _load(bytes(data), ext)


@settings(suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(name=st.sampled_from(["stl-ascii", "ply-ascii", "obj"]),
       words=st.lists(st.sampled_from(["nan", "-1", "0", "1e999", "x", "vertex", "facet",
                                       "endfacet", "f", "v", "3", "255", "-", "1/2/3",
                                       "\n", "  ", "endloop", "1e", ".", "end_header"]),
                      min_size=1, max_size=6),
       where=st.floats(0.0, 1.0, exclude_max=True))
def test_token_corruption_of_text_files(name, words, where):
    data = VALID[name]
    i = int(where * len(data))
    _load(data[:i] + " ".join(words).encode() + data[i:], ".txt")


@pytest.mark.parametrize("header", [
    b"ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\n"
    b"property float y\nproperty float z\nelement face 1\n"
    b"property list uchar int vertex_indices\nend_header\n" + b"\0" * 64,
    b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
    b"property float y\nproperty float z\nelement face 999999999999\n"
    b"property list uchar int vertex_indices\nend_header\n" + b"\0" * 36 + b"\x03" + b"\0" * 12,
    b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
    b"property float z\nelement face 99999999999\nproperty list uchar int vertex_indices\n"
    b"end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
])
def test_huge_counts_do_not_allocate(header):
    with pytest.raises(MeshError, match="fuzz"):
        p = _TMP / "fuzz.ply"
        p.write_bytes(header)
        load_mesh(p)


# --------------------------------------------------------------------------- kernels


def _strip_reference(strip):
    tris, cur = [], []
    for idx in strip:
        if idx < 0:
            cur = []
            continue
        cur.append(idx)
        if len(cur) >= 3:
            a, b, c = cur[-3:]
            if (len(cur) - 3) % 2:
                a, b = b, a
            if len({a, b, c}) == 3:
                tris.append((a, b, c))
    return tris


@given(st.lists(st.integers(-1, 6), max_size=60))
def test_tristrip_decoder_matches_reference(strip):
    from icefab.mesh.ply import _tristrips
    got = _tristrips(np.array(strip, np.int64)).tolist()
    assert [tuple(t) for t in got] == _strip_reference(strip)


@given(st.lists(st.lists(st.integers(0, 50), min_size=3, max_size=9), min_size=1,
                max_size=20))
def test_fan_triangulation_matches_reference(polys):
    from icefab.mesh.topology import _fan
    flat = np.array([i for p in polys for i in p], np.int64)
    counts = np.array([len(p) for p in polys], np.int64)
    want = [(p[0], p[j + 1], p[j + 2]) for p in polys for j in range(len(p) - 2)]
    assert [tuple(t) for t in _fan(flat, counts).tolist()] == want


@given(st.lists(st.tuples(st.sampled_from([0.0, -0.0, 1.5, -2.25, 1e-300, 3e38]),
                          st.sampled_from([0.0, 7.0, -7.0]),
                          st.sampled_from([1.0, 2.0, np.float32(0.1).item()])),
                min_size=1, max_size=40))
def test_exact_weld_property(points):
    from icefab.mesh import weld_vertices
    pts = np.array(points, np.float64)
    v, idx = weld_vertices(pts)
    np.testing.assert_array_equal(v[idx], pts + 0.0)  # -0.0 welds with 0.0
    assert len(v) == len({tuple(p) for p in (pts + 0.0).tolist()})
    # first occurrence order
    firsts = [int(np.flatnonzero(idx == k)[0]) for k in range(len(v))]
    assert firsts == sorted(firsts)


def test_ply_element_declared_twice_is_one_mesh_error():
    # found by bench/fuzz_inputs.py (mesh:662): a repeated 'element vertex' without
    # properties shadowed the first and was a KeyError traceback
    data = VALID["ply-le"].replace(b"element face", b"element vertex 8\nelement face", 1)
    p = _TMP / "twice.ply"
    p.write_bytes(data)
    with pytest.raises(MeshError, match="element 'vertex' declared twice"):
        load_mesh(p)


@pytest.mark.parametrize("blank", [b"\x0b", b"\x0c"])
def test_obj_vertical_tab_or_form_feed_between_numbers_does_not_hang(blank):
    # found by bench/fuzz_inputs.py (mesh:2338): 'v 1 2 3\x0b...' looped forever
    data = VALID["obj"].replace(b"\n", blank + b"7\n", 1)
    p = _TMP / "vt.obj"
    p.write_bytes(data)
    assert load_mesh(p).n_faces == 12
