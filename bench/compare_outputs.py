"""Digests of the demo pipeline's results, to prove a refactoring changed no output.

Runs the demo mug (``icefab demo``'s stages, default job) through slicing, scaffold, paths,
minimum-time trajectories and valve programs, plus a few simulator layers open loop and
with SMF, and prints one SHA-256 per stage over every array the stage produced (in
memory, in a fixed order, with dtype and shape) and per member of the saved npz files.

    python3 bench/compare_outputs.py --out digests.json            # record
    python3 bench/compare_outputs.py --against digests.json        # compare, exit 1 if not equal

Use only public entry points (``icefab.*`` and the stage modules' save functions) so the
same script runs on the code before and after a move. ``--layers N`` takes the first N
layers only (faster; the full mug is the default).
"""

from __future__ import annotations

import argparse
import hashlib
import importlib
import json
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np


def _feed(h, a) -> None:
    a = np.ascontiguousarray(a)
    h.update(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())


def _feed_region(h, region) -> None:
    _feed(h, np.asarray(region.parent))
    for r in region.rings:
        _feed(h, r)


def _path_fields(p) -> bytes:
    return repr((float(p.z), p.material, p.role, bool(p.closed), float(p.width), int(p.layer),
                 p.frame, p.tool)).encode()


def _npz_members(path: Path) -> dict[str, str]:
    out = {}
    with zipfile.ZipFile(path) as z:
        for name in sorted(z.namelist()):
            out[name] = hashlib.sha256(z.read(name)).hexdigest()[:16]
    return out


def run(layers: int, sim_layers: int) -> dict:
    import icefab
    stack_mod = importlib.import_module("icefab.slicing")
    paths_mod = importlib.import_module("icefab.paths")
    motion_mod = importlib.import_module("icefab.motion")
    flow_mod = importlib.import_module("icefab.flow")
    mesh_mod = importlib.import_module("icefab.mesh")

    job = icefab.Job()
    times = {}
    t0 = time.perf_counter()
    mesh = mesh_mod.transform(icefab.demo_mug(), job.parts)
    h = hashlib.sha256()
    _feed(h, mesh.vertices)
    _feed(h, mesh.faces)
    res = {"mesh": h.hexdigest()}

    stack = icefab.slice_mesh(mesh, job)
    if layers:
        stack = type(stack)(layers=stack.layers[:layers], job=stack.job,
                            layer_thickness=stack.layer_thickness, warnings=stack.warnings)
    stack = icefab.add_scaffold(stack, job)
    h = hashlib.sha256()
    h.update(repr((len(stack), stack.layer_thickness, stack.warnings)).encode())
    for layer in stack:
        h.update(repr((layer.index, layer.z, layer.top_z)).encode())
        _feed_region(h, layer.part)
        _feed_region(h, layer.scaffold)
    res["stack"] = h.hexdigest()
    times["slice+scaffold"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    tp = icefab.plan_paths(stack, job)
    h = hashlib.sha256()
    h.update(repr(tp.warnings).encode())
    for lp in tp:
        h.update(repr((lp.index, lp.z, lp.unfilled_mm2)).encode())
        for p in lp.paths:
            h.update(_path_fields(p))
            _feed(h, p.points)
    res["toolpaths"] = h.hexdigest()
    times["paths"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    motion = motion_mod.plan_toolpaths(tp, job)
    h = hashlib.sha256()
    for lm in motion.layers:
        h.update(repr(lm.index).encode())
        for tr in lm.trajectories:
            h.update(repr((tr.dt, tr.duration)).encode())
            for a in (tr.xy, tr.joints, tr.speed, tr.pieces):
                _feed(h, a)
            if tr.path is not None:
                h.update(_path_fields(tr.path))
    res["trajectories"] = h.hexdigest()
    times["trajectories"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    h = hashlib.sha256()
    n_prog = 0
    for lm in motion.layers:
        for tr in lm.trajectories:
            if tr.path is None or not tr.path.depositing:
                continue
            prog = flow_mod.plan_valves(tr, tr.path.material, job)
            for piece in flow_mod.program_pieces(prog):
                h.update(flow_mod.encode_valve_program(piece))
            h.update(repr(prog.warnings).encode())
            n_prog += 1
    res["valves"] = h.hexdigest()
    res["valve_programs"] = n_prog
    times["valves"] = time.perf_counter() - t0

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        stack_mod.save_stack(stack, tmp / "stack.npz")
        paths_mod.save_toolpaths(tp, tmp / "toolpaths.npz")
        motion_mod.save_trajectories(motion, tmp / "trajectories.npz")
        res["files"] = {name: _npz_members(tmp / name)
                        for name in ("stack.npz", "toolpaths.npz", "trajectories.npz")}

    if sim_layers:
        t0 = time.perf_counter()
        sim = importlib.import_module("icefab.sim")
        for closed in (False, True):
            r = sim.simulate_build(tp, job, layers=sim_layers, closed_loop=closed)
            h = hashlib.sha256()
            for a in (r.layers, r.nominal_z, r.rms, r.max_abs, r.rms_measured, r.height.z):
                _feed(h, a)
            for k in sorted(r.surfaces):
                _feed(h, r.surfaces[k].z)
            h.update(repr((r.volume_commanded, r.volume_deposited, r.flow_gain,
                           r.pulses)).encode())
            res["sim_smf" if closed else "sim_open"] = h.hexdigest()
        times["sim"] = time.perf_counter() - t0
    res["layers"] = len(stack)
    return res, times


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}/"))
        else:
            out[prefix + k] = v
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=0)
    ap.add_argument("--sim-layers", type=int, default=12)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--against", type=Path)
    args = ap.parse_args(argv)
    res, times = run(args.layers, args.sim_layers)
    res["settings"] = {"layers": args.layers, "sim_layers": args.sim_layers}
    for k, v in times.items():
        print(f"{k}: {v:.1f} s", file=sys.stderr)
    if args.out:
        args.out.write_text(json.dumps(res, indent=1, sort_keys=True) + "\n")
    if args.against:
        ref = _flatten(json.loads(args.against.read_text()))
        now = _flatten(res)
        bad = sorted(k for k in set(ref) | set(now) if ref.get(k) != now.get(k))
        n = len(set(ref) | set(now))
        if bad:
            for k in bad:
                print(f"DIFFERS {k}: {ref.get(k)} -> {now.get(k)}")
            return 1
        print(f"identical: {n} digests (stack, toolpaths, trajectories, valve programs, "
              f"simulator, npz members)")
    else:
        print(json.dumps(res, indent=1, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
