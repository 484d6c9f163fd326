"""An emulator of the LK-G subset in :mod:`icefab.cell.lkg`, on a pty or in memory.

:class:`LaserController` is the device: its storage, the command interpreter
(:meth:`LaserController.handle`: one command line in, one response line out) and the
timing input (:meth:`LaserController.timing_path`: the C40 holds the input high for one
measurement path; while storage runs, one value per storage cycle is stored, starting at
the rising edge). What the head reads is given by the caller (the virtual cell's laser
model). :class:`PtyLaser` serves a controller on a pseudo-terminal, so the driver
(:class:`icefab.cell.laser.LaserLink`) talks to it as to a serial port.
"""

from __future__ import annotations

import logging
import os
import threading

import numpy as np

from icefab.cell import lkg

log = logging.getLogger(__name__)


class LaserController:
    """The emulated LK-G3001P: storage of up to 65 536 values, the commands of
    :data:`icefab.cell.lkg.COMMANDS`. Thread-safe."""

    def __init__(self, capacity: int = lkg.STORAGE_CAPACITY):
        self.capacity = int(capacity)
        self._values: list[float] = []
        self._storing = False
        self._current = (float("nan"), float("nan"))
        self._lock = threading.Lock()

    @property
    def storing(self) -> bool:
        return self._storing

    def timing_path(self, values_mm: np.ndarray) -> int:
        """The timing input was high for one path while the head read ``values_mm`` (one
        per storage cycle from the rising edge). Stored if storage runs, up to capacity;
        returns how many were stored."""
        vals = np.asarray(values_mm, dtype=np.float64).reshape(-1)
        with self._lock:
            if len(vals):
                self._current = (float(vals[-1]), float("nan"))
            if not self._storing:
                return 0
            room = self.capacity - len(self._values)
            take = vals[:max(room, 0)]
            self._values.extend(take.tolist())
            if len(self._values) >= self.capacity:
                self._storing = False  # storage full: it stops by itself
            return len(take)

    def handle(self, line: str) -> str:
        """One command (without its CR) -> the response (without its CR)."""
        text = line.strip()
        if len(text) > lkg.MAX_COMMAND:
            return f"ER,{text[:2].upper()},20"
        parts = text.upper().split(",")
        cmd = parts[0]
        if cmd not in lkg.COMMANDS:
            return f"ER,{cmd[:2]},00"
        if len(parts) - 1 != lkg.COMMANDS[cmd]:
            return f"ER,{cmd},21"
        with self._lock:
            if cmd == "M0":
                return "M0," + ",".join(lkg.format_value(v) for v in self._current)
            if cmd == "AS":
                self._storing = True
                return "AS"
            if cmd == "AP":
                self._storing = False
                return "AP"
            if cmd == "AQ":
                if self._storing:
                    return "ER,AQ,01"
                self._values = []
                return "AQ"
            if cmd == "AN":
                return f"AN,{int(self._storing)},{len(self._values)}"
            # AO,<out>: output the stored values of OUT1 (the one head icefab uses)
            if parts[1] not in ("1", "01"):
                return "ER,AO,22"
            if self._storing:
                return "ER,AO,01"
            return ",".join(["AO"] + [lkg.format_value(v) for v in self._values])


class PtyLaser:
    """A :class:`LaserController` on a pseudo-terminal: :attr:`path` is the serial
    device a driver opens. Commands are read up to CR; each gets its response and CR."""

    def __init__(self, controller: LaserController | None = None):
        self.controller = controller or LaserController()
        self._master, slave = os.openpty()
        self.path = os.ttyname(slave)
        import tty

        tty.setraw(slave)
        self._slave = slave   # kept open so the pty stays while no client is connected
        self._quit = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def start(self) -> "PtyLaser":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._quit.set()
        self._thread.join(2)
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def _serve(self) -> None:
        import select

        buf = b""
        while not self._quit.is_set():
            r, _, _ = select.select([self._master], [], [], 0.1)
            if not r:
                continue
            try:
                chunk = os.read(self._master, 4096)
            except OSError:
                return
            buf += chunk
            while lkg.CR in buf:
                line, buf = buf.split(lkg.CR, 1)
                # a byte beyond ASCII becomes "?": echoed in the error reply, it had
                # killed this thread (the reply's ASCII encoding raised) and every later
                # measurement timed out
                text = line.decode("ascii", errors="replace").replace("\ufffd", "?")
                text = text.lstrip("\n")
                if not text:
                    continue
                self._write(self.controller.handle(text).encode("ascii") + lkg.CR)
            if len(buf) > 4 * lkg.MAX_COMMAND:
                self._write(b"ER,??,20" + lkg.CR)
                buf = b""

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
            except BlockingIOError:  # pragma: no cover - the reader is slow
                continue
            except OSError:
                return
            view = view[n:]
