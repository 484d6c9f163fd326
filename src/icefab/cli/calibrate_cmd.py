"""``icefab calibrate laser|valve|synthetic``: the calibrations a real cell needs.

* ``icefab calibrate laser --jig JIG.csv --jig-scans SCANS.csv --edge-scans SCANS.csv
  [-c JOB] -o OUT [--force]``: the laser's offset (scans over a jig with known edges) and
  latency (parallel scans of a sharp edge in opposite directions), thesis 5.2.1. Writes
  ``OUT/laser.toml`` (a job fragment: ``[cell] laser_offset_mm``, ``laser_latency_s``,
  the uncertainties as comments) and ``OUT/laser.json`` (every figure). When the expanded
  uncertainty misses the thesis' tolerances (0.2 mm, 0.002 s) nothing is written and
  the command says why (exit 2), unless ``--force``.
* ``icefab calibrate valve MASSES.csv [--material part|scaffold] [--density G_CM3]
  [-c JOB] -o OUT``: the valve's frequency-flow table from mass measurements
  (``frequency_hz,duration_s,mass_g``), thesis 6.1. Writes ``OUT/calibration_MATERIAL.csv``
  (what ``materials.MATERIAL.calibration_file`` reads), ``OUT/valve_MATERIAL.png`` (fit and
  residuals) and ``OUT/valve_MATERIAL.toml`` (the job fragment naming the table).
* ``icefab calibrate synthetic -o OUT [--seed N]``: scan and mass data of a simulated cell
  with known true values drawn at random (``OUT/truth.json``), to try the two commands
  above; not the virtual cell of ``icefab cell serve`` (the job's laser offset,
  ``simulation.laser_latency_s``).

File layouts: :mod:`icefab.calibration`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from icefab.cli.common import add_job_argument, job_from_args, output_dir
from icefab.config import toml_string
from icefab.errors import ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "calibrate", help="laser offset/latency and valve frequency-flow calibrations",
        description="Calibrations a real cell needs (thesis 5.2.1, 6.1).")
    sub = p.add_subparsers(dest="what", metavar="WHAT")
    sub.required = True

    lp = sub.add_parser("laser", help="laser offset and latency from scan files",
                        description="Laser offset from jig scans, latency from opposite-"
                                    "direction scans of a sharp edge (thesis 5.2.1).")
    lp.add_argument("--jig", required=True, metavar="JIG.csv",
                    help="the jig's edges: axis,position_mm,step_mm (base frame)")
    lp.add_argument("--jig-scans", required=True, metavar="SCANS.csv",
                    help="scans over the jig: scan,t_s,x_mm,y_mm,z_mm")
    lp.add_argument("--edge-scans", required=True, metavar="SCANS.csv",
                    help="parallel scans of a sharp edge in opposite directions")
    lp.add_argument("--match-mm", type=float, default=5.0,
                    help="a crossing belongs to the jig edge its nominal position is "
                         "within this distance of (default 5 mm)")
    lp.add_argument("--force", action="store_true",
                    help="write the result even when it misses the thesis' tolerances")
    add_job_argument(lp)
    lp.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    lp.set_defaults(func=run_laser)

    vp = sub.add_parser("valve", help="valve frequency-flow table from mass measurements",
                        description="Fit the frequency-flow table nu = h(Q) of a valve "
                                    "from mass measurements (thesis 6.1).")
    vp.add_argument("masses", metavar="MASSES.csv",
                    help="a header line frequency_hz,duration_s,mass_g (the columns in "
                         "any order), then one row per measurement")
    vp.add_argument("--material", choices=("part", "scaffold"), default="part",
                    help="the valve measured (default part): the masses become flows with "
                         "the job's materials.MATERIAL.density_g_cm3 unless --density, and "
                         "OUT/valve_MATERIAL.toml sets materials.MATERIAL.calibration_file to "
                         "OUT/calibration_MATERIAL.csv")
    vp.add_argument("--density", type=float, metavar="G_CM3",
                    help="density, g/cm^3 (default: the job's materials.MATERIAL."
                         "density_g_cm3)")
    add_job_argument(vp)
    vp.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    vp.set_defaults(func=run_valve)

    sp = sub.add_parser("synthetic", help="calibration data of a simulated cell with known "
                                          "true values",
                        description="Write jig, scan and mass files of a simulated cell whose "
                                    "true laser offset (the job's within 0.5 mm) and latency "
                                    "(5-20 ms) are drawn at random, and the job's valve tables "
                                    "(truth.json), to try 'calibrate laser' and 'calibrate "
                                    "valve'. Not the virtual cell of 'icefab cell serve', whose "
                                    "laser has the job's offset and simulation.laser_latency_s.")
    sp.add_argument("--seed", type=int, default=0,
                    help="seed (>= 0) of the random true values and measurement noise: the "
                         "same seed writes the same files (default 0)")
    add_job_argument(sp)
    sp.add_argument("-o", "--out", required=True, metavar="OUT", help="output folder")
    sp.set_defaults(func=run_synthetic)


def run_laser(args: argparse.Namespace) -> int:
    from icefab import calibration as cal

    job = job_from_args(args)
    jig = cal.read_jig(args.jig)
    jig_scans = cal.read_scans(args.jig_scans)
    edge_scans = cal.read_scans(args.edge_scans)
    if not args.match_mm > 0:
        raise ConfigError(f"--match-mm {args.match_mm}: must be > 0")
    result = cal.calibrate_laser(jig_scans, jig, edge_scans,
                                 nominal_offset_mm=job.cell.laser_offset_mm,
                                 match_mm=args.match_mm)
    o, lt = result.offset, result.latency
    print(f"laser offset: ({o.offset_mm[0]:.3f}, {o.offset_mm[1]:.3f}) mm +- "
          f"({o.expanded_mm[0]:.3f}, {o.expanded_mm[1]:.3f}) mm (95 %; "
          f"{o.crossings[0]} + {o.crossings[1]} jig crossings)")
    print(f"laser latency: {lt.latency_s * 1000:.2f} ms +- {lt.expanded_s * 1000:.2f} ms "
          f"(95 %; {lt.crossings} edge crossings at {lt.speed_mm_s:.0f} mm/s)")
    if lt.estimate_s is not None:
        print(f"note: the fit gave {lt.estimate_s * 1000:.3f} ms, below 0 within its "
              "uncertainty: taken as 0 (a latency cannot be negative)")
    findings = result.findings()
    if findings and not args.force:
        raise ConfigError(findings[0] + (f" (and {len(findings) - 1} more)"
                                         if len(findings) > 1 else "")
                          + "; nothing written (--force writes it anyway)")
    for line in findings:
        print(f"warning: {line}")
    if not findings:
        print("within the thesis' tolerances (0.2 mm, 0.002 s; 5.2.1)")
    with output_dir(args.out, "calibrate-laser") as tmp:
        (tmp / "laser.toml").write_text(result.to_toml(), encoding="utf-8")
        (tmp / "laser.json").write_text(json.dumps(result.as_dict(), indent=1) + "\n",
                                        encoding="utf-8")
    print(f"wrote {Path(args.out) / 'laser.toml'} (add it to the job)")
    return 0


def run_valve(args: argparse.Namespace) -> int:
    from icefab import calibration as cal

    job = job_from_args(args)
    density = job.materials[args.material].density_g_cm3
    if args.density is not None:
        # the job setting's range (a tester's --density 1000, water in kg/m^3, wrote a
        # table 1000 times too small, and inf a traceback)
        try:
            job.replace(**{f"materials.{args.material}.density_g_cm3": args.density})
        except ConfigError as exc:
            reason = str(exc).split(": ", 1)[-1]
            raise ConfigError(f"--density {args.density:g} g/cm^3: {reason}") from None
        density = args.density
    f, d, m, lines = cal.read_mass_runs(args.masses)
    fit = cal.fit_valve_table(f, d, m, density, source=str(args.masses), lines=lines)
    name = f"calibration_{args.material}.csv"
    table = (Path(args.out) / name).resolve()
    try:   # the fragment names the table in TOML, which holds UTF-8 text only
        str(table).encode("utf-8")
    except UnicodeEncodeError:
        raise ConfigError(f"-o {args.out!r}: the job fragment names the table by its path, "
                          "and this folder's name is not UTF-8 text, which TOML cannot hold; "
                          "choose another folder") from None
    with output_dir(args.out, f"calibrate-valve-{args.material}") as tmp:
        cal.write_valve_table(fit, tmp / name, args.material)
        cal.plot_valve_fit(fit, tmp / f"valve_{args.material}.png",
                           f"{args.material} valve: {len(f)} runs, density {density:g} g/cm^3")
        (tmp / f"valve_{args.material}.toml").write_text(
            f"# icefab calibrate valve: {len(f)} mass measurements, RMS residual "
            f"{100 * fit.rms_residual:.2f} %\n[materials.{args.material}]\n"
            f"calibration_file = {toml_string(str(table))}\n", encoding="utf-8")
    print(f"{args.material} valve: {len(fit.frequency_hz)} table rows from {len(f)} "
          f"measurements, up to {fit.flow_mm3_s[-1]:.4g} mm^3/s at "
          f"{fit.frequency_hz[-1]:g} Hz; RMS residual {100 * fit.rms_residual:.2f} %, largest "
          f"{100 * abs(fit.residual).max():.2f} %")
    if fit.method != "polynomial":
        print("note: no polynomial follows these runs (a valve that barely opens or "
              "saturates): the table is the runs' mean flows, made to rise with the "
              "frequency")
    for line in fit.warnings:
        print(f"warning: {line}")
    top = float(fit.measured_hz.max())
    if fit.frequency_hz[-1] < top:
        print(f"note: the flow rises by less than {100 * cal.PLATEAU_RISE:g} % above "
              f"{fit.frequency_hz[-1]:g} Hz (measured up to {top:g} Hz): the valve saturates "
              "there and the table ends there")
    out = Path(args.out)
    print(f"wrote {out / name} (materials.{args.material}.calibration_file), "
          f"{out / f'valve_{args.material}.toml'} (the job fragment naming it) and "
          f"{out / f'valve_{args.material}.png'} (the fit)")
    return 0


def run_synthetic(args: argparse.Namespace) -> int:
    import numpy as np

    from icefab import calibration as cal
    from icefab.flow import calibration_for

    job = job_from_args(args)
    if args.seed < 0:
        raise ConfigError(f"--seed {args.seed}: must be >= 0")
    rng = np.random.default_rng(args.seed)
    nominal = np.asarray(job.cell.laser_offset_mm, dtype=np.float64)
    # the true offset differs from the nominal one by machining and assembly (5.2.1)
    offset = nominal + rng.uniform(-0.5, 0.5, 2)
    latency = float(rng.uniform(0.005, 0.02))
    jig = cal.default_jig()
    jig_scans = cal.synthetic_jig_scans(jig, offset_mm=offset, latency_s=latency, rng=rng)
    edge_scans = cal.synthetic_edge_scans(offset_mm=offset, latency_s=latency, rng=rng)
    truth: dict = {"laser_offset_mm": offset.tolist(), "laser_latency_s": latency}
    with output_dir(args.out, "calibrate-synthetic") as tmp:
        cal.write_jig(jig, tmp / "jig.csv")
        cal.write_scans(jig_scans, tmp / "jig_scans.csv")
        cal.write_scans(edge_scans, tmp / "edge_scans.csv")
        for material in ("part", "scaffold"):
            table = calibration_for(material, job)
            freqs = table.frequency_hz[table.frequency_hz > 0]
            density = job.materials[material].density_g_cm3
            f, d, m = cal.synthetic_masses(table.flow, freqs, density_g_cm3=density, rng=rng)
            cal.write_masses(tmp / f"masses_{material}.csv", f, d, m)
            truth[f"{material}_table"] = {"frequency_hz": table.frequency_hz.tolist(),
                                          "flow_mm3_s": table.flow_mm3_s.tolist(),
                                          "density_g_cm3": density}
        (tmp / "truth.json").write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")
    print(f"wrote jig.csv, jig_scans.csv, edge_scans.csv, masses_part.csv, "
          f"masses_scaffold.csv and truth.json to {args.out}")
    return 0
