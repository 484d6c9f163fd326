"""Part set-up (thesis 3.1.2, Table 3-1, paper Table 1): rotation, scaling, copies and
translation of a build, and loading the job's parts.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from icefab.core import Mesh
from icefab.errors import ConfigError, MeshError
from icefab.mesh.holes import prepare_closed
from icefab.mesh.load import load_meshes
from icefab.workload import check_copies, check_placed_part

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job, PartSetup

log = logging.getLogger(__name__)


def _rotation_matrix(axis: int, angle_deg: float) -> np.ndarray:
    """(3, 3) right-handed rotation about space-fixed axis 1 (x), 2 (y) or 3 (z)."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    i, j = [(1, 2), (2, 0), (0, 1)][axis - 1]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def rotation_matrix(rotation_deg: Sequence[float], order: Sequence[int]) -> np.ndarray:
    """(3, 3) rotation: about the space-fixed axes in ``order`` (1 = x, 2 = y, 3 = z).

    rotation_deg: angles about x, y, z, degrees. The first axis in ``order`` is applied
    first; space-fixed (extrinsic) rotations compose by left multiplication:
    ``R = R[order[2]] @ R[order[1]] @ R[order[0]]`` (thesis 3.1.2).
    """
    if sorted(int(o) for o in order) != [1, 2, 3]:
        raise ConfigError(f"parts.rotation_order = {tuple(order)!r}: must be a permutation "
                          "of 1, 2, 3")
    r = np.eye(3)
    for axis in order:
        r = _rotation_matrix(int(axis), float(rotation_deg[int(axis) - 1])) @ r
    return r


def transform(mesh: Mesh, parts: "PartSetup", job: "Job | None" = None) -> Mesh:
    """Place a build as the part set-up asks (thesis 3.1.2, Table 3-1, paper Table 1).

    Steps, in this order:

    1. If any rotation or scaling is asked, the mesh is first moved so that its minimum
       coordinate on every axis is zero (thesis 3.1.2).
    2. Rotations about the space-fixed x, y, z axes by ``rotation_deg``, one axis at a
       time in ``rotation_order`` (see :func:`rotation_matrix`).
    3. Scaling by ``scale`` along the space-fixed axes (after rotation, as the paper's
       "rotated, scaled, and translated").
    4. Copies: ``copies = (p1, p2, p3)`` lays ``p3`` copies out row by row in a grid of
       ``p1`` columns (x) by ``p2`` rows (y), spaced by the part's extent plus
       ``copy_gap_mm``; ``p3`` must not exceed ``p1 * p2``.
    5. Translation of the whole build per axis: a number is the build's minimum
       coordinate on that axis (mm); ``'cent'`` centres its bounding box on 0; ``'orig'``
       keeps the bounding-box centre where the original model's was.

    Returns a new Mesh (faces of copies appended after the original's). ``job`` (default:
    the default cell with these ``parts``) bounds the grid of copies by the robot's reach
    before they are made (:func:`icefab.workload.check_copies`).
    """
    from icefab.config import Job
    v = np.array(mesh.vertices, dtype=np.float64)
    if len(v) == 0:
        raise MeshError(f"{mesh.name or 'mesh'}: nothing to transform (no vertices)")
    lo0, hi0 = v.min(axis=0), v.max(axis=0)
    centre0 = 0.5 * (lo0 + hi0)
    scale = np.asarray(parts.scale, dtype=np.float64)
    rot = np.asarray(parts.rotation_deg, dtype=np.float64)
    if np.any(scale != 1.0) or np.any(rot % 360.0 != 0.0):
        v -= lo0  # thesis 3.1.2: minimum at zero before rotating or scaling
        v = v @ rotation_matrix(rot, parts.rotation_order).T
        v *= scale
    p1, p2, p3 = (int(c) for c in parts.copies)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if p3 > p1 * p2:
        raise ConfigError(f"parts.copies = {tuple(parts.copies)!r}: {p3} copies do not fit "
                          f"a {p1} x {p2} grid")
    if p3 > 1:
        lo, hi = v.min(axis=0), v.max(axis=0)
        check_copies(hi - lo, job if job is not None else Job(parts=parts))  # before copying
        pitch = (hi - lo)[:2] + float(parts.copy_gap_mm)
        k = np.arange(p3)
        shift = np.zeros((p3, 3))
        shift[:, 0] = (k % p1) * pitch[0]
        shift[:, 1] = (k // p1) * pitch[1]
        v = (v[None, :, :] + shift[:, None, :]).reshape(-1, 3)
        faces = (faces[None, :, :] + (np.arange(p3) * len(mesh.vertices))[:, None, None]
                 ).reshape(-1, 3)
    lo, hi = v.min(axis=0), v.max(axis=0)
    for axis, t in enumerate(parts.translation):
        if isinstance(t, str):
            if t == "cent":
                v[:, axis] -= 0.5 * (lo[axis] + hi[axis])
            elif t == "orig":
                v[:, axis] += centre0[axis] - 0.5 * (lo[axis] + hi[axis])
            else:
                raise ConfigError(f"parts.translation = {tuple(parts.translation)!r}: the "
                                  f"{'xyz'[axis]} entry must be a number, 'cent' or 'orig'")
        else:
            v[:, axis] += float(t) - lo[axis]
    return dataclasses.replace(mesh, vertices=v, faces=faces)


def part_fraction_range(mesh: Mesh, parts: "PartSetup") -> tuple[float, float]:
    """(zmin, zmax) mm of the slice of the build height to make (``parts.part_fraction``).

    ``[0, 1]`` is the whole part; fractions are of the height between the lowest and
    highest vertex.
    """
    lo, hi = mesh.bounds[:, 2]
    f0, f1 = parts.part_fraction
    h = float(hi - lo)
    return float(lo + f0 * h), float(lo + f1 * h)


def prepare_parts(job: "Job", base_dir: str | os.PathLike[str] | None = None) -> Mesh:
    """Load ``job.parts.files`` (relative to ``base_dir``), merge and place them.

    Welding follows ``job.parts.inexact`` / ``weld_tolerance_mm``; placement follows
    :func:`transform`; then holes are closed in 3D (``job.parts.close_holes``) and defects
    located in the build's coordinates (:func:`icefab.mesh.holes.prepare_closed`). Raises
    :class:`MeshError` when the job names no file.
    """
    parts = job.parts
    if not parts.files:
        raise MeshError("parts.files is empty: the job names no mesh file to build")
    base = Path(base_dir) if base_dir is not None else None
    paths = [Path(f) if base is None or Path(f).is_absolute() else base / f
             for f in parts.files]
    mesh = load_meshes(paths, inexact=parts.inexact, tolerance=parts.weld_tolerance_mm)
    return place_mesh(mesh, job)


def place_mesh(mesh: Mesh, job: "Job") -> Mesh:
    """A loaded mesh placed for the build, as :func:`prepare_parts` places the job's files:
    ``job.parts``' scale, rotation, copies and translation (:func:`transform`), checked
    against the cell (:func:`icefab.workload.check_placed_part`: units, the stroke, the
    robot's or gantry's reach, the laser's) and its holes closed in 3D
    (``job.parts.close_holes``). What :func:`icefab.slicing.slice_mesh` expects: a program
    that loads a mesh with :func:`load_mesh` gets the checks ``icefab slice`` makes (they
    were skipped on that path: a part in metres or out of reach went on to slicing).
    Raises WorkspaceError or ConfigError naming the setting to change."""
    placed = transform(mesh, job.parts, job)
    check_placed_part(placed.vertices, job, placed.faces)  # units, stroke, reach: before slicing
    return prepare_closed(placed, job)
