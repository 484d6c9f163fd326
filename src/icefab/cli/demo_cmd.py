"""``icefab demo``: every stage on the built-in beer mug and the default Cobra 600 cell.

No input file is needed: the mug is generated in code (``icefab.demo.demo_mug``). The
stages run in pipeline order — slice, scaffold, paths, trajectories, valve programs, and
the build simulator open loop and with surface mapping feedback — and their results and
pictures are written to the output folder, which appears only when everything succeeded.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from icefab.cli.common import (ESTIMATE_WORDS, Progress, add_job_argument, hours,
                               job_from_args, layer_thickness_text, output_dir)
from icefab.report import html_report, plot_speed, plot_toolpaths


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="run every stage on the built-in demo part (a beer mug)",
        description="Generate a beer mug with a handle (about 125 mm tall) and run every "
                    "stage on it with the default Cobra 600 cell (or -c JOB's settings; "
                    "the part is always the mug, whatever parts.files says), writing "
                    "results and pictures to OUT.")
    add_job_argument(p)
    p.add_argument("-o", "--out", default="icefab-demo", metavar="OUT",
                   help="output folder (default: icefab-demo)")
    p.add_argument("--layers", type=int, default=0, metavar="N",
                   help="build only the first N layers (default, or 0: all)")
    p.add_argument("--sim-layers", type=int, default=60, metavar="N",
                   help="layers run on the build simulator, open loop and with SMF "
                        "(default: 60; 0 skips the simulator)")
    p.set_defaults(func=run)


def _say(text: str) -> None:
    print(text, flush=True)


def run(args: argparse.Namespace) -> int:
    from icefab.demo import demo_mug
    from icefab.flow import (n_pulses, plan_build_valves, program_pieces,
                             summarise_findings, write_valve_layer)
    from icefab.mesh import check_mesh, transform, write_stl
    from icefab.motion import plan_toolpaths, save_trajectories
    from icefab.paths import estimate_build_time, plan_paths, save_toolpaths
    from icefab.regions import add_scaffold
    from icefab.slicing import save_stack, slice_mesh
    from icefab.workload import check_placed_part
    from icefab.core import Stack, Toolpaths

    from icefab.errors import ConfigError
    from icefab.headroom import check_slowest_flow
    from icefab.workload import check_pulses

    if args.layers < 0 or args.sim_layers < 0:
        raise ConfigError(f"--layers {args.layers} / --sim-layers {args.sim_layers}: must be "
                          ">= 0")
    job = job_from_args(args)
    n_sim = min(args.sim_layers, args.layers) if args.layers else args.sim_layers
    if n_sim and n_sim < job.feedback.interval_layers:  # before any work, not after it
        raise _no_measurement(n_sim, job)
    summary: dict = {}
    t_all = time.perf_counter()
    with output_dir(args.out, "demo") as out:
        t0 = time.perf_counter()
        # Placed like any part (thesis 3.1.2): by default centred on the building origin.
        mesh = transform(demo_mug(), job.parts, job)
        check_placed_part(mesh.vertices, job, mesh.faces)  # units, stroke, reach: before slicing
        check_slowest_flow(job)  # a flow no valve program can make: before slicing
        report = check_mesh(mesh)
        write_stl(mesh, out / "demo-mug.stl")
        _say(f"part: demo mug, {mesh.n_faces} facets, size "
             f"{np.ptp(mesh.vertices, axis=0).round(1).tolist()} mm, watertight: "
             f"{report.watertight}")

        stack = slice_mesh(mesh, job, progress=Progress("slicing"))
        if args.layers:
            stack = Stack(layers=stack.layers[:args.layers], job=stack.job,
                          layer_thickness=stack.layer_thickness, warnings=stack.warnings)
        stack = add_scaffold(stack, job)
        save_stack(stack, out / "stack.npz")
        n = len(stack)
        ks = sorted({0, n // 8, n // 2, (3 * n) // 4, n - 1})
        summary["slice"] = {"layers": n, "warnings": len(stack.warnings),
                            "seconds": round(time.perf_counter() - t0, 3)}
        _say(f"sliced and scaffolded: {n} layer{'s' * (n != 1)} of "
             f"{layer_thickness_text(stack)}, "
             f"{len(stack.warnings)} warnings")

        t0 = time.perf_counter()
        toolpaths: Toolpaths = plan_paths(stack, job)
        save_toolpaths(toolpaths, out / "toolpaths.npz")
        plot_toolpaths(stack, toolpaths, ks, out / "layers.png")
        per_layer, const_s = estimate_build_time(toolpaths, job)
        n_paths = sum(len(lp.paths) for lp in toolpaths)
        summary["paths"] = {"paths": n_paths, "constant_speed_s": round(const_s, 1),
                            "seconds": round(time.perf_counter() - t0, 3)}
        _say(f"paths: {n_paths} (travel included); constant-speed estimate {hours(const_s)} "
             f"({ESTIMATE_WORDS})")

        t0 = time.perf_counter()
        motion = plan_toolpaths(toolpaths, job, progress=Progress("trajectories"))
        save_trajectories(motion, out / "trajectories.npz")
        for k in ks[1:3] or ks[:1]:  # two layers, or the one there is
            plot_speed(motion.layers[k], out / f"speed_layer_{motion.layers[k].index}.png",
                       job.motion.speed_mm_s, job)
        summary["motion"] = {"samples": motion.n_points, "build_s": round(motion.duration, 1),
                             "seconds": round(time.perf_counter() - t0, 3)}
        # No comparison here: the one build-time comparison (minimum-time vs the same paths
        # at constant speed with the robot's accelerations) is 'icefab plan''s; the estimate
        # above is a lower bound no robot runs, so a percentage against it would mislead.
        _say(f"trajectories: {motion.n_points} samples at {job.motion.dt_s * 1000:g} ms, "
             f"build motion time {hours(motion.duration)} with minimum-time trajectories "
             "('icefab plan' compares it with constant speed)")

        t0 = time.perf_counter()
        check_pulses(motion.layers, job)
        programs = plan_build_valves(motion.layers, job, progress=Progress("valve programs"))
        pulses = pieces = 0
        flagged: list[tuple[int, str]] = []  # (layer, finding) of every flagged path
        for lm, layer_programs in zip(motion.layers, programs):
            for lp in layer_programs:
                flagged += [(lm.index, w) for w in lp.program.warnings]
                pulses += n_pulses(lp.program)
                pieces += len(program_pieces(lp.program))
        valves_dir = out / "valves"
        valves_dir.mkdir()
        first = motion.layers[0].index
        # one readable example layer, in the form 'icefab valves' writes; the rest are counted
        write_valve_layer(first, programs[0], valves_dir / f"layer_{first:04d}.txt", fmt="txt")
        summary["valves"] = {"pulses": pulses, "pieces": pieces,
                             "seconds": round(time.perf_counter() - t0, 3)}
        findings = summarise_findings(flagged)  # one line per kind of valve limit
        summary["valves"]["findings"] = findings
        _say(f"valve programs: {pulses} pulses in {pieces} pieces")
        for line in findings:
            _say(f"  {line}")

        if args.sim_layers:
            _run_simulator(toolpaths, job, min(args.sim_layers, n), out, summary)

        summary["seconds"] = round(time.perf_counter() - t_all, 2)
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        pictures = [("Layers: part and scaffold regions, boundaries, fill and travel",
                     out / "layers.png")]
        pictures += [(f"Speed along the paths of layer {p.stem.rsplit('_', 1)[1]} "
                      "(thesis Fig. 4-11), each nozzle drawn where it is in the part frame",
                      p) for p in sorted(out.glob("speed_layer_*.png"))]
        pictures += [(caption, out / "simulation" / name) for caption, name in (
            ("RMS height error per measurement layer, open loop vs SMF (thesis Fig. 5-9)",
             "rms_vs_height.png"),
            ("Height error surfaces, open loop vs SMF (thesis Fig. 5-8)", "surfaces.png"))
            if (out / "simulation" / name).exists()]
        (out / "report.html").write_text(
            html_report("icefab demo: beer mug on the Cobra 600 cell", summary, pictures,
                        notes=list(stack.warnings)), encoding="utf-8")
    _say(f"wrote {args.out}/ in {summary['seconds']:.1f} s; open {args.out}/report.html")
    return 0


def _no_measurement(n_layers: int, job) -> Exception:
    from icefab.errors import ConfigError

    return ConfigError(f"the simulator's {n_layers} layers hold no measurement layer "
                       f"(feedback.interval_layers = {job.feedback.interval_layers}): SMF "
                       "would never act; simulate more layers (--sim-layers) or measure "
                       "more often")


def _run_simulator(toolpaths, job, n_layers: int, out, summary: dict) -> None:
    from icefab.cli.simulate_cmd import write_simulation_outputs
    from icefab.sim import measured_layers, simulate_open_and_smf

    # the exact check (which layers carry measurement paths) after the early one in run()
    if not measured_layers(toolpaths, job, layers=n_layers):
        raise _no_measurement(n_layers, job)
    t0 = time.perf_counter()
    open_loop, closed = simulate_open_and_smf(toolpaths, job, layers=n_layers,
                                              progress=Progress("simulator, open loop and SMF"))
    write_simulation_outputs(open_loop, closed, out / "simulation")
    summary["simulation"] = {"layers": n_layers,
                             "final_rms_open_loop_mm": float(open_loop.rms[-1]),
                             "final_rms_smf_mm": float(closed.rms[-1]),
                             "final_rms_footprint_open_loop_mm":
                                 float(open_loop.rms_footprint[-1]),
                             "final_rms_footprint_smf_mm": float(closed.rms_footprint[-1]),
                             "seconds": round(time.perf_counter() - t0, 3)}
    _say(f"simulator ({n_layers} layers, flow error {job.simulation.flow_error:+.0%}): final "
         f"RMS height error {open_loop.rms[-1]:.3f} mm open loop, {closed.rms[-1]:.3f} mm "
         f"with SMF (over the whole footprint, part and scaffold: "
         f"{open_loop.rms_footprint[-1]:.3f} / {closed.rms_footprint[-1]:.3f} mm)")
