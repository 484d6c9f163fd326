"""The virtual cell: ``icefab cell serve --state DIR`` (thesis Fig. 2-5 behind its links).

One process, independent of any client, with the three devices of the cell behind the
same links as the real ones:

* the robot: :class:`~icefab.cell.virtual_robot.VirtualRobot` on 127.0.0.1 (TCP, the
  protocol of :mod:`icefab.cell.robot_protocol`);
* the valve controller: the firmware's host build (the real C core, ``firmware/``) on a
  pty, its trigger input driven by the virtual robot (SIGUSR1, as the C40's digital
  output drives the LPC2148's pin), its pulses read from its pulse log;
* the laser controller: :class:`~icefab.cell.laser_emulator.PtyLaser` on a pty, its
  timing input driven by the virtual robot.

``DIR/endpoints.json`` says where they are::

    {"robot": {"host": "127.0.0.1", "port": 7100}, "valve": {"device": "/dev/pts/5"},
     "laser": {"device": "/dev/pts/6"}, "pid": 1234, "state": "DIR",
     "time_factor": 0.0}

The part lives in ``DIR/surface.npz`` (:mod:`icefab.cell.world`: layout, model and
determinism), saved after every path together with the robot's ``last_done``, so a
restarted cell carries on with the same surface, as real ice would, and reports what it
completed; a path under way when the process died (``DIR/robot-running``) is reported
``cut``. ``DIR/executed.log`` lists the paths run to their end, one per line. Time runs
as fast as possible (``time_factor`` 0) or at a factor of real time (1: real time).
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path

import numpy as np

from icefab.cell import robot_protocol as rp
from icefab.cell.laser_emulator import PtyLaser
from icefab.cell.robot import RobotPath
from icefab.cell.virtual_robot import VirtualRobot
from icefab.cell.world import World
from icefab.errors import CellError

log = logging.getLogger(__name__)

__all__ = ["VirtualCell", "FirmwareValves", "ValveHookup", "read_endpoints"]

RUNNING_FILE = "robot-running"
EXECUTED_FILE = "executed.log"


class ValveHookup:
    """What the virtual cell needs from the valve controller: its serial device, the
    trigger input, and the pulses of the play a trigger started."""

    device: str = ""

    def trigger(self) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def play_pulses(self, timeout_s: float) -> tuple[list[tuple[int, float, float]], bool]:
        """After :meth:`trigger`: (valve, t s from the trigger, width us) of the play it
        started, and whether the play ran to its end; ([], False) if it started none."""
        raise NotImplementedError  # pragma: no cover - interface

    def failure(self) -> str | None:
        """Why the valve controller can no longer play (None while it can)."""
        return None

    def close(self) -> None:  # pragma: no cover - interface
        pass


class FirmwareValves(ValveHookup):
    """The firmware's host build (``firmware/PROTOCOL.md`` section 9) on a pty, virtual
    clock, with a pulse log in the state folder. The trigger is SIGUSR1 (the pin)."""

    def __init__(self, state_dir: Path, *, tick_s: float, time_factor: float = 0.0,
                 exe: str | os.PathLike | None = None):
        from icefab.cell import valve_host

        build = state_dir / "firmware-build"
        exe = Path(exe) if exe else valve_host.build_host(build)
        self.log_path = state_dir / "valve-pulses.log"
        self.log_path.unlink(missing_ok=True)
        clock = "virtual" if time_factor <= 0 else "real"
        self.host = valve_host.HostFirmware(exe, clock=clock,
                                            speed=time_factor if time_factor > 0 else 1.0,
                                            pulse_log=self.log_path)
        self.device = self.host.pty
        self.tick_s = float(tick_s)
        self._offset = 0
        self._buf = ""

    def trigger(self) -> None:
        import signal

        self._lines()   # what came before this trigger (an aborted play's tail) is not ours
        # ... so the log starts again here: it grew with the build (2-3 KB a path, 1.5 GB
        # over a 300 mm part). The firmware appends (O_APPEND): its next line lands at 0.
        try:
            os.truncate(self.log_path, 0)
        except FileNotFoundError:
            pass   # removed with the state folder: play_pulses says so (failure())
        self._offset, self._buf = 0, ""
        os.kill(self.host.pid, signal.SIGUSR1)

    def _lines(self) -> list[str]:
        try:
            with open(self.log_path, "r", encoding="ascii") as fh:
                fh.seek(self._offset)
                data = fh.read()
        except FileNotFoundError:
            return []
        self._offset += len(data.encode("ascii"))
        data = self._buf + data
        lines = data.split("\n")
        self._buf = lines.pop()
        return lines

    def failure(self) -> str | None:
        if not self.host.alive():
            return (f"the valve controller's firmware (pid {self.host.pid}) ended with "
                    f"status {self.host.proc.returncode}")
        if not self.log_path.exists():   # the firmware writes to the file it opened
            return f"the valve pulse log {self.log_path} was removed (the state folder?)"
        return None

    def play_pulses(self, timeout_s: float) -> tuple[list[tuple[int, float, float]], bool]:
        pulses: list[tuple[int, float, float]] = []
        play = None
        deadline = time.monotonic() + timeout_s
        start_deadline = time.monotonic() + 10.0   # a loaded machine may be slow to start it
        while True:
            for line in self._lines():
                f = line.split()
                if len(f) < 2 or not f[1].isdigit():
                    continue   # a line cut by the truncation at the trigger, before our play
                if f[0] == "start" and play is None:   # the first play after the trigger
                    play = int(f[1])
                elif f[0] == "pulse" and play is not None and int(f[1]) == play:
                    pulses.append((int(f[2]), int(f[3]) * self.tick_s, float(f[4])))
                elif f[0] in ("done", "abort") and play is not None and int(f[1]) == play:
                    return pulses, f[0] == "done"
                elif f[0] == "fault" and play is not None:
                    log.warning("virtual cell: valve controller fault %s during play %d",
                                f[1], play)
                    return pulses, False
            now = time.monotonic()
            why = self.failure()
            if why is not None:
                log.error("virtual cell: %s during valve play %s", why, play)
                return pulses, False
            if play is None and now > start_deadline:
                log.warning("virtual cell: the valve trigger started no play (nothing armed)")
                return [], False
            if now > deadline:
                log.warning("virtual cell: valve play %s did not end in %.0f s", play,
                            timeout_s)
                return pulses, False
            time.sleep(0.002)

    def close(self) -> None:
        self.host.stop()


class _Hooks:
    """What the robot's motion does in the virtual cell (see VirtualRobot)."""

    def __init__(self, cell: "VirtualCell"):
        self.cell = cell

    def layer_begin(self, layer: int, z_mm: float) -> None:
        with self.cell.lock:
            self.cell.world._layer(layer)
            self.cell.world.save()

    def layer_end(self, layer: int) -> None:
        with self.cell.lock:
            self.cell.world.freeze()
            self.cell.world.save()

    def refuse(self, path: RobotPath) -> int:
        """ER 10 for a deposition or measurement path off the surface grid: its drops
        fell nowhere and its laser read 0, and a tester's build on a cell started over
        another place was 'complete' with nothing deposited."""
        if path.flags & rp.FLAG_PARK or not path.flags & (rp.FLAG_VALVE | rp.FLAG_LASER) \
                or path.tool not in ("part", "scaffold", "laser"):
            return 0
        with self.cell.lock:
            return 0 if self.cell.world.covers(path.xy, path.tool) else 10

    def path_run(self, seq: int, path: RobotPath, stop: threading.Event,
                 time_factor: float) -> bool:
        cell = self.cell
        if path.flags & rp.FLAG_PARK:      # a stop's lift: no path of the build
            if time_factor > 0:
                stop.wait(path.duration_s / time_factor)
            return not stop.is_set()
        cell.mark_running(seq)
        if path.flags & rp.FLAG_LASER:
            with cell.lock:
                values = cell.world.laser_values(path.xy, path.dt_s, path.z_mm)
            cell.laser.controller.timing_path(values)
        if path.flags & rp.FLAG_VALVE and cell.valves is not None:
            cell.valves.trigger()
        if time_factor > 0 and stop.wait(path.duration_s / time_factor):
            with cell.lock:
                cell.world.cut = seq
                cell.world.save()
            return False
        played = True
        if path.flags & rp.FLAG_VALVE:
            pulses, played = ([], True) if cell.valves is None else \
                cell.valves.play_pulses(30.0 + 2.0 * path.duration_s)
            with cell.lock:
                cell.world.deposit_path(path.layer, path.xy, path.dt_s, path.width_mm,
                                        path.tool, pulses)
        # a valve program that did not play to its end (its controller died, stalled or
        # faulted) cut the path short: reported cut, never done (a tester's killed valvectl
        # left a path of 9 of its 617 pulses journaled done)
        finished = played and not stop.is_set()
        with cell.lock:
            # the deposit and the number that says it is done, in one atomic save
            if finished:
                cell.world.last_done = seq
            else:
                cell.world.cut = seq
            cell.world.save()
        if finished:
            cell.executed(seq)
        cell.paths_run += 1
        return finished

    def abort(self) -> None:
        log.info("virtual cell: robot abort")


class VirtualCell:
    """The three virtual devices and the surface; see the module docstring.

    state_dir: the state folder; job: the cell's settings (simulation model, frames,
    calibration); grid: (origin (2,), shape (ny, nx), spacing) for a new surface (None if
    ``state_dir/surface.npz`` exists); time_factor: 0 fast, else a factor of real time;
    robot_port: 0 for any free port; firmware_exe: a built ``valvectl`` (default: build
    ``firmware/`` into the state folder); valves: False to run without a valve
    controller (deposition paths then drop nothing; for tests of the other links).
    """

    def __init__(self, state_dir: str | os.PathLike, job, *, grid=None,
                 time_factor: float = 0.0, robot_port: int = 0,
                 firmware_exe: str | os.PathLike | None = None, valves: bool = True):
        if not (np.isfinite(time_factor) and time_factor >= 0):
            raise CellError(f"time factor {time_factor!r}: expected 0 (as fast as possible) "
                            "or a positive factor of real time")
        self.dir = Path(state_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.lock = threading.RLock()
        origin, shape, spacing = grid if grid is not None else (None, None, None)
        self.world = World(self.dir, job, origin=origin, shape=shape, spacing=spacing)
        self.job = self.world.job
        self.time_factor = float(time_factor)
        self.paths_run = 0
        self._recover_cut()
        self.valves: ValveHookup | None = None
        self.laser = PtyLaser().start()
        try:
            if valves:
                self.valves = FirmwareValves(self.dir, tick_s=job.flow.tick_s,
                                             time_factor=time_factor, exe=firmware_exe)
            self.robot = VirtualRobot(_Hooks(self), port=robot_port,
                                      time_factor=time_factor, last_done=self.world.last_done,
                                      cut=self.world.cut).start()
        except BaseException:
            self.laser.stop()
            if self.valves is not None:
                self.valves.close()
            raise
        self.endpoints = {"robot": {"host": "127.0.0.1", "port": self.robot.port},
                          "valve": {"device": self.valves.device if self.valves else ""},
                          "laser": {"device": self.laser.path}, "pid": os.getpid(),
                          "state": str(self.dir), "time_factor": self.time_factor}
        from icefab.atomic import atomic_path

        with atomic_path(self.dir / "endpoints.json", suffix=".json") as tmp:
            Path(tmp).write_text(json.dumps(self.endpoints, indent=1) + "\n",
                                 encoding="utf-8")

    # ------------------------------------------------------------------ restarts

    def mark_running(self, seq: int) -> None:
        """Note that path ``seq`` starts (``DIR/robot-running``): a cell that dies before
        the path's end reports it cut when it starts again (:meth:`_recover_cut`)."""
        from icefab.atomic import write_atomic

        write_atomic(self.dir / RUNNING_FILE, f"{int(seq)}\n")

    def _recover_cut(self) -> None:
        """A path that had started when the cell's process died, neither done nor cut in
        the surface's state, was cut short: the robot reports it as ``cut``."""
        try:
            seq = int((self.dir / RUNNING_FILE).read_text(encoding="ascii"))
        except (OSError, ValueError):
            return
        if seq not in (self.world.last_done, self.world.cut):
            log.warning("virtual cell: path %d was under way when the cell stopped: cut short",
                        seq)
            self.world.cut = seq
            self.world.save()

    def failure(self) -> str | None:
        """Why this cell can no longer run a build (its valve controller's firmware ended,
        its pulse log was removed), None while it can: ``icefab cell serve`` then stops
        (its surface and record saved), so that a build names it and a ``--virtual`` build
        starts the cell again (a tester's cell kept a dead firmware's pty in its endpoints:
        every resume failed on it, and the pty was later another cell's laser)."""
        return self.valves.failure() if self.valves is not None else None

    def executed(self, seq: int) -> None:
        """Append ``seq`` to ``DIR/executed.log``: the paths the cell ran to their end, one
        line each (the exactly-once evidence tests and benchmarks read)."""
        with open(self.dir / EXECUTED_FILE, "a", encoding="ascii") as fh:
            fh.write(f"{int(seq)}\n")

    def close(self) -> None:
        """Stop the devices; the surface stays in the state folder."""
        self.robot.stop()
        self.laser.stop()
        if self.valves is not None:
            self.valves.close()
        with self.lock:
            self.world.save()
        try:
            (self.dir / "endpoints.json").unlink()
        except FileNotFoundError:
            pass

    def __enter__(self) -> "VirtualCell":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_endpoints(state_dir: str | os.PathLike, timeout_s: float = 0.0) -> dict:
    """``DIR/endpoints.json`` of a running cell (waiting up to ``timeout_s`` for it to
    appear). CellError naming the file if it is missing or malformed."""
    path = Path(state_dir) / "endpoints.json"
    deadline = time.monotonic() + timeout_s
    while not path.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        data["robot"]["port"] = int(data["robot"]["port"])
        if not isinstance(data["robot"]["host"], str):   # 5 was a TypeError's traceback
            raise TypeError(f"robot host {data['robot']['host']!r}: expected a string")
        str(data["valve"]["device"]), str(data["laser"]["device"])
    except FileNotFoundError:
        raise CellError(f"{path}: no endpoints (is 'icefab cell serve --state "
                        f"{state_dir}' running?)") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise CellError(f"{path}: malformed endpoints file ({exc})") from None
    return data
