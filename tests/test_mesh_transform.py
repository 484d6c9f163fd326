"""Part set-up (thesis 3.1.2, Table 3-1): scale, rotations in order, translation, copies."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from icefab.config import Job, PartSetup
from icefab.errors import ConfigError, MeshError
from icefab.mesh import (check_mesh, load_mesh, part_fraction_range, place_mesh,
                         prepare_parts, transform, write_stl)
from icefab.core import Mesh


def _box(lo=(0.0, 0.0, 0.0), size=(10.0, 20.0, 30.0)) -> Mesh:
    tm = trimesh.creation.box(extents=size)
    tm.apply_translation(np.asarray(lo) + np.asarray(size) / 2)
    return Mesh(np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64), "box")


def _setup(**kw) -> PartSetup:
    kw.setdefault("translation", ("orig", "orig", "orig"))
    return PartSetup(**kw)


def test_identity_keeps_the_mesh():
    box = _box(lo=(5.0, -3.0, 7.0))
    out = transform(box, _setup())
    np.testing.assert_array_equal(out.vertices, box.vertices)
    np.testing.assert_array_equal(out.faces, box.faces)


def test_rotation_order_matters_hand_computed():
    box = _box()
    corner = int(np.flatnonzero((box.vertices == [10.0, 0.0, 0.0]).all(axis=1))[0])
    # x by +90 then y by +90 (space-fixed): (x, y, z) -> (z', ...) worked by hand:
    # Rx(90): (x, y, z) -> (x, -z, y); Ry(90): (x, y, z) -> (z, y, -x)
    a = transform(box, _setup(rotation_deg=(90.0, 90.0, 0.0), rotation_order=(1, 2, 3),
                              translation=(0.0, 0.0, 0.0)))
    np.testing.assert_allclose(a.bounds, [[0, 0, 0], [20, 30, 10]], atol=1e-12)
    np.testing.assert_allclose(a.vertices[corner], [0, 30, 0], atol=1e-12)
    b = transform(box, _setup(rotation_deg=(90.0, 90.0, 0.0), rotation_order=(2, 1, 3),
                              translation=(0.0, 0.0, 0.0)))
    np.testing.assert_allclose(b.bounds, [[0, 0, 0], [30, 10, 20]], atol=1e-12)
    np.testing.assert_allclose(b.vertices[corner], [0, 10, 0], atol=1e-12)


@pytest.mark.parametrize("order", [(1, 2, 3), (3, 1, 2), (2, 3, 1), (3, 2, 1)])
def test_rotation_matches_scipy_extrinsic(order):
    box = _box(lo=(3.0, 4.0, 5.0))
    angles = (30.0, -45.0, 110.0)
    out = transform(box, _setup(rotation_deg=angles, rotation_order=order))
    seq = "".join("xyz"[o - 1] for o in order)  # lowercase: extrinsic (space-fixed)
    rot = Rotation.from_euler(seq, [angles[o - 1] for o in order], degrees=True)
    moved = box.vertices - box.vertices.min(axis=0)  # thesis: minimum at zero first
    expected = rot.apply(moved)
    expected += (box.bounds.mean(axis=0)
                 - 0.5 * (expected.min(axis=0) + expected.max(axis=0)))  # 'orig'
    np.testing.assert_allclose(out.vertices, expected, atol=1e-9)
    assert check_mesh(out).volume == pytest.approx(6000.0)


def test_translation_modes():
    box = _box(lo=(5.0, -3.0, 7.0))
    out = transform(box, _setup(translation=("cent", 12.5, "orig")))
    lo, hi = out.bounds
    assert lo[0] == pytest.approx(-5.0) and hi[0] == pytest.approx(5.0)   # centred
    assert lo[1] == pytest.approx(12.5)                                   # minimum
    np.testing.assert_allclose([lo[2], hi[2]], [7.0, 37.0])               # kept
    # default set-up: centred in x and y, standing on z = 0
    d = transform(box, PartSetup())
    np.testing.assert_allclose(d.bounds, [[-5, -10, 0], [5, 10, 30]])


def test_orig_keeps_centre_after_rotation():
    box = _box(lo=(100.0, 50.0, 20.0))
    out = transform(box, _setup(rotation_deg=(0.0, 0.0, 90.0)))
    np.testing.assert_allclose(out.bounds.mean(axis=0), box.bounds.mean(axis=0))
    np.testing.assert_allclose(np.ptp(out.vertices, axis=0), [20, 10, 30])


def test_scaling_after_rotation_along_space_axes():
    box = _box()
    out = transform(box, _setup(scale=(2.0, 1.0, 0.5), rotation_deg=(0.0, 0.0, 90.0),
                                translation=(0.0, 0.0, 0.0)))
    # z-rotation swaps the 10 x 20 footprint to 20 x 10, then x doubles and z halves
    np.testing.assert_allclose(out.bounds, [[0, 0, 0], [40, 10, 15]], atol=1e-12)
    assert check_mesh(out).volume == pytest.approx(6000.0)


def test_copies_grid():
    box = _box()
    out = transform(box, _setup(copies=(3, 2, 5), copy_gap_mm=4.0,
                                translation=(0.0, 0.0, 0.0)))
    assert out.n_faces == 5 * box.n_faces
    np.testing.assert_allclose(out.bounds, [[0, 0, 0], [3 * 10 + 2 * 4, 2 * 20 + 4, 30]])
    rep = check_mesh(out)
    assert rep.watertight and rep.volume == pytest.approx(5 * 6000.0)
    # five separate boxes: their minimum corners on the grid, row by row
    corners = out.vertices.reshape(5, -1, 3).min(axis=1)
    np.testing.assert_allclose(corners, [[0, 0, 0], [14, 0, 0], [28, 0, 0], [0, 24, 0],
                                         [14, 24, 0]])
    with pytest.raises(ConfigError, match="copies"):
        transform(box, _setup(copies=(2, 2, 5)))


def test_part_fraction_range():
    box = _box(lo=(0, 0, 10.0))
    assert part_fraction_range(box, PartSetup(part_fraction=(0.25, 0.5))) == \
        pytest.approx((17.5, 25.0))


def test_prepare_parts(tmp_path):
    a = _box()
    b = _box(lo=(20.0, 0.0, 0.0), size=(5.0, 5.0, 5.0))
    write_stl(a, tmp_path / "a.stl")
    write_stl(b, tmp_path / "b.stl")
    job = Job(parts=PartSetup(files=("a.stl", str(tmp_path / "b.stl")),
                              translation=("cent", "cent", 0.0), copies=(2, 1, 2)))
    mesh = prepare_parts(job, base_dir=tmp_path)
    assert mesh.n_faces == 2 * (a.n_faces + b.n_faces)
    lo, hi = mesh.bounds
    width = 2 * 25.0 + 10.0  # two builds of 25 mm with the default 10 mm gap
    np.testing.assert_allclose([lo[0], hi[0], lo[2], hi[2]], [-width / 2, width / 2, 0, 30])
    assert check_mesh(mesh).volume == pytest.approx(2 * (6000.0 + 125.0))


def test_place_mesh_places_and_checks_a_loaded_mesh_as_prepare_parts_does(tmp_path):
    # the README's API path (load_mesh, then slice_mesh) skipped the placement and its
    # checks: a part in metres or beyond the reach went on to slicing
    from icefab.errors import WorkspaceError

    write_stl(_box(lo=(5.0, -3.0, 7.0)), tmp_path / "a.stl")
    job = Job(parts=PartSetup(files=("a.stl",)))
    placed = place_mesh(load_mesh(tmp_path / "a.stl"), job)
    np.testing.assert_array_equal(placed.vertices, prepare_parts(job, tmp_path).vertices)
    lo, hi = placed.bounds
    np.testing.assert_allclose([lo[0] + hi[0], lo[1] + hi[1], lo[2]], [0, 0, 0], atol=1e-9)
    metres = Mesh(_box().vertices / 1000.0, _box().faces, "m")
    with pytest.raises(ConfigError, match="metres or inches"):
        place_mesh(metres, Job())
    with pytest.raises(WorkspaceError, match="beyond the reach"):
        place_mesh(_box(size=(900.0, 20.0, 30.0)), Job())


def test_prepare_parts_without_files():
    with pytest.raises(MeshError, match="parts.files"):
        prepare_parts(Job())


def test_bad_rotation_order():
    with pytest.raises(ConfigError, match="rotation_order"):
        transform(_box(), _setup(rotation_deg=(10.0, 0, 0), rotation_order=(1, 1, 2)))
