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

:mod:`icefab.cli.warm_up` compiles ahead of time what a first run needs (the editable
install runs it).
"""

from __future__ import annotations

import os
import sys
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
