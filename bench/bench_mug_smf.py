"""Issue 15's accuracy check on the demo mug, over many disturbance seeds.

    python3 bench/bench_mug_smf.py [--seeds 40] [--layers 60] [--peer SETTING=VALUE ...]

The build simulator (``icefab.sim.simulate_open_and_smf``, the default job: +10 % flow
error, laser noise, debris) runs the demo mug's first ``--layers`` layers open loop and
with SMF, once with the default job and once with the peer, under seeds 0 .. ``--seeds``
- 1 (``simulation.seed``: the noise and the debris). The peer is by default the same job
with ``variable_width = false`` (the gap fill's centre lines in runs of one width each,
issue 15's "today's gap fill"); ``--peer`` names other settings (JSON values, e.g.
``feedback.measure_spacing_mm=4.5``), which act on the paths and the simulated cell
alike; ``--base`` sets both jobs (e.g. ``simulation.deposition="valves"``: the valve
programs' pulses, not the ideal flow). The paths do not depend on the seed; each
variant's are planned once.

Prints, for open loop and SMF: the final RMS height error of each variant (mean over the
seeds), their ratio, the paired difference (default - peer: mean, standard deviation), in
how many seeds the default is worse, and the two-sided Wilcoxon signed-rank p-value. One
seed's figure moves by some 30 % with the seed (the debris), so a single run compares the
seeds' draws more than the paths.
"""
from __future__ import annotations

import argparse
import datetime
import platform
import time

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from _report import parse_settings  # noqa: E402

PEER = {"materials.part.variable_width": False, "materials.scaffold.variable_width": False}


def final_rms(toolpaths, job, layers: int, seeds: range) -> np.ndarray:
    """(len(seeds), 2) final RMS height error, mm: open loop, SMF."""
    from icefab.sim import simulate_open_and_smf

    out = np.zeros((len(seeds), 2))
    for i, seed in enumerate(seeds):
        open_loop, smf = simulate_open_and_smf(
            toolpaths, job.replace(**{"simulation.seed": seed}), layers=layers)
        out[i] = open_loop.rms[-1], smf.rms[-1]
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--layers", type=int, default=60)
    ap.add_argument("--peer", nargs="*", default=None, metavar="SETTING=VALUE",
                    help="the peer job's settings (JSON values); default: "
                         "materials.part.variable_width=false "
                         "materials.scaffold.variable_width=false")
    ap.add_argument("--base", nargs="*", default=[], metavar="SETTING=VALUE",
                    help="settings of both jobs (JSON values), e.g. "
                         "simulation.deposition=\"valves\"")
    ap.add_argument("--no-write", action="store_true", help="accepted for run_all.py; this "
                    "benchmark only prints (its figures are copied into BENCHMARKS.md by hand)")
    args, _ = ap.parse_known_args()
    if args.seeds < 2 or args.layers < 1:
        ap.error("--seeds must be >= 2 and --layers >= 1")
    try:
        peer = parse_settings(args.peer) if args.peer is not None else PEER
        base = parse_settings(args.base)
    except ValueError as exc:
        ap.error(f"--peer / --base {exc}")
    from scipy import stats

    from icefab import Job
    from icefab.core import Stack
    from icefab.demo import demo_mug
    from icefab.mesh import transform
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.slicing import slice_mesh

    print(f"{platform.machine()}, {platform.python_version()}, "
          f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC", flush=True)
    from icefab.errors import ConfigError

    try:
        job = Job().replace(**base)
        peer_job = job.replace(**peer)   # a bad setting stops here, before any work
    except ConfigError as exc:
        ap.error(f"--peer / --base: {exc}")
    print(f"peer: {peer}; both: {base}", flush=True)
    t0 = time.perf_counter()
    # the scaffold of the whole mug (a layer's scaffold depends on the layers above), then
    # the simulated layers alone
    stack = add_scaffold(slice_mesh(transform(demo_mug(), job.parts, job), job), job)
    stack = Stack(layers=stack.layers[:args.layers], job=stack.job,
                  layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    seeds = range(args.seeds)
    res = {}
    for name, vjob in (("default", job), ("peer", peer_job)):
        res[name] = final_rms(plan_paths(stack, vjob), vjob, args.layers, seeds)
        print(f"{name}: {len(seeds)} seeds simulated ({time.perf_counter() - t0:.0f} s)",
              flush=True)
    print(f"\ndemo mug, first {args.layers} layers, seeds 0-{args.seeds - 1}; default: the "
          f"default job; peer: {peer}\n")
    print("| final RMS height error | default (mm) | peer (mm) | ratio | paired difference "
          "(um) | default worse in | Wilcoxon p |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for col, label in ((0, "open loop"), (1, "SMF")):
        a, b = res["default"][:, col], res["peer"][:, col]
        d = (a - b) * 1000.0
        p = stats.wilcoxon(a, b).pvalue if np.any(d != 0) else 1.0
        print(f"| {label} | {a.mean():.6f} | {b.mean():.6f} | {a.mean() / b.mean():.4f} | "
              f"{d.mean():+.3f} +- {d.std(ddof=1):.3f} | {int((d > 0).sum())} / {len(d)} | "
              f"{p:.2g} |")
    print(f"\nseed 0 (the demo's): default {res['default'][0, 0]:.6f} / "
          f"{res['default'][0, 1]:.6f} mm, peer {res['peer'][0, 0]:.6f} / "
          f"{res['peer'][0, 1]:.6f} mm (open loop / SMF)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
