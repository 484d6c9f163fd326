"""Reference frames of the cell: part (building) frame, tool frames, robot base frame.

Thesis Table 3-1 and 4.1: the end effector (EE) keeps a constant orientation (joint 4);
the water nozzle, the scaffold nozzle and the laser spot are fixed offsets from it. Paths
are planned in the part frame of the tool that follows them; trajectories are EE
positions in the robot base frame. This module is the one place that converts between
them, for paths (``icefab.paths``), trajectories (``icefab.motion``), valve programs and
control action (``icefab.flow``) and the simulator.

All points: (n, 2) float64, mm.

May import: ``icefab.config``, ``icefab.errors``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from icefab.errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job

#: The tools that have a frame of their own (paths can be given in it); ``core.TOOLS``
#: is the set a Toolpath's ``tool`` may name, which adds "" (derived from its role).
FRAME_TOOLS = ("part", "scaffold", "laser")


def tool_offset(tool: str, job: "Job") -> np.ndarray:
    """(2,) float64, mm: origin of a tool's frame in the end-effector frame (Table 3-1).

    tool: "part" (water nozzle), "scaffold" (scaffold nozzle) or "laser".
    """
    if tool == "laser":
        return np.asarray(job.cell.laser_offset_mm, dtype=np.float64)
    if tool in ("part", "scaffold"):
        return np.asarray(job.materials[tool].nozzle_offset_mm, dtype=np.float64)
    raise ConfigError(f"unknown tool {tool!r}: expected one of {', '.join(FRAME_TOOLS)}")


def to_base_frame(points: np.ndarray, tool: str, job: "Job") -> np.ndarray:
    """End-effector positions in the robot base frame that put ``tool`` on part points.

    points: (n, 2) float64, mm, part-frame points where the tool must be.
    Returns (n, 2) float64, mm: ``points + ee_origin - tool_offset``.

    Sign convention (thesis Table 3-1, 2.x): ``cell.ee_origin_mm`` is where the end
    effector (EE) frame origin sits in the base frame when the part origin is under it,
    and a tool's offset (``nozzle_offset_mm``, ``laser_offset_mm``) is the origin of the
    tool's frame *in the EE frame* (the EE keeps a constant orientation, joint 4). A tool
    at EE position ``E`` is therefore at ``E + offset``; to put it at the part point ``p``
    (base point ``p + ee_origin``) the EE moves to ``p + ee_origin - offset``.

    Why this sign: the EE frame moves with the end effector (4.1: joint 4 keeps its
    orientation; "the two deposition nozzles and the laser displacement sensor ... are
    all offset from the Joint 4 axis", Fig. 4-1), so a frame whose origin has fixed
    coordinates in it is carried by the EE: the water, scaffold and laser frames are the
    tool points (4.2.1: measurement paths are the deposition paths "offset to the
    coordinate frame of the laser emission point"). Reading Table 3-1 instead as fixed
    building frames placed at ``ee_origin + offset`` (``p + ee_origin + offset``) would
    put the scaffold 2 x (0.3, 8.5) mm (about 17 mm) away from the water for the same
    part point, since the EE carries both nozzles.
    """
    pts = np.asarray(points, dtype=np.float64)
    return pts + (np.asarray(job.cell.ee_origin_mm, dtype=np.float64) - tool_offset(tool, job))


def to_part_frame(base_xy: np.ndarray, tool: str, job: "Job") -> np.ndarray:
    """The inverse of :func:`to_base_frame`: where ``tool`` is, in the part frame, when
    the end effector is at ``base_xy``.

    base_xy: (n, 2) float64, mm, EE positions in the robot base frame.
    Returns (n, 2) float64, mm: ``base_xy - ee_origin + tool_offset``.
    """
    off = np.asarray(job.cell.ee_origin_mm, dtype=np.float64) - tool_offset(tool, job)
    return np.asarray(base_xy, dtype=np.float64) - off
