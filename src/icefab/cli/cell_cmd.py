"""``icefab cell serve --state DIR [-c JOB] [--grid-for TRAJECTORIES [--layers N] |
--bounds X0,Y0,X1,Y1] [--time-factor F] [--port P]``.

Runs the virtual cell (:mod:`icefab.cell.virtual`) in the foreground until SIGTERM or
Ctrl-C: a virtual Adept C40 on 127.0.0.1:PORT (robot link), the valve firmware's host
build on a pty, the LK-G laser emulator on a pty. Writes ``DIR/endpoints.json`` and keeps
the part in ``DIR/surface.npz`` (restart with the same DIR to carry on). A new DIR needs
the surface grid: ``--grid-for`` gives the grid ``icefab simulate`` uses for those
trajectories (so both can be compared bit for bit), ``--bounds`` a rectangle in the part
frame (mm). The job's simulation settings (seed, disturbances) model the cell.
"""

from __future__ import annotations

import argparse
import math
import shutil
import signal
import threading
from pathlib import Path

from icefab.cli.common import add_job_argument, job_from_args
from icefab.errors import CellError, ConfigError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("cell", help="the virtual cell (robot, valve controller, laser)",
                              description="The virtual cell behind the real cell's links.")
    sub = p.add_subparsers(dest="what", metavar="WHAT")
    sub.required = True
    s = sub.add_parser(
        "serve", help="run the virtual cell until stopped",
        description="Run a virtual Adept C40 (TCP on 127.0.0.1), the valve firmware's host "
                    "build (pty) and the Keyence LK-G emulator (pty), depositing on "
                    "DIR/surface.npz with icefab's simulator. Endpoints in "
                    "DIR/endpoints.json. Stop with SIGTERM or Ctrl-C.")
    s.add_argument("--state", required=True, metavar="DIR",
                   help="state folder (surface.npz, endpoints.json, logs)")
    add_job_argument(s)
    s.add_argument("--grid-for", metavar="TRAJECTORIES",
                   help="a new surface on the grid 'icefab simulate' uses for this "
                        "trajectories.npz")
    s.add_argument("--layers", type=int, default=0,
                   help="with --grid-for: the first N layers only (0: all)")
    s.add_argument("--bounds", metavar="X0,Y0,X1,Y1",
                   help="a new surface over this rectangle of the part frame, mm")
    s.add_argument("--time-factor", type=float, default=0.0, metavar="F",
                   help="0: as fast as possible (default); F > 0: F times real time")
    s.add_argument("--port", type=int, default=7100,
                   help="robot TCP port on 127.0.0.1 (default 7100; 0: any free port)")
    s.add_argument("--firmware", metavar="VALVECTL",
                   help="a built valve firmware host executable (default: build firmware/)")
    s.set_defaults(func=run_serve)
    c = sub.add_parser(
        "check", help="say hello on each link of a cell and print what answers",
        description="Connect to the robot controller (TCP), the valve controller and the "
                    "laser (serial) of a cell -- the virtual one of --state DIR or real "
                    "devices -- and print each one's answer. Exit 2 with one line naming "
                    "the first device that does not answer.")
    c.add_argument("--state", metavar="DIR", help="a running 'icefab cell serve' state folder")
    c.add_argument("--robot", metavar="HOST:PORT", help="the C40's V+ server")
    c.add_argument("--valve", metavar="DEVICE", help="the valve controller's serial port")
    c.add_argument("--laser", metavar="DEVICE", help="the laser controller's serial port")
    c.add_argument("--timeout", type=float, default=5.0, metavar="S",
                   help="seconds to wait for each answer (default 5)")
    c.set_defaults(func=run_check)


def _grid(args, job):
    if args.grid_for and args.bounds:
        raise ConfigError("--grid-for and --bounds: give one of them")
    if args.layers < 0:
        raise ConfigError(f"--layers {args.layers}: expected >= 0")
    if args.grid_for:
        from icefab.cell.world import grid_for
        from icefab.motion import open_trajectories

        src = Path(args.grid_for)
        if not src.is_file():
            raise ConfigError(f"--grid-for {src}: trajectories file not found")
        return grid_for(open_trajectories(src), job, layers=args.layers or None)
    if args.bounds:
        import numpy as np

        try:
            x0, y0, x1, y1 = (float(v) for v in args.bounds.split(","))
        except ValueError:
            raise ConfigError(f"--bounds {args.bounds!r}: expected X0,Y0,X1,Y1 in mm"
                              ) from None
        g = job.simulation.grid_mm
        if not all(map(math.isfinite, (x0, y0, x1, y1))) or x1 <= x0 or y1 <= y0:
            raise ConfigError(f"--bounds {args.bounds!r}: expected X0 < X1 and Y0 < Y1")
        shape = (int(math.floor((y1 - y0) / g)) + 2, int(math.floor((x1 - x0) / g)) + 2)
        if shape[0] * shape[1] > 50_000_000:
            raise ConfigError(f"--bounds {args.bounds!r}: {shape[0]} x {shape[1]} cells of "
                              f"{g} mm is too large")
        return np.array([x0, y0]), shape, g
    return None


def _firmware(given: str) -> str:
    """The valve firmware's host build as an absolute path (a name alone is looked up on
    PATH); ConfigError saying why it cannot run. './valvectl' was looked up on PATH as
    'valvectl', and a folder or a file without execute permission was "No such file or
    directory" (hunt W)."""
    import os

    found = shutil.which(given)
    if found is not None:
        return str(Path(found).absolute())
    p = Path(given)
    if os.sep not in given:   # a name alone is a program on PATH, as for a shell
        here = (f"; this folder's is --firmware ./{given}" if p.is_file()
                and os.access(p, os.X_OK) else "")
        raise ConfigError(f"--firmware {given}: no such program on PATH (give its path"
                          f"{here})")
    if not p.exists():
        raise ConfigError(f"--firmware {given}: no such file")
    if p.is_dir():
        raise ConfigError(f"--firmware {given}: is a folder, not the firmware's host build")
    raise ConfigError(f"--firmware {given}: not executable (chmod +x, or build it: "
                      "'make -C firmware host')")


def run_serve(args: argparse.Namespace) -> int:
    from icefab.cell.virtual import VirtualCell

    if not (math.isfinite(args.time_factor) and args.time_factor >= 0):
        raise ConfigError(f"--time-factor {args.time_factor}: expected 0 or a positive "
                          "factor of real time")
    if not 0 <= args.port <= 65535:
        raise ConfigError(f"--port {args.port}: expected 0..65535")
    state = Path(args.state)
    if state.exists() and not state.is_dir():
        raise ConfigError(f"--state {state}: exists and is not a folder")
    exists = (state / "surface.npz").exists()
    if exists and (args.grid_for or args.bounds):
        raise ConfigError(f"--state {state}: already holds a surface; --grid-for and "
                          "--bounds only start a new one")
    if exists and not getattr(args, "job", None):
        job = _stored_job(state)
    else:
        job = job_from_args(args)
    grid = None if exists else _grid(args, job)
    if grid is None and not exists:
        raise ConfigError(f"--state {state}: no surface yet; give --grid-for TRAJECTORIES "
                          "or --bounds X0,Y0,X1,Y1")
    firmware = _firmware(args.firmware) if args.firmware else None
    made = not state.exists()
    try:
        cell = VirtualCell(state, job, grid=grid, time_factor=args.time_factor,
                           robot_port=args.port, firmware_exe=firmware)
    except BaseException as exc:
        # a cell that never started leaves no state behind (a firmware that announced no
        # pty left a new surface.npz)
        if made:
            shutil.rmtree(state, ignore_errors=True)
        if isinstance(exc, OSError):
            where = f"{exc.filename}: " if exc.filename else ""
            raise CellError(f"virtual cell: cannot start ({where}{exc.strerror or exc})") \
                from None
        raise
    # a signal from here on ends the serving loop; while the cell started, it ended the
    # start as Ctrl-C does (the handlers set before it made a start that waits on a silent
    # firmware deaf to both for its 10 s: a hunt's)
    stop = threading.Event()
    why = None
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        for sig in old:
            signal.signal(sig, lambda *_: stop.set())
        e = cell.endpoints
        print(f"robot 127.0.0.1:{e['robot']['port']}  valve {e['valve']['device']}  laser "
              f"{e['laser']['device']}  (endpoints in {state / 'endpoints.json'})",
              flush=True)
        while not stop.wait(0.5):
            why = cell.failure()
            if why is not None:
                break
    finally:
        cell.close()
        for sig, handler in old.items():
            signal.signal(sig, handler)
    if why is not None:
        raise CellError(f"virtual cell: {why}; stopped after {cell.paths_run} paths, its "
                        f"surface and record kept in {state / 'surface.npz'} (start it "
                        "again; a --virtual build does)")
    print(f"stopped after {cell.paths_run} paths; surface in {state / 'surface.npz'}")
    return 0


def _stored_job(state: Path):
    import tomllib

    import numpy as np

    from icefab.config import stored_job_from_dict
    from icefab.resultfiles import NPZ_DAMAGE

    try:
        with np.load(state / "surface.npz", allow_pickle=False) as d:
            return stored_job_from_dict(tomllib.loads(str(d["job"])))
    except NPZ_DAMAGE as exc:
        # a truncated file was a BadZipFile / EOFError traceback, and 'icefab build'
        # restarted the cell 21 times over it (a hunt's)
        damaged = "" if isinstance(exc, OSError) else "; the file is damaged"
        raise CellError(f"{state / 'surface.npz'}: cannot read the cell's job "
                        f"({type(exc).__name__}: {exc}){damaged}") from None


#: The longest wait ``cell check --timeout`` takes, s.
MAX_TIMEOUT_S = 3600.0


def _ran(last: int) -> str:
    """What the robot's count of completed commands ``last`` says to a user about to build
    (``icefab build`` refuses a cell that ran one without --platform-cleared)."""
    if last <= 0:
        return "no command completed since its program started"
    return (f"commands completed up to number {last} (an earlier build: its platform may "
            "hold ice; 'icefab build' needs --platform-cleared once it is cleared)")


def run_check(args: argparse.Namespace) -> int:
    from icefab.cell.laser import LaserLink
    from icefab.cell.robot import RobotLink

    if not (math.isfinite(args.timeout) and 0 < args.timeout <= MAX_TIMEOUT_S):
        # 1e300 s overflowed the socket's timeout in a traceback (hunt W)
        raise ConfigError(f"--timeout {args.timeout}: expected a number of seconds above 0, "
                          f"at most {MAX_TIMEOUT_S:g}")
    ends = {}
    if args.state:
        from icefab.cell.virtual import read_endpoints

        e = read_endpoints(args.state)
        ends = {"robot": f"{e['robot']['host']}:{e['robot']['port']}",
                "valve": e["valve"]["device"], "laser": e["laser"]["device"]}
    for key in ("robot", "valve", "laser"):
        if getattr(args, key):
            ends[key] = getattr(args, key)
    if not ends:
        raise ConfigError("give --state DIR or at least one of --robot, --valve, --laser")
    if "robot" in ends:
        host, _, port = ends["robot"].rpartition(":")
        if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            # port 99999 reached whatever listened on 34463 (hunt W)
            raise ConfigError(f"--robot {ends['robot']!r}: expected HOST:PORT, the port "
                              "1..65535")
        with RobotLink.connect(host, int(port), timeout_s=args.timeout) as link:
            info = link.hello()
            st = link.status()
        print(f"robot {ends['robot']}: protocol {info.version}, {info.max_points} points x "
              f"{info.max_paths} paths, {st['state']}, {st['stored']} stored, "
              f"{_ran(max(st['last_done'], st['cut']))}")
    if ends.get("valve"):
        from icefab.cell.valve import ValveController

        # the valve controller re-sends a frame it got no answer to (5 times): the whole
        # wait is --timeout, as for the other links (it was 3 s whatever --timeout said)
        with ValveController.open(ends["valve"], timeout_s=args.timeout / 6.0,
                                  retries=5) as ctl:
            st = ctl.status()
        print(f"valve {ends['valve']}: {st.state_name}, plays {st.plays}")
    if ends.get("laser"):
        with LaserLink.open(ends["laser"], timeout_s=args.timeout) as laser:
            storing, count = laser.status()
        print(f"laser {ends['laser']}: storage {'running' if storing else 'stopped'}, "
              f"{count} values stored")
    return 0
