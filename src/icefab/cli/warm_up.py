"""Compiling numba's kernels ahead of the first run (issue 10).

The editable install runs :func:`warm_up_main` (``tools/icefab_build.py``): a fresh
install's first ``icefab demo`` then loads its kernels from numba's cache instead of
compiling them for a minute.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import time

from icefab.cli import main
from icefab.cli.compiling import compile_notice

#: A tetrahedron in each text mesh format the readers take (their kernels compile on the
#: first file of each kind).
_TEXT_MESHES = {
    "warm.obj": "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 10\nf 1 3 2\nf 1 2 4\nf 1 4 3\n"
                "f 2 3 4\n",
    "warm.ply": "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n"
                "property float y\nproperty float z\nelement face 4\n"
                "property list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n"
                "0 10 0\n0 0 10\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",
}


def _gap_fill_kernels() -> None:
    """The gap fill's centre lines (medial axis, width runs) on a thin strip and a narrow
    ring: the mug's first layers may leave no gap that needs them (its smoothed fill
    rings meet closely), while a longer run does."""
    import numpy as np

    from icefab import geometry as geo
    from icefab.paths import centre_paths

    strip = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 0.8], [0.0, 1.2]])
    outer = np.array([[-10.0, -10.0], [10.0, -10.0], [10.0, 10.0], [-10.0, 10.0]])
    hole = (outer * 0.95)[::-1].copy()
    for rings in ([strip], [outer, hole]):
        region = geo.region_from_rings([r * 1.5 for r in rings])
        centre_paths(rings, 0.15, 3.0, 0.05, region)


def _pwm_widths_kernel() -> None:
    """PWM's widths (the demo's valves are FM)."""
    import numpy as np

    from icefab._pulses import pwm_widths_us

    pwm_widths_us(np.array([100.0, 700.0]), 500.0, 8000.0)


def warm_up() -> int:
    """Compile and cache the numba kernels of a first run; returns how many compiled.

    Runs what a newcomer runs first, small: ``icefab demo`` on the demo mug's first 8
    layers (4 on the simulator, SMF included) with one worker, so every stage's kernels
    compile with the argument types of a real run, reads its trajectory file back (the
    sample decoder's kernel), runs the gap fill's centre lines on a strip and a narrow ring,
    and reads the mug back as binary STL and a tetrahedron as OBJ and PLY (the mesh
    readers' kernels). Nothing is written
    outside a temporary folder but numba's cache (beside the sources, or
    ``NUMBA_CACHE_DIR``).
    """
    from icefab.mesh import load_mesh
    from icefab.resultfiles import load_trajectories

    notice_text = io.StringIO()
    with tempfile.TemporaryDirectory(prefix="icefab-warm-") as tmp, \
            compile_notice(notice_text) as notice:
        folder = os.path.join(tmp, "demo")
        job = os.path.join(tmp, "one-worker.toml")
        with open(job, "w", encoding="utf-8") as fh:
            fh.write("[cell]\ncpus = 1\n")  # the kernels compile in this process
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            code = main(["demo", "-c", job, "-o", folder, "--layers", "8",
                         "--sim-layers", "4"])
        if code:
            raise RuntimeError(f"icefab demo (warm-up) exited with {code}: {out.getvalue()}")
        load_trajectories(os.path.join(folder, "trajectories.npz"))
        _gap_fill_kernels()
        _pwm_widths_kernel()
        load_mesh(os.path.join(folder, "demo-mug.stl"))
        for name, text in _TEXT_MESHES.items():
            with open(os.path.join(tmp, name), "w", encoding="ascii") as fh:
                fh.write(text)
            load_mesh(os.path.join(tmp, name))
    return notice.kernels


def warm_up_main() -> None:
    """:func:`warm_up`, and one line on stdout saying what it did (the build backend's)."""
    t0 = time.perf_counter()
    n = warm_up()
    print(f"icefab: compiled {n} numba kernels ahead of the first run in "
          f"{time.perf_counter() - t0:.0f} s")
