"""Frames of the valve controller link (``firmware/PROTOCOL.md``, the one normative text).

Pure bytes in, bytes out: no serial port here (:mod:`icefab.cell.valve` drives one).

Frame (both directions, little-endian)::

    0xA5 0x5A | LEN (0..240) | SEQ | TYPE | payload (LEN bytes) | CRC-16 (2)

CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over LEN, SEQ, TYPE and the payload, computed
by :func:`binascii.crc_hqx`. The constants below mirror ``firmware/core/protocol.h``
(a test compares them).
"""

from __future__ import annotations

import binascii
import math
import struct
from dataclasses import dataclass

MARK = b"\xa5\x5a"
MAX_PAYLOAD = 240
OVERHEAD = 7
BYTE_TIMEOUT_S = 0.050
TICK_US = 2000
N_VALVES = 2
STORE_BYTES = 12288
#: Most pulses of a PWM piece the controller takes: 4 n + 10 bytes of the store, so the
#: next piece's first pulse fits beside the last piece's widths (PROTOCOL.md 5).
PWM_PIECE_MAX = (STORE_BYTES - 10) // 4
QUEUE = 4
MAX_DATA = MAX_PAYLOAD - 5  # program bytes per PROG_DATA frame
PROTOCOL_VERSION = 1

# commands; replies are TYPE | 0x80
HELLO, STATUS, CONFIG = 0x01, 0x02, 0x03
PROG_BEGIN, PROG_DATA, PROG_VERIFY = 0x10, 0x11, 0x12
ARM, ABORT, TRIGGER = 0x20, 0x21, 0x22
STALL = 0x70
# events and errors
EV_DONE, EV_FAULT, EV_BOOT = 0xE1, 0xE2, 0xE3
ERROR = 0xFF

STATES = {0: "idle", 1: "loaded", 2: "armed", 3: "playing", 4: "fault"}
IDLE, LOADED, ARMED, PLAYING, FAULT = 0, 1, 2, 3, 4
FAULTS = {0: "none", 1: "watchdog", 2: "underrun", 3: "internal", 4: "bad stream"}
ERRORS = {1: "CRC", 2: "TRUNCATED", 3: "OVERSIZE", 4: "NOISE", 5: "SEQUENCE",
          6: "UNKNOWN_TYPE", 7: "BAD_LENGTH", 8: "STATE", 9: "NO_ROOM", 10: "PROGRAM",
          11: "OFFSET", 12: "BAD_VALUE", 13: "TRIGGER"}
E_CRC, E_TRUNCATED, E_OVERSIZE, E_NOISE, E_SEQUENCE = 1, 2, 3, 4, 5
E_UNKNOWN_TYPE, E_BAD_LENGTH, E_STATE, E_NO_ROOM, E_PROGRAM = 6, 7, 8, 9, 10
E_OFFSET, E_BAD_VALUE, E_TRIGGER = 11, 12, 13
#: errors about bytes on the line (the frame was not received; re-sending is safe)
LINK_ERRORS = frozenset({E_CRC, E_TRUNCATED, E_OVERSIZE, E_NOISE})


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (0x29B1 for b"123456789")."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode(seq: int, type_: int, payload: bytes = b"") -> bytes:
    """One frame. ``seq``, ``type_``: 0..255; payload at most 240 bytes (ValueError)."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes, at most {MAX_PAYLOAD}")
    body = bytes((len(payload), seq & 0xFF, type_ & 0xFF)) + payload
    return MARK + body + struct.pack("<H", crc16(body))


@dataclass(frozen=True)
class Frame:
    """A received frame (CRC good)."""

    seq: int
    type: int
    payload: bytes

    @property
    def is_event(self) -> bool:
        return 0xE0 <= self.type <= 0xEF

    @property
    def is_error(self) -> bool:
        return self.type == ERROR


#: A frame not completed within this long after its last byte is dropped and the hunt
#: for the marker starts again (PROTOCOL.md 2: the controller's TRUNCATED), s.
FRAME_TIMEOUT_S = 0.05


def _whole_frame_after(buf: bytearray) -> int:
    """Where in ``buf`` (a frame's start, incomplete) a later marker begins a whole frame
    with a good CRC; -1 if none does."""
    j = buf.find(MARK, 1)
    while j >= 0:
        if len(buf) >= j + 3:
            n = buf[j + 2]
            if n <= MAX_PAYLOAD and len(buf) >= j + n + OVERHEAD and \
                    crc16(bytes(buf[j + 2:j + 5 + n])) == \
                    struct.unpack_from("<H", buf, j + 5 + n)[0]:
                return j
        j = buf.find(MARK, j + 1)
    return -1


class FrameReader:
    """Splits a byte stream into frames, hunting for the marker as the controller does.

    Bytes with a bad CRC or outside frames are skipped and counted in ``bad_bytes``; the
    controller's replies never have them on a good line. Given the time of each feed
    (``now``, s, monotonic), a frame whose bytes stop for ``FRAME_TIMEOUT_S`` is dropped
    as the controller drops one: a cut-off reply (a controller reset or unplugged
    mid-frame) had waited for the bytes its length named, swallowing the replies after it.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._last = -math.inf
        self.bad_bytes = 0

    def feed(self, data: bytes, now: float | None = None) -> list[Frame]:
        if now is not None:
            if self._buf and data and now - self._last > FRAME_TIMEOUT_S:
                self.bad_bytes += len(self._buf)
                del self._buf[:]
            if data:
                self._last = now
        self._buf += data
        out: list[Frame] = []
        buf = self._buf
        while True:
            i = buf.find(MARK)
            if i < 0:
                keep = 1 if buf[-1:] == MARK[:1] else 0
                self.bad_bytes += len(buf) - keep
                del buf[:len(buf) - keep]
                break
            if i:
                self.bad_bytes += i
                del buf[:i]
            if len(buf) < 3:
                break
            n = buf[2]
            if n > MAX_PAYLOAD:
                self.bad_bytes += 2
                del buf[:2]
                continue
            if len(buf) < n + OVERHEAD:
                # incomplete: unless a whole frame with a good CRC starts after its marker
                # (a cut-off frame, then a reply: the reply is not the cut frame's rest)
                j = _whole_frame_after(buf)
                if j < 0:
                    break
                self.bad_bytes += j
                del buf[:j]
                continue
            body = bytes(buf[2:5 + n])
            if crc16(body) != struct.unpack_from("<H", buf, 5 + n)[0]:
                self.bad_bytes += 2
                del buf[:2]
                continue
            out.append(Frame(seq=buf[3], type=buf[4], payload=bytes(buf[5:5 + n])))
            del buf[:n + OVERHEAD]
        return out


# --------------------------------------------------------------------------- payloads


@dataclass(frozen=True)
class ErrorReply:
    """An ERROR frame's payload (PROTOCOL.md 5, 0xFF)."""

    code: int
    seq: int
    expected: int
    type: int
    state: int
    fault: int
    detail: int

    @property
    def name(self) -> str:
        return ERRORS.get(self.code, f"error {self.code}")

    def describe(self) -> str:
        return (f"{self.name} (code {self.code}, detail {self.detail}) for type 0x{self.type:02x} "
                f"seq {self.seq}; controller {STATES.get(self.state, self.state)}, fault "
                f"{FAULTS.get(self.fault, self.fault)}")


def parse_error(payload: bytes) -> ErrorReply:
    return ErrorReply(*struct.unpack("<6BI", payload[:10]))


@dataclass(frozen=True)
class Hello:
    version: int
    n_valves: int
    max_payload: int
    tick_us: int
    store_bytes: int
    queue: int
    state: int
    fault: int
    host_build: bool
    pulse_us: tuple[int, int]


def parse_hello(p: bytes) -> Hello:
    v, nv, mp, tick, store, q, st, fa, fl, p0, p1 = struct.unpack("<BBHIIBBBBHH", p[:20])
    return Hello(v, nv, mp, tick, store, q, st, fa, bool(fl & 1), (p0, p1))


@dataclass(frozen=True)
class ValveStatus:
    queued: int
    receiving: bool
    pulse_us: int
    free: int
    received: int
    emitted: int


@dataclass(frozen=True)
class Status:
    """STATUS reply (PROTOCOL.md 5, 0x82). Ticks are 2 ms."""

    state: int
    fault: int
    outputs: int
    armed_mask: int
    flags: int
    expected: int
    plays: int
    play_tick: int
    late_ticks: int
    play_len: int
    errors_sent: int
    valves: tuple[ValveStatus, ...]

    @property
    def state_name(self) -> str:
        return STATES.get(self.state, str(self.state))

    @property
    def fault_name(self) -> str:
        return FAULTS.get(self.fault, str(self.fault))


def parse_status(p: bytes) -> Status:
    head = struct.unpack("<6BHIIII", p[:24])
    valves = tuple(ValveStatus(q, bool(r), pu, fr, rc, em)
                   for q, r, pu, fr, rc, em in struct.iter_unpack("<BBHIII", p[24:24 + 16 * N_VALVES]))
    return Status(*head, valves=valves)


@dataclass(frozen=True)
class Verify:
    valve: int
    complete: bool
    crc: int
    received: int
    total: int
    pulses: int


def parse_verify(p: bytes) -> Verify:
    v, c, crc, rec, tot, pul = struct.unpack("<BBHIII", p[:16])
    return Verify(v, bool(c), crc, rec, tot, pul)


@dataclass(frozen=True)
class Done:
    """DONE event: a play ended (ticks of 2 ms)."""

    play: int
    play_len: int
    late_ticks: int
    emitted: tuple[int, int]
    state: int


def parse_done(p: bytes) -> Done:
    play, length, late, e0, e1, st, _ = struct.unpack("<HIIIIBB", p[:20])
    return Done(play, length, late, (e0, e1), st)


@dataclass(frozen=True)
class FaultEvent:
    fault: int
    state_before: int
    play_tick: int


def parse_fault(p: bytes) -> FaultEvent:
    return FaultEvent(*struct.unpack("<BBI", p[:6]))


#: BOOT's reset causes (PROTOCOL.md 5, 0xE3).
RESET_CAUSES = {0: "power-on or external reset", 1: "watchdog",
                2: "brown-out: the supply dipped"}


def boot_cause(p: bytes) -> str:
    """What a BOOT event's payload says restarted the controller."""
    cause = p[0] if p else -1
    return RESET_CAUSES.get(cause, f"reset cause {cause}")


# payload builders (commands)


def hello_payload() -> bytes:
    return b"RDY" + bytes((PROTOCOL_VERSION,))


def begin_payload(valve: int, total: int, replace: bool = False) -> bytes:
    return struct.pack("<BBI", valve, 1 if replace else 0, total)


def data_payload(valve: int, offset: int, data: bytes) -> bytes:
    return struct.pack("<BI", valve, offset) + data


def config_payload(valve: int, pulse_us: int) -> bytes:
    return struct.pack("<BH", valve, pulse_us)
