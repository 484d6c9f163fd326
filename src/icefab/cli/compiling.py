"""Saying plainly, on stderr, when a command waits for numba to compile.

icefab's kernels are compiled by numba on first use and cached beside the package
(``cache=True``), so the first run after installing (or changing) icefab spends tens of
seconds compiling before the stage's own progress moves; later runs load the cache. A
:class:`CompileNotice` listens to numba's compile events in the command's process and
writes one line when compiling starts, a progress line every ``interval_s`` while it goes
on, and a summary when the command ends (``compiled N kernels in S s``). Nothing is written
when every kernel came from the cache. The lines go to a terminal (a person waiting); when
stderr is a file or pipe they are written only with ``ICEFAB_COMPILE_NOTICE=1`` (logs and
tests that read stderr line by line see no extra lines on a cold cache). Pool workers compile
what they need themselves; their compiling shows as a slow first step of the stage's
progress.

:func:`warm_up` compiles ahead of time what a first run needs: the editable install runs
it (``tools/icefab_build.py``, through :func:`warm_up_main`), so a fresh install's first
``icefab demo`` loads its kernels instead of compiling them.
"""

from __future__ import annotations

import io
import os
import sys
import tempfile
import time
from contextlib import contextmanager
from typing import Iterator, TextIO

FIRST_LINE = ("compiling icefab's numba kernels (first run after installing or changing "
              "icefab; they are cached for later runs)...")


class CompileNotice:
    """Counts top-level numba compilations in this process and reports them on ``stream``."""

    def __init__(self, stream: TextIO | None = None, interval_s: float = 5.0) -> None:
        self.stream = stream or sys.stderr
        self.interval_s = interval_s
        self.pid = os.getpid()
        self.depth = 0
        self.kernels = 0
        self.seconds = 0.0
        self._t0 = 0.0
        self._last = 0.0

    def _say(self, text: str) -> None:
        self.stream.write(text + "\n")
        self.stream.flush()

    def on_start(self, event) -> None:  # numba.core.event.Listener protocol
        if os.getpid() != self.pid:
            return
        if self.depth == 0:
            now = time.perf_counter()
            self._t0 = now
            self.kernels += 1
            if self.kernels == 1:
                self._say(FIRST_LINE)
                self._last = now
            elif now - self._last >= self.interval_s:
                self._say(f"compiling: {self.kernels} kernels so far, "
                          f"{self.seconds:.0f} s")
                self._last = now
        self.depth += 1

    def on_end(self, event) -> None:
        if os.getpid() != self.pid:
            return
        self.depth = max(0, self.depth - 1)
        if self.depth == 0:
            self.seconds += time.perf_counter() - self._t0

    def summary(self) -> str | None:
        if not self.kernels:
            return None
        return (f"compiled {self.kernels} numba kernels in {self.seconds:.0f} s "
                f"(cached: later runs skip this)")


@contextmanager
def compile_notice(stream: TextIO | None = None, interval_s: float = 5.0
                   ) -> Iterator[CompileNotice]:
    """Report numba compilation on ``stream`` while the block runs (default: stderr, when
    it is a terminal or ``ICEFAB_COMPILE_NOTICE=1``; otherwise the block runs silently)."""
    notice = CompileNotice(stream, interval_s)
    if stream is None and not (sys.stderr.isatty()
                               or os.environ.get("ICEFAB_COMPILE_NOTICE") == "1"):
        yield notice
        return
    try:
        from numba.core import event
    except ImportError:  # pragma: no cover - numba is a dependency
        yield notice
        return

    class _Listener(event.Listener):
        def on_start(self, ev):
            notice.on_start(ev)

        def on_end(self, ev):
            notice.on_end(ev)

    with event.install_listener("numba:compile", _Listener()):
        yield notice
    line = notice.summary()
    if line:
        notice._say(line)


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


def warm_up() -> int:
    """Compile and cache the numba kernels of a first run; returns how many compiled.

    Runs what a newcomer runs first, small: ``icefab demo`` on the demo mug's first 8
    layers (4 on the simulator, SMF included) with one worker, so every stage's kernels
    compile with the argument types of a real run, and reads the mug back as binary STL
    and a tetrahedron as OBJ and PLY (the mesh readers' kernels). Nothing is written
    outside a temporary folder but numba's cache (beside the sources, or
    ``NUMBA_CACHE_DIR``).
    """
    from icefab.cli import main
    from icefab.mesh import load_mesh

    notice_text = io.StringIO()
    with tempfile.TemporaryDirectory(prefix="icefab-warm-") as tmp, \
            compile_notice(notice_text) as notice:
        folder = os.path.join(tmp, "demo")
        job = os.path.join(tmp, "one-worker.toml")
        with open(job, "w", encoding="utf-8") as fh:
            fh.write("[cell]\ncpus = 1\n")  # the kernels compile in this process
        out = io.StringIO()
        stdout, sys.stdout = sys.stdout, out
        try:
            code = main(["demo", "-c", job, "-o", folder, "--layers", "8",
                         "--sim-layers", "4"])
        finally:
            sys.stdout = stdout
        if code:
            raise RuntimeError(f"icefab demo (warm-up) exited with {code}: {out.getvalue()}")
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
