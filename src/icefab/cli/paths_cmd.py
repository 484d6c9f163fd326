"""``icefab paths MODEL...|STACK.npz [-c job.toml] -o OUT [--layers 10,50,100]``.

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
from typing import Sequence

import numpy as np

from icefab.cli.common import (ESTIMATE_WORDS, Progress, add_job_argument,
                               check_layers_before_slicing, command_inputs, file_job, hours,
                               job_from_args, layer_list, output_dir, parse_layers,
                               placed_model, warning_lines, write_warnings)
from icefab.core import DEPOSITING_ROLES, MATERIALS, ROLES, area_text
from icefab.report import plot_toolpaths
from icefab.resultfiles import LayerHead, packed_lengths

SHOW_WARNINGS = 5


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "paths", help="scaffold regions and deposition paths of every layer",
        description="Scaffold regions (thesis 3.3) and ordered boundary, fill, measurement "
                    "and travel paths of both materials (thesis 3.4-3.7). Input: a mesh "
                    "(STL, PLY, OBJ) or a stack.npz from 'icefab slice'. Writes "
                    "OUT/toolpaths.npz and OUT/paths.png.")
    p.add_argument("model", nargs="*", metavar="MODEL|STACK",
                   help="mesh file(s) (replace parts.files of the job), 'demo' (the "
                        "built-in mug) or one stack .npz (default: parts.files of the job)")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--layers", metavar="K,K,...", type=layer_list,
                   help="layer indices to draw in paths.png (default: four evenly spread)")
    p.set_defaults(func=run)


#: The summary's name of every (role, material) code pair, as ``role * len(MATERIALS) +
#: material``: "<material> <role>", travel moves of both tools as one.
_KEYS = np.array(["travel" if role == "travel" else f"{material} {role}"
                  for role in ROLES for material in MATERIALS], dtype=object)


class PathTally:
    """Counts and lengths of a build's paths by material and role, and the constant-speed
    estimate of every layer (:func:`icefab.paths.layer_estimate`), added layer by layer as
    the pool hands them back, from the arrays the workers packed them in: made while the
    workers plan the next layers, without a Toolpath (issue 17)."""

    def __init__(self, job) -> None:
        self.job = job
        self.counts: dict[str, int] = {}
        self.length: dict[str, float] = {}
        self.per_layer: list[float] = []
        #: continuous tours (icefab.paths.join_tours) by key: tours, the paths they join,
        #: mm of travel curves (included in ``length``)
        self.tours: dict[str, list[float]] = {}

    def add_packed(self, packed: dict[str, np.ndarray]) -> None:
        """One layer's paths as :func:`icefab.resultfiles.pack_paths` packed them."""
        from icefab.paths import packed_estimate

        lengths = packed_lengths(packed)
        key = _KEYS[packed["role"].astype(np.int64) * len(MATERIALS)
                    + packed["material"].astype(np.int64)]
        for k in sorted(set(key.tolist())):
            mask = key == k
            self.counts[k] = self.counts.get(k, 0) + int(mask.sum())
            # added one path after the other, as a running sum would (cumsum is sequential)
            self.length[k] = float(np.cumsum(np.concatenate(
                [[self.length.get(k, 0.0)], lengths[mask]]))[-1])
        if "point_off" in packed:
            self._add_tours(packed, key)
        self.per_layer.append(packed_estimate(packed, self.job, lengths))

    def _add_tours(self, packed: dict[str, np.ndarray], key: np.ndarray) -> None:
        off = np.asarray(packed["point_off"], dtype=bool)
        pts, start = packed["points"], packed["path_start"]
        owner = np.repeat(np.arange(len(start) - 1), np.diff(start))
        # a tour's travel curves never include a closed path's closing edge
        seg = np.zeros(len(pts))
        seg[:-1] = np.hypot(*np.diff(pts, axis=0).T)
        curve = np.bincount(owner[off], weights=seg[off], minlength=len(start) - 1)
        first = off & ~np.r_[False, off[:-1]]   # where a travel curve begins
        heads = start[:-1][start[:-1] < len(pts)]
        first[heads] = off[heads]               # a path's first point follows no other
        curves = np.bincount(owner[first], minlength=len(start) - 1)
        for k in sorted(set(key[curves > 0].tolist())):
            m = (key == k) & (curves > 0)
            t = self.tours.setdefault(k, [0, 0, 0.0])
            t[0] += int(m.sum())
            t[1] += int((curves[m] + 1).sum())
            t[2] += float(curve[m].sum())


def _empty_material_warnings(stack, tally: PathTally, job) -> list[str]:
    """A material with area and not one path, and a part edge strip left without paths on
    purpose (``initial_offset_mm`` beyond half the path width: the nominal area, against
    which the unfilled area is measured, excludes it). A tester's part at an initial
    offset of 50 mm got no path, with 'unfilled area: part 0 mm²' and no warning."""
    out = []
    for material in ("part", "scaffold"):
        mat = job.materials[material]
        area = sum((layer.part if material == "part" else layer.scaffold).area
                   for layer in stack.layers)
        paths = sum(tally.counts.get(f"{material} {role}", 0) for role in DEPOSITING_ROLES)
        if area > 0 and paths == 0:
            out.append(f"no {material} path in any layer: {area:.4g} mm^2 of {material} "
                       f"regions, none left inside materials.{material}.initial_offset_mm = "
                       f"{mat.initial_offset_mm:g} and the path width "
                       f"{mat.path_width_mm:g} mm")
    strip = job.materials.part.initial_offset_mm - job.materials.part.path_width_mm / 2.0
    if strip > 0:
        out.append(f"materials.part.initial_offset_mm = {job.materials.part.initial_offset_mm:g}"
                   f" leaves a {strip:.3g} mm strip inside every part contour without paths "
                   "(on purpose: it is not counted as unfilled area)")
    return out


def summary_lines(layers: Sequence[LayerHead], warnings: Sequence[str],
                  tally: PathTally) -> list[str]:
    """Counts by role and material, length, unfilled area and the time estimate."""
    per_layer_s = np.array(tally.per_layer, dtype=np.float64)
    lines = [f"layers: {len(layers)}"]
    for key in sorted(tally.counts):
        line = f"  {key}: {tally.counts[key]} paths, {tally.length[key] / 1000:.2f} m"
        if key in tally.tours:
            n, joined, curve = tally.tours[key]
            line += (f" ({n} of them continuous tours of {joined} paths, with "
                     f"{curve / 1000:.2f} m of travel curves, valve off)")
        lines.append(line)
    unf = np.array([lp.unfilled_mm2 for lp in layers]).reshape(-1, 2).sum(axis=0)
    lines.append(f"unfilled area: part {area_text(unf[0])} mm², scaffold "
                 f"{area_text(unf[1])} mm²")
    if len(per_layer_s):
        lines.append(f"constant-speed estimate: {hours(float(per_layer_s.sum()))} (layers "
                     f"{per_layer_s.min():.1f} .. {per_layer_s.max():.1f} s; "
                     f"{ESTIMATE_WORDS}; 'icefab plan' gives the build time)")
    lines += warning_lines(warnings, "paths")
    return lines


def _load_stack(args: argparse.Namespace, job):
    from icefab.slicing import load_stack, slice_mesh

    model = command_inputs(args.model, job, words=("demo",))
    first = Path(model[0])
    if len(model) == 1 and first.suffix.lower() == ".npz":
        stack = load_stack(first)
        # the stack decided its layers and parts: what the job file names of them must
        # agree (another part's job recorded its files beside this geometry), the rest of
        # what it names applies, and what it does not name stays the stack's
        stack = dataclasses.replace(stack, job=file_job(
            stack.job, args, f"{first}: the stack's layers", "icefab slice"))
        return stack, stack.job
    mesh, job = placed_model(model, job)
    check_layers_before_slicing(args.layers, mesh, job)
    return slice_mesh(mesh, job, progress=Progress("slicing")), job


def run(args: argparse.Namespace) -> int:
    from icefab.motion import check_packed_workspace
    from icefab.paths import iter_plan_paths_packed, paths_warnings
    from icefab.regions import add_scaffold
    from icefab.resultfiles import save_toolpath_layers, unpack_layer_paths
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
    # counts and estimate are taken on the way (the main process waits for the workers).
    # The layers stay as the workers packed them (the file's members); only the pictured
    # ones become Toolpaths (issue 17: 432 k of them took the bunny's main process 2.5 s)
    robot = get_robot(job)
    tally = PathTally(job)
    heads: list[LayerHead] = []
    packed_layers: list[dict[str, np.ndarray]] = []
    pictured = {}
    for k, packed in enumerate(iter_plan_paths_packed(stack, job,
                                                      progress=Progress("paths"))):
        index, z, unfilled, arrays, thickness, top_z = packed
        check_packed_workspace(index, arrays, job, robot)
        tally.add_packed(arrays)
        heads.append(LayerHead(index, z, unfilled, thickness, top_z))
        packed_layers.append(arrays)
        if k in ks:
            pictured[k] = unpack_layer_paths(packed)
    warnings = list(paths_warnings(stack, heads)) + _empty_material_warnings(stack, tally, job)
    t_paths = time.perf_counter() - t0 - t_scaf
    # OUT may hold the stack.npz this command read: output_dir leaves it there
    out = Path(args.out)
    with output_dir(out, "paths") as tmp, ThreadPoolExecutor(1) as pool:
        # the file is written (mostly zlib, which lets other threads run) while the
        # picture and the summary are made (issue 17)
        saving = pool.submit(save_toolpath_layers, tmp / "toolpaths.npz", job, warnings,
                             heads, packed_layers)
        plot_toolpaths(stack, pictured, ks, tmp / "paths.png")
        write_warnings(warnings, tmp, "paths")
        summary = summary_lines(heads, warnings, tally)
        saving.result()
    for line in summary:
        print(line)
    print(f"time: stack and scaffold {t_scaf:.2f} s, paths {t_paths:.2f} s")
    print(f"wrote {out / 'toolpaths.npz'} and {out / 'paths.png'} "
          f"(layers {', '.join(map(str, ks))})")
    return 0
