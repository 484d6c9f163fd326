"""Result files given back to icefab: ``stack.npz``, ``toolpaths.npz``, ``trajectories.npz``.

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
* scaffold regions, when present, stored the same way under the prefix ``scaffold_``.

Toolpath file (``icefab paths``; :func:`save_toolpaths` / :func:`load_toolpaths`),
version 2:

* ``format`` "icefab-toolpaths", ``version`` int, ``job`` str (TOML), ``warnings`` (w,) str;
* ``points`` (N, 2) float64 mm: the points of all paths, concatenated in order;
* ``state`` (N,) int8: Ossino's deposition state of every point (0 OFF, 1 ON1 part,
  2 ON2 scaffold), the state of the segment leaving the point along its path
  (:func:`icefab.core.point_states`: a closed path's last point deposits along its
  closing edge, an open path's last point is OFF; travel and measurement points are OFF);
* ``path_start`` (P + 1,) int64: path i has ``points[path_start[i]:path_start[i+1]]``;
* per path (P,): ``z`` float64 mm, ``material`` int8 (0 part, 1 scaffold), ``role``
  int8 (0 boundary, 1 fill, 2 measure, 3 travel), ``closed`` bool, ``width`` float64
  mm, ``layer`` int64, ``frame`` int8 (0 part, 1 base), ``tool`` int8 (0 derived,
  1 part nozzle, 2 scaffold nozzle, 3 laser);
* per layer (L,): ``layer_index`` int64, ``layer_z`` float64 mm, ``layer_start``
  (L + 1,) int64 (paths of layer j are ``layer_start[j]:layer_start[j+1]``),
  ``unfilled_mm2`` (L, 2) float64.

Version 1 toolpath files (without ``state``) are still read; states are derived from the
paths.

Trajectory file (``icefab plan``; :func:`save_trajectories` / :func:`load_trajectories`):

* ``format`` = "icefab-trajectories", ``version`` = 2, ``dt`` float s (the first
  trajectory's; ``traj_dt`` has each one's), ``robot`` str, ``joint_names`` (j,) str,
  ``job`` str (TOML);
* ``xy`` (M, 2) float64 mm (robot base frame), ``joints`` (M, j) float64 rad or mm,
  ``speed`` (M,) float64 mm/s: the samples of all trajectories, concatenated in order;
* ``traj_start`` (T + 1,) int64: trajectory i is rows ``traj_start[i]:traj_start[i+1]``;
* ``piece_start`` (Q,) int64 sample indices (within its trajectory) where pieces start
  and ``piece_owner`` (Q,) int64 the trajectory each belongs to;
* per trajectory (T,): ``duration`` float64 s, ``traj_dt`` float64 s, ``layer`` int64,
  ``path_index`` int64 (index within its layer), ``material`` int8 (0 part, 1 scaffold),
  ``role`` int8 (0 boundary, 1 fill, 2 measure, 3 travel), and the rest of its Path:
  ``width`` float64 mm, ``closed`` bool, ``tool`` str ("" = derived), ``path_z``
  float64 mm; a trajectory without a Path has width 0, closed False, tool "", z 0;
* per layer (L,): ``layer_index`` int64, ``layer_z`` float64 mm, ``layer_start`` (L+1,)
  int64 (trajectories of layer k are ``layer_start[k]:layer_start[k+1]``).

Version 1 trajectory files (no ``traj_dt``, ``width``, ``closed``, ``tool``, ``path_z``)
still load, with a logged warning: every trajectory gets ``dt``, width 0 (the valve stage
then uses the job's widths), closed False, the derived tool and the layer's z.

Errors: :class:`~icefab.errors.StackFileError` naming the file (and the member) when a
file is missing, truncated, corrupt or of another kind.

May import: ``icefab.core``, ``icefab.config``, ``icefab.errors``, ``icefab.atomic``.
"""

from __future__ import annotations

import logging
import os
import tomllib
import zipfile
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from icefab.atomic import atomic_path
from icefab.config import job_from_dict, to_toml
from icefab.core import (OFF, ON2, BuildMotion, Layer, LayerMotion, LayerPaths, Region, Stack,
                         Toolpath, Toolpaths, Trajectory, point_states)
from icefab.errors import ConfigError, StackFileError

log = logging.getLogger(__name__)

STACK_FORMAT = "icefab-stack"
STACK_VERSION = 1
TOOLPATHS_FORMAT = "icefab-toolpaths"
TOOLPATHS_VERSION = 2
TRAJECTORIES_FORMAT = "icefab-trajectories"
TRAJECTORIES_VERSION = 2
#: Versions load_trajectories reads (1: without per-trajectory dt and Path fields).
TRAJECTORIES_READABLE = (1, 2)

#: Codes of the path attributes in the files and worker packing (index = code).
MATERIAL_CODES = ("part", "scaffold")
ROLE_CODES = ("boundary", "fill", "measure", "travel")
FRAME_CODES = ("part", "base")
TOOL_CODES = ("", "part", "scaffold", "laser")


# --------------------------------------------------------------------------- ragged arrays


def offsets(counts: Sequence[int] | np.ndarray) -> np.ndarray:
    """(n + 1,) int64 start offsets of ``n`` items of ``counts`` rows: ``[0, cumsum]``."""
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


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


def _write(path: str | os.PathLike, arrays: dict[str, np.ndarray]) -> Path:
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(target) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    return target


def _read_all(path: Path, what: str) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise StackFileError(f"{path}: {what} file not found") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, zlib.error) as exc:
        raise StackFileError(f"{path}: not a readable {what} file ({exc})") from None


def _job(data: dict[str, np.ndarray], path: Path):
    try:
        return job_from_dict(tomllib.loads(str(data["job"])))
    except (tomllib.TOMLDecodeError, ConfigError) as exc:
        raise StackFileError(f"{path}: the stored job is invalid ({exc})") from None


def file_format(path: str | os.PathLike) -> str:
    """The ``format`` member of an icefab ``.npz`` result file ("" when it has none);
    reads only that member. StackFileError when the file is missing or not a readable npz."""
    try:
        with np.load(path, allow_pickle=False) as npz:
            return str(npz["format"]) if "format" in npz.files else ""
    except FileNotFoundError:
        raise StackFileError(f"{path}: file not found") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError, zlib.error) as exc:
        raise StackFileError(f"{path}: not a readable .npz file ({exc})") from None


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


def _unpack_regions(data: dict[str, np.ndarray], n_layers: int, path: str,
                    prefix: str = "") -> list[Region]:
    pts = data[prefix + "points"]
    off = data[prefix + "ring_offsets"]
    par = data[prefix + "ring_parent"]
    lay = data[prefix + "ring_layer"]
    n_r = len(lay)
    if (pts.ndim != 2 or pts.shape[1] != 2 or len(off) != n_r + 1 or len(par) != n_r
            or (n_r and (off[0] != 0 or off[-1] != len(pts) or np.any(np.diff(off) < 0)))
            or (n_r and (np.any(np.diff(lay) < 0) or lay[0] < 0 or lay[-1] >= n_layers))):
        raise StackFileError(f"{path}: inconsistent ring arrays ({prefix or 'part'}): the "
                             "file is corrupt")
    starts = np.searchsorted(lay, np.arange(n_layers + 1))
    rings = np.split(pts, off[1:-1]) if n_r else []
    out = []
    for k in range(n_layers):
        a, b = int(starts[k]), int(starts[k + 1])
        p = par[a:b].astype(np.int64)
        if np.any(p >= b - a) or np.any(p < -1):
            raise StackFileError(f"{path}: layer {k}: ring parent out of range: the file is "
                                 "corrupt")
        out.append(Region(rings=tuple(rings[a:b]), parent=p))
    return out


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
    }
    if any(not L.scaffold.is_empty for L in stack.layers):
        arrays.update({"scaffold_" + k: v for k, v in
                       _pack_regions([L.scaffold for L in stack.layers]).items()})
    return _write(path, arrays)


def load_stack(path: str | os.PathLike) -> Stack:
    """Read a stack written by :func:`save_stack`.

    Raises StackFileError naming the file when it is missing, truncated, corrupt or not a
    stack file.
    """
    path = Path(path)
    if not path.is_file():
        raise StackFileError(f"{path}: stack file not found")
    data = _read_all(path, "stack")
    need = ("format", "version", "points", "ring_offsets", "ring_parent", "ring_layer",
            "layer_index", "layer_z", "layer_top_z", "layer_thickness", "warnings", "job")
    missing = [k for k in need if k not in data]
    if missing:
        raise StackFileError(f"{path}: not an icefab stack file (missing {', '.join(missing)})")
    if str(data["format"]) != STACK_FORMAT:
        raise StackFileError(f"{path}: format {str(data['format'])!r}: expected "
                             f"{STACK_FORMAT!r}")
    if int(data["version"]) != STACK_VERSION:
        raise StackFileError(f"{path}: stack file version {int(data['version'])}: this icefab "
                             f"reads version {STACK_VERSION}")
    job = _job(data, path)
    n = len(data["layer_index"])
    if len(data["layer_z"]) != n or len(data["layer_top_z"]) != n:
        raise StackFileError(f"{path}: layer arrays of different lengths: the file is corrupt")
    parts = _unpack_regions(data, n, str(path))
    if "scaffold_points" in data:
        scaffolds = _unpack_regions(data, n, str(path), "scaffold_")
    else:
        scaffolds = [Region() for _ in range(n)]
    layers = tuple(Layer(index=int(data["layer_index"][k]), z=float(data["layer_z"][k]),
                         part=parts[k], scaffold=scaffolds[k],
                         top_z=float(data["layer_top_z"][k])) for k in range(n))
    return Stack(layers=layers, job=job, layer_thickness=float(data["layer_thickness"]),
                 warnings=tuple(str(w) for w in data["warnings"]))


# --------------------------------------------------------------------------- toolpaths


def pack_paths(paths: Sequence[Toolpath]) -> dict[str, np.ndarray]:
    """The paths as flat arrays (the toolpath file's per-point and per-path members, the
    worker processes' packing): ``points``, ``path_start``, ``z``, ``material``, ``role``,
    ``closed``, ``width``, ``layer``, ``frame``, ``tool``."""
    points, start = pack([p.points for p in paths])
    return {
        "points": points,
        "path_start": start,
        "z": np.array([p.z for p in paths], dtype=np.float64),
        "material": np.array([MATERIAL_CODES.index(p.material) for p in paths], dtype=np.int8),
        "role": np.array([ROLE_CODES.index(p.role) for p in paths], dtype=np.int8),
        "closed": np.array([p.closed for p in paths], dtype=bool),
        "width": np.array([p.width for p in paths], dtype=np.float64),
        "layer": np.array([p.layer for p in paths], dtype=np.int64),
        "frame": np.array([FRAME_CODES.index(p.frame) for p in paths], dtype=np.int8),
        "tool": np.array([TOOL_CODES.index(p.tool) for p in paths], dtype=np.int8),
    }


def unpack_paths(d: dict[str, np.ndarray], copy: bool = False) -> list[Toolpath]:
    """The paths of :func:`pack_paths`' arrays (points are views unless ``copy``)."""
    pts, start = d["points"], d["path_start"]
    out = []
    for i in range(len(start) - 1):
        p = pts[start[i]:start[i + 1]]
        out.append(Toolpath(p.copy() if copy else p, float(d["z"][i]),
                            MATERIAL_CODES[d["material"][i]], ROLE_CODES[d["role"][i]],
                            bool(d["closed"][i]), float(d["width"][i]), int(d["layer"][i]),
                            FRAME_CODES[d["frame"][i]], TOOL_CODES[d["tool"][i]]))
    return out


def pack_layer_paths(lp: LayerPaths) -> tuple:
    """One layer's paths for the trip back from a worker process (one pickled object per
    path would cost more than planning a small layer)."""
    return lp.index, lp.z, lp.unfilled_mm2, pack_paths(lp.paths)


def unpack_layer_paths(packed: tuple) -> LayerPaths:
    index, z, unfilled, arrays = packed
    return LayerPaths(index, z, tuple(unpack_paths(arrays)), unfilled)


def save_toolpaths(tp: Toolpaths, path: str | os.PathLike) -> None:
    """Write toolpaths to a ``.npz`` file (layout in the module docstring), atomically."""
    paths = [p for lp in tp.layers for p in lp.paths]
    packed = pack_paths(paths)
    data = {
        "format": np.array(TOOLPATHS_FORMAT),
        "version": np.array(TOOLPATHS_VERSION),
        "job": np.array(to_toml(tp.job)),
        "warnings": np.array(list(tp.warnings), dtype=str),
        "points": packed.pop("points"),
        "state": (np.concatenate([point_states(p) for p in paths]) if paths
                  else np.zeros(0, dtype=np.int8)),
        **packed,
        "layer_index": np.array([lp.index for lp in tp.layers], dtype=np.int64),
        "layer_z": np.array([lp.z for lp in tp.layers], dtype=np.float64),
        "layer_start": offsets([len(lp.paths) for lp in tp.layers]),
        "unfilled_mm2": np.array([lp.unfilled_mm2 for lp in tp.layers],
                                 dtype=np.float64).reshape(-1, 2),
    }
    _write(path, data)


def load_toolpaths(path: str | os.PathLike) -> Toolpaths:
    """Read a file written by :func:`save_toolpaths`; StackFileError if it is missing,
    truncated, corrupt or not a toolpath file."""
    path = Path(path)

    def bad(msg: str) -> StackFileError:
        return StackFileError(f"{path}: {msg}")

    d = _read_all(path, "toolpath")
    if str(d.get("format", "")) != TOOLPATHS_FORMAT:
        raise bad(f"not an icefab toolpath file (format {str(d.get('format', 'missing'))!r}, "
                  f"expected {TOOLPATHS_FORMAT!r})")
    version = int(d.get("version", -1))
    if version not in (1, TOOLPATHS_VERSION):
        raise bad(f"toolpath file version {version}: expected {TOOLPATHS_VERSION} (or 1)")
    need = ("job", "warnings", "points", "path_start", "z", "material", "role", "closed",
            "width", "layer", "frame", "tool", "layer_index", "layer_z", "layer_start",
            "unfilled_mm2")
    missing = [k for k in need if k not in d]
    if missing:
        raise bad(f"missing arrays {', '.join(missing)}")
    job = _job(d, path)
    pts, start = d["points"], d["path_start"]
    P = len(d["z"])
    L = len(d["layer_index"])
    ok = (pts.ndim == 2 and pts.shape[1] == 2 and start.shape == (P + 1,)
          and all(len(d[k]) == P for k in ("material", "role", "closed", "width", "layer",
                                            "frame", "tool"))
          and d["layer_start"].shape == (L + 1,) and len(d["layer_z"]) == L
          and d["unfilled_mm2"].shape == (L, 2)
          and (P == 0 or (start[0] == 0 and start[-1] == len(pts)
                          and bool(np.all(np.diff(start) >= 0))))
          and (L == 0 or (d["layer_start"][0] == 0 and d["layer_start"][-1] == P
                          and bool(np.all(np.diff(d["layer_start"]) >= 0)))))
    if version >= 2:
        state = d.get("state")
        ok = ok and state is not None and state.shape == (len(pts),)
    if not ok:
        raise bad("inconsistent array sizes (truncated or corrupt)")
    for key, names in (("material", MATERIAL_CODES), ("role", ROLE_CODES),
                       ("frame", FRAME_CODES), ("tool", TOOL_CODES)):
        v = d[key]
        if len(v) and (v.min() < 0 or v.max() >= len(names)):
            raise bad(f"{key} codes out of range")
    if not np.all(np.isfinite(pts)):
        raise bad("non-finite point coordinates")
    if version >= 2 and len(d["state"]) and (d["state"].min() < OFF or d["state"].max() > ON2):
        raise bad("state codes out of range (expected 0 OFF, 1 ON1, 2 ON2)")
    paths = unpack_paths(d, copy=True)
    if version >= 2 and paths and not np.array_equal(
            d["state"], np.concatenate([point_states(p) for p in paths])):
        raise bad("per-point states disagree with the paths' materials and roles")
    ls = d["layer_start"]
    layers = tuple(LayerPaths(int(d["layer_index"][j]), float(d["layer_z"][j]),
                              tuple(paths[ls[j]:ls[j + 1]]),
                              (float(d["unfilled_mm2"][j, 0]), float(d["unfilled_mm2"][j, 1])))
                   for j in range(L))
    return Toolpaths(layers, job, tuple(str(w) for w in d["warnings"]))


# --------------------------------------------------------------------------- trajectories


def pack_trajectories(trajs: Sequence[Trajectory], n_joints: int = 0, *,
                      empty_pieces: bool = False) -> dict[str, np.ndarray]:
    """Trajectories' samples as flat arrays (the trajectory file's members, the worker
    processes' packing): ``xy``, ``joints``, ``speed``, ``traj_start``, ``piece_start``,
    ``piece_owner``, ``duration``, ``traj_dt``. A trajectory without pieces (one piece from
    sample 0) stores the piece at 0, unless ``empty_pieces`` (the worker packing keeps it
    empty, so the trajectory comes back as it was)."""
    xy, start = pack([t.xy for t in trajs])
    pcs = [t.pieces if len(t.pieces) or empty_pieces else np.zeros(1, np.int64)
           for t in trajs]
    return {
        "xy": xy,
        "joints": (np.concatenate([t.joints for t in trajs]) if trajs
                   else np.zeros((0, n_joints))),
        "speed": np.concatenate([t.speed for t in trajs]) if trajs else np.zeros(0),
        "traj_start": start,
        "piece_start": (np.concatenate(pcs) if pcs else np.zeros(0)).astype(np.int64),
        "piece_owner": np.repeat(np.arange(len(trajs)), [len(p) for p in pcs]).astype(np.int64),
        "duration": np.array([t.duration for t in trajs], dtype=np.float64),
        "traj_dt": np.array([t.dt for t in trajs], dtype=np.float64),
    }


def unpack_trajectories(d: dict[str, np.ndarray],
                        paths: Sequence[Toolpath | None]) -> list[Trajectory]:
    """The trajectories of :func:`pack_trajectories`' arrays, following ``paths``."""
    ts = d["traj_start"]
    pb = np.searchsorted(d["piece_owner"], np.arange(len(ts)))
    pstart = d["piece_start"]
    return [Trajectory(dt=float(d["traj_dt"][i]), xy=d["xy"][a:b], joints=d["joints"][a:b],
                       speed=d["speed"][a:b], duration=float(d["duration"][i]),
                       path=paths[i], pieces=pstart[pb[i]:pb[i + 1]])
            for i, (a, b) in enumerate(zip(ts[:-1], ts[1:]))]


def owner_arrays(motion: BuildMotion) -> dict[str, np.ndarray]:
    """Per trajectory, in file order: ``layer`` (T,) int64, ``path_index`` (T,) int64
    (within its layer), ``material`` (T,) int8 (0 part, 1 scaffold) and ``role`` (T,) int8
    (0 boundary, 1 fill, 2 measure, 3 travel); a trajectory without a path counts as 0."""
    owners = [(lm.index, i, t.path) for lm in motion.layers
              for i, t in enumerate(lm.trajectories)]
    return {"layer": np.array([o[0] for o in owners], dtype=np.int64),
            "path_index": np.array([o[1] for o in owners], dtype=np.int64),
            "material": np.array([MATERIAL_CODES.index(p.material) if p else 0
                                  for *_, p in owners], dtype=np.int8),
            "role": np.array([ROLE_CODES.index(p.role) if p else 0 for *_, p in owners],
                             dtype=np.int8)}


def save_trajectories(motion: BuildMotion, path: str | os.PathLike) -> None:
    """Write a BuildMotion to ``.npz`` (layout in the module docstring), atomically."""
    trajs = [t for lm in motion.layers for t in lm.trajectories]
    zs = [lm.z for lm in motion.layers for _ in lm.trajectories]
    jn = len(motion.joint_names) or (trajs[0].joints.shape[1] if trajs else 0)
    paths = [t.path for t in trajs]
    packed = pack_trajectories(trajs, jn)
    data = {
        "format": np.array(TRAJECTORIES_FORMAT), "version": np.array(TRAJECTORIES_VERSION),
        "dt": np.array(trajs[0].dt if trajs else motion.job.motion.dt_s),
        "robot": np.array(motion.robot),
        "joint_names": np.array(list(motion.joint_names), dtype=str),
        "job": np.array(to_toml(motion.job)),
        **packed,
        **owner_arrays(motion),
        "width": np.array([float(p.width) if p else 0.0 for p in paths], dtype=np.float64),
        "closed": np.array([bool(p.closed) if p else False for p in paths], dtype=bool),
        "tool": np.array([p.tool if p else "" for p in paths], dtype=str).reshape(-1),
        "path_z": np.array([float(p.z) if p else z for p, z in zip(paths, zs)],
                           dtype=np.float64),
        "layer_index": np.array([lm.index for lm in motion.layers], dtype=np.int64),
        "layer_z": np.array([lm.z for lm in motion.layers], dtype=np.float64),
        "layer_start": offsets([len(lm.trajectories) for lm in motion.layers]),
    }
    _write(path, data)


def load_trajectories(path: str | os.PathLike) -> BuildMotion:
    """Read a file written by :func:`save_trajectories` (versions 1 and 2).

    The trajectories' ``path`` is a stand-in Toolpath in the robot base frame whose
    ``polyline()`` is the samples (a closed path's last sample, back on its first, is the
    closing point), carrying layer, z, material, role, width, closed and tool.
    StackFileError if the file is missing, truncated, corrupt or of another kind.
    """
    path = Path(path)

    def bad(msg: str) -> StackFileError:
        return StackFileError(f"{path}: {msg}")

    data = _read_all(path, "trajectory")
    if str(data.get("format", "")) != TRAJECTORIES_FORMAT:
        raise bad(f"not an icefab trajectory file (format {str(data.get('format', ''))!r})")
    version = int(data.get("version", -1))
    if version not in TRAJECTORIES_READABLE:
        raise bad(f"trajectory file version {version}, expected one of "
                  f"{', '.join(map(str, TRAJECTORIES_READABLE))}")
    need = ["dt", "xy", "joints", "speed", "traj_start", "piece_start", "piece_owner",
            "duration", "layer", "path_index", "material", "role", "layer_index", "layer_z",
            "layer_start", "job", "robot", "joint_names"]
    if version >= 2:
        need += ["traj_dt", "width", "closed", "tool", "path_z"]
    missing = [k for k in need if k not in data]
    if missing:
        raise bad(f"missing arrays {', '.join(missing)}")
    job = _job(data, path)
    ts = data["traj_start"]
    nt = len(ts) - 1
    per_traj = ["duration", "layer", "material", "role"] + (
        ["traj_dt", "width", "closed", "tool", "path_z"] if version >= 2 else [])
    if nt < 0 or ts[-1] != len(data["xy"]) or np.any(np.diff(ts) < 0) \
            or any(len(data[k]) != nt for k in per_traj):
        raise bad("inconsistent trajectory index arrays (truncated or corrupt)")
    ls = data["layer_start"]
    if version >= 2:
        dts = data["traj_dt"].astype(np.float64)
        widths = data["width"].astype(np.float64)
        closed = data["closed"].astype(bool)
        tools = [str(x) for x in data["tool"]]
        zs = data["path_z"].astype(np.float64)
    else:
        log.warning("%s: trajectory file version 1 stores neither path widths, tools and "
                    "closed flags nor each trajectory's dt: widths 0 (the valve stage uses "
                    "the job's widths), open paths, dt %.4g s for all; re-run 'icefab plan' "
                    "to store them", path, float(data["dt"]))
        dts = np.full(nt, float(data["dt"]))
        widths = np.zeros(nt)
        closed = np.zeros(nt, dtype=bool)
        tools = [""] * nt
        zs = np.repeat(data["layer_z"].astype(np.float64), np.diff(ls)) \
            if len(ls) and ls[-1] == nt else np.zeros(nt)
    owner = data["piece_owner"]
    pstart = data["piece_start"]
    if len(owner) != len(pstart) or np.any(np.diff(owner) < 0):
        raise bad("inconsistent piece arrays (truncated or corrupt)")
    stand_ins = []
    for i in range(nt):
        xy = data["xy"][int(ts[i]):int(ts[i + 1])]
        pts = xy[:-1] if closed[i] and len(xy) > 2 and np.array_equal(xy[0], xy[-1]) else xy
        stand_ins.append(Toolpath(points=pts, z=float(zs[i]),
                                  material=MATERIAL_CODES[int(data["material"][i])],
                                  role=ROLE_CODES[int(data["role"][i])], closed=bool(closed[i]),
                                  width=float(widths[i]), layer=int(data["layer"][i]),
                                  frame="base", tool=tools[i]))
    trajs = unpack_trajectories({**data, "traj_dt": dts}, stand_ins)
    layers = tuple(LayerMotion(index=int(data["layer_index"][k]), z=float(data["layer_z"][k]),
                               trajectories=tuple(trajs[int(ls[k]):int(ls[k + 1])]))
                   for k in range(len(ls) - 1))
    return BuildMotion(layers=layers, job=job, robot=str(data["robot"]),
                       joint_names=tuple(str(x) for x in data["joint_names"]))
