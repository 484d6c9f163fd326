"""A virtual C40 speaking the robot link (:mod:`icefab.cell.robot_protocol`) on TCP.

It keeps the V+ server's state machine (:mod:`icefab.cell.vplus`): a ring of
``max_paths`` stored paths, uploads checked by count and check sum, ``GO`` for the oldest
stored path, ``DN`` with the path's sequence number when its motion is over, ``AB``
stopping at once with both triggers off, a repeated command answered with the same
reply. Motion takes ``(n - 1) * dt`` of cell time: as fast as possible
(``time_factor = 0``) or that time divided by ``time_factor`` of wall time.

What the robot's motion does to the world is left to a :class:`RobotHooks` (the virtual
cell: triggers to the valve controller and the laser, deposition): hooks run on the
motion thread, one path after another in the order the paths were run.
"""

from __future__ import annotations

import logging
import socket
import threading
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from icefab.cell import robot_protocol as rp
from icefab.cell.robot import RobotPath
from icefab.errors import CellError
from icefab.robots import CONTROLLER_PATH_POINTS

log = logging.getLogger(__name__)


class RobotHooks(Protocol):
    """What happens in the cell when the virtual robot acts (all on the motion thread)."""

    def layer_begin(self, layer: int, z_mm: float) -> None: ...

    def layer_end(self, layer: int) -> None: ...

    def path_run(self, seq: int, path: RobotPath, stop: threading.Event,
                 time_factor: float) -> bool:
        """Run one path: raise its triggers at time 0, take its motion time (``stop``
        set: abort now), drop the triggers. Returns False if it was stopped."""
        ...

    def abort(self) -> None: ...

    def refuse(self, path: RobotPath) -> int:
        """An ``ER`` code for a path the cell cannot run (0: none), checked when it has
        arrived whole."""
        ...


@dataclass
class _Upload:
    seq: int
    header: dict
    xs: list = field(default_factory=list)
    ys: list = field(default_factory=list)
    check: int = 0


class VirtualRobot:
    """The TCP server. ``start()`` binds 127.0.0.1:``port`` (0: any free port, see
    :attr:`port`) and serves one client at a time on a thread; ``stop()`` ends it."""

    def __init__(self, hooks: RobotHooks, *, port: int = 0, time_factor: float = 0.0,
                 max_points: int = CONTROLLER_PATH_POINTS, max_paths: int = 4, host: str = "127.0.0.1",
                 last_done: int = 0, cut: int = 0):
        self.hooks = hooks
        self.time_factor = float(time_factor)
        self.max_points = int(max_points)
        self.max_paths = int(max_paths)
        self._srv = socket.create_server((host, int(port)))
        self._srv.settimeout(0.2)   # accept wakes up to see stop()
        self.port = self._srv.getsockname()[1]
        self._lock = threading.RLock()
        self._stop_motion = threading.Event()
        self._quit = threading.Event()
        self._stored: list[tuple[int, RobotPath]] = []
        self._upload: _Upload | None = None
        self._moving: int = 0
        self._state = 0
        self._last_done = int(last_done)   # kept by the cell across restarts (its hooks)
        self._cut = int(cut)
        self._failed = False   # the cell model failed: no more paths (ERRORS[12])
        self._last: tuple[str, int, bytes] | None = None
        self._conn: socket.socket | None = None
        self._motion = threading.Thread(target=self._motion_loop, daemon=True)
        self._go = threading.Condition(self._lock)
        self._queue: list[int] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> "VirtualRobot":
        self._motion.start()
        self._thread.start()
        return self

    def stop(self) -> None:
        self._quit.set()
        self._stop_motion.set()
        with self._go:
            self._go.notify_all()
        try:
            self._srv.close()
        except OSError:  # pragma: no cover
            pass
        if self._conn is not None:
            try:
                self._conn.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
        self._thread.join(5)
        self._motion.join(5)

    def _serve(self) -> None:
        while not self._quit.is_set():
            try:
                conn, _ = self._srv.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(0.2)
            self._conn = conn
            buf = b""
            try:
                while not self._quit.is_set():
                    try:
                        chunk = conn.recv(65536)
                    except socket.timeout:
                        continue
                    if not chunk:
                        break
                    buf += chunk
                    while b"\n" in buf:
                        line, buf = buf.split(b"\n", 1)
                        self._handle(line)
                    if len(buf) > 4 * rp.MAX_LINE:
                        self._reply_error(0, 1, "")
                        buf = b""
            except OSError:
                pass
            finally:
                self._conn = None
                conn.close()

    def _send(self, data: bytes) -> None:
        conn = self._conn
        if conn is not None:
            try:
                conn.sendall(data)
            except OSError:
                pass

    def _reply(self, code: str, name: str, seq: int, *values) -> None:
        data = rp.encode(name, seq, *values)
        with self._lock:
            self._last = (code, seq, data)
        self._send(data)

    def _reply_error(self, seq: int, code: int, cmd: str) -> None:
        self._reply(cmd, "error", seq, code)

    # ------------------------------------------------------------------ commands

    def _handle(self, line: bytes) -> None:
        try:
            msg = rp.decode(line, "host")
        except CellError as exc:
            log.debug("virtual robot: %s", exc)
            seq = 0
            parts = line.split(b",")
            if len(parts) > 1 and parts[1].strip().isdigit():
                seq = min(int(parts[1]), rp.MAX_SEQ)
            with self._lock:
                if self._upload is not None and parts[0] == b"PP":
                    self._upload = None
            self._reply_error(seq, 1, "")
            return
        code = msg.message.code
        with self._lock:
            last = self._last
        if last is not None and code != "PP" and last[0] == code and last[1] == msg.seq:
            self._send(last[2])  # a repeat: same reply, not executed twice
            return
        getattr(self, "_on_" + msg.name)(msg)

    def _on_hello(self, msg: rp.Decoded) -> None:
        if msg["version"] != rp.VERSION:
            self._reply_error(msg.seq, 9, "HI")
            return
        self._reply("HI", "hello_reply", msg.seq, rp.VERSION, self.max_points, self.max_paths)

    def _on_layer_begin(self, msg: rp.Decoded) -> None:
        with self._go:
            self._queue.append(("layer_begin", (int(msg["layer"]), msg["z_um"] / 1000.0)))
            self._go.notify_all()
        self._reply("LB", "ok", msg.seq)

    def _on_layer_end(self, msg: rp.Decoded) -> None:
        with self._go:
            self._queue.append(("layer_end", (int(msg["layer"]),)))
            self._go.notify_all()
        self._reply("LE", "ok", msg.seq)

    def _on_path_begin(self, msg: rp.Decoded) -> None:
        with self._lock:
            if self._upload is not None:
                self._reply_error(msg.seq, 7, "PB")
                return
            if len(self._stored) >= self.max_paths:
                self._reply_error(msg.seq, 3, "PB")
                return
            if not 1 <= msg["npts"] <= self.max_points:
                self._reply_error(msg.seq, 4, "PB")
                return
            if msg["tool"] >= len(rp.TOOLS) or msg["dt_us"] == 0:
                self._reply_error(msg.seq, 1, "PB")
                return
            if not msg["flags"] & rp.FLAG_PARK and msg.seq < rp.FIRST_LINK_SEQ \
                    and msg.seq <= self._last_done:
                # a build's number runs once: a tester's client ran 5, 5 and 3, and the
                # last done went back to 3, so a resume would have run 4 and 5 again (the
                # link's own numbers start at random each session: not checked)
                self._reply_error(msg.seq, 11, "PB")
                return
            self._upload = _Upload(msg.seq, dict(msg.values))

    def _on_path_points(self, msg: rp.Decoded) -> None:
        with self._lock:
            up = self._upload
            if up is None:
                return
            if msg.seq != up.seq or msg["first"] != len(up.xs):
                self._upload = None
                self._reply_error(msg.seq, 2, "PE")
                return
            if len(up.xs) + msg["n"] > up.header["npts"]:
                self._upload = None
                self._reply_error(msg.seq, 5, "PE")
                return
            for x, y in msg.group:
                up.xs.append(x)
                up.ys.append(y)
                up.check = (up.check + rp.point_um(x) + rp.CHECK_OFFSET_UM
                            + rp.point_um(y) + rp.CHECK_OFFSET_UM) % rp.CHECK_MODULUS

    def _on_path_end(self, msg: rp.Decoded) -> None:
        with self._lock:
            up = self._upload
            if up is None:
                return
            self._upload = None
            if msg.seq != up.seq:
                self._reply_error(msg.seq, 2, "PE")
                return
            h = up.header
            if msg["npts"] != len(up.xs) or msg["npts"] != h["npts"] or \
                    msg["check"] != up.check:
                self._reply_error(msg.seq, 5, "PE")
                return
            path = RobotPath(xy=np.column_stack([up.xs, up.ys]).astype(np.float64),
                             dt_s=h["dt_us"] / 1e6, z_mm=h["z_um"] / 1000.0,
                             flags=int(h["flags"]), tool=rp.TOOLS[int(h["tool"])],
                             width_mm=float(h["width"]), layer=int(h["layer"]),
                             index=int(h["index"]))
            code = self.hooks.refuse(path) if hasattr(self.hooks, "refuse") else 0
            if self._failed:
                code = 12
            if code:
                self._reply_error(msg.seq, code, "PE")
                return
            self._stored.append((msg.seq, path))
        self._reply("PE", "ok", msg.seq)

    def _on_go(self, msg: rp.Decoded) -> None:
        with self._go:
            if self._failed:
                self._reply_error(msg.seq, 12, "GO")
                return
            if self._moving or any(q[0] == "go" for q in self._queue):
                self._reply_error(msg.seq, 7, "GO")
                return
            if not self._stored or self._stored[0][0] != msg.seq:
                self._reply_error(msg.seq, 6, "GO")
                return
            self._stop_motion.clear()
            self._state = 1
            self._moving = msg.seq
            self._queue.append(("go", (msg.seq,)))
            self._reply("GO", "ok", msg.seq)
            self._go.notify_all()

    def _on_abort(self, msg: rp.Decoded) -> None:
        self._stop_motion.set()
        with self._go:
            if self._moving:
                self._cut = self._moving   # reported in SS: never to be sent again
            self._stored.clear()
            self._upload = None
            self._queue = [q for q in self._queue if q[0] != "go"]
            self._state = 2
        self.hooks.abort()
        self._reply("AB", "ok", msg.seq)

    def _on_status(self, msg: rp.Decoded) -> None:
        with self._lock:
            vals = (self._state, len(self._stored), self._last_done, self._cut)
        self._reply("ST", "state", msg.seq, *vals)

    # ------------------------------------------------------------------ motion

    def _motion_loop(self) -> None:
        while True:
            with self._go:
                while not self._queue and not self._quit.is_set():
                    self._go.wait(0.5)
                if self._quit.is_set():
                    return
                kind, args = self._queue.pop(0)
                if kind == "go":
                    if not self._stored or self._stored[0][0] != args[0]:
                        self._moving = 0
                        continue
                    seq, path = self._stored[0]
            try:
                if kind == "layer_begin":
                    self.hooks.layer_begin(*args)
                elif kind == "layer_end":
                    self.hooks.layer_end(*args)
                else:
                    finished = self.hooks.path_run(seq, path, self._stop_motion,
                                                   self.time_factor)
                    with self._go:
                        self._moving = 0
                        if finished and not self._stop_motion.is_set():
                            self._stored.pop(0)
                            if not path.flags & rp.FLAG_PARK:
                                self._last_done = max(self._last_done, seq)
                            self._state = 0
                            done = True
                        else:
                            self._cut = seq
                            done = False
                            if not self._stop_motion.is_set():
                                # the cell cut it short (its valve program did not play
                                # to its end): the robot stops there, as after an abort,
                                # and a new session settles it
                                self._stored.clear()
                                self._state = 2
                    if done:
                        self._reply("GO", "done", seq, len(path.xy))
            except Exception:  # a bug in the cell model must not kill the robot silently
                log.exception("virtual robot: the cell failed while running %s", kind)
                with self._go:
                    self._moving = 0
                    self._state = 2
                    if kind == "go":
                        # it may have run (deposited) before the failure: cut, never run
                        # again; and no path after it (a full disk failed the surface's
                        # save after each deposit: one path was laid 21 times, a hunt's)
                        self._cut = seq
                        self._stored.clear()
                    self._failed = True
                if kind == "go":   # at once, not the link's timeout for a "done"
                    self._reply_error(seq, 12, "GO")
