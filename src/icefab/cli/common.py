"""Helpers shared by the subcommands: the job option, progress lines, atomic output."""

from __future__ import annotations

import argparse
import dataclasses
import fcntl
import math
import os
import re
import shutil
import signal
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Iterator, NoReturn

import numpy as np

from icefab.config import Job, load_job, load_named_job
from icefab.atomic import fsync_path, fsync_tree, make_temp_dir, replace_durably
from icefab.errors import ConfigError, OutputError

if TYPE_CHECKING:
    from icefab.core import Mesh, Stack


def add_job_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("-c", "--job", metavar="JOB",
                        help="job settings: TOML file or the thesis' legacy control .txt file "
                             "(default: the Cobra 600 cell)")


def job_from_args(args: argparse.Namespace) -> Job:
    """The ``-c`` job, its unnamed settings the defaults (``Job()`` without ``-c``): for a
    command that starts from meshes. One that reads a result file: :func:`file_job`."""
    return load_job(args.job) if getattr(args, "job", None) else Job()


def file_job(made: Job, args: argparse.Namespace, source: str, remake: str,
             settings: tuple[str, ...] | None = None,
             error: type[Exception] = ConfigError) -> Job:
    """The job a command that reads a result file runs with: without ``-c``, the job the
    file was ``made`` with; with ``-c JOB``, that job overlaid with the settings the job
    file names (:func:`icefab.stages.overlay_job`: one among ``settings``, default
    ``icefab.stages.DECIDED``, that differs from the file's is ``error`` naming
    ``source``, the setting and ``remake``, the command that makes the file again)."""
    from icefab.stages import DECIDED, overlay_job

    if not getattr(args, "job", None):
        return made
    given, named = load_named_job(args.job)
    return overlay_job(made, given, named, source, remake,
                       DECIDED if settings is None else settings, error)


def command_inputs(given: list[str], job: Job, *, words: tuple[str, ...] = ()) -> list[str]:
    """A command's inputs: the MODEL arguments, or the job's ``parts.files`` when none are
    given (as ``icefab slice`` takes them; a legacy control file names its meshes). A result
    file (``.npz``) or one of ``words`` (``demo``) stands for the whole build and must be
    given alone: among mesh files it was read as a mesh ('unknown mesh format')."""
    if not given:
        if not job.parts.files:
            raise ConfigError("no input: give mesh file(s)" + "".join(
                f", '{w}'" for w in words) + " or a result .npz, or parts.files in the job "
                "file")
        return list(job.parts.files)
    if len(given) > 1:
        lone = [g for g in given if Path(g).suffix.lower() == ".npz" or g in words]
        if lone:
            raise ConfigError(f"{lone[0]}: give it alone; it holds the whole build, not one "
                              f"of several parts (inputs: {' '.join(given)})")
    return list(given)


def placed_model(model: list[str], job: Job) -> tuple["Mesh", Job]:
    """The mesh a command slices and its job: ``["demo"]`` is the built-in demo mug, other
    names are mesh files (they become the job's ``parts.files``); either is placed by the
    job and checked against the cell (:func:`icefab.mesh.place_mesh`). The README promised
    ``demo`` to slice, paths and plan, which read it as a file name."""
    from icefab import mesh as meshmod

    if model == ["demo"]:
        from icefab.demo import demo_mug

        return meshmod.place_mesh(demo_mug(), job), job
    files = tuple(str(Path(m).resolve()) for m in model)
    job = dataclasses.replace(job, parts=dataclasses.replace(job.parts, files=files))
    return meshmod.prepare_parts(job), job


def layer_numbers(text: str) -> list[int]:
    """The numbers of a ``--layers K,K,...`` option, in order (ValueError when an entry is
    not an integer)."""
    return [int(t) for t in text.replace(" ", "").split(",") if t]


def layer_list(text: str) -> str:
    """argparse ``type=`` of a ``--layers K,K,...`` option: the text, its syntax checked as
    the options are read (a docs hunt's 'icefab slice --layers a,b' was refused only after
    slicing); whether the numbers are layers needs the layer count (:func:`parse_layers`)."""
    try:
        ks = layer_numbers(text)
    except ValueError:
        ks = []
    if not ks:
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated layer numbers, "
                                         "e.g. 10,50,100")
    return text


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
        ks = layer_numbers(text)
    except ValueError:
        raise ConfigError(f"--layers {text!r}: expected comma-separated layer numbers, e.g. "
                          "10,50,100") from None
    bad = [k for k in ks if not 0 <= k < n]
    if bad or not ks:
        raise ConfigError(f"--layers {text!r}: layer numbers must be between 0 and {n - 1}")
    return list(dict.fromkeys(ks))   # a layer named twice is drawn once, in the given order


def check_layers_before_slicing(text: str | None, mesh: "Mesh", job: Job) -> None:
    """A ``--layers K,K,...`` option checked (:func:`parse_layers`) against the number of
    layers slicing the placed ``mesh`` with ``job`` will make, before it is sliced: 'icefab
    slice --layers 3,99' of a part of 40 layers was refused only after slicing it (a
    review's). Adaptive layers are counted by slicing alone: the option waits for it
    (:func:`icefab.slicing.layer_count`)."""
    from icefab.slicing import layer_count

    n = layer_count(mesh, job) if text else None
    if n is not None:
        parse_layers(text, n)


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main process as Ctrl-C is (``icefab.cli.main``, a build
    while it plans), so that a command's clean-up (its temporary result folder, the cell
    it started) runs as on Ctrl-C: a killed command had left its temporary folder of
    results behind (hunt P). Exit status 143."""


#: Whether this process was sent SIGTERM (:func:`terminate`).
_TERMINATED = [False]


def forked_end(pid: int) -> bool:
    """In a SIGTERM handler installed by process ``pid``: when this is a process forked
    from it (a pool worker before its initializer reset the handler), end it as SIGTERM
    ends a process and return True (the handler raised the command's Terminated in each
    worker, each printing a traceback); False in ``pid`` itself."""
    if os.getpid() == pid:
        return False
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    os.kill(os.getpid(), signal.SIGTERM)
    return True


def terminate() -> NoReturn:
    """Raise :class:`Terminated` from a SIGTERM handler, and remember it: a handler that
    runs inside a weakref callback or a ``__del__`` has its exception printed as
    "Exception ignored" and lost (Python's own import locks have such a callback), and
    the command went on: a build stopped at once planned on and '--stop' gave up after 60
    s (CI stop 48). :func:`check_terminated`, called by every :class:`Progress` and
    before a build makes its journal, raises it again; a build's runner takes it over as
    a stop (:func:`terminated`)."""
    _TERMINATED[0] = True
    raise Terminated()


def forget_terminated() -> None:
    """A new command in this process (:func:`icefab.cli.main`): no SIGTERM yet."""
    _TERMINATED[0] = False


def terminated() -> bool:
    """Whether this command's process was sent SIGTERM (:func:`terminate`)."""
    return _TERMINATED[0]


def check_terminated() -> None:
    """Raise :class:`Terminated` again when this process was sent SIGTERM
    (:func:`terminate`) and goes on working (its first one lost)."""
    if _TERMINATED[0]:
        raise Terminated()


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
        check_terminated()
        now = time.perf_counter()
        final = done >= total
        if not final and now - self._last < (0.1 if self.tty else self.interval_s):
            return
        self._last = now
        pct = 100.0 * done / total if total else 100.0
        text = f"{self.label}: {done}/{total} ({pct:.0f} %, {now - self._start:.1f} s)"
        try:
            if self.tty:
                self.stream.write("\r" + text + ("\n" if final else ""))
            else:
                self.stream.write(text + "\n")
            self.stream.flush()
        except OSError:   # stderr on a full disk ('2>/dev/full'): the job goes on (hunt P)
            self._last = math.inf


def hours(seconds: float) -> str:
    """``5.81 h`` (or ``42.0 min`` under an hour): build times as people read them."""
    return f"{seconds / 3600:.2f} h" if seconds >= 3600 else f"{seconds / 60:.1f} min"


def layer_thickness_text(stack: "Stack") -> str:
    """The stack's layer thickness, ``0.25 mm``, or with adaptive layers (their own
    thicknesses, ``slicing.cusp_height_mm``) their range, ``0.1 .. 0.5 mm (adaptive)``:
    the demo named the job's ``slicing.layer_thickness_mm`` for adaptive layers."""
    t = stack.thicknesses
    if len(t) and np.isfinite([L.thickness for L in stack]).any():
        lo, hi = f"{t.min():.3g}", f"{t.max():.3g}"
        return f"{lo} .. {hi} mm (adaptive)" if lo != hi else f"{lo} mm (adaptive)"
    return f"{stack.layer_thickness:g} mm"


#: How every command names the length / speed figure (paths, plan, demo): it is not a build
#: time a robot can achieve, so nothing is compared with it.
ESTIMATE_WORDS = ("path length / speed at the thesis' constant speeds, accelerations "
                  "ignored: a lower bound for constant speed, not a build time")


def compare_build_times(mtts_s: float, constant_s: float) -> str:
    """The one build-time comparison icefab makes, in words: minimum-time trajectories
    (MTTS) against the same paths planned at the thesis' constant speeds with the robot's
    accelerations (thesis 4.4); both are build motion times the robot can run."""
    if not (constant_s > 0 and mtts_s > 0):
        return "minimum-time vs constant speed: no motion to compare"
    change = 1.0 - mtts_s / constant_s
    how = (f"{100 * change:.0f} % shorter ({constant_s / mtts_s:.2f}x as fast)" if change >= 0
           else f"{-100 * change:.0f} % longer")
    return (f"minimum-time trajectories take {hours(mtts_s)}, the same paths at constant "
            f"speed {hours(constant_s)}: minimum-time is {how}")


def check_output_dir(path: str | os.PathLike) -> None:
    """OutputError when ``-o path`` names an existing file: checked before a command
    starts its work (``icefab.cli.main``) and again when the folder is made."""
    if not str(path):   # '' wrote into the current folder (hunt P)
        raise OutputError(f"-o {str(path)!r}: an empty folder name")
    if Path(path).is_symlink():   # refused when the results were put in place, as "not a
        # folder": the results move in by renames from beside it, the same file system
        raise OutputError(f"-o {path}: is a symbolic link; give the folder it points to "
                          f"({os.path.realpath(path)})")
    if Path(path).exists() and not Path(path).is_dir():
        raise OutputError(f"-o {path}: exists and is not a folder")
    # a file further up: 'afile/sub' was found only when the results were written
    for up in Path(path).parents:
        if up.exists():
            if not up.is_dir():
                raise OutputError(f"-o {path}: {up} is a file, not a folder")
            break
    # where the results are written (OUT, and beside it, where they wait until done):
    # a read-only folder was found only after all the work (hunt P)
    for folder in ([Path(path)] if Path(path).is_dir() else []) + [Path(path).parent]:
        while not folder.exists() and folder != folder.parent:
            folder = folder.parent
        if folder.is_dir() and not os.access(folder, os.W_OK | os.X_OK):
            raise OutputError(f"-o {path}: cannot write into {folder} (permission denied)")
        refused = _cannot_create_in(folder) if folder.is_dir() else None
        if refused:
            raise OutputError(f"-o {path}: cannot write into {folder} ({refused})")


def _cannot_create_in(folder: Path) -> str | None:
    """Why no folder can be made in ``folder`` (the reason, as the system gives it), or
    None: found by making one and removing it. ``os.access`` asks for permissions only,
    and root has them everywhere: '-o /proc/x' (a folder where nothing can be made), a
    read-only mount for root, were found only after all the work (a review's)."""
    try:
        probe = make_temp_dir(folder, f".icefab-probe-{os.getpid()}.")
    except OSError as exc:
        return exc.strerror or str(exc)
    try:
        probe.rmdir()
    except OSError:
        pass
    return None


#: Hidden folders beside OUT (``.OUT.icefab-PID.RANDOM``) hold a running command's results
#: until they are published; inside OUT, ``.icefab-backup-PID.RANDOM`` holds the files a
#: publish replaces until it has finished (for the roll-back).
_TEMP = ".icefab-"
_BACKUP = ".icefab-backup-"
#: At most this many characters of OUT's name go into its temporary folder's name: a
#: folder of a valid 240-character name was refused, its temporary one's name too long
#: for the file system (255 bytes; hunt P).
TEMP_STEM_CHARS = 100


def _stem(final: Path) -> str:
    return final.name[:TEMP_STEM_CHARS]


#: Temporary folders of icefab before it named them with their process (``.OUT.XXXXXXXX``
#: from ``tempfile.mkdtemp``) are removed once they are this old, seconds.
LEGACY_TEMP_AGE_S = 3600.0


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temporaries(final: Path) -> list[Path]:
    """Remove what killed icefab commands left beside and inside ``final``: temporary
    result folders (``.OUT.icefab-PID.RANDOM``) and publish backups
    (``OUT/.icefab-backup-PID.RANDOM``) whose process no longer runs, and the older
    ``.OUT.XXXXXXXX`` folders (no process recorded) once older than an hour.
    Returns the removed paths."""
    own = re.compile(rf"^\.{re.escape(_stem(final))}\.icefab-(\d+)\.[0-9a-f]{{8}}$")
    legacy = re.compile(rf"^\.{re.escape(final.name)}\.[a-z0-9_]{{8}}$")
    backup = re.compile(rf"^{re.escape(_BACKUP)}(\d+)\.[0-9a-f]{{8}}$")
    removed = []
    now = time.time()
    places = [(final.parent, own, True)] + ([(final, backup, False)] if final.is_dir() else [])
    for folder, pattern, legacy_too in places:
        try:
            entries = list(os.scandir(folder))
        except OSError:
            continue
        for entry in entries:
            if not entry.is_dir(follow_symlinks=False):
                continue
            m = pattern.match(entry.name)
            if m:
                stale = not _alive(int(m.group(1)))
            elif legacy_too and legacy.match(entry.name):
                try:
                    stale = now - entry.stat(follow_symlinks=False).st_mtime > LEGACY_TEMP_AGE_S
                except OSError:
                    stale = False
            else:
                continue
            if stale:
                shutil.rmtree(entry.path, ignore_errors=True)
                removed.append(Path(entry.path))
    return removed


@contextmanager
def _locked(folder: Path, final: Path) -> Iterator[None]:
    """Hold an exclusive lock for publishing into ``final``: a ``flock`` on its parent
    folder, so two commands never interleave their renames (whoever comes second waits,
    saying so once on stderr, and then publishes on top of the first's complete set)."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            sys.stderr.write(f"waiting for another icefab command writing into {folder} "
                             f"to finish...\n")
            sys.stderr.flush()
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # releases the lock


@contextmanager
def output_dir(path: str | os.PathLike, command: str) -> Iterator[Path]:
    """A folder whose new results appear at ``path`` only if the block succeeds.

    Files are written into a temporary sibling folder (``.OUT.icefab-PID.RANDOM``). On
    success it becomes ``path`` (which did not exist) or its files replace their
    namesakes in ``path``. What ``command`` wrote there last time and did not write
    again is removed (its names are kept in ``path/.icefab-COMMAND``), so an earlier run's
    G-code or pictures do not sit next to results they no longer match; every other file
    is left alone (the stack or toolpaths a command read from the same folder, the user's
    own files, another command's results).

    All or nothing, as the user sees ``path``: every obstacle (a file where a folder goes
    or the reverse, a symbolic link, a name another command's results use) is found
    before anything changes; replaced files are moved aside, not deleted, until the record
    ``.icefab-COMMAND`` is swapped in last, and any failure puts them back. Publishing
    holds a lock on the folder (:func:`_locked`); temporary folders that killed runs left
    are removed first (:func:`remove_stale_temporaries`). On failure nothing in ``path``
    changes and the temporary folder goes.
    Raises OutputError naming the user's path when ``path`` or a parent is a file, cannot
    be written or a result cannot be put in place.
    """
    final = Path(path)
    check_output_dir(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temporaries(final)
        tmp = make_temp_dir(final.parent, f".{_stem(final)}{_TEMP}{os.getpid()}.")
    except OSError as exc:
        raise OutputError(f"-o {final}: cannot create the output folder "
                          f"({exc.strerror or exc})") from None
    try:
        yield tmp
        with _locked(final.parent, final):
            _publish(tmp, final, command)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _kind(path: Path) -> str:
    if path.is_symlink():
        return "a symbolic link"
    if path.is_dir():
        return "a folder"
    return "a file" if path.exists() else "absent"


def _records(final: Path) -> dict[str, set[str]]:
    """The names each command's record in ``final`` lists: {command: names}."""
    out = {}
    for record in final.glob(".icefab-*"):
        if record.is_file() and not record.is_symlink() and \
                not record.name.startswith(_BACKUP):
            try:
                names = record.read_text(encoding="utf-8").splitlines()
            except (OSError, UnicodeDecodeError):
                continue
            out[record.name.removeprefix(".icefab-")] = set(names)
    return out


def _plain_name(name: str) -> bool:
    """A name a record may list for removal: a plain entry of the folder itself."""
    return name not in ("", ".", "..") and "/" not in name and "\0" not in name \
        and not name.startswith(".icefab-")


def _publish(tmp: Path, final: Path, command: str) -> None:
    """Move the results in ``tmp`` to ``final`` (see :func:`output_dir`)."""
    manifest = f".icefab-{command}"
    written = sorted(item.name for item in tmp.iterdir())
    (tmp / manifest).write_text("".join(f"{name}\n" for name in written), encoding="utf-8")
    if not final.exists() and not final.is_symlink():
        try:
            replace_durably(tmp, final)
        except OSError as exc:
            raise OutputError(f"{final}: cannot move the results into place "
                              f"({exc.strerror or exc})") from None
        return
    if final.is_symlink() or not final.is_dir():
        raise OutputError(f"-o {final}: exists and is not a folder")
    records = _records(final)
    before = records.pop(command, set())
    # every obstacle is found before anything changes
    for name in written:
        target, item = final / name, tmp / name
        for other, names in sorted(records.items()):
            if name in names and (target.exists() or target.is_symlink()):
                raise OutputError(f"{target}: written there by 'icefab {other}', which this "
                                  f"command would overwrite; write into another folder (-o)")
        have, want = _kind(target), _kind(item)
        if have == "a symbolic link" or (have != "absent" and have != want):
            raise OutputError(f"{target}: is {have}, where icefab writes {want}; move it "
                              f"away or write into another folder (-o)")
    stale = [n for n in sorted(before - set(written)) if _plain_name(n)
             and (final / n).exists() and not (final / n).is_symlink()]
    try:
        backup = make_temp_dir(final, f"{_BACKUP}{os.getpid()}.")
    except OSError as exc:
        raise OutputError(f"{final}: cannot write into the output folder "
                          f"({exc.strerror or exc})") from None
    moved_aside: list[str] = []   # old entries now in backup/
    placed: list[str] = []        # new entries now in final/
    current = ""
    try:
        # the new results on disk before any old one is moved aside (fsyncing the 1 200
        # valve files between the moves had kept the folder half-replaced for as long)
        for name in written + [manifest]:
            current = name
            fsync_tree(tmp / name) if (tmp / name).is_dir() else fsync_path(tmp / name)
        # Ctrl-C or SIGTERM while the entries move waits until they have (a hunt's
        # interrupt there left the old valve programs only in the backup, which the next
        # command removed); any other failure puts everything back
        with _signals_held():
            for name in written + [manifest]:   # the record last
                current = name
                target = final / name
                if target.exists():
                    os.rename(target, backup / name)
                    moved_aside.append(name)
                os.rename(tmp / name, target)
                placed.append(name)
            for name in stale:
                current = name
                os.rename(final / name, backup / name)
                moved_aside.append(name)
            fsync_path(final)
    except BaseException as exc:
        for name in reversed(placed):
            try:
                os.rename(final / name, tmp / name)
            except OSError:
                pass
        for name in reversed(moved_aside):
            try:
                os.rename(backup / name, final / name)
            except OSError:
                pass
        shutil.rmtree(backup, ignore_errors=True)
        if not isinstance(exc, OSError):
            raise
        raise OutputError(f"{final / current}: cannot put the result in place "
                          f"({exc.strerror or exc}); {final} is as it was") from None
    shutil.rmtree(backup, ignore_errors=True)


@contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT and SIGTERM held back for the block: one that comes meanwhile is raised
    again when it ends. The Python handlers are swapped, not the signal mask: the kernel
    gives a signal to any thread that does not block it (a thread writing a result file)
    and Python runs the handler in the main thread at once. Only in the main thread
    (where handlers are set); elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: list[int] = []
    old = {s: signal.signal(s, lambda signum, _frame: got.append(signum))
           for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, handler in old.items():
            signal.signal(s, handler)
        if got:
            signal.raise_signal(got[0])


def warnings_file(command: str) -> str:
    """``COMMAND-warnings.txt``: each command's own name, so two commands writing into
    one folder (slice, then paths) never replace each other's list."""
    from icefab.findings import WARNINGS_FILE

    return f"{command}-{WARNINGS_FILE}"


def warning_lines(warnings, command: str) -> list[str]:
    """The summary's warning lines: the count, then one line per kind with its count and
    layers (:func:`icefab.findings.summarise_warnings`), and where the full list is."""
    from icefab.findings import summarise_warnings

    if not warnings:
        return ["warnings: 0"]
    return ([f"warnings: {len(warnings)} (all in {warnings_file(command)}), by kind:"]
            + [f"  {line}" for line in summarise_warnings(warnings)])


def write_warnings(warnings, folder: Path, command: str) -> None:
    """The full list of ``warnings`` as ``folder/COMMAND-warnings.txt`` (the publishing
    folder of :func:`output_dir`, so it appears with the results or not at all); nothing
    when there are none."""
    from icefab.findings import warnings_text

    source = f"icefab {command}"
    if warnings:
        (folder / warnings_file(command)).write_text(warnings_text(warnings, source), encoding="utf-8")
