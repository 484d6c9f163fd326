"""Driver of the valve microcontroller (thesis 2.3.1, 6.2) over its serial link.

The link is ``firmware/PROTOCOL.md``; the frames are :mod:`icefab.cell.valve_frames`. The
same code drives the LPC-H2148 on a real port (``/dev/ttyUSB0``) and the firmware's host
build on a pty: the port is opened with :func:`serial.serial_for_url` (pyserial).

What a path needs, as the thesis describes it (2.3.1): the "data ready" handshake
(:meth:`ValveController.hello`), the upload of the path's valve program in the binary
layout :mod:`icefab.flow` writes, checked end to end (:meth:`ValveController.upload`: the
controller's byte count, CRC-16 and pulse count must match what was sent; otherwise the
program is sent again), arming, the trigger from the robot controller, and the report of
what was played. Programs longer than the controller's 12 288-byte store stream while they
play (:meth:`ValveController.play`).

Every command carries a sequence number; a lost reply makes the driver send the same
frame again, which the controller answers without executing it twice. Ticks are 2 ms.
"""

from __future__ import annotations

import logging
import struct
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from icefab.errors import CellError
from icefab.cell import valve_frames as vf

log = logging.getLogger(__name__)

PART, SCAFFOLD = 0, 1
VALVES = {"part": PART, "scaffold": SCAFFOLD}


class ValveLinkError(CellError):
    """The valve controller cannot be reached, refused a command, or faulted; the message
    names the port, the command and the controller's answer."""


@dataclass
class Upload:
    """One program being sent: its bytes and how many of them the controller has."""

    valve: int
    data: bytes
    sent: int = 0
    attempts: int = 1

    @property
    def complete(self) -> bool:
        return self.sent == len(self.data)


@dataclass(frozen=True)
class PlayReport:
    """What the controller reports for one play (DONE event or STATUS).

    play: play number since the controller's reset; play_ticks: its length in 2 ms ticks;
    late_ticks: ticks handled more than a tick late; emitted: pulses per valve (part,
    scaffold); streamed_bytes: program bytes sent after the trigger.
    """

    play: int
    play_ticks: int
    late_ticks: int
    emitted: tuple[int, int]
    streamed_bytes: int = 0


def program_bytes(program: Any) -> bytes:
    """A :class:`icefab.core.ValveProgram` (with its pieces) or the bytes of its binary
    file, as bytes."""
    if isinstance(program, (bytes, bytearray, memoryview)):
        return bytes(program)
    from icefab.flow import encode_valve_program
    return encode_valve_program(program)


def _piece_headers(data: bytes) -> list[tuple[int, int]] | None:
    """(byte offset, pulses) of every piece of a complete program in flow's binary layout
    (None if it does not parse: the controller will say what is wrong)."""
    try:
        mode = data[6]
        (pieces,) = struct.unpack_from("<I", data, 12)
        pos, out = 16, []
        for _ in range(pieces):
            n, _dur = struct.unpack_from("<II", data, pos)
            out.append((pos, n))
            pos += 8 + 2 * n * (2 if mode == 1 else 1)
        return out
    except (struct.error, IndexError):
        return None


def count_pulses(data: bytes) -> int | None:
    """Pulses in a complete program in flow's binary layout (None if it does not parse:
    the controller will say what is wrong)."""
    pieces = _piece_headers(data)
    return None if pieces is None else sum(n for _pos, n in pieces)


class ValveController:
    """The control PC's side of the valve link.

    port: an open pyserial port (or anything with ``read``, ``write`` and ``close``);
        :meth:`open` makes one from a device path or URL.
    timeout_s: how long to wait for a reply before sending the frame again.
    retries: re-sends of one frame (and of one program failing verification) before
        :class:`ValveLinkError`.
    """

    def __init__(self, port: Any, *, name: str = "valve controller", timeout_s: float = 0.5,
                 retries: int = 5) -> None:
        self._port = port
        self.name = name
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self._reader = vf.FrameReader()
        self._seq = 0
        self.events: deque[vf.Frame] = deque(maxlen=1000)
        self.boots: list[str] = []      # the cause of every restart seen, in order
        self._boots_at_arm = 0
        self.resent_frames = 0
        self.resent_programs = 0
        self.info: vf.Hello | None = None

    # ------------------------------------------------------------------ opening

    @classmethod
    def open(cls, url: str, *, baudrate: int = 115200, **kwargs: Any) -> "ValveController":
        """Open ``url`` (a serial device, a pty path or a pyserial URL) at 115 200 8N1 and
        say "data ready" (HELLO)."""
        import serial

        try:
            port = serial.serial_for_url(url, baudrate=baudrate, bytesize=8, parity="N",
                                         stopbits=1, timeout=0.005)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise ValveLinkError(f"valve controller at {url}: cannot open its port ({exc})") \
                from None
        # named as the robot's and laser's links are ("robot at ...", "laser at ..."): a
        # pty path alone did not say which device failed (a hunt's)
        ctl = cls(port, name=f"valve controller at {url}", **kwargs)
        try:
            ctl.hello()
        except ValveLinkError:
            port.close()
            raise
        return ctl

    def close(self) -> None:
        self._port.close()

    def __enter__(self) -> "ValveController":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ frames

    def _write(self, frame: bytes) -> None:
        try:
            self._port.write(frame)
        except OSError as exc:    # pyserial's SerialException too: the port is gone
            raise ValveLinkError(f"{self.name}: the serial link failed while sending "
                                 f"({exc})") from None

    def _poll(self) -> list[vf.Frame]:
        try:
            data = self._port.read(4096)
        except OSError as exc:
            raise ValveLinkError(f"{self.name}: the serial link failed while reading "
                                 f"({exc})") from None
        frames = self._reader.feed(data, time.monotonic()) if data else []
        for f in frames:
            if f.is_event:
                self.events.append(f)
                if f.type == vf.EV_FAULT:
                    ev = vf.parse_fault(f.payload)
                    log.warning("%s: fault %s", self.name, vf.FAULTS.get(ev.fault, ev.fault))
                elif f.type == vf.EV_BOOT:
                    self.boots.append(vf.boot_cause(f.payload))
                    log.warning("%s: the controller restarted (%s)", self.name,
                                self.boots[-1])
        return [f for f in frames if not f.is_event]

    def request(self, type_: int, payload: bytes = b"", *,
                allow: frozenset[int] = frozenset()) -> vf.Frame:
        """Send one command and return its reply frame (re-sent on silence or a link
        error; a SEQUENCE error re-opens the session with HELLO and sends it again).
        An ERROR reply raises :class:`ValveLinkError` unless its code is in ``allow``."""
        seq = self._seq & 0xFF
        frame = vf.encode(seq, type_, payload)
        for _attempt in range(self.retries + 1):
            self._write(frame)
            deadline = time.monotonic() + self.timeout_s
            resend = False
            while not resend and time.monotonic() < deadline:
                for f in self._poll():
                    if f.is_error:
                        err = vf.parse_error(f.payload)
                        if err.code in vf.LINK_ERRORS:
                            resend = True         # our frame may be the damaged one
                            continue
                        # ours only if it names our SEQ and TYPE: a trigger edge with
                        # nothing armed is answered with SEQ 0xFF, a valid command number
                        if f.seq != seq or err.type != type_:
                            continue
                        if err.code == vf.E_SEQUENCE:  # controller restarted: new session
                            self._hello_seq(seq)
                            seq = self._seq & 0xFF
                            frame = vf.encode(seq, type_, payload)
                            resend = True
                            break
                        self._seq += 1
                        if err.code in allow:
                            return f
                        raise ValveLinkError(f"{self.name}: command 0x{type_:02x} refused: "
                                             f"{err.describe()}")
                    elif f.seq == seq and f.type == (type_ | 0x80):
                        self._seq += 1
                        return f
            self.resent_frames += 1
        # the controller may have run it and its replies been lost: the next command takes
        # the next SEQ, or the controller would take it for a repeat and send this one's
        # cached reply without running it (an ABORT after a lost TRIGGER reply did not
        # abort); if it never saw this one, the next gets SEQUENCE and a new session
        self._seq += 1
        raise ValveLinkError(f"{self.name}: no answer to command 0x{type_:02x} after "
                             f"{self.retries + 1} tries of {self.timeout_s:g} s")

    def _hello_seq(self, seq: int) -> vf.Hello:
        """HELLO with ``seq`` (accepted whatever the controller expects)."""
        frame = vf.encode(seq, vf.HELLO, vf.hello_payload())
        for _ in range(self.retries + 1):
            self._write(frame)
            deadline = time.monotonic() + self.timeout_s
            while time.monotonic() < deadline:
                for f in self._poll():
                    if f.seq == seq and f.type == (vf.HELLO | 0x80):
                        self.info = vf.parse_hello(f.payload)
                        self._seq = seq + 1
                        return self.info
            self.resent_frames += 1
        raise ValveLinkError(f"{self.name}: no answer to HELLO ('data ready')")

    # ------------------------------------------------------------------ commands

    def hello(self) -> vf.Hello:
        """The thesis' "data ready" sequence: opens a session; returns the controller's
        limits (tick, store size, valves). ValveLinkError if its tick is not 2 ms."""
        info = self._hello_seq(self._seq & 0xFF)
        if info.version != vf.PROTOCOL_VERSION or info.tick_us != vf.TICK_US:
            raise ValveLinkError(f"{self.name}: controller speaks protocol {info.version} "
                                 f"with {info.tick_us} us ticks; expected "
                                 f"{vf.PROTOCOL_VERSION} and {vf.TICK_US} us")
        return info

    def status(self) -> vf.Status:
        return vf.parse_status(self.request(vf.STATUS).payload)

    def configure(self, valve: int, pulse_us: int) -> None:
        """FM pulse width of ``valve`` in microseconds (1..65535)."""
        if not 1 <= int(pulse_us) <= 65535:
            raise ValveLinkError(f"{self.name}: valve pulse width {pulse_us} us: expected "
                                 "1..65535")
        self.request(vf.CONFIG, vf.config_payload(valve, int(pulse_us)))

    def abort(self) -> tuple[int, int]:
        """Every valve off at once, every program discarded, a fault cleared. Returns the
        pulses each valve had emitted in the play it stopped."""
        p = self.request(vf.ABORT).payload
        return struct.unpack_from("<II", p, 2)

    def arm(self, valves: int | list[int] | tuple[int, ...]) -> int | None:
        """Arm the next program of each valve; returns the play length in ticks (None
        while a program still streams)."""
        idx = [valves] if isinstance(valves, int) else list(valves)
        mask = 0
        for v in idx:
            mask |= 1 << int(v)
        length = struct.unpack_from("<I", self.request(vf.ARM, bytes((mask,))).payload, 2)[0]
        self._boots_at_arm = len(self.boots)
        return None if length == 0xFFFFFFFF else length

    def _restarted(self) -> str:
        """' (it restarted: CAUSE)' when a BOOT event came since the last ARM, else ''."""
        new = self.boots[self._boots_at_arm:]
        return f" (it restarted: {new[-1]})" if new else ""

    def trigger(self) -> None:
        """Software trigger (host builds only; the LPC2148 takes the robot's signal)."""
        self.request(vf.TRIGGER)

    def stall(self, ms: int) -> None:
        """Stop the controller's main loop feeding its watchdog for ``ms`` (host builds)."""
        self.request(vf.STALL, struct.pack("<I", int(ms)))

    def verify(self, valve: int) -> vf.Verify:
        return vf.parse_verify(self.request(vf.PROG_VERIFY, bytes((valve,))).payload)

    # ------------------------------------------------------------------ programs

    def send_data(self, up: Upload, free: int) -> int:
        """Send as much of ``up`` as fits in ``free`` bytes of the store; returns the free
        bytes the controller reports after."""
        while not up.complete and free > 0:
            n = min(vf.MAX_DATA, len(up.data) - up.sent, free)
            r = self.request(vf.PROG_DATA,
                             vf.data_payload(up.valve, up.sent, up.data[up.sent:up.sent + n]),
                             allow=frozenset({vf.E_NO_ROOM}))
            if r.is_error:                # NO_ROOM although it fitted: a PWM piece
                limit = vf.PWM_PIECE_MAX   # too large to stream from the store
                pwm = up.data[6:7] == b"\x01"
                bad = [(pos, n) for pos, n in (_piece_headers(up.data) or []) if n > limit
                       and pwm]
                where = (f"its piece at byte {bad[0][0]} ({bad[0][1]} pulses)" if bad
                         else "a piece")
                raise ValveLinkError(
                    f"{self.name}: valve {up.valve} program refused: {where}; a PWM piece "
                    f"of more than {limit} pulses does not fit the controller's "
                    f"{vf.STORE_BYTES}-byte store (its widths follow all its ticks and go at "
                    "its end, and the next piece streams in beside them); lower "
                    "flow.max_pulses")
            up.sent += n
            free = struct.unpack_from("<I", r.payload, 5)[0]
        return free

    def upload(self, valve: int, program: Any, *, verify: bool = True) -> Upload:
        """Send one valve program (a ValveProgram or its binary file's bytes): PROG_BEGIN,
        PROG_DATA until it is all there or the store is full (the rest streams during
        :meth:`play`), then PROG_VERIFY. On a mismatch of byte count, CRC or (complete
        programs) pulse count, the program is sent again (``retries`` times)."""
        data = program_bytes(program)
        up = Upload(valve, data)
        for attempt in range(self.retries + 1):
            up.sent = 0
            up.attempts = attempt + 1
            r = self.request(vf.PROG_BEGIN, vf.begin_payload(valve, len(data), replace=attempt > 0))
            free = struct.unpack_from("<I", r.payload, 2)[0]
            self.send_data(up, free)
            if not verify:
                return up
            got = self.verify(valve)
            want_pulses = count_pulses(data) if up.complete else None
            if (got.received == up.sent and got.crc == vf.crc16(data[:up.sent])
                    and got.complete == up.complete
                    and (want_pulses is None or got.pulses == want_pulses)):
                return up
            self.resent_programs += 1
            log.warning("%s: valve %d program verification failed (controller %d bytes CRC "
                        "0x%04x, sent %d bytes CRC 0x%04x); sending it again", self.name, valve,
                        got.received, got.crc, up.sent, vf.crc16(data[:up.sent]))
        raise ValveLinkError(f"{self.name}: valve {valve} program failed verification "
                             f"{self.retries + 1} times")

    def play(self, programs: Mapping[int, Any], *,
             trigger: str | Callable[[], None] | None = "command",
             timeout_s: float | None = None, poll_s: float = 0.005) -> PlayReport:
        """Upload, verify and arm one program per valve (``{valve: program}``), trigger,
        stream what did not fit while it plays, and wait for the end.

        trigger: "command" (host builds), a callable that raises the trigger input (e.g.
            the robot link), or None (the robot program raises it by itself).
        timeout_s: give up (ABORT, every valve off, ValveLinkError) after this long
            (default: 1.5 x the longest program + 10 s).
        """
        ups = [self.upload(int(v), p) for v, p in programs.items()]
        if not ups:
            raise ValveLinkError(f"{self.name}: play needs at least one program")
        if timeout_s is None:
            timeout_s = 10.0 + 1.5 * max(_duration_s(u.data) for u in ups)
        play = (self.status().plays + 1) & 0xFFFF
        self.events.clear()
        self.arm([u.valve for u in ups])
        if trigger == "command":
            self.trigger()
        elif callable(trigger):
            trigger()
        return self.wait_done(play, ups, timeout_s=timeout_s, poll_s=poll_s)

    def wait_done(self, play: int, streaming: "list[Upload] | tuple[Upload, ...]" = (), *,
                  timeout_s: float = 600.0, poll_s: float = 0.005) -> PlayReport:
        """Wait for the end of play number ``play`` (STATUS ``plays`` + 1 when it was
        armed), sending the rest of every incomplete upload in ``streaming`` as room frees
        up. Meanwhile the caller may have uploaded and armed the next path (queued ARM).

        Raises ValveLinkError on a fault (every valve is then off) or after ``timeout_s``
        (the controller is aborted first)."""
        streamed = 0
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if st.state == vf.FAULT:
                raise ValveLinkError(f"{self.name}: controller fault '{st.fault_name}' during "
                                     f"play {play}{self._restarted()}; every valve is off")
            done = self._done_event(play)
            if done is not None:
                return PlayReport(done.play, done.play_len, done.late_ticks, done.emitted, streamed)
            for u in streaming:
                if not u.complete:
                    sent = u.sent
                    self.send_data(u, st.valves[u.valve].free)
                    streamed += u.sent - sent
            if st.plays == play and st.state not in (vf.PLAYING, vf.ARMED):  # DONE lost
                return PlayReport(st.plays, st.play_len, st.late_ticks,
                                  (st.valves[0].emitted, st.valves[1].emitted), streamed)
            if 0 < (st.plays - play) & 0xFFFF < 0x8000:
                raise ValveLinkError(f"{self.name}: play {play} ended but its DONE report was "
                                     f"lost (play {st.plays} runs now)")
            if st.plays != play and st.state not in (vf.PLAYING, vf.ARMED):
                # neither armed nor playing any more: the controller restarted (power, a
                # brown-out: it comes up idle, its count at 0) or someone aborted it. It
                # was noticed only at the timeout, 1.5 times the path plus 10 s later,
                # with the robot moving and nothing laid meanwhile (a review's)
                why = self._restarted() or (f" (the controller is {st.state_name} after "
                                            f"{st.plays} plays: it restarted, or it was "
                                            "aborted)")
                raise ValveLinkError(f"{self.name}: play {play} is no longer armed or "
                                     f"playing{why}; every valve is off")
            if time.monotonic() > deadline:
                self.abort()
                raise ValveLinkError(f"{self.name}: play {play} did not end within "
                                     f"{timeout_s:g} s; aborted, every valve is off")
            if all(u.complete for u in streaming):
                time.sleep(poll_s)

    def _done_event(self, play: int) -> vf.Done | None:
        for f in list(self.events):
            if f.type == vf.EV_DONE:
                d = vf.parse_done(f.payload)
                if d.play == play:
                    return d
        return None


def _duration_s(data: bytes) -> float:
    """Total duration of a program in flow's binary layout, s (0 if it does not parse)."""
    try:
        (pieces,) = struct.unpack_from("<I", data, 12)
        mode = data[6]
        pos, total = 16, 0
        for _ in range(pieces):
            n, dur = struct.unpack_from("<II", data, pos)
            total += dur
            pos += 8 + 2 * n * (2 if mode == 1 else 1)
        return total * 1e-6
    except (struct.error, IndexError):
        return 0.0
