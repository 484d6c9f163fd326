"""Where the bunny's build time goes, and what the levers a job or the cell offers are
worth (issue 15): MTTS time on a few bunny layers, by kind of path, beside its floor.

    python3 bench/bench_time_levers.py [--layers 150,350,550,750,950]

On the chosen layers (planned by ``plan_layer`` without measurement; the bunny sliced as
``bench_build_time.py`` slices it, origin (340, 0)), prints:

* per kind of path (role, material, constant or variable width, closed or open): count,
  MTTS time (jerk on, default limits, ``plan_paths_durations``), the speed-bound floor
  (length over ``motion.path_limits``), PATHSPLIT pieces and the time each piece costs
  beyond its floor;
* what a rest-to-rest straight move of 5-200 mm costs beyond length / speed;
* the same paths under other limits: the joint bounds x10, the Cartesian jerk bound x10,
  jerk off (the thesis' limits are eq. 4.10; what binds);
* the paths of other fill patterns (``materials.*.fill_pattern``): time and unfilled area.

Every figure is from the same run; the default job is the peer of each variant.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from bench_build_time import BUNNY_EE, _bunny_stack  # noqa: E402


def bunny_layers(spec: str, **settings):
    """(job, stack, picks, layers): the default job (with ``settings``, dotted names) at
    the bunny's origin (340, 0), the bunny's stack and its layers ``spec``
    ("150,350,...") planned without measurement."""
    from icefab.config import Job
    from icefab.paths import plan_layer

    job = Job().replace(**{"cell.ee_origin_mm": BUNNY_EE, "cell.stroke_mm": 400.0,
                           **settings})
    stack = _bunny_stack(job, 1)
    picks = [int(k) for k in spec.split(",")]
    return job, stack, picks, [plan_layer(stack.layers[k], job, measured=False)
                               for k in picks]


def _durations(layers, job):
    from icefab.motion import plan_paths_durations
    return [plan_paths_durations(lp.paths, job, layer=lp.index) for lp in layers]


def _by_kind(layers, durations, job) -> dict:
    from icefab.core import path_lengths
    from icefab.motion import path_limits, pathsplit

    out: dict = defaultdict(lambda: np.zeros(5))
    for lp, d in zip(layers, durations):
        lengths = path_lengths(lp.paths)
        for p, t, mm in zip(lp.paths, d, lengths):
            pts = np.vstack([p.points, p.points[:1]]) if p.closed else p.points
            key = (p.role, p.material, "variable" if p.widths is not None else "constant",
                   "closed" if p.closed else "open")
            out[key] += [1, t, mm, len(pathsplit(pts, job)), mm / path_limits(p, job)]
    return out


def _total(durations) -> float:
    return float(sum(d.sum() for d in durations))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", default="150,350,550,750,950",
                    help="bunny layer indices (default: five spread over the part)")
    args = ap.parse_args()
    from icefab.motion import plan_motion
    from icefab.paths import plan_layer

    print(f"machine: {os.cpu_count()}-core {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    job, stack, picks, layers = bunny_layers(args.layers)
    base = _durations(layers, job)
    total = _total(base)
    print(f"\nbunny layers {picks}: MTTS {total:.1f} s (jerk on, default limits)")
    print("| kind of path | paths | MTTS s | floor s | pieces | mean piece mm | s per piece "
          "beyond floor |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for key, (n, t, mm, pieces, floor) in sorted(_by_kind(layers, base, job).items(),
                                                 key=lambda kv: -kv[1][1]):
        print(f"| {' '.join(key)} | {int(n)} | {t:.1f} | {floor:.1f} | {int(pieces)} | "
              f"{mm / pieces:.1f} | {(t - floor) / pieces:.3f} |")

    print("\nrest-to-rest straight moves (fill speed bound):")
    v = job.motion.speed_mm_s
    for length in (5.0, 20.0, 50.0, 200.0):
        pts = np.c_[np.linspace(300.0, 300.0 + length, 50), np.zeros(50)]
        t = plan_motion(pts, job).duration
        print(f"  {length:5.0f} mm: {t:.3f} s, {t - length / v:.3f} s beyond length / speed")

    m = job.motion
    print("\nthe same paths under other limits (ratio to the default):")
    for label, changes in (
            ("joint speed, acceleration and jerk bounds x10",
             {"motion.joint_speed_deg_s": tuple(10 * x for x in m.joint_speed_deg_s),
              "motion.joint_accel_deg_s2": tuple(10 * x for x in m.joint_accel_deg_s2),
              "motion.joint_jerk_deg_s3": tuple(10 * x for x in m.joint_jerk_deg_s3)}),
            ("Cartesian jerk bound x10", {"motion.jerk_mm_s3": 10 * m.jerk_mm_s3}),
            ("jerk off", {"motion.jerk_limited": False})):
        t = _total(_durations(layers, job.replace(**changes)))
        print(f"  {label}: {t:.1f} s ({t / total:.3f})")

    print("\nother fill patterns (paths planned again; ratio to the default, unfilled mm^2 "
          "part / scaffold):")
    unf = np.sum([lp.unfilled_mm2 for lp in layers], axis=0)
    print(f"  concentric (default): {total:.1f} s, unfilled {unf[0]:.1f} / {unf[1]:.1f}")
    for pattern in ("hybrid", "zigzag"):
        for mats in (("part",), ("part", "scaffold")):
            j = job.replace(**{f"materials.{m_}.fill_pattern": pattern for m_ in mats})
            other = [plan_layer(stack.layers[k], j, measured=False) for k in picks]
            t = _total(_durations(other, j))
            u = np.sum([lp.unfilled_mm2 for lp in other], axis=0)
            print(f"  {pattern}, {' and '.join(mats)}: {t:.1f} s ({t / total:.3f}), unfilled "
                  f"{u[0]:.1f} / {u[1]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
