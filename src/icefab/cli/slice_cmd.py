"""``icefab slice MODEL [-c job.toml] -o OUT [--layers 10,50,100]``.

Loads and places the model(s) (``icefab.mesh``), slices them (``icefab.slicing``) and
writes ``OUT/stack.npz`` (format: ``icefab.slicing`` docstring) and ``OUT/layers.png``
(the chosen layers' contours: outer rings solid, holes dashed), then prints a summary.
Models given on the command line replace ``parts.files`` of the job.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from icefab.cli.common import (Progress, add_job_argument, check_layers_before_slicing,
                               command_inputs, job_from_args, layer_list, layer_thickness_text,
                               output_dir, parse_layers, placed_model, warning_lines,
                               write_warnings)
from icefab.report import plot_layers
from icefab.core import Stack



def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "slice", help="slice a model into layers of closed contours",
        description="Slice a mesh (STL, PLY, OBJ) into layers of nested, oriented contours "
                    "(thesis 3.2). Writes OUT/stack.npz and OUT/layers.png.")
    p.add_argument("model", nargs="*", metavar="MODEL",
                   help="mesh file(s) (replace parts.files of the job) or 'demo' (the "
                        "built-in mug; default: parts.files of the job)")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--layers", metavar="K,K,...", type=layer_list,
                   help="layer indices to draw in layers.png (default: six evenly spread)")
    p.set_defaults(func=run)


def summary_lines(stack: Stack, elapsed_s: float | None = None) -> list[str]:
    """A short human summary of a stack: layers, contours, area range, warnings."""
    areas = np.array([L.part.area for L in stack])
    n_rings = sum(len(L.part) for L in stack)
    n_pts = sum(L.part.n_points for L in stack)
    nonempty = areas[areas > 0]
    lines = [f"layers: {len(stack)} of {layer_thickness_text(stack)}, z = "
             f"{stack[0].z:.3f} .. {stack[len(stack) - 1].z:.3f} mm"
             if len(stack) else "layers: 0",
             f"contours: {n_rings} ({n_pts} points)"]
    if len(nonempty):
        lines.append(f"area: {nonempty.min():.2f} .. {nonempty.max():.2f} mm² "
                     f"(empty layers: {int((areas <= 0).sum())})")
    else:
        lines.append("area: every layer is empty")
    lines += warning_lines(stack.warnings, "slice")
    if elapsed_s is not None:
        lines.append(f"time: {elapsed_s:.2f} s")
    return lines


def run(args: argparse.Namespace) -> int:
    from icefab.slicing import save_stack, slice_mesh, slice_report

    job = job_from_args(args)
    model = command_inputs(args.model, job, words=("demo",))
    out = Path(args.out)
    t0 = time.perf_counter()
    mesh, job = placed_model(model, job)
    check_layers_before_slicing(args.layers, mesh, job)
    t_load = time.perf_counter() - t0
    stack = slice_mesh(mesh, job, progress=Progress("slicing"))
    elapsed = time.perf_counter() - t0
    ks = parse_layers(args.layers, len(stack), default_count=6)
    with output_dir(out, "slice") as tmp:
        save_stack(stack, tmp / "stack.npz")
        plot_layers(stack, ks, tmp / "layers.png")
        write_warnings(stack.warnings, tmp, "slice")
    stack_path, png = out / "stack.npz", out / "layers.png"
    print(f"{mesh.name or 'model'}: {len(mesh.faces)} facets, loaded and placed in "
          f"{t_load:.2f} s")
    for line in summary_lines(stack, elapsed):
        print(line)
    rep = slice_report(stack)
    if rep is not None and rep.uniform_layers:
        sl = stack.job.slicing
        print(f"adaptive layers: cusp height at most {rep.max_cusp_mm:.3g} mm (bound "
              f"{sl.cusp_height_mm:g} mm) in {len(stack)} layers; uniform layers thin enough "
              f"for the same bound: {rep.uniform_layers} ({rep.uniform_layers - len(stack)} "
              "more)")
    if rep is not None:
        print(f"linking: {rep.segments} segments, {rep.open_chains} open chains "
              f"({rep.gaps_closed} small and {rep.large_gaps_closed} large gaps closed, "
              f"{rep.chains_dropped} dropped), {rep.tolerance_matched_ends} ends matched by "
              f"tolerance, {len(rep.union_layers)} layers united; filter "
              f"{rep.points_before_filter} -> {rep.points_after_filter} points"
              # the united layers' contours are made after the filter: 'contours' above
              # counts their points (a teapot: 432 there, 446 here)
              + (" (before the unions)" if rep.union_layers else "")
              + f", {rep.rings_collapsed} collapsed contours dropped")
    print(f"wrote {stack_path} and {png} (layers {', '.join(map(str, ks))})")
    return 0
