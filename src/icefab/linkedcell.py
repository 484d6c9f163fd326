"""The build runner's cell on the cell's three links: what ``icefab build`` drives.

:class:`LinkedCell` is the :class:`icefab.runcell.Cell` of :mod:`icefab.build` on
:class:`~icefab.cell.links.CellLinks`: the robot controller (TCP, :mod:`~icefab.cell.robot`),
the valve controller (serial, :mod:`~icefab.cell.valve`) and the laser (serial,
:mod:`~icefab.cell.laser`), of a real cell or of ``icefab cell serve``
(:func:`start_virtual_cell` starts one as its own process). Per path it does what
:func:`icefab.cell.links.run_layer` does (thesis 2.3, Fig. 2-5), with the build's journal
sequence numbers:

* a deposition path: the robot path is uploaded under the path's journal number, the valve
  program is uploaded, verified and armed, and the robot's ``GO`` is the trigger; the path
  is done when the valve controller reports its play over and the robot its ``DN``;
* a measurement path: the laser's storage is cleared and started before ``GO``, stopped
  and read out after ``DN``; its values are kept for :meth:`LinkedCell.laser_samples`;
* travel: ``GO`` and ``DN``; ``LB`` before the first path of a layer, ``LE`` (journal
  number) at its end.

The robot does not wait for data: while a path moves (between its ``GO`` and its ``DN``)
the next one the runner names (``upcoming``, already journaled as sent) is uploaded to
the robot and its valve program to the valve controller, so only the valves' ``ARM``
lies between a ``DN`` and the next ``GO``. :meth:`LinkedCell.stop`: valves off, ``AB``,
and the tool lifted :data:`SAFE_LIFT_MM` by a park path (``FLAG_PARK``: not a build path).
A refusal no repeat can change (:class:`~icefab.errors.CellRefused`) ends the build.

Exactly once across crashes (robot_protocol: sequence numbers): the controller keeps the
number of the last path it ran to its end (``last_done``) and of the last one it stopped
mid-motion (``cut``). On connecting, :meth:`LinkedCell.hello` lets a motion the crashed
session started finish, discards paths it had stored and valve programs it had uploaded or
armed (nothing half-sent is played later), and stops the laser's storage; then
:meth:`~LinkedCell.status` tells the runner what is done. The laser values of a
measurement path whose ``DN`` the crash lost are still in the laser's storage (it is only
cleared before the next measurement path) and are read from there.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from icefab.cell import robot_protocol as rp
from icefab.cell.valve_host import end_group
from icefab.errors import CellError, CellRefused

log = logging.getLogger(__name__)

__all__ = ["LinkedCell", "start_virtual_cell", "cell_alive", "shutdown_virtual_cell",
           "load_endpoints"]

#: how long :meth:`LinkedCell.hello` waits for a motion the previous session started
SETTLE_S = 600.0
#: how far :meth:`LinkedCell.stop` lifts the tool above the last path's height, mm
SAFE_LIFT_MM = 20.0


def load_endpoints(path: str | os.PathLike) -> dict:
    """A cell's endpoints: ``endpoints.json`` of ``icefab cell serve`` (or its folder), or
    the same keys for a real cell::

        {"robot": {"host": "192.168.0.10", "port": 7100},
         "valve": {"device": "/dev/ttyUSB0"}, "laser": {"device": "/dev/ttyS0"}}

    CellError naming the file when it is missing or malformed."""
    from icefab.cell.virtual import read_endpoints
    from icefab.inputs import read_input_text

    p = Path(path)
    if p.is_dir():
        return read_endpoints(p)
    if not p.exists():
        # 'icefab cell serve' removes its endpoints file when it stops
        raise CellError(f"{p}: no cell endpoints file (a cell started with 'icefab cell "
                        "serve' removes it when it stops: start it again)")
    # a regular file of a page at most: /dev/zero ran out of memory, a FIFO hung
    text = read_input_text(p, "job", CellError, what="the cell endpoints file")
    try:
        data = json.loads(text)
        data["robot"]["host"] = str(data["robot"]["host"])
        data["robot"]["port"] = int(data["robot"]["port"])
        str(data["valve"]["device"]), str(data["laser"]["device"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise CellError(f"{p}: not a cell's endpoints file: expected robot host and port, "
                        f"valve and laser devices ({type(exc).__name__}: {exc})") from None
    return data


class LinkedCell:
    """The runner's :class:`~icefab.runcell.Cell` on a cell's links (module docstring).

    endpoints: as :func:`load_endpoints` returns; job: the build's job (frames for the
    laser samples, the storage rate); timeout_s: per reply on every link.
    """

    def __init__(self, endpoints: dict, job, *, timeout_s: float = 10.0) -> None:
        self.endpoints = endpoints
        self.job = job
        self.timeout_s = float(timeout_s)
        self.links = None
        self._layer: int | None = None
        self._last_done = 0
        self._samples: dict[int, np.ndarray] = {}
        self._preloaded: tuple | None = None   # (seq, CellPath, valve uploads or None)
        self._last_path = None                  # the RobotPath run last (stop's lift)

    # ------------------------------------------------------------------ session

    def hello(self) -> dict:
        """Open the three links (the handshake on each) and settle what a previous
        session left: a motion under way runs to its end, stored paths and valve programs
        are discarded, the laser stops storing."""
        from icefab.cell.links import CellLinks

        if self.links is None:
            self.links = CellLinks.open(self.endpoints, timeout_s=self.timeout_s)
        robot = self.links.robot
        deadline = time.monotonic() + SETTLE_S
        st = robot.status()
        while st["state"] == "moving":
            if time.monotonic() > deadline:
                raise CellError(f"{robot.where}: still moving {SETTLE_S:g} s after "
                                "connecting")
            time.sleep(0.02)
            st = robot.status()
        if st["stored"]:
            robot.abort()           # paths the crashed session uploaded but never started
        self.links.valves.abort()   # programs uploaded or armed for them: never played
        self.links.laser.stop()
        self._last_done = st["last_done"]
        self._layer = None
        self._preloaded = None
        info = robot.info
        return {"cell": "icefab cell links", "robot": robot.where,
                "protocol": None if info is None else info.version,
                "valve": self.links.valves.name, "laser": self.links.laser.where}

    def stop_now(self) -> None:
        """Valves off, then the robot stops at once (``AB``), on freshly opened links and
        without settling first: what ``icefab build --stop`` tells a cell no build runs
        on. :meth:`hello` would let a motion under way run to its end, its valve
        dispensing (a hunt's stop waited 7.4 s for a measurement path). The tool is not
        lifted: where it stopped is the build's to know."""
        from icefab.cell.links import CellLinks

        if self.links is None:
            self.links = CellLinks.open(self.endpoints, timeout_s=self.timeout_s)
        try:
            self.links.valves.abort()
        finally:
            self.links.robot.abort()

    def check_paths(self, motion) -> None:
        """Refuse, before anything moves, trajectories the controller cannot store: more
        points in one path than its ``max_points`` (``HI``). CellError naming the first
        such path."""
        info = self._need().robot.info
        if info is None:
            return
        for lm in motion.layers:
            for k, tr in enumerate(lm.trajectories):
                if len(tr.xy) > info.max_points:
                    raise CellRefused(
                        f"layer {lm.index} path {k}: {len(tr.xy)} points, the robot "
                        f"controller stores {info.max_points} per path: raise max_points "
                        "in the controller's V+ program (icefab.cell.vplus) if its memory "
                        "allows")

    def close(self) -> None:
        if self.links is not None:
            self.links.close()
            self.links = None

    def _need(self):
        if self.links is None:
            raise CellError("the cell's links are not open (hello first)")
        return self.links

    def status(self):
        from icefab.runcell import CellStatus

        st = self._need().robot.status()
        self._last_done = st["last_done"]
        return CellStatus(last_done=st["last_done"], cut=st["cut"], prepared=True)

    def prepare(self, job_toml: str, lo_mm, hi_mm) -> None:
        """Nothing to do: a cell (or ``icefab cell serve``) holds its build plate."""
        return None

    # ------------------------------------------------------------------ paths

    def _robot_path(self, path):
        from icefab.cell.robot import RobotPath, path_flags

        role = path.role if path.tool != "none" else "travel"
        return RobotPath(xy=np.asarray(path.xy, dtype=np.float64), dt_s=float(path.dt_s),
                         z_mm=float(path.z_mm), flags=path_flags(role), tool=path.tool,
                         width_mm=float(path.width_mm), layer=int(path.layer),
                         index=int(path.item))

    def run_path(self, seq: int, path, upcoming=None) -> bool:
        """Run one :class:`~icefab.runcell.CellPath` under journal number ``seq``; False
        (nothing run) when the controller completed ``seq`` already. ``upcoming`` (seq,
        CellPath): the next path of the layer, uploaded to the robot and its valve
        program to the valve controller while this one moves, so that between this path's
        ``DN`` and the next ``GO`` only the arm of its valves remains."""
        links = self._need()
        if seq <= self._last_done:
            return False
        robot, valves = links.robot, links.valves
        if self._layer != path.layer:
            robot.begin_layer(int(path.layer), float(path.z_mm))
            self._layer = int(path.layer)
        rpath = self._robot_path(path)
        wait = self.timeout_s + rpath.duration_s
        ups = self._take_preloaded(seq)
        if ups is None:
            robot.upload(rpath, seq)
            ups = self._upload_program(path)
        if rpath.flags & rp.FLAG_VALVE:
            if not ups:
                raise CellRefused(f"layer {path.layer} path {path.item}: a deposition "
                                  "path without a valve program")
            st = valves.status()
            for u in ups:       # what did not fit while the previous program played
                if not u.complete:
                    valves.send_data(u, st.valves[u.valve].free)
            play = (st.plays + 1) & 0xFFFF
            valves.events.clear()
            valves.arm([u.valve for u in ups])
            robot.go(seq)                      # the robot's output is the valves' trigger
            self._preload(upcoming, streaming=not all(u.complete for u in ups))
            valves.wait_done(play, ups, timeout_s=10.0 + 1.5 * rpath.duration_s)
            robot.wait_done(seq, wait)
        elif rpath.flags & rp.FLAG_LASER:
            links.laser.clear()
            links.laser.start()
            robot.go(seq)
            self._preload(upcoming)
            robot.wait_done(seq, wait)
            links.laser.stop()
            self._samples[seq] = self._rows(rpath, links.laser.read_stored())
        else:
            robot.go(seq)
            self._preload(upcoming)
            robot.wait_done(seq, wait)
        self._last_done = seq
        self._last_path = rpath
        return True

    def _upload_program(self, path) -> list:
        """Upload and verify a deposition path's valve program (what fits the store; the
        rest streams while it plays); [] for other paths."""
        from icefab.cell.valve import VALVES

        if path.tool not in VALVES or not path.program:
            return []
        return [self._need().valves.upload(VALVES[path.tool], path.program)]

    def _preload(self, upcoming, *, streaming: bool = False) -> None:
        """Upload the next path while this one moves (robot always; its valve program
        unless this path's program still streams into the store). It may be the next
        layer's first: its ``LB`` is sent when it runs, after this layer's ``LE``."""
        if upcoming is None or self._preloaded is not None:
            return
        seq, path = upcoming
        if seq <= self._last_done:
            return
        self._need().robot.upload(self._robot_path(path), seq)
        self._preloaded = (seq, path, None if streaming else self._upload_program(path))

    def _take_preloaded(self, seq: int):
        """The valve uploads of path ``seq`` if it was preloaded (robot path stored), else
        None; a preload of another path is discarded (robot ``AB`` while idle, valves
        aborted)."""
        pre, self._preloaded = self._preloaded, None
        if pre is None:
            return None
        if pre[0] == seq:
            return pre[2] if pre[2] is not None else self._upload_program(pre[1])
        self._need().robot.abort()
        self._need().valves.abort()
        return None

    def _rows(self, rpath, values: np.ndarray) -> np.ndarray:
        """(m, 4) rows (t s from the trigger, EE x, y base frame mm, height mm) of the
        stored laser values of one measurement path (NaN values dropped)."""
        from icefab.cell.laser import stored_times

        xy = rpath.xy
        t = np.arange(len(xy)) * rpath.dt_s
        tk, vals = stored_times(rpath, values, float(self.job.simulation.laser_rate_hz))
        ok = np.isfinite(vals)
        ee = np.column_stack([np.interp(tk, t, xy[:, 0]), np.interp(tk, t, xy[:, 1])])
        return np.column_stack([tk[ok], ee[ok], rpath.z_mm + vals[ok]])

    def end_layer(self, seq: int, layer: int) -> bool:
        """``LE`` under journal number ``seq`` (the virtual cell freezes the layer)."""
        self._need().robot.end_layer(int(layer), int(seq))
        self._layer = None
        return True

    def laser_samples(self, seq: int, path) -> np.ndarray:
        """(m, 4) rows of measurement path ``seq``: t s from its trigger, end-effector x, y
        (base frame, mm), height mm. After a crash between its ``DN`` and this call the
        values are read from the laser's storage (the last path stored); (0, 4) and a
        warning when they are gone."""
        got = self._samples.pop(seq, None)
        if got is not None:
            return got
        links = self._need()
        if seq == self._last_done:
            try:
                return self._rows(self._robot_path(path), links.laser.read_stored())
            except CellError as exc:
                log.warning("measurement path %d: its laser values are gone (%s)", seq, exc)
        else:
            log.warning("measurement path %d: its laser values are gone (another path ran "
                        "since)", seq)
        return np.zeros((0, 4))

    def stop(self) -> float:
        """Valves off first (every program discarded), then the robot stops at once with
        both triggers off (``AB``: V+ ``BRAKE``) and lifts the tool :data:`SAFE_LIFT_MM`
        straight up from where the last path of this session ended (within
        ``cell.stroke_mm``): a one-point park path (``FLAG_PARK``: the controller does not
        count it as the last path done, so the journal's numbering stays whole), which it
        reaches at its approach speed (thesis 4.3), clear of the part's top. Returns how
        far it lifted the tool, mm: 0 with no path of this session to lift from (where
        the tool is was not known here)."""
        from icefab.cell.robot import RobotPath

        links = self._need()
        try:
            links.valves.abort()
        finally:
            links.robot.abort()
        if self._last_path is None:
            return 0.0
        last = self._last_path
        z = min(float(last.z_mm) + SAFE_LIFT_MM, float(self.job.cell.stroke_mm))
        lift = RobotPath(xy=np.asarray(last.xy[-1:], dtype=np.float64), dt_s=0.01, z_mm=z,
                         flags=rp.FLAG_PARK, tool="none", width_mm=0.0,
                         layer=int(last.layer), index=0)
        links.robot.run(lift, self.timeout_s + 30.0)
        return z - float(last.z_mm)


# =========================================================================== the process


def start_virtual_cell(state_dir: str | os.PathLike, job_file: str | os.PathLike,
                       trajectories: str | os.PathLike, *, layers: int = 0,
                       time_factor: float = 0.0, timeout_s: float = 120.0) -> int:
    """Start ``icefab cell serve`` as its own process (own session: killing the build
    leaves it running, as a real controller would) with its state in ``state_dir``; a new
    folder gets the grid ``icefab simulate`` uses for ``trajectories`` (first ``layers``).
    Waits for its endpoints; returns its pid. CellError (naming ``DIR/cell.log``) if it
    does not start."""
    from icefab.cell.virtual import read_endpoints

    d = Path(state_dir)
    d.mkdir(parents=True, exist_ok=True)
    (d / "endpoints.json").unlink(missing_ok=True)   # a killed cell's: not this one's
    args = [sys.executable, "-m", "icefab", "cell", "serve", "--state", str(d), "--port", "0",
            "--time-factor", repr(float(time_factor))]
    if not (d / "surface.npz").exists():
        args += ["-c", str(job_file), "--grid-for", str(trajectories), "--layers",
                 str(int(layers))]
    with open(d / "cell.log", "ab") as log_f:
        proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log_f, stderr=log_f,
                                start_new_session=True)
    deadline = time.monotonic() + timeout_s
    try:
        while not (d / "endpoints.json").is_file():
            if proc.poll() is not None:
                tail = (d / "cell.log").read_text(errors="replace").strip().splitlines()[-1:]
                # status 2 is icefab's refusal (a damaged state file, a setting): starting
                # it again gives the same, and the build tried 21 times over 100 s with
                # advice to resume when the cell answered (a hunt's)
                error = CellRefused if proc.returncode == 2 else CellError
                raise error(f"the virtual cell exited at start (status {proc.returncode}"
                            f"{': ' + tail[0] if tail else ''}); see {d / 'cell.log'}")
            if time.monotonic() > deadline:
                raise CellError(f"the virtual cell did not start within {timeout_s:g} s; "
                                f"see {d / 'cell.log'}")
            time.sleep(0.05)
        read_endpoints(d)
    except BaseException:
        # a cell that did not start, or a build stopped (--stop, Ctrl-C) while it started:
        # it goes, with its firmware (its own session), before its folder is removed (one
        # stopped then wrote its files into a removed folder and ran on, out of reach)
        end_group(proc, signal.SIGKILL)
        raise
    return proc.pid


def _pid(state_dir: Path) -> int | None:
    try:
        return int(json.loads((state_dir / "endpoints.json").read_text())["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def cell_alive(state_dir: str | os.PathLike) -> bool:
    """Whether the cell process named in ``DIR/endpoints.json`` is running."""
    pid = _pid(Path(state_dir))
    if pid is None:
        return False
    try:  # our own child that died is a zombie until reaped: reap it
        if os.waitpid(pid, os.WNOHANG)[0] == pid:
            return False
    except ChildProcessError:
        pass
    try:
        os.kill(pid, 0)
    except OSError:
        return False
    return True


def shutdown_virtual_cell(state_dir: str | os.PathLike, timeout_s: float = 30.0) -> None:
    """End the virtual cell serving ``state_dir`` (SIGTERM: it saves its surface and
    removes its endpoints), if one runs."""
    d = Path(state_dir)
    if not cell_alive(d):
        return
    pid = _pid(d)
    try:
        os.kill(pid, signal.SIGTERM)
    except OSError:
        return
    deadline = time.monotonic() + timeout_s
    while cell_alive(d) and time.monotonic() < deadline:
        time.sleep(0.05)
