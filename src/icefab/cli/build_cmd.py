"""``icefab build``: a closed-loop build on a cell that survives crashes (thesis 2.5).

* ``icefab build INPUT... [-c JOB] -o BUILD --virtual|--cell ENDPOINTS [--layers N]``:
  INPUT is mesh file(s), ``demo``, a toolpaths or a trajectories file (as for
  ``icefab simulate``); the trajectories of the first N layers are planned once and kept
  in ``BUILD/trajectories.npz``. ``--virtual`` starts a virtual cell as its own process
  with its state in ``BUILD/cell/`` (killing the build leaves it running);
  ``--cell ENDPOINTS`` uses a cell already running (its ``endpoints.json``).
* ``icefab build --resume BUILD``: after a crash, power cut, ``--stop`` or Ctrl-C:
  reconnect, ask the cell what it completed, carry on so that every path is deposited
  exactly once. A complete build: nothing to resume (exit 0, nothing contacted or
  written). INPUT and ``-c JOB`` are checked against the journal's digests; ``--cell``
  names the build's cell's endpoints anew; ``--virtual`` only on a virtual build (whose
  resume restarts its virtual cell); ``--layers`` is refused.
* ``icefab build --status BUILD [--json]``; ``icefab build --stop BUILD`` (valves off
  first, robot to its safe point, journaled); Ctrl-C does the same.

Refused before anything moves (exit 2, one line): options of a new build or a resume
with ``--status`` or ``--stop``, a BUILD that holds a journal already
(resume it), inputs or job changed since the journal (digests), a part taller than the
vertical stroke (210 mm) or out of reach (checked when planning), a cell that does not
answer its handshake. Files: :mod:`icefab.build`.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import json
import math
import os
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

from icefab.atomic import remove_temps
from icefab.cli.common import (add_job_argument, check_terminated, command_inputs,
                               forked_end, job_from_args, terminated, terminate)
from icefab.errors import CellError, ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "build", help="run a closed-loop build on a cell, crash-safe (journal, resume)",
        description="Build layer by layer on a cell (virtual or real): trajectories, valve "
                    "programs, measurement every n_d layers, SMF; every command journaled "
                    "before it is sent (BUILD/journal.sqlite) so a build resumes after a "
                    "crash with every path deposited exactly once.")
    p.add_argument("input", nargs="*", metavar="INPUT",
                   help="mesh file(s), 'demo', a toolpaths .npz or a trajectories .npz")
    add_job_argument(p)
    p.add_argument("-o", "--out", metavar="BUILD", help="build folder (new build)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--virtual", action="store_true",
                       help="start a virtual cell process with its state in BUILD/cell")
    where.add_argument("--cell", metavar="ENDPOINTS",
                       help="a running cell's endpoints.json")
    p.add_argument("--layers", type=int, metavar="N", help="build only the first N layers")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--resume", metavar="BUILD", help="resume the build in BUILD")
    mode.add_argument("--status", metavar="BUILD", help="show the state of the build")
    mode.add_argument("--stop", metavar="BUILD", help="stop the build: valves off first, "
                                                     "robot to its safe point")
    p.add_argument("--json", action="store_true", help="--status as JSON")
    p.add_argument("--cell-lost-record", action="store_true",
                   help="with --resume: the cell lost its record of completed paths (a new "
                        "state folder, its controller restarted) but its platform holds the "
                        "part: the journal's record stands, a path sent but not confirmed "
                        "counts as cut (not run again)")
    p.add_argument("--platform-cleared", action="store_true",
                   help="the cell ran an earlier build and its platform has been cleared "
                        "since: build on it (refused without this: the nozzle would run "
                        "into the earlier build's ice)")
    # the virtual cell's speed (icefab cell serve --time-factor): tests that kill it mid-path
    p.add_argument("--cell-time-factor", type=float, default=0.0, help=argparse.SUPPRESS)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.json and not args.status:   # it was ignored (a docs hunt's)
        raise ConfigError("--json goes with --status BUILD")
    if args.status or args.stop:
        mode = "--status" if args.status else "--stop"
        extra = _new_build_options(args)
        if extra:   # they were ignored without a word (a reviewer's)
            raise ConfigError(f"{mode} BUILD takes none of {', '.join(extra)}: they "
                              "start a build or resume one")
    if args.status:
        return _status(Path(args.status), args.json)
    if args.stop:
        return _stop(Path(args.stop))
    if args.cell_lost_record and not args.resume:
        raise ConfigError("--cell-lost-record goes with --resume BUILD")
    if args.platform_cleared and args.virtual:
        raise ConfigError("--platform-cleared goes with --cell ENDPOINTS: a new virtual "
                          "cell's platform is empty")
    if args.resume:
        if args.out:
            raise ConfigError("--resume BUILD and -o BUILD: give one of them")
        if args.layers is not None:
            # a resumed build is the build that was started (a tester's --layers 3 was
            # ignored and all 12 layers built)
            raise ConfigError(f"--resume {args.resume} --layers {args.layers}: --layers "
                              "starts a new build; a resumed build keeps its layers")
        with _build_process(Path(args.resume), new=False) as ctl:
            return _run(Path(args.resume), args, ctl, resume=True)
    if not args.out:
        raise ConfigError("-o BUILD is required for a new build (or --resume/--status/--stop "
                          "BUILD)")
    if args.layers is not None and args.layers < 1:
        raise ConfigError(f"--layers {args.layers}: expected a number >= 1")
    with _build_process(Path(args.out), new=True) as ctl:
        # no INPUT: the job's own parts (parts.files; a legacy control file names them)
        args.input = command_inputs(args.input, job_from_args(args), words=("demo",))
        if not (args.virtual or args.cell):
            raise ConfigError("choose the cell: --virtual (start one) or --cell ENDPOINTS")
        if args.cell:
            from icefab.linkedcell import load_endpoints

            ends = load_endpoints(args.cell)   # a bad file is said before any planning
            if not args.platform_cleared:
                _refuse_a_used_cell(ends)
        return _run(Path(args.out), args, ctl, resume=False)


# --------------------------------------------------------------------------- helpers


def _refuse_a_used_cell(ends: dict) -> None:
    """Refuse, before the part is planned (minutes for a large one), a cell that ran an
    earlier build (:func:`icefab.build.check_cell_numbers`), asking its robot alone. A
    robot that does not answer within a few seconds is left to the build's own link
    (its faults and waits): this only saves the planning, the build checks again."""
    from icefab import build as bmod
    from icefab.cell.robot import RobotLink

    try:
        with RobotLink.connect(ends["robot"]["host"], ends["robot"]["port"],
                               timeout_s=5.0) as link:
            link.hello()
            st = link.status()
    except CellError:
        return
    bmod.check_cell_numbers(max(st["last_done"], st["cut"]))


def _new_build_options(args: argparse.Namespace) -> list[str]:
    """The options given that start or resume a build, as the user typed them (for a
    refusal where they would do nothing: with --status and --stop)."""
    given = [("INPUT", bool(args.input)), ("-o", bool(args.out)), ("-c", bool(args.job)),
             ("--virtual", args.virtual), ("--cell", bool(args.cell)),
             ("--layers", args.layers is not None),
             ("--cell-lost-record", args.cell_lost_record),
             ("--platform-cleared", args.platform_cleared)]
    return [name for name, on in given if on]


def resume_cell_refusal(build: Path, journal_cell: str, virtual: bool) -> str | None:
    """Why ``--resume BUILD --virtual`` cannot be done, or None: a resume goes on on the
    cell whose platform holds the part. ``journal_cell``: the journal's ``cell`` ("virtual"
    or the endpoints file the build started with). A virtual build's resume restarts its
    own virtual cell, so --virtual there says what happens; on any other build it was
    ignored without a word and the resume went to the build's cell (a reviewer's)."""
    if not virtual or journal_cell == "virtual":
        return None
    return (f"{build} was built on the cell of {journal_cell}: a resume goes on on that "
            "cell (its platform holds the part), not on a new virtual one; drop --virtual "
            "(--cell ENDPOINTS if that cell's endpoints file moved)")


def stop_asked_by(signum: int | None, requested: bool) -> str | None:
    """Who asked the build to stop, in its stop's words, or None when no one did:
    ``requested`` (``BUILD/stop.request``) is ``icefab build --stop``'s, which sends
    SIGTERM too; ``signum`` the signal the build caught (SIGINT: Ctrl-C). The stop said
    "a stop was asked for" to all three alike (a reviewer's)."""
    if requested:
        return "'icefab build --stop' asked for it"
    if signum == signal.SIGINT:
        return "Ctrl-C"
    if signum is not None:
        return f"{signal.Signals(signum).name} received"
    return None


def journal_complete(journal) -> bool:
    """Whether the build's journal says it completed (the runner's "complete" event,
    journaled after its last layer)."""
    return any(e["kind"] == "complete" for e in journal.events())


#: The journal's name for the digest of the valves' calibration tables: the job names
#: their files, and a table changed between a crash and the resume re-planned every
#: program and was refused as "not deterministic" (a tester's).
CALIBRATION_DIGEST = "the calibration tables (materials.*.calibration_file)"


def _calibration_digest(job) -> str:
    from icefab.journal import digest_file, digest_text

    parts = []
    for m in ("part", "scaffold"):
        name = job.materials[m].calibration_file
        if name:
            f = Path(name)
            parts.append(f"{m}:{digest_file(f) if f.is_file() else 'missing ' + name}")
    return digest_text("|".join(parts))


def _input_digest(inputs: list[str]) -> str:
    from icefab.journal import digest_file, digest_text

    parts = []
    for name in inputs:
        if name == "demo":
            parts.append("demo")
        else:
            f = Path(name)
            if not f.is_file():
                raise ConfigError(f"{f}: input file not found")
            parts.append(f"{f.name}:{digest_file(f)}")
    return digest_text("|".join(parts))


def _plan(args: argparse.Namespace, out: Path):
    """The job and a warning for each path whose flow with SMF's full correction the
    valve cannot give (:func:`icefab.headroom.headroom_findings`: there the valve
    saturates the correction and the build goes on), after writing the trajectories of
    the layers to build to ``out`` (a trajectories file), planned layer by layer as they
    stream into it: a 1 M-facet part's build never holds its samples in memory (issue
    17)."""
    from icefab.cli.common import Progress
    from icefab.cli.simulate_cmd import load_build
    from icefab.core import Toolpaths
    from icefab.headroom import (beyond_valve, beyond_valve_refusal, headroom_findings,
                                 stored_layer_headroom, tightest)
    from icefab.motion import BuildMotion, TrajectoryFile, TrajectoryWriter, iter_plan_toolpaths
    from icefab.robots import get_robot
    from icefab.stages import check_agrees, settings_up_to

    ns = argparse.Namespace(job=args.job, flow_error=None, seed=None, deposition="valves",
                            layers=args.layers or 0)
    given = job_from_args(args)
    if given.slicing.cusp_height_mm > 0 and not str(args.input[0]).lower().endswith(".npz"):
        # a mesh sliced into adaptive layers would be refused after slicing, paths and
        # planning (check_build): the job alone decides it
        raise ConfigError(f"slicing.cusp_height_mm = {given.slicing.cusp_height_mm:g}: "
                          "adaptive layers, which the build runner does not run yet; "
                          "simulate them ('icefab simulate') or build with "
                          "slicing.cusp_height_mm = 0")
    from icefab import build as bmod
    from icefab.feedback import gains_verdict

    if not str(args.input[0]).lower().endswith(".npz"):
        bmod.check_build_robot(given)   # a mesh's job decides it: before slicing it
    verdict = gains_verdict(given)
    if verdict is not None and verdict[0] == "grows":
        # check_build refuses them too, after slicing, paths and planning (a mug's 500
        # layers: a user's minute lost); the job's gains are the build's whatever its input
        raise ConfigError(f"{verdict[1]}; refused before anything moves")
    build, job = load_build(list(args.input), given, ns)
    bmod.check_build_robot(job)   # a result file's job: before its paths are planned
    n = min(args.layers or len(build), len(build))
    if isinstance(build, BuildMotion) and args.job:
        # what the trajectories were planned with holds: a -c job's other speed was
        # recorded in BUILD/job.toml, named by the warnings, and had no effect (a tester's)
        check_agrees(build.job, job, f"{args.input[0]}: the trajectories",
                     "icefab plan, or build from the toolpaths or the mesh",
                     settings=settings_up_to("motion", job))
    if isinstance(build, BuildMotion):  # kept with the job it was planned with
        planned, robot, joints, layers = build.job, build.robot, build.joint_names, \
            build.layers[:n]
    else:
        r = get_robot(job)
        planned, robot, joints = job, r.name, r.joint_names
        layers = iter_plan_toolpaths(Toolpaths(layers=tuple(build.layers[:n]), job=build.job),
                                     job, progress=Progress("trajectories"))
    room: list = []
    over: list = []   # each layer's paths beyond the valve, in build order
    with TrajectoryWriter(out, planned, robot, joints) as w:
        for lm in layers:
            w.add(lm)
            mine = stored_layer_headroom(lm, job)
            room = tightest(room + mine)
            over += beyond_valve(mine)
    with TrajectoryFile(out) as f:
        if not f.depositing().any():
            raise ConfigError(f"{args.input[0]}: nothing to deposit in the first {n} layers")
    if over and job.flow.out_of_range == "error":
        # before anything moves: a build stopped at this layer's valve programs with half
        # the part deposited, and every resume stopped there again (a tester's)
        raise ConfigError(beyond_valve_refusal(over, job))
    return job, [f"warning: {line}" for line in headroom_findings(room, job)]


def _box(motion, job):
    """Part-frame box (lo, hi) of every deposition and measurement point, mm."""
    import numpy as np

    from icefab import flow

    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for lm in motion.layers:  # one layer's points at a time (35 M samples on the bunny)
        for tr in lm.trajectories:
            p = tr.path
            if p is None or len(tr.xy) == 0 or p.role == "travel":
                continue
            tool = "laser" if p.role == "measure" else p.material
            pts = flow.trajectory_part_xy(tr, tool, job)
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
    return lo, hi


def _shutdown_cell(cdir: Path) -> None:
    """End the virtual cell process serving ``cdir`` if one runs."""
    from icefab.linkedcell import shutdown_virtual_cell

    shutdown_virtual_cell(cdir)


def _process_marker(build: Path) -> Path:
    return build.parent / f".{build.name}.icefab-build"


@contextlib.contextmanager
def _build_process(build: Path, *, new: bool):
    """For the whole life of a build or resume of ``build``: a marker beside the folder
    holding this process' id, so that ``--stop`` and ``--status`` find the process from
    its first instant (a --stop in the first second of a build, before any marker or
    journal, said "no build journal here" and the build ran to its end; one sent while a
    resume started read the stopped run's status, said no build ran, and the resume
    deleted its request: a hunt's). A new build into a folder whose parent is missing
    makes the parent first (it had no marker at all; an empty one goes again).

    SIGTERM (what --stop sends) raises :class:`Terminated` while the build is prepared
    (the temporary plan removed, a started virtual cell shut down, as Ctrl-C does: SIGINT
    is ignored in a build started in the background of a non-interactive shell); once
    the runner is in charge (``ctl["runner"]``) it only sets ``ctl["signal"]``, which the
    runner's stop check reads, so the tool is lifted and the build stops between
    commands. Yields ``ctl``."""
    ctl = {"runner": False, "signal": None}
    pid = os.getpid()

    def on_term(signum, frame):
        if forked_end(pid):
            return
        if ctl["runner"]:
            ctl["signal"] = signum
        else:
            terminate()

    old = signal.signal(signal.SIGTERM, on_term)   # the handler first, then the marker
    made: list[Path] = []
    try:
        if new:
            p = build.absolute().parent
            while not p.exists():
                made.append(p)
                p = p.parent
            try:
                for d in reversed(made):
                    d.mkdir()
            except OSError:    # the build's own mkdir says why, as before
                pass
        _claim_marker(build)
        yield ctl
    finally:
        # a stop at any instant, the marker's claim included (a hunt's SIGTERM then left
        # it and the parents behind): the marker goes if it is this process'
        signal.signal(signal.SIGTERM, old)
        _release_marker(build)
        for d in made:     # deepest first; a folder that holds the build stays
            try:
                d.rmdir()
            except OSError:
                break


def _hand_over(ctl: dict) -> None:
    """From here a stop is the runner's (the tool lifted, between commands): SIGTERM only
    sets ``ctl["signal"]``. One sent before whose Terminated was lost (see
    :func:`icefab.cli.common.terminate`: as the journal was made, a build ran all its
    paths and exited 0) is the runner's too: it stops at its first check."""
    ctl["runner"] = True
    if terminated():
        ctl["signal"] = signal.SIGTERM


def _claim_marker(build: Path) -> None:
    """Put this process' id into the marker of ``build`` and hold the marker locked
    (flock) until :func:`_release_marker`: the kernel drops the lock when the process
    ends, however it ends (killed, the PC restarted), so a locked marker is a running
    build and an unlocked one a killed build's, whatever process has that id since
    (after a restart of the PC, --status called a crashed build "running" because its
    id was another program's, and --stop sent SIGTERM to any program with "build" in its
    command line). Written and locked under another name, then linked into place, so
    that it never exists without its id and its lock. Nothing when the folder cannot
    hold it. ConfigError when another build process of ``build`` holds it: a second
    'icefab build -o B' or '--resume B' wrote its own id over the running one's, was
    refused, and removed the marker as it left, and --stop then found no build (hunt
    Y). A marker whose process is gone is taken over."""
    global _MARKER_FD
    marker = _process_marker(build)
    tmp = marker.with_name(f"{marker.name}.{os.getpid()}")
    try:
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o644)
    except OSError:        # an unwritable or missing parent: nothing to find it by
        return
    try:
        os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)   # a new file: never refused
        except OSError:    # a file system without locks: the id alone tells (_alive)
            pass
        for _ in range(2):
            try:
                os.link(tmp, marker)
                break
            except FileExistsError:
                pid = _build_pid(build)   # removes a stale one
                if pid is not None:
                    raise _running_already(build, pid) from None
            except OSError:   # a file system without hard links: written in place
                os.close(fd)
                fd = -1
                fd = _claim_in_place(build, marker)
                break
        else:
            raise ConfigError(f"{build}: {marker} keeps coming back; another build of this "
                              f"folder is starting ('icefab build --status {build}')")
        _MARKER_FD, fd = fd, -1
    finally:
        if fd >= 0:
            os.close(fd)
        tmp.unlink(missing_ok=True)


def _claim_in_place(build: Path, marker: Path) -> int:
    """The marker opened and locked in place (no hard links): locked first, then its id
    written. Locked by another process: ConfigError (it was truncated and written first,
    and a second build took a running one's marker and removed it as it left: a hunt's).
    Returns the open file."""
    fd = os.open(marker, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise _running_already(build, os.read(fd, 64).decode("ascii", "replace").strip()
                                   ) from None
        except OSError:   # no locks either: the id alone tells (_alive)
            pass
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode("ascii"))
        return fd
    except BaseException:
        os.close(fd)
        raise


def _running_already(build: Path, pid: int | str | None = None) -> ConfigError:
    """The refusal of a second build or resume of ``build`` (``pid``: the running one's)."""
    process = f"process {pid}; " if pid is not None else ""
    return ConfigError(f"{build}: a build is running for this folder already ({process}"
                       f"'icefab build --status {build}')")


#: The open, locked marker of this process' build (:func:`_claim_marker`), or None.
_MARKER_FD: int | None = None
#: The open, locked ``BUILD/build.lock`` of this process' runner (:func:`_lock`), or None.
_LOCK_FD: int | None = None


def _forget_locks_in_child() -> None:
    """A forked child (a planning pool's worker) closes its copies of the marker and the
    folder's lock: a lock is the open file's, and a worker left behind by a killed build
    would keep both, the build "running" and a resume refused. Closing a copy does not
    unlock the parent's."""
    global _MARKER_FD, _LOCK_FD
    for fd in (_MARKER_FD, _LOCK_FD):
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass
    _MARKER_FD = _LOCK_FD = None


os.register_at_fork(after_in_child=_forget_locks_in_child)


def _release_marker(build: Path) -> None:
    """Remove the marker of ``build`` if this process claimed it (it holds it open and its
    id is in it), then let go of its lock."""
    global _MARKER_FD
    marker = _process_marker(build)
    try:
        if _MARKER_FD is not None \
                and int(marker.read_text(encoding="utf-8").strip()) == os.getpid():
            marker.unlink(missing_ok=True)
    except (OSError, ValueError):
        pass
    if _MARKER_FD is not None:
        os.close(_MARKER_FD)
        _MARKER_FD = None


def _build_pid(build: Path) -> int | None:
    """The id of the build or resume process running for ``build`` (its marker, locked
    by that process), or None; a marker whose process is gone (killed, or the PC
    restarted since) is removed."""
    marker = _process_marker(build)
    try:
        fd = os.open(marker, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        try:
            pid = int(os.read(fd, 64).decode("ascii").strip())
        except (OSError, ValueError):
            pid = None
        if pid is not None and _alive(fd, pid):
            return pid
        if pid is None and _held(fd):   # being claimed in place: locked, its id not yet in
            return None                  # (a look then removed a live build's marker)
        try:    # stale; the same file still (a new build may have just taken its place)
            if os.stat(marker).st_ino == os.fstat(fd).st_ino:
                marker.unlink(missing_ok=True)
        except OSError:
            pass
        return None
    finally:
        os.close(fd)


def _held(fd: int) -> bool | None:
    """Whether another open file holds a lock on the file open as ``fd``; None where the
    file system has no locks."""
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return None
    fcntl.flock(fd, fcntl.LOCK_UN)
    return False


def _alive(fd: int, pid: int) -> bool:
    """Whether the marker open as ``fd`` (holding ``pid``) is held by its build: locked.
    A file system without locks: whether ``pid`` runs as an icefab build."""
    held = _held(fd)
    return _build_running(pid) if held is None else held


def _build_running(pid: int) -> bool:
    """Whether process ``pid`` runs as an icefab build: not gone, not a zombie its parent
    has not reaped yet (an empty command line), not a killed build's id now another
    program's (no /proc: taken as running). A guess: the marker's lock is the answer
    (:func:`_alive`) where the file system has locks."""
    try:
        os.kill(pid, 0)
    except OSError:
        return False
    try:
        return b"build" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except FileNotFoundError:
        return not Path("/proc/self").exists()
    except OSError:
        return False


def _stop_orphan_cell(build: Path) -> bool:
    """A build killed (-9) while it started its virtual cell, before its journal existed,
    left the cell running and no journal to find it by (``--stop`` said "no build journal
    here", and the cell and its firmware ran on). End that cell; True when there was one.
    Nothing was sent to it: a new ``icefab build`` with the same -o starts afresh."""
    from icefab import build as bmod
    from icefab.linkedcell import cell_alive

    cdir = build / bmod.CELL_DIR
    if not cdir.is_dir() or not cell_alive(cdir):
        return False
    _shutdown_cell(cdir)
    print(f"{build}: a build killed while it was starting left its virtual cell running: "
          "stopped it; no path had been sent to it (start the build again)")
    return True


def _lock(build: Path):
    """``BUILD/build.lock``, locked (flock) by the build's runner for its whole run: the
    kernel drops the lock with the process, however it ends, so --status tells a running
    build from a killed one by it (:func:`_folder_locked`). A --status looking (it holds
    the lock shared for an instant) is waited out for a second."""
    global _LOCK_FD
    f = open(build / "build.lock", "a+")
    deadline = time.monotonic() + 1.0
    while True:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
            _LOCK_FD = f.fileno()    # closed in forked children (_forget_locks_in_child)
            return f
        except BlockingIOError:
            if time.monotonic() < deadline:
                time.sleep(0.02)
                continue
        except OSError:   # a file system without locks: the marker and the journal guard
            return f
        f.close()
        raise _running_already(build) from None


def _unlock(f) -> None:
    """Close the folder's lock of :func:`_lock` (its descriptor's number is free again:
    no forked child closes it any more)."""
    global _LOCK_FD
    if _LOCK_FD == f.fileno():
        _LOCK_FD = None
    f.close()


def _folder_locked(build: Path) -> bool | None:
    """Whether a build's runner holds ``BUILD/build.lock`` (:func:`_lock`): True while
    it runs, False once it ended, however (killed, the PC restarted: its process id may
    be another program's by then), None where the file system has no locks."""
    try:
        fd = os.open(build / "build.lock", os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return False
    try:
        return _held(fd)
    finally:
        os.close(fd)


def _connector(build: Path, args: argparse.Namespace, meta: dict, job):
    """A function that returns a new :class:`~icefab.linkedcell.LinkedCell`: on the
    virtual cell of ``BUILD/cell`` (started as its own process when it does not run: at
    the start, after it was killed) or on the cell of an endpoints file."""
    from icefab import build as bmod
    from icefab.linkedcell import (LinkedCell, cell_alive, load_endpoints,
                                        start_virtual_cell)

    if meta.get("cell") == "virtual":
        cdir = build / bmod.CELL_DIR
        factor = float(meta.get("cell_time_factor", 0.0))

        def connect():
            if not cell_alive(cdir):
                start_virtual_cell(cdir, build / "job.toml", build / bmod.TRAJECTORIES,
                                   time_factor=factor)
            return LinkedCell(load_endpoints(cdir), job)
        return connect
    endpoints = Path(args.cell) if getattr(args, "cell", None) else Path(meta["cell"])
    return lambda: LinkedCell(load_endpoints(endpoints), job)


# --------------------------------------------------------------------------- run


def _run(build: Path, args: argparse.Namespace, ctl: dict, *, resume: bool) -> int:
    from icefab import build as bmod
    from icefab.config import load_job, to_toml
    from icefab.journal import (Journal, JournalError, digest_file, digest_text,
                                remove_files)
    from icefab.motion import TrajectoryFile, open_trajectories

    jpath = build / bmod.JOURNAL
    if resume:
        job = load_job(build / "job.toml", stored=True)
        # a gantry build started before icefab refused one: before the journal is opened
        bmod.check_build_robot(job)
        journal = Journal.open(jpath)
        meta = journal.meta()
        digests = {"job": digest_file(build / "job.toml"),
                   "trajectories": digest_file(build / bmod.TRAJECTORIES)}
        if args.job:
            digests["job"] = digest_text(to_toml(load_job(args.job)))
        if args.input:
            digests["input"] = _input_digest(list(args.input))
        if CALIBRATION_DIGEST in meta.get("digests", {}):   # builds started since it is kept
            digests[CALIBRATION_DIGEST] = _calibration_digest(job)
        journal.check_digests(digests)
        refusal = resume_cell_refusal(build, str(meta.get("cell")), args.virtual)
        if refusal is not None:
            journal.close()
            raise ConfigError(refusal)
        if journal_complete(journal):
            # nothing to send: a resume of a complete build waited for its cell (gone
            # with it) and, stopped, turned "complete" into "stopped" (a reviewer's)
            journal.close()
            print(f"{build}: build complete, nothing to resume ('icefab build --status "
                  f"{build}')")
            return 0
        motion = open_trajectories(build / bmod.TRAJECTORIES)  # a block at a time
        if args.cell:
            meta["cell"] = str(Path(args.cell).resolve())
        lock = _lock(build)
        # a killed run's half-written report or status, never renamed into place (a
        # crash hunt's .report.html.<hex>.tmp): no other writer holds the lock
        remove_temps(build)
        journal.add_indexes()     # a journal of an earlier icefab (the lock is ours)
        # a request left by the stop that ended the last run; this process' marker was
        # written first, so a --stop from now on signals it (ctl) and is not lost
        (build / bmod.STOP_REQUEST).unlink(missing_ok=True)
        journal.event("resume", "resumed")
        _hand_over(ctl)
    else:
        if jpath.exists():
            raise ConfigError(f"{build}: holds a build journal already: resume it with "
                              f"'icefab build --resume {build}' or choose another -o")
        in_digest = _input_digest(list(args.input))
        with tempfile.TemporaryDirectory(prefix="icefab-build-plan-") as tmp:
            planned = Path(tmp) / bmod.TRAJECTORIES
            job, room_warnings = _plan(args, planned)
            with TrajectoryFile(planned) as f:
                bmod.check_build(f.motion(), job, f.n_layers)
            created = not build.exists()
            build.mkdir(parents=True, exist_ok=True)
            lock = _lock(build)
            if jpath.exists():
                # another build started here while this one planned (a hunt's second
                # build deleted the first one's cell and wrote over its job and
                # trajectories, then failed at the journal)
                _unlock(lock)
                raise ConfigError(f"{build}: another build started in this folder while "
                                  f"this one was planning: resume it with 'icefab build "
                                  f"--resume {build}' or choose another -o")
            cdir = build / bmod.CELL_DIR
            if cdir.is_dir():
                # a start killed before its journal existed: nothing was sent; start afresh
                _shutdown_cell(cdir)
                shutil.rmtree(cdir)
            job_toml = to_toml(job)
            (build / "job.toml").write_text(job_toml, encoding="utf-8")
            shutil.move(planned, build / bmod.TRAJECTORIES)
        motion = open_trajectories(build / bmod.TRAJECTORIES)
        meta = {"cell": "virtual" if args.virtual else str(Path(args.cell).resolve()),
                "cell_time_factor": args.cell_time_factor, "layers": len(motion.layers),
                "layer_indices": [int(lm.index) for lm in motion.layers],
                "measured_layers": [int(lm.index) for lm in motion.layers
                                    if bmod.measures(lm)],
                "inputs": list(args.input),
                "digests": {"input": in_digest, "job": digest_file(build / "job.toml"),
                            "trajectories": digest_file(build / bmod.TRAJECTORIES),
                            CALIBRATION_DIGEST: _calibration_digest(job)}}
        connect = _connector(build, args, meta, job)
        cell = journal = None
        try:
            cell = connect()
            cell.hello()                      # the handshake, before anything is journaled
            cell.check_paths(motion)
            st = cell.status()
            if not st.prepared:
                lo, hi = _box(motion, job)
                cell.prepare(job_toml, tuple(lo), tuple(hi))
            check_terminated()    # a SIGTERM whose Terminated was lost (terminate)
            # what the cell had completed before this build: in the journal's first write,
            # so a journal that later lost its records is told (bmod.CELL_DONE_AT_START)
            meta[bmod.CELL_DONE_AT_START] = max(int(st.last_done), int(st.cut))
            # a cell that ran an earlier build: refused here, before anything is written
            bmod.check_cell_numbers(meta[bmod.CELL_DONE_AT_START], args.platform_cleared)
            if args.platform_cleared:
                meta[bmod.PLATFORM_CLEARED] = True
            # whole or absent (Journal.create); a stop until it exists undoes all this
            journal = Journal.create(jpath, meta)
        except BaseException:   # Ctrl-C or --stop too
            # nothing of a build that never started stays behind (README: output folders
            # only on success): a refused cell left the folder with its lock file, and a
            # stop as the journal was renamed into place left it alone there (hunt Y)
            if cell is not None:
                cell.close()
            if journal is not None:
                journal.close()
            remove_files(jpath)
            if args.virtual:
                _shutdown_cell(build / bmod.CELL_DIR)
                shutil.rmtree(build / bmod.CELL_DIR, ignore_errors=True)
            (build / "job.toml").unlink(missing_ok=True)
            (build / bmod.TRAJECTORIES).unlink(missing_ok=True)
            _unlock(lock)
            (build / "build.lock").unlink(missing_ok=True)
            if created:
                try:
                    build.rmdir()
                except OSError:   # something else was put there meanwhile: keep it
                    pass
            raise
        _hand_over(ctl)
        n = len(motion.layers)
        journal.event("start", f"build of {n} layer{'s' if n != 1 else ''} on "
                      f"{'a virtual cell' if args.virtual else meta['cell']}")
        for line in room_warnings:   # once the build starts (a refusal is one line)
            journal.event("headroom", line)
            print(line, file=sys.stderr)
        cell.close()
    connect = _connector(build, args, meta, job)

    def on_signal(signum, frame):
        ctl["signal"] = signum

    old = {signal.SIGINT: signal.signal(signal.SIGINT, on_signal)}   # SIGTERM: ctl's
    last = [0.0]
    tty = sys.stderr.isatty()

    def on_progress(p):
        now = time.monotonic()
        if now - last[0] < (0.2 if tty else 2.0) and p.state == "running":
            return
        last[0] = now
        line = bmod.progress_line(p)
        if tty:
            sys.stderr.write(_console_line(line, shutil.get_terminal_size((80, 24)).columns))
        else:
            sys.stderr.write(line + "\n")
        sys.stderr.flush()

    runner = bmod.Runner(build, motion, job, journal, connect, on_progress=on_progress,
                         should_stop=lambda: stop_asked_by(
                             ctl["signal"], (build / bmod.STOP_REQUEST).exists()),
                         accept_cell_reset=args.cell_lost_record,
                         platform_cleared=args.platform_cleared)
    cdir = build / bmod.CELL_DIR
    # a resume whose virtual cell has no surface starts a new one: if the runner then
    # refuses it (the cell lost its record), that cell goes with the refusal (a tester's
    # stayed running on an empty folder, in the way of moving the old cell back)
    fresh_cell = meta.get("cell") == "virtual" and not (cdir / "surface.npz").exists()
    try:
        p = runner.run()
    except JournalError:
        if fresh_cell and not args.cell_lost_record:
            _shutdown_cell(cdir)
            shutil.rmtree(cdir, ignore_errors=True)
        raise
    except bmod.BuildStopped as exc:
        if tty:
            sys.stderr.write("\n")
        print(f"icefab build: {exc}", file=sys.stderr)
        # not 0: a supervisor told a stopped build from a complete one by its words only
        # (hunt P); 130 as Ctrl-C, 143 as SIGTERM (what --stop sends)
        return 130 if ctl["signal"] == signal.SIGINT else 143
    except Exception as exc:
        try:
            runner.fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
        except Exception:     # the journal or folder itself may be what failed
            pass
        raise
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        journal.close()
        _unlock(lock)
    if tty:
        sys.stderr.write("\n")
    if meta.get("cell") == "virtual":
        _shutdown_cell(build / bmod.CELL_DIR)   # the build is complete: the cell may go
    rms = f"{p.last_rms_mm:.3f} mm" if math.isfinite(p.last_rms_mm) else "-"
    done = Journal.open(build / bmod.JOURNAL)
    try:
        notes, warns = _completion_notes(done)
    finally:
        done.close()
    for line in notes:
        print(f"note: {line}")
    for line in warns:
        print(f"warning: {line}", file=sys.stderr)
    print(f"build complete: {p.layers} layer{'s' if p.layers != 1 else ''}, {p.paths_done} "
          f"paths, last measured RMS {rms}; "
          f"{build / bmod.REPORT}")
    return 0


def _console_line(line: str, width: int) -> str:
    """A progress line drawn over the last one on a terminal ``width`` columns wide: cut
    to the width and the rest of the row erased (a shorter line left a link fault's words
    behind it on the screen, a longer one wrapped over rows ``\\r`` does not go back
    to: a hunt's)."""
    return "\r" + line[:max(width - 1, 20)] + "\x1b[K"


def _completion_notes(journal) -> tuple[list[str], list[str]]:
    """The notes and warnings a completed build ends with, from its journal: a cell that
    ran another build first; volume the valve did not give; paths a cell fault cut short
    (the last line said '199 paths' with one of them cut, a hunt's); measurement paths the
    laser gave nothing for (the build ran open loop there and said nothing, a hunt's)."""
    notes, warns = [], []
    events = journal.events()
    for ev in events:
        if ev["kind"] == "cell-numbers":
            notes.append(ev["text"])
        elif ev["kind"] in ("clamp", "cell-fault"):
            warns.append(ev["text"])
    blind = sorted({ev["layer"] for ev in events if ev["kind"] == "measurement"
                    and "gave no laser samples" in ev["text"]})
    if blind:
        more = ", ..." if len(blind) > 10 else ""
        warns.append(f"{len(blind)} of {len(journal.measured_layers())} measured layers had "
                     f"a measurement path the laser gave no samples for (layers "
                     f"{', '.join(map(str, blind[:10]))}{more}): SMF did not correct from "
                     "what it missed; check the laser")
    return notes, warns


# --------------------------------------------------------------------------- status, stop


def _status(build: Path, as_json: bool) -> int:
    from icefab import build as bmod
    from icefab.journal import Journal

    f = build / bmod.STATUS
    pid = _build_pid(build)
    if pid is not None and _read_status(build).get("pid") != pid:
        # planning, starting its cell, or a resume reconnecting: its runner has not
        # written a status yet (it said "no build journal here", or the last run's
        # "stopped", a hunt's)
        if as_json:   # the keys of every state (a program's d["paths_done"] failed)
            print(json.dumps({**{k: None for k in bmod.STATUS_KEYS}, "state": "preparing",
                              "pid": pid, "rms": [], "events": []}, indent=1))
        else:
            print(f"{build}: being prepared (process {pid}): planning, starting its cell or "
                  "reconnecting to it")
        return 0
    if not f.is_file():
        Journal.open(build / bmod.JOURNAL).close()   # names the folder when it is no build
        raise ConfigError(f"{build}: no status yet (the build has not started a layer)")
    st = json.loads(f.read_text(encoding="utf-8"))
    # its runner's lock, not its process id: after a restart of the PC the id of a build
    # that died with it was another program's, and the build read "running"
    alive = _folder_locked(build)
    if alive is None:
        try:
            alive = _build_running(int(st.get("pid", -1)))
        except (TypeError, ValueError):
            alive = False
    if st["state"] == "running" and not alive:
        st["state"] = "interrupted"   # a token for programs; the line says what to do
        st["update_by"] = None        # no update comes
        st["eta_wall_s"] = None       # no pace: nothing runs
        # status.json is written at most once a second: the journal is the record of what
        # was done (a killed build's status said 38 paths where 66 were done)
        journal = Journal.open(build / bmod.JOURNAL)
        try:
            st["paths_done"] = journal.paths_done()
            meta = journal.meta()
            # the runner's rule: a build killed in its measurement goes on with that layer
            measures = set(meta.get("measured_layers", ()))
            measured, cut = journal.measured_layers(), journal.cut_layers()
            ended = set(journal.layers_done())
            done = {L for L in ended
                    if bmod.layer_finished(L, ended, measured, L in measures, cut)}
            st["layers_done"] = len(done)
            # and the layer it goes on with (the status may still name one it finished)
            order = meta.get("layer_indices")
            if order and st["layer"] in done:
                st["layer"] = next((L for L in order if L not in done), order[-1])
        finally:
            journal.close()
    if as_json:
        print(json.dumps(st, indent=1))
        return 0
    rms = "-" if st["last_rms_mm"] is None else f"{st['last_rms_mm']:.3f} mm"
    state = st["state"] + (" (resume with --resume)" if st["state"] == "interrupted" else "")
    print(f"{build}: {state}; "
          f"layer {bmod.layer_place(st['layer'], st['layers_done'], st['layers'])}, paths "
          f"{st['paths_done']}/{st['paths']}, "
          f"{bmod.eta_text(st['eta_s'], st.get('eta_wall_s'))}, last RMS {rms}")
    if st.get("waiting") and alive:
        print(f"  waiting for the cell: {st['waiting']}")
    if alive and st.get("update_by") is not None and time.time() > st["update_by"]:
        # the process holds its lock but wrote no status when it was due: it hangs (a
        # cell that answers nothing within its timeouts is reported as a link fault)
        print(f"  no status since {time.strftime('%H:%M:%S', time.localtime(st['time']))}"
              f", due by {time.strftime('%H:%M:%S', time.localtime(st['update_by']))}: "
              f"the build process (pid {st['pid']}) runs but does not report; it may hang")
    for line in st.get("events", [])[-5:]:
        print(f"  {line}")
    return 0


def _read_status(build: Path) -> dict:
    from icefab import build as bmod

    try:
        return json.loads((build / bmod.STATUS).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


#: How long ``--stop`` waits for a build process to end: a build stops between commands
#: (the path under way ends, valves off, the tool lifted), a preparing one at once.
STOP_WAIT_S = 60.0


def _stop(build: Path) -> int:
    from icefab import build as bmod
    from icefab.journal import Journal
    from icefab.linkedcell import cell_alive

    pid = _build_pid(build)
    if pid is not None:
        return _stop_process(build, pid)
    if not (build / bmod.JOURNAL).exists() and _stop_orphan_cell(build):
        return 0
    journal = Journal.open(build / bmod.JOURNAL)   # names the folder when it is no build
    meta = journal.meta()
    cdir = build / bmod.CELL_DIR
    if _read_status(build).get("state") == "complete":
        # nothing to stop (it wrote a request into the finished folder and journaled "no
        # build was running"); a virtual cell still up means the build was killed as it
        # ended, and no resume will end it (a hunt's)
        journal.close()
        if meta.get("cell") == "virtual" and cell_alive(cdir):
            _shutdown_cell(cdir)
            print(f"{build}: the build is complete; its virtual cell was still running (the "
                  "build was killed as it ended): stopped it")
        else:
            print(f"{build}: the build is complete: nothing to stop")
        return 0
    # no build process: tell the cell directly
    from icefab.config import load_job

    if meta.get("cell") == "virtual" and not cell_alive(cdir):
        journal.event("stop", "stop asked: no build and no virtual cell were running")
        journal.close()
        print(f"{build}: no build and no virtual cell were running")
        return 0

    connect = _connector(build, argparse.Namespace(cell=None), meta,
                         load_job(build / "job.toml", stored=True))
    cell = connect()
    try:
        cell.stop_now()
    finally:
        cell.close()
    journal.event("stop", "stop sent to the cell (no build was running): valves off, robot "
                  "stopped at once, tool not lifted")
    journal.close()
    # the cell stopped its motion at once (it let a path under way run to its end first,
    # and said the tool was lifted: a hunt's); its processes stay for --resume: a tester
    # read "told to stop" as the cell's programs ending
    print(f"{build}: no build was running; the cell was told to stop at once (valves off, "
          f"the robot stopped where it was; the tool was not lifted: no build knows where it "
          f"is); it keeps running for 'icefab build --resume {build}'")
    return 0


def _stop_process(build: Path, pid: int) -> int:
    """Stop the build or resume process ``pid`` of ``build`` and wait for it to end: a
    request the runner reads between commands and SIGTERM (which also ends one that is
    still being prepared); then say how it ended."""
    from icefab import build as bmod

    request = build / bmod.STOP_REQUEST
    if (build / bmod.JOURNAL).exists():
        request.write_text("stop\n", encoding="utf-8")
    try:
        os.kill(pid, signal.SIGTERM)
    except OSError:
        pass
    deadline = time.monotonic() + STOP_WAIT_S
    while _build_pid(build) == pid:
        if time.monotonic() > deadline:
            raise ConfigError(f"{build}: the build (process {pid}) did not stop within "
                              f"{STOP_WAIT_S:g} s")
        time.sleep(0.1)
    st = _read_status(build)
    if st.get("pid") != pid:    # its runner never started: nothing was sent
        request.unlink(missing_ok=True)
        print(f"{build}: stopped while it was being prepared (planning, starting its cell "
              "or reconnecting to it); no path was sent to the cell")
    elif st.get("state") == "complete":
        request.unlink(missing_ok=True)
        print(f"{build}: the build completed before the stop reached it")
    else:
        print(f"{build}: stopped ({(st.get('events') or ['-'])[-1]})")
    return 0
