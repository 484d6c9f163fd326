"""Benchmark of minimum-time trajectory shaping (issue 4). One command:

    python3 bench/bench_motion.py [--layers-every K] [--toppra-sample N]

1. All paths of the 1 M-facet bunny at 300 mm (``bench/meshes.py``), both materials, with
   the job's paths (``icefab.paths``); the toolpaths are built once and cached in
   ``bench/.cache/`` under a key of the code, mesh and job that make them
   (``bench/_cache.py``; slicing + scaffold + paths take minutes).
   The bunny's footprint (302 x 235 mm) does not fit the default part origin (260, -100)
   (its near corner would be inside the 163 mm minimum reach), so the end-effector origin
   is moved to (340, 0) mm. MTTS (jerk on, the thesis' limits) on one core: output
   samples per CPU second, plus wall time on all cores.
2. TOPP-RA (the ``toppra`` package) timed on a seeded sample of the same paths with the
   jerk bounds off, next to MTTS on the same paths: time per path and duration agreement.
3. Build time against constant speed (thesis 4.4): the bunny, and a rounded box like
   thesis Fig. 4-15 (outer 150 x 110 mm with 20 mm rounds, inner boundary the Fig. 4-2
   outline, 20 mm tall) with straight-line (zigzag) fill at constant speed versus
   concentric fill with MTTS (the thesis: 11.6 h -> 2.6 h; concentric at constant
   25 mm/s: 7.4 h). The constant-speed cases are given twice: planned with the robot's
   accelerations (``icefab.motion.constant_speed_motion``: ramps, stops at split corners,
   as the thesis' robot ran them) and as length / speed
   (``icefab.paths.estimate_build_time``).

CPU time (``time.process_time``) is reported next to wall time: the benchmark machine is
shared, and per-core throughput is what the issue asks for.
"""
from __future__ import annotations

import argparse
import logging
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

from icefab import Job, Layer, Region, Stack  # noqa: E402
from icefab.errors import StackFileError  # noqa: E402
from icefab.motion import (constant_speed_motion, path_limits, pathsplit,  # noqa: E402
                           plan_motion, plan_paths_motion, plan_toolpaths, thesis_test_path)
from icefab.paths import (estimate_build_time, load_toolpaths, plan_paths,  # noqa: E402
                          save_toolpaths, to_base_frame)
from icefab.regions import add_scaffold  # noqa: E402

from _cache import PATHS_MODULES, cache_path, drop_stale, job_key  # noqa: E402

BUNNY_EE = (340.0, 0.0)


def _cached_toolpaths(path):
    """The cached toolpaths at ``path`` (see ``_cache.cache_path``: keyed by the code, mesh
    and job that make them) if they are there and readable; None otherwise."""
    if not path.exists():
        return None
    try:
        tp = load_toolpaths(path)
    except StackFileError as exc:
        print(f"cache not usable, rebuilding: {exc}", flush=True)
        return None
    return tp if tuple(tp.job.cell.ee_origin_mm) == BUNNY_EE else None


def _save_cache(tp, path):
    save_toolpaths(tp, path)
    drop_stale(path)


def bunny_job(pattern: str | None = None) -> Job:
    """The default job with the end-effector origin moved so the 300 mm bunny fits the
    reach, and optionally another fill pattern for both materials."""
    job = Job().replace(**{"cell.ee_origin_mm": list(BUNNY_EE)})
    if pattern is not None:
        job = job.replace(**{"materials.part.fill_pattern": pattern,
                             "materials.scaffold.fill_pattern": pattern})
    return job


def bunny_toolpaths():
    """The bunny's toolpaths with the default (concentric) fill, cached under
    ``bench/.cache/bunny-toolpaths-concentric-<key>.npz``."""
    from meshes import big_mesh
    mesh = big_mesh("bunny")
    job = bunny_job()
    path = cache_path("bunny-toolpaths-concentric", PATHS_MODULES, mesh, job_key(job, "paths"))
    tp = _cached_toolpaths(path)
    if tp is not None:
        return tp, 0.0

    from icefab.mesh import load_mesh
    from icefab.slicing import slice_mesh
    t0 = time.perf_counter()
    print("building bunny toolpaths (slice, scaffold, paths; cached afterwards) ...",
          flush=True)
    stack = add_scaffold(slice_mesh(load_mesh(mesh), job), job)
    tp = plan_paths(stack, job)
    _save_cache(tp, path)
    return tp, time.perf_counter() - t0


def bunny_zigzag_toolpaths():
    """The bunny's toolpaths with straight-line (zigzag) fill, for the thesis'
    constant-speed case, cached under ``bench/.cache/bunny-toolpaths-zigzag-<key>.npz``."""
    from meshes import big_mesh
    mesh = big_mesh("bunny")
    zjob = bunny_job("zigzag")
    path = cache_path("bunny-toolpaths-zigzag", PATHS_MODULES, mesh, job_key(zjob, "paths"))
    tp = _cached_toolpaths(path)
    if tp is not None:
        return tp, 0.0

    from icefab.mesh import load_mesh
    from icefab.slicing import slice_mesh
    t0 = time.perf_counter()
    print("building bunny zigzag toolpaths (cached afterwards) ...", flush=True)
    stack = slice_mesh(load_mesh(mesh), zjob)
    tp = plan_paths(add_scaffold(stack, zjob), zjob)
    _save_cache(tp, path)
    return tp, time.perf_counter() - t0


def rounded_rect(w, h, r, step=0.5):
    pts = []
    for cx, cy, a0 in ((w / 2 - r, -h / 2 + r, -90), (w / 2 - r, h / 2 - r, 0),
                       (-w / 2 + r, h / 2 - r, 90), (-w / 2 + r, -h / 2 + r, 180)):
        n = max(2, int(np.ceil(np.pi / 2 * r / step)) + 1)
        t = np.radians(np.linspace(a0, a0 + 90, n))
        pts.append(np.c_[cx + r * np.cos(t), cy + r * np.sin(t)])
    return np.concatenate(pts)


def rounded_box_toolpaths(job, height_mm=20.0):
    """Toolpaths of the Fig. 4-15-like box: every layer has the same region."""
    return plan_paths(rounded_box_stack(job, height_mm), job)


def rounded_box_stack(job, height_mm=20.0):
    """The Fig. 4-15-like box's stack, scaffold added: every layer has the same region."""
    outer = rounded_rect(150.0, 110.0, 20.0)
    hole = thesis_test_path((-50.0, -30.0), step_mm=0.5)[::-1].copy()
    region = Region(rings=(outer, hole), parent=np.array([-1, 0]))
    dz = job.slicing.layer_thickness_mm
    n = int(round(height_mm / dz))
    layers = tuple(Layer(index=i, z=(i + 0.5) * dz, part=region, top_z=(i + 1) * dz)
                   for i in range(n))
    stack = Stack(layers=layers, job=job, layer_thickness=dz)
    return add_scaffold(stack, job)


def toppra_duration(pts, job, robot, inscribed=True):
    from tests.test_motion_toppra import toppra_duration as f
    return f(pts, job, robot, inscribed=inscribed)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers-every", type=int, default=1,
                    help="plan every K-th bunny layer only (default: all)")
    ap.add_argument("--toppra-sample", type=int, default=40,
                    help="number of bunny paths timed with TOPP-RA")
    ap.add_argument("--smoothing", type=float, default=None,
                    help="motion.smoothing_tolerance_mm (default: the config default; "
                         "the cached toolpaths' job is not used for it)")
    ap.add_argument("--box-height", type=float, default=20.0, help="rounded box height, mm")
    args = ap.parse_args()
    logging.getLogger("toppra").setLevel(logging.ERROR)
    print(f"machine: {os.cpu_count()}-core {platform.processor() or platform.machine()}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")

    # ---------------------------------------------------------------- 1. bunny, MTTS
    tp, t_build = bunny_toolpaths()
    tol = Job().motion.smoothing_tolerance_mm if args.smoothing is None else args.smoothing
    tp = type(tp)(layers=tp.layers, warnings=tp.warnings, job=tp.job.replace(
        **{"motion.smoothing_tolerance_mm": tol}))
    print(f"path smoothing within {tol:g} mm" if tol else "path smoothing off")
    if t_build:
        print(f"bunny toolpaths built in {t_build:.0f} s")
    job = tp.job
    layers = tp.layers[::args.layers_every]
    n_paths = sum(len(lp.paths) for lp in layers)
    length_m = sum(p.length for lp in layers for p in lp.paths) / 1000.0
    print(f"bunny (1 111 216 facets, 300 mm): {len(layers)} layers, {n_paths} paths, "
          f"{length_m:.0f} m of path")
    plan_paths_motion(layers[0].paths[:20], job)  # compile / load the kernels
    c0, w0 = time.process_time(), time.perf_counter()
    n_out = 0
    mtts_time = 0.0
    for lp in layers:
        trs = plan_paths_motion(lp.paths, job, layer=lp.index)
        n_out += sum(len(t.xy) for t in trs)
        mtts_time += sum(t.duration for t in trs)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    rate = n_out / cpu
    print(f"MTTS, 1 core, jerk on: {n_out} samples in {cpu:.2f} s CPU ({wall:.2f} s wall) "
          f"-> {rate / 1e6:.2f} M samples/s/core (thesis: 14 M points in 20 min on 4 cores "
          f"= {14e6 / 1200 / 4:.0f} points/s/core)")
    # sampled kinematics of every 10th layer (finite differences at dt)
    import shapely

    from icefab.robots import get_robot
    fk = get_robot(job).fk
    acc_all, jerk_all, v_all = [], [], []
    dev = dev_q = 0.0
    for lp in layers[::10]:
        for t, p in zip(plan_paths_motion(lp.paths, job, layer=lp.index), lp.paths):
            if len(t.xy) > 1:
                line = shapely.LineString(to_base_frame(p.polyline(), p.tool_name, job))
                dev = max(dev, float(shapely.distance(shapely.points(t.xy), line).max()))
                dev_q = max(dev_q, float(shapely.distance(shapely.points(fk(t.joints)),
                                                          line).max()))
            if len(t.xy) > 3:
                v_all.append(np.hypot(*np.diff(t.xy, axis=0).T) / t.dt)
                acc_all.append(np.hypot(*np.diff(t.xy, 2, axis=0).T) / t.dt ** 2)
                jerk_all.append(np.hypot(*np.diff(t.xy, 3, axis=0).T) / t.dt ** 3)
    v_all, acc_all, jerk_all = (np.concatenate(x) for x in (v_all, acc_all, jerk_all))
    m = job.motion
    print(f"sampled kinematics (every 10th layer, {len(acc_all)} steps): speed max "
          f"{v_all.max():.1f} mm/s (bound {m.speed_mm_s:g}); total acceleration max "
          f"{acc_all.max():.0f}, 99.9 % {np.percentile(acc_all, 99.9):.0f} mm/s^2 (bound "
          f"{m.accel_mm_s2:g}); jerk median {np.median(jerk_all):.0f}, 99 % "
          f"{np.percentile(jerk_all, 99):.0f}, max {jerk_all.max():.0f} mm/s^3 (bound "
          f"{m.jerk_mm_s3:g}), {100 * np.mean(jerk_all > 1.2 * m.jerk_mm_s3):.2f} % of steps "
          f"above bound + 20 %; samples within {dev:.4f} mm of the input paths (smoothing "
          f"tolerance {m.smoothing_tolerance_mm:g} mm), the joints' forward kinematics "
          f"within {dev_q:.4f} mm (issue 4: 0.02 mm)")
    workers = os.cpu_count() or 1
    w0 = time.perf_counter()
    sub = type(tp)(layers=tuple(layers), job=job)
    motion = plan_toolpaths(sub, job.replace(**{"cell.cpus": workers}))
    wall_par = time.perf_counter() - w0
    print(f"MTTS, {workers} processes (plan_toolpaths): {wall_par:.2f} s wall, "
          f"{motion.n_points} samples")
    _, const = estimate_build_time(sub, job)
    vb = job.motion.boundary_speed_mm_s
    slow = job.replace(**{"motion.fill_speed_mm_s": vb})
    _, const25 = estimate_build_time(sub, slow)
    pjob = job.replace(**{"cell.cpus": workers})
    w0 = time.perf_counter()
    raw = plan_toolpaths(sub, pjob.replace(**{"motion.smoothing_tolerance_mm": 0.0})).duration
    cacc = constant_speed_motion(sub, pjob).duration
    cacc25 = constant_speed_motion(sub, pjob, fill_mm_s=vb).duration
    tpz, t_z = bunny_zigzag_toolpaths()
    zjob = tpz.job.replace(**{"motion.smoothing_tolerance_mm": tol, "cell.cpus": workers})
    subz = type(tpz)(layers=tpz.layers[::args.layers_every], job=zjob)
    czz = constant_speed_motion(subz, zjob).duration
    _, ezz = estimate_build_time(subz, zjob)
    print(f"bunny, zigzag fill (thesis' constant-speed technique: boundary {vb:g}, fill "
          f"{zjob.motion.fill_speed_mm_s:g} mm/s): planned with accelerations "
          f"{czz / 3600:.2f} h (MTTS on concentric paths {czz / mtts_time:.2f}x faster), "
          f"length / speed {ezz / 3600:.2f} h" + (f"  [toolpaths built in {t_z:.0f} s]"
                                                 if t_z else ""))
    print(f"bunny build time: MTTS {mtts_time / 3600:.2f} h (smoothing off: "
          f"{raw / 3600:.2f} h); constant speed (boundary "
          f"{vb:g}, fill {job.motion.fill_speed_mm_s:g} mm/s) planned with the robot's "
          f"accelerations {cacc / 3600:.2f} h (MTTS {cacc / mtts_time:.2f}x faster), "
          f"length / speed estimate {const / 3600:.2f} h; everything at {vb:g} mm/s (the "
          f"thesis' concentric case): planned {cacc25 / 3600:.2f} h (MTTS "
          f"{cacc25 / mtts_time:.2f}x faster), estimate {const25 / 3600:.2f} h  "
          f"[{time.perf_counter() - w0:.0f} s]")

    # ---------------------------------------------------------------- 2. TOPP-RA sample
    # Same geometry for both: TOPP-RA needs a twice-differentiable path, so it gets its
    # cubic spline through each piece's 0.4 mm grid; MTTS plans that spline sampled every
    # 0.02 mm (at dt 4 ms, so rounding to whole steps stays small). Timing: TOPP-RA per
    # path vs MTTS on the path as it is (the real workload).
    import toppra as ta

    from icefab.robots import get_robot
    # smoothing off: both solvers get the same spline (MTTS would smooth it again)
    job_nj = job.replace(**{"motion.jerk_limited": False, "motion.dt_s": 0.004,
                            "motion.smoothing_tolerance_mm": 0.0})
    robot = get_robot(job_nj)
    rng = np.random.default_rng(7)
    cands = [p for lp in tp.layers for p in lp.paths
             if p.role in ("boundary", "fill") and 20.0 < p.length < 400.0]
    pick = [cands[i] for i in rng.choice(len(cands), size=min(args.toppra_sample,
                                                               len(cands)), replace=False)]
    base = [to_base_frame(p.polyline(), p.tool_name, job) for p in pick]
    t_top, t_m, ratios = 0.0, 0.0, []
    failed = 0
    for p, pts in zip(pick, base):
        jb = job_nj.replace(**{"motion.speed_mm_s": path_limits(p, job_nj)})
        c = time.process_time()
        plan_motion(pts, job.replace(**{"motion.speed_mm_s": path_limits(p, job),
                                        "motion.jerk_limited": False}))
        t_m += time.process_time() - c
        dur_top = dur_m = 0.0
        try:
            for piece in pathsplit(pts, jb):
                c = time.process_time()
                dur_top += toppra_duration(piece, jb, robot)
                t_top += time.process_time() - c
                sg = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(piece, axis=0).T))])
                dense = ta.SplineInterpolator(sg, piece)(
                    np.linspace(0.0, sg[-1], max(3, int(sg[-1] / 0.02) + 1)))
                dur_m += plan_motion(dense, jb.replace(**{"motion.smooth_angle_deg": 179.0})
                                     ).duration
        except RuntimeError:
            failed += 1
            continue
        ratios.append(dur_m / dur_top)
    ratios = np.array(ratios)
    print(f"TOPP-RA on {len(pick)} bunny paths (jerk off, inscribed 64-gon): "
          f"{t_top / len(pick) * 1e3:.1f} ms CPU/path vs MTTS {t_m / len(pick) * 1e3:.2f} ms "
          f"CPU/path (MTTS {t_top / max(t_m, 1e-9):.0f}x faster); duration MTTS/TOPP-RA on "
          f"the same spline: median {np.median(ratios):.4f}, range "
          f"{ratios.min():.4f}..{ratios.max():.4f}"
          + (f", TOPP-RA failed on {failed}" if failed else ""))
    jon = sum(plan_motion(pts, job.replace(**{"motion.speed_mm_s": path_limits(p, job)})
                          ).duration for p, pts in zip(pick, base))
    joff = sum(plan_motion(pts, job.replace(**{"motion.speed_mm_s": path_limits(p, job),
                                               "motion.jerk_limited": False})).duration
               for p, pts in zip(pick, base))
    print(f"jerk bounds on these paths: {jon:.1f} s vs {joff:.1f} s off "
          f"(+{100 * (jon / joff - 1):.1f} %)")

    # ---------------------------------------------------------------- 3. rounded box
    bjob = Job().replace(**{"motion.smoothing_tolerance_mm": tol})
    box_const_job = bjob.replace(**{"materials.part.fill_pattern": "zigzag",
                                    "materials.scaffold.fill_pattern": "zigzag"})
    c0 = time.perf_counter()
    tp_zz = rounded_box_toolpaths(box_const_job, args.box_height)
    tp_cc = rounded_box_toolpaths(bjob, args.box_height)
    _, const_zz = estimate_build_time(tp_zz, box_const_job)
    conc_const = bjob.replace(**{"motion.fill_speed_mm_s": bjob.motion.boundary_speed_mm_s})
    _, const_cc = estimate_build_time(tp_cc, conc_const)
    pj = {"cell.cpus": workers}
    m_cc = plan_toolpaths(tp_cc, bjob.replace(**pj))
    m_zz = plan_toolpaths(tp_zz, box_const_job.replace(**pj))
    m_raw = plan_toolpaths(tp_cc, bjob.replace(**pj, **{"motion.smoothing_tolerance_mm": 0.0}))
    a_zz = constant_speed_motion(tp_zz, box_const_job.replace(**pj)).duration
    a_cc = constant_speed_motion(tp_cc, bjob.replace(**pj),
                                 fill_mm_s=bjob.motion.boundary_speed_mm_s).duration
    h = 3600.0
    print(f"rounded box (Fig. 4-15 like, {len(tp_cc)} layers)  [{time.perf_counter() - c0:.0f} s]"
          f"\n  constant speed, zigzag fill (boundary 25, fill 125 mm/s): planned with "
          f"accelerations {a_zz / h:.2f} h, length / speed {const_zz / h:.2f} h  (thesis 11.6 h)"
          f"\n  constant 25 mm/s, concentric fill: planned {a_cc / h:.2f} h, length / speed "
          f"{const_cc / h:.2f} h  (thesis 7.4 h)"
          f"\n  MTTS, concentric fill {m_cc.duration / h:.2f} h (thesis 2.6 h; smoothing off "
          f"{m_raw.duration / h:.2f} h); MTTS, zigzag {m_zz.duration / h:.2f} h"
          f"\n  MTTS vs constant-speed zigzag planned: {a_zz / m_cc.duration:.1f}x (thesis "
          f"4.5x); vs concentric at 25 mm/s: {a_cc / m_cc.duration:.1f}x (thesis 2.8x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
