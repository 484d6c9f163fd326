"""Compressed meshes (gzip, xz, bzip2) read through the normal loader, and the bounds on
decompression."""
from __future__ import annotations

import bz2
import gzip
import io
import lzma
import zipfile

import numpy as np
import pytest
from hypothesis import given, seed, settings
from hypothesis import strategies as st

import icefab
from icefab.errors import MeshError
from icefab.mesh import compressed, read_mesh, write_stl

# a unit tetrahedron in OBJ text, and the same in ASCII STL (outward normals)
OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
PLY = (b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
       b"property float z\nelement face 4\nproperty list uchar int vertex_indices\n"
       b"end_header\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")


def _same(a: icefab.Mesh, b: icefab.Mesh) -> None:
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


@pytest.mark.parametrize("name,data", [("t.obj", OBJ), ("t.ply", PLY)])
def test_gzip_text_formats_read_like_the_plain_file(tmp_path, name, data):
    plain = tmp_path / name
    plain.write_bytes(data)
    packed = tmp_path / (name + ".gz")
    packed.write_bytes(gzip.compress(data))
    a, b = read_mesh(plain), read_mesh(packed)
    _same(a[0], b[0])
    assert b[1].watertight and b[1].volume == pytest.approx(1 / 6)


def test_gzip_binary_stl_recognised_by_content_not_name(tmp_path):
    mug = icefab.demo_mug()
    stl = tmp_path / "mug.stl"
    write_stl(mug, stl)
    hidden = tmp_path / "mug.bin"  # no .gz, no .stl: the magic bytes decide
    hidden.write_bytes(gzip.compress(stl.read_bytes()))
    _same(icefab.load_mesh(stl), icefab.load_mesh(hidden))


def test_concatenated_gzip_members_are_one_file(tmp_path):
    p = tmp_path / "t.obj.gz"
    p.write_bytes(gzip.compress(OBJ[:40]) + gzip.compress(OBJ[40:]))
    assert read_mesh(p)[0].n_faces == 4


def test_gzip_bomb_refused_before_it_is_held(tmp_path, monkeypatch):
    p = tmp_path / "bomb.stl.gz"
    p.write_bytes(gzip.compress(b"\0" * (3 << 20)))  # 3 MiB of zeros in ~3 kB
    monkeypatch.setattr(compressed, "MAX_DECOMPRESSED_BYTES", 1 << 20)
    with pytest.raises(MeshError, match=r"bomb\.stl\.gz: gzip-compressed mesh expands to "
                                        r"more than 1 MiB"):
        read_mesh(p)


@pytest.mark.parametrize("damage,message", [
    (lambda d: d[:-9], "truncated gzip data"),
    (lambda d: d + b"junk", "trailing garbage"),
    (lambda d: d[:20] + bytes([d[20] ^ 0xFF]) + d[21:], "corrupt gzip data"),
])
def test_damaged_gzip_is_one_line_naming_the_file(tmp_path, damage, message):
    p = tmp_path / "t.obj.gz"
    p.write_bytes(damage(gzip.compress(OBJ * 50)))
    with pytest.raises(MeshError, match=rf"t\.obj\.gz: .*{message}") as info:
        read_mesh(p)
    assert "\n" not in str(info.value)


@seed(1010)
@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 400), st.integers(0, 255))
def test_fuzzed_gzip_gives_a_mesh_or_mesh_error(tmp_path_factory, body, at, xor):
    _read_flipped(tmp_path_factory.mktemp("gz") / "f.obj.gz", gzip.compress(OBJ + body),
                  at, xor)


def _read_flipped(p, packed: bytes, at: int, xor: int) -> None:
    """Byte ``at`` of ``packed`` XORed with ``xor``, written to ``p`` and read: a mesh or
    one line of MeshError naming the file."""
    data = bytearray(packed)
    if at < len(data):
        data[at] ^= xor
    p.write_bytes(bytes(data))
    try:
        read_mesh(p)
    except MeshError as exc:
        assert str(exc).startswith(str(p)) and "\n" not in str(exc)


def test_zlib_errors_never_escape():
    with pytest.raises(MeshError):
        compressed.gunzip(b"\x1f\x8b" + b"\0" * 30, compressed.Path("x.gz"))


COMPRESSORS = {"xz": lzma.compress, "bzip2": bz2.compress}


@pytest.mark.parametrize("kind", COMPRESSORS)
@pytest.mark.parametrize("name,data", [("t.obj", OBJ), ("t.ply", PLY)])
def test_xz_and_bzip2_read_like_the_plain_file(tmp_path, kind, name, data):
    """xz and bzip2 from the standard library, by their magic bytes (both were 'unknown
    mesh format'); concatenated streams are one file, as for gzip."""
    plain = tmp_path / name
    plain.write_bytes(data)
    packed = tmp_path / (name + ".x")   # the extension is not needed
    packed.write_bytes(COMPRESSORS[kind](data[:50]) + COMPRESSORS[kind](data[50:]))
    _same(read_mesh(plain)[0], read_mesh(packed)[0])


@pytest.mark.parametrize("kind,module,command", [("xz", "lzma", "xz -d"),
                                                 ("bzip2", "bz2", "bunzip2")])
def test_a_python_without_lzma_or_bz2_refuses_only_those_files(tmp_path, monkeypatch, kind,
                                                                module, command):
    """pyenv builds Python without lzma or bz2 when their headers are missing: every
    mesh still loads (the modules were imported with the package, and failed it), and
    only such a compressed file is refused, saying how to unpack it."""
    monkeypatch.setattr(compressed, module, None)
    p = tmp_path / "t.obj.z"
    p.write_bytes(COMPRESSORS[kind](OBJ))
    with pytest.raises(MeshError, match=rf"t\.obj\.z: {kind}-compressed, and this Python was "
                                        rf"built without its {module} module: decompress the "
                                        rf"file first \({command}\)"):
        read_mesh(p)
    (tmp_path / "t.obj").write_bytes(OBJ)
    assert read_mesh(tmp_path / "t.obj")[0].n_faces == 4


@pytest.mark.parametrize("kind", COMPRESSORS)
def test_xz_and_bzip2_bombs_refused_before_they_are_held(tmp_path, monkeypatch, kind):
    p = tmp_path / "bomb.stl.z"
    p.write_bytes(COMPRESSORS[kind](b"\0" * (3 << 20)))
    monkeypatch.setattr(compressed, "MAX_DECOMPRESSED_BYTES", 1 << 20)
    with pytest.raises(MeshError, match=rf"^\S*bomb\.stl\.z: {kind}-compressed mesh expands "
                                        r"to more than 1 MiB") as info:
        read_mesh(p)
    assert "corrupt" not in str(info.value)   # it was 'corrupt xz data (... expands ...)'


@pytest.mark.parametrize("kind", COMPRESSORS)
@pytest.mark.parametrize("damage,message", [
    (lambda d: d[:-9], "truncated {} data"),
    (lambda d: d + b"junk", "trailing garbage after the {} data"),
    (lambda d: d[:60] + bytes([d[60] ^ 0xFF]) + d[61:], "corrupt {} data"),
])
def test_damaged_xz_and_bzip2_are_one_line_naming_the_file(tmp_path, kind, damage, message):
    p = tmp_path / "t.obj.z"
    p.write_bytes(damage(COMPRESSORS[kind](OBJ * 50)))
    with pytest.raises(MeshError, match=rf"t\.obj\.z: .*{message.format(kind)}") as info:
        read_mesh(p)
    assert "\n" not in str(info.value)


def test_zip_holding_a_mesh_is_told_to_extract_it(tmp_path):
    """A zip archive (meshes come so from download sites) was told to take the .npz
    extension of icefab's result files; it is named with what it holds."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        z.writestr("tetra.obj", OBJ)
    for name in ("tetra.zip", "tetra.stl"):   # .stl: it was a 'truncated binary STL'
        p = tmp_path / name
        p.write_bytes(buf.getvalue())
        with pytest.raises(MeshError, match=rf"{name}: a zip archive holding tetra\.obj, not "
                                            r"a mesh: extract the mesh") as info:
            read_mesh(p)
        assert ".npz" not in str(info.value)


@seed(1011)
@settings(max_examples=40, deadline=None)
@given(st.sampled_from(sorted(COMPRESSORS)), st.binary(max_size=200), st.integers(0, 300),
       st.integers(1, 255))
def test_fuzzed_xz_and_bzip2_give_a_mesh_or_mesh_error(tmp_path_factory, kind, body, at, xor):
    _read_flipped(tmp_path_factory.mktemp("z") / "f.obj.z", COMPRESSORS[kind](OBJ + body),
                  at, xor)
