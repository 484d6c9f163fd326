"""``icefab simulate MODEL...|TOOLPATHS.npz|TRAJECTORIES.npz|demo [-c job.toml] [--layers N] -o OUT``.

Runs a build (or its first N layers) on the virtual cell (``icefab.sim``) twice with the
same disturbances: open loop, and with surface mapping feedback. Prints the RMS height
deviation at every measurement layer for both side by side (thesis Fig. 5-9) and writes
to OUT:

* ``rms_vs_height.png``: RMS height deviation vs nominal height, open loop and SMF
  (Fig. 5-9);
* ``surfaces.png``: the height error surfaces of one measurement layer, open loop and SMF,
  on one colour scale (Fig. 5-8);
* ``simulation.json``: the settings used and both results per measurement layer;
* ``rms.csv``: the table that was printed.

MODEL is one or more mesh files (they replace ``parts.files`` of the job; placed, sliced,
scaffolded and planned here), ``demo`` for the built-in mug, a toolpaths file written
by ``icefab paths``, or a trajectories file written by ``icefab plan``.

Deposition (``--deposition``, ``simulation.deposition``): ``flow`` lays the commanded
volume along the paths (an ideal valve); ``valves`` runs the minimum-time trajectories
through their valve programs, pulse by pulse, and SMF re-plans the programs of the next
layers (thesis Ch. 6, 5.1.3). From a mesh or toolpaths the trajectories of the simulated
layers are planned once here; a trajectories file is simulated with ``valves`` unless
``--deposition flow`` is given, with the job it was planned with unless ``-c`` names
one (which must agree with it on frames, tool offsets, widths and layer thickness).
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from icefab.cli.common import (Progress, add_job_argument, command_inputs, file_job,
                               job_from_args, output_dir, placed_model)
from icefab.atomic import write_atomic
from icefab.errors import ConfigError, SimulationError, StackFileError
from icefab.report import plot_rms, plot_surfaces
from icefab.resultfiles import file_format

if TYPE_CHECKING:  # pragma: no cover
    from icefab.config import Job
    from icefab.motion import BuildMotion
    from icefab.sim import SimResult
    from icefab.core import Toolpaths


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="build on the virtual cell, open loop and with SMF",
        description="Deposit a build (or its first N layers) on the simulated cell with "
                    "the job's disturbances (flow error and drift, noise, debris, edge "
                    "loss; section [simulation]), once open loop and once with surface "
                    "mapping feedback, and compare the RMS height deviation per measurement "
                    "layer (thesis Fig. 5-8, 5-9). Input: mesh file(s), 'demo', a "
                    "toolpaths.npz from 'icefab paths' or a trajectories.npz from "
                    "'icefab plan'.")
    p.add_argument("model", nargs="*", metavar="MODEL|TOOLPATHS|TRAJECTORIES",
                   help="mesh file(s), 'demo' (the built-in mug), one toolpaths .npz or one "
                        "trajectories .npz (default: parts.files of the job)")
    add_job_argument(p)
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    p.add_argument("--layers", type=int, metavar="N",
                   help="simulate only the first N layers (default: simulation.layers, "
                        "0 = all)")
    p.add_argument("--flow-error", type=float, metavar="F",
                   help="flow gain error, e.g. 0.1 for 10 %% too much (simulation.flow_error)")
    p.add_argument("--seed", type=int, metavar="S", help="random seed (simulation.seed)")
    p.add_argument("--deposition", choices=("flow", "valves"),
                   help="'flow': commanded flow along the paths (ideal valve); 'valves': the "
                        "minimum-time trajectories run through their valve programs, pulse "
                        "by pulse, re-planned with the control action (simulation."
                        "deposition; default for a trajectories file: valves)")
    p.add_argument("--surface-layer", type=int, metavar="K",
                   help="measurement layer (toolpaths index) whose error surfaces are "
                        "drawn (default: the last one)")
    p.set_defaults(func=run)


# --------------------------------------------------------------------------- input


def _job_with_options(job: "Job", args: argparse.Namespace) -> "Job":
    changes = {}
    if args.flow_error is not None:
        changes["simulation.flow_error"] = args.flow_error
    if args.seed is not None:
        changes["simulation.seed"] = args.seed
    if args.deposition is not None:
        changes["simulation.deposition"] = args.deposition
    if args.layers is not None:
        if args.layers < 0:
            raise ConfigError(f"--layers {args.layers}: expected a number >= 0 (0: all)")
        changes["simulation.layers"] = args.layers
    return job.replace(**changes) if changes else job


def load_build(model: list[str], job: "Job", args: argparse.Namespace
               ) -> "tuple[Toolpaths | BuildMotion, Job]":
    """The build to simulate and the job to simulate it with (the command's options
    applied). From a trajectories file: its trajectories, with the job they were planned
    with and what a ``-c`` job file names laid over it (:func:`file_job`; it must agree on
    ``icefab.sim.MOTION_SETTINGS``), deposition ``valves`` unless ``--deposition`` says
    otherwise. Otherwise toolpaths: from a toolpaths file (its job, the same way), or the
    first ``simulation.layers`` layers (0: all) of the demo mug or mesh files (placed,
    sliced, scaffolded over the whole part, paths planned) with ``job``."""
    from icefab.core import Stack

    first = Path(model[0])
    if len(model) == 1 and first.suffix.lower() == ".npz":
        from icefab import motion as motion_mod
        from icefab import paths as paths_mod

        fmt = file_format(first)
        if fmt == motion_mod.FORMAT:
            from icefab.sim import MOTION_SETTINGS, check_motion_job

            motion = motion_mod.open_trajectories(first)  # its layers read as asked for
            source = f"{first}: the trajectories"
            job = _job_with_options(file_job(motion.job, args, source,
                                             "icefab paths, then icefab plan",
                                             MOTION_SETTINGS, SimulationError), args)
            if args.deposition is None:
                job = job.replace(**{"simulation.deposition": "valves"})
            check_motion_job(motion.job, job, source=source)
            return motion, job
        if fmt != paths_mod.FORMAT:
            raise StackFileError(f"{first}: not an icefab toolpath or trajectory file (format "
                                 f"{fmt!r}; expected {paths_mod.FORMAT!r} from 'icefab paths' "
                                 f"or {motion_mod.FORMAT!r} from 'icefab plan')")
        toolpaths = paths_mod.load_toolpaths(first)
        job = file_job(toolpaths.job, args, f"{first}: the toolpaths", "icefab paths")
        return toolpaths, _job_with_options(job, args)
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh

    job = _job_with_options(job, args)
    n_layers = job.simulation.layers
    mesh, job = placed_model(model, job)
    stack = slice_mesh(mesh, job, progress=Progress("slicing"))
    # the scaffold depends on every layer above, so it is made for the whole part first
    stack = add_scaffold(stack, job, progress=Progress("scaffold"))
    if n_layers:
        stack = Stack(layers=stack.layers[:n_layers], job=stack.job,
                      layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    return plan_paths(stack, job, progress=Progress("paths")), job


# --------------------------------------------------------------------------- outputs


def table_rows(open_loop: "SimResult", closed: "SimResult") -> list[list[float]]:
    """Per measurement layer: layer, nominal height, RMS and max |error| open and SMF over
    the part, then the same over the whole footprint, part and scaffold (mm)."""
    cols = [open_loop.layers, open_loop.nominal_z, open_loop.rms, closed.rms,
            open_loop.max_abs, closed.max_abs, open_loop.rms_footprint,
            closed.rms_footprint, open_loop.max_abs_footprint, closed.max_abs_footprint]
    return [[int(r[0])] + [float(v) for v in r[1:]] for r in zip(*cols)]


HEADER = ["layer", "height_mm", "rms_open_mm", "rms_smf_mm", "max_open_mm", "max_smf_mm",
          "rms_footprint_open_mm", "rms_footprint_smf_mm", "max_footprint_open_mm",
          "max_footprint_smf_mm"]


def final_rms_line(open_loop: "SimResult", closed: "SimResult") -> str:
    """The summary's last figure: both builds' RMS at the last measurement layer with a
    part footprint in both, named when it is not the last measured (a top layer too small
    for the grid has none: it printed 'nan mm')."""
    ok = np.flatnonzero(np.isfinite(open_loop.rms) & np.isfinite(closed.rms))
    if not len(ok):
        return ("final RMS height deviation: none (no measurement layer has a part "
                "footprint on the simulator grid)")
    j = int(ok[-1])
    at = "" if j == len(open_loop.rms) - 1 else \
        f" (layer {int(open_loop.layers[j])}, the last measured with a part footprint)"
    return (f"final RMS height deviation: {open_loop.rms[j]:.3f} mm open loop, "
            f"{closed.rms[j]:.3f} mm with SMF{at}")


def final_footprint_line(open_loop: "SimResult", closed: "SimResult") -> str:
    """The last measurement layer's error over its whole footprint, part and scaffold: RMS
    and largest, open loop and with SMF. The part's RMS alone hid millimetre ridges in
    the scaffold and where the materials' beads meet (a control review's). The last layer
    that covers a cell in both, as :func:`final_rms_line` (a layer that covers none, e.g.
    after the flow drifted to nothing, printed 'nan mm')."""
    o, c = open_loop, closed
    ok = np.flatnonzero(np.isfinite(o.rms_footprint) & np.isfinite(c.rms_footprint))
    if not len(ok):
        return ("over the whole footprint (part and scaffold): none (no measurement layer "
                "covers a cell of the simulator grid)")
    j = int(ok[-1])
    return (f"over the whole footprint (part and scaffold), layer {int(o.layers[j])}: RMS "
            f"{o.rms_footprint[j]:.3f} mm open loop, {c.rms_footprint[j]:.3f} mm with "
            f"SMF; largest {o.max_abs_footprint[j]:.3f} / {c.max_abs_footprint[j]:.3f} mm")


def format_table(rows: list[list[float]]) -> list[str]:
    """The printed table; a layer without a part footprint on the grid shows '-' (it
    printed 'nan'), said under the table."""
    def f(v: float, w: int) -> str:
        return f"{v:{w}.3f}" if math.isfinite(v) else f"{'-':>{w}}"

    wide = any(len(r) > 6 for r in rows)
    lines = ["layer  height mm   RMS open   RMS SMF   max open   max SMF"
             + ("   all open   all SMF" if wide else "") + "  (mm)"]
    for k, z, ro, rc, mo, mc, *foot in rows:
        lines.append(f"{k:5d}  {z:9.2f}  {f(ro, 9)}  {f(rc, 8)}  {f(mo, 9)}  {f(mc, 8)}"
                     + (f"  {f(foot[0], 9)}  {f(foot[1], 8)}" if foot else ""))
    if any(not math.isfinite(v) for r in rows for v in r[2:6]):
        lines.append("  -: no part footprint on the simulator grid at that layer")
    if any(not math.isfinite(v) for r in rows for v in r[6:]):
        lines.append("  - under all: the layer covers no cell of the simulator grid")
    if wide:
        lines.append("  RMS, max: the part, inside its rim; all: RMS over the whole "
                     "footprint, part and scaffold")
    return lines


def _csv_value(v: float) -> str:
    """A figure of rms.csv; empty where the layer has no part footprint (it wrote nan)."""
    return f"{v:.6f}" if math.isfinite(v) else ""


#: What a null in simulation.json's per-layer lists means (strict JSON has no NaN).
NULL_MEANS = ("rms_mm and max_abs_mm are null at a measurement layer whose part footprint "
              "is empty; rms_measured_mm where the laser took no samples; "
              "rms_footprint_mm and max_abs_footprint_mm where the layer covers no cell")
_PER_LAYER = ("rms_mm", "max_abs_mm", "rms_measured_mm", "rms_footprint_mm",
              "max_abs_footprint_mm")


def _strict_json_figures(result: "SimResult", name: str, job: "Job | None") -> dict:
    """``result.as_dict()`` with NaN per-layer figures as None (see :data:`NULL_MEANS`).

    Raises SimulationError when the simulation itself broke down: an infinite height on the
    simulated surface, or any non-finite figure other than those per-layer gaps (NaN or
    Infinity would make simulation.json invalid JSON, and a number like 1e308 misleads).
    """
    data = result.as_dict()
    bad = []
    z = np.asarray(result.height.z, dtype=np.float64)
    if np.isinf(z).any():
        bad.append(f"{int(np.isinf(z).sum())} surface heights are infinite")
    for key, value in data.items():
        if key in _PER_LAYER:
            data[key] = [None if not math.isfinite(v) else v for v in value]
            inf = [k for k, v in zip(data["layers"], value) if math.isinf(v)]
            if inf:
                bad.append(f"{key} infinite at layer {inf[0]}")
        elif isinstance(value, float) and not math.isfinite(value):
            bad.append(f"{key} = {value}")
        elif isinstance(value, list) and any(isinstance(v, float) and not math.isfinite(v)
                                             for v in value):
            bad.append(f"{key} = {value}")
    if bad:
        hint = ""
        if job is not None:
            from icefab.config import Job as _Job, to_dict

            now, default = to_dict(job), to_dict(_Job())
            changed = [f"{sec}.{k} = {v!r}" for sec in ("simulation", "flow")
                       for k, v in now[sec].items() if default[sec].get(k) != v]
            if changed:
                hint = f"; settings changed from the defaults: {', '.join(changed[:6])}"
        raise SimulationError(f"the {name} simulation's results are not finite ("
                              f"{'; '.join(bad[:3])}): the simulated surface overflowed, "
                              f"nothing was written{hint}")
    return data


def write_simulation_outputs(open_loop: "SimResult", closed: "SimResult", out: Path, *,
                             surface_layer: int | None = None,
                             job: "Job | None" = None) -> list[Path]:
    """Write rms_vs_height.png, surfaces.png, simulation.json and rms.csv into ``out``
    (created if missing). ``surface_layer``: the measurement layer drawn (default: the last
    one whose surfaces both results kept). Returns the files written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = table_rows(open_loop, closed)
    written = []
    common = sorted(set(open_loop.surfaces) & set(closed.surfaces))
    if surface_layer is None and common:
        surface_layer = common[-1]
    if surface_layer is not None and surface_layer not in common:
        raise ConfigError(f"--surface-layer {surface_layer}: not a measurement layer of the "
                          f"simulation (measured: {', '.join(map(str, open_loop.layers))})")
    data = {"format": "icefab-simulation", "version": 1,
            "open_loop": _strict_json_figures(open_loop, "open-loop", job),
            "smf": _strict_json_figures(closed, "SMF", job),
            "surface_layer": surface_layer, "null_means": NULL_MEANS}
    if job is not None:
        from icefab.config import to_dict

        settings = to_dict(job)
        data["settings"] = {"simulation": settings["simulation"],
                            "feedback": settings["feedback"]}
    write_atomic(out / "simulation.json",
                 (json.dumps(data, indent=2, allow_nan=False) + "\n").encode())
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(HEADER)
    w.writerows([[r[0]] + [_csv_value(v) for v in r[1:]] for r in rows])
    write_atomic(out / "rms.csv", buf.getvalue().encode())
    written += [out / "simulation.json", out / "rms.csv"]
    if rows:
        plot_rms(open_loop, closed, out / "rms_vs_height.png")
        written.append(out / "rms_vs_height.png")
    if surface_layer is not None:
        plot_surfaces(open_loop, closed, surface_layer, out / "surfaces.png")
        written.append(out / "surfaces.png")
    return written


# --------------------------------------------------------------------------- command


def own_thicknesses(layers) -> np.ndarray:
    """(L,) float64 mm: the own thickness of each of ``layers`` (NaN: the job's), a
    trajectory file's without decoding its layers
    (:meth:`icefab.resultfiles.LayerSequence.thicknesses`)."""
    if hasattr(layers, "thicknesses"):
        return np.asarray(layers.thicknesses(), dtype=np.float64)
    return np.array([lay.thickness for lay in layers], dtype=np.float64)


def measurement_interval_text(job: "Job", thicknesses) -> str:
    """How often the simulation measures: every ``feedback.interval_layers`` layers, or
    with adaptive layers (some own ``thicknesses``, mm) every ``interval_layers x
    slicing.layer_thickness_mm`` of height (:func:`icefab.stages.measured_layers`): it
    said "every 4 layers" of layers measured every 1 mm (a review's)."""
    fb = job.feedback
    if not np.isfinite(np.asarray(thicknesses, dtype=np.float64)).any():
        return f"every {fb.interval_layers} layers"
    step = fb.interval_layers * job.slicing.layer_thickness_mm
    return (f"every {step:g} mm of height (adaptive layers: feedback.interval_layers = "
            f"{fb.interval_layers} x slicing.layer_thickness_mm = "
            f"{job.slicing.layer_thickness_mm:g} mm)")


def run(args: argparse.Namespace) -> int:
    from icefab.motion import BuildMotion, plan_toolpaths
    from icefab.feedback import gains_verdict
    from icefab.sim import measured_layers, simulate_build, simulate_open_and_smf
    from icefab.core import Toolpaths

    t0 = time.perf_counter()
    given = job_from_args(args)
    args.model = command_inputs(args.model, given, words=("demo",))
    build, job = load_build(args.model, given, args)
    n = job.simulation.layers or len(build)
    n = min(n, len(build))
    # check what can be checked before anything is planned or simulated
    if isinstance(build, BuildMotion) and not any(
            t.path is not None and t.path.depositing
            for lm in build.layers[:n] for t in lm.trajectories):
        raise ConfigError(f"{args.model[0]}: no boundary or fill trajectories in the first "
                          f"{n} layers: no valve programs, nothing to deposit")
    measured = measured_layers(build, job, layers=n)
    if not measured:
        raise ConfigError(f"{n} layers hold no measurement layer (feedback.interval_layers "
                          f"= {job.feedback.interval_layers}): simulate more layers")
    if args.surface_layer is not None and args.surface_layer not in measured:
        raise ConfigError(f"--surface-layer {args.surface_layer}: not a measurement layer of "
                          f"the simulation (measured: {', '.join(map(str, measured))})")
    valves = job.simulation.deposition == "valves"
    if valves and not isinstance(build, BuildMotion):
        # the cell's minimum-time trajectories, planned once for both runs
        build = plan_toolpaths(Toolpaths(layers=tuple(build.layers[:n]), job=build.job), job,
                               progress=Progress("trajectories"))
    headroom: list[str] = []
    if valves:  # the feedback's headroom, before 2 x n layers are simulated (issue 11)
        from icefab.headroom import feedback_headroom, headroom_findings
        from icefab.stages import layer_height
        from icefab.workload import check_pulses

        check_pulses(build.layers[:n], job)

        headroom = headroom_findings(feedback_headroom(
            ((lm.index, t, layer_height(lm.thickness, job)) for lm in build.layers[:n]
             for t in lm.trajectories), job), job)
    t_prep = time.perf_counter() - t0
    keep = None if args.surface_layer is None else [args.surface_layer]
    if job.feedback.enabled:
        open_loop, closed = simulate_open_and_smf(build, job, layers=n, keep_surfaces=keep,
                                                  progress=Progress("open loop and with SMF"))
    else:
        # the job measures nothing: 'icefab build' runs it open loop, and so does this (SMF
        # ran here on the laser along the deposition paths: the two commands disagreed)
        open_loop = closed = simulate_build(build, job, layers=n, closed_loop=False,
                                            keep_surfaces=keep, progress=Progress("open loop"))
    t_sim = time.perf_counter() - t0 - t_prep
    with output_dir(args.out, "simulate") as tmp:
        write_simulation_outputs(open_loop, closed, tmp, surface_layer=args.surface_layer,
                                 job=job)
    sim = job.simulation
    print(f"{n} layers, flow error {sim.flow_error:+.0%}, drift {sim.flow_drift_per_cm3:g}/cm³, "
          f"noise {sim.noise_mm:g} mm, debris {sim.debris_rate:g}/layer, edge loss "
          f"{sim.edge_loss:.0%}, seed {sim.seed}; gains Kp {job.feedback.kp:g}, "
          f"Ki* {job.feedback.ki:g}, Kd* {job.feedback.kd:g}, "
          f"{measurement_interval_text(job, own_thicknesses(build.layers[:n]))}")
    stopped = [m for m, g in zip(("part", "scaffold"), open_loop.flow_gain) if g <= 0.0]
    if stopped:
        print(f"warning: the {' and '.join(stopped)} valve's flow drifted to nothing "
              f"(simulation.flow_drift_per_cm3 = {sim.flow_drift_per_cm3:g}): it deposited "
              "nothing from then on", file=sys.stderr)
    if valves:
        print(f"deposition: valve pulses along the minimum-time trajectories "
              + (f"({open_loop.pulses} pulses open loop, {closed.pulses} with SMF)"
                 if job.feedback.enabled else f"({open_loop.pulses} pulses, open loop)"))
    else:
        print("deposition: commanded flow (ideal valve)"
              + (" along the trajectories" if isinstance(build, BuildMotion) else ""))
    for line in headroom:
        print(f"warning: {line}")
    verdict = gains_verdict(job)
    if verdict is not None:   # simulated all the same: showing what such gains do is a use
        print(f"warning: {verdict[1]} ('icefab build' refuses gains that make it unstable)")
    if valves:  # what the valve limits did, once per kind, and the volume clamping cost
        from icefab.findings import clamped_volume, saturated_volume
        from icefab.flow import summarise_findings

        # feedback.enabled = false: one open-loop run (closed is it), said once as such
        runs = (("open loop", open_loop), ("with SMF", closed)) if job.feedback.enabled \
            else (("open loop", open_loop),)
        for label, res in runs:
            n_paths, n_layers, got, asked = clamped_volume(res.findings)
            if n_paths:
                print(f"clamped ({label}, flow.out_of_range = 'clamp'): {n_paths} paths in "
                      f"{n_layers} layers deliver {got:.6g} of {asked:.6g} mm^3 commanded "
                      f"({100 * (got / asked - 1):+.2f} %)")
            n_paths, n_layers, got, asked = saturated_volume(res.findings)
            if n_paths:
                print(f"saturated ({label}, the valve's range, thesis 5.2.2): SMF's "
                      f"correction on {n_paths} paths in {n_layers} layers delivers "
                      f"{got:.6g} of {asked:.6g} mm^3 asked ({100 * (got / asked - 1):+.2f} %)")
            for line in summarise_findings(res.findings)[:8]:
                print(f"valve limits ({label}): {line}")
    for line in format_table(table_rows(open_loop, closed)):
        print(line)
    print(final_rms_line(open_loop, closed))
    print(final_footprint_line(open_loop, closed))
    if not job.feedback.enabled:
        print("feedback.enabled = false: the build runs open loop (no measurement, no SMF); "
              "the SMF columns repeat it")
    print(f"time: build preparation {t_prep:.1f} s, simulation {t_sim:.1f} s")
    print(f"wrote {args.out}/ (rms_vs_height.png, surfaces.png, simulation.json, rms.csv)")
    return 0
