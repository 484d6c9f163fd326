"""The job: every setting of a build, with the Cobra 600 RFP cell defaults.

This module is the single source of defaults (thesis Ch. 2-6, DESIGN.md). A ``Job`` is a
frozen dataclass of sections; each section is a frozen dataclass whose fields carry their
unit in the name where it could be read two ways, and a range in their metadata. A job is
validated when it is built, whether from Python, from TOML (:func:`load_job`) or from the
thesis' legacy control-parameter text file (:func:`load_legacy_control`).

TOML layout: one table per section, named like the ``Job`` attributes::

    [slicing]
    layer_thickness_mm = 0.25

    [materials.part]
    initial_offset_mm = 0.6

Unknown tables or keys, wrong types and out-of-range values raise :class:`ConfigError`
naming the file, line, setting, value and what was expected.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from icefab.errors import ConfigError
from icefab.inputs import read_input_text

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]


def setting(default: Any, help: str, *, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False, choices: tuple[str, ...] | None = None,
            why: str = "") -> Any:
    """A dataclass field with a description and an allowed range.

    lo/hi bound the value (every element for tuples); ``lo_open`` makes ``lo`` exclusive;
    ``why`` says what the range means physically (shown in range errors). Every numeric
    setting has both bounds (tests/test_config_ranges.py), so no setting can ask the
    pipeline for absurd work; work that depends on several settings and the part is
    estimated before it starts (:mod:`icefab.workload`).
    """
    meta = {"help": help, "lo": lo, "hi": hi, "lo_open": lo_open, "choices": choices,
            "why": why}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for defaults")
    return field(default=default, metadata=meta)


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class PartSetup:
    """Mesh files and their placement (thesis 3.1.2, Table 3-1)."""

    files: tuple[str, ...] = setting((), "mesh files (STL, PLY, OBJ) merged into one build; "
                                         "a relative name is relative to the job file")
    inexact: bool = setting(False, "weld vertices within weld_tolerance_mm instead of exactly "
                                   "(thesis 'inexact' option)")
    weld_tolerance_mm: float = setting(
        1e-4,
        "tolerance for inexact welding and point comparison",
        lo=0.0, hi=1.0, lo_open=True,
        why="beyond 1 mm welding merges distinct features of any part the cell builds")
    scale: Vec3 = setting(
        (1.0, 1.0, 1.0),
        "scaling factors along x, y, z",
        lo=1e-4, hi=1e4,
        why="unit conversions (1000: metres to mm, 0.001: micrometres) times a resize; the "
            "placed part must still fit the cell (checked before slicing)")
    rotation_deg: Vec3 = setting(
        (0.0, 0.0, 0.0),
        "rotations about the space-fixed x, y, z axes",
        lo=-360.0, hi=360.0,
        why="one turn either way")
    rotation_order: tuple[int, int, int] = setting((1, 2, 3), "order of the rotations (axes 1-3)",
                                                   lo=1, hi=3)
    translation: tuple[float | str, float | str, float | str] = setting(
        ("cent", "cent", 0.0),
        "per axis: a number is the part's minimum coordinate (mm), 'cent' centres it on 0, "
        "'orig' keeps the original position",
        lo=-1e4, hi=1e4,
        why="mm; the placed part must fit the workspace (checked before slicing)")
    copies: tuple[int, int, int] = setting(
        (1, 1, 1),
        "p1 x p2 grid of copies, p3 copies in all",
        lo=1, hi=100,
        why="p1, p2: more than 100 copies along an axis fit no workspace; p3: at most 100 "
            "copies in all")
    copy_gap_mm: float = setting(
        10.0,
        "gap between part copies in the grid",
        lo=0.0, hi=1000.0,
        why="wider than the largest workspace")
    part_fraction: Vec2 = setting((0.0, 1.0), "[min, max] fraction of the part height to slice",
                                  lo=0.0, hi=1.0)
    close_holes: bool = setting(True, "close the holes of an open surface (a scan) in 3D, "
                                      "once, after placement and before slicing "
                                      "(icefab.mesh.holes); the per-layer closure of "
                                      "slicing.open_contours is then only a last resort")


@dataclass(frozen=True)
class SlicingSettings:
    """Layer planes, contour linking and the path filter (thesis 3.2, Ossino 2)."""

    layer_thickness_mm: float = setting(
        0.25,
        "layer (slice) thickness",
        lo=0.01, hi=10.0,
        why="deposited layers are 0.1-1 mm (thesis 3.2: 0.25); 0.01 mm is 21 000 layers in the "
            "210 mm stroke, 10 mm is thicker than any drop")
    cut_fraction: float = setting(0.5, "where inside each layer the cutting plane lies: 0 "
                                       "bottom, 0.5 middle, 1 top", lo=0.0, hi=1.0)
    mode: str = setting("3d", "'3d' slices every layer; '2d' slices once and copies the "
                              "contour to all layers (thesis slicing option 3)",
                        choices=("3d", "2d"))
    min_point_spacing_mm: float = setting(
        0.4,
        "path filter: minimum distance between consecutive contour points",
        lo=0.0, hi=10.0,
        why="0: no filter; over 10 mm the filter removes the shape")
    max_filter_deviation_mm: float = setting(
        0.05,
        "path filter: largest distance a removed point may lie from the filtered contour",
        lo=0.0, hi=5.0,
        why="over 5 mm the filtered contour no longer describes the part")
    cusp_height_mm: float = setting(
        0.0, "adaptive layers (icefab.adaptive, Zhang & Liou): each layer as thick as keeps "
             "the staircase's cusp height t * |n_z| under this bound, within "
             "[min_layer_thickness_mm, max_layer_thickness_mm]; 0: every layer "
             "layer_thickness_mm thick (the water cell's default, thesis 4.1)",
        lo=0.0, hi=5.0,
        why="0: off; a cusp over 5 mm is no surface finish")
    min_layer_thickness_mm: float = setting(
        0.05, "with cusp_height_mm: the thinnest layer", lo=0.01, hi=10.0,
        why="as layer_thickness_mm")
    max_layer_thickness_mm: float = setting(
        0.0, "with cusp_height_mm: the thickest layer (0: layer_thickness_mm, so the bound "
             "only ever thins layers)", lo=0.0, hi=10.0,
        why="0: layer_thickness_mm; else as layer_thickness_mm")
    fit_contours: bool = setting(
        False, "replace the path filter by smooth contours: a local cubic B-spline through "
               "the exact section's points (icefab.fitting, Zhang & Liou), within "
               "fit_tolerance_mm of it, corners over corner_angle_deg kept, sampled at most "
               "min_point_spacing_mm apart (0.4 mm when 0); for faceted meshes, whose "
               "polygon vertices cap MTTS' curvature-limited speed")
    fit_tolerance_mm: float = setting(
        0.02, "largest distance between a fitted contour and the exact section",
        lo=0.001, hi=0.05,
        why="0.02 mm is the paths' own smoothing bound (motion.smoothing_tolerance_mm); "
            "over 0.05 mm the fit moves the part more than the path filter does; under "
            "0.001 mm it is the polygon")
    corner_angle_deg: float = setting(
        40.0, "with fit_contours: a contour turning by more than this at one point keeps "
              "the point as a sharp corner (a CAD edge, not faceting)",
        lo=5.0, hi=175.0,
        why="a 16-facet cylinder turns 22.5 degrees per facet; CAD edges turn 60-90")
    open_contours: str = setting("refuse", "open chains left after the 3D hole closing "
                                           "(parts.close_holes) whose closure in the layer "
                                           "needs a straight chord longer than max_gap_mm: "
                                           "'refuse' (default) stops with the layer, the "
                                           "chord and this setting named; 'close' builds "
                                           "the layer closed across it (your consent, "
                                           "reported); 'drop' leaves the chain out "
                                           "(reported)", choices=("refuse", "close", "drop"))
    max_gap_mm: float = setting(
        2.0,
        "the bound of the per-layer last resort: a straight chord closing an open contour in "
        "its layer may be at most this long (each closure reported); longer ones follow "
        "open_contours",
        lo=0.0, hi=100.0,
        why="a gap over 100 mm is not a mesh defect")


@dataclass(frozen=True)
class ScaffoldSettings:
    """Scaffold (support) regions (thesis 3.3, 3.7; Ossino 4)."""

    enabled: bool = setting(True, "generate scaffolding")
    buffer_mm: float = setting(
        3.3,
        "how far the scaffold surrounds the merged part region (0: classic support only under "
        "what is above)",
        lo=0.0, hi=100.0,
        why="the scaffold must fit the workspace beside the part")
    mode: str = setting("surround", "'surround': full scaffold around everything above; "
                                    "'overhang': only under overhangs steeper than "
                                    "overhang_angle_deg", choices=("surround", "overhang"))
    overhang_angle_deg: float = setting(45.0, "limiting overhang angle from vertical "
                                              "(overhang mode: steeper overhangs get "
                                              "scaffold; surround mode: how far the smoothed "
                                              "outer wall may lean out)", lo=0.0, hi=90.0)
    smoothing_mm: float = setting(
        0.1,
        "surround mode: how far the scaffold's outer wall may move to lose the scan's noise "
        "(0: the exact buffer). The buffer's offset keeps every wiggle of the part's "
        "slices, which holds the jerk-limited robot to ~40 mm/s along the outermost "
        "scaffold paths; the wall is smoothed within this and grown back over the buffer, "
        "so the scaffold only gets wider, by up to about twice this. More widens the band "
        "between the part and the wall past what its two boundary paths cover: on the "
        "bunny 0.1 mm took 1.8 % off 5 layers' MTTS time and left 6 mm^2 less unfilled, "
        "0.5 mm 2.4 % and 85 mm^2 more (BENCHMARKS.md, issue 15)",
        lo=0.0, hi=10.0,
        why="a scan's wiggles are a few hundredths to tenths of a millimetre; 10 mm would "
            "move the wall by six buffers")
    subset: Vec2 = setting((0.0, 1.0), "[min, max] fraction of the height that gets scaffold",
                           lo=0.0, hi=1.0)
    min_width_mm: float = setting(
        1.5,
        "scaffold pieces narrower than this are removed or merged",
        lo=0.0, hi=100.0,
        why="wider than any scaffold piece")
    hook_wall: bool = setting(False, "ice hook wall: outer scaffold paths of the first layers "
                                     "become part paths (thesis 3.7, Fig. 3-8)")


@dataclass(frozen=True)
class MaterialSettings:
    """Deposition settings of one material (thesis Table 3-1, 3.4-3.5)."""

    path_width_mm: float = setting(
        1.5,
        "boundary path width",
        lo=0.2, hi=20.0,
        why="a deposited line is 0.5-5 mm wide (thesis 3.4: 1.5)")
    fill_width_mm: float = setting(
        3.0,
        "fill path width (spacing of fill paths)",
        lo=0.5, hi=50.0,
        why="fill paths are spaced by about one line width, 0.5 mm or more (at 0.05 mm the "
            "demo mug's first 4 layers took over 120 s of path planning)")
    initial_offset_mm: float = setting(
        0.6,
        "inward offset of the first boundary path from the region edge",
        lo=0.0, hi=50.0,
        why="about half a path width")
    boundary_count: int = setting(
        1,
        "number of boundary paths",
        lo=0, hi=100,
        why="100 rings of 1.5 mm fill 300 mm")
    fill_pattern: str = setting("concentric", "fill: 'concentric', 'zigzag', 'raster' "
                                              "(unlinked), 'hybrid' (rings then zigzag), "
                                              "'none'",
                                choices=("concentric", "zigzag", "raster", "hybrid", "none"))
    fill_smoothing_mm: float = setting(
        0.25,
        "concentric fill: how far the outermost fill ring may move to take the noise of the "
        "contour off (a scanned mesh's slices wiggle by ~0.05 mm every few mm, which holds a "
        "jerk-limited robot to ~40 mm/s); the first ring then overlaps the boundary by up to "
        "twice this, never leaving a sliver between them. Every ring, this one too, is then "
        "smoothed within 10 % of the fill width (the corners inward offsets make of a "
        "contour's bumps rounded off) and the next offset from it, its bead widened by twice "
        "how far it moved inward (beyond the path filter inside the first), so the band "
        "outside stays covered (the valve follows the width). 0: off",
        lo=0.0, hi=2.0,
        why="beyond 2 mm the fill no longer follows the part's shape")
    fill_angle_deg: float = setting(
        0.0,
        "raster angle for zigzag/raster fill with fill_angle_mode = 'fixed'",
        lo=-360.0, hi=360.0,
        why="one turn either way")
    fill_angle_mode: str = setting(
        "optimal",
        "zigzag/raster angle: 'optimal' (each island of the region at the angle of least "
        "time by Jin's model, in steps of hybrid_angle_step_deg; hybrid fill always does "
        "this) or 'fixed' (fill_angle_deg); a job file that gives fill_angle_deg without "
        "it means 'fixed'",
        choices=("optimal", "fixed"))
    hybrid_rings: int = setting(
        2,
        "contour rings before zigzag in hybrid fill",
        lo=0, hi=100,
        why="100 rings of 1.5 mm fill 300 mm")
    hybrid_angle_step_deg: float = setting(
        15.0,
        "step of the raster angles compared by the optimal angle (zigzag, raster, hybrid)",
        lo=1.0, hi=90.0,
        why="at most 90 raster angles compared per region")
    nozzle_offset_mm: Vec2 = setting(
        (-0.1, -0.3),
        "origin of this material's building frame in the end-effector frame",
        lo=-200.0, hi=200.0,
        why="the nozzles sit on the end effector, within centimetres of joint 4")
    min_bead_width_mm: float = setting(
        0.0,
        "narrowest bead the gap fill lays: a strip down to 1/1.3 of it gets a bead this "
        "wide (at most 30 % more than it holds), a narrower one is left unfilled, and so "
        "is a gap path shorter than its width. The valve lays a line with at least "
        "flow.min_drops_per_mm drops per mm (thesis 6.1), each as large as its largest "
        "pulse: a bead w wide takes w dh c per mm, so w >= drops x pulse / dh: 1.0 mm for "
        "water (0.25 mm^3 pulses in the built-in table) and 1.25 mm for the scaffold "
        "(0.31 mm^3) at 0.25 mm layers. 0 (default for now): down to a tenth of the path "
        "width, beads the valve lays as separate drops or not at all",
        lo=0.0, hi=50.0,
        why="as the fill width")
    gap_fill: bool = setting(True, "fill the gaps the fill paths leave (e.g. between "
                                   "concentric rings) with extra rings of the boundary width")
    variable_width: bool = setting(
        True, "gap fill along a strip's centre line: one path per centre line whose width "
              "follows the strip's (the valve's flow follows it, w dh c); False: runs of "
              "one width each (a path wherever the width changes by 30 %), for a valve "
              "whose bead should not vary")
    tour_max_turn_deg: float = setting(
        240.0,
        "continuous tours (issue 15): consecutive boundary or fill paths of this material "
        "are joined through a travel curve the robot does not stop for (the valve is off "
        "over it) when the heading turns by at most this much from one path's end to the "
        "next one's start (120 deg from one closed path to another); 0: every path starts "
        "and ends at rest",
        lo=0.0, hi=360.0,
        why="degrees of heading change, 360 a U-turn; on 5 bunny layers 240 saves 3.8 % of "
            "the MTTS time, 120 2.8 %, 360 3.3 % (BENCHMARKS.md, issue 15)")
    calibration_file: str = setting("", "CSV of valve frequency (Hz) vs flow (mm^3/s), a "
                                        "relative name relative to the job file; empty: "
                                        "built-in table")
    density_g_cm3: float = setting(
        1.0,
        "density of the material, g/cm^3 (turns the masses of 'icefab calibrate valve' into "
        "volumes)",
        lo=0.1, hi=25.0,
        why="building materials weigh 0.5-2 g/cm^3; osmium, the densest, 22.6")


def _part_material() -> MaterialSettings:
    return MaterialSettings()


def _scaffold_material() -> MaterialSettings:
    # shortening methyl ester (thesis 2.4): about 0.88 g/cm^3
    return MaterialSettings(initial_offset_mm=1.2, nozzle_offset_mm=(0.2, 8.2),
                            density_g_cm3=0.88)


@dataclass(frozen=True)
class Materials:
    """Per-material settings: 'part' (water) and 'scaffold'."""

    part: MaterialSettings = field(default_factory=_part_material)
    scaffold: MaterialSettings = field(default_factory=_scaffold_material)
    order: tuple[str, ...] = setting(("part:boundary", "part:fill", "scaffold:boundary",
                                      "scaffold:fill"),
                                     "deposition order within a layer: each of the four "
                                     "groups once")

    def __getitem__(self, material: str) -> MaterialSettings:
        if material not in ("part", "scaffold"):
            raise ConfigError(f"unknown material {material!r}: expected 'part' or 'scaffold'")
        return getattr(self, material)


#: The part origin of the thesis' Cobra 600 cell (2.x), mm: ``cell.ee_origin_mm``'s default.
SCARA_EE_ORIGIN_MM = (260.0, -100.0)


def _placed(cell: "CellSettings") -> "CellSettings":
    """The cell with the part origin where its robot can build: a gantry whose
    ``ee_origin_mm`` was left at the default (a SCARA position, outside any gantry travel
    starting at 0) builds at the centre of its travel, where the part (centred on its origin
    by default, ``parts.translation``) fits. Resolved once, when the Job is built, so every
    stage (paths to base frame, trajectories, valve programs, the simulator) and every saved
    job carry the same origin. An origin the user set differently is kept."""
    if cell.robot != "gantry" or tuple(map(float, cell.ee_origin_mm)) != SCARA_EE_ORIGIN_MM:
        return cell
    return dataclasses.replace(cell, ee_origin_mm=tuple(0.5 * float(v)
                                                        for v in cell.gantry_travel_mm))


@dataclass(frozen=True)
class CellSettings:
    """The robot cell: kinematics, joint ranges and reference frames (thesis Ch. 2, 4.2)."""

    robot: str = setting("scara", "kinematics: 'scara' or 'gantry'", choices=("scara", "gantry"))
    l1_mm: float = setting(
        325.0,
        "SCARA inner link length",
        lo=10.0, hi=2000.0,
        why="SCARA links are 0.1-1 m long (Cobra 600: 325 mm)")
    l2_mm: float = setting(
        275.0,
        "SCARA outer link length",
        lo=10.0, hi=2000.0,
        why="SCARA links are 0.1-1 m long (Cobra 600: 275 mm)")
    reach_mm: Vec2 = setting(
        (163.0, 600.0),
        "[min, max] radial reach of the SCARA",
        lo=0.0, hi=4000.0,
        why="the maximum is at most l1_mm + l2_mm (checked)")
    joint_range_deg: Vec2 = setting(
        (105.0, 150.0),
        "SCARA joint 1 and 2 ranges (+/-)",
        lo=0.0, hi=360.0, lo_open=True,
        why="a revolute joint turns at most a full turn either way")
    elbow: str = setting("right", "SCARA elbow configuration", choices=("right", "left"))
    gantry_travel_mm: Vec2 = setting(
        (300.0, 300.0),
        "gantry x and y travel (from 0)",
        lo=10.0, hi=5000.0,
        why="gantry printers travel 0.1-2 m")
    ee_origin_mm: Vec2 = setting(
        SCARA_EE_ORIGIN_MM,
        "end-effector frame origin in the robot base frame when building (part origin); a gantry"
        " left at this default builds at the centre of its travel",
        lo=-5000.0, hi=5000.0,
        why="within the largest workspace")
    laser_offset_mm: Vec2 = setting(
        (-30.0, 19.0),
        "laser measurement frame origin in the end-effector frame",
        lo=-200.0, hi=200.0,
        why="the laser sits on the end effector")
    laser_latency_s: float = setting(
        0.0,
        "laser measurement latency: a sample reads the surface where the laser was this long "
        "before the position it is tagged with; compensated when building on a cell ('icefab "
        "calibrate laser', thesis 5.2.1)",
        lo=0.0, hi=1.0,
        why="sensor latency is milliseconds")
    encoder_resolution_deg: float = setting(
        0.001,
        "joint encoder resolution",
        lo=0.0, hi=1.0,
        why="robot encoders resolve far below a degree")
    stroke_mm: float = setting(
        210.0,
        "vertical stroke: the tallest build the cell can make (Cobra 600, thesis Table 2-1)",
        lo=1.0, hi=5000.0,
        why="robot and gantry z axes travel 0.05-2 m")
    cpus: int = setting(
        0,
        "worker processes for parallel stages (0: all cores)",
        lo=0, hi=1024,
        why="used as min(cpus, the machine's cores)")


@dataclass(frozen=True)
class MotionSettings:
    """Minimum-time trajectory shaping limits (thesis Ch. 4, eq. 4.10)."""

    dt_s: float = setting(
        0.016,
        "output time step",
        lo=0.001, hi=0.1,
        why="the controller's trajectory step (Cobra 600 C40: 16 ms); at 125 mm/s a 0.1 s "
            "step is 12.5 mm, and coarser steps cut whole paths short (a 31 mm ring planned "
            "at 1 s was one point, its volume lost unsaid)")
    speed_mm_s: float = setting(
        125.0,
        "Cartesian speed bound",
        lo=1.0, hi=10000.0,
        why="the Cobra 600 exceeds 1 m/s; below 1 mm/s water freezes in the nozzle")
    accel_mm_s2: float = setting(
        500.0,
        "total Cartesian acceleration bound; with motion.dt_s, accel x dt^2 / 8 (how far "
        "a step cuts a curve taken at it) must stay within half the narrowest path width",
        lo=1.0, hi=1e6,
        why="up to 100 g")
    jerk_mm_s3: float = setting(
        4000.0,
        "Cartesian jerk bound",
        lo=1.0, hi=1e8,
        why="up to 10 000 g/s")
    jerk_limited: bool = setting(True, "apply jerk bounds (off: compare with TOPP-RA)")
    joint_speed_deg_s: Vec2 = setting(
        (33.0, 39.0),
        "joint 1, 2 speed bounds",
        lo=0.1, hi=3600.0,
        why="up to 10 turns/s")
    joint_accel_deg_s2: Vec2 = setting(
        (165.0, 195.0),
        "joint 1, 2 acceleration bounds",
        lo=1.0, hi=1e5,
        why="robot joints")
    joint_jerk_deg_s3: Vec2 = setting(
        (1320.0, 1560.0),
        "joint 1, 2 jerk bounds",
        lo=1.0, hi=1e7,
        why="robot joints")
    gantry_speed_mm_s: Vec2 = setting(
        (250.0, 250.0),
        "gantry x, y axis speed bounds",
        lo=1.0, hi=10000.0,
        why="up to 10 m/s")
    gantry_accel_mm_s2: Vec2 = setting(
        (2000.0, 2000.0),
        "gantry x, y axis acceleration bounds",
        lo=1.0, hi=1e6,
        why="up to 100 g")
    gantry_jerk_mm_s3: Vec2 = setting(
        (20000.0, 20000.0),
        "gantry x, y axis jerk bounds",
        lo=1.0, hi=1e8,
        why="up to 10 000 g/s")
    smooth_angle_deg: float = setting(
        30.0,
        "direction change above which a path is split and the robot stops (PATHSPLIT). "
        "A corner below it is passed at a speed the acceleration bound allows for its turn "
        "within one sample (dt): the acceleration holds within ~10 % between grid points, "
        "but the jerk bound cannot hold at a corner passed at speed (at 180 a 106 deg turn "
        "was passed at 6 mm/s: 1.2 times the acceleration, 9 times the jerk bound)",
        lo=1.0, hi=180.0,
        why="below 1 degree every filtered vertex stops the robot")
    point_spacing_mm: float = setting(
        0.4,
        "resampling spacing of split pieces",
        lo=0.01, hi=1.0,
        why="samples within a drop width of each other; the acceleration bound holds "
            "between grid points up to 1 mm (on a 2 mm grid a 5 mm circle planned 1.10 "
            "times it, on a 10 mm grid a straight line 1.8 times)")
    smoothing_tolerance_mm: float = setting(
        0.02,
        "smoothing of the resampled paths within this tolerance (0: off; a hard bound: every "
        "sample stays within it of the input path). The joints' Savitzky-Golay filter gets what "
        "is left of 0.02 mm (at most 0.01; none at this default), so the tool stays within 0.02 "
        "mm of the input (issue 4). Default 0.02 mm: the slicer's filtered polygons turn a few "
        "degrees at every vertex, which costs v*turn/dt of acceleration; 0.02 mm makes MTTS 6-9 "
        "% faster on the bunny and a rounded box, twice what 0.01 mm with the joint filter "
        "gives, at the same joint jerk (BENCHMARKS.md)",
        lo=0.0, hi=1.0,
        why="below the path width")
    measure_speed_mm_s: float = setting(
        50.0,
        "speed bound along the part's (ice's) measurement paths (thesis 4.2.1: the laser "
        "reads ice best slowly); the scaffold's are measured at up to motion.speed_mm_s",
        lo=1.0, hi=10000.0,
        why="as speed_mm_s")
    travel_speed_mm_s: float = setting(
        125.0,
        "speed of travel moves",
        lo=1.0, hi=10000.0,
        why="as speed_mm_s")
    boundary_speed_mm_s: float = setting(
        25.0,
        "constant speed of boundary paths in the constant-speed estimate",
        lo=1.0, hi=10000.0,
        why="as speed_mm_s")
    fill_speed_mm_s: float = setting(
        125.0,
        "constant speed of fill paths in the constant-speed estimate",
        lo=1.0, hi=10000.0,
        why="as speed_mm_s")
    savgol_window: int = setting(
        7,
        "Savitzky-Golay window for joint vectors (odd, 0: off)",
        lo=0, hi=101,
        why="samples; a wider window averages whole paths")
    rest_accel_mm_s2: float = setting(
        80.0,
        "initial and final acceleration of the from/to rest curves with jerk on, so the first "
        "samples move the joints beyond the encoder resolution (thesis 4.2.6); at most "
        "accel_mm_s2",
        lo=0.0, hi=1e6,
        why="as accel_mm_s2")


@dataclass(frozen=True)
class FlowSettings:
    """Variable-flow valve control (thesis Ch. 6, 2.3.1)."""

    mode: str = setting("fm", "'fm' frequency modulation or 'pwm'", choices=("fm", "pwm"))
    tick_s: float = setting(
        0.002,
        "microcontroller tick",
        lo=1e-5, hi=0.1,
        why="microcontroller timers tick in 10 us-100 ms (thesis 2.3.1: 2 ms)")
    max_piece_s: float = setting(
        131.072,
        "longest program piece; a piece also ends before its ticks overflow uint16 "
        "(65 535.5 ticks: 131.071 s at the 2 ms tick, icefab.flow.piece_max_s)",
        lo=0.01, hi=1e4,
        why="a piece spans at least a few ticks")
    max_pulses: int = setting(
        16384,
        "most pulses in one program piece (PWM pieces also at most 2 048: the valve "
        "controller must hold a PWM piece whole, icefab.flow.PWM_PIECE_PULSES)",
        lo=1, hi=16384,
        why="the valve controller's protocol takes at most 16 384 pulses a piece "
            "(firmware/PROTOCOL.md, thesis 2.3.1)")
    max_frequency_hz: float = setting(
        500.0,
        "highest valve frequency the cell can make: at most one pulse per tick (1 / tick_s, "
        "500 Hz at the thesis' 2 ms tick, 2.3.1); the valve itself is rated 1000 Hz (6.1)",
        lo=1.0, hi=1e5,
        why="solenoid valves switch below 10 kHz")
    min_pulse_ms: float = setting(
        0.5,
        "shortest valve opening",
        lo=0.01, hi=1000.0,
        why="valve openings")
    min_drops_per_mm: float = setting(
        1.0,
        "at least this many drops per mm of path",
        lo=0.0, hi=100.0,
        why="drops are about 0.1-1 mm apart")
    layer_scale: float = setting(
        1.0,
        "nominal flow factor c in q = w * dh * c",
        lo=0.1, hi=10.0,
        why="the deposited volume is within a factor 10 of w * dh")
    out_of_range: str = setting("error", "a nominal flow beyond the calibration table or a "
                                         "frequency beyond max_frequency_hz: 'error' "
                                         "(default) or 'clamp' to the limit (opt-in; reported "
                                         "with the volume it costs); SMF's correction beyond "
                                         "the valve is always saturated (thesis 5.2.2)",
                                choices=("clamp", "error"))
    pwm_frequency_hz: float = setting(
        125.0,
        "PWM mode: constant valve frequency (thesis 6.1: >= 125 Hz for one drop per mm at 125 "
        "mm/s)",
        lo=1.0, hi=1e5,
        why="as max_frequency_hz")
    calibration_pulse_ms: float = setting(
        0.5,
        "pulse width at which the calibration table was measured (FM pulse width; PWM scales "
        "flow per pulse with the width)",
        lo=0.01, hi=1000.0,
        why="as min_pulse_ms")


@dataclass(frozen=True)
class FeedbackSettings:
    """Surface mapping feedback (thesis Ch. 5)."""

    enabled: bool = setting(True, "close the loop with the laser measurements")
    interval_layers: int = setting(
        4,
        "n_d: measure every this many layers",
        lo=1, hi=1000,
        why="at least one measurement per 1000 layers")
    kp: float = setting(
        1.0,
        "proportional gain Kp",
        lo=0.0, hi=100.0,
        why="stable gains are of order 1 (thesis 5.5)")
    ki: float = setting(
        0.33,
        "normalised integral gain Ki* = Ki * dh_m",
        lo=0.0, hi=100.0,
        why="stable gains are of order 1 (thesis 5.5)")
    kd: float = setting(
        0.03,
        "normalised derivative gain Kd* = Kd / dh_m",
        lo=0.0, hi=100.0,
        why="stable gains are of order 1 (thesis 5.5)")
    saturation: float = setting(
        0.3,
        "saturation of the control action U (fraction)",
        lo=0.0, hi=1.0, lo_open=True,
        why="at most the whole nominal flow")
    integral_saturation: float = setting(
        0.3,
        "saturation of the integral term (fraction)",
        lo=0.0, hi=1.0, lo_open=True,
        why="as saturation")
    controller: str = setting("flow", "'flow' (nu-controller, valve flow) or 'speed' "
                                      "(c-controller)", choices=("flow", "speed"))
    grid_mm: float = setting(
        1.0,
        "error surface grid pitch",
        lo=0.1, hi=20.0,
        why="near the laser spot and path width")
    measure_spacing_mm: float = setting(
        3.0,
        "spacing of concentric measurement paths; what the rings leave farther than half "
        "of it (a wall narrower than the spacing holds none) is measured along its centre "
        "line",
        lo=1.0, hi=100.0,
        why="about the path width (thesis Fig. 5-5: concentric BUFFERF paths); at 0.1 mm "
            "the demo mug's first 4 layers took over 120 s to plan")
    smoothing: bool = setting(True, "robust smoothing of the measured surface")


@dataclass(frozen=True)
class SimulationSettings:
    """The virtual cell's disturbances (thesis 5.6-5.7)."""

    seed: int = setting(
        0,
        "random seed",
        lo=0, hi=4294967295,
        why="a 32-bit seed")
    grid_mm: float = setting(
        0.5,
        "height map pitch",
        lo=0.1, hi=20.0,
        why="a tenth of a drop's width at the finest (the work grows fourfold per halving: "
            "0.05 mm took over 2 min for 4 mug layers); the demo mug needs 0.5 mm")
    flow_error: float = setting(
        0.10,
        "flow gain error (fraction, +0.1 = 10 % too much)",
        lo=-0.9, hi=10.0,
        why="fraction")
    flow_drift_per_cm3: float = setting(
        0.0,
        "flow gain drift per cm^3 deposited (fraction)",
        lo=-0.1, hi=0.1,
        why="10 % per cm^3 is a valve failing within a few layers")
    noise_mm: float = setting(
        0.02,
        "random height noise per layer (std)",
        lo=0.0, hi=10.0,
        why="beyond 10 mm per layer nothing is built")
    laser_noise_mm: float = setting(
        0.01,
        "laser measurement noise (std)",
        lo=0.0, hi=10.0,
        why="laser sensors resolve microns")
    debris_rate: float = setting(
        0.0,
        "debris pulses per layer",
        lo=0.0, hi=1000.0,
        why="per layer")
    edge_loss: float = setting(0.1, "weaker deposition at region edges (fraction)", lo=0.0,
                               hi=1.0)
    layers: int = setting(
        0,
        "simulate only the first N layers (0: all)",
        lo=0, hi=1000000,
        why="layers")
    noise_corr_mm: float = setting(
        3.0,
        "correlation length of the height noise",
        lo=0.0, hi=1000.0,
        why="up to the workspace")
    debris_height_mm: float = setting(
        0.5,
        "height of one debris pulse (thesis d_p = 0.5 measurement intervals)",
        lo=0.0, hi=10.0,
        why="about a layer")
    debris_radius_mm: float = setting(
        2.0,
        "radius (Gaussian sigma) of one debris pulse",
        lo=0.0, hi=100.0, lo_open=True,
        why="about a drop")
    laser_latency_s: float = setting(
        0.002,
        "the simulated laser's own latency (the simulator's and the virtual cell's): a sample "
        "reads where the spot was this long before the position it is tagged with; builds "
        "and the simulator take cell.laser_latency_s off",
        lo=0.0, hi=1.0,
        why="sensor latency is milliseconds")
    laser_rate_hz: float = setting(
        100.0,
        "laser sampling rate along measurement paths",
        lo=1.0, hi=1e5,
        why="laser sensors sample at 10 Hz-50 kHz")
    deposition: str = setting("flow", "volume deposited along the paths: 'flow' = the "
                                      "commanded flow (ideal valve), 'valves' = the pulses of "
                                      "the valve programs x the calibrated drop volume",
                              choices=("flow", "valves"))
    spread_mm: float = setting(
        1.0,
        "how far the liquid of a layer flows (diffusion length) before it freezes: fills gaps "
        "between paths up to twice this wide; at least one cell of the height map "
        "(simulation.grid_mm)",
        lo=0.1, hi=50.0,
        why="water and SME spread before they freeze (thesis 3.7, 4.2), within millimetres; a "
            "layer that does not flow at least one cell of the height map stacks every "
            "overlap and gap between beads into ridges and holes, layer after layer (0 "
            "left +16.5 / -9.7 mm on the demo mug's first 60 layers)")


@dataclass(frozen=True)
class Job:
    """Every setting of a build. ``Job()`` is the default Cobra 600 RFP cell."""

    parts: PartSetup = field(default_factory=PartSetup)
    slicing: SlicingSettings = field(default_factory=SlicingSettings)
    scaffold: ScaffoldSettings = field(default_factory=ScaffoldSettings)
    materials: Materials = field(default_factory=Materials)
    cell: CellSettings = field(default_factory=CellSettings)
    motion: MotionSettings = field(default_factory=MotionSettings)
    flow: FlowSettings = field(default_factory=FlowSettings)
    feedback: FeedbackSettings = field(default_factory=FeedbackSettings)
    simulation: SimulationSettings = field(default_factory=SimulationSettings)

    def __post_init__(self) -> None:
        _validate(self, "")
        object.__setattr__(self, "cell", _placed(self.cell))  # frozen: set once, here
        _check_cross(self)

    def replace(self, **changes: Any) -> "Job":
        """A copy with dotted settings changed: ``job.replace(**{"slicing.layer_thickness_mm": 0.5})``."""
        data = to_dict(self)
        for dotted, value in changes.items():
            node = data
            *head, last = dotted.split(".")
            for key in head:
                if key not in node or not isinstance(node[key], dict):
                    raise ConfigError(f"unknown setting {dotted!r}")
                node = node[key]
            if last not in node:
                raise ConfigError(f"unknown setting {dotted!r}")
            node[last] = value
        return job_from_dict(data)


# --------------------------------------------------------------------------- validation


@functools.lru_cache(maxsize=None)
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _check_value(path: str, value: Any, meta: dict[str, Any]) -> None:
    items = value if isinstance(value, tuple) else (value,)
    lo, hi = meta.get("lo"), meta.get("hi")
    def num(v: float) -> str:   # an integer bound in full ("<= 4.29497e+09" for a seed)
        return f"{v}" if isinstance(v, int) else f"{v:g}"

    rng = [f"{'>' if meta.get('lo_open') else '>='} {num(lo)}"] if lo is not None else []
    rng += [f"<= {num(hi)}"] if hi is not None else []
    for v in items:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        if v != v or v in (float("inf"), float("-inf")):
            # the range too (a tester's --density inf was told only 'finite')
            raise ConfigError(f"{path} = {value!r}: must be a finite number"
                              + (f" {' and '.join(rng)}" if rng else ""))
        below = lo is not None and (v <= lo if meta.get("lo_open") else v < lo)
        if below or (hi is not None and v > hi):
            why = f" ({meta['why']})" if meta.get("why") else ""
            raise ConfigError(f"{path} = {value!r}: must be {' and '.join(rng)}{why}")
    choices = meta.get("choices")
    if choices and value not in choices:
        raise ConfigError(f"{path} = {value!r}: must be one of {', '.join(choices)}")


def _validate(obj: Any, prefix: str) -> None:
    """Check every setting of ``obj`` (a Job or a section) and give it its field's type.

    A Job built directly (``Job(motion=MotionSettings(speed_mm_s=...))``, not by
    ``replace`` or a file) gets the same checks as one read from TOML: a numpy scalar
    becomes a Python number and is range-checked, a string where a number belongs or a
    list where a tuple belongs is refused or converted, as ``_coerce`` does for TOML
    values. The sections are frozen, so the converted values are set here, once."""
    hints = _hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        path = f"{prefix}{f.name}"
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            if type(value) is not hint:
                raise ConfigError(f"{path} = {value!r}: expected a {hint.__name__} section")
            _validate(value, path + ".")
            continue
        typed = _coerce(path, value, hint)
        if typed is not value:
            object.__setattr__(obj, f.name, typed)
        if f.metadata:
            _check_value(path, typed, dict(f.metadata))


def _check_cross(job: Job) -> None:
    """Checks that involve more than one setting."""
    for i, f in enumerate(job.parts.files):   # '' was read as the current folder (hunt P)
        if not f.strip():
            raise ConfigError(f"parts.files[{i}] = {f!r}: an empty file name")
    lo, hi = job.parts.part_fraction
    if lo >= hi:
        raise ConfigError(f"parts.part_fraction = {job.parts.part_fraction!r}: min must be "
                          "below max")
    lo, hi = job.scaffold.subset
    if lo > hi:
        raise ConfigError(f"scaffold.subset = {job.scaffold.subset!r}: min must not exceed max")
    sl = job.slicing
    if sl.cusp_height_mm > 0 and sl.min_layer_thickness_mm > (sl.max_layer_thickness_mm
                                                            or sl.layer_thickness_mm):
        raise ConfigError(f"slicing.min_layer_thickness_mm = {sl.min_layer_thickness_mm:g} "
                          "must not exceed slicing.max_layer_thickness_mm (or, when that is "
                          f"0, slicing.layer_thickness_mm = {sl.layer_thickness_mm:g})")
    rmin, rmax = job.cell.reach_mm
    if rmin >= rmax:
        raise ConfigError(f"cell.reach_mm = {job.cell.reach_mm!r}: min must be below max")
    links = job.cell.l1_mm + job.cell.l2_mm
    if rmax > links:
        raise ConfigError(f"cell.reach_mm = {job.cell.reach_mm!r}: max must not exceed "
                          f"cell.l1_mm + cell.l2_mm = {links:g} (the arm stretched out)")
    w = job.motion.savgol_window
    if w and (w % 2 == 0 or w < 5):
        raise ConfigError(f"motion.savgol_window = {w}: must be 0 (off) or an odd number >= 5")
    for axis, t in zip("xyz", job.parts.translation):
        if isinstance(t, str) and t not in ("cent", "orig"):
            raise ConfigError(f"parts.translation = {job.parts.translation!r}: the {axis} entry "
                              "must be a number, 'cent' or 'orig'")
    if sorted(job.parts.rotation_order) != [1, 2, 3]:
        raise ConfigError(f"parts.rotation_order = {tuple(job.parts.rotation_order)!r}: must "
                          "be a permutation of 1, 2, 3")
    mo = job.motion
    narrow = min(job.materials.part.path_width_mm, job.materials.scaffold.path_width_mm)
    chord = mo.accel_mm_s2 * mo.dt_s ** 2 / 8.0
    if chord > narrow / 2.0:
        # a hunt's 1e6 mm/s^2: a 3 mm ring became two samples at one point, a 200 mm
        # circle an octagon 17 mm off; at the defaults 0.016 mm
        raise ConfigError(f"motion.accel_mm_s2 = {mo.accel_mm_s2:g} with motion.dt_s = "
                          f"{mo.dt_s:g}: a curve taken at that acceleration is cut by up to "
                          f"accel x dt^2 / 8 = {chord:.3g} mm between two samples, over half "
                          f"the narrowest path width ({narrow:g} mm): the bead would leave "
                          "its path; lower either")
    p1, p2, p3 = job.parts.copies
    if p3 > p1 * p2:
        raise ConfigError(f"parts.copies = {tuple(job.parts.copies)!r}: {p3} copies do not "
                          f"fit a {p1} x {p2} grid")
    fl = job.flow
    if abs(fl.tick_s * 1e6 - round(fl.tick_s * 1e6)) > 1e-6:
        raise ConfigError(f"flow.tick_s = {fl.tick_s!r}: must be a whole number of "
                          "microseconds (valve programs store the tick in microseconds: "
                          f"{fl.tick_s:g} s was read back as {round(fl.tick_s * 1e6) / 1e6:g} s, "
                          "every pulse late or early)")
    sim = job.simulation
    if sim.spread_mm < sim.grid_mm:
        # below one cell the liquid levels nothing: the beads' overlaps and gaps of every
        # layer stack up (spread 0.25 at grid 0.5 left -5.7 mm holes on the demo mug)
        raise ConfigError(f"simulation.spread_mm = {sim.spread_mm:g}: must be >= "
                          f"simulation.grid_mm = {sim.grid_mm:g} (the simulated liquid must "
                          "flow at least one cell of the height map, or every layer's "
                          "overlaps and gaps between beads stack into ridges and holes); "
                          "raise simulation.spread_mm or lower simulation.grid_mm")
    if job.feedback.controller == "speed" and job.feedback.saturation >= 1.0:
        raise ConfigError(f"feedback.saturation = {job.feedback.saturation:g} with "
                          "feedback.controller = 'speed': must be below 1 (the speed "
                          "controller slows a path by up to this fraction of its speed; at 1 "
                          "it would stop)")
    if fl.max_frequency_hz * fl.tick_s > 1.0 + 1e-9:
        raise ConfigError(f"flow.max_frequency_hz = {fl.max_frequency_hz:g}: above "
                          f"1 / flow.tick_s = {1.0 / fl.tick_s:g} Hz, one pulse per "
                          "microcontroller tick (pulses would share a tick); lower "
                          "flow.max_frequency_hz or flow.tick_s")
    limits = {"1 / flow.tick_s": 1.0 / fl.tick_s, "flow.max_frequency_hz": fl.max_frequency_hz,
              "1 / flow.min_pulse_ms": 1000.0 / fl.min_pulse_ms}
    name, top = min(limits.items(), key=lambda kv: kv[1])
    if fl.mode == "pwm" and fl.pwm_frequency_hz > top:
        # only PWM uses it (FM at max_frequency_hz = 100 was refused for PWM's 125 Hz)
        raise ConfigError(f"flow.pwm_frequency_hz = {fl.pwm_frequency_hz:g}: must not exceed "
                          f"{name} = {top:g} Hz")
    if fl.calibration_pulse_ms < fl.min_pulse_ms:
        raise ConfigError(f"flow.calibration_pulse_ms = {fl.calibration_pulse_ms:g}: must be at "
                          f"least flow.min_pulse_ms = {fl.min_pulse_ms:g}")
    order = job.materials.order
    allowed = {f"{m}:{r}" for m in ("part", "scaffold") for r in ("boundary", "fill")}
    # every group once: one left out was silently never laid, and the summary called its
    # area filled (hunt P); a group is left out by its own settings
    if sorted(order) != sorted(allowed):
        raise ConfigError(f"materials.order = {order!r}: must list each of "
                          f"{', '.join(sorted(allowed))} once (to lay no boundaries or no "
                          f"fill, set materials.*.boundary_count = 0 or fill_pattern = "
                          f"\"none\")")


def _coerce(path: str, value: Any, hint: Any) -> Any:
    """Convert a TOML value to the field's type, or raise ConfigError."""
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(f"{path}: expected a table, got {value!r}")
        return _build(hint, value, path + ".")
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path} = {value!r}: expected a list")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(f"{path}[{i}]", v, args[0]) for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{path} = {value!r}: expected {len(args)} values, got "
                              f"{len(value)}")
        return tuple(_coerce(f"{path}[{i}]", v, a) for i, (v, a) in enumerate(zip(value, args)))
    if origin in (typing.Union, types.UnionType):
        for a in typing.get_args(hint):
            try:
                return _coerce(path, value, a)
            except ConfigError:
                continue
        names = " or ".join(getattr(a, "__name__", str(a)) for a in typing.get_args(hint))
        raise ConfigError(f"{path} = {value!r}: expected {names}")
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{path} = {value!r}: expected true or false")
    # numpy's scalars are numbers too (a program's np.float32(0.5) was 'expected a number')
    if hint is int:
        if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
            return int(value)
        raise ConfigError(f"{path} = {value!r}: expected an integer")
    if hint is float:
        if isinstance(value, (int, float, np.integer, np.floating)) \
                and not isinstance(value, (bool, np.bool_)):
            try:
                return float(value)
            except OverflowError:   # an integer of hundreds of digits (hunt P)
                raise ConfigError(f"{path}: an integer of {len(str(abs(value)))} digits, "
                                  f"beyond any number a setting takes") from None
        raise ConfigError(f"{path} = {value!r}: expected a number")
    if hint is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{path} = {value!r}: expected a string")
    raise ConfigError(f"{path}: unsupported setting type {hint!r}")  # pragma: no cover


def _build(cls: type, data: dict[str, Any], prefix: str, base: Any = None) -> Any:
    """A settings section from its table: the values given, the others from ``base`` (the
    section's default where it sits: the scaffold's material settings are not the part's)
    or the class's defaults."""
    hints = _hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if key not in fields:
            raise ConfigError(f"unknown setting {prefix}{key!r}".replace("'", "") +
                              f": expected one of {', '.join(sorted(fields))}")
        if dataclasses.is_dataclass(hints[key]) and isinstance(value, dict):
            f = fields[key]
            default = (f.default_factory() if f.default_factory is not dataclasses.MISSING
                       else None if f.default is dataclasses.MISSING else f.default)
            kwargs[key] = _build(hints[key], value, prefix + key + ".", default)
        else:
            kwargs[key] = _coerce(prefix + key, value, hints[key])
    if cls is Job:
        return Job(**kwargs)
    if base is not None:
        return dataclasses.replace(base, **kwargs)
    return cls(**kwargs)


def job_from_dict(data: dict[str, Any]) -> Job:
    """Build and validate a Job from nested plain data (as read from TOML)."""
    return _build(Job, _angles_given(data), "")


def stored_job_from_dict(data: dict[str, Any]) -> Job:
    """:func:`job_from_dict` of a job an earlier icefab stored (a result file's, a build
    folder's or a cell's ``job.toml``), after raising a setting whose range has since
    narrowed to its new least value, so that the files still load (a job file given with
    ``-c`` is refused instead: :func:`job_from_dict`).

    ``simulation.spread_mm``: 0 ("no spreading") and values under one cell of
    ``simulation.grid_mm`` were valid before 2026-11-29; the simulator's liquid must now
    flow at least max(0.1 mm, one cell). Only the simulator reads it: a stacked stack or
    paths file made with 0 was refused by every later command, though none used it (a
    review's)."""
    sim = data.get("simulation")
    if isinstance(sim, dict) and "spread_mm" in sim:
        least = max(SimulationSettings.__dataclass_fields__["spread_mm"].metadata["lo"],
                    _number(sim.get("grid_mm", SimulationSettings().grid_mm)))
        spread = _number(sim["spread_mm"])
        if 0.0 <= spread < least:   # NaN, negative and non-numbers stay refused
            data = {**data, "simulation": {**sim, "spread_mm": least}}
    return job_from_dict(data)


def _number(value: Any) -> float:
    """``value`` as a float, NaN when it is not a plain number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return math.nan
    return float(value)


def _angles_given(data: dict[str, Any]) -> dict[str, Any]:
    """A material section that gives ``fill_angle_deg`` and no ``fill_angle_mode`` asks for
    that angle: its mode is 'fixed' (the default, 'optimal', would ignore the angle)."""
    mats = data.get("materials")
    if not isinstance(mats, dict):
        return data
    fixed = {k: {**v, "fill_angle_mode": "fixed"} for k, v in mats.items()
             if isinstance(v, dict) and "fill_angle_deg" in v and "fill_angle_mode" not in v}
    return {**data, "materials": {**mats, **fixed}} if fixed else data


def to_dict(obj: Any) -> dict[str, Any]:
    """Nested plain data of a Job (or section); tuples become lists (TOML-ready)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = to_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def toml_string(text: str) -> str:
    """``text`` as a TOML basic string: backslash, quote and the control characters TOML
    forbids raw (U+0000-U+001F, U+007F) escaped, every other character as it is (JSON's
    escapes of characters beyond U+FFFF, surrogate pairs, are not TOML: a calibration's
    fragment for an output folder named with an emoji did not load)."""
    out = text.replace("\\", "\\\\").replace('"', '\\"')
    out = re.sub(r"[\x00-\x1f\x7f]", lambda m: f"\\u{ord(m.group()):04x}", out)
    return f'"{out}"'


def to_toml(job: Job) -> str:
    """The job as TOML text that :func:`load_job` reads back to an equal job."""
    lines: list[str] = []

    def fmt(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return toml_string(v)
        if isinstance(v, list):
            return "[" + ", ".join(fmt(x) for x in v) + "]"
        return repr(v)

    def emit(name: str, d: dict[str, Any]) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict)}
        if scalars:
            lines.append(f"[{name}]")
            lines.extend(f"{k} = {fmt(v)}" for k, v in scalars.items())
            lines.append("")
        for k, v in d.items():
            if isinstance(v, dict):
                emit(f"{name}.{k}", v)

    for section, d in to_dict(job).items():
        emit(section, d)
    return "\n".join(lines)


def _line_of(text: str, dotted: str) -> int | None:
    """1-based line where a dotted setting is written in TOML text (best effort)."""
    parts = re.sub(r"\[\d+\]", "", dotted).split(".")
    key = parts[-1]
    table = ".".join(parts[:-1])
    current = ""
    fallback = None
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        m = re.match(r"^\[\s*([A-Za-z0-9_.\s]+?)\s*\]", line)
        if m:
            current = re.sub(r"\s", "", m.group(1))
            if current == dotted:
                fallback = n
            continue
        m = re.match(r"^([A-Za-z0-9_.\"']+)\s*=", line)
        if m:
            k = m.group(1).strip("\"'")
            full = f"{current}.{k}" if current else k
            if full == f"{table}.{key}" if table else full == key:
                return n
            # an inline table: slicing = { layer_thickness_mm = -1 }
            if (table and full == table and "{" in line
                    and re.search(rf"[{{,]\s*{re.escape(key)}\s*=", line)):
                return n
    return fallback


def _setting_of(msg: str) -> str:
    """The dotted setting name a validation message starts with."""
    return re.split(r"[ :=]", msg.removeprefix("unknown setting "), maxsplit=1)[0]


def _located(exc: ConfigError, path: Path, line_of: Callable[[str], int | None]
             ) -> ConfigError:
    """``exc`` prefixed with ``path:line`` of the setting it names (``path`` alone when the
    line is unknown)."""
    msg = str(exc)
    line = line_of(_setting_of(msg))
    return ConfigError(f"{path}:{line}: {msg}" if line else f"{path}: {msg}")


def load_job(path: str | Path, *, stored: bool = False) -> Job:
    """Read a job from a TOML file (``.toml``) or a legacy control text file (other).
    ``stored``: a job icefab wrote (a build folder's or a cell's ``job.toml``), read as
    :func:`stored_job_from_dict` does.

    Raises ConfigError naming the file and line on any problem.
    """
    return load_named_job(path, stored=stored)[0]


def load_named_job(path: str | Path, *, stored: bool = False
                   ) -> tuple[Job, frozenset[str]]:
    """:func:`load_job`, and the dotted settings the file names explicitly: a TOML file's
    keys (a material's ``fill_angle_deg`` names its ``fill_angle_mode`` too: it asks for
    'fixed'), a legacy control file's entries. The job fills the others with defaults; a
    command reading a result file lays only the named ones over the job stored in it
    (:func:`icefab.stages.overlay_job`), so that a job file "names only what differs"."""
    path = Path(path)
    text = read_input_text(path, "job", ConfigError)
    if path.suffix.lower() != ".toml":
        return _read_legacy(path, text)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:   # arrays nested 50 000 deep (hunt P)
        raise ConfigError(f"{path}: not valid TOML: arrays or tables nested too deeply") \
            from None
    except ValueError as exc:   # an integer over Python's 4 300 digits (hunt P)
        raise ConfigError(f"{path}: not valid TOML: {exc}".split("; use sys.")[0]) from None
    try:
        job = (stored_job_from_dict if stored else job_from_dict)(data)
    except ConfigError as exc:
        raise _located(exc, path, lambda name: _line_of(text, name)) from None
    # Relative file names (meshes, valve calibration tables) are relative to the job
    # file, stored resolved: the job travels inside every result file and each later step
    # reads the table again, from wherever it runs (a tester's relative calibration_file
    # was read from the current folder: other valve programs from the same trajectories)
    def beside(f: str) -> str:
        return str((path.parent / f).resolve()) if f and not Path(f).is_absolute() else f

    files = tuple(beside(f) for f in job.parts.files)
    job = dataclasses.replace(job, parts=dataclasses.replace(job.parts, files=files))
    tables = {f"materials.{m}.calibration_file": beside(job.materials[m].calibration_file)
              for m in ("part", "scaffold") if job.materials[m].calibration_file}
    return (job.replace(**tables) if tables else job), frozenset(_flatten(_angles_given(data)))


# --------------------------------------------------------------------------- legacy file

# Keys recognised in the description text of a legacy control file (thesis Table 3-1, paper
# Table 1). Matching is by description rather than by position so both published layouts
# (and files with entries left out) are read.
_LEGACY_KEYS: list[tuple[str, str]] = [
    ("number of stl", "n_files"),
    ("file names", "files"),
    ("inexact", "inexact"),
    ("slicing option", "slicing_option"),
    ("scaffolding option", "scaffold_on"),
    ("tolerance", "tolerance"),
    ("path width", "path_width"),
    ("slice thickness", "thickness"),
    ("smooth", "smooth"),
    ("scaling vector", "scale"),
    ("rotation axis order", "rot_order"),
    ("rotation vector", "rotation"),
    ("translation vector", "translation"),
    ("part fraction", "part_fraction"),
    ("scaffolding subset", "scaffold_subset"),
    ("part copy vector", "copies"),
    ("scaffolding buffer", "buffer"),
    ("number of cpus", "cpus"),
    ("end effector", "ee"),
    ("water building frame", "water_frame"),
    ("scaffolding building frame", "scaffold_frame"),
    ("laser measurement frame", "laser_frame"),
]


def _is_legacy_value(token: str) -> bool:
    """A number, a translation keyword or a mesh file name; anything else starts the text."""
    if token in ("cent", "orig") or re.fullmatch(r"\S+\.(stl|ply|obj)", token, re.I):
        return True
    try:
        float(token)
    except ValueError:
        return False
    return True


def _legacy_split(line: str) -> tuple[list[str], str]:
    """Values (tokens before the first '[' or '(' token) and the description text."""
    tokens = line.split()
    values: list[str] = []
    i = 0
    while i < len(tokens) and _is_legacy_value(tokens[i]):
        values.append(tokens[i])
        i += 1
    rest = " ".join(tokens[i:])
    # Drop leading bracketed groups: units, data format, restrictions.
    desc = re.sub(r"^(\s*(\[[^\]]*\]|\([^)]*\)))+", "", rest).strip()
    return values, desc


def load_legacy_control(path: str | Path, text: str | None = None) -> Job:
    """Read the thesis' control-parameter text file (Table 3-1 / paper Table 1 layout).

    Each line is ``values [units] [format] (restrictions) description``; lines whose
    description is not recognised, and section headings in capitals, are errors and
    skipped respectively. Switch entries ``1/0 a b c`` turn a vector on or off.
    """
    return _read_legacy(Path(path), text)[0]


def _read_legacy(path: Path, text: str | None) -> tuple[Job, frozenset[str]]:
    """:func:`load_legacy_control`, and the dotted settings the file's entries set (a
    vector switched off sets nothing: :func:`load_named_job`)."""
    if text is None:
        text = read_input_text(path, "job", ConfigError, "control file")
    data: dict[str, dict[str, Any]] = {k: {} for k in
                                       ("parts", "slicing", "scaffold", "cell")}
    materials: dict[str, dict[str, Any]] = {"part": {}, "scaffold": {}}
    expect_files = 0
    n = 0

    def fail(msg: str) -> ConfigError:
        return ConfigError(f"{path}:{n}: {msg}")

    def nums(vals: list[str], count: int, what: str) -> list[float]:
        if len(vals) < count:
            raise fail(f"{what}: expected {count} number{'s' * (count > 1)}, got "
                       f"{' '.join(vals) or 'none'}")
        try:
            out = [float(v) for v in vals[:count]]
        except ValueError:
            raise fail(f"{what}: expected {count} number{'s' * (count > 1)}, got "
                       f"{' '.join(vals)}") from None
        if not all(math.isfinite(x) for x in out):
            raise fail(f"{what} = {' '.join(vals[:count])}: must be finite numbers")
        return out

    def whole(vals: list[str], count: int, what: str) -> list[int]:
        """Whole numbers (a float such as 1e400 or 2.5 is refused, not truncated)."""
        out = nums(vals, count, what)
        if any(x != int(x) or abs(x) > 2**31 for x in out):
            raise fail(f"{what} = {' '.join(vals[:count])}: must be whole numbers")
        return [int(x) for x in out]

    def switch(vals: list[str], what: str) -> bool:
        """A 1/0 switch (thesis Table 3-1); anything else, NaN included, is refused."""
        x = nums(vals, 1, what)[0]
        if x not in (0.0, 1.0):
            raise fail(f"{what} = {vals[0]}: must be 1 (on) or 0 (off)")
        return x == 1.0

    set_on: dict[str, int] = {}  # dotted setting -> line that set it, for range errors
    given_on: dict[str, int] = {}  # control entry -> line that gave it

    def settings_now() -> dict[str, Any]:
        flat = _flatten({**data, "materials": materials})
        return {k: repr(v) for k, v in flat.items()}

    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith(("#", "%")):
            continue
        if re.fullmatch(r"[A-Z][A-Z\s]+", line):
            continue  # section heading like "SLICING CONTROL"
        before = settings_now()
        values, desc = _legacy_split(line)
        low = desc.lower()
        found = [(pat, k) for pat, k in _LEGACY_KEYS if pat in low]
        if len(found) > 1:   # "smoothing tolerance" set the weld tolerance, unsaid
            raise fail(f"control entry {line!r} names several settings: "
                       f"{', '.join(repr(pat) for pat, _ in found)}")
        key = found[0][1] if found else None
        if key is None and expect_files > 0 and values:
            key = "files"
        if key is None:
            if re.fullmatch(r"\s*\[[A-Za-z_][\w.]*\]\s*", line):
                # a TOML job under another name ('job.txt', 'fl.json') was read as a legacy
                # control file: "unrecognised control entry '[flow]'" (a reviewer's)
                raise fail(f"{line.strip()!r} is a TOML table: a job in TOML must be "
                           "named '.toml' (any other name is read as a legacy control file)")
            raise fail(f"unrecognised control entry {line!r}")
        if key in given_on and key != "files":   # the last one won, unsaid
            raise fail(f"{desc.strip() or key!r} is given twice (line {given_on[key]} too)")
        given_on.setdefault(key, n)
        try:
            if key == "n_files":
                expect_files = whole(values, 1, "number of files")[0]
                if expect_files < 1:
                    raise fail(f"number of files = {expect_files}: must be >= 1")
            elif key == "files":
                if "n_files" not in given_on:
                    raise fail("mesh file names before the number of files")
                if len(values) > expect_files:
                    raise fail(f"{len(values)} mesh file name(s) where the number of files "
                               f"leaves {expect_files}")
                files = [str((path.parent / v).resolve()) for v in values]
                data["parts"]["files"] = data["parts"].get("files", []) + files
                expect_files -= len(values)
            elif key == "inexact":
                data["parts"]["inexact"] = switch(values, "inexact option")
            elif key == "slicing_option":
                opt = whole(values, 1, "slicing option")[0]
                if opt not in (1, 2, 3):
                    raise fail(f"slicing option = {opt}: must be 1, 2 or 3")
                if opt == 3:
                    data["slicing"]["mode"] = "2d"
                if opt == 1:
                    materials["part"]["fill_pattern"] = "none"
                    materials["scaffold"]["fill_pattern"] = "none"
            elif key == "scaffold_on":
                data["scaffold"]["enabled"] = switch(values, "scaffolding option")
            elif key == "tolerance":
                data["parts"]["weld_tolerance_mm"] = nums(values, 1, "tolerance")[0]
            elif key == "path_width":
                w = nums(values, 2, "path width")
                materials["part"]["path_width_mm"] = w[0]
                materials["scaffold"]["path_width_mm"] = w[1]
            elif key == "thickness":
                data["slicing"]["layer_thickness_mm"] = nums(values, 1, "slice thickness")[0]
            elif key == "smooth":
                data.setdefault("motion", {})["smooth_angle_deg"] = nums(values, 1,
                                                                         "smooth angle")[0]
            elif key == "scale":
                v = nums(values, 4, "scaling vector")
                if switch(values, "scaling vector on/off"):
                    data["parts"]["scale"] = v[1:]
            elif key == "rotation":
                v = nums(values, 4, "rotation vector")
                if switch(values, "rotation vector on/off"):
                    data["parts"]["rotation_deg"] = v[1:]
            elif key == "rot_order":
                v = nums(values, 3, "rotation axis order")
                if sorted(v) != [1.0, 2.0, 3.0]:
                    raise fail(f"rotation axis order = {values[:3]}: must be a permutation of "
                               "1 2 3")
                data["parts"]["rotation_order"] = [int(x) for x in v]
            elif key == "translation":
                if len(values) < 4:   # a word other than cent/orig ends the values
                    raise fail(f"translation vector: expected 4 entries (1/0, then Tx Ty Tz: "
                               f"each a number, cent or orig), got {' '.join(values)} before "
                               f"{desc.split()[0]!r}" if desc.split() else
                               f"translation vector: expected 4 entries, got "
                               f"{' '.join(values)}")
                if switch(values, "translation on/off"):
                    t: list[Any] = []
                    for v in values[1:4]:
                        if v in ("cent", "orig"):
                            t.append(v)
                        else:
                            t.append(nums([v], 1, "translation")[0])
                    data["parts"]["translation"] = t
                else:
                    data["parts"]["translation"] = ["orig", "orig", "orig"]
            elif key == "part_fraction":
                data["parts"]["part_fraction"] = nums(values, 2, "part fraction")
            elif key == "scaffold_subset":
                data["scaffold"]["subset"] = nums(values, 2, "scaffolding subset")
            elif key == "copies":
                data["parts"]["copies"] = whole(values, 3, "part copy vector")
            elif key == "buffer":
                data["scaffold"]["buffer_mm"] = nums(values, 1, "scaffolding buffer")[0]
            elif key == "cpus":
                data["cell"]["cpus"] = whole(values, 1, "number of CPUs")[0]
            elif key == "ee":
                data["cell"]["ee_origin_mm"] = nums(values, 2, "end-effector origin")
            elif key == "water_frame":
                materials["part"]["nozzle_offset_mm"] = nums(values, 2, "water frame")
            elif key == "scaffold_frame":
                materials["scaffold"]["nozzle_offset_mm"] = nums(values, 2, "scaffold frame")
            elif key == "laser_frame":
                data["cell"]["laser_offset_mm"] = nums(values, 2, "laser frame")
        except ConfigError as exc:
            if str(exc).startswith(f"{path}:"):
                raise
            raise fail(str(exc)) from None
        after = settings_now()
        set_on.update({k: n for k, v in after.items() if before.get(k) != v})
    if expect_files > 0:
        raise ConfigError(f"{path}: {expect_files} mesh file name(s) missing after the number "
                          "of files")
    data["materials"] = {k: v for k, v in materials.items() if v}
    data = {k: v for k, v in data.items() if v}
    try:
        return job_from_dict(data), frozenset(_flatten(data))
    except ConfigError as exc:
        raise _located(exc, path, lambda name: set_on.get(re.sub(r"\[\d+\]", "", name))
                       ) from None


def _flatten(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts as {dotted key: leaf value}."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out
