"""Protocol fuzzing of a valve controller (``firmware/PROTOCOL.md``): random and malformed
frames and byte streams, each followed by a probe that checks the controller still
answers, answered the bad input with an error frame, and left no valve open.

Used by the bounded pytest (``tests/test_cell_valve_fuzz.py``) and by
``bench/fuzz_firmware.py`` (10 000+ cases against the firmware's host build). Seeded:
the same seed gives the same cases.
"""

from __future__ import annotations

import random
import struct
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Callable

from icefab.cell import valve_frames as vf

#: case classes; the value says whether the case must be answered with an error frame
CLASSES = {
    "random_bytes": True,          # bytes with no structure
    "bit_flip": True,              # a good frame with one bit flipped
    "truncated": True,             # a good frame cut short (waits the 50 ms byte timeout)
    "oversize": True,              # LEN > 240
    "unknown_type": True,          # good CRC, no such command
    "bad_length": True,            # good CRC, known command, wrong payload length
    "out_of_order": True,          # good frame, SEQ neither expected nor a repeat
    "repeat": False,               # the last command again: its kept reply, not run twice
    "random_command": False,       # good CRC, known type, random payload: reply or error
    "bad_program": False,          # a program with random damage: every frame answered
    "program_too_big": True,       # a fifth program / more bytes than the store holds
    "trigger_idle": True,          # a trigger with nothing armed
    "play_with_noise": False,      # a real play with garbage bytes thrown in
}


@dataclass
class FuzzReport:
    """Counts of one fuzz run. ``failures`` lists (case index, class, what went wrong)."""

    cases: int = 0
    by_class: Counter = field(default_factory=Counter)
    error_frames: int = 0
    bytes_sent: int = 0
    plays: int = 0
    failures: list = field(default_factory=list)
    seconds: float = 0.0
    max_probe_s: float = 0.0


def _small_program(rng: random.Random) -> bytes:
    """A valid FM program (flow's binary layout) of a few pulses, 1..3 pieces."""
    pieces = rng.randint(1, 3)
    out = [b"ICEV", struct.pack("<HBBII", 1, 0, 0, vf.TICK_US, pieces)]
    for _ in range(pieces):
        dur_ticks = rng.randint(1, 40)
        n = rng.randint(0, 12)
        ticks = sorted(rng.randint(0, dur_ticks) for _ in range(n))
        out.append(struct.pack("<II", n, dur_ticks * vf.TICK_US))
        out.append(struct.pack(f"<{n}H", *ticks))
    return b"".join(out)


class Fuzzer:
    """Drive one controller through a serial-like ``port`` (read/write) with fuzz cases.

    alive: returns False once the controller process died (checked after every case).
    """

    def __init__(self, port: Any, alive: Callable[[], bool] = lambda: True, *,
                 seed: int = 0, probe_timeout_s: float = 2.0) -> None:
        self.port = port
        self.alive = alive
        self.rng = random.Random(seed)
        self.reader = vf.FrameReader()
        self.seq = self.rng.randrange(256)
        self.probe_timeout_s = probe_timeout_s
        self.report = FuzzReport()
        self.last_cmd: bytes | None = None
        self.last_reply: vf.Frame | None = None
        self.repeat_of: vf.Frame | None = None

    # -------------------------------------------------------------- i/o

    def _send(self, data: bytes) -> None:
        self.port.write(data)
        self.report.bytes_sent += len(data)

    def _collect(self, until: Callable[[vf.Frame], bool], timeout_s: float) -> list[vf.Frame] | None:
        """Frames until one satisfies ``until`` (included), or None on timeout."""
        got: list[vf.Frame] = []
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            data = self.port.read(4096)
            if data:
                for f in self.reader.feed(data):
                    got.append(f)
                    if until(f):
                        return got
        return None

    def _command(self, type_: int, payload: bytes = b"") -> vf.Frame | None:
        """A well-formed command with the expected SEQ; its reply (or error) frame."""
        seq = self.seq
        frame = vf.encode(seq, type_, payload)
        self._send(frame)
        got = self._collect(lambda f: f.seq == seq and not f.is_event and
                            (f.type == (type_ | 0x80) or
                             (f.is_error and vf.parse_error(f.payload).code not in vf.LINK_ERRORS)),
                            self.probe_timeout_s)
        self.seq = (self.seq + 1) & 0xFF
        if got is None:
            return None
        self.report.error_frames += sum(1 for f in got if f.is_error)
        self.last_cmd, self.last_reply = frame, got[-1]
        return got[-1]

    def _probe(self) -> tuple[list[vf.Frame] | None, vf.Status | None]:
        """HELLO (accepted with any SEQ: re-synchronises) then STATUS. Returns the frames
        that came before the HELLO reply, and the status."""
        t0 = time.monotonic()
        seq = self.seq
        self._send(vf.encode(seq, vf.HELLO, vf.hello_payload()))
        before = self._collect(lambda f: f.seq == seq and f.type == (vf.HELLO | 0x80),
                               self.probe_timeout_s)
        self.seq = (seq + 1) & 0xFF
        if before is None:
            return None, None
        r = self._command(vf.STATUS)
        self.report.max_probe_s = max(self.report.max_probe_s, time.monotonic() - t0)
        if r is None or r.type != (vf.STATUS | 0x80):
            return before, None
        return before, vf.parse_status(r.payload)

    # -------------------------------------------------------------- cases

    def _good_frame(self, seq: int | None = None) -> bytes:
        return vf.encode(self.seq if seq is None else seq, vf.STATUS)

    def case(self, cls: str) -> None:
        rng = self.rng
        if cls == "random_bytes":
            self._send(bytes(rng.randrange(256) for _ in range(rng.randint(1, 300))))
        elif cls == "bit_flip":
            f = bytearray(vf.encode(self.seq, rng.choice([vf.STATUS, vf.HELLO, vf.ARM]),
                                    bytes(rng.randrange(256) for _ in range(rng.randint(0, 20)))))
            i = rng.randrange(len(f))
            f[i] ^= 1 << rng.randrange(8)
            self._send(bytes(f))
        elif cls == "truncated":
            f = vf.encode(self.seq, vf.PROG_DATA, bytes(rng.randrange(256) for _ in range(rng.randint(1, 200))))
            self._send(f[:rng.randint(1, len(f) - 1)])
            time.sleep(vf.BYTE_TIMEOUT_S * 1.5)
        elif cls == "oversize":
            self._send(vf.MARK + bytes((rng.randint(241, 255), self.seq, vf.STATUS)) +
                       bytes(rng.randrange(256) for _ in range(rng.randint(0, 30))))
        elif cls == "unknown_type":
            known = {vf.HELLO, vf.STATUS, vf.CONFIG, vf.PROG_BEGIN, vf.PROG_DATA,
                     vf.PROG_VERIFY, vf.ARM, vf.ABORT, vf.TRIGGER, vf.STALL}
            t = rng.choice([x for x in range(256) if x not in known])
            self._command(t, bytes(rng.randrange(256) for _ in range(rng.randint(0, 40))))
        elif cls == "bad_length":
            t, good = rng.choice([(vf.STATUS, 0), (vf.CONFIG, 3), (vf.PROG_BEGIN, 6),
                                  (vf.PROG_VERIFY, 1), (vf.ARM, 1), (vf.ABORT, 0), (vf.HELLO, 4)])
            n = rng.choice([x for x in range(0, 12) if x != good])
            if t == vf.HELLO:
                self._send(vf.encode(self.seq, t, bytes(n)))
            else:
                self._command(t, bytes(rng.randrange(256) for _ in range(n)))
        elif cls == "out_of_order":
            self._send(self._good_frame((self.seq + rng.randint(1, 254)) & 0xFF))
        elif cls == "repeat":
            r = self._command(vf.STATUS)
            self.repeat_of = r
            if r is not None and self.last_cmd is not None:
                self._send(self.last_cmd)
        elif cls == "random_command":
            t = rng.choice([vf.CONFIG, vf.PROG_BEGIN, vf.PROG_DATA, vf.PROG_VERIFY, vf.ARM,
                            vf.TRIGGER])
            self._command(t, bytes(rng.randrange(256) for _ in range(rng.randint(0, 30))))
        elif cls == "bad_program":
            prog = bytearray(_small_program(rng))
            for _ in range(rng.randint(1, 3)):
                prog[rng.randrange(len(prog))] = rng.randrange(256)
            if rng.random() < 0.3:
                prog = prog[:rng.randint(1, len(prog))]
            valve = rng.randrange(2)
            announced = len(prog) + rng.choice([0, 0, 0, 1, -1, 7])
            r = self._command(vf.PROG_BEGIN, vf.begin_payload(valve, max(announced, 0)))
            if r is not None and not r.is_error:
                for off in range(0, len(prog), vf.MAX_DATA):
                    r = self._command(vf.PROG_DATA, vf.data_payload(valve, off, bytes(prog[off:off + vf.MAX_DATA])))
                    if r is None or r.is_error:
                        break
        elif cls == "program_too_big":
            valve = rng.randrange(2)
            if rng.random() < 0.5:
                for _ in range(vf.QUEUE + 1):
                    prog = _small_program(rng)
                    self._command(vf.PROG_BEGIN, vf.begin_payload(valve, len(prog)))
                    self._command(vf.PROG_DATA, vf.data_payload(valve, 0, prog))
            else:
                n = 16384
                total = 16 + 8 + 2 * n
                head = b"ICEV" + struct.pack("<HBBII", 1, 0, 0, vf.TICK_US, 1) + \
                    struct.pack("<II", n, 131072000)
                data = head + struct.pack(f"<{n}H", *[i * 4 for i in range(n)])
                self._command(vf.PROG_BEGIN, vf.begin_payload(valve, total))
                for off in range(0, total, vf.MAX_DATA):
                    r = self._command(vf.PROG_DATA, vf.data_payload(valve, off, data[off:off + vf.MAX_DATA]))
                    if r is None or r.is_error:
                        break
        elif cls == "trigger_idle":
            self._command(vf.ABORT)
            self._command(vf.TRIGGER)
        elif cls == "play_with_noise":
            self._command(vf.ABORT)
            prog = _small_program(rng)
            valve = rng.randrange(2)
            self._command(vf.PROG_BEGIN, vf.begin_payload(valve, len(prog)))
            self._command(vf.PROG_DATA, vf.data_payload(valve, 0, prog))
            self._command(vf.ARM, bytes((1 << valve,)))
            self._command(vf.TRIGGER)
            self._send(bytes(rng.randrange(256) for _ in range(rng.randint(1, 100))))
            self.report.plays += 1
        else:  # pragma: no cover
            raise ValueError(f"unknown fuzz class {cls!r}")

    def run(self, n: int) -> FuzzReport:
        """Run ``n`` cases (classes drawn uniformly). After each: the probe must be
        answered within ``probe_timeout_s`` (no hang), the process alive (no crash), an
        error frame seen for the classes that need one, and, once nothing plays, every
        valve closed."""
        rep = self.report
        t0 = time.monotonic()
        self._probe()
        names = list(CLASSES)
        for i in range(n):
            cls = names[self.rng.randrange(len(names))]
            errors_before = rep.error_frames
            self.case(cls)
            before, st = self._probe()
            rep.cases += 1
            rep.by_class[cls] += 1
            if before is None or st is None:
                rep.failures.append((i, cls, "no answer to the probe (hang or crash)"))
                if not self.alive():
                    rep.failures.append((i, cls, "controller process died"))
                    break
                continue
            errs = sum(1 for f in before if f.is_error)
            rep.error_frames += errs
            if CLASSES[cls] and rep.error_frames == errors_before:
                rep.failures.append((i, cls, "no error frame"))
            if cls == "repeat" and self.repeat_of is not None:
                again = [f for f in before if f.seq == self.repeat_of.seq and not f.is_event]
                if not again or again[0] != self.repeat_of:
                    rep.failures.append((i, cls, "repeat not answered with the kept reply"))
            deadline = time.monotonic() + 5.0
            while st is not None and st.state == vf.PLAYING and time.monotonic() < deadline:
                time.sleep(0.002)
                _, st = self._probe()
            if st is None:
                rep.failures.append((i, cls, "no status after the play"))
                continue
            if st.state != vf.PLAYING and st.outputs:
                rep.failures.append((i, cls, f"valve outputs 0b{st.outputs:02b} open while "
                                             f"{st.state_name}"))
            if st.state == vf.PLAYING:
                rep.failures.append((i, cls, "still playing after 5 s"))
            if st.state != vf.IDLE:
                r = self._command(vf.ABORT)
                _, st2 = self._probe()
                if r is None or st2 is None or st2.outputs or st2.state != vf.IDLE:
                    rep.failures.append((i, cls, "ABORT did not close every valve"))
            if not self.alive():
                rep.failures.append((i, cls, "controller process died"))
                break
        rep.seconds = time.monotonic() - t0
        return rep
