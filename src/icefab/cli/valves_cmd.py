"""``icefab valves TRAJECTORIES -o OUT [-c job.toml] [--format bin|txt|both] [--layers K,K]
[--out-of-range error|clamp]``.

Variable-flow valve programs (thesis Ch. 6, 2.3.1) for every depositing trajectory of a
trajectory file written by ``icefab plan`` (``trajectories.npz``). Writes into OUT (which
appears only when everything worked):

* ``layer_KKKK/path_NNNN.bin`` (and/or ``.txt``): one program per path, in the binary or
  text form documented in :mod:`icefab.flow` (pulse instants as uint16 ticks of 2 ms,
  split into pieces at 131.072 s / 16 384 pulses);
* ``summary.txt``: paths, pulses, pieces and the number of limit findings per layer, then
  every kind of finding once with its count (:func:`icefab.flow.summarise_findings`); also
  printed.

A flow outside the calibration table (or, in PWM, beyond the valve fully open) stops the
command with an error naming the path, unless ``flow.out_of_range = "clamp"`` (or
``--out-of-range clamp``): then it is clamped and the findings say how much volume that
costs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from icefab.cli.common import Progress, add_job_argument, output_dir
from icefab.errors import ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "valves", help="valve pulse programs for the trajectories of a build",
        description="Make the variable-flow valve program of every depositing trajectory "
                    "(thesis Ch. 6): flow w * dh * speed, frequency from the calibration "
                    "table, pulse instants as uint16 ticks, split at the microcontroller's "
                    "limits. Writes OUT/layer_KKKK/path_NNNN.bin|txt and OUT/summary.txt.")
    p.add_argument("input", metavar="TRAJECTORIES",
                   help="trajectory file (trajectories.npz from 'icefab plan')")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--format", choices=("bin", "txt", "both"), default="bin",
                   help="file form of the programs (default bin)")
    p.add_argument("--layers", metavar="K,K,...", help="only these layers (default all)")
    p.add_argument("--out-of-range", choices=("error", "clamp"), default=None,
                   help="a flow beyond the calibration table: stop with an error, or clamp "
                        "it and report the volume lost (default: the job's "
                        "flow.out_of_range)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from icefab.config import load_job
    from icefab.flow import (n_pulses, plan_valves, program_pieces, summarise_findings,
                             write_valve_program)
    from icefab.motion import load_trajectories

    src = Path(args.input)
    if not src.exists():
        raise ConfigError(f"{src}: trajectory file not found")
    motion = load_trajectories(src)
    job = load_job(args.job) if args.job else motion.job
    if args.out_of_range:
        job = job.replace(**{"flow.out_of_range": args.out_of_range})
    layers = motion.layers
    if args.layers:
        try:
            wanted = {int(t) for t in args.layers.replace(" ", "").split(",") if t}
        except ValueError:
            raise ConfigError(f"--layers {args.layers!r}: expected comma-separated layer "
                              "numbers") from None
        known = {lm.index for lm in layers}
        if not wanted or not wanted <= known:
            raise ConfigError(f"--layers {args.layers!r}: layers must be among "
                              f"{min(known)}..{max(known)}" if known else
                              f"--layers {args.layers!r}: the file has no layers")
        layers = tuple(lm for lm in layers if lm.index in wanted)
    from icefab.headroom import check_feedback_headroom, feedback_headroom

    # the closed-loop build's needs, before any program is written (issue 11)
    headroom = check_feedback_headroom(feedback_headroom(
        ((lm.index, t) for lm in layers for t in lm.trajectories), job), job)
    fmts = ("bin", "txt") if args.format == "both" else (args.format,)
    progress = Progress("valves")
    lines = ["layer  paths  pulses  pieces  findings"]
    totals = [0, 0, 0, 0]
    found: list[tuple[int, str]] = []
    with output_dir(args.out, "valves") as tmp:
        for n, lm in enumerate(layers):
            folder = tmp / f"layer_{lm.index:04d}"
            paths = pulses = pieces = findings = 0
            for i, traj in enumerate(lm.trajectories):
                p = traj.path
                if p is not None and not p.depositing:
                    continue
                material = p.material if p is not None else "part"
                prog = plan_valves(traj, material, job)
                for f in fmts:
                    write_valve_program(prog, folder / f"path_{i:04d}.{f}", fmt=f)
                paths += 1
                pulses += n_pulses(prog)
                pieces += len(program_pieces(prog))
                findings += len(prog.warnings)
                found.extend((lm.index, w) for w in prog.warnings)
            lines.append(f"{lm.index:5d}  {paths:5d}  {pulses:6d}  {pieces:6d}  {findings:8d}")
            for k, v in enumerate((paths, pulses, pieces, findings)):
                totals[k] += v
            progress(n + 1, len(layers))
        lines.append(f"total  {totals[0]:5d}  {totals[1]:6d}  {totals[2]:6d}  {totals[3]:8d}")
        lines.append(f"mode {job.flow.mode}, tick {job.flow.tick_s * 1e3:g} ms, split at "
                     f"{job.flow.max_piece_s:g} s / {job.flow.max_pulses} pulses, "
                     f"flow.out_of_range = {job.flow.out_of_range!r}")
        lines.extend(headroom)
        if found:
            lines.append(f"findings ({len(found)}), one line per kind:")
            lines.extend(f"  {t}" for t in summarise_findings(found))
        (tmp / "summary.txt").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0
