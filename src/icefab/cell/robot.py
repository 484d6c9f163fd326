"""The control PC's side of the robot link (protocol: :mod:`icefab.cell.robot_protocol`).

The API the build runner uses::

    link = RobotLink.connect("127.0.0.1", 7100)     # CellError if nobody answers
    info = link.hello()
    link.begin_layer(layer, z_mm)
    for p in robot_paths(layer_motion, job):         # RobotPath: what the robot needs
        seq = link.upload(p)                          # stored on the controller, OK'd
        link.go(seq)                                  # motion starts (triggers raised)
        done = link.wait_done(seq)                    # motion over, triggers dropped
    link.end_layer(layer)
    link.abort()                                      # any time: stop, triggers off

``upload`` of the next path may be sent while the previous one moves (the controller
stores ``max_paths``), so the robot never waits for data. Every call raises
:class:`~icefab.errors.CellError` with one line on a refused command, a malformed reply,
a closed connection or a timeout.
"""

from __future__ import annotations

import logging
import secrets
import socket
import time
from dataclasses import dataclass

import numpy as np

from icefab.cell import robot_protocol as rp
from icefab.errors import CellError, CellRefused

log = logging.getLogger(__name__)

__all__ = ["RobotPath", "RobotInfo", "RobotLink", "robot_paths", "path_flags"]


@dataclass(frozen=True, eq=False)
class RobotPath:
    """One path as the controller gets it (thesis 4.3: constant dt, speed in the spacing).

    xy: (n, 2) float64, mm, joint-4 axis positions in the robot base frame, one every
        ``dt_s`` (the planner's ``Trajectory.xy``).
    dt_s: point-to-point duration, s (V+ ``DURATION``).
    z_mm: height of the path (the layer's nominal top), mm above the build platform.
    flags: :data:`~icefab.cell.robot_protocol.FLAG_VALVE` | ``FLAG_LASER``: which triggers
        the controller raises for the path.
    tool: one of :data:`~icefab.cell.robot_protocol.TOOLS` (the tool point the path was
        planned for; the controller records it, the virtual cell deposits under it).
    width_mm: deposition width (recorded; the virtual cell uses it); 0 when not depositing;
        a variable-width path's nominal (mean) width: the controller needs none, and the
        virtual cell spreads the valve program's drops (whose volumes follow the width)
        over it.
    layer, index: toolpaths layer index and the trajectory's index in that layer.
    """

    xy: np.ndarray
    dt_s: float
    z_mm: float
    flags: int
    tool: str
    width_mm: float
    layer: int
    index: int

    @property
    def duration_s(self) -> float:
        return max(len(self.xy) - 1, 0) * self.dt_s


@dataclass(frozen=True)
class RobotInfo:
    """The controller's ``HI`` reply: protocol version, points per path, stored paths."""

    version: int
    max_points: int
    max_paths: int


@dataclass(frozen=True)
class DoneReport:
    """A ``DN``: the path with ``seq`` ran to its end through ``points`` points."""

    seq: int
    points: int


def path_flags(role: str) -> int:
    """Triggers for a path role: deposition paths raise the valve trigger, measurement
    paths the laser trigger, travel none (thesis 2.3, Fig. 2-5)."""
    if role in ("boundary", "fill"):
        return rp.FLAG_VALVE
    if role == "measure":
        return rp.FLAG_LASER
    return 0


def robot_paths(layer, job) -> list[RobotPath]:
    """The robot paths of one ``icefab.motion.LayerMotion``: every trajectory with at least
    one sample, in order (travel included, without triggers), at the top of the layer
    being deposited (``layer.top(job)``; measurement paths read that top). It sent the
    layer's cutting plane ``layer.z``, inside the layer, where the build runner sends the
    top (a review's)."""
    from icefab import flow

    out = []
    z = float(layer.top(job))
    for k, tr in enumerate(layer.trajectories):
        if len(tr.xy) == 0:
            continue
        p = tr.path
        role = p.role if p is not None else "travel"
        if role == "measure":
            tool = "laser"
        elif p is not None and p.depositing:
            tool = p.material
        else:
            tool = "none"
        width = flow.trajectory_width(tr, p.material, job) if tool in ("part", "scaffold") \
            else 0.0
        out.append(RobotPath(xy=np.asarray(tr.xy, dtype=np.float64), dt_s=float(tr.dt),
                             z_mm=z, flags=path_flags(role), tool=tool, width_mm=width,
                             layer=int(layer.index), index=k))
    return out


class RobotLink:
    """A TCP connection to the V+ server (or the virtual robot). See the module doc."""

    def __init__(self, sock: socket.socket, *, timeout_s: float = 10.0, where: str = ""):
        self._sock = sock
        self._buf = b""
        # the link's own numbers: the upper half, from a random point (robot_protocol)
        self._seq = rp.FIRST_LINK_SEQ + secrets.randbelow(rp.MAX_SEQ - rp.FIRST_LINK_SEQ)
        self._done: dict[int, DoneReport] = {}
        self.timeout_s = float(timeout_s)
        self.where = where
        self.info: RobotInfo | None = None

    # ------------------------------------------------------------------ connection

    @classmethod
    def connect(cls, host: str, port: int, *, timeout_s: float = 10.0) -> "RobotLink":
        """Open the link; CellError naming HOST:PORT when it cannot be reached."""
        where = f"robot at {host}:{port}"
        try:
            sock = socket.create_connection((host, int(port)), timeout=timeout_s)
        except (OSError, ValueError) as exc:
            raise CellError(f"{where}: cannot connect ({getattr(exc, 'strerror', None) or exc})"
                            ) from None
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return cls(sock, timeout_s=timeout_s, where=where)

    def close(self) -> None:
        try:
            self._sock.close()
        except OSError:  # pragma: no cover - already gone
            pass

    def __enter__(self) -> "RobotLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ plumbing

    def _next_seq(self) -> int:
        self._seq = self._seq + 1 if self._seq < rp.MAX_SEQ else rp.FIRST_LINK_SEQ
        return self._seq

    def _send(self, data: bytes) -> None:
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise CellError(f"{self.where}: connection lost while sending ({exc})") from None

    def _read_line(self, deadline: float) -> bytes:
        while b"\n" not in self._buf:
            left = deadline - time.monotonic()
            if left <= 0:
                raise CellError(f"{self.where}: no reply within {self.timeout_s:g} s")
            self._sock.settimeout(left)
            try:
                chunk = self._sock.recv(65536)
            except socket.timeout:
                continue
            except OSError as exc:
                raise CellError(f"{self.where}: connection lost ({exc})") from None
            if not chunk:
                raise CellError(f"{self.where}: the controller closed the connection")
            self._buf += chunk
            if len(self._buf) > 64 * rp.MAX_LINE and b"\n" not in self._buf:
                raise CellError(f"{self.where}: malformed reply: no line end in "
                                f"{len(self._buf)} bytes")
        line, self._buf = self._buf.split(b"\n", 1)
        return line

    def _await(self, seq: int, names: tuple[str, ...], timeout_s: float | None = None
               ) -> rp.Decoded:
        """The reply to ``seq`` (one of ``names``); DN of other paths are kept."""
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            try:
                msg = rp.decode(self._read_line(deadline), "robot")
            except CellError as exc:   # the decoder's own words name no device (hunt W)
                if str(exc).startswith(self.where):
                    raise
                raise CellError(f"{self.where}: {exc}") from None
            if msg.name == "done":
                self._done[msg.seq] = DoneReport(msg.seq, int(msg["points"]))
                if "done" in names and msg.seq == seq:
                    return msg
                continue
            if msg.seq != seq:
                raise CellError(f"{self.where}: reply {msg.message.code} for sequence "
                                f"{msg.seq} while waiting for {seq}")
            if msg.name == "error":
                code = int(msg["code"])
                kind = CellRefused if code in rp.PERMANENT_ERRORS else CellError
                raise kind(f"{self.where}: command {seq} refused: error {code} "
                           f"({rp.ERRORS.get(code, 'unknown code')})")
            if msg.name not in names:
                raise CellError(f"{self.where}: unexpected reply {msg.message.code} to "
                                f"command {seq}")
            return msg

    def _command(self, name: str, *values: float, reply: tuple[str, ...] = ("ok",)
                 ) -> rp.Decoded:
        seq = self._next_seq()
        self._send(rp.encode(name, seq, *values))
        return self._await(seq, reply)

    # ------------------------------------------------------------------ commands

    def hello(self) -> RobotInfo:
        """Open the session; the controller's limits (:class:`RobotInfo`)."""
        try:
            msg = self._command("hello", rp.VERSION, reply=("hello_reply",))
        except CellError as exc:
            if "no reply within" not in str(exc):
                raise
            # the controller serves one client at a time: a second build (or 'icefab cell
            # check') on a busy cell waits unanswered
            raise CellError(f"{exc} to its handshake: is another build or session "
                            "connected to it? (the controller serves one at a time)") from None
        self.info = RobotInfo(int(msg["version"]), int(msg["max_points"]),
                              int(msg["max_paths"]))
        return self.info

    def begin_layer(self, layer: int, z_mm: float) -> None:
        self._command("layer_begin", int(layer), _um(z_mm, "layer height"))

    def end_layer(self, layer: int, seq: int | None = None) -> None:
        """``LE``; ``seq``: a build's journal number (a repeat after a crash is answered,
        not executed twice), else the link's next one."""
        if seq is None:
            self._command("layer_end", int(layer))
        else:
            self._send(rp.encode("layer_end", int(seq), int(layer)))
            self._await(int(seq), ("ok",))

    def upload(self, path: RobotPath, seq: int | None = None) -> int:
        """Store one path on the controller; returns its sequence number (reported back
        by :meth:`wait_done`): ``seq`` (a build's journal number, 1 ..
        ``FIRST_LINK_SEQ`` - 1) or the link's next one. CellRefused for a path no
        controller takes (checked here first) or one this controller refuses for good."""
        xy = np.asarray(path.xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) == 0 or not np.isfinite(xy).all():
            raise CellRefused(f"layer {path.layer} path {path.index}: points must be a "
                            "non-empty finite (n, 2) array")
        if self.info is not None and len(xy) > self.info.max_points:
            raise CellRefused(f"layer {path.layer} path {path.index}: {len(xy)} points, the "
                            f"controller takes {self.info.max_points} per path")
        if path.tool not in rp.TOOLS:
            raise CellRefused(f"layer {path.layer} path {path.index}: tool {path.tool!r}; "
                            f"expected one of {', '.join(rp.TOOLS)}")
        if seq is None:
            seq = self._next_seq()
        elif not 1 <= int(seq) < rp.FIRST_LINK_SEQ:
            raise CellRefused(f"layer {path.layer} path {path.index}: sequence number {seq}: "
                            f"expected 1..{rp.FIRST_LINK_SEQ - 1}")
        seq = int(seq)
        dt_us = int(round(path.dt_s * 1e6))
        if abs(dt_us - path.dt_s * 1e6) > 1e-6 * max(1.0, path.dt_s * 1e6):
            raise CellRefused(f"layer {path.layer} path {path.index}: time step "
                            f"{path.dt_s!r} s is not a whole number of microseconds")
        lines = [rp.encode("path_begin", seq, int(path.layer), int(path.index),
                           int(path.flags), rp.TOOLS.index(path.tool),
                           float(path.width_mm), len(xy), dt_us,
                           _um(path.z_mm, "path height"))]
        k = rp.POINTS_PER_LINE
        for i in range(0, len(xy), k):
            chunk = xy[i:i + k]
            lines.append(rp.encode("path_points", seq, i, len(chunk),
                                   group=tuple(map(tuple, chunk))))
        lines.append(rp.encode("path_end", seq, len(xy), rp.point_check(xy[:, 0], xy[:, 1])))
        self._send(b"".join(lines))
        self._await(seq, ("ok",))
        return seq

    def go(self, seq: int) -> None:
        """Run the stored path ``seq`` (the oldest stored one); returns when it started."""
        self._send(rp.encode("go", seq))
        self._await(seq, ("ok",))

    def wait_done(self, seq: int, timeout_s: float | None = None) -> DoneReport:
        """Wait for the ``DN`` of path ``seq`` (default timeout: the link's)."""
        if seq in self._done:
            return self._done.pop(seq)
        self._await(seq, ("done",), timeout_s)
        return self._done.pop(seq)

    def run(self, path: RobotPath, timeout_s: float | None = None) -> DoneReport:
        """Upload, run and wait for one path."""
        seq = self.upload(path)
        self.go(seq)
        return self.wait_done(seq, timeout_s if timeout_s is not None
                              else self.timeout_s + path.duration_s)

    def abort(self) -> None:
        """Stop the motion at once, drop both triggers, discard stored paths."""
        self._command("abort")

    def status(self) -> dict:
        """``{"state": "idle"|"moving"|"aborted", "stored": n, "last_done": seq,
        "cut": seq}``: the number of the last path run to its end and of the last one an
        abort or fault stopped mid-motion (0: none)."""
        msg = self._command("status", reply=("state",))
        return {"state": rp.STATES.get(int(msg["state"]), str(msg["state"])),
                "stored": int(msg["stored"]), "last_done": int(msg["last_done"]),
                "cut": int(msg["cut"])}


def _um(value_mm: float, what: str) -> int:
    v = float(value_mm)
    if not (np.isfinite(v) and 0 <= v * 1000 <= rp.MAX_INT):
        raise CellError(f"{what} {value_mm!r} mm: expected 0 .. {rp.MAX_INT / 1000:g} mm")
    return int(round(v * 1000))


def as_received(motion):
    """The trajectories as the controller stores them: every sample rounded to the
    micrometre exactly as the wire carries it (``%.3f`` mm text read back), the rest
    unchanged. Simulating these (``icefab simulate``) and running them through the
    virtual cell deposit along the same points."""
    import dataclasses

    def wire(xy: np.ndarray) -> np.ndarray:
        flat = [float(rp._fmt(v, "mm", "point")) for v in np.asarray(xy, np.float64).ravel()]
        return np.array(flat, dtype=np.float64).reshape(np.shape(xy))

    layers = tuple(dataclasses.replace(lm, trajectories=tuple(
        dataclasses.replace(t, xy=wire(t.xy)) for t in lm.trajectories))
        for lm in motion.layers)
    return dataclasses.replace(motion, layers=layers)
