"""What continuous tours would buy (issue 15): consecutive paths joined through their
travel move without a stop, timed by MTTS against the same paths apart.

    python3 bench/bench_tour_joins.py [--layers 150,350,550,750,950] [--handle 0.3]

On the chosen bunny layers (planned by ``plan_layer`` without measurement, the bunny as
``bench_time_levers.py`` has it), every deposition path A followed by a travel move and a
path B of the same material and role is joined: A, a connector, B as one path that the
robot follows without stopping between them. The connector is a cubic Bezier curve
tangent to A's end and B's start (the directions over their last and first millimetre),
its handles ``--handle`` times the gap long (at least 0.5 mm), sampled every 0.1 mm: it
turns smoothly but its curvature jumps where it meets the paths (G1), as a real tour's
would unless it is built for it. Nothing of the valve is modelled; only motion.

Prints:

* per kind of join (material, role, open or closed ends): joins, the time one join saves
  (A + travel + B apart, minus the joined path; MTTS jerk on, default limits) and how many
  joins lose time, by the turn the connector makes (the angle from A's end to the gap's
  direction plus from it to B's start: 0 for paths in line, 180 for a sideways step
  between parallel paths, 360 for a U-turn);
* the whole layers with every such run joined into one path, against the same paths
  apart, and the sum of the joins that save time taken one by one (joining only where
  it pays): what joining is worth in today's order, which only shortens travel.

The paths are planned with tours off (``materials.*.tour_max_turn_deg = 0``): this is
the measurement that decided to build them and how (``icefab.paths.join_tours`` joins by
the turn, as the table below shows it pays; ``bench_build_time.py --peer`` with tours off
measures what the built ones give).
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

from bench_time_levers import bunny_layers  # noqa: E402

#: Turn bins (degrees) of the per-kind table.
TURNS = ((0, 60), (60, 120), (120, 240), (240, 361))


def direction(pts: np.ndarray, at_end: bool, span_mm: float = 1.0) -> np.ndarray | None:
    """Unit direction of travel over the first (or last) ``span_mm`` of a polyline."""
    p = pts[::-1] if at_end else pts
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    k = int(np.clip(np.searchsorted(arc, span_mm), 1, len(p) - 1))
    t = p[0] - p[k] if at_end else p[k] - p[0]
    n = float(np.linalg.norm(t))
    return t / n if n > 0 else None


def connector(a: np.ndarray, ta: np.ndarray, b: np.ndarray, tb: np.ndarray, handle: float,
              step_mm: float = 0.1) -> np.ndarray:
    """Inner points of a cubic Bezier from ``a`` (leaving along ``ta``) to ``b`` (arriving
    along ``tb``), handles ``handle`` x the gap long (at least 0.5 mm)."""
    h = max(handle * float(np.linalg.norm(b - a)), 0.5)
    ctrl = np.array([a, a + ta * h, b - tb * h, b])
    n = max(int(np.ceil((np.linalg.norm(b - a) + 2 * h) / step_mm)), 8)
    s = np.linspace(0.0, 1.0, n)[1:-1, None]
    return ((1 - s) ** 3 * ctrl[0] + 3 * (1 - s) ** 2 * s * ctrl[1]
            + 3 * (1 - s) * s * s * ctrl[2] + s ** 3 * ctrl[3])


def turn_deg(a: np.ndarray, ta: np.ndarray, b: np.ndarray, tb: np.ndarray) -> float:
    u = b - a
    n = float(np.linalg.norm(u))
    if n == 0:
        return float(np.degrees(np.arccos(np.clip(ta @ tb, -1, 1))))
    u = u / n
    return float(np.degrees(np.arccos(np.clip(ta @ u, -1, 1))
                            + np.arccos(np.clip(u @ tb, -1, 1))))


def joinable(paths, i: int) -> bool:
    """paths[i] is a travel move between two paths of one material and role."""
    if not 0 < i < len(paths) - 1 or paths[i].role != "travel":
        return False
    a, b = paths[i - 1], paths[i + 1]
    return a.role == b.role and a.role not in ("travel", "measure") and a.material == b.material


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", default="150,350,550,750,950")
    ap.add_argument("--handle", type=float, default=0.3,
                    help="connector handle length over the gap")
    args = ap.parse_args()
    from icefab.core import Toolpath
    from icefab.motion import plan_paths_durations

    print(f"machine: {os.cpu_count()}-core {platform.machine()}, Python "
          f"{platform.python_version()}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    # the paths apart, as before tours: each join measured on its own
    job, _stack, picks, layers = bunny_layers(
        args.layers, **{"materials.part.tour_max_turn_deg": 0.0,
                        "materials.scaffold.tour_max_turn_deg": 0.0})

    def joined(a, pts, layer):
        return Toolpath(pts, material=a.material, role=a.role, layer=layer)

    saved: dict[str, list[tuple[float, float]]] = defaultdict(list)
    apart_total = joined_total = 0.0
    for lp in layers:
        paths = list(lp.paths)
        apart = plan_paths_durations(paths, job, layer=lp.index)
        apart_total += float(apart.sum())
        chains: list = []      # the layer with every joinable run as one path
        i = 0
        while i < len(paths):
            p = paths[i]
            if joinable(paths, i) and chains and isinstance(chains[-1], tuple):
                a, pts = chains[-1]
                b = paths[i + 1]
                bp = b.polyline()
                ta, tb = direction(pts, True), direction(bp, False)
                if ta is not None and tb is not None:
                    c = connector(pts[-1], ta, bp[0], tb, args.handle)
                    # this join alone, against its three paths apart
                    ap_ = paths[i - 1].polyline()
                    ta1 = direction(ap_, True)
                    if ta1 is not None:
                        c1 = connector(ap_[-1], ta1, bp[0], tb, args.handle)
                        one = plan_paths_durations(
                            [joined(b, np.vstack([ap_, c1, bp]), lp.index)], job,
                            layer=lp.index)[0]
                        kind = (f"{b.material} {b.role}, "
                                f"{'closed' if paths[i - 1].closed else 'open'} -> "
                                f"{'closed' if b.closed else 'open'}")
                        saved[kind].append((float(apart[i - 1:i + 2].sum() - one),
                                            turn_deg(ap_[-1], ta1, bp[0], tb)))
                    chains[-1] = (a, np.vstack([pts, c, bp]))
                    i += 2
                    continue
            if p.role in ("travel", "measure"):
                chains.append(p)
            else:
                chains.append((p, p.polyline()))
            i += 1
        out = [joined(c[0], c[1], lp.index) if isinstance(c, tuple) else c for c in chains]
        joined_total += float(plan_paths_durations(out, job, layer=lp.index).sum())

    print(f"\nbunny layers {picks}, connector handles {args.handle:g} x the gap")
    print("| join | joins | s saved per join | joins losing time | "
          + " | ".join(f"turn {lo}-{min(hi, 360)} deg: joins, s saved" for lo, hi in TURNS)
          + " |")
    print("| --- | ---: | ---: | ---: |" + " ---: |" * len(TURNS))
    n_all = 0
    for kind, rows in sorted(saved.items(), key=lambda kv: -len(kv[1])):
        s, t = np.array(rows).T
        n_all += len(s)
        cells = []
        for lo, hi in TURNS:
            m = (t >= lo) & (t < hi)
            cells.append(f"{m.sum()}, {s[m].mean():.3f}" if m.any() else "0")
        print(f"| {kind} | {len(s)} | {s.mean():.3f} | {(s < 0).sum()} | "
              + " | ".join(cells) + " |")
    print(f"\nevery run joined: {joined_total:.1f} s against {apart_total:.1f} s apart "
          f"({joined_total / apart_total:.3f}), {n_all} joins, "
          f"{(apart_total - joined_total) / max(n_all, 1):.3f} s per join")
    gains = np.array([g for rows in saved.values() for g, _t in rows])
    best = float(gains[gains > 0].sum())
    print(f"only the joins that save time, one by one: {best:.1f} s "
          f"({(apart_total - best) / apart_total:.3f} of the time apart), {(gains > 0).sum()} "
          "joins")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
