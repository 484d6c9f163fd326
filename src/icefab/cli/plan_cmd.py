"""``icefab plan MODEL...|TOOLPATHS [-c job.toml] -o OUT [--layers K,K] [--no-jerk] [--gcode]
[--constant-spacing MM]``.

Minimum-time trajectories for every path of a build (thesis Ch. 4). The input is a mesh
(sliced, scaffolded and given paths with the job's settings) or a toolpath file written by
``icefab paths`` (``.npz``). ``--layers`` is checked as soon as the input is loaded. A
gantry (``[cell] robot = "gantry"``) with the default part origin builds at the centre of
its travel (``cell.ee_origin_mm``). Writes into OUT (which appears only when
everything worked; every file is written in a temporary folder first):

* ``trajectories.npz`` — every trajectory at constant dt (format: ``icefab.motion``
  docstring);
* ``speed_layer_K.png`` — per chosen layer, the trajectory samples coloured by speed
  (thesis Fig. 4-11: the speed lives in the point spacing);
* ``plan-summary.txt`` — build time with MTTS next to the thesis' constant-speed case (4.4:
  boundaries 25 mm/s, fill 125 mm/s) planned with the robot's accelerations
  (``icefab.motion.constant_speed_time``) and the idealised length / speed estimate
  (``icefab.paths.estimate_build_time``), points, paths and computing time; also printed;
* with ``--gcode``: ``trajectories.gcode`` — the whole Marlin program for a gantry, the
  same file as ``icefab export gcode`` writes (``icefab.export.save_gcode``, format in its
  docstring: ``G1 X Y F S`` per time step with the valve's PWM duty inline, ``T0``/``T1``
  material changes, ``G0`` travel with the valve closed); where it cannot play a path's
  valve program move by move, the summary's warnings say so;
* with ``--constant-spacing MM``: ``constant_spacing.npz`` — constant point spacing and
  variable duration (``icefab.motion.save_constant_spacing``, format in its docstring).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from icefab.cli.common import (ESTIMATE_WORDS, Progress, add_job_argument,
                               check_layers_before_slicing, command_inputs,
                               compare_build_times, file_job, hours, job_from_args,
                               output_dir, layer_list, parse_layers, placed_model)
from icefab.core import DEPOSITING_CODES
from icefab.errors import ConfigError
from icefab.report import plot_speed


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "plan", help="minimum-time trajectories for all paths of a build",
        description="Plan minimum-time trajectories (thesis Ch. 4: PATHSPLIT, VCON, ACON, "
                    "JCON, AREST) for every path of a model or toolpath file. Writes "
                    "OUT/trajectories.npz, OUT/speed_layer_K.png and OUT/plan-summary.txt; "
                    "with --gcode also OUT/trajectories.gcode, with --constant-spacing "
                    "OUT/constant_spacing.npz (formats: 'pydoc icefab.export' for the "
                    "G-code, its G1 moves in icefab.motion.gcode_moves; "
                    "icefab.motion.save_constant_spacing for the .npz).")
    p.add_argument("input", nargs="*", metavar="MODEL|TOOLPATHS",
                   help="mesh file(s) (STL, PLY, OBJ; replace parts.files of the job), "
                        "'demo' (the built-in mug) or one toolpath file (.npz from 'icefab "
                        "paths'; default: parts.files of the job)")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--layers", metavar="K,K,...", type=layer_list,
                   help="layers to draw speed pictures of (default: three evenly spread)")
    p.add_argument("--no-jerk", action="store_true",
                   help="switch the jerk bounds off (motion.jerk_limited = false)")
    p.add_argument("--gcode", action="store_true",
                   help="also write OUT/trajectories.gcode, the same file as 'icefab "
                        "export gcode': a whole Marlin program for a gantry (job "
                        "[cell] robot = \"gantry\"), G1 X Y F S per time step (F mm/min, "
                        "each move lasting one step; S the valve's PWM duty, 0 or at least "
                        "flow.min_pulse_ms a period), T0/T1 material changes, G0 travel with "
                        "the valve closed; the Marlin build it needs is in its header")
    p.add_argument("--constant-spacing", type=float, metavar="MM", default=None,
                   help="also write OUT/constant_spacing.npz: points every MM mm along each "
                        "trajectory with the duration from each point to the next")
    p.set_defaults(func=run)


def load_input(inputs: list[str], job, args: argparse.Namespace):
    """Toolpaths and the job to plan them with. From a toolpath file: the job it was made
    with, the settings a ``-c`` job file names laid over it (:func:`file_job`). From mesh
    files: sliced, scaffolded and laid with ``job`` (the ``-c`` job, or the default)."""
    from icefab.paths import plan_paths
    from icefab.resultfiles import load_packed_toolpaths
    src = Path(inputs[0])
    if len(inputs) == 1 and src.suffix.lower() == ".npz":
        if not src.exists():
            raise ConfigError(f"{src}: input file not found")
        # as its arrays: checked and sent to the workers so, no Toolpath made (issue 17)
        tp = load_packed_toolpaths(src)
        job = file_job(tp.job, args, f"{src}: the toolpaths", "icefab paths")
        if job.cell.robot != tp.job.cell.robot:
            # allowed (toolpaths are in the part's frame), but said: the job file names
            # another robot than the toolpaths were made for
            print(f"note: planning for the {job.cell.robot} of the job, its part origin "
                  f"cell.ee_origin_mm = {_mm(job.cell.ee_origin_mm)}; the toolpaths were made "
                  f"with a {tp.job.cell.robot} (cell.robot)", file=sys.stderr)
        return tp, job
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh
    mesh, job = placed_model(inputs, job)   # placement per the job (thesis 3.1.2)
    check_layers_before_slicing(args.layers, mesh, job)
    stack = slice_mesh(mesh, job, progress=Progress("slicing"))
    stack = add_scaffold(stack, job)
    return plan_paths(stack, job), job


def _mm(v) -> str:
    """A point, mm, as a job file writes it: ``[260, -100]``."""
    return "[" + ", ".join(f"{float(x):g}" for x in v) + "]"


def _hms(s: float) -> str:
    h, rem = divmod(int(round(s)), 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}"


def run(args: argparse.Namespace) -> int:
    from icefab.export import check_gcode_robot, gcode_job, save_gcode
    from icefab.headroom import stored_layer_headroom, tightest
    from icefab.motion import (TrajectoryFile, TrajectoryWriter, iter_plan_packed,
                               save_constant_spacing, total_path_length,
                               unpack_layer_motion)
    from icefab.paths import estimate_build_time
    from icefab.robots import get_robot
    from icefab.workload import check_samples

    spacing = getattr(args, "constant_spacing", None)
    if spacing is not None and not (math.isfinite(spacing) and spacing > 0.0):
        raise ConfigError(f"--constant-spacing {spacing:g}: expected a positive number of mm")
    given = job_from_args(args)
    if getattr(args, "gcode", False) and getattr(args, "job", None):
        gcode_job(given, "--gcode")   # before slicing a mesh (and again for its own job)
    inputs = command_inputs(args.input, given, words=("demo",))
    t0 = time.perf_counter()
    tp, job = load_input(inputs, given, args)
    ks = parse_layers(args.layers, len(tp.layers), default_count=3)  # before planning
    if spacing is not None:
        # the output is made in memory, from the whole build (a tester's 0.0001 mm asked
        # for billions of points and the machine ran out of memory)
        check_samples(total_path_length(tp), spacing, f"--constant-spacing {spacing:g}",
                      what="the build's constant-spacing output")
    if args.no_jerk:
        job = job.replace(**{"motion.jerk_limited": False})
    robot = get_robot(job)
    if getattr(args, "gcode", False):
        check_gcode_robot(robot.name, "--gcode", planning=True)
        gcode_job(job, "--gcode")   # before planning, not after it
    # what valves/simulate will refuse, from each layer as it passes
    check_room = job.feedback.enabled and job.flow.mode == "fm"
    with output_dir(args.out, "plan") as tmp:
        # the build streams into the file: a few layers' samples in memory (issue 17)
        t1 = time.perf_counter()
        pictured, room = {}, []
        n_traj = n_points = 0
        total = dep = const_acc = 0.0
        with TrajectoryWriter(tmp / "trajectories.npz", job, robot.name,
                              robot.joint_names) as out:
            # the trajectories go to the file as the workers packed them (no Trajectory
            # objects but the pictured layers'); the workers take each layer's feedback
            # headroom too (issue 17)
            for k, pl in enumerate(iter_plan_packed(
                    tp, job, progress=Progress("planning"),
                    per_layer=stored_layer_headroom if check_room else None)):
                lp, packed, arrays = pl.paths, pl.packed, pl.path_arrays
                out.add_packed(lp.index, lp.z, lp.thickness,
                               lp.paths if arrays is None else arrays, packed,
                               top_z=lp.top_z)
                const_acc += pl.const_s
                durations = packed["duration"]
                n_traj += len(durations)
                n_points += int(packed["traj_start"][-1])
                total += float(durations.sum())
                if arrays is None:
                    depositing = [p.depositing for p in lp.paths]
                else:
                    depositing = np.isin(arrays["role"], DEPOSITING_CODES).tolist()
                dep += sum(d for d, keep in zip(durations.tolist(), depositing) if keep)
                if check_room:
                    room = tightest(room + pl.extra)
                if k in ks:
                    pictured[k] = unpack_layer_motion(
                        lp if arrays is None else tp.layer_paths(k), packed)
        t_plan = time.perf_counter() - t1
        _, const = estimate_build_time(tp, job)
        lines = [
            f"layers: {len(tp.layers)}, trajectories: {n_traj}, samples: {n_points} "
            f"at dt = {job.motion.dt_s * 1000:g} ms ({robot.name}, jerk "
            f"{'on' if job.motion.jerk_limited else 'off'})",
            f"build motion time (MTTS): {total:.1f} s ({_hms(total)}), "
            f"depositing {dep:.1f} s",
            f"constant speed, planned:  {const_acc:.1f} s ({_hms(const_acc)}; boundary "
            f"{job.motion.boundary_speed_mm_s:g}, fill {job.motion.fill_speed_mm_s:g} mm/s with "
            f"the robot's accelerations, thesis 4.4)",
            compare_build_times(total, const_acc),
            f"constant-speed estimate:  {hours(const)} ({ESTIMATE_WORDS}; 'icefab paths' "
            f"prints it)",
            f"planning (MTTS and constant speed) and writing the trajectories: {t_plan:.2f} s "
            f"({n_points / max(t_plan, 1e-9) / 1e6:.2f} M samples/s), total "
            f"{time.perf_counter() - t0:.2f} s",
        ]
        # FM's limits are the valve stages' (valves, simulate, build); the G-code runs no
        # SMF and its PWM valve has limits of its own (its own findings), so say whose
        gc = (" (icefab valves, simulate and build: flow.mode = 'fm'; the G-code runs no "
              "SMF and drives the valve by PWM, whose limits its warnings give)"
              if getattr(args, "gcode", False) and job.flow.mode == "fm" else "")
        lines += [f"warning: {r.message(job)}{gc}" for r in room if not r.fits]
        vmax = job.motion.speed_mm_s
        for k in ks:
            plot_speed(pictured[k], tmp / f"speed_layer_{pictured[k].index}.png", vmax, job)
        extra = []
        if getattr(args, "gcode", False) or spacing is not None:
            with TrajectoryFile(tmp / "trajectories.npz") as motion:  # read back a block at a time
                if getattr(args, "gcode", False):
                    # before the summary is written: it says where the G-code cannot play
                    # a path's valve program move by move
                    found = save_gcode(motion, tmp / "trajectories.gcode")
                    lines += [f"warning: G-code: {line}" for line in found]
                    extra.append("trajectories.gcode")
                if spacing is not None:
                    save_constant_spacing(motion, spacing, tmp / "constant_spacing.npz")
                    extra.append("constant_spacing.npz")
        (tmp / "plan-summary.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    for line in lines:
        print(line)
    print(f"wrote {args.out}/trajectories.npz, plan-summary.txt"
          + "".join(f", {name}" for name in extra)
          + f" and speed pictures of layers "
          f"{', '.join(str(pictured[k].index) for k in ks)}")
    return 0
