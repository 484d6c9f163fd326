"""Result files given back to icefab: ``stack.npz``, ``toolpaths.npz``, ``trajectories.npz``
(and ``ruled.npz``, layout at :func:`save_ruled`).

One module reads and writes all three (and packs the same data for worker processes), so
their shared parts exist once: the header (``format``, ``version``, the job as TOML text,
``icefab.config.to_toml``), one encoding of ragged arrays (:func:`pack` / :func:`split`:
the rows of all items concatenated, plus ``(n + 1,)`` int64 offsets, item ``i`` being rows
``offsets[i]:offsets[i+1]``), the code tables of path attributes, and atomic writing
(``icefab.atomic``: a temporary file renamed into place, so a failure leaves nothing
half-written). Every file is a numpy ``.npz`` (zip, members compressed).

Stack file (``icefab slice``; :func:`save_stack` / :func:`load_stack`):

* ``format`` "icefab-stack", ``version`` 1, ``job`` str (TOML);
* ``points`` (P, 2) float64 mm: all rings of all layers, concatenated, first point not
  repeated; ``ring_offsets`` (R + 1,) int64 into ``points``; ``ring_parent`` (R,) int64
  (index within its layer, -1 top level); ``ring_layer`` (R,) int64;
* ``layer_index`` (L,) int64, ``layer_z`` (L,) float64 mm, ``layer_top_z`` (L,) float64
  mm, ``layer_thickness`` () float64 mm, ``warnings`` (W,) str;
* scaffold regions, when present, stored the same way under the prefix ``scaffold_``;
* ``layer_height`` (L,) float64 mm, only for adaptive layers (``slicing.cusp_height_mm``):
  each layer's own thickness (the toolpath and trajectory files carry it the same way).

The toolpath and trajectory files carry each layer's top as the optional ``layer_top_z``
(L,) float64 mm, the stack's: where the nozzle goes (:meth:`icefab.core.LayerMotion.top`).
Files written before it have none (NaN: the top is derived from ``layer_z``, too low on a
top layer the part does not fill); NaN entries mean the same.

Toolpath file (``icefab paths``; :func:`save_toolpaths` / :func:`load_toolpaths`),
version 5:

* ``format`` "icefab-toolpaths", ``version`` int, ``job`` str (TOML), ``warnings`` (w,) str;
* the points of all paths (N, 2) mm, concatenated in order, exactly as the paths hold
  them: ``point_counts`` (2, k, N) uint8, each coordinate in counts of Clipper's grid
  (``POINT_GRID_PER_MM``, 1e4: the point is ``counts / 1e4``) as :func:`encode_counts`
  stores trajectory samples (the paths stage puts almost every point on that grid: 93 %
  of the demo mug's); ``point_exact_index`` (m,) int64, increasing, the points that are
  not ``counts / 1e4`` exactly, and ``point_exact`` (m, 2) float64 mm, their values
  (version 4 stored ``points`` (N, 2) float64: the bunny's file was 174 MB);
* ``state`` (N,) int8: Ossino's deposition state of every point (0 OFF, 1 ON1 part,
  2 ON2 scaffold), the state of the segment leaving the point along its path
  (:func:`icefab.core.point_states`: a closed path's last point deposits along its
  closing edge, an open path's last point is OFF, as are a tour's travel segments; travel
  and measurement points are OFF);
* ``path_start`` (P + 1,) int64: path i has ``points[path_start[i]:path_start[i+1]]``;
* per path (P,): ``z`` float64 mm, ``material`` int8 (0 part, 1 scaffold), ``role``
  int8 (0 boundary, 1 fill, 2 measure, 3 travel), ``closed`` bool, ``width`` float64
  mm, ``layer`` int64, ``frame`` int8 (0 part, 1 base), ``tool`` int8 (0 derived,
  1 part nozzle, 2 scaffold nozzle, 3 laser);
* only when some path has a width per point (:attr:`icefab.core.Toolpath.widths`):
  ``variable`` (P,) bool, which paths do, and ``point_width`` (V,) float64 mm, the width
  at every point of those paths, in order;
* only when some path has segments that deposit nothing (:attr:`icefab.core.Toolpath.off`,
  a continuous tour's travel; version 4): ``point_off`` (N,) bool, True where the segment
  leaving the point is off (its ``state`` is OFF);
* per layer (L,): ``layer_index`` int64, ``layer_z`` float64 mm, ``layer_start``
  (L + 1,) int64 (paths of layer j are ``layer_start[j]:layer_start[j+1]``),
  ``unfilled_mm2`` (L, 2) float64.

Version 1 toolpath files (without ``state``), version 2 (no per-point widths), version 3
(no tours) and version 4 (``points`` as floats) are still read; states are derived from
the paths.

Trajectory file (``icefab plan``; :func:`save_trajectories` / :func:`load_trajectories`):

* ``format`` = "icefab-trajectories", ``version`` = 6, ``dt`` float s (the first
  trajectory's; ``traj_dt`` has each one's), ``robot`` str, ``joint_names`` (j,) str,
  ``job`` str (TOML);
* the samples of all trajectories, in order, as integer counts of a resolution (issue
  17: what the cell can use, in a tenth of the bytes), in blocks of whole layers
  (``block_layer_start`` (B + 1,) int64: block k holds layers
  ``block_layer_start[k]:block_layer_start[k+1]``, about :data:`BLOCK_SAMPLES` samples,
  so a reader or writer holds one block at a time, :class:`TrajectoryFile`,
  :class:`TrajectoryWriter`): ``xy_counts_K`` (2, k, M_k) uint8 at ``xy_resolution`` mm
  (robot base frame), ``joint_counts_K`` (j, k, M_k) at ``joint_resolution`` (rad or
  mm), ``speed_counts_K`` (1, k, M_k) at ``speed_resolution`` mm/s (k <= 8 byte planes,
  each member its own), each resolution a float member; the reader gives back float64
  ``xy`` (M, 2), ``joints`` (M, j) and ``speed`` (M,) within half a resolution of what was
  saved (:func:`encode_counts` says how the counts are stored); ``width_counts_K`` (1, k,
  W_k) at ``width_resolution`` mm: the width at every sample of the block's variable-width
  trajectories (``variable``), in order. Version 4 had no widths; version 3 stored one
  block, as ``xy_counts``, ``joint_counts`` and ``speed_counts`` of 8 planes each without
  ``block_layer_start``; version 2 the
  float64 arrays ``xy``, ``joints`` and ``speed`` themselves; both are still read;
* ``traj_start`` (T + 1,) int64: trajectory i is rows ``traj_start[i]:traj_start[i+1]``;
* ``piece_start`` (Q,) int64 sample indices (within its trajectory) where pieces start
  and ``piece_owner`` (Q,) int64 the trajectory each belongs to;
* per trajectory (T,): ``duration`` float64 s, ``traj_dt`` float64 s, ``layer`` int64,
  ``path_index`` int64 (index within its layer), ``material`` int8 (0 part, 1 scaffold),
  ``role`` int8 (0 boundary, 1 fill, 2 measure, 3 travel), and the rest of its Path:
  ``width`` float64 mm, ``closed`` bool, ``tool`` str ("" = derived), ``path_z``
  float64 mm, ``variable`` bool (its Path has a width per point, and the trajectory a
  width per sample); a trajectory without a Path has width 0, closed False, tool "", z 0;
* ``span_owner`` (S,) int64 ascending and ``on_spans`` (S, 2) float64 s: the spans over
  which each continuous tour's valve is on (:attr:`icefab.core.Trajectory.on_spans`),
  each with its trajectory's index; version 5 files have none (their tours' valves then
  switch at the samples, as the widths do);
* per layer (L,): ``layer_index`` int64, ``layer_z`` float64 mm, ``layer_start`` (L+1,)
  int64 (trajectories of layer k are ``layer_start[k]:layer_start[k+1]``).

Version 1 trajectory files (no ``traj_dt``, ``width``, ``closed``, ``tool``, ``path_z``)
still load, with a logged warning: every trajectory gets ``dt``, width 0 (the valve stage
then uses the job's widths), closed False, the derived tool and the layer's z.

Errors: :class:`~icefab.errors.StackFileError` naming the file (and the member) when a
file is missing, truncated, corrupt or of another kind.

May import: ``icefab.core``, ``icefab.config``, ``icefab.errors``, ``icefab.atomic``,
``icefab._codec``.
"""

from __future__ import annotations

import collections.abc
import contextlib
import dataclasses
import functools
import logging
import math
import os
import stat
import struct
import sys
import threading
import tomllib
import zipfile
import zlib
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple, Sequence

import numpy as np

from icefab.atomic import atomic_path
from icefab.config import Job, stored_job_from_dict, to_toml
from icefab.core import (FRAMES, MATERIALS, OFF, ON1, ON2, ROLES, TOOLS, BuildMotion, Layer,
                         LayerMotion, LayerPaths, Region, RuledEdges, Stack, Toolpath,
                         Toolpaths, Trajectory, offsets, polyline_lengths, spans_fine,
                         spans_problem)
from icefab.errors import ConfigError, StackFileError

log = logging.getLogger(__name__)

STACK_FORMAT = "icefab-stack"
STACK_VERSION = 1
TOOLPATHS_FORMAT = "icefab-toolpaths"
TOOLPATHS_VERSION = 5
#: Versions load_toolpaths reads (1: without ``state``; 2: no per-point widths; 3: no
#: tours; 4: the points as floats). Until version 5 only 1 and the newest were let in.
TOOLPATHS_READABLE = (1, 2, 3, 4, 5)
#: Toolpath points are stored in counts of this grid (per mm): Clipper's
#: (``icefab.geometry.SCALE``), where the paths stage puts its points.
POINT_GRID_PER_MM = 10_000
TRAJECTORIES_FORMAT = "icefab-trajectories"
TRAJECTORIES_VERSION = 6
#: Versions load_trajectories reads (1: without per-trajectory dt and Path fields; 2: float
#: samples; 3: the samples in one block; 4: no per-sample widths; 5: no tours' spans).
TRAJECTORIES_READABLE = (1, 2, 3, 4, 5, 6)
#: Resolutions of the samples in a trajectory file (versions 3 to 6; each file stores its
#: own): 1 um of tool position (the Cobra 600 repeats to 17 um), 1e-5 rad (0.00057 deg,
#: finer than its 0.001 deg encoder counts) or 1e-5 mm of a joint, 0.01 mm/s of path
#: speed (1/12 500 of the 125 mm/s bound: the valve frequency follows the speed far more
#: finely than the calibration table knows the flow; at 1 um/s, version 3's, the speed took
#: a quarter of the bunny's 197 MB file).
XY_RESOLUTION_MM = 1e-3
#: ... and 0.1 um of a variable-width path's width (version 5): the flow is proportional
#: to it, so 1e-4 mm of a 0.15 mm bead is 0.07 % of its flow.
WIDTH_RESOLUTION_MM = 1e-4
JOINT_RESOLUTION = 1e-5
SPEED_RESOLUTION_MM_S = 1e-2

#: Codes of the path attributes in the files and worker packing (index = code).
MATERIAL_CODES = MATERIALS
ROLE_CODES = ROLES
FRAME_CODES = FRAMES
TOOL_CODES = TOOLS


# --------------------------------------------------------------------------- ragged arrays




def pack(items: Sequence[np.ndarray], empty: tuple[int, ...] = (0, 2),
         dtype: type | None = np.float64) -> tuple[np.ndarray, np.ndarray]:
    """Ragged arrays as ``(rows, offsets)``: ``rows`` the items concatenated (``empty``
    shape when there are none), ``offsets`` (n + 1,) int64 (:func:`offsets`)."""
    if items:
        rows = np.concatenate(items)
        if dtype is not None:
            rows = rows.astype(dtype)
    else:
        rows = np.zeros(empty, dtype=dtype or np.float64)
    return rows, offsets([len(a) for a in items])


def split(rows: np.ndarray, offs: np.ndarray) -> list[np.ndarray]:
    """The items of :func:`pack`'s ``(rows, offsets)`` (views into ``rows``)."""
    return [rows[a:b] for a, b in zip(offs[:-1], offs[1:])]


# --------------------------------------------------------------------------- common


#: zlib level of the result files' members: 1, the fastest. The float members (most of a
#: trajectory file) shrink by a fifth at any level; level 6 (numpy's savez_compressed)
#: took 1.5x as long as level 1 for 0.5 % less on the demo's trajectories.
COMPRESS_LEVEL = 1


def _write(path: str | os.PathLike, arrays: "dict[str, np.ndarray]") -> Path:
    """An ``.npz`` (numpy's zip of ``.npy`` members, as ``np.savez_compressed`` writes it,
    at :data:`COMPRESS_LEVEL`), written atomically."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp, zipfile.ZipFile(
            tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=COMPRESS_LEVEL) as zf:
        for name, value in arrays.items():
            with zf.open(name + ".npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)
    return target


#: Bounds a result file must respect before anything is decompressed or allocated: the
#: uncompressed size of one member and of all its members (declared in the zip directory;
#: a member that inflates beyond its declaration is a CRC error), and the size of the file
#: itself. A build of the thesis' scale is far below them.
MAX_MEMBER_BYTES = 1 << 30
MAX_TOTAL_BYTES = 3 << 29
MAX_FILE_BYTES = 1 << 31
#: Coordinates, heights and widths beyond this are not a build of any cell, mm.
MAX_COORD_MM = 1e5
#: Errors the zip and npy readers raise on damaged data (any npz icefab reads back).
NPZ_DAMAGE = (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, KeyError,
           NotImplementedError, RuntimeError, SyntaxError, TypeError, struct.error,
           UnicodeDecodeError)
_KIND_NAMES = {"f": "floating point", "iu": "integers", "b": "booleans", "U": "text",
               "fiu": "a number"}


class _Members:
    """The members of one result file, read one at a time and checked before reading.

    Only members a loader asks for are decompressed; a member is read only when its declared
    size, dtype and shape fit what is asked. Every problem is a StackFileError naming the
    file and the member.
    """

    def __init__(self, path: Path, what: str) -> None:
        self.path, self.what, self.zip = path, what, None
        try:
            st = path.stat()
        except FileNotFoundError:
            raise StackFileError(f"{path}: {what} file not found") from None
        except OSError as exc:
            raise StackFileError(f"{path}: cannot read the {what} file ({exc.strerror or exc})"
                                 ) from None
        if not stat.S_ISREG(st.st_mode):
            raise StackFileError(f"{path}: not a regular file, expected a {what} file (.npz)")
        if st.st_size > MAX_FILE_BYTES:
            raise StackFileError(f"{path}: {st.st_size} bytes, more than a {what} file may have "
                                 f"({MAX_FILE_BYTES})")
        try:
            self.zip = zipfile.ZipFile(path)
            infos = self.zip.infolist()
        except NPZ_DAMAGE as exc:
            self.close()
            raise StackFileError(f"{path}: not a readable {what} file (not a numpy .npz "
                                 f"archive: {exc})") from None
        self.infos: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            name = info.filename[:-4]
            if name in self.infos or not info.filename.endswith(".npy"):
                self.close()
                raise StackFileError(f"{path}: member {info.filename[:80]!r}: not a numpy "
                                     "array or given twice; not an icefab result file")
            self.infos[name] = info

    def __enter__(self) -> "_Members":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.zip is not None:
            self.zip.close()
            self.zip = None

    def bad(self, name: str | None, msg: str) -> StackFileError:
        where = f"{self.path}: member {name}" if name else f"{self.path}"
        return StackFileError(f"{where}: {msg}")

    @property
    def names(self) -> set[str]:
        return set(self.infos)

    def expect(self, required: Sequence[str], optional: Sequence[str] = (),
               streamed: Sequence[str] = ()) -> None:
        """Every required member present, no member outside required + optional, and their
        declared sizes within the bounds; the ``streamed`` members (read a block at a time,
        :meth:`block_bound`) are left out of the total."""
        missing = [k for k in required if k not in self.infos]
        if missing:
            raise self.bad(None, f"not a complete {self.what} file: missing arrays "
                           f"{', '.join(missing)}")
        extra = sorted(self.names - set(required) - set(optional))
        if extra:
            raise self.bad(None, f"unexpected members {', '.join(x[:40] for x in extra[:5])} "
                           "(not written by icefab: the file is corrupt or of another kind)")
        total = sum(self.infos[k].file_size for k in self.names - set(streamed))
        if total > MAX_TOTAL_BYTES:
            raise self.bad(None, f"{total} bytes uncompressed, more than a {self.what} file "
                           f"may hold ({MAX_TOTAL_BYTES})")

    def block_bound(self, names: Sequence[str]) -> None:
        """The members read together as one block hold at most MAX_TOTAL_BYTES."""
        total = sum(self.infos[k].file_size for k in names)
        if total > MAX_TOTAL_BYTES:
            raise self.bad(names[0], f"its block holds {total} bytes uncompressed, more than "
                           f"a {self.what} file may hold at once ({MAX_TOTAL_BYTES})")

    def array(self, name: str, kinds: str, ndim: int, cols: int | None = None) -> np.ndarray:
        """Member ``name``: dtype kind one of ``kinds`` ("f" float, "i" signed and "u"
        unsigned integer, "b" bool, "U" text), ``ndim`` dimensions, ``cols`` columns."""
        info = self.infos.get(name)
        if info is None:
            raise self.bad(name, "missing")
        if info.file_size > MAX_MEMBER_BYTES:
            raise self.bad(name, f"{info.file_size} bytes uncompressed, more than a member may "
                           f"hold ({MAX_MEMBER_BYTES})")
        try:
            with self.zip.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
                elif version == (2, 0):
                    shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
                else:
                    raise self.bad(name, f"npy format version {version}, expected 1.0 or 2.0")
                if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
                    raise self.bad(name, f"dtype {dtype}: objects or records, expected plain "
                                   "numbers or text")
                if dtype.kind not in kinds or dtype.itemsize == 0:
                    raise self.bad(name, f"dtype {dtype}, expected {_KIND_NAMES[kinds]}")
                if len(shape) != ndim or (cols is not None and shape[1] != cols):
                    want = "()" if ndim == 0 else "(n,)" if ndim == 1 else f"(n, {cols or 'm'})"
                    raise self.bad(name, f"shape {shape}, expected {want}")
                count = math.prod(shape)
                nbytes = count * dtype.itemsize
                held = info.file_size - fh.tell()
                if nbytes != held:
                    raise self.bad(name, f"shape {shape} of {dtype} needs {nbytes} bytes, the "
                                   f"member holds {held}")
                buf = bytearray(nbytes)
                if fh.readinto(buf) != nbytes:
                    raise self.bad(name, "truncated")
        except StackFileError:
            raise
        except NPZ_DAMAGE as exc:
            raise self.bad(name, f"unreadable ({type(exc).__name__}: {exc})") from None
        arr = np.frombuffer(buf, dtype=dtype, count=count)
        if not dtype.isnative:
            arr = arr.astype(dtype.newbyteorder("="))
        return arr.reshape(shape, order="F" if fortran else "C")

    def text(self, name: str) -> str:
        return str(self.array(name, "U", 0)[()])

    def integer(self, name: str) -> int:
        return int(self.array(name, "iu", 0)[()])

    def number(self, name: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
        v = float(self.array(name, "fiu", 0)[()])
        if not (math.isfinite(v) and (v > lo if lo_open else v >= lo) and v <= hi):
            raise self.bad(name, f"{v!r}, expected a number in {'(' if lo_open else '['}{lo:g}, "
                           f"{hi:g}]")
        return v

    def values(self, name: str, kinds: str, ndim: int, cols: int | None = None, *,
               n: int | None = None, lo: float | None = None, hi: float | None = None,
               nan_ok: bool = False) -> np.ndarray:
        """:meth:`array` with ``n`` rows and every value finite (NaN allowed if ``nan_ok``)
        within ``[lo, hi]``."""
        a = self.array(name, kinds, ndim, cols)
        if n is not None and len(a) != n:
            raise self.bad(name, f"{len(a)} rows, expected {n}: the file is corrupt")
        if a.size and a.dtype.kind in "fiu":
            v = a[~np.isnan(a)] if nan_ok and a.dtype.kind == "f" else a
            if v.dtype.kind == "f" and not np.isfinite(v).all():
                raise self.bad(name, "NaN or infinite values, expected finite numbers")
            if v.size and lo is not None and v.min() < lo:
                raise self.bad(name, f"value {v.min().item()!r} below {lo:g}")
            if v.size and hi is not None and v.max() > hi:
                raise self.bad(name, f"value {v.max().item()!r} above {hi:g}")
        return a

    def offsets(self, name: str, n_items: int | None, n_rows: int | None) -> np.ndarray:
        """(n_items + 1,) int64 offsets into ``n_rows`` rows: from 0 to n_rows, never
        decreasing (``n_items`` None: any count; ``n_rows`` None: any end, e.g. rows
        stored in blocks that are checked against it when read)."""
        a = self.array(name, "iu", 1)
        if n_items is not None and len(a) != n_items + 1:
            raise self.bad(name, f"{len(a)} offsets for {n_items} items, expected "
                           f"{n_items + 1}: the file is corrupt")
        b = a.astype(np.int64)
        end = n_rows if n_rows is not None else (int(b[-1]) if len(b) else 0)
        if len(b) == 0 or b[0] != 0 or b[-1] != end or np.any(np.diff(b) < 0) \
                or np.any(b != a):
            raise self.bad(name, f"offsets must run from 0 to {end} without decreasing: "
                           "the file is corrupt")
        return b

    def codes(self, name: str, table: Sequence[str], n: int) -> np.ndarray:
        return self.values(name, "iu", 1, n=n, lo=0, hi=len(table) - 1).astype(np.int64)

    def header(self, fmt: str, readable: Sequence[int]) -> int:
        """Check ``format`` (first, so another kind of file is named as such) and
        ``version``; returns the version."""
        if "format" not in self.infos:
            raise self.bad(None, f"not an icefab {self.what} file (no format member)")
        found = self.text("format")
        if found != fmt:
            raise self.bad(None, f"not an icefab {self.what} file (format {found[:80]!r}, "
                           f"expected {fmt!r})")
        version = self.integer("version")
        if version not in readable:
            raise self.bad("version", f"{self.what} file version {version}: this icefab reads "
                           f"version {' or '.join(map(str, readable))}")
        return version

    def job(self):
        try:
            return _job_from_toml(self.text("job"))
        except (tomllib.TOMLDecodeError, ConfigError) as exc:
            raise self.bad("job", f"the stored job is invalid ({exc})") from None

    def strings(self, name: str) -> tuple[str, ...]:
        return tuple(str(w) for w in self.array(name, "U", 1))


@functools.lru_cache(maxsize=8)
def _job_from_toml(text: str):
    """The Job a result file stores (cached: the files of one build share it, and a Job is
    frozen)."""
    return stored_job_from_dict(tomllib.loads(text))


def _check_tree(m: _Members, name: str, parent: np.ndarray, first: np.ndarray) -> None:
    """Ring parents: ``parent[i]`` (index within its layer, -1 top level) must name another
    ring of the same layer and the chains must end (a cycle would hang ``Region.depth``).
    ``first[i]``: global index of the first ring of ring i's layer."""
    r = len(parent)
    if r == 0:
        return
    g = np.where(parent >= 0, parent + first, -1)
    if np.any(g == np.arange(r)):
        raise m.bad(name, "a ring is its own parent: the file is corrupt")
    jump = g
    for _ in range(int(r).bit_length() + 1):  # pointer doubling: 2^k-th ancestors
        nxt = np.where(jump >= 0, jump[np.maximum(jump, 0)], -1)
        if np.array_equal(nxt, jump):
            break
        jump = nxt
    if np.any(jump >= 0):
        raise m.bad(name, "ring parents form a cycle: the file is corrupt")


def file_format(path: str | os.PathLike) -> str:
    """The ``format`` member of an icefab ``.npz`` result file ("" when it has none);
    reads only that member. StackFileError when the file is missing or not a readable npz."""
    with _Members(Path(path), "result") as m:
        return m.text("format") if "format" in m.names else ""


# --------------------------------------------------------------------------- layer heights


def _heights(values: Sequence[float]) -> dict[str, np.ndarray]:
    """The optional ``layer_height`` member (L,) float64 mm: every layer's own thickness
    (adaptive slicing), written only when the layers have one, so uniform builds keep
    their files unchanged."""
    h = np.asarray(list(values), dtype=np.float64)
    return {"layer_height": h} if h.size and np.isfinite(h).any() else {}


def _tops(values: Sequence[float]) -> dict[str, np.ndarray]:
    """The optional ``layer_top_z`` member (L,) float64 mm: every layer's top surface (the
    stack's), written when some layer knows it (layers made by hand may not)."""
    h = np.asarray(list(values), dtype=np.float64)
    return {"layer_top_z": h} if h.size and np.isfinite(h).any() else {}


def _read_tops(m: "_Members", z: np.ndarray) -> np.ndarray:
    """(n,) float64: the ``layer_top_z`` member, or NaN (derived from ``z``, the layers'
    cutting planes) without; a top below its layer's cutting plane is corruption."""
    if "layer_top_z" not in m.names:
        return np.full(len(z), np.nan)
    top = m.values("layer_top_z", "f", 1, n=len(z), lo=-MAX_COORD_MM, hi=MAX_COORD_MM,
                   nan_ok=True).astype(np.float64)
    # a micrometre of slack for the rounding of a plane cut at the top (cut_fraction 1)
    if np.any(top < np.asarray(z, dtype=np.float64) - 1e-3):   # NaN compares False
        raise m.bad("layer_top_z", "a layer's top below its cutting plane layer_z: the file "
                    "is corrupt")
    return top


def _read_heights(m: "_Members", n: int) -> np.ndarray:
    """(n,) float64: the ``layer_height`` member, or NaN (the job's thickness) without."""
    if "layer_height" not in m.names:
        return np.full(n, np.nan)
    h = m.values("layer_height", "f", 1, n=n, lo=0.0, hi=1e3)
    if np.any(h <= 0):
        raise m.bad("layer_height", "a layer thickness <= 0: the file is corrupt")
    return h


# --------------------------------------------------------------------------- stack


def _pack_regions(regions: list[Region]) -> dict[str, np.ndarray]:
    points, ring_offsets = pack([r for reg in regions for r in reg.rings])
    return {
        "points": points,
        "ring_offsets": ring_offsets,
        "ring_parent": (np.concatenate([np.asarray(reg.parent, dtype=np.int64)
                                        for reg in regions])
                        if regions else np.zeros(0, dtype=np.int64)),
        "ring_layer": np.repeat(np.arange(len(regions), dtype=np.int64),
                                [len(reg.rings) for reg in regions]),
    }


def _unpack_regions(m: _Members, n_layers: int, prefix: str = "") -> list[Region]:
    """The regions of every layer from the ring members under ``prefix``, checked: finite
    points within MAX_COORD_MM, offsets, layers ascending, parents inside their layer and
    without cycles."""
    pts = m.values(prefix + "points", "f", 2, 2, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
    lay = m.values(prefix + "ring_layer", "iu", 1, lo=0, hi=max(n_layers - 1, 0))
    n_r = len(lay)
    if n_r and n_layers == 0:
        raise m.bad(prefix + "ring_layer", "rings but no layers: the file is corrupt")
    if np.any(np.diff(lay.astype(np.int64)) < 0):
        raise m.bad(prefix + "ring_layer", "layers not in ascending order: the file is corrupt")
    off = m.offsets(prefix + "ring_offsets", n_r, len(pts))
    if n_r and np.any(np.diff(off) < 3):
        raise m.bad(prefix + "ring_offsets", "a ring with fewer than 3 points: the file is "
                    "corrupt")
    lay = lay.astype(np.int64)
    starts = np.searchsorted(lay, np.arange(n_layers + 1))
    count = np.diff(starts)[lay] if n_r else np.zeros(0, np.int64)
    par = m.values(prefix + "ring_parent", "iu", 1, n=n_r, lo=-1).astype(np.int64)
    if n_r and np.any(par >= count):
        raise m.bad(prefix + "ring_parent", "ring parent out of range of its layer: the file "
                    "is corrupt")
    _check_tree(m, prefix + "ring_parent", par, starts[lay] if n_r else lay)
    rings = split(pts, off)
    return [Region(rings=tuple(rings[starts[k]:starts[k + 1]]),
                   parent=par[starts[k]:starts[k + 1]].copy()) for k in range(n_layers)]


_STACK_REQUIRED = ("format", "version", "points", "ring_offsets", "ring_parent", "ring_layer",
                   "layer_index", "layer_z", "layer_top_z", "layer_thickness", "warnings", "job")
_STACK_SCAFFOLD = ("scaffold_points", "scaffold_ring_offsets", "scaffold_ring_parent",
                   "scaffold_ring_layer")


def save_stack(stack: Stack, path: str | os.PathLike) -> Path:
    """Write a stack to ``path`` (``.npz``, layout in the module docstring), atomically.

    Returns the path written.
    """
    regions = [L.part for L in stack.layers]
    arrays: dict[str, np.ndarray] = {
        "format": np.array(STACK_FORMAT),
        "version": np.array(STACK_VERSION),
        "layer_index": np.array([L.index for L in stack.layers], dtype=np.int64),
        "layer_z": np.array([L.z for L in stack.layers], dtype=np.float64),
        "layer_top_z": np.array([L.top_z for L in stack.layers], dtype=np.float64),
        "layer_thickness": np.array(float(stack.layer_thickness)),
        "warnings": np.array(list(stack.warnings), dtype=str),
        "job": np.array(to_toml(stack.job)),
        **_pack_regions(regions),
        **_heights([L.thickness for L in stack.layers]),
    }
    if any(not L.scaffold.is_empty for L in stack.layers):
        arrays.update({"scaffold_" + k: v for k, v in
                       _pack_regions([L.scaffold for L in stack.layers]).items()})
    return _write(path, arrays)


def load_stack(path: str | os.PathLike) -> Stack:
    """Read a stack written by :func:`save_stack`, checking every member (module docstring).

    Raises StackFileError naming the file (and the member) when it is missing, truncated,
    corrupt or not a stack file.
    """
    with _Members(Path(path), "stack") as m:
        m.header(STACK_FORMAT, (STACK_VERSION,))
        m.expect(_STACK_REQUIRED, _STACK_SCAFFOLD + ("layer_height",))
        has_scaffold = [k in m.names for k in _STACK_SCAFFOLD]
        if any(has_scaffold) and not all(has_scaffold):
            raise m.bad(None, "scaffold ring members incomplete: the file is corrupt")
        job = m.job()
        thickness = m.number("layer_thickness", 0.0, 1e3, lo_open=True)
        index = m.values("layer_index", "iu", 1, lo=0, hi=2**31 - 1)
        n = len(index)
        z = m.values("layer_z", "f", 1, n=n, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        top = m.values("layer_top_z", "f", 1, n=n, lo=-MAX_COORD_MM, hi=MAX_COORD_MM,
                       nan_ok=True)
        warnings = m.strings("warnings")
        heights = _read_heights(m, n)
        parts = _unpack_regions(m, n)
        scaffolds = (_unpack_regions(m, n, "scaffold_") if all(has_scaffold)
                     else [Region() for _ in range(n)])
    layers = tuple(Layer(index=int(index[k]), z=float(z[k]), part=parts[k],
                         scaffold=scaffolds[k], top_z=float(top[k]),
                         thickness=float(heights[k])) for k in range(n))
    return Stack(layers=layers, job=job, layer_thickness=thickness, warnings=warnings)


# --------------------------------------------------------------------------- toolpaths


def pack_paths(paths: Sequence[Toolpath]) -> dict[str, np.ndarray]:
    """The paths as flat arrays (the toolpath file's per-point and per-path members, the
    worker processes' packing): ``points``, ``path_start``, ``z``, ``material``, ``role``,
    ``closed``, ``width``, ``layer``, ``frame``, ``tool``, and ``variable`` and
    ``point_width`` when some path has per-point widths, ``point_off`` when some path has
    ``off`` segments (a continuous tour)."""
    points, start = pack([p.points for p in paths])

    def codes(attr: str, table: Sequence[str]) -> np.ndarray:
        code = {name: k for k, name in enumerate(table)}
        return np.array([code[getattr(p, attr)] for p in paths], dtype=np.int8)
    variable = np.array([p.widths is not None for p in paths], dtype=bool)
    extra = {}
    if variable.any():
        extra = {"variable": variable,
                 "point_width": np.concatenate([np.asarray(p.widths, np.float64)
                                                for p in paths if p.widths is not None])}
    if any(p.off is not None for p in paths):
        extra["point_off"] = np.concatenate(
            [np.zeros(len(p.points), dtype=bool) if p.off is None
             else np.asarray(p.off, dtype=bool) for p in paths])
    return {
        "points": points,
        "path_start": start,
        "z": np.array([p.z for p in paths], dtype=np.float64),
        "material": codes("material", MATERIAL_CODES),
        "role": codes("role", ROLE_CODES),
        "closed": np.array([p.closed for p in paths], dtype=bool),
        "width": np.array([p.width for p in paths], dtype=np.float64),
        "layer": np.array([p.layer for p in paths], dtype=np.int64),
        "frame": codes("frame", FRAME_CODES),
        "tool": codes("tool", TOOL_CODES),
        **extra,
    }


def _point_states(packed: dict[str, np.ndarray]) -> np.ndarray:
    """:func:`icefab.core.point_states` of every path of :func:`pack_paths`' arrays, at
    once: each path's state at all its points, OFF at the last point of an open path and
    where ``point_off`` is set."""
    start = packed["path_start"]
    role, material = packed["role"], packed["material"]
    depositing = np.isin(role, [ROLE_CODES.index("boundary"), ROLE_CODES.index("fill")])
    state = np.where(depositing, np.where(material == MATERIAL_CODES.index("part"), ON1, ON2),
                     OFF).astype(np.int8)
    out = np.repeat(state, np.diff(start))
    ends = start[1:] - 1
    last = ~packed["closed"] & (np.diff(start) > 0)
    out[ends[last]] = OFF
    if "point_off" in packed:
        out[np.asarray(packed["point_off"], dtype=bool)] = OFF
    return out


def packed_polylines(d: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Every path's :meth:`~icefab.core.Toolpath.polyline` (closed ones back to their first
    point) of :func:`pack_paths`' arrays, concatenated: points (N, 2) and counts (P,), as
    the paths would give them, without a Toolpath."""
    start = d["path_start"]
    n = np.diff(start)
    close = d["closed"].astype(bool) & (n > 1)
    order = np.insert(np.arange(len(d["points"])), start[1:][close], start[:-1][close])
    return d["points"][order], n + close


def packed_lengths(d: dict[str, np.ndarray]) -> np.ndarray:
    """(P,) float64 mm: the length of every path of :func:`pack_paths`' arrays, closed ones
    back to their first point: ``polyline_lengths(*packed_polylines(d))`` bit for bit,
    without the closed copy of the points (``icefab paths`` tallies the bunny's 17 M
    points as they come)."""
    pts, start = d["points"], d["path_start"]
    n = np.diff(start)
    out = polyline_lengths(pts, n)
    # the closing edges, each added after its path's own steps (as bincount adds them)
    close = np.flatnonzero(d["closed"].astype(bool) & (n > 1))
    first, last = start[close], start[close + 1] - 1
    cx, cy = pts[first, 0] - pts[last, 0], pts[first, 1] - pts[last, 1]
    out[close] += np.sqrt(cx * cx + cy * cy)
    return out


def packed_tools(d: dict[str, np.ndarray]) -> np.ndarray:
    """(P,) the :attr:`~icefab.core.Toolpath.tool_name` of every path of
    :func:`pack_paths`' arrays ("" where the points are in the robot base frame)."""
    tool = np.array(TOOL_CODES, dtype=object)[d["tool"]]
    derived = np.where(d["role"] == ROLE_CODES.index("measure"), "laser",
                       np.array(MATERIAL_CODES, dtype=object)[d["material"]])
    out = np.where(tool != "", tool, derived)
    return np.where(d["frame"] == FRAME_CODES.index("base"), "", out)


def unpack_paths(d: dict[str, np.ndarray], copy: bool = False) -> list[Toolpath]:
    """The paths of :func:`pack_paths`' arrays (points are views unless ``copy``)."""
    pts, start = d["points"], d["path_start"].tolist()
    fields = zip(start[:-1], start[1:], d["z"].tolist(), d["material"].tolist(),
                 d["role"].tolist(), d["closed"].tolist(), d["width"].tolist(),
                 d["layer"].tolist(), d["frame"].tolist(), d["tool"].tolist())
    paths = [Toolpath(pts[a:b].copy() if copy else pts[a:b], float(z), MATERIAL_CODES[m],
                      ROLE_CODES[r], bool(c), float(w), int(ly), FRAME_CODES[f],
                      TOOL_CODES[t])
             for a, b, z, m, r, c, w, ly, f, t in fields]
    if "variable" in d:
        pw = d["point_width"]
        idx = np.flatnonzero(d["variable"])
        ws = offsets(np.diff(d["path_start"])[idx])
        for j, i in enumerate(idx.tolist()):
            w = pw[ws[j]:ws[j + 1]]
            object.__setattr__(paths[i], "widths", w.copy() if copy else w)
    if "point_off" in d:
        po = np.asarray(d["point_off"], dtype=bool)
        owner = np.repeat(np.arange(len(paths)), np.diff(d["path_start"]))
        for i in np.unique(owner[po]).tolist():
            object.__setattr__(paths[i], "off", po[start[i]:start[i + 1]].copy())
    return paths


def pack_layer_paths(lp: LayerPaths) -> tuple:
    """One layer's paths for the trip back from a worker process (one pickled object per
    path would cost more than planning a small layer)."""
    return lp.index, lp.z, lp.unfilled_mm2, pack_paths(lp.paths), lp.thickness, lp.top_z


def unpack_layer_paths(packed: tuple) -> LayerPaths:
    index, z, unfilled, arrays, thickness, top_z = packed
    return LayerPaths(index, z, tuple(unpack_paths(arrays)), unfilled, thickness, top_z)


def concat_packed(parts: Sequence[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """:func:`pack_paths` of all the paths of ``parts`` (each :func:`pack_paths` of some
    paths), in order: equal to packing them again, without a Toolpath in sight (the
    workers of ``icefab paths`` send their layers packed: packing the bunny's 432 k paths
    again for the file took 1.4 s, issue 17)."""
    if not parts:
        return pack_paths([])
    n_points = np.array([len(d["points"]) for d in parts], dtype=np.int64)
    shift = np.concatenate([[0], np.cumsum(n_points)[:-1]])
    out = {"points": np.concatenate([d["points"] for d in parts]).astype(np.float64,
                                                                       copy=False),
           "path_start": np.concatenate(
               [d["path_start"][:-1] + s for d, s in zip(parts, shift)]
               + [np.array([n_points.sum()], dtype=np.int64)]).astype(np.int64)}
    for key in ("z", "material", "role", "closed", "width", "layer", "frame", "tool"):
        out[key] = np.concatenate([d[key] for d in parts])
    if any("variable" in d for d in parts):
        out["variable"] = np.concatenate(
            [d["variable"] if "variable" in d else np.zeros(len(d["z"]), dtype=bool)
             for d in parts])
        out["point_width"] = np.concatenate([d["point_width"] for d in parts
                                             if "variable" in d]).astype(np.float64,
                                                                         copy=False)
    if any("point_off" in d for d in parts):
        out["point_off"] = np.concatenate(
            [d["point_off"] if "point_off" in d else np.zeros(len(d["points"]), dtype=bool)
             for d in parts])
    return out


class LayerHead(NamedTuple):
    """A layer of a toolpath file but its paths: what :func:`save_toolpath_layers` takes
    beside the layer's packed paths (``icefab paths`` writes the workers' packed layers
    without making their Toolpaths, issue 17); a LayerPaths serves as well."""

    index: int
    z: float
    #: (part, scaffold) mm^2 that no path sweeps.
    unfilled_mm2: tuple[float, float]
    #: The layer's own thickness, mm; NaN: the job's.
    thickness: float = math.nan
    #: The layer's top surface, mm (the stack's); NaN: not known.
    top_z: float = math.nan


def save_toolpaths(tp: Toolpaths, path: str | os.PathLike) -> None:
    """Write toolpaths to a ``.npz`` file (layout in the module docstring), atomically."""
    save_toolpath_layers(path, tp.job, tp.warnings, tp.layers,
                         [pack_paths(lp.paths) for lp in tp.layers])


def save_toolpath_layers(path: str | os.PathLike, job: Job, warnings: Sequence[str],
                         layers: Sequence[LayerHead | LayerPaths],
                         packed_layers: Sequence[dict[str, np.ndarray]]) -> None:
    """:func:`save_toolpaths` of layers given as their heads (index, z, unfilled area,
    thickness, top: :class:`LayerHead` or LayerPaths) and their paths as :func:`pack_paths`
    packed them, one dict per layer (``icefab paths``: as its workers send them)."""
    if len(packed_layers) != len(layers):
        raise ValueError(f"save_toolpath_layers: {len(packed_layers)} packed layers for "
                         f"{len(layers)} layers")
    packed = concat_packed(packed_layers)
    data = {
        "format": np.array(TOOLPATHS_FORMAT),
        "version": np.array(TOOLPATHS_VERSION),
        "job": np.array(to_toml(job)),
        "warnings": np.array(list(warnings), dtype=str),
        **encode_points(packed.pop("points")),
        "state": _point_states(packed),
        **packed,
        "layer_index": np.array([lp.index for lp in layers], dtype=np.int64),
        "layer_z": np.array([lp.z for lp in layers], dtype=np.float64),
        "layer_start": offsets([len(d["z"]) for d in packed_layers]),
        "unfilled_mm2": np.array([lp.unfilled_mm2 for lp in layers],
                                 dtype=np.float64).reshape(-1, 2),
        **_heights([lp.thickness for lp in layers]),
        **_tops([lp.top_z for lp in layers]),
    }
    _write(path, data)


_TOOLPATHS_REQUIRED = ("format", "version", "job", "warnings", "path_start", "z",
                       "material", "role", "closed", "width", "layer", "frame", "tool",
                       "layer_index", "layer_z", "layer_start", "unfilled_mm2")
_POINT_MEMBERS = ("point_counts", "point_exact_index", "point_exact")


def encode_points(points: np.ndarray) -> dict[str, np.ndarray]:
    """A toolpath file's points (N, 2) mm as its members ``point_counts``,
    ``point_exact_index`` and ``point_exact`` (module docstring); :func:`decode_points`
    gives back the same floats, bit for bit. A coordinate at a time and only the byte
    planes kept, so the bunny's 21 M points need a few hundred MB beside them, not four
    times their size (``icefab paths`` peaked at 1.91 GB; issue 17)."""
    from icefab._codec import encode_plane_column

    pts = np.asarray(points, np.float64).reshape(-1, 2)
    exact = np.zeros(len(pts), dtype=bool)

    def counts(c: int) -> np.ndarray:
        col = pts[:, c]
        q = np.rint(col * POINT_GRID_PER_MM)
        # on the grid: the count gives the float back (-0.0 is not 0 / 1e4) and is a
        # whole number a float holds; else the float is stored and the count is 0
        off = np.divide(q, POINT_GRID_PER_MM) != col
        off |= (q > 2.0 ** 53) | (q < -2.0 ** 53)
        off |= (col == 0.0) & np.signbit(col)
        q[off] = 0.0
        exact[off] = True
        return q

    # each column's counts are made twice, to count the planes and to fill them: both
    # columns' counts at once would cost 16 bytes a point
    k = max(encode_plane_column(counts(c), 1.0, np.empty((0, len(pts)), np.uint8))
            for c in range(2))
    planes = np.empty((2, k, len(pts)), np.uint8)
    for c in range(2):
        encode_plane_column(counts(c), 1.0, planes[c])
    index = np.flatnonzero(exact)
    return {"point_counts": planes, "point_exact_index": index.astype(np.int64),
            "point_exact": np.ascontiguousarray(pts[index])}


def decode_points(m: "_Members") -> np.ndarray:
    """The points (N, 2) mm of a version 5 toolpath file, checked like the float
    ``points`` of older versions."""
    planes = m.array("point_counts", "u", 3)
    if planes.dtype.itemsize != 1 or planes.shape[0] != 2 or not 1 <= planes.shape[1] <= 8:
        raise m.bad("point_counts", f"{planes.dtype} of shape {planes.shape}, expected uint8 "
                    "byte planes of shape (2, 1..8, n): the file is corrupt")
    pts = decode_counts(planes, 1.0) / POINT_GRID_PER_MM
    del planes
    n = len(pts)
    idx = m.values("point_exact_index", "iu", 1, lo=0, hi=max(n - 1, 0)).astype(np.int64)
    if len(idx) and (n == 0 or np.any(np.diff(idx) <= 0)):
        raise m.bad("point_exact_index", "not increasing indices of points: the file is "
                    "corrupt")
    pts[idx] = m.values("point_exact", "f", 2, 2, n=len(idx), lo=-MAX_COORD_MM,
                        hi=MAX_COORD_MM)
    if n and not (np.abs(pts).max() <= MAX_COORD_MM):
        raise m.bad("point_counts", f"a coordinate beyond {MAX_COORD_MM:g} mm: the file is "
                    "corrupt")
    return pts


def load_toolpaths(path: str | os.PathLike) -> Toolpaths:
    """Read a file written by :func:`save_toolpaths`, checking every member (module
    docstring); StackFileError naming the file (and the member) if it is missing,
    truncated, corrupt or not a toolpath file."""
    return load_packed_toolpaths(path).toolpaths()


def load_packed_toolpaths(path: str | os.PathLike) -> PackedToolpaths:
    """:func:`load_toolpaths` without making a Toolpath: the same checks, the build as
    :class:`PackedToolpaths`."""
    with _Members(Path(path), "toolpath") as m:
        version = m.header(TOOLPATHS_FORMAT, TOOLPATHS_READABLE)
        m.expect(_TOOLPATHS_REQUIRED + (("state",) if version >= 2 else ())
                 + (_POINT_MEMBERS if version >= 5 else ("points",)),
                 ("layer_height", "layer_top_z")
                 + (("variable", "point_width") if version >= 3 else ())
                 + (("point_off",) if version >= 4 else ()))
        job = m.job()
        warnings = m.strings("warnings")
        if version >= 5:
            pts = decode_points(m)
        else:
            pts = m.values("points", "f", 2, 2, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        z = m.values("z", "f", 1, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        n_paths = len(z)
        d = {"points": pts, "z": z,
             "path_start": m.offsets("path_start", n_paths, len(pts)),
             "material": m.codes("material", MATERIAL_CODES, n_paths),
             "role": m.codes("role", ROLE_CODES, n_paths),
             "frame": m.codes("frame", FRAME_CODES, n_paths),
             "tool": m.codes("tool", TOOL_CODES, n_paths),
             "closed": m.values("closed", "b", 1, n=n_paths),
             "width": m.values("width", "f", 1, n=n_paths, lo=0.0, hi=MAX_COORD_MM),
             "layer": m.values("layer", "iu", 1, n=n_paths, lo=-1, hi=2**31 - 1)}
        if ("variable" in m.names) != ("point_width" in m.names):
            raise m.bad(None, "members 'variable' and 'point_width' come together: one is "
                        "missing")
        if "variable" in m.names:
            d["variable"] = m.values("variable", "b", 1, n=n_paths)
            n_var = int(np.diff(d["path_start"])[d["variable"].astype(bool)].sum())
            d["point_width"] = m.values("point_width", "f", 1, n=n_var, lo=0.0,
                                        hi=MAX_COORD_MM)
        if "point_off" in m.names:
            d["point_off"] = m.values("point_off", "b", 1, n=len(pts))
            if np.any(d["point_off"] & ~np.repeat(
                    np.isin(d["role"], [ROLE_CODES.index("boundary"), ROLE_CODES.index("fill")]),
                    np.diff(d["path_start"]))):
                raise m.bad("point_off", "off segments on a path that deposits nothing")
        index = m.values("layer_index", "iu", 1, lo=-1, hi=2**31 - 1)
        n_layers = len(index)
        layer_z = m.values("layer_z", "f", 1, n=n_layers, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        ls = m.offsets("layer_start", n_layers, n_paths)
        unfilled = m.values("unfilled_mm2", "f", 2, 2, n=n_layers, lo=0.0,
                            hi=MAX_COORD_MM ** 2)
        heights = _read_heights(m, n_layers)
        tops = _read_tops(m, layer_z)
        if version >= 2:
            state = m.values("state", "iu", 1, n=len(pts), lo=OFF, hi=ON2)
            if n_paths and not np.array_equal(state, _point_states(d)):
                raise m.bad("state", "per-point states disagree with the paths' materials and "
                            "roles: the file is corrupt")
    heads = tuple(LayerHead(int(index[j]), float(layer_z[j]),
                            (float(unfilled[j, 0]), float(unfilled[j, 1])), float(heights[j]),
                            float(tops[j]))
                  for j in range(n_layers))
    return PackedToolpaths(job, tuple(warnings), heads, tuple(_split_packed(d, ls)))


def _split_packed(d: dict[str, np.ndarray], layer_start: np.ndarray
                  ) -> list[dict[str, np.ndarray]]:
    """:func:`pack_paths`' arrays of many layers cut into each layer's (views; the path
    starts counted from the layer's first point), layer j holding paths
    ``layer_start[j]:layer_start[j + 1]``."""
    start = d["path_start"]
    var = d.get("variable")
    if var is not None:   # where each path's point widths begin
        wstart = offsets(np.where(var.astype(bool), np.diff(start), 0))
    out = []
    for a, b in zip(layer_start[:-1].tolist(), layer_start[1:].tolist()):
        p0, p1 = int(start[a]), int(start[b])
        layer = {"points": d["points"][p0:p1], "path_start": start[a:b + 1] - p0}
        for key in ("z", "material", "role", "closed", "width", "layer", "frame", "tool"):
            layer[key] = d[key][a:b]
        if var is not None and var[a:b].any():
            layer["variable"] = var[a:b]
            layer["point_width"] = d["point_width"][int(wstart[a]):int(wstart[b])]
        if "point_off" in d and d["point_off"][p0:p1].any():
            layer["point_off"] = d["point_off"][p0:p1]
        out.append(layer)
    return out


@dataclasses.dataclass(frozen=True, eq=False)
class PackedToolpaths:
    """A toolpath file's build as its arrays, layer by layer, with no Toolpath made
    (:func:`load_packed_toolpaths`; ``icefab plan`` checks and ships the layers so, issue
    17: the bunny's 432 k Toolpaths took 2.2 s to make before any planning began).

    job, warnings: the file's; heads: per layer its :class:`LayerHead`; layers: per layer
    its paths as :func:`pack_paths` packs them (views into the file's arrays).
    """

    job: Job
    warnings: tuple[str, ...]
    heads: tuple[LayerHead, ...]
    layers: tuple[dict[str, np.ndarray], ...]

    def __len__(self) -> int:
        return len(self.heads)

    def packed_layer(self, k: int) -> tuple:
        """Layer k as :func:`pack_layer_paths` gives it (what the workers take)."""
        h = self.heads[k]
        return h.index, h.z, h.unfilled_mm2, self.layers[k], h.thickness, h.top_z

    def layer_paths(self, k: int) -> LayerPaths:
        """Layer k with its Toolpaths (their points copied out of the file's arrays)."""
        h = self.heads[k]
        return LayerPaths(h.index, h.z, tuple(unpack_paths(self.layers[k], copy=True)),
                          h.unfilled_mm2, h.thickness, h.top_z)

    def toolpaths(self) -> Toolpaths:
        """The build with every layer's Toolpaths."""
        return Toolpaths(tuple(self.layer_paths(k) for k in range(len(self))), self.job,
                         self.warnings)


# --------------------------------------------------------------------------- trajectories


def pack_trajectories(trajs: Sequence[Trajectory], n_joints: int = 0, *,
                      empty_pieces: bool = False) -> dict[str, np.ndarray]:
    """Trajectories' samples as flat arrays (the worker processes' packing, the members of
    a version 2 trajectory file): ``xy``, ``joints``, ``speed``, ``traj_start``,
    ``piece_start``, ``piece_owner``, ``duration``, ``traj_dt``. A trajectory without
    pieces (one piece from sample 0) gets the piece at 0, unless ``empty_pieces`` (the
    worker packing keeps it empty, so the trajectory comes back as it was)."""
    pcs = [t.pieces if len(t.pieces) or empty_pieces else np.zeros(1, np.int64)
           for t in trajs]
    xy, _ = pack([t.xy for t in trajs])
    return {
        "xy": xy,
        "joints": (np.concatenate([t.joints for t in trajs]) if trajs
                   else np.zeros((0, n_joints))),
        "speed": np.concatenate([t.speed for t in trajs]) if trajs else np.zeros(0),
        "traj_start": offsets([len(t.xy) for t in trajs]),
        "piece_start": (np.concatenate(pcs) if pcs else np.zeros(0)).astype(np.int64),
        "piece_owner": np.repeat(np.arange(len(trajs)), [len(p) for p in pcs]).astype(np.int64),
        "duration": np.array([t.duration for t in trajs], dtype=np.float64),
        "traj_dt": np.array([t.dt for t in trajs], dtype=np.float64),
        **_packed_widths(trajs),
        **_packed_spans(trajs),
    }


def _packed_spans(trajs: Sequence[Trajectory]) -> dict[str, np.ndarray]:
    """``span_owner`` (S,) int64 and ``on_spans`` (S, 2) float64 s: the spans the valve is
    on of the continuous tours' trajectories (:attr:`~icefab.core.Trajectory.on_spans`),
    in order, each with its trajectory's index; nothing when there are none."""
    spanned = [(i, np.asarray(t.on_spans, np.float64).reshape(-1, 2))
               for i, t in enumerate(trajs) if t.on_spans is not None]
    if not spanned:
        return {}
    return {"span_owner": np.repeat([i for i, _ in spanned],
                                    [len(x) for _, x in spanned]).astype(np.int64),
            "on_spans": np.concatenate([x for _, x in spanned])}


def _packed_widths(trajs: Sequence[Trajectory]) -> dict[str, np.ndarray]:
    """``variable`` (T,) bool and ``widths`` (W,) float64 mm, the samples' widths of the
    variable-width trajectories in order; nothing when there are none."""
    variable = np.array([t.widths is not None for t in trajs], dtype=bool)
    if not variable.any():
        return {}
    return {"variable": variable,
            "widths": np.concatenate([np.asarray(t.widths, np.float64) for t in trajs
                                      if t.widths is not None])}


def unpack_trajectories(d: dict[str, np.ndarray],
                        paths: Sequence[Toolpath | None]) -> list[Trajectory]:
    """The trajectories of :func:`pack_trajectories`' arrays, following ``paths``."""
    ts = d["traj_start"]
    pb = np.searchsorted(d["piece_owner"], np.arange(len(ts)))
    pstart = d["piece_start"]
    trajs = [Trajectory(dt=float(d["traj_dt"][i]), xy=d["xy"][a:b], joints=d["joints"][a:b],
                        speed=d["speed"][a:b], duration=float(d["duration"][i]),
                        path=paths[i], pieces=pstart[pb[i]:pb[i + 1]])
             for i, (a, b) in enumerate(zip(ts[:-1], ts[1:]))]
    if "variable" in d:
        idx = np.flatnonzero(d["variable"])
        wstart = offsets(np.diff(ts)[idx])
        for j, i in enumerate(idx.tolist()):
            object.__setattr__(trajs[i], "widths", d["widths"][wstart[j]:wstart[j + 1]])
    if "span_owner" in d:
        owner, spans = d["span_owner"], d["on_spans"]
        tours = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]]) if len(owner) else owner
        bounds = np.append(tours, len(owner)).tolist()
        for j, k in enumerate(owner[tours].tolist()):
            object.__setattr__(trajs[k], "on_spans", spans[bounds[j]:bounds[j + 1]])
    return trajs


#: The per-trajectory members a trajectory file takes from each trajectory's Path, with
#: their dtypes (:func:`_path_fields`).
_PATH_FIELDS = {"layer": np.int64, "path_index": np.int64, "material": np.int8,
                "role": np.int8, "width": np.float64, "closed": bool, "tool": str,
                "path_z": np.float64}


def _path_fields(index: int, z: float, paths: "Sequence[Toolpath | None]"
                 ) -> dict[str, list]:
    """Per trajectory of a layer (``index``, ``z``) following ``paths``, the values of
    :data:`_PATH_FIELDS`: its layer, index in the layer, material and role codes and its
    Path's width, closed flag, tool and z (a trajectory without a Path: codes 0, width 0,
    open, tool "", the layer's z)."""
    codes = {"material": {n: k for k, n in enumerate(MATERIAL_CODES)},
             "role": {n: k for k, n in enumerate(ROLE_CODES)}}
    return {"layer": [int(index)] * len(paths),
            "path_index": list(range(len(paths))),
            "material": [codes["material"][p.material] if p else 0 for p in paths],
            "role": [codes["role"][p.role] if p else 0 for p in paths],
            "width": [float(p.width) if p else 0.0 for p in paths],
            "closed": [bool(p.closed) if p else False for p in paths],
            "tool": [p.tool if p else "" for p in paths],
            "path_z": [float(p.z) if p else float(z) for p in paths]}


def _packed_path_fields(index: int, d: dict[str, np.ndarray]) -> dict[str, list]:
    """:func:`_path_fields` of a layer's paths as :func:`pack_paths` packs them."""
    n = len(d["z"])
    return {"layer": [int(index)] * n,
            "path_index": list(range(n)),
            "material": d["material"].astype(np.int64).tolist(),
            "role": d["role"].astype(np.int64).tolist(),
            "width": d["width"].astype(np.float64).tolist(),
            "closed": d["closed"].astype(bool).tolist(),
            "tool": [TOOL_CODES[t] for t in d["tool"].tolist()],
            "path_z": d["z"].astype(np.float64).tolist()}


def owner_arrays(motion: BuildMotion) -> dict[str, np.ndarray]:
    """Per trajectory, in file order: ``layer`` (T,) int64, ``path_index`` (T,) int64
    (within its layer), ``material`` (T,) int8 (0 part, 1 scaffold) and ``role`` (T,) int8
    (0 boundary, 1 fill, 2 measure, 3 travel); a trajectory without a path counts as 0."""
    keys = ("layer", "path_index", "material", "role")
    out: dict[str, list] = {k: [] for k in keys}
    for lm in motion.layers:
        fields = _path_fields(lm.index, lm.z, [t.path for t in lm.trajectories])
        for k in keys:
            out[k].extend(fields[k])
    return {k: np.array(v, dtype=_PATH_FIELDS[k]) for k, v in out.items()}


def encode_counts(values: np.ndarray, resolution: float) -> np.ndarray:
    """Samples as a trajectory file stores them: ``(c, k, n)`` uint8.

    ``values`` (n,) or (n, c) float64 become, column by column, integer counts of
    ``resolution`` (rounded to the nearest), their second differences down the column (a
    sampled motion's are its accelerations in counts: a few units; the first ones against
    zeros), zig-zag mapped to unsigned (0, -1, 1, -2, ... -> 0, 1, 2, 3, ...) and split
    into the byte planes of their little-endian uint64 (the shuffle filter of Blosc and
    HDF5), of which the low ``k`` that hold any non-zero byte are kept (``k`` <= 8; the
    first samples' absolute counts need about three): what is left deflates to little.
    The demo's trajectories take 5 MB instead of 53. :func:`decode_counts` inverts it
    exactly (compiled, :mod:`icefab._codec`).
    """
    v = np.asarray(values, np.float64)
    v = v[:, None] if v.ndim == 1 else v
    return _encode_columns((v[:, c] for c in range(v.shape[1])), v.shape[1], len(v),
                           resolution)


def _encode_columns(columns: Iterable[np.ndarray], cols: int, n: int, resolution: float
                    ) -> np.ndarray:
    """:func:`encode_counts` of ``cols`` columns of ``n`` values each, taken one at a time
    from ``columns`` (a writer concatenates each from its trajectories only when asked:
    the float samples are never held again whole, issue 17)."""
    from icefab._codec import encode_plane_column

    planes = np.empty((cols, 8, n), np.uint8)
    k = 1
    for c, column in enumerate(columns):
        k = max(k, encode_plane_column(np.ascontiguousarray(column, dtype=np.float64),
                                       float(resolution), planes[c]))
    return np.ascontiguousarray(planes[:, :k])


def decode_counts(planes: np.ndarray, resolution: float) -> np.ndarray:
    """The float64 ``(n, c)`` samples of :func:`encode_counts`' ``(c, k, n)`` planes
    (compiled, :mod:`icefab._codec`; overflow wraps: the callers' bounds catch it)."""
    from icefab._codec import decode_plane_column

    c, _, n = planes.shape
    out = np.empty((n, c), np.float64)
    for col in range(c):
        decode_plane_column(np.ascontiguousarray(planes[col]), float(resolution), out[:, col])
    return out


def as_stored(layer: LayerMotion) -> LayerMotion:
    """``layer`` as a trajectory file gives it back: each trajectory's speeds in counts of
    :data:`SPEED_RESOLUTION_MM_S` and a variable-width one's widths in counts of
    :data:`WIDTH_RESOLUTION_MM` (:func:`encode_counts`, then :func:`decode_counts`: the
    same floats :class:`TrajectoryFile` reads); the rest is stored exactly. What is
    measured on trajectories before they are written and again from the file must be
    measured on these: ``icefab plan`` said SMF's headroom was +18 %, ``icefab valves``
    +17 % on the same path (a review's)."""
    trajs = layer.trajectories
    if not trajs:
        return layer
    n = np.array([len(t.speed) for t in trajs])
    speeds = np.split(_stored(np.concatenate([np.asarray(t.speed, np.float64)
                                              for t in trajs]), SPEED_RESOLUTION_MM_S),
                      np.cumsum(n)[:-1])
    variable = [k for k, t in enumerate(trajs) if t.widths is not None]
    widths: dict[int, np.ndarray] = {}
    if variable:
        w = _stored(np.concatenate([np.asarray(trajs[k].widths, np.float64)
                                    for k in variable]), WIDTH_RESOLUTION_MM)
        nw = [len(trajs[k].widths) for k in variable]
        widths = dict(zip(variable, np.split(w, np.cumsum(nw)[:-1])))
    return dataclasses.replace(layer, trajectories=tuple(
        dataclasses.replace(t, speed=v, widths=widths.get(k, t.widths))
        for k, (t, v) in enumerate(zip(trajs, speeds))))


def _stored(values: np.ndarray, resolution: float) -> np.ndarray:
    """(n,) float64: ``values`` written at ``resolution`` and read back."""
    if not len(values):
        return values
    return decode_counts(encode_counts(values, resolution), resolution)[:, 0]


#: Samples per block of a version 4 trajectory file: a reader decodes one block at a time
#: (float64 position, joints and speed: 80 MB for a SCARA at this size), a writer encodes
#: one; a 300 mm bunny layer has about 35 000 samples, the demo mug's whole build under a
#: million.
BLOCK_SAMPLES = 2_000_000


class TrajectoryWriter:
    """A trajectory file written layer by layer (issue 17: ``icefab plan`` streams the
    build into it instead of holding every layer's samples).

    Use as a context manager; :meth:`add` each layer in build order. Layers are buffered
    until they hold :data:`BLOCK_SAMPLES` samples, then written as one block of counts
    members; the per-trajectory and per-layer members follow on a clean exit, and the
    file appears at ``path`` only then (atomically; an exception leaves nothing).
    """

    def __init__(self, path: str | os.PathLike, job, robot: str,
                 joint_names: Sequence[str], block_samples: int = BLOCK_SAMPLES) -> None:
        self.path = Path(path)
        self.job, self.robot, self.joint_names = job, robot, tuple(joint_names)
        self.block_samples = max(1, int(block_samples))
        self._buffer: list[dict[str, np.ndarray]] = []   # packed layers
        self._buffered = 0
        self._blocks = [0]        # layer offsets of the blocks written
        self._meta: dict[str, list] = {k: [] for k in (
            "lengths", "piece_start", "piece_count", "duration", "traj_dt", "variable",
            "span_owner", "on_spans", *_PATH_FIELDS)}
        self._layers: list[tuple[int, float, int, float, float]] = []
        self._dt: float | None = None
        self._n_joints = len(self.joint_names)
        self._zip: zipfile.ZipFile | None = None

    def __enter__(self) -> "TrajectoryWriter":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stack = contextlib.ExitStack()
        tmp = self._stack.enter_context(atomic_path(self.path))
        self._zip = self._stack.enter_context(zipfile.ZipFile(
            tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=COMPRESS_LEVEL))
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                self._flush()
                self._finish()
            except BaseException:
                if not self._stack.__exit__(*sys.exc_info()):
                    raise
                return False
        return self._stack.__exit__(exc_type, exc, tb)

    def add(self, layer: LayerMotion) -> None:
        """Append one layer (after the previous one)."""
        trajs = layer.trajectories
        self.add_packed(layer.index, layer.z, layer.thickness, [t.path for t in trajs],
                        pack_trajectories(trajs, self._n_joints, empty_pieces=True),
                        top_z=layer.top_z)

    def add_packed(self, index: int, z: float, thickness: float,
                   paths: Sequence[Toolpath | None] | dict[str, np.ndarray],
                   packed: dict[str, np.ndarray], *, top_z: float) -> None:
        """Append one layer given as :func:`pack_trajectories` packs it (``empty_pieces``
        either way), trajectory i following ``paths[i]`` (None: no path), or path i of
        ``paths`` given as :func:`pack_paths` packs them: what the planning's workers
        send, written without making Trajectory (or Toolpath) objects of it. ``top_z``:
        the layer's top, mm (the stack's; NaN: not known); asked for by name, as a
        forgotten one would send the nozzle of a part's top layer too low."""
        ts = np.asarray(packed["traj_start"], np.int64)
        n_traj = len(ts) - 1
        if n_traj and self._dt is None:
            self._dt = float(packed["traj_dt"][0])
        if n_traj and not self._n_joints:
            self._n_joints = int(np.asarray(packed["joints"]).reshape(int(ts[-1]), -1).shape[1])
        m = self._meta
        # a trajectory without pieces has one, from its first sample
        owner = np.asarray(packed["piece_owner"], np.int64)
        starts = np.asarray(packed["piece_start"], np.int64)
        count = np.bincount(owner, minlength=n_traj)
        if (count == 0).any():
            where = np.searchsorted(owner, np.flatnonzero(count == 0))
            starts = np.insert(starts, where, 0)
            count = np.maximum(count, 1)
        m["lengths"].extend(np.diff(ts).tolist())
        m["piece_start"].append(starts)
        m["piece_count"].extend(count.tolist())
        m["duration"].extend(np.asarray(packed["duration"], np.float64).tolist())
        m["traj_dt"].extend(np.asarray(packed["traj_dt"], np.float64).tolist())
        m["variable"].extend(np.asarray(packed["variable"], bool).tolist()
                             if "variable" in packed else [False] * n_traj)
        if "span_owner" in packed:   # the tours' spans, by trajectory of the whole file
            m["span_owner"].append(np.asarray(packed["span_owner"], np.int64)
                                   + (len(m["lengths"]) - n_traj))
            m["on_spans"].append(np.asarray(packed["on_spans"], np.float64).reshape(-1, 2))
        fields = (_packed_path_fields(index, paths) if isinstance(paths, dict)
                  else _path_fields(index, z, paths))
        for k, v in fields.items():
            m[k].extend(v)
        self._layers.append((int(index), float(z), n_traj, float(thickness), float(top_z)))
        self._buffer.append(packed)
        self._buffered += int(ts[-1])
        if self._buffered >= self.block_samples:
            self._flush()

    def _flush(self) -> None:
        """Write the buffered layers' samples as the next block."""
        if not self._buffer:
            return
        n, k = self._buffered, len(self._blocks) - 1

        def columns(name: str, cols: int) -> Iterator[np.ndarray]:
            """Column by column, every buffered layer's ``name`` samples."""
            arrays = [np.asarray(d[name], np.float64) for d in self._buffer]
            if cols > 1:   # a layer without paths packs its joints as (0, 0)
                arrays = [a if len(a) else a.reshape(0, cols) for a in arrays]
            whole = np.concatenate(arrays) if arrays else np.zeros((0, cols))
            for c in range(cols):
                yield np.ascontiguousarray(whole[:, c] if whole.ndim == 2 else whole)
        for name, attr, cols, res in (("xy", "xy", 2, XY_RESOLUTION_MM),
                                      ("joint", "joints", self._n_joints, JOINT_RESOLUTION),
                                      ("speed", "speed", 1, SPEED_RESOLUTION_MM_S)):
            planes = _encode_columns(columns(attr, cols), cols, n, res)
            with self._zip.open(f"{name}_counts_{k}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, planes, allow_pickle=False)
        widths = np.concatenate([np.asarray(d["widths"], np.float64) for d in self._buffer
                                 if "widths" in d] or [np.zeros(0)])
        planes = _encode_columns(iter([widths]), 1, len(widths), WIDTH_RESOLUTION_MM)
        with self._zip.open(f"width_counts_{k}.npy", "w", force_zip64=True) as fh:
            np.lib.format.write_array(fh, planes, allow_pickle=False)
        self._blocks.append(self._blocks[-1] + len(self._buffer))
        self._buffer, self._buffered = [], 0

    def _finish(self) -> None:
        m, L = self._meta, self._layers
        counts = np.array(m["piece_count"], dtype=np.int64)
        data = {
            "format": np.array(TRAJECTORIES_FORMAT), "version": np.array(TRAJECTORIES_VERSION),
            "dt": np.array(self._dt if self._dt is not None else self.job.motion.dt_s),
            "robot": np.array(self.robot),
            "joint_names": np.array(list(self.joint_names), dtype=str),
            "job": np.array(to_toml(self.job)),
            "xy_resolution": np.array(XY_RESOLUTION_MM),
            "joint_resolution": np.array(JOINT_RESOLUTION),
            "speed_resolution": np.array(SPEED_RESOLUTION_MM_S),
            "width_resolution": np.array(WIDTH_RESOLUTION_MM),
            "variable": np.array(m["variable"], dtype=bool),
            "span_owner": (np.concatenate(m["span_owner"]) if m["span_owner"]
                           else np.zeros(0, np.int64)),
            "on_spans": (np.concatenate(m["on_spans"]) if m["on_spans"]
                         else np.zeros((0, 2))),
            "block_layer_start": np.array(self._blocks, dtype=np.int64),
            "traj_start": offsets(m["lengths"]),
            "piece_start": (np.concatenate(m["piece_start"]) if m["piece_start"]
                            else np.zeros(0)).astype(np.int64),
            "piece_owner": np.repeat(np.arange(len(counts)), counts).astype(np.int64),
            "duration": np.array(m["duration"], dtype=np.float64),
            "traj_dt": np.array(m["traj_dt"], dtype=np.float64),
            **{k: np.array(m[k], dtype=dt).reshape(-1) for k, dt in _PATH_FIELDS.items()},
            "layer_index": np.array([x[0] for x in L], dtype=np.int64),
            "layer_z": np.array([x[1] for x in L], dtype=np.float64),
            "layer_start": offsets([x[2] for x in L]),
            **_heights([x[3] for x in L]),
            **_tops([x[4] for x in L]),
        }
        for name, value in data.items():
            with self._zip.open(name + ".npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)


def save_trajectories(motion: BuildMotion, path: str | os.PathLike,
                      block_samples: int = BLOCK_SAMPLES) -> None:
    """Write a BuildMotion to ``.npz`` (layout in the module docstring), atomically."""
    with TrajectoryWriter(path, motion.job, motion.robot, motion.joint_names,
                          block_samples) as w:
        for lm in motion.layers:
            w.add(lm)


_TRAJ_REQUIRED = ("format", "version", "dt", "traj_start", "piece_start", "piece_owner",
                  "duration", "layer", "path_index", "material", "role", "layer_index",
                  "layer_z", "layer_start", "job", "robot", "joint_names")
_TRAJ_FLOATS = ("xy", "joints", "speed")
_TRAJ_COUNTS = ("xy_counts", "joint_counts", "speed_counts", "xy_resolution",
                "joint_resolution", "speed_resolution")
_TRAJ_V2 = ("traj_dt", "width", "closed", "tool", "path_z")
#: The sample members of one block of a version 4 file (``NAME_K`` for block K); version 5
#: adds ``width_counts``.
_TRAJ_BLOCK = ("xy_counts", "joint_counts", "speed_counts")
_TRAJ_V5 = ("variable", "width_resolution")
_TRAJ_V6 = ("span_owner", "on_spans")
#: Largest time step and joint value a trajectory file may hold (s; rad or mm).
MAX_DT_S = 60.0
MAX_JOINT = 1e6
#: Sample bounds per member: (name, lo, hi).
_SAMPLE_BOUNDS = (("xy", -MAX_COORD_MM, MAX_COORD_MM), ("joint", -MAX_JOINT, MAX_JOINT),
                  ("speed", 0.0, MAX_COORD_MM))


def _sample_counts(m: "_Members", n_joints: int, suffix: str = "", n: int | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples of a version 3 trajectory file, or of block ``suffix`` ("_K") of a
    version 4 one (xy (M, 2), joints (M, j), speed (M,)), decoded and checked like version
    2's float members (``n_joints`` 0: any number; ``n``: the rows expected)."""
    out = []
    for name, lo, hi in _SAMPLE_BOUNDS:
        cols = {"xy": 2, "joint": n_joints, "speed": 1}[name]
        res = m.number(f"{name}_resolution", 0.0, 1.0, lo_open=True)
        member = f"{name}_counts{suffix}"
        planes = m.array(member, "u", 3)
        if name == "joint" and not cols:  # unnamed joints: as many as stored (as version 2)
            cols = planes.shape[0]
        if planes.dtype.itemsize != 1 or planes.shape[0] != cols or \
                not 1 <= planes.shape[1] <= 8 or (n is not None and planes.shape[2] != n):
            raise m.bad(member, f"{planes.dtype} of shape {planes.shape}, expected "
                        f"uint8 byte planes of shape ({cols}, 1..8, "
                        f"{'n' if n is None else n}): the file is corrupt")
        n = planes.shape[2]
        v = decode_counts(planes, res)
        del planes
        if v.size and not (v.min() >= lo and v.max() <= hi):
            raise m.bad(member, f"a value outside [{lo:g}, {hi:g}]: the file is corrupt")
        out.append(v)
    xy, joints, speed = out
    return xy, joints, speed[:, 0]


class TrajectoryFile:
    """A trajectory file (versions 1 to 6) open for reading: its per-layer and
    per-trajectory members at once, its samples block by block (:meth:`iter_layers`), so a
    stage that works layer by layer holds one block of samples (issue 17). It stands in
    for a BuildMotion wherever the layers are walked once.

    Every member is checked as :func:`load_trajectories` says. Attributes: ``path``,
    ``version``, ``job``, ``robot``, ``joint_names``, ``dt``, ``duration``, ``n_points``;
    per layer (L,)
    ``layer_index``, ``layer_z``, ``heights`` (NaN: the job's thickness), ``tops`` (NaN:
    not known, :meth:`~icefab.core.LayerMotion.top` derives it),
    ``layer_start`` (L + 1,); per trajectory (T,) ``durations`` s, ``material`` and
    ``role`` codes (the file's tables).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._m = _Members(self.path, "trajectory")
        self._lock = threading.RLock()
        self._cache: dict[int, list[LayerMotion]] = {}
        try:
            self._read_header()
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> "TrajectoryFile":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._m.close()

    def _read_header(self) -> None:
        m = self._m
        version = self.version = m.header(TRAJECTORIES_FORMAT, TRAJECTORIES_READABLE)
        if version >= 4:
            if "block_layer_start" not in m.names:
                raise m.bad(None, "not a complete trajectory file: missing arrays "
                            "block_layer_start")
            bls = m.array("block_layer_start", "iu", 1).astype(np.int64)
            if not 1 <= len(bls) <= 1_000_000:
                raise m.bad("block_layer_start", f"{len(bls)} offsets: the file is corrupt")
            self._block = _TRAJ_BLOCK + (("width_counts",) if version >= 5 else ())
            blocks = [f"{s}_{k}" for k in range(len(bls) - 1) for s in self._block]
            m.expect(_TRAJ_REQUIRED + _TRAJ_V2 + _TRAJ_COUNTS[3:]
                     + ("block_layer_start",) + tuple(blocks)
                     + (_TRAJ_V5 if version >= 5 else ())
                     + (_TRAJ_V6 if version >= 6 else ()), ("layer_height", "layer_top_z"),
                     streamed=blocks)
        else:
            m.expect(_TRAJ_REQUIRED + (_TRAJ_V2 if version >= 2 else ())
                     + (_TRAJ_COUNTS if version >= 3 else _TRAJ_FLOATS),
                     ("layer_height", "layer_top_z"))
        self.job = m.job()
        self.robot = m.text("robot")
        self.joint_names = m.strings("joint_names")
        self.dt = dt = m.number("dt", 0.0, MAX_DT_S, lo_open=True)
        self.durations = duration = m.values("duration", "f", 1, lo=0.0, hi=1e9)
        nt = len(duration)
        if version >= 4:  # each block's rows are checked against it when read
            ts = m.offsets("traj_start", nt, None)
        else:
            self._samples = self._whole_samples()
            ts = m.offsets("traj_start", nt, len(self._samples[0]))
        self._ts = ts
        self._layer = m.values("layer", "iu", 1, n=nt, lo=-1, hi=2**31 - 1)
        self.material = m.codes("material", MATERIAL_CODES, nt)
        self.role = m.codes("role", ROLE_CODES, nt)
        m.values("path_index", "iu", 1, n=nt, lo=0, hi=2**31 - 1)
        self.layer_index = index = m.values("layer_index", "iu", 1, lo=-1, hi=2**31 - 1)
        self.layer_z = m.values("layer_z", "f", 1, n=len(index), lo=-MAX_COORD_MM,
                                hi=MAX_COORD_MM)
        self.heights = _read_heights(m, len(index))
        self.tops = _read_tops(m, self.layer_z)
        self.layer_start = ls = m.offsets("layer_start", len(index), nt)
        owner = m.values("piece_owner", "iu", 1, lo=0, hi=max(nt - 1, 0)).astype(np.int64)
        pstart = m.values("piece_start", "iu", 1, n=len(owner), lo=0).astype(np.int64)
        if len(owner) and (nt == 0 or np.any(np.diff(owner) < 0)):
            raise m.bad("piece_owner", "not in ascending trajectory order: the file is corrupt")
        if len(owner) and np.any(pstart >= np.maximum(np.diff(ts)[owner], 1)):
            raise m.bad("piece_start", "a piece starts after the end of its trajectory: the "
                        "file is corrupt")
        self._owner, self._pstart = owner, pstart
        if version >= 2:
            dts = m.values("traj_dt", "f", 1, n=nt, lo=0.0, hi=MAX_DT_S).astype(np.float64)
            if np.any(dts <= 0.0):
                raise m.bad("traj_dt", "a time step <= 0, expected > 0 s")
            widths = m.values("width", "f", 1, n=nt, lo=0.0, hi=MAX_COORD_MM).astype(np.float64)
            closed = m.values("closed", "b", 1, n=nt)
            tools = [str(x) for x in m.values("tool", "U", 1, n=nt)]
            unknown = sorted(set(tools) - set(TOOL_CODES))
            if unknown:
                raise m.bad("tool", f"unknown tool {unknown[0][:40]!r}, expected one of "
                            f"{', '.join(map(repr, TOOL_CODES))}")
            zs = m.values("path_z", "f", 1, n=nt, lo=-MAX_COORD_MM,
                          hi=MAX_COORD_MM).astype(np.float64)
        else:
            log.warning("%s: trajectory file version 1 stores neither path widths, tools and "
                        "closed flags nor each trajectory's dt: widths 0 (the valve stage uses "
                        "the job's widths), open paths, dt %.4g s for all; re-run 'icefab plan' "
                        "to store them", self.path, dt)
            dts = np.full(nt, dt)
            widths = np.zeros(nt)
            closed = np.zeros(nt, dtype=bool)
            tools = [""] * nt
            zs = np.repeat(self.layer_z.astype(np.float64), np.diff(ls))
        self._dts, self._widths, self._closed, self._tools, self._zs = (dts, widths, closed,
                                                                          tools, zs)
        self._variable = (m.values("variable", "b", 1, n=nt).astype(bool) if version >= 5
                          else np.zeros(nt, dtype=bool))
        self._span_owner, self._spans = self._read_spans(nt) if version >= 6 else \
            (np.zeros(0, np.int64), np.zeros((0, 2)))
        if version >= 4:
            if bls[0] != 0 or bls[-1] != len(index) or np.any(np.diff(bls) < 0):
                raise m.bad("block_layer_start", f"offsets must run from 0 to {len(index)} "
                            "layers without decreasing: the file is corrupt")
            self._block_layers = bls
        else:
            self._block_layers = np.array([0, len(index)], dtype=np.int64)

    def _read_spans(self, nt: int) -> tuple[np.ndarray, np.ndarray]:
        """``span_owner`` and ``on_spans`` (version 6), checked: owners ascending, every
        trajectory's spans in order within its duration (:func:`~icefab.core.
        spans_problem`)."""
        m = self._m
        owner = m.values("span_owner", "iu", 1, lo=0, hi=max(nt - 1, 0)).astype(np.int64)
        spans = m.values("on_spans", "f", 2, 2, n=len(owner), lo=0.0, hi=1e9)
        if len(owner) and (nt == 0 or np.any(np.diff(owner) < 0)):
            raise m.bad("span_owner", "not in ascending trajectory order: the file is corrupt")
        spans = spans.astype(np.float64).reshape(-1, 2)
        fine = spans_fine(owner, spans, self.durations)
        if not fine.all():
            k = int(np.flatnonzero(~fine)[0])
            problem = spans_problem(spans[owner == k], float(self.durations[k]))
            raise m.bad("on_spans", f"trajectory {k}: {problem}: the file is corrupt")
        return owner, spans

    def _whole_samples(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The samples of a version 1 to 3 file (one block)."""
        m = self._m
        if self.version >= 3:
            return _sample_counts(m, len(self.joint_names))
        xy = m.values("xy", "f", 2, 2, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        joints = m.values("joints", "f", 2, len(self.joint_names) or None, n=len(xy),
                          lo=-MAX_JOINT, hi=MAX_JOINT)
        speed = m.values("speed", "f", 1, n=len(xy), lo=0.0, hi=MAX_COORD_MM)
        return xy, joints, speed

    @property
    def n_layers(self) -> int:
        return len(self.layer_index)

    @property
    def n_points(self) -> int:
        return int(self._ts[-1])

    @property
    def duration(self) -> float:
        """Whole-build motion time, s."""
        return float(self.durations.sum())

    def depositing(self) -> np.ndarray:
        """(T,) bool: the trajectories that deposit (part or scaffold, boundary or fill)."""
        return np.isin(self.role, [ROLE_CODES.index(r) for r in ("boundary", "fill")])

    def layer_at(self, pos: int) -> LayerMotion:
        """The layer at position ``pos`` (0-based, file order), from a cache of the two
        blocks last decoded (thread-safe: the build runner's planning thread reads ahead)."""
        with self._lock:
            k = int(np.searchsorted(self._block_layers, pos, side="right")) - 1
            if not 0 <= pos < self.n_layers:
                raise IndexError(f"layer position {pos} of {self.n_layers}")
            block = self._cache.get(k)
            if block is None:
                block = list(self._decode_block(k, None))
                self._cache[k] = block
                while len(self._cache) > 2:
                    self._cache.pop(next(iter(self._cache)))
            return block[pos - int(self._block_layers[k])]

    def sequence(self) -> "LayerSequence":
        """The layers as a read-only sequence, decoded a block at a time as they are asked
        for (:meth:`layer_at`)."""
        return LayerSequence(self, range(self.n_layers))

    def motion(self) -> BuildMotion:
        """A BuildMotion whose layers are :meth:`sequence` (read while this file is open)."""
        return BuildMotion(layers=self.sequence(), job=self.job, robot=self.robot,
                           joint_names=self.joint_names)

    @property
    def layers(self) -> "Iterator[LayerMotion]":
        """Every layer, decoded one block at a time: a new pass each time it is asked for,
        so a consumer of a BuildMotion that walks its layers once (``icefab.export``'s
        G-code, ``owner_arrays``) takes the file instead."""
        return self.iter_layers()

    def iter_layers(self, wanted: "set[int] | None" = None) -> "Iterator[LayerMotion]":
        """The layers in file order (only those whose index is in ``wanted``, if given),
        decoded one block at a time."""
        for k in self.blocks(wanted):
            yield from self._decode_block(k, wanted)

    def blocks(self, wanted: "set[int] | None" = None) -> list[int]:
        """The blocks that hold layers (whose index is in ``wanted``, if given), in file
        order: each one :meth:`iter_block` decodes at once (a worker's share of a build)."""
        bls = self._block_layers
        return [k for k in range(len(bls) - 1)
                if wanted is None or wanted.intersection(
                    self.layer_index[int(bls[k]):int(bls[k + 1])].tolist())]

    def iter_block(self, k: int, wanted: "set[int] | None" = None
                   ) -> "Iterator[LayerMotion]":
        """The layers of block ``k`` (only those whose index is in ``wanted``, if given)."""
        return self._decode_block(k, wanted)

    def _decode_block(self, k: int, wanted: "set[int] | None") -> "Iterator[LayerMotion]":
        """The layers of block k (those in ``wanted``, if given)."""
        bls, ls, ts = self._block_layers, self.layer_start, self._ts
        a, b = int(bls[k]), int(bls[k + 1])
        t0, t1 = int(ls[a]), int(ls[b])
        r0, r1 = int(ts[t0]), int(ts[t1])
        widths = None
        if self.version >= 4:
            self._m.block_bound([f"{s}_{k}" for s in self._block])
            xy, joints, speed = _sample_counts(self._m, len(self.joint_names), f"_{k}",
                                               r1 - r0)
            if self.version >= 5:
                widths = self._block_widths(k, t0, t1)
        else:
            xy, joints, speed = (x[r0:r1] for x in self._samples)
        yield from self._layers_of(a, b, xy, joints, speed, wanted, widths)

    def _block_widths(self, k: int, t0: int, t1: int) -> np.ndarray:
        """The widths at the samples of the variable-width trajectories t0..t1-1 (block k)."""
        m, member = self._m, f"width_counts_{k}"
        n = int(np.diff(self._ts[t0:t1 + 1])[self._variable[t0:t1]].sum())
        res = m.number("width_resolution", 0.0, 1.0, lo_open=True)
        planes = m.array(member, "u", 3)
        if planes.dtype.itemsize != 1 or planes.shape[0] != 1 or \
                not 1 <= planes.shape[1] <= 8 or planes.shape[2] != n:
            raise m.bad(member, f"{planes.dtype} of shape {planes.shape}, expected uint8 "
                        f"byte planes of shape (1, 1..8, {n}): the file is corrupt")
        w = decode_counts(planes, res)[:, 0]
        if w.size and not (w.min() >= 0.0 and w.max() <= MAX_COORD_MM):
            raise m.bad(member, f"a width outside [0, {MAX_COORD_MM:g}] mm: the file is "
                        "corrupt")
        return w

    def _layers_of(self, a: int, b: int, xy, joints, speed, wanted,
                   widths: np.ndarray | None = None) -> "Iterator[LayerMotion]":
        """LayerMotion of layers a..b-1 from their samples (rows from the first one's)."""
        ls, ts = self.layer_start, self._ts
        t0, t1 = int(ls[a]), int(ls[b])
        r0 = int(ts[t0])
        lo, hi = np.searchsorted(self._owner, [t0, t1])
        data = {"xy": xy, "joints": joints, "speed": speed,
                "traj_start": ts[t0:t1 + 1] - r0, "piece_start": self._pstart[lo:hi],
                "piece_owner": self._owner[lo:hi] - t0, "duration": self.durations[t0:t1],
                "traj_dt": self._dts[t0:t1]}
        variable = self._variable[t0:t1]
        if variable.any():
            data["variable"], data["widths"] = variable, widths
        s0, s1 = np.searchsorted(self._span_owner, [t0, t1])
        if s1 > s0:
            data["span_owner"] = self._span_owner[s0:s1] - t0
            data["on_spans"] = self._spans[s0:s1]
        # one stand-in Toolpath per trajectory (558 872 on the bunny): its fields as lists
        # first, and the closing check of closed paths (first sample == last) for all
        lo_row, hi_row = ts[t0:t1] - r0, ts[t0 + 1:t1 + 1] - r0
        closed = self._closed[t0:t1].tolist()
        longer = (hi_row - lo_row) > 2
        ends = np.zeros(t1 - t0, dtype=bool)
        ends[longer] = (xy[lo_row[longer]] == xy[hi_row[longer] - 1]).all(axis=1)
        cut = (self._closed[t0:t1] & ends).tolist()
        materials = [MATERIAL_CODES[c] for c in self.material[t0:t1].tolist()]
        roles = [ROLE_CODES[c] for c in self.role[t0:t1].tolist()]
        stand_ins = [Toolpath(points=xy[a0:b0 - 1] if c else xy[a0:b0], z=z, material=mt,
                              role=rl, closed=cl, width=w, layer=ly, frame="base", tool=tl)
                     for a0, b0, c, z, mt, rl, cl, w, ly, tl in zip(
                         lo_row.tolist(), hi_row.tolist(), cut, self._zs[t0:t1].tolist(),
                         materials, roles, closed, self._widths[t0:t1].tolist(),
                         self._layer[t0:t1].tolist(), self._tools[t0:t1])]
        trajs = unpack_trajectories(data, stand_ins)
        for i in np.flatnonzero(variable).tolist():   # the stand-in's points are the samples
            t = trajs[i]
            object.__setattr__(t.path, "widths", t.widths[:-1] if cut[i] else t.widths)
        for k in range(a, b):
            if wanted is not None and int(self.layer_index[k]) not in wanted:
                continue
            yield LayerMotion(index=int(self.layer_index[k]), z=float(self.layer_z[k]),
                              trajectories=tuple(trajs[int(ls[k]) - t0:int(ls[k + 1]) - t0]),
                              thickness=float(self.heights[k]),
                              top_z=float(self.tops[k]))


def load_trajectories(path: str | os.PathLike) -> BuildMotion:
    """Read a file written by :func:`save_trajectories` (versions 1 to 6), checking every
    member (module docstring): finite samples within MAX_COORD_MM, joints one column per
    joint name, speeds >= 0, time steps in (0, MAX_DT_S], pieces inside their trajectory,
    codes and tools from their tables, tours' spans in order within their trajectory's
    duration (version 6). The whole build in memory: a stage that works layer
    by layer reads :class:`TrajectoryFile`'s layers instead.

    The trajectories' ``path`` is a stand-in Toolpath in the robot base frame whose
    ``polyline()`` is the samples (a closed path's last sample, back on its first, is the
    closing point), carrying layer, z, material, role, width, closed and tool.
    StackFileError naming the file (and the member) if it is missing, truncated, corrupt or
    of another kind.
    """
    with TrajectoryFile(path) as f:
        layers = tuple(f.iter_layers())
        return BuildMotion(layers=layers, job=f.job, robot=f.robot, joint_names=f.joint_names)


class LayerSequence(collections.abc.Sequence):
    """A trajectory file's layers as a read-only sequence (``BuildMotion.layers`` of
    :func:`open_trajectories`): indexing decodes the layer's block (two kept,
    :meth:`TrajectoryFile.layer_at`), a slice is another such sequence, iterating walks
    the blocks once."""

    def __init__(self, source: TrajectoryFile, positions: range) -> None:
        self._source, self._positions = source, positions

    def __len__(self) -> int:
        return len(self._positions)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return LayerSequence(self._source, self._positions[i])
        return self._source.layer_at(self._positions[i])

    def __iter__(self) -> "Iterator[LayerMotion]":
        for pos in self._positions:
            yield self._source.layer_at(pos)

    def summary(self) -> tuple[np.ndarray, np.ndarray]:
        """(L,) motion time of each layer, s, and (L,) its trajectories with samples (the
        build runner's paths), from the file's per-trajectory arrays without decoding a
        layer: the runner walked every block for them at each start and resume (a hunt
        measured 0.9 s for 11 000 trajectories, ~45 s for the bunny's 555 000)."""
        src = self._source
        pos = np.asarray(self._positions, dtype=np.int64)
        lo, hi = src.layer_start[pos], src.layer_start[pos + 1]
        time_cum = np.concatenate([[0.0], np.cumsum(src.durations, dtype=np.float64)])
        paths_cum = np.concatenate([[0], np.cumsum(np.diff(src._ts) > 0)])
        return time_cum[hi] - time_cum[lo], paths_cum[hi] - paths_cum[lo]

    def thicknesses(self) -> np.ndarray:
        """(L,) float64 mm: each layer's own thickness (NaN: the job's), from the file's
        per-layer member without decoding a layer."""
        return self._source.heights[np.asarray(self._positions, dtype=np.int64)]


def open_trajectories(path: str | os.PathLike) -> BuildMotion:
    """A trajectory file as a BuildMotion whose layers are read a block at a time as they
    are asked for (:class:`LayerSequence`): what :func:`load_trajectories` gives, in the
    memory of two blocks (issue 17: the build runner on a 1 M-facet part). The file stays
    open while the BuildMotion lives. Same checks and errors as load_trajectories."""
    return TrajectoryFile(path).motion()


# --------------------------------------------------------------------------- ruled edges

RULED_FORMAT = "icefab-ruled"
RULED_VERSION = 1
_RULED_REQUIRED = ("format", "version", "job", "layer", "ring", "point", "z", "match",
                   "match_ring", "dz", "tilt")


def save_ruled(edges: RuledEdges, job, path: str | os.PathLike) -> Path:
    """Write ruled layer edges (``icefab export ruled``) to ``path`` atomically.

    Layout: ``format`` "icefab-ruled", ``version`` 1, ``job`` str (TOML, the stack's);
    per contour point (n,): ``layer`` int64, ``ring`` int64, ``point`` (n, 2) float64 mm,
    ``z`` float64 mm, ``match`` (n, 2) float64 mm (NaN: none), ``match_ring`` int64 (-1:
    none), ``dz`` float64 mm (NaN: none), ``tilt`` float64 rad (NaN: none); the meaning of
    each in :class:`icefab.core.RuledEdges`.
    """
    arrays = {"format": np.array(RULED_FORMAT), "version": np.array(RULED_VERSION),
              "job": np.array(to_toml(job))}
    arrays.update({k: np.asarray(getattr(edges, k)) for k in _RULED_REQUIRED[3:]})
    return _write(path, arrays)


def load_ruled(path: str | os.PathLike) -> tuple[RuledEdges, object]:
    """Read a file of :func:`save_ruled`, every member checked: (edges, job).

    A point has a match exactly when ``match_ring >= 0``; then its match and dz are finite,
    dz > 0 and |tilt| < pi/2. StackFileError naming the file and member otherwise.
    """
    with _Members(Path(path), "ruled edges") as m:
        m.header(RULED_FORMAT, (RULED_VERSION,))
        m.expect(_RULED_REQUIRED)
        job = m.job()
        layer = m.values("layer", "iu", 1, lo=0, hi=2**31 - 1).astype(np.int64)
        n = len(layer)
        ring = m.values("ring", "iu", 1, n=n, lo=0, hi=2**31 - 1).astype(np.int64)
        point = m.values("point", "f", 2, 2, n=n, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        z = m.values("z", "f", 1, n=n, lo=-MAX_COORD_MM, hi=MAX_COORD_MM)
        mring = m.values("match_ring", "iu", 1, n=n, lo=-1, hi=2**31 - 1).astype(np.int64)
        match = m.values("match", "f", 2, 2, n=n, lo=-MAX_COORD_MM, hi=MAX_COORD_MM,
                         nan_ok=True)
        dz = m.values("dz", "f", 1, n=n, lo=0.0, hi=MAX_COORD_MM, nan_ok=True)
        tilt = m.values("tilt", "f", 1, n=n, lo=-math.pi / 2, hi=math.pi / 2, nan_ok=True)
        has = mring >= 0
        for name, col in (("match", np.isnan(match).any(axis=1)), ("dz", np.isnan(dz)),
                          ("tilt", np.isnan(tilt))):
            if np.any(col == has):
                raise m.bad(name, "must be given exactly where match_ring >= 0: the file is "
                            "corrupt")
        if np.any(dz[has] <= 0.0):
            raise m.bad("dz", "a layer height <= 0: the file is corrupt")
        if np.any(np.diff(layer) < 0):
            raise m.bad("layer", "layers not in ascending order: the file is corrupt")
    return RuledEdges(layer=layer, ring=ring, point=point, z=z, match=match, match_ring=mring,
                      dz=dz, tilt=tilt), job
