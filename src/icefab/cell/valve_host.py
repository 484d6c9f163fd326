"""The valve firmware's host build as a process on a pty (``firmware/PROTOCOL.md`` 9).

:func:`build_host` compiles ``firmware/`` with the system C compiler (``make host``);
:class:`HostFirmware` runs it and reads the pty path it prints. The same C core runs on the
LPC2148; tests, benchmarks and the virtual cell drive this process through
:class:`icefab.cell.valve.ValveController` exactly as they would the real board.

The firmware sources live beside the package in a clone (``<repo>/firmware``); set
``ICEFAB_FIRMWARE_DIR`` to use another copy.
"""

from __future__ import annotations

import os
import select
import shutil
import signal
import subprocess
import time
from pathlib import Path

from icefab.cell.valve import ValveLinkError


def firmware_dir() -> Path:
    """The ``firmware/`` folder (``ICEFAB_FIRMWARE_DIR`` or the clone's)."""
    env = os.environ.get("ICEFAB_FIRMWARE_DIR")
    path = Path(env) if env else Path(__file__).resolve().parents[3] / "firmware"
    if not (path / "Makefile").is_file():
        raise ValveLinkError(f"valve firmware sources not found at {path} (a clone of icefab "
                             "has them in firmware/; or set ICEFAB_FIRMWARE_DIR)")
    return path


def missing_tools() -> list[str]:
    """The build tools of the host build that are not on PATH (``make``, ``cc``)."""
    return [t for t in ("make", "cc") if shutil.which(t) is None]


def build_host(build_dir: str | os.PathLike) -> Path:
    """Compile the host build into ``build_dir``; returns the executable's path."""
    missing = missing_tools()
    if missing:
        raise ValveLinkError(f"cannot build the valve firmware's host build: {', '.join(missing)} "
                             "not found (install a C compiler and make, e.g. apt-get install "
                             "build-essential)")
    build_dir = Path(build_dir).resolve()
    # its own process group, ended whole when this process is interrupted: subprocess.run
    # ended only make, and the compilers it ran went on after 'icefab cell serve' had
    # stopped (a check's, 4 runs in 4); SIGTERM, on which gcc removes its half-written
    # output (make would take a truncated object for up to date)
    proc = subprocess.Popen(["make", "-s", "-C", str(firmware_dir()), "host",
                             f"BUILD={build_dir}"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        _out, err = proc.communicate()
    except BaseException:
        end_group(proc, signal.SIGTERM)
        raise
    if proc.returncode != 0:
        raise ValveLinkError(f"valve firmware host build failed: {err.strip()[-500:]}")
    return build_dir / "valvectl"


def end_group(proc: subprocess.Popen, sig: int) -> None:
    """Send ``sig`` to the process group that ``proc`` leads (a child started with
    ``start_new_session``: it and what it ran) unless it has ended, and wait for it."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except OSError:     # gone meanwhile
            pass
        proc.wait()


def _end_with_parent() -> None:
    """In the child before exec (Linux): SIGTERM when the process that started it dies,
    so a virtual cell killed with SIGKILL leaves no firmware behind holding its pty."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM))   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):   # not Linux: the firmware outlives a killed cell
        pass


#: How long the host build may take to announce its pty, s (it does so at once).
ANNOUNCE_TIMEOUT_S = 10.0


class HostFirmware:
    """A running host build. ``pty``: the serial device to open; ``pid``: for SIGUSR1 (the
    trigger input). Use as a context manager, or call :meth:`stop`.

    clock: "virtual" (as fast as possible, never ahead of the program bytes) or "real";
    speed: real-clock factor; pulse_log: file of ``pulse <play> <valve> <tick> <width_us>``
    lines; watchdog_ms: the emulated watchdog's period (10 000 on the board).
    """

    def __init__(self, exe: str | os.PathLike, *, clock: str = "virtual", speed: float = 1.0,
                 pulse_log: str | os.PathLike | None = None, watchdog_ms: int = 10000) -> None:
        args = [str(exe), "--clock", clock, "--speed", repr(float(speed)),
                "--watchdog-ms", str(int(watchdog_ms))]
        if pulse_log is not None:
            args += ["--pulse-log", str(pulse_log)]
        self.proc = subprocess.Popen(args, stdout=subprocess.PIPE, stdin=subprocess.DEVNULL,
                                     text=True, preexec_fn=_end_with_parent)
        self.pid = self.proc.pid
        self.pulse_log = None if pulse_log is None else Path(pulse_log)
        assert self.proc.stdout is not None
        # a program that never announces (the ARM image, any other program) hung the
        # cell's start for ever, Ctrl-C included (hunt W)
        ready, _, _ = select.select([self.proc.stdout], [], [], ANNOUNCE_TIMEOUT_S)
        if not ready:
            self.stop(timeout_s=1.0)
            raise ValveLinkError(f"valve firmware host build {exe}: no pty announced within "
                                 f"{ANNOUNCE_TIMEOUT_S:g} s (is it the host build, 'make -C "
                                 "firmware host'?)")
        line = self.proc.stdout.readline().split()
        if len(line) != 2 or line[0] != "PTY":
            self.stop()
            raise ValveLinkError(f"valve firmware host build {exe}: no pty announced "
                                 f"(got {' '.join(line)!r})")
        self.pty = line[1]

    def trigger(self) -> None:
        """Raise the trigger input (SIGUSR1), as the robot controller's output does."""
        os.kill(self.pid, signal.SIGUSR1)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def stop(self, timeout_s: float = 5.0) -> int:
        """SIGTERM (the firmware closes the valves and exits 0); returns the exit status."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        return self.proc.returncode

    def pulses(self) -> list[tuple[int, int, int, int]]:
        """(play, valve, tick, width_us) of every pulse in the pulse log so far."""
        if self.pulse_log is None:
            return []
        out = []
        deadline = time.monotonic() + 1.0
        while not self.pulse_log.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        for line in self.pulse_log.read_text().splitlines():
            parts = line.split()
            if parts and parts[0] == "pulse":
                out.append(tuple(int(x) for x in parts[1:5]))
        return out

    def __enter__(self) -> "HostFirmware":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
