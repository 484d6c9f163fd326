"""``icefab valves TRAJECTORIES -o OUT [-c job.toml] [--format bin|txt|both] [--layers K,K]
[--out-of-range error|clamp]``.

Variable-flow valve programs (thesis Ch. 6, 2.3.1) for every depositing trajectory of a
trajectory file written by ``icefab plan`` (``trajectories.npz``). Writes into OUT (which
appears only when everything worked):

* ``valves/layer_KKKK.bin`` (and/or ``.txt``): one file per layer holding every program of
  the layer in build order, the form a controller link streams (:mod:`icefab.flow`, "Layer
  files"; each program keeps the per-program binary layout, pulse instants as uint16
  ticks of 2 ms, split into pieces at 131.071 s / 16 384 pulses: the last tick a uint16
  holds, 65 535, within the firmware's 131.072 s);
* ``valves-paths.csv``: one row per path (length, duration, pulses, pieces, drop
  spacing, the length deposited with fewer drops than ``flow.min_drops_per_mm``, findings);
* ``valves-summary.txt``: the summary printed (one screen: totals, every kind of finding
  once with its count, what it costs in volume and whether it matters), then the
  per-layer table.

A flow outside the calibration table (or, in PWM, beyond the valve fully open) stops the
command with an error naming the path, unless ``flow.out_of_range = "clamp"`` (or
``--out-of-range clamp``): then it is clamped and the findings say how much volume that
costs. A path whose nominal flow fits but whose flow with SMF's full correction
(``feedback.saturation``) does not is named in the summary: in a closed-loop build the
valve saturates the correction there (thesis 5.2.2).
"""

from __future__ import annotations

import argparse
import csv
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from icefab.cli.common import (Progress, add_job_argument, layer_list, layer_numbers,
                               output_dir)
from icefab.core import arc_lengths
from icefab.errors import ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "valves", help="valve pulse programs for the trajectories of a build",
        description="Make the variable-flow valve program of every depositing trajectory "
                    "(thesis Ch. 6): flow w * dh * speed, frequency from the calibration "
                    "table, pulse instants as uint16 ticks, split at the microcontroller's "
                    "limits. Writes OUT/valves/layer_KKKK.bin|txt (every program of a "
                    "layer in one file), OUT/valves-paths.csv and OUT/valves-summary.txt.")
    p.add_argument("input", metavar="TRAJECTORIES",
                   help="trajectory file (trajectories.npz from 'icefab plan')")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--format", choices=("bin", "txt", "both"), default="bin",
                   help="file form of the layer files (default bin; both: one of each per "
                        "layer)")
    p.add_argument("--layers", metavar="K,K,...", type=layer_list,
                   help="only these layers (default all)")
    p.add_argument("--out-of-range", choices=("error", "clamp"), default=None,
                   help="a flow beyond the calibration table: stop with an error, or clamp "
                        "it and report the volume lost (default: the job's "
                        "flow.out_of_range)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from icefab.motion import TrajectoryFile

    src = Path(args.input)
    if not src.exists():
        raise ConfigError(f"{src}: trajectory file not found")
    with TrajectoryFile(src) as motion:  # its samples are read a block at a time
        return _run(args, motion)


def _run(args: argparse.Namespace, motion) -> int:
    from icefab.cli.common import file_job
    from icefab.headroom import headroom_findings, tightest
    from icefab.parallel import parallel_imap
    from icefab.workload import check_pulse_durations

    # the volume per mm is width x layer thickness: a job file naming others than the
    # file's lays another build along these paths (a tester's bunny: 0.5 mm layers, twice
    # the water); what it does not name stays the file's (a flow-only job was refused)
    job = file_job(motion.job, args, f"{motion.path}: the trajectories",
                   "icefab paths, then icefab plan")
    if args.out_of_range:
        job = job.replace(**{"flow.out_of_range": args.out_of_range})
    known = {int(k) for k in motion.layer_index}
    wanted = None
    if args.layers:   # its syntax checked as the options were read (layer_list)
        wanted = set(layer_numbers(args.layers))
        if not wanted or not wanted <= known:
            raise ConfigError(f"--layers {args.layers!r}: layers must be among "
                              f"{min(known)}..{max(known)}" if known else
                              f"--layers {args.layers!r}: the file has no layers")
    chosen = np.isin(motion.layer_index, list(wanted if wanted else known))
    check_pulse_durations(motion.durations[np.repeat(chosen, np.diff(motion.layer_start))
                                           & motion.depositing()], job)
    n_layers = int(chosen.sum())
    rooms: list = []
    fmts = ("bin", "txt") if args.format == "both" else (args.format,)
    progress = Progress("valves")
    table = ["layer  paths  pulses  pieces  findings"]
    totals = dict(paths=0, pulses=0, pieces=0, findings=0, length=0.0, sparse=0.0)
    sparse_paths = 0
    max_gap = max_gap_width = 0.0
    found: list[tuple[int, str]] = []
    volume = _Volume()
    done = 0
    with output_dir(args.out, "valves") as tmp, \
            open(tmp / "valves-paths.csv", "w", newline="", encoding="utf-8") as fh:
        folder = tmp / "valves"
        folder.mkdir()
        csv.writer(fh).writerow(PATH_COLUMNS)
        # the file's blocks are shared out to the workers, which read them, make and write
        # their layers' programs and hand back what the summary needs (issue 17: one core
        # did it all); their results are taken in build order
        items = [(str(motion.path), k, wanted, job, fmts, str(folder))
                 for k in motion.blocks(wanted)]
        own = (os.getpid(), str(motion.path))
        _OPEN[own] = motion   # a serial run reads the command's own file
        try:
            for block in parallel_imap(_block_valves, items, job, chunk_items=1):
                for lv in block:
                    # the closed-loop build's needs (issue 11): the tightest path of
                    # each material so far
                    rooms = tightest(rooms + lv.rooms)
                    fh.write(lv.rows)
                    for length, sparse, gap, width, material, commanded, laid in lv.paths:
                        volume.add(material, commanded, laid)
                        totals["length"] += length
                        totals["sparse"] += sparse
                        if sparse > 0:
                            sparse_paths += 1
                        if gap - width > max_gap - max_gap_width:
                            max_gap, max_gap_width = gap, width
                    found.extend((lv.index, w) for w in lv.found)
                    table.append(f"{lv.index:5d}  {lv.counts[0]:5d}  {lv.counts[1]:6d}  "
                                 f"{lv.counts[2]:6d}  {lv.counts[3]:8d}")
                    for k, key in enumerate(("paths", "pulses", "pieces", "findings")):
                        totals[key] += lv.counts[k]
                    done += 1
                    progress(done, n_layers)
        finally:
            _OPEN.pop(own, None)
        lines = _summary(args.out, n_layers, fmts, totals, sparse_paths, max_gap,
                         max_gap_width, found, job, volume)
        # the closed-loop build's needs (issue 11), before findings
        lines[2:2] = headroom_findings(rooms, job)
        (tmp / "valves-summary.txt").write_text(
            "\n".join(lines + ["", "per layer:"] + table) + "\n", encoding="utf-8")
    print("\n".join(lines))
    return 0


class _LayerValves(NamedTuple):
    """What the summary needs of one layer's valve programs (:func:`_block_valves`)."""

    index: int
    rooms: list            # the layer's feedback headroom (icefab.headroom)
    rows: str              # its valves-paths.csv rows
    counts: tuple          # paths, pulses, pieces, findings
    paths: list            # per path: length, sparse length, largest drop gap, width (mm),
    #                        material, volume commanded and laid (mm^3)
    found: list            # its findings' texts


#: Trajectory files open for :func:`_block_valves`, by (process, path): a worker opens its
#: own once and reads several blocks; a serial run reads the command's own (a file object
#: inherited through a fork would share its offset with the parent's).
_OPEN: dict = {}


def _block_valves(args: tuple) -> list[_LayerValves]:
    """Worker: the valve programs of the layers of one block of a trajectory file (those
    in ``wanted``) with each layer's feedback headroom (issue 11), written as layer files
    into ``folder``; returns what the summary needs of each. args: (trajectory file, block,
    wanted layer indices or None, Job, formats, folder)."""
    import io

    from icefab.flow import (n_pulses, plan_build_valves, program_pieces, trajectory_width,
                             write_valve_layer)
    from icefab.headroom import layer_headroom
    from icefab.motion import TrajectoryFile

    src, k, wanted, job, fmts, folder = args
    key = (os.getpid(), src)
    motion = _OPEN.get(key)
    if motion is None:
        motion = _OPEN[key] = TrajectoryFile(src)   # closed when the worker ends
    out = []
    for lm in motion.iter_block(k, wanted):
        rooms = layer_headroom(lm, job)
        (programs,) = plan_build_valves([lm], job)
        spacing = _drop_spacings([lm.trajectories[lp.path] for lp in programs],
                                 [lp.program for lp in programs], job.flow.min_drops_per_mm)
        text = io.StringIO()
        rows = csv.writer(text)
        counts = [0, 0, 0, 0]
        per_path, found = [], []
        for lp, (length, gap, sparse) in zip(programs, spacing):
            material, prog = lp.material, lp.program
            traj = lm.trajectories[lp.path]
            p = traj.path
            width = trajectory_width(traj, material, job)
            pulses, pieces = n_pulses(prog), len(program_pieces(prog))
            rows.writerow([lm.index, lp.path, material, p.role if p is not None else "",
                           f"{length:.3f}", f"{traj.duration:.3f}", pulses, pieces,
                           f"{width:.3f}", f"{gap:.3f}", f"{sparse:.3f}",
                           len(prog.warnings), " | ".join(prog.warnings)])
            for c, v in enumerate((1, pulses, pieces, len(prog.warnings))):
                counts[c] += v
            per_path.append((length, sparse, gap, width, material, prog.commanded_mm3,
                             prog.laid_mm3))
            found.extend(prog.warnings)
        for f in fmts:
            write_valve_layer(lm.index, programs, Path(folder) / f"layer_{lm.index:04d}.{f}",
                              fmt=f)
        out.append(_LayerValves(int(lm.index), rooms, text.getvalue(), tuple(counts),
                                per_path, found))
    return out


#: Columns of valves-paths.csv (lengths mm, times s).
PATH_COLUMNS = ["layer", "path", "material", "role", "length_mm", "duration_s", "pulses",
                "pieces", "width_mm", "largest_drop_spacing_mm", "sparse_length_mm",
                "findings", "finding_texts"]


def _drop_spacings(trajs, progs, min_drops_per_mm: float) -> list[tuple[float, float, float]]:
    """:func:`_drop_spacing` of many paths (a layer's) in a few array operations: each
    path's samples and pulses are shifted to lie after the previous path's, so one
    interpolation places them all; a continuous tour's pulses are counted by the span its
    valve is on that holds them (the values agree with the per-path function to float
    rounding). Issue 17: once per path it took 17 s of the bunny's valves."""
    from icefab.flow import pulse_times

    if not trajs:
        return []
    n = np.array([len(t.xy) for t in trajs], dtype=np.int64)
    if np.any(n < 2):  # the rare bare point: path by path
        return [_drop_spacing(t, p, min_drops_per_mm) for t, p in zip(trajs, progs)]
    xy = np.concatenate([np.asarray(t.xy, np.float64) for t in trajs])
    first = np.concatenate([[0], np.cumsum(n)[:-1]])
    step = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    step[first[1:] - 1] = 0.0                                  # between two paths
    s = np.concatenate([[0.0], np.cumsum(step)])
    s0 = s[first]
    length = s[first + n - 1] - s0
    dt = np.array([float(t.dt) for t in trajs])
    local = (np.arange(len(xy)) - np.repeat(first, n)).astype(np.float64)
    span = (n - 1) * dt + 1.0                                    # each path's time, and a gap
    shift = np.concatenate([[0.0], np.cumsum(span)[:-1]])
    t = local * np.repeat(dt, n) + np.repeat(shift, n)
    pulses = [pulse_times(p) for p in progs]
    n_p = np.array([len(a) for a in pulses], dtype=np.int64)
    p_owner = np.repeat(np.arange(len(trajs)), n_p)
    p_t = np.concatenate(pulses) + shift[p_owner]
    at = np.interp(p_t, t, s) - s0[p_owner]
    # the stretches drops are spaced over: whole paths, and each span a tour's valve is on
    # (by the global times of the spans' starts; a pulse outside every span belongs to none)
    unit = p_owner.copy()
    u_len, u_owner = length.copy(), np.arange(len(trajs))
    tours = [k for k, tr in enumerate(trajs) if tr.on_spans is not None]
    if tours:
        spans = [np.asarray(trajs[k].on_spans, np.float64).reshape(-1, 2) for k in tours]
        s_owner = np.repeat(tours, [len(x) for x in spans])
        g = np.concatenate(spans) + shift[s_owner][:, None]        # global times
        ends = np.interp(g.ravel(), t, s).reshape(-1, 2)
        in_tour = np.isin(p_owner, tours)
        j = np.searchsorted(g[:, 0], p_t[in_tour] + 1e-12, side="right") - 1
        jc = np.maximum(j, 0)
        held = (j >= 0) & (s_owner[jc] == p_owner[in_tour]) & (p_t[in_tour] <= g[jc, 1] + 1e-12)
        unit[in_tour] = np.where(held, len(trajs) + jc, -1)
        u_len[tours] = 0.0                                           # a tour is its spans
        u_len = np.concatenate([u_len, ends[:, 1] - ends[:, 0]])
        u_owner = np.concatenate([u_owner, s_owner])
        keep = unit >= 0
        unit, at = unit[keep], at[keep]
    limit = 1.0 / min_drops_per_mm if min_drops_per_mm > 0 else np.inf
    gaps = np.diff(at) if len(at) else np.zeros(0)
    inside = unit[1:] == unit[:-1] if len(at) else np.zeros(0, dtype=bool)
    g_unit = unit[1:] if len(at) else np.zeros(0, np.int64)
    gw = np.where(inside, gaps, 0.0)
    widest = np.zeros(len(u_len))
    np.maximum.at(widest, g_unit, gw)
    sparse = np.zeros(len(u_len))
    np.add.at(sparse, g_unit, np.where(inside & (gw > limit), gw, 0.0))
    few = np.bincount(unit, minlength=len(u_len)) < 2   # one drop (or none) for a stretch
    few[tours] = False                                  # (a tour: its spans are the stretches)
    widest[few] = u_len[few]
    sparse[few] = np.where(u_len[few] > limit, u_len[few], 0.0)
    tot_len = np.bincount(u_owner, weights=u_len, minlength=len(trajs))
    tot_sparse = np.bincount(u_owner, weights=sparse, minlength=len(trajs))
    tot_widest = np.zeros(len(trajs))
    np.maximum.at(tot_widest, u_owner, widest)
    return [(float(a), float(b), float(c)) for a, b, c in zip(tot_len, tot_widest,
                                                               tot_sparse)]


def _drop_spacing(traj, prog, min_drops_per_mm: float) -> tuple[float, float, float]:
    """Deposited length, largest distance between consecutive drops, and the length over
    which drops are farther apart than ``1 / min_drops_per_mm`` (mm), from the program's
    pulse instants placed on the trajectory (what the valve will do, not the planned
    frequency). A continuous tour counts each of its paths apart (:func:`icefab.flow.
    on_times`): its travel deposits nothing, and no drop spacing spans it."""
    from icefab.flow import on_times, positions_at, pulse_times

    xy = np.asarray(traj.xy, dtype=np.float64)
    if len(xy) < 2:
        return 0.0, 0.0, 0.0
    limit = 1.0 / min_drops_per_mm if min_drops_per_mm > 0 else np.inf
    p_t = pulse_times(prog)
    total, widest, sparse = 0.0, 0.0, 0.0
    for ts in on_times(traj):
        pts = positions_at(xy, float(traj.dt), ts)
        s = arc_lengths(np.linalg.norm(np.diff(pts, axis=0), axis=1))
        at = np.interp(p_t[(p_t >= ts[0] - 1e-12) & (p_t <= ts[-1] + 1e-12)], ts, s)
        length = float(s[-1])
        total += length
        if len(at) < 2:  # one drop (or none) for the whole stretch
            widest = max(widest, length)
            sparse += length if length > limit else 0.0
            continue
        gaps = np.diff(at)
        widest = max(widest, float(gaps.max()))
        sparse += float(gaps[gaps > limit].sum())
    return total, widest, sparse


class _Volume:
    """The volume the paths' flow commands and the volume their pulses lay, per material,
    and the paths that get no pulse at all though they have a volume to lay (2 566 of a
    tester's thin rocker's 4 258 paths got none, -7 %, under "volume cost: none").
    Every other path lays its volume within half a pulse (eq. 6.6 rounds its count)."""

    def __init__(self) -> None:
        self.commanded: dict[str, float] = {}
        self.laid: dict[str, float] = {}
        self.none = 0

    def add(self, material: str, commanded: float, laid: float) -> None:
        if not (np.isfinite(commanded) and np.isfinite(laid)):
            return
        self.commanded[material] = self.commanded.get(material, 0.0) + commanded
        self.laid[material] = self.laid.get(material, 0.0) + laid
        self.none += commanded > 0.0 and laid <= 0.0

    def text(self) -> str:
        """'the pulses lay D of C mm^3 commanded (x %); part ..., scaffold ...; K paths ...'"""
        def said(d: float, c: float, what: str = "") -> str:
            pct = f"{100.0 * (d / c - 1.0):+.1f} %" if c > 0 else "n/a"
            return f"{d:.4g} of {c:.4g} mm^3{what} ({pct})"

        each = ", ".join(f"{m} {said(self.laid[m], self.commanded[m])}"
                         for m in sorted(self.commanded))
        total = said(sum(self.laid.values()), sum(self.commanded.values()), " commanded")
        none = (f"{self.none} paths get no pulse (their volume is under half of the "
                "valve's smallest pulse, and rounds to none)" if self.none
                else "every path gets a pulse")
        return f"the pulses lay {total}; {each}; {none}"


def _summary(out, n_layers, fmts, totals, sparse_paths, max_gap, max_gap_width, found, job,
             volume: _Volume) -> list[str]:
    """The one-screen summary of a valves run."""
    from icefab.flow import piece_max_s, piece_pulses, summarise_findings

    fl = job.flow
    files = " and ".join(f"{out}/valves/layer_KKKK.{f}" for f in fmts)
    lines = [f"valve programs: {totals['paths']} paths in {n_layers} layers, "
             f"{totals['pulses']} pulses in {totals['pieces']} pieces "
             f"(mode {fl.mode}, tick {fl.tick_s * 1e3:g} ms, split at {piece_max_s(job):.6g} s / "
             f"{piece_pulses(job)} pulses, flow.out_of_range = {fl.out_of_range!r})",
             f"written: {files} (one file per layer, its programs in build order), "
             f"{out}/valves-paths.csv (one row per path), {out}/valves-summary.txt",
             f"volume: {volume.text()}"]
    if not found:
        lines.append("findings: none")
        return lines
    kinds = summarise_findings(found)
    lines.append(f"findings: {len(found)}, one line per kind (each path's own: "
                 f"valves-paths.csv):")
    # the drop spacing is one figure over every material's paths: said once, under the
    # last kind of finding it explains
    last_sparse = max((k for k, line in enumerate(kinds) if "min_drops_per_mm" in line),
                      default=-1)
    for k, line in enumerate(kinds):
        lines.append(f"  {line}")
        if k == last_sparse:
            total_m, sparse_m = totals["length"] / 1000, totals["sparse"] / 1000
            share = 100 * totals["sparse"] / totals["length"] if totals["length"] else 0.0
            verdict = ("drops never lie farther apart than the path is wide, so they still "
                       "touch: a continuous bead" if max_gap <= max_gap_width else
                       f"the widest spacing, {max_gap:.2f} mm, exceeds its path's width "
                       f"{max_gap_width:.2f} mm: there the bead may break into separate "
                       "drops")
            cost = ("none (every pulse is still placed; the volume per mm is as commanded)"
                    if not volume.none else
                    f"{volume.none} paths get no pulse (see volume above)")
            lines.append(f"    volume cost: {cost}; affected, all materials: {sparse_m:.2f} m "
                         f"of {total_m:.2f} m deposited ({share:.1f} %) on {sparse_paths} "
                         f"paths; {verdict}")
    return lines
