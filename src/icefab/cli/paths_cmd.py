"""``icefab paths MODEL|STACK.npz [-c job.toml] -o OUT [--layers 10,50,100]``.

From a mesh (loaded, placed and sliced) or a saved stack (``icefab slice``), adds the
scaffold regions if the stack has none (``icefab.regions``), plans the paths of every
layer (``icefab.paths``) and writes ``OUT/toolpaths.npz`` (format:
``icefab.paths.save_toolpaths``) and ``OUT/paths.png`` (the chosen layers: part and
scaffold regions filled in distinct colours, boundaries solid, fill thin, travel dashed,
measurement paths dotted). Prints a summary with the constant-speed time estimate.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from icefab.cli.common import (ESTIMATE_WORDS, Progress, add_job_argument, hours,
                               job_from_args, output_dir, parse_layers, warning_lines,
                               write_warnings)
from icefab.report import plot_toolpaths
from icefab.core import LayerPaths, Toolpaths, path_lengths

SHOW_WARNINGS = 5


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "paths", help="scaffold regions and deposition paths of every layer",
        description="Scaffold regions (thesis 3.3) and ordered boundary, fill, measurement "
                    "and travel paths of both materials (thesis 3.4-3.7). Input: a mesh "
                    "(STL, PLY, OBJ) or a stack.npz from 'icefab slice'. Writes "
                    "OUT/toolpaths.npz and OUT/paths.png.")
    p.add_argument("model", nargs="+", metavar="MODEL|STACK",
                   help="mesh file(s) (replace parts.files of the job) or one stack .npz")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--layers", metavar="K,K,...",
                   help="layer indices to draw in paths.png (default: four evenly spread)")
    p.set_defaults(func=run)


class PathTally:
    """Counts and lengths of a build's paths by material and role, and the constant-speed
    estimate of every layer (:func:`icefab.paths.layer_estimate`), added layer by layer as
    the pool hands them back: one pass over each layer's paths, made while the workers plan
    the next ones (issue 17)."""

    def __init__(self, job) -> None:
        self.job = job
        self.counts: dict[str, int] = {}
        self.length: dict[str, float] = {}
        self.per_layer: list[float] = []

    def add(self, lp: LayerPaths) -> None:
        from icefab.paths import layer_estimate

        lengths = path_lengths(lp.paths)
        for p, mm in zip(lp.paths, lengths.tolist()):
            key = f"{p.material} {p.role}" if p.role != "travel" else "travel"
            self.counts[key] = self.counts.get(key, 0) + 1
            self.length[key] = self.length.get(key, 0.0) + mm
        self.per_layer.append(layer_estimate(lp, self.job, lengths))


def summary_lines(toolpaths: Toolpaths, tally: PathTally) -> list[str]:
    """Counts by role and material, length, unfilled area and the time estimate."""
    per_layer_s = np.array(tally.per_layer, dtype=np.float64)
    lines = [f"layers: {len(toolpaths)}"]
    for key in sorted(tally.counts):
        lines.append(f"  {key}: {tally.counts[key]} paths, {tally.length[key] / 1000:.2f} m")
    unf = np.array([lp.unfilled_mm2 for lp in toolpaths]).reshape(-1, 2).sum(axis=0)
    lines.append(f"unfilled area: part {unf[0]:.0f} mm², scaffold {unf[1]:.0f} mm²")
    if len(per_layer_s):
        lines.append(f"constant-speed estimate: {hours(float(per_layer_s.sum()))} (layers "
                     f"{per_layer_s.min():.1f} .. {per_layer_s.max():.1f} s; "
                     f"{ESTIMATE_WORDS}; 'icefab plan' gives the build time)")
    ws = toolpaths.warnings
    lines += warning_lines(ws, "paths")
    return lines


def _load_stack(args: argparse.Namespace, job):
    from icefab import mesh as meshmod
    from icefab.slicing import load_stack, slice_mesh

    first = Path(args.model[0])
    if len(args.model) == 1 and first.suffix.lower() == ".npz":
        stack = load_stack(first)
        if args.job:
            stack = dataclasses.replace(stack, job=job)
        return stack, stack.job
    files = tuple(str(Path(m).resolve()) for m in args.model)
    job = dataclasses.replace(job, parts=dataclasses.replace(job.parts, files=files))
    mesh = meshmod.prepare_parts(job)
    return slice_mesh(mesh, job, progress=Progress("slicing")), job


def run(args: argparse.Namespace) -> int:
    from icefab.motion import check_layer_workspace
    from icefab.paths import (collect_toolpaths, iter_plan_paths_packed, save_toolpaths,
                              unpack_layer_paths)
    from icefab.regions import add_scaffold
    from icefab.robots import get_robot

    job = job_from_args(args)
    t0 = time.perf_counter()
    stack, job = _load_stack(args, job)
    ks = parse_layers(args.layers, len(stack))
    if not any(not layer.scaffold.is_empty for layer in stack):
        stack = add_scaffold(stack, job, progress=Progress("scaffold"))
    t_scaf = time.perf_counter() - t0
    # each layer's reach is checked as it comes, before any file is written (issue 11):
    # an unreachable part stops the planning at its first bad layer; the summary's
    # counts and estimate are taken on the way (the main process waits for the workers)
    robot = get_robot(job)
    tally = PathTally(job)
    packed_layers = []   # as the workers packed them: the file's members (issue 17)

    def checked(packed: tuple) -> LayerPaths:
        lp = unpack_layer_paths(packed)
        check_layer_workspace(lp, job, robot)
        tally.add(lp)
        packed_layers.append(packed[3])
        return lp
    toolpaths = collect_toolpaths(stack, job, map(checked, iter_plan_paths_packed(
        stack, job, progress=Progress("paths"))))
    t_paths = time.perf_counter() - t0 - t_scaf
    # OUT may hold the stack.npz this command read: output_dir leaves it there
    out = Path(args.out)
    with output_dir(out, "paths") as tmp, ThreadPoolExecutor(1) as pool:
        # the file is written (mostly zlib, which lets other threads run) while the
        # picture and the summary are made (issue 17)
        saving = pool.submit(save_toolpaths, toolpaths, tmp / "toolpaths.npz",
                             packed_layers)
        plot_toolpaths(stack, toolpaths, ks, tmp / "paths.png")
        write_warnings(toolpaths.warnings, tmp, "paths")
        summary = summary_lines(toolpaths, tally)
        saving.result()
    for line in summary:
        print(line)
    print(f"time: stack and scaffold {t_scaf:.2f} s, paths {t_paths:.2f} s")
    print(f"wrote {out / 'toolpaths.npz'} and {out / 'paths.png'} "
          f"(layers {', '.join(map(str, ks))})")
    return 0
