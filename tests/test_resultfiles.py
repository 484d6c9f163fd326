"""The result files given back to icefab (stack, toolpaths, trajectories): round trips,
and every damaged or crafted file is one StackFileError naming the file (and the member),
never a traceback, a hang or a large allocation (issue 10). ``bench/fuzz_results.py`` runs
the same mutations by the ten thousand."""

from __future__ import annotations

import io
import os
import struct
import zlib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from icefab import resultfiles as rf
from icefab.config import Job
from icefab.core import (BuildMotion, Layer, LayerMotion, LayerPaths, Region, Stack, Toolpath,
                         Toolpaths, Trajectory)
from icefab.errors import StackFileError


def _square(c: float, r: float, ccw: bool = True) -> np.ndarray:
    sq = np.array([[c - r, c - r], [c + r, c - r], [c + r, c + r], [c - r, c + r]], float)
    return sq if ccw else sq[::-1].copy()


def small_stack() -> Stack:
    part = Region(rings=(_square(0, 10), _square(0, 4, ccw=False)), parent=np.array([-1, 0]))
    scaffold = Region(rings=(_square(0, 14), _square(0, 10.5, ccw=False)),
                      parent=np.array([-1, 0]))
    layers = tuple(Layer(index=k, z=0.125 + 0.25 * k, part=part, scaffold=scaffold,
                         top_z=0.25 * (k + 1)) for k in range(3))
    return Stack(layers=layers, job=Job(), layer_thickness=0.25, warnings=("a warning",))


def small_toolpaths() -> Toolpaths:
    paths = (Toolpath(_square(0, 9), 0.25, "part", "boundary", True, 1.5, 0),
             Toolpath(np.array([[9.0, -9.0], [13.0, -13.0]]), 0.25, "scaffold", "travel",
                      False, 0.0, 0, tool="scaffold"),
             Toolpath(_square(0, 13), 0.25, "scaffold", "fill", True, 1.5, 0),
             Toolpath(_square(0, 12), 0.25, "part", "measure", True, 0.0, 0),
             # a continuous tour: two fill lines, the travel between them off
             Toolpath(np.array([[-8.0, -8.0], [8.0, -8.0], [8.0, -6.5], [-8.0, -6.5]]), 0.25,
                      "part", "fill", False, 1.5, 0,
                      off=np.array([False, True, False, False])))
    return Toolpaths((LayerPaths(0, 0.25, paths, (1.0, 2.0)), LayerPaths(1, 0.5, paths[:2])),
                     Job(), ("w",))


def small_motion() -> BuildMotion:
    def traj(n: int, path: Toolpath | None, pieces=(0,)) -> Trajectory:
        t = np.linspace(0.0, 1.0, n)
        xy = np.c_[250 + 10 * t, -100 + 5 * t]
        return Trajectory(dt=0.016, xy=xy, joints=np.c_[t, -t, t, 2 * t], speed=10 * t,
                          duration=0.016 * (n - 1), path=path,
                          pieces=np.asarray(pieces, np.int64))

    tp = small_toolpaths().layers[0].paths
    layers = (LayerMotion(0, 0.25, (traj(5, tp[0], (0, 2)), traj(3, tp[1]), traj(4, tp[2]))),
              LayerMotion(1, 0.5, (traj(6, tp[3]),)))
    return BuildMotion(layers=layers, job=Job(), robot="scara",
                       joint_names=("j1", "j2", "j3", "j4"))


KINDS = {
    "stack": (small_stack, rf.save_stack, rf.load_stack),
    "toolpaths": (small_toolpaths, rf.save_toolpaths, rf.load_toolpaths),
    "trajectories": (small_motion, rf.save_trajectories, rf.load_trajectories),
}


@pytest.fixture(scope="module")
def good(tmp_path_factory) -> dict[str, bytes]:
    out = {}
    d = tmp_path_factory.mktemp("good")
    for kind, (make, save, _) in KINDS.items():
        save(make(), d / f"{kind}.npz")
        out[kind] = (d / f"{kind}.npz").read_bytes()
    return out


def _members(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


# --------------------------------------------------------------------------- round trips


def test_round_trips(tmp_path):
    st_ = small_stack()
    back = rf.load_stack(rf.save_stack(st_, tmp_path / "s.npz"))
    assert back.layer_thickness == 0.25 and back.warnings == ("a warning",)
    for a, b in zip(st_, back):
        assert (a.index, a.z, a.top_z) == (b.index, b.z, b.top_z)
        for ra, rb in ((a.part, b.part), (a.scaffold, b.scaffold)):
            assert np.array_equal(ra.parent, rb.parent)
            assert all(np.array_equal(x, y) for x, y in zip(ra.rings, rb.rings))
    tp = small_toolpaths()
    rf.save_toolpaths(tp, tmp_path / "t.npz")
    back_tp = rf.load_toolpaths(tmp_path / "t.npz")
    for la, lb in zip(tp, back_tp):
        assert la.unfilled_mm2 == lb.unfilled_mm2
        for p, q in zip(la.paths, lb.paths):
            assert np.array_equal(p.points, q.points)
            assert (p.z, p.material, p.role, p.closed, p.width, p.layer, p.frame, p.tool) == \
                (q.z, q.material, q.role, q.closed, q.width, q.layer, q.frame, q.tool)
    mo = small_motion()
    rf.save_trajectories(mo, tmp_path / "m.npz")
    back_mo = rf.load_trajectories(tmp_path / "m.npz")
    assert back_mo.joint_names == mo.joint_names
    for la, lb in zip(mo.layers, back_mo.layers):
        for a, b in zip(la.trajectories, lb.trajectories):
            # samples come back within half their resolution (issue 17), pieces exactly
            for x, y, res in ((a.xy, b.xy, rf.XY_RESOLUTION_MM),
                              (a.joints, b.joints, rf.JOINT_RESOLUTION),
                              (a.speed, b.speed, rf.SPEED_RESOLUTION_MM_S)):
                assert x.shape == y.shape and np.abs(x - y).max(initial=0) <= res / 2 + 1e-12
            assert np.array_equal(a.pieces, b.pieces)
            assert (a.dt, a.duration, a.path.material, a.path.role, a.path.width) == \
                (b.dt, b.duration, b.path.material, b.path.role, b.path.width)


def test_ragged_encoding_round_trips():
    items = [np.arange(6.0).reshape(3, 2), np.zeros((0, 2)), np.ones((1, 2))]
    rows, offs = rf.pack(items)
    assert offs.tolist() == [0, 3, 3, 4] and offs.dtype == np.int64
    assert all(np.array_equal(a, b) for a, b in zip(rf.split(rows, offs), items))
    rows, offs = rf.pack([])
    assert rows.shape == (0, 2) and offs.tolist() == [0]


# --------------------------------------------------------------------------- reproducers


def _write(tmp_path: Path, members: dict[str, np.ndarray], name="bad.npz") -> Path:
    p = tmp_path / name
    np.savez_compressed(p, **members)
    return p


@pytest.mark.parametrize("kind,change,member", [
    ("toolpaths", {"role": np.full(4, 99, np.int8)}, "role"),
    ("trajectories", {"role": np.array([0, 3, 1, 99], np.int8)}, "role"),
    ("stack", {"version": np.array("x")}, "version"),
    ("toolpaths", {"version": np.array("x")}, "version"),
    ("trajectories", {"version": np.array(2.5)}, "version"),
    ("stack", {"job": np.array("[slicing\n")}, "job"),
    ("trajectories", {"job": np.array("[slicing\n")}, "job"),
    ("stack", {"points": None}, "points"),        # one NaN (262 PiB in `icefab paths`)
    ("trajectories", {"xy_resolution": np.array(np.nan)}, "xy_resolution"),
    ("trajectories", {"xy_counts_0": "ff"}, "xy_counts_0"),  # counts far outside any cell
    ("stack", {"ring_parent": np.array([1, 0, -1, 0, -1, 0])}, "ring_parent"),  # a cycle
    ("stack", {"layer_thickness": np.array(-0.25)}, "layer_thickness"),
    ("toolpaths", {"path_start": np.array([0, 4, 2, 10, 14])}, "path_start"),
    ("trajectories", {"joint_counts_0": np.zeros((3, 8, 17), np.uint8)}, "joint_counts_0"),
    ("trajectories", {"joint_counts_0": np.zeros((2, 8, 18), np.uint8)}, "joint_counts_0"),
    ("trajectories", {"speed_counts_0": np.zeros((1, 8, 18), np.int64)}, "speed_counts_0"),
    ("trajectories", {"speed_counts_0": np.zeros((18, 8), np.uint8)}, "speed_counts_0"),
    ("trajectories", {"piece_start": np.array([0, 2, 0, 9, 0])}, "piece_start"),
    ("trajectories", {"tool": np.array(["", "scaffold", "", "nozzle"])}, "tool"),
    ("trajectories", {"traj_dt": np.array([0.016, 0.0, 0.016, 0.016])}, "traj_dt"),
    ("toolpaths", {"point_counts": np.zeros((3, 1, 18), np.uint8)}, "point_counts"),
    ("toolpaths", {"point_counts": np.zeros((2, 9, 18), np.uint8)}, "point_counts"),
    ("toolpaths", {"point_counts": "ff"}, "point_counts"),   # counts far outside any cell
    ("toolpaths", {"point_exact_index": np.array([1, 1]),
                   "point_exact": np.zeros((2, 2))}, "point_exact_index"),
    ("toolpaths", {"point_exact_index": np.array([5, 2], np.uint64),
                   "point_exact": np.zeros((2, 2))}, "point_exact_index"),
    ("toolpaths", {"point_exact_index": np.array([10**9])}, "point_exact_index"),
    ("toolpaths", {"point_exact_index": np.array([3]),
                   "point_exact": np.array([[np.nan, 0.0]])}, "point_exact"),
    ("toolpaths", {"point_exact_index": np.array([3]),
                   "point_exact": np.zeros((2, 2))}, "point_exact"),
    ("toolpaths", {"width": np.array([1.5, 0, 1.5, np.inf])}, "width"),
    ("stack", {"points": np.array([[1e300, 0.0]] * 24)}, "points"),
])
def test_bad_members_name_file_and_member(tmp_path, good, kind, change, member):
    members = _members(good[kind])
    for k, v in change.items():
        if v is None:  # one NaN in the first coordinate
            v = members[k].copy()
            v.flat[0] = np.nan
        elif isinstance(v, str):  # every byte 0xff
            v = np.full_like(members[k], 0xFF)
        members[k] = v
    p = _write(tmp_path, members)
    with pytest.raises(StackFileError) as e:
        KINDS[kind][2](p)
    msg = str(e.value)
    assert "bad.npz" in msg and f"member {member}" in msg and "\n" not in msg, msg


def test_raw_zlib_damage_is_one_line(tmp_path, good):
    data = bytearray(good["trajectories"])
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as z:
        info = z.getinfo("xy_counts_0.npy")
    # flip a byte inside the compressed data of the positions: a zlib or CRC error, named
    off = info.header_offset
    n_name, n_extra = struct.unpack("<HH", bytes(data[off + 26:off + 30]))
    pos = off + 30 + n_name + n_extra + 10
    data[pos] ^= 0xFF
    p = tmp_path / "flip.npz"
    p.write_bytes(bytes(data))
    with pytest.raises(StackFileError, match=r"flip.npz: member xy_counts_0: unreadable"):
        rf.load_trajectories(p)


def test_members_not_needed_are_never_decompressed(tmp_path, good, monkeypatch):
    """An unexpected member (here 64 MB of zeros, 64 kB on disk) is refused from the zip
    directory alone; the loaders open only the members they know."""
    members = _members(good["stack"])
    p = tmp_path / "big.npz"
    np.savez_compressed(p, **members, unused=np.zeros(8 << 20))
    opened = []
    real_open = zipfile.ZipFile.open

    def spy(self, name, *a, **k):
        opened.append(getattr(name, "filename", name))
        return real_open(self, name, *a, **k)

    monkeypatch.setattr(zipfile.ZipFile, "open", spy)
    with pytest.raises(StackFileError, match="unexpected members unused"):
        rf.load_stack(p)
    assert "unused.npy" not in opened
    opened.clear()
    rf.load_stack(_write(tmp_path, members, "ok.npz"))
    assert set(opened) <= {k + ".npy" for k in members}


def test_declared_sizes_are_checked_before_reading(tmp_path, good, monkeypatch):
    monkeypatch.setattr(rf, "MAX_MEMBER_BYTES", 200)
    p = tmp_path / "s.npz"
    p.write_bytes(good["stack"])
    with pytest.raises(StackFileError, match=r"member \w+: \d+ bytes uncompressed, more than"):
        rf.load_stack(p)
    # a header promising more than the member holds is refused before any allocation
    monkeypatch.setattr(rf, "MAX_MEMBER_BYTES", 1 << 30)
    members = _members(good["toolpaths"])
    with zipfile.ZipFile(tmp_path / "t.npz", "w") as z:
        for k, v in members.items():
            b = io.BytesIO()
            if k == "point_counts":  # 10^13 points promised (160 TB of counts), 20 given
                np.lib.format.write_array_header_1_0(
                    b, {"descr": "|u1", "fortran_order": False, "shape": (2, 8, 10**13)})
                b.write(v.tobytes())
            else:
                np.lib.format.write_array(b, v)
            z.writestr(k + ".npy", b.getvalue())
    with pytest.raises(StackFileError, match=r"member point_counts: shape \(2, 8, 10000000000000\)"):
        rf.load_toolpaths(tmp_path / "t.npz")


@pytest.mark.parametrize("kind", list(KINDS))
def test_other_files_are_named_as_such(tmp_path, kind):
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    with pytest.raises(StackFileError, match="not a regular file"):
        KINDS[kind][2](fifo)
    with pytest.raises(StackFileError, match="not found"):
        KINDS[kind][2](tmp_path / "missing.npz")
    p = _write(tmp_path, {"x": np.zeros(3)}, "other.npz")
    with pytest.raises(StackFileError, match="not an icefab"):
        KINDS[kind][2](p)


# --------------------------------------------------------------------------- fuzz

_DTYPES = st.sampled_from([np.float64, np.float32, np.int64, np.int8, np.uint16, np.bool_,
                           np.dtype("<U4"), np.complex64])


@st.composite
def mutations(draw, members: dict[str, np.ndarray]):
    """A crafted version of a good file's members: some replaced by arrays of any dtype and
    shape (NaN, infinities, extremes included), dropped, or joined by unknown ones."""
    out = dict(members)
    names = sorted(members)
    for _ in range(draw(st.integers(1, 3))):
        what = draw(st.sampled_from(["replace", "replace", "drop", "add", "perturb"]))
        name = draw(st.sampled_from(names))
        if what == "drop":
            out.pop(name, None)
        elif what == "add":
            out["extra_" + name] = np.zeros(2)
        elif what == "perturb" and name in out and out[name].dtype.kind in "fiu" \
                and out[name].size:
            a = out[name].copy()
            i = draw(st.integers(0, a.size - 1))
            a.flat[i] = draw(st.sampled_from([np.nan, np.inf, -1, 1e300, 2**40, -(2**40), 0,
                                              a.flat[i] + 1])) if a.dtype.kind == "f" else \
                draw(st.sampled_from([v for v in (-1, 0, 1, 127, np.iinfo(a.dtype).max,
                                                  np.iinfo(a.dtype).min)
                                      if np.iinfo(a.dtype).min <= v])) # uint8 counts: no -1
            out[name] = a
        else:
            out[name] = draw(hnp.arrays(_DTYPES, hnp.array_shapes(min_dims=0, max_dims=3,
                                                                  max_side=6)))
    return out


@pytest.mark.parametrize("kind", list(KINDS))
def test_crafted_files_load_or_raise_stack_file_error(tmp_path, good, kind):
    members = _members(good[kind])
    load = KINDS[kind][2]
    p = tmp_path / "crafted.npz"

    @settings(max_examples=60, deadline=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(mutations(members))
    def check(crafted):
        np.savez_compressed(p, **crafted)
        try:
            load(p)
        except StackFileError as exc:
            assert "crafted.npz" in str(exc) and "\n" not in str(exc)

    check()


@pytest.mark.parametrize("kind", list(KINDS))
def test_damaged_bytes_load_or_raise_stack_file_error(tmp_path, good, kind):
    data = good[kind]
    load = KINDS[kind][2]
    p = tmp_path / "damaged.npz"

    @settings(max_examples=60, deadline=None, derandomize=True)
    @given(st.lists(st.tuples(st.integers(0, len(data) - 1), st.integers(0, 255)),
                    min_size=1, max_size=6), st.integers(1, len(data)))
    def check(flips, cut):
        b = bytearray(data[:cut])
        for i, v in flips:
            if i < len(b):
                b[i] = v
        p.write_bytes(bytes(b))
        try:
            load(p)
        except StackFileError as exc:
            assert "damaged.npz" in str(exc) and "\n" not in str(exc)

    check()


@given(hnp.arrays(np.float64, st.tuples(st.integers(0, 40), st.integers(1, 3)),
                  elements=st.floats(-rf.MAX_COORD_MM, rf.MAX_COORD_MM)),
       st.sampled_from([rf.XY_RESOLUTION_MM, rf.JOINT_RESOLUTION, 0.5]))
def test_sample_counts_round_trip_within_half_a_resolution(values, resolution):
    planes = rf.encode_counts(values, resolution)
    assert planes.dtype == np.uint8 and planes.shape[::2] == (values.shape[1], len(values))
    assert 1 <= planes.shape[1] <= 8
    # the planes left out are zeros: the numpy form of the counts, all 8 planes
    q = np.rint(values / resolution).astype(np.int64)
    d = np.diff(np.diff(q, axis=0, prepend=0), axis=0, prepend=0)
    zz = ((d << 1) ^ (d >> 63)).astype("<u8")
    full = np.ascontiguousarray(zz.T).view(np.uint8).reshape(values.shape[1], len(values), 8)
    assert np.array_equal(full.transpose(0, 2, 1)[:, :planes.shape[1]], planes)
    assert not full.transpose(0, 2, 1)[:, planes.shape[1]:].any()
    assert planes.shape[1] == 1 or full.transpose(0, 2, 1)[:, planes.shape[1] - 1].any()
    back = rf.decode_counts(planes, resolution)
    assert back.shape == values.shape
    # exactly the nearest counts: within half a resolution (and float rounding)
    assert np.all(np.abs(back - values) <= resolution * (0.5 + 1e-9) + 1e-12 * np.abs(values))


def test_smooth_samples_take_a_few_bits_a_value():
    """A sampled motion's second differences are small: its high byte planes are zeros."""
    t = np.linspace(0, 10, 5000)
    xy = np.c_[300 + 80 * np.cos(t), 80 * np.sin(t)]
    planes = rf.encode_counts(xy, rf.XY_RESOLUTION_MM)
    # after the first two samples of each column, two bytes a value at most; the first
    # samples' absolute counts need three planes, the rest are left out
    assert planes.shape[1] == 3 and not planes[:, 2:, 2:].any()
    assert len(zlib.compress(planes.tobytes(), 1)) < 0.1 * xy.nbytes


@given(st.lists(st.tuples(st.integers(1, 6), st.sampled_from(["boundary", "fill", "measure",
                                                             "travel"]),
                          st.sampled_from(["part", "scaffold"]), st.booleans()),
                max_size=30))
def test_point_states_of_packed_paths_are_each_paths(shapes):
    from icefab.core import Toolpath, point_states
    paths = [Toolpath(points=np.zeros((k, 2)) + i, role=r, material=m, closed=c)
             for i, (k, r, m, c) in enumerate(shapes)]
    want = (np.concatenate([point_states(p) for p in paths]) if paths
            else np.zeros(0, np.int8))
    got = rf._point_states(rf.pack_paths(paths))
    assert got.dtype == np.int8 and np.array_equal(got, want)
    back = rf.unpack_paths(rf.pack_paths(paths))
    assert [(p.role, p.material, p.closed, len(p.points)) for p in back] == \
        [(r, m, c, k) for k, r, m, c in shapes]


@given(st.lists(st.tuples(st.integers(0, 6), st.booleans()), max_size=12),
       st.integers(0, 2 ** 32 - 1))
def test_packed_lengths_are_those_of_the_paths_polylines(shapes, seed):
    """packed_lengths gives, bit for bit, the lengths of the paths' polylines (closed
    ones back to their first point) that packed_polylines + polyline_lengths give, with
    empty, one-point and two-point paths among them; and each path's own length."""
    from icefab.core import Toolpath, path_lengths, polyline_lengths
    rng = np.random.default_rng(seed)
    paths = [Toolpath(points=rng.uniform(-300, 300, (k, 2)), role="fill", closed=c)
             for k, c in shapes]
    d = rf.pack_paths(paths)
    got = rf.packed_lengths(d)
    assert got.dtype == np.float64 and got.shape == (len(paths),)
    assert np.array_equal(got, polyline_lengths(*rf.packed_polylines(d)))
    # each path on its own (empty paths at either end once shortened their neighbours)
    own = [float(np.hypot(*np.diff(p.polyline(), axis=0).T).sum()) if len(p.points) > 1
           else 0.0 for p in paths]
    np.testing.assert_allclose(got, own, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(path_lengths(paths), own, rtol=1e-12, atol=1e-9)


@given(st.lists(st.lists(st.tuples(st.integers(1, 5), st.booleans(), st.booleans()),
                         max_size=6), max_size=5))
def test_packed_layers_concatenate_to_the_packing_of_all_their_paths(layers):
    """concat_packed (icefab paths writes the workers' packed layers without packing the
    paths again) gives pack_paths of all the paths, member for member, dtypes too:
    layers with and without variable-width paths, and empty ones."""
    from icefab.core import Toolpath
    layer_paths = []
    for li, shapes in enumerate(layers):
        layer_paths.append([
            Toolpath(points=np.arange(2.0 * k).reshape(k, 2) + 10 * li + i, z=0.25 * li,
                     role="fill", closed=c, width=1.5, layer=li,
                     widths=np.linspace(1.0, 2.0, k) + i if var else None)
            for i, (k, c, var) in enumerate(shapes)])
    want = rf.pack_paths([p for paths in layer_paths for p in paths])
    got = rf.concat_packed([rf.pack_paths(paths) for paths in layer_paths])
    assert sorted(got) == sorted(want)
    for key in want:
        assert got[key].dtype == want[key].dtype, key
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


def test_toolpath_file_from_packed_layers_is_the_same_file(tmp_path):
    """save_toolpath_layers (icefab paths: the layers' heads and the workers' packed
    arrays) writes the bytes save_toolpaths writes from the paths."""
    from icefab.core import Toolpath
    layers = tuple(LayerPaths(k, 0.5 * k, tuple(
        Toolpath(points=_square(3.0 * i, 1.0 + i), z=0.5 * k, role="boundary", closed=True,
                 width=1.5, layer=k, widths=np.full(4, 1.2) if i == 1 else None)
        for i in range(k)), (0.1 * k, 0.0), top_z=0.5 * k + 0.25) for k in range(4))
    tp = Toolpaths(layers, Job())
    rf.save_toolpaths(tp, tmp_path / "a.npz")
    heads = [rf.LayerHead(lp.index, lp.z, lp.unfilled_mm2, lp.thickness, lp.top_z)
             for lp in layers]
    rf.save_toolpath_layers(tmp_path / "b.npz", tp.job, tp.warnings, heads,
                            [rf.pack_paths(lp.paths) for lp in layers])
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    with pytest.raises(ValueError, match="3 packed layers for 4"):
        rf.save_toolpath_layers(tmp_path / "c.npz", tp.job, (), heads,
                                [rf.pack_paths(()) for _ in range(3)])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.lists(st.tuples(st.integers(1, 5), st.booleans(), st.booleans(),
                                   st.booleans()),
                         max_size=5), min_size=1, max_size=5))
def test_toolpath_files_read_as_arrays_give_each_layers_paths(layers):
    """load_packed_toolpaths cuts the file's arrays into layers: each layer's arrays are
    pack_paths of that layer's paths (variable widths and tours' off segments in some
    layers only, empty layers), and its Toolpaths those of load_toolpaths."""
    import tempfile

    from icefab.core import Toolpath
    tp = Toolpaths(tuple(
        LayerPaths(li, 0.25 * (li + 1), tuple(
            Toolpath(points=np.arange(2.0 * k).reshape(k, 2) + i, z=0.25 * (li + 1),
                     role="fill", closed=c, width=1.5, layer=li,
                     widths=np.linspace(1.0, 2.0, k) if var else None,
                     off=np.arange(k) == 1 if tour and not c and k >= 3 else None)
            for i, (k, c, var, tour) in enumerate(shapes)), (0.5 * li, 0.0))
        for li, shapes in enumerate(layers)), Job())
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "t.npz"
        rf.save_toolpaths(tp, f)
        arrays, whole = rf.load_packed_toolpaths(f), rf.load_toolpaths(f)
    assert len(arrays) == len(tp.layers) and arrays.warnings == whole.warnings
    for k, lp in enumerate(tp.layers):
        want = rf.pack_paths(lp.paths)
        got = arrays.layers[k]
        assert sorted(got) == sorted(want)
        for key in want:
            np.testing.assert_array_equal(got[key], want[key], err_msg=key)
        assert arrays.heads[k][:3] == (lp.index, lp.z, lp.unfilled_mm2)
        assert np.isnan(arrays.heads[k].thickness) and np.isnan(whole.layers[k].thickness)
        back = arrays.layer_paths(k)
        assert [(p.role, p.closed, p.points.tolist(),
                 None if p.widths is None else p.widths.tolist(),
                 None if p.off is None else p.off.tolist()) for p in back.paths] == \
            [(p.role, p.closed, p.points.tolist(),
              None if p.widths is None else p.widths.tolist(),
              None if p.off is None else p.off.tolist()) for p in whole.layers[k].paths] == \
            [(p.role, p.closed, p.points.tolist(),
              None if p.widths is None else p.widths.tolist(),
              None if p.off is None else p.off.tolist()) for p in lp.paths]


_COORD = st.one_of(st.floats(-rf.MAX_COORD_MM, rf.MAX_COORD_MM, allow_nan=False),
                   st.integers(-10**9, 10**9).map(lambda k: k / rf.POINT_GRID_PER_MM),
                   st.sampled_from([0.0, -0.0, 1e-300, -5e-324, rf.MAX_COORD_MM]))


@settings(max_examples=60, deadline=None)
@given(hnp.arrays(np.float64, st.tuples(st.integers(1, 40), st.just(2)), elements=_COORD))
def test_toolpath_points_come_back_bit_for_bit(points):
    """Version 5 stores the points in counts of Clipper's grid and the few that are not on
    it as floats: whatever the floats (on the grid, off it, -0.0, subnormal, at the
    coordinate bound), load_toolpaths gives back the same bits."""
    import tempfile

    from icefab.core import Toolpath
    tp = Toolpaths((LayerPaths(0, 0.25, (Toolpath(points=points, z=0.25, role="travel",
                                                  frame="base"),)),), Job())
    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "t.npz"
        rf.save_toolpaths(tp, f)
        got = rf.load_toolpaths(f).layers[0].paths[0].points
    assert got.tobytes() == np.ascontiguousarray(points).tobytes()


def test_toolpath_points_on_the_grid_take_a_few_bytes_each(tmp_path):
    """A ring of 20 000 points on Clipper's grid (what the paths stage writes) takes under
    a fifth of the bytes its floats took (version 4), and no float is stored."""
    from icefab import geometry
    from icefab.core import Toolpath
    assert rf.POINT_GRID_PER_MM == geometry.SCALE   # the grid the paths stage rounds to
    t = np.linspace(0.0, 2.0 * np.pi, 20_000, endpoint=False)
    ring = np.round(np.c_[150.0 * np.cos(t), 150.0 * np.sin(t)] * 1e4) / 1e4 + 0.0  # no -0.0
    rf.save_toolpaths(Toolpaths((LayerPaths(0, 0.25, (Toolpath(
        points=ring, z=0.25, role="fill", closed=True, width=3.0),)),), Job()),
        tmp_path / "r.npz")
    with zipfile.ZipFile(tmp_path / "r.npz") as z:
        stored = {i.filename: i.compress_size for i in z.infolist()}
    assert stored["point_counts.npy"] < 0.2 * len(zlib.compress(ring.tobytes(), 6))
    with np.load(tmp_path / "r.npz") as d:
        assert len(d["point_exact"]) == 0
