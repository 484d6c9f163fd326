"""Mesh import: formats, welding, diagnostics, errors (icefab.mesh)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from icefab.errors import MeshError
from icefab.mesh import check_mesh, load_mesh, read_mesh, write_stl
from icefab.types import Mesh


def _box() -> Mesh:
    tm = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    return Mesh(np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64), "box")


def test_binary_stl_roundtrip(tmp_path):
    box = _box()
    p = tmp_path / "box.stl"
    write_stl(box, p)
    mesh, report = read_mesh(p)
    assert mesh.n_faces == 12 and len(mesh.vertices) == 8
    assert report.watertight
    assert report.volume == pytest.approx(6000.0, rel=1e-9)
    np.testing.assert_allclose(np.sort(mesh.triangles().reshape(-1, 3), axis=0),
                               np.sort(box.triangles().reshape(-1, 3), axis=0))
