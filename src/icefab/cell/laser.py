"""The control PC's driver for the Keyence LK-G laser controller (thesis 2.3.2, 5.2.1).

Protocol subset and its source: :mod:`icefab.cell.lkg`. Works the same on a real serial
port (``/dev/ttyS0``, 115 200 8N1) and on the emulator's pty
(:class:`icefab.cell.laser_emulator.PtyLaser`)::

    laser = LaserLink.open("/dev/ttyS0")     # CellError if the port cannot be opened
    laser.clear(); laser.start()             # before the measurement path
    ... the robot runs the path with the laser trigger ...
    laser.stop()
    values = laser.read_stored()             # (k,) float64 mm, NaN out of range
    samples = path_samples(path, values, job)   # (k, 3) x, y, z in the part frame

Every call raises :class:`~icefab.errors.CellError` with one line for an error response
(with its code's meaning), a malformed response or a timeout.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from icefab.cell import lkg
from icefab.errors import CellError

log = logging.getLogger(__name__)

__all__ = ["LaserLink", "path_samples", "sample_times", "stored_times"]


#: How long a link waits for the answer to the lone CR that ends a partial line, s.
FLUSH_S = 0.2


class LaserLink:
    """A serial connection to an LK-G controller (or its emulator)."""

    def __init__(self, port, *, timeout_s: float = 5.0, where: str = "laser"):
        self._port = port
        self.timeout_s = float(timeout_s)
        self.where = where
        self._buf = b""
        self._fresh = True   # no command answered yet on this link

    @classmethod
    def open(cls, device: str, *, timeout_s: float = 5.0) -> "LaserLink":
        import serial

        try:
            port = serial.Serial(device, baudrate=lkg.BAUD, bytesize=8, parity="N",
                                 stopbits=1, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise CellError(f"laser at {device}: cannot open the serial port ({exc})"
                            ) from None
        return cls(port, timeout_s=timeout_s, where=f"laser at {device}")

    def close(self) -> None:
        try:
            self._port.close()
        except Exception:  # pragma: no cover - already closed
            pass

    def __enter__(self) -> "LaserLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def command(self, text: str, timeout_s: float | None = None) -> list[str]:
        """Send one command; the response's fields after its header. CellError on an
        ``ER`` response, a response for another command, or no response in time."""
        cmd = text.split(",")[0].upper()
        try:
            self._port.reset_input_buffer()
            self._buf = b""
            self._port.write(text.encode("ascii") + lkg.CR)
        except Exception as exc:
            raise CellError(f"{self.where}: cannot send {cmd} ({exc})") from None
        line = self._read_line(self.timeout_s if timeout_s is None else timeout_s, cmd)
        fields = line.split(",")
        if self._fresh and fields[0] == "ER" and fields[2:3] == ["00"]:
            # a command error for the link's first command: bytes already on the line
            # (noise, a probe on the wrong port) were read in front of it, and a healthy
            # laser failed its check once (hunt W). A lone CR ends that partial line;
            # its answer is drained, and the command is sent once more
            self._fresh = False
            try:
                self._port.write(lkg.CR)
                time.sleep(FLUSH_S)
                self._port.reset_input_buffer()
            except Exception as exc:
                raise CellError(f"{self.where}: cannot send {cmd} ({exc})") from None
            return self.command(text, timeout_s)
        self._fresh = False
        if fields[0] == "ER":
            code = fields[2] if len(fields) > 2 else "??"
            raise CellError(f"{self.where}: {cmd} refused: error {code} "
                            f"({lkg.ERRORS.get(code, 'unknown code')})")
        if fields[0] != cmd:
            raise CellError(f"{self.where}: malformed response to {cmd}: {line[:40]!r}")
        return fields[1:]

    def _read_line(self, timeout_s: float, cmd: str) -> str:
        deadline = time.monotonic() + timeout_s
        while lkg.CR not in self._buf:
            if time.monotonic() > deadline:
                raise CellError(f"{self.where}: no response to {cmd} within {timeout_s:g} s")
            try:
                chunk = self._port.read(max(1, self._port.in_waiting))
            except Exception as exc:
                raise CellError(f"{self.where}: read failed ({exc})") from None
            self._buf += chunk
        line, self._buf = self._buf.split(lkg.CR, 1)
        try:
            return line.decode("ascii").strip()
        except UnicodeDecodeError:
            raise CellError(f"{self.where}: malformed response to {cmd}: not ASCII") from None

    # ------------------------------------------------------------------ the subset

    def current(self) -> float:
        """OUT1's current value, mm (NaN: out of range / no value)."""
        fields = self.command("M0")
        if not fields:
            raise CellError(f"{self.where}: malformed response to M0: no value")
        return lkg.parse_value(fields[0])

    def clear(self) -> None:
        """Empty the storage (``AQ``)."""
        self.command("AQ")

    def start(self) -> None:
        """Start storing (``AS``): a value per storage cycle while the timing input is high."""
        self.command("AS")

    def stop(self) -> None:
        """Stop storing (``AP``)."""
        self.command("AP")

    def status(self) -> tuple[bool, int]:
        """(storing, values stored) (``AN``)."""
        fields = self.command("AN")
        if len(fields) != 2 or fields[0] not in ("0", "1") or not fields[1].isdigit():
            raise CellError(f"{self.where}: malformed response to AN: {fields!r}")
        return fields[0] == "1", int(fields[1])

    def read_stored(self) -> np.ndarray:
        """The stored values of OUT1 (``AO,1``): (k,) float64 mm, NaN where the head had
        no value or was out of range. Waits long enough for 65 536 values at 115 200
        bit/s (about 60 s) on a real line."""
        fields = self.command("AO,1", timeout_s=max(self.timeout_s, 75.0))
        return np.array([lkg.parse_value(f) for f in fields], dtype=np.float64)


def sample_times(duration_s: float, rate_hz: float = lkg.RATE_HZ) -> np.ndarray:
    """Instants of the values stored along a path of ``duration_s`` from its trigger: one
    every ``1 / rate_hz`` s from 0 to the path's end (thesis 5.2.1: 100 Hz)."""
    n = int(math.floor(duration_s * rate_hz + 1e-9)) + 1
    return np.arange(n) / rate_hz


def stored_times(path, values_mm: np.ndarray, rate_hz: float) -> tuple[np.ndarray,
                                                                         np.ndarray]:
    """(t, values): the instants (s from the trigger) of the values stored along one
    measurement path, one per storage cycle, and the values as float64. Raises CellError
    if there are more values than the path's duration allows (storage not cleared)."""
    duration = max(len(path.xy) - 1, 0) * path.dt_s
    tk = sample_times(duration, rate_hz)
    vals = np.asarray(values_mm, dtype=np.float64).reshape(-1)
    if len(vals) > len(tk):
        raise CellError(f"laser: {len(vals)} stored values for a {duration:.3f} s path at "
                        f"{rate_hz:g} Hz (at most {len(tk)}): storage was not cleared, or "
                        "another path was stored")
    return tk[:len(vals)], vals


def path_samples(path, values_mm: np.ndarray, job, rate_hz: float | None = None
                 ) -> np.ndarray:
    """Laser samples (x, y, z) of one measurement path, part frame, mm.

    path: the :class:`~icefab.cell.robot.RobotPath` the robot ran (base-frame joint-4
    axis every ``dt_s``); values_mm: what :meth:`LaserLink.read_stored` returned for it
    (relative to the path's height ``z_mm``: the laser is zeroed at its reference
    distance, thesis 2.2). Sample k is tagged with where the laser spot was at
    ``k / rate_hz`` s (the robot trajectory interpolated in time; the laser frame of
    ``cell.laser_offset_mm``) and its height is ``z_mm + value``. Samples without a
    value (NaN) are dropped. Raises CellError if there are more values than the path's
    duration allows.
    """
    from icefab.frames import tool_offset

    rate = float(job.simulation.laser_rate_hz if rate_hz is None else rate_hz)
    xy = np.asarray(path.xy, dtype=np.float64) - (
        np.asarray(job.cell.ee_origin_mm, dtype=np.float64) - tool_offset("laser", job))
    t = np.arange(len(xy)) * path.dt_s
    tk, vals = stored_times(path, values_mm, rate)
    pos = np.column_stack([np.interp(tk, t, xy[:, 0]), np.interp(tk, t, xy[:, 1])])
    ok = np.isfinite(vals)
    return np.column_stack([pos[ok], path.z_mm + vals[ok]])
