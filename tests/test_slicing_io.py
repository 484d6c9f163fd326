"""Stack files (save/load, corrupt files) and the path filter's bounds."""
from __future__ import annotations

import numpy as np
import pytest
import shapely
import trimesh

from icefab.config import Job
from icefab.errors import StackFileError
from icefab.slicing import load_stack, save_stack, slice_mesh, slice_report
from icefab.core import Layer, Mesh, Region, Stack


def as_mesh(tm):
    return Mesh(np.asarray(tm.vertices, float), np.asarray(tm.faces, np.int64), "t")


@pytest.fixture(scope="module")
def tube_stack():
    tm = trimesh.creation.annulus(r_min=3, r_max=8, height=3, sections=48)
    tm.apply_translation((0, 0, 1.5))
    return slice_mesh(as_mesh(tm), Job().replace(**{"slicing.layer_thickness_mm": 0.5}))


def test_save_load_roundtrip(tmp_path, tube_stack):
    path = save_stack(tube_stack, tmp_path / "s.npz")
    back = load_stack(path)
    assert len(back) == len(tube_stack)
    assert back.job == tube_stack.job
    assert back.warnings == tube_stack.warnings
    assert back.layer_thickness == tube_stack.layer_thickness
    for a, b in zip(tube_stack, back):
        assert (a.index, a.z, a.top_z) == (b.index, b.z, b.top_z)
        assert np.array_equal(a.part.parent, b.part.parent)
        assert len(a.part.rings) == len(b.part.rings)
        for ra, rb in zip(a.part.rings, b.part.rings):
            assert np.array_equal(ra, rb)
        assert b.scaffold.is_empty
    assert not list(tmp_path.glob("*.tmp"))


def test_roundtrip_with_scaffold_and_empty_layers(tmp_path):
    sq = np.array([[0, 0], [4, 0], [4, 4], [0, 4]], float)
    layers = (Layer(0, 0.1, Region((sq,), np.array([-1])), Region((sq + 10,), np.array([-1])),
                    0.25),
              Layer(1, 0.35, Region(), Region(), 0.5))
    st = Stack(layers, Job(), 0.25, ("layer 1: empty",))
    back = load_stack(save_stack(st, tmp_path / "x.npz"))
    assert np.array_equal(back[0].scaffold.rings[0], sq + 10)
    assert back[1].part.is_empty and back[1].scaffold.is_empty
    assert back.warnings == ("layer 1: empty",)


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty", "missing"])
def test_corrupt_stack_files(tmp_path, tube_stack, damage):
    path = save_stack(tube_stack, tmp_path / "s.npz")
    data = path.read_bytes()
    if damage == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"\x00not a zip" * 100)
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        path.unlink()
    with pytest.raises(StackFileError, match="s.npz"):
        load_stack(path)


def test_inconsistent_arrays_are_reported(tmp_path, tube_stack):
    path = save_stack(tube_stack, tmp_path / "s.npz")
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    d["ring_offsets"] = d["ring_offsets"][:-1]
    np.savez(tmp_path / "bad.npz", **d)
    with pytest.raises(StackFileError, match="corrupt"):
        load_stack(tmp_path / "bad.npz")
    np.savez(tmp_path / "other.npz", a=np.arange(3))
    with pytest.raises(StackFileError, match="not an icefab stack"):
        load_stack(tmp_path / "other.npz")


# --------------------------------------------------------------------------- filter


@pytest.mark.parametrize("spacing,dev", [(0.4, 0.05), (1.0, 0.01), (2.0, 0.2), (0.4, 0.0)])
def test_filter_deviation_bound(spacing, dev):
    """Every unfiltered contour point lies within max_filter_deviation_mm of the filtered
    contour; the filter only removes points."""
    tm = trimesh.creation.icosphere(subdivisions=5, radius=20.0)
    tm.apply_translation((0, 0, 20))
    exact = Job().replace(**{"slicing.min_point_spacing_mm": 0.0,
                             "slicing.max_filter_deviation_mm": 0.0,
                             "slicing.layer_thickness_mm": 2.0})
    job = exact.replace(**{"slicing.min_point_spacing_mm": spacing,
                           "slicing.max_filter_deviation_mm": dev})
    raw = slice_mesh(as_mesh(tm), exact)
    filt = slice_mesh(as_mesh(tm), job)
    assert slice_report(filt).points_after_filter <= slice_report(raw).points_after_filter
    for a, b in zip(raw, filt):
        assert len(a.part.rings) == len(b.part.rings) == 1
        ra, rb = a.part.rings[0], b.part.rings[0]
        # filtered points are a subset of the original points
        sa = {tuple(p) for p in ra}
        assert all(tuple(p) in sa for p in rb)
        ring = shapely.LinearRing(rb)
        d = shapely.distance(shapely.points(ra), ring)
        assert d.max() <= dev + 1e-9
        if dev == 0.0:
            assert b.part.area == pytest.approx(a.part.area, rel=1e-12)


def test_filter_enforces_spacing_on_collinear_runs():
    """On a box, points along the straight sides go and only the corners remain."""
    tm = trimesh.creation.box(extents=(30, 10, 2)).subdivide().subdivide()
    tm.apply_translation((0, 0, 1))
    st = slice_mesh(as_mesh(tm), Job())
    for layer in st:
        assert len(layer.part.rings[0]) == 4
        assert layer.part.area == pytest.approx(300.0)


def test_filter_drops_collapsed_rings():
    """A sliver thinner than the filter bound collapses and is counted."""
    thin = trimesh.creation.box(extents=(10, 1e-7, 2))
    thin.apply_translation((0, 20, 0))
    tm = trimesh.util.concatenate([trimesh.creation.box(extents=(5, 5, 2)), thin])
    tm.apply_translation((0, 0, 1))
    st = slice_mesh(as_mesh(tm), Job())
    assert slice_report(st).rings_collapsed > 0
    assert all(len(L.part.rings) == 1 for L in st)


def test_random_corruption_gives_stack_file_error(tmp_path, tube_stack):
    """Flipped bytes anywhere in a stack file: it loads or raises StackFileError, nothing else."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    good = save_stack(tube_stack, tmp_path / "good.npz").read_bytes()

    @settings(max_examples=60, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, len(good) - 1), st.integers(0, 255)),
                    min_size=1, max_size=8),
           st.integers(0, len(good)))
    def check(flips, cut):
        data = bytearray(good[:max(cut, 1)])
        for i, b in flips:
            if i < len(data):
                data[i] = b
        p = tmp_path / "bad.npz"
        p.write_bytes(bytes(data))
        try:
            load_stack(p)
        except StackFileError as exc:
            assert "bad.npz" in str(exc)

    check()


@pytest.mark.parametrize("spacing", [0.2, 0.4, 1.0])
def test_filter_enforces_min_point_spacing(spacing):
    """A finely sampled curved ring (0.1 mm steps, no collinear points) loses the points
    closer than the minimum spacing to the last kept one: the gaps between kept points are
    at least ``spacing`` except where the deviation bound forbids a removal, and the
    removed points stay within the bound (thesis 3.2 PATHFILTER)."""
    from icefab.slicing import _filter_compact

    t = np.linspace(0.0, 2 * np.pi, 1257, endpoint=False)  # 0.1 mm steps on r = 20 mm
    ring = np.c_[20 * np.cos(t), 20 * np.sin(t)]
    dev = 0.05
    pts, off = _filter_compact(ring, np.array([0, len(ring)]), np.array([0]), spacing, dev)
    kept = pts[off[0]:off[1]]
    gaps = np.linalg.norm(np.diff(np.vstack([kept, kept[:1]]), axis=0), axis=1)
    # a chord of length c on r = 20 sags c^2 / (8 r): spacings up to ~2.8 mm fit the bound
    assert np.all(gaps >= spacing - 1e-9)
    assert len(kept) <= len(ring) * 0.1 / spacing + 1
    d = shapely.distance(shapely.points(ring), shapely.LinearRing(kept))
    assert d.max() <= dev + 1e-9
    # without a spacing only collinear points may go: none here
    pts0, off0 = _filter_compact(ring, np.array([0, len(ring)]), np.array([0]), 0.0, dev)
    assert off0[1] == len(ring)
