"""Helpers shared by the subcommands: the job option, progress lines, atomic output."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from icefab.config import Job, load_job
from icefab.atomic import DIR_MODE
from icefab.errors import ConfigError, OutputError


def add_job_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--job", metavar="JOB",
                        help="job settings: TOML file or the thesis' legacy control .txt file "
                             "(default: the Cobra 600 cell)")


def job_from_args(args: argparse.Namespace) -> Job:
    return load_job(args.job) if getattr(args, "job", None) else Job()


def parse_layers(text: str | None, n: int, default_count: int = 4) -> list[int]:
    """Layer indices from a ``--layers K,K,...`` option for a build of ``n`` layers.

    No option: ``default_count`` layers evenly spread from the first to the last. Raises
    ConfigError naming the option when an entry is not a number or not a layer.
    """
    if n == 0:
        return []
    if not text:
        count = min(default_count, n)
        return sorted(set(np.linspace(0, n - 1, count).round().astype(int).tolist()))
    try:
        ks = [int(t) for t in text.replace(" ", "").split(",") if t]
    except ValueError:
        raise ConfigError(f"--layers {text!r}: expected comma-separated layer numbers, e.g. "
                          "10,50,100") from None
    bad = [k for k in ks if not 0 <= k < n]
    if bad or not ks:
        raise ConfigError(f"--layers {text!r}: layer numbers must be between 0 and {n - 1}")
    return ks


class Progress:
    """Progress of a long stage on stderr: ``label: done/total``.

    On a terminal the line is rewritten in place; otherwise (CI, logs) a line is printed
    at most every ``interval_s`` seconds and at the end. Call it as ``progress(done, total)``.
    """

    def __init__(self, label: str, *, interval_s: float = 2.0, stream=None) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.interval_s = interval_s
        self._last = 0.0
        self._start = time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        final = done >= total
        if not final and now - self._last < (0.1 if self.tty else self.interval_s):
            return
        self._last = now
        pct = 100.0 * done / total if total else 100.0
        text = f"{self.label}: {done}/{total} ({pct:.0f} %, {now - self._start:.1f} s)"
        if self.tty:
            self.stream.write("\r" + text + ("\n" if final else ""))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()


def check_output_dir(path: str | os.PathLike) -> None:
    """OutputError when ``-o path`` names an existing file: checked before a command
    starts its work (``icefab.cli.main``) and again when the folder is made."""
    if Path(path).exists() and not Path(path).is_dir():
        raise OutputError(f"-o {path}: exists and is not a folder")


@contextmanager
def output_dir(path: str | os.PathLike, command: str) -> Iterator[Path]:
    """A folder whose new results appear at ``path`` only if the block succeeds.

    Files are written into a temporary sibling folder. On success it becomes ``path``
    (which did not exist) or its files replace their namesakes in ``path``, one rename
    each. What ``command`` wrote there last time and did not write again is removed (its
    names are kept in ``path/.icefab-COMMAND``), so an earlier run's G-code or pictures do
    not sit next to results they no longer match; every other file is left alone (the
    stack or toolpaths a command read from the same folder, the user's own files). On
    failure nothing in ``path`` changes and the temporary folder goes.
    Raises OutputError when ``path`` or a parent is a file or cannot be written.
    """
    final = Path(path)
    check_output_dir(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    except OSError as exc:
        raise OutputError(f"-o {final}: cannot create the output folder "
                          f"({exc.strerror or exc})") from None
    try:
        yield tmp
        _publish(tmp, final, f".icefab-{command}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _publish(tmp: Path, final: Path, manifest: str) -> None:
    """Move the results in ``tmp`` to ``final`` (see :func:`output_dir`)."""
    os.chmod(tmp, DIR_MODE)  # mkdtemp's 0700; what is inside was made with the umask
    written = sorted(item.name for item in tmp.iterdir())
    (tmp / manifest).write_text("".join(f"{name}\n" for name in written), encoding="utf-8")
    if not final.exists():
        tmp.rename(final)
        return
    record = final / manifest
    before = set(record.read_text(encoding="utf-8").splitlines()) if record.is_file() else set()
    for item in sorted(tmp.iterdir()):
        target = final / item.name
        if item.is_dir() and target.is_dir():
            shutil.rmtree(target)
        os.replace(item, target)
    for name in sorted(before - set(written)):
        stale = final / name
        if name in ("", ".", "..") or name != stale.name or name.startswith(".icefab-"):
            continue  # only plain names this command wrote into the folder itself
        if stale.is_dir() and not stale.is_symlink():
            shutil.rmtree(stale)
        elif stale.exists() or stale.is_symlink():
            stale.unlink()


def warning_lines(warnings) -> list[str]:
    """The summary's warning lines: the count, then one line per kind with its count and
    layers (:func:`icefab.findings.summarise_warnings`), and where the full list is."""
    from icefab.findings import WARNINGS_FILE, summarise_warnings

    if not warnings:
        return ["warnings: 0"]
    return ([f"warnings: {len(warnings)} (all in {WARNINGS_FILE}), by kind:"]
            + [f"  {line}" for line in summarise_warnings(warnings)])


def write_warnings(warnings, folder: Path, source: str = "") -> None:
    """The full list of ``warnings`` as ``folder/warnings.txt`` (the publishing folder of
    :func:`output_dir`, so it appears with the results or not at all); nothing when there
    are none."""
    from icefab.findings import WARNINGS_FILE, warnings_text

    if warnings:
        (folder / WARNINGS_FILE).write_text(warnings_text(warnings, source), encoding="utf-8")
