"""``icefab export vplus [TRAJECTORIES] -o OUT`` and ``icefab export gcode TRAJECTORIES -o OUT``.

``vplus`` writes ``OUT/icefab_server.v2``: the V+ server for the Adept C40
(:mod:`icefab.cell.vplus`; untested on a controller) that receives each layer's
trajectories from the control PC over TCP and runs them at constant dt with the valve and
laser triggers. Given a ``trajectories.npz`` it checks that every path fits the
controller's path store and sizes the store for the longest path.

``gcode`` writes ``OUT/trajectories.gcode`` for a gantry running Marlin
(:mod:`icefab.export`, the convention in its docstring).

``ruled STACK -o OUT`` writes ``OUT/ruled.npz`` (layout: ``icefab.resultfiles.save_ruled``)
and ``OUT/ruled.png``: the ruled side surface of every layer for cells that tilt their
nozzle or trim the layer edge (:mod:`icefab.ruled`; planar cells ignore it).
"""

from __future__ import annotations

import argparse
import math
import sys

import numpy as np
from pathlib import Path

from icefab.cli.common import layer_list, output_dir
from icefab.errors import ConfigError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="programs for the cell's controllers (V+ for the C40, G-code, "
                  "ruled edges)",
        description="Write controller programs: 'vplus' the Adept C40's V+ server of the "
                    "robot link (untested on a controller), 'gcode' G-code for a gantry "
                    "running Marlin, 'ruled' the ruled layer edges for cells that tilt the "
                    "nozzle or trim the edge.")
    sub = p.add_subparsers(dest="what", metavar="WHAT")
    sub.required = True
    v = sub.add_parser("vplus", help="the V+ server program for the Adept C40",
                       description="Write OUT/icefab_server.v2, the V+ programs of the robot "
                                   "link (icefab.cell.vplus). UNTESTED ON A CONTROLLER.")
    v.add_argument("input", nargs="?", metavar="TRAJECTORIES",
                   help="trajectories.npz from 'icefab plan': checked to fit, sizes the "
                        "path store")
    v.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    v.add_argument("--port", type=int, default=7100, help="TCP port (default 7100)")
    v.add_argument("--valve-output", type=int, default=97,
                   help="digital output wired to the valve controller's trigger (97)")
    v.add_argument("--laser-output", type=int, default=98,
                   help="digital output wired to the laser controller's timing input (98)")
    # None: not given, written as 0 with a warning (the program drives a real robot)
    v.add_argument("--zbase", type=float, default=None, metavar="MM",
                   help="build platform height in the robot base frame, mm (teach it; "
                        "default 0, with a warning)")
    v.add_argument("--yaw", type=float, default=None, metavar="DEG",
                   help="fixed end-effector orientation, degrees (teach it; default 0, "
                        "with a warning)")
    v.add_argument("--max-paths", type=int, default=4,
                   help="paths the controller stores at once (default 4)")
    v.set_defaults(func=run_vplus)
    g = sub.add_parser("gcode", help="G-code for a gantry running Marlin (valve duty inline)",
                       description="Write OUT/trajectories.gcode from a trajectories.npz "
                                   "(icefab.export: Marlin cutter PWM drives the valve, T0/T1 "
                                   "material, G0 travel). Plan the trajectories for a gantry "
                                   "([cell] robot = 'gantry').")
    g.add_argument("input", metavar="TRAJECTORIES", help="trajectories.npz from 'icefab plan'")
    g.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    g.set_defaults(func=run_gcode)
    r = sub.add_parser("ruled", help="ruled layer edges for multi-axis cells",
                       description="Write OUT/ruled.npz and OUT/ruled.png: for every part "
                                   "contour point the matching point on the next layer's "
                                   "contour and the tilt of the straight edge between them "
                                   "(icefab.ruled, Zhang & Liou; the top layer's points, "
                                   "with no layer above, and ledges get none). The tilt is "
                                   "as exact as the "
                                   "contours: slice with a small "
                                   "slicing.max_filter_deviation_mm (the filter moves a "
                                   "contour by up to it, which tilts an edge by up to "
                                   "atan(2 x deviation / layer height)).")
    r.add_argument("input", metavar="STACK", help="stack.npz from 'icefab slice'")
    r.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    r.add_argument("--max-tilt", type=float, default=80.0, metavar="DEG",
                   help="edges flatter than this from vertical are ledges, not edges "
                        "(default 80)")
    r.add_argument("--layers", metavar="K,K,...", type=layer_list,
                   help="layers drawn in ruled.png (default: three evenly spread)")
    r.set_defaults(func=run_ruled)


def run_ruled(args: argparse.Namespace) -> int:
    from icefab.cli.common import Progress, parse_layers
    from icefab.report import plot_ruled
    from icefab.resultfiles import load_stack, save_ruled
    from icefab.ruled import ruled_edges

    if not (math.isfinite(args.max_tilt) and 0.0 < args.max_tilt < 90.0):
        raise ConfigError(f"--max-tilt {args.max_tilt}: expected a number of degrees between "
                          "0 and 90")
    stack = load_stack(args.input)
    if not len(stack):
        raise ConfigError(f"{args.input}: the stack has no layers")
    ks = parse_layers(args.layers, max(len(stack) - 1, 1), default_count=3)
    edges = ruled_edges(stack, args.max_tilt, progress=Progress("ruled edges"))
    sl = stack.job.slicing
    dev = sl.max_filter_deviation_mm if sl.min_point_spacing_mm > 0 else 0.0  # 0: no filter
    # the thinnest layer bounds it (adaptive layers: 0.08 mm, not the nominal 0.25 mm;
    # a tester's spot was told 21.8 deg where its thinnest layers allow 51)
    thinnest = float(stack.thicknesses.min())
    bound = math.degrees(math.atan(2.0 * dev / thinnest))
    with output_dir(args.out, "export-ruled") as tmp:
        save_ruled(edges, stack.job, tmp / "ruled.npz")
        plot_ruled(edges, stack, ks, tmp / "ruled.png")
    ok = edges.matched
    tilt = np.degrees(np.abs(edges.tilt[ok]))
    print(f"ruled edges: {int(ok.sum())} of {len(edges)} contour points have an edge to the "
          f"next layer ({int((~ok).sum())} without: top layer, ledges flatter than "
          f"{args.max_tilt:g} deg, contours that end)")
    if ok.any():
        print(f"tilt from vertical: median {np.median(tilt):.1f} deg, 95 % under "
              f"{np.percentile(tilt, 95):.1f} deg, largest {tilt.max():.1f} deg; contour filter "
              f"{dev:g} mm over layers {thinnest:.4g} mm thick at the thinnest: tilts "
              f"uncertain by up to {bound:.1f} deg")
    print(f"wrote {args.out}/ruled.npz and {args.out}/ruled.png (layers "
          f"{', '.join(map(str, ks))})")
    return 0


def run_gcode(args: argparse.Namespace) -> int:
    from icefab.export import check_gcode_robot, gcode_job, save_gcode
    from icefab.motion import load_trajectories

    src = Path(args.input)
    motion = load_trajectories(src)   # names a missing file, a folder, /dev/zero
    check_gcode_robot(motion.robot, str(src))
    gcode_job(motion.job, str(src))
    if not motion.layers:   # a file of no moves, exit 0 (hunt W); 'export ruled' refuses too
        raise ConfigError(f"{src}: holds no layers: no G-code to write")
    with output_dir(args.out, "export-gcode") as tmp:
        found = save_gcode(motion, tmp / "trajectories.gcode")
    n = len(motion.layers)
    print(f"wrote {args.out}/trajectories.gcode (Marlin, {n} layer{'s' if n != 1 else ''}, "
          f"{motion.duration:.1f} s of motion)")
    for line in found:   # one per kind of valve limit, as 'export vplus' warns: on stderr
        print(f"warning: {line}", file=sys.stderr)
    return 0


def run_vplus(args: argparse.Namespace) -> int:
    from icefab.cell.vplus import VplusSettings, vplus_program

    if not 1 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: expected 1..65535")
    for name in ("valve_output", "laser_output"):
        # V+ numbers outputs 1-512; 1001-1512 are inputs and 2001-2512 software signals,
        # which SIGNAL refuses at run time or which drive no wire (1001 was written)
        if not 1 <= getattr(args, name) <= 512:
            raise ConfigError(f"--{name.replace('_', '-')} {getattr(args, name)}: expected "
                              "a V+ digital output number, 1..512 (1001-1512 are inputs, "
                              "2001-2512 software signals; the C40's XDIO outputs are "
                              "97-104)")
    if args.valve_output == args.laser_output:
        raise ConfigError("--valve-output and --laser-output name the same output")
    # a height and an angle a Cobra can take (1e308 was written as a 309-digit REAL)
    untaught = [f"--{name}" for name in ("zbase", "yaw") if getattr(args, name) is None]
    for name, lim, unit in (("zbase", 1000.0, "mm"), ("yaw", 360.0, "degrees")):
        v = 0.0 if getattr(args, name) is None else getattr(args, name)
        setattr(args, name, v)
        if not (math.isfinite(v) and abs(v) <= lim):
            raise ConfigError(f"--{name} {v:g}: expected a number of {unit} within "
                              f"+-{lim:g}")
    if not 1 <= args.max_paths <= 64:
        raise ConfigError(f"--max-paths {args.max_paths}: expected 1..64")
    max_points = 8192
    summary = ""
    if args.input:
        from icefab.motion import load_trajectories

        src = Path(args.input)
        motion = load_trajectories(src)   # names a missing file, a folder, /dev/zero
        if motion.robot != "scara":   # the Adept C40's program moves a SCARA
            raise ConfigError(f"{src}: the V+ program is for the Cobra 600 (a SCARA), and "
                              f"these trajectories were planned for a {motion.robot}: plan "
                              "with [cell] robot = \"scara\", or use 'icefab export gcode'")
        longest = max((len(t.xy) for lm in motion.layers for t in lm.trajectories), default=0)
        max_points = max(1024, 1024 * math.ceil(longest / 1024))
        if max_points * args.max_paths > 1_000_000:
            raise ConfigError(f"{src}: the longest path has {longest} points; "
                              f"{args.max_paths} of them ({max_points * args.max_paths} "
                              "points) do not fit the controller's arrays (1 000 000); plan "
                              "shorter paths or lower --max-paths")
        summary = (f" for {src.name}: longest path {longest} points, path store "
                   f"{args.max_paths} x {max_points} points")
    text = vplus_program(VplusSettings(port=args.port, valve_output=args.valve_output,
                                       laser_output=args.laser_output, zbase_mm=args.zbase,
                                       yaw_deg=args.yaw, max_points=max_points,
                                       max_paths=args.max_paths))
    with output_dir(args.out, "export-vplus") as tmp:
        (tmp / "icefab_server.v2").write_text(text, encoding="ascii", newline="\r\n")
    print(f"wrote {args.out}/icefab_server.v2 (V+, untested on a controller){summary}")
    if untaught:   # a docs hunt's: 0 was written silently for a program meant for a robot
        units = {"--zbase": "ice.zbase = 0 mm (platform height)",
                 "--yaw": "ice.yaw = 0 deg (end-effector orientation)"}
        print(f"warning: {' and '.join(untaught)} not given: the program sets "
              f"{' and '.join(units[n] for n in untaught)}; teach "
              f"{'them' if len(untaught) > 1 else 'it'} on the cell and export again",
              file=sys.stderr)
    return 0
