"""Benchmark of the build simulator (icefab.sim) on the demo mug.

    python3 bench/bench_sim.py [--layers 100]

Prints, for the first N layers of the demo mug (default job: +10 % flow error, noise):
the time to prepare the layer plans, to simulate them open loop and with SMF (seconds
per layer), and the deposition of one layer compared with a peer measured in the same
run: the textbook raster approach (each segment's volume splatted at its midpoint into
an impulse image, then convolved with a disc of the path width, scipy.ndimage) — its
time, and how flat and how volume-true each leaves the layer.
"""
from __future__ import annotations

import argparse
import datetime
import platform
import time

import numpy as np
from scipy import ndimage


def _peer_deposit(z, origin, g, a, b, vol, half_w):
    """Impulse image at the segment midpoints (bilinear) convolved with a disc per width."""
    out = np.zeros_like(z)
    mid = 0.5 * (a + b)
    for hw in np.unique(half_w):
        sel = half_w == hw
        img = np.zeros_like(z)
        fx = (mid[sel, 0] - origin[0]) / g
        fy = (mid[sel, 1] - origin[1]) / g
        ix = np.floor(fx).astype(int)
        iy = np.floor(fy).astype(int)
        tx, ty = fx - ix, fy - iy
        v = vol[sel] / (g * g)
        for dx, dy, w in ((0, 0, (1 - tx) * (1 - ty)), (1, 0, tx * (1 - ty)),
                          (0, 1, (1 - tx) * ty), (1, 1, tx * ty)):
            np.add.at(img, (iy + dy, ix + dx), v * w)
        r = int(np.ceil(hw / g))
        yy, xx = np.mgrid[-r:r + 1, -r:r + 1] * g
        disc = (xx ** 2 + yy ** 2 <= hw ** 2).astype(float)
        out += ndimage.convolve(img, disc / disc.sum(), mode="constant")
    return z + out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--layers", type=int, default=100)
    ap.add_argument("--no-write", action="store_true", help="accepted for run_all.py; this "
                    "benchmark only prints (its figures are copied into BENCHMARKS.md by hand)")
    args, _ = ap.parse_known_args()
    from icefab import Job
    from icefab.demo import demo_mug
    from icefab.mesh import transform
    from icefab.paths import plan_paths
    from icefab.regions import add_scaffold
    from icefab.sim import plan_layer, simulate_build
    from icefab.sim.cell import grid_for
    from icefab.sim.deposition import _splat
    from icefab.slicing import slice_mesh
    from icefab.core import Stack

    job = Job()
    n = args.layers
    t0 = time.perf_counter()
    stack = add_scaffold(slice_mesh(transform(demo_mug(), job.parts), job), job)
    stack = Stack(layers=stack.layers[:n], job=job, layer_thickness=stack.layer_thickness)
    tp = plan_paths(stack, job)
    t_prep = time.perf_counter() - t0
    # warm up numba (compiled once, cached on disk)
    simulate_build(tp, job, layers=4, closed_loop=False)

    t0 = time.perf_counter()
    plans = [plan_layer(lp.index, lp.paths, job) for lp in tp.layers]
    t_plan = time.perf_counter() - t0
    t0 = time.perf_counter()
    open_loop = simulate_build(tp, job, closed_loop=False)
    t_open = time.perf_counter() - t0
    t0 = time.perf_counter()
    smf = simulate_build(tp, job, closed_loop=True)
    t_smf = time.perf_counter() - t0

    # one deposition: a wall layer of the mug (part + scaffold), mine vs the peer
    k = min(n - 1, 40)
    plan = plans[k]
    grid = grid_for([plan], job)
    dh = job.slicing.layer_thickness_mm
    times_me, times_peer = [], []
    for _ in range(3):
        z = np.zeros_like(grid.z)
        t0 = time.perf_counter()
        _splat(z, grid.origin, grid.spacing, plan.a, plan.b, plan.volume, plan.half_width,
               plan.n0, plan.n1, plan.ext)
        times_me.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        zp = _peer_deposit(np.zeros_like(grid.z), grid.origin, grid.spacing, plan.a, plan.b,
                           plan.volume, plan.half_width)
        times_peer.append(time.perf_counter() - t0)
    g2 = grid.spacing ** 2
    interior = ndimage.binary_erosion(z > 0.5 * dh, iterations=3)

    def flat(img):
        return float(np.sqrt(np.mean((img[interior] - dh) ** 2)))

    print(f"machine: 2-core {platform.machine()} {platform.processor() or '(processor n/a)'}, "
          f"{datetime.date.today()}")
    print(f"demo mug, first {n} layers ({open_loop.nominal_z[-1]:.1f} mm), "
          f"{sum(len(p.volume) for p in plans)} segments, grid {grid.spacing} mm")
    print(f"slice + scaffold + paths: {t_prep:.2f} s; layer plans: {t_plan:.2f} s")
    print(f"open loop: {t_open:.2f} s ({1000 * t_open / n:.0f} ms/layer); "
          f"SMF: {t_smf:.2f} s ({1000 * t_smf / n:.0f} ms/layer, "
          f"{len(smf.layers)} measurements)")
    print(f"final RMS height error: open loop {open_loop.rms[-1]:.3f} mm, SMF "
          f"{smf.rms[-1]:.3f} mm")
    me, peer = min(times_me), min(times_peer)
    print(f"deposit layer {plan.index} ({len(plan.volume)} segments): icefab {1000 * me:.1f} "
          f"ms, peer (impulse + disc convolution) {1000 * peer:.1f} ms, ratio "
          f"{peer / me:.2f}")
    print(f"  volume error: icefab {abs(z.sum() * g2 / plan.volume.sum() - 1):.1e}, peer "
          f"{abs(zp.sum() * g2 / plan.volume.sum() - 1):.1e}")
    print(f"  RMS deviation from the layer thickness inside the footprint: icefab "
          f"{flat(z):.4f} mm, peer {flat(zp):.4f} mm (dh = {dh} mm)")


if __name__ == "__main__":
    main()
