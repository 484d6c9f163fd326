"""The robot link's messages: one table that both ends are generated from.

Transport (thesis 2.1: the C40 has RS-232 and Ethernet): a **TCP socket**, the C40 the
server, the control PC the client. Chosen over RS-232 because the serial line's
115 200 bit/s is what the thesis names as the slow part of the controller's data path
(4.2.1) while TCP already frames, checks and re-sends bytes, so the protocol above it only
needs message framing and sequence numbers, and because the C40's serial ports stay free
for a teach pendant or terminal. The V+ side is :mod:`icefab.cell.vplus`.

Wire format
-----------
ASCII lines, one message per line: ``TYPE,SEQ,FIELD,...`` ending in CR LF, at most
:data:`MAX_LINE` characters (V+ strings hold 128). ``TYPE`` is two letters; every field
is a decimal number in the format its table entry names: ``int`` (0 <= v < 2**24, exact
in a V+ single-precision REAL), ``mm`` (``%.3f``, |v| < 100 000) or ``real`` (Python's
shortest round-trip text of a double, |v| < 100 000: a value the controller only records,
carried exactly for the virtual cell). A line with another
type, another field count or a field that does not parse is malformed.

Sequence numbers (``SEQ``, 1 .. 2**24 - 1) are drawn by the host, one per command; a path
uses ONE number for its whole upload (``PB``, every ``PP`` and ``PE``), and the controller
reports that number back when the path's motion is done (``DN``). A build numbers its
paths and layer ends from its journal (increasing, below :data:`FIRST_LINK_SEQ`) and
keeps a command's number when it sends it again after a crash; the link's other commands
(``HI``, ``LB``, ``ST``, ``AB``) take numbers from :data:`FIRST_LINK_SEQ` up, starting at
a random point each session so that a new session's first ``ST`` is never taken for a
repeat of the last one. The controller remembers the number of the last path it ran to
its end (``last_done``) and of the last path an ``AB`` or a fault stopped mid-motion
(``cut``) and reports both in ``SS``: after a crash of the control PC the build asks
``ST`` and knows which paths are done, which one was cut short, and sends the rest.

Every command except ``PP`` gets exactly one reply with its ``SEQ``: ``OK``, ``ER``
(with a code, :data:`ERRORS`) or its own answer (``HI``, ``SS``); ``GO`` gets ``OK`` when
the motion starts and ``DN`` when it is done. A command repeated with the ``SEQ`` of the
last reply sent (its reply was lost) gets that reply again and is not executed twice.

A path upload: ``PB`` (header: point count, time step, height, flags: the triggers, or
:data:`FLAG_PARK` for a park motion such as a stop's lift, which the controller runs and
reports but does not record as ``last_done``), then the points
in ``PP`` lines of up to :data:`POINTS_PER_LINE` (x, y) pairs in order, then ``PE`` with
the count and a check sum (:func:`point_check`); the controller answers ``PE`` with
``OK`` (stored) or ``ER``. ``GO`` runs the oldest stored path, which must carry its
``SEQ``. ``LB`` / ``LE`` bracket a layer (the controller only records them; the virtual
cell freezes the layer's deposit at ``LE``). ``AB`` stops the motion at once (V+
``BRAKE``), drops both triggers and discards every stored path.

Units: x, y in mm in the robot base frame (the planner's base-frame samples, the joint-4
axis), heights in micrometres, time steps in microseconds, widths in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

from icefab.errors import CellError

VERSION = 2       # 2: SS carries "cut" (a path an abort or fault stopped mid-motion)
MAX_LINE = 120          # characters before CR LF; V+ strings hold 128
POINTS_PER_LINE = 4     # (x, y) pairs per PP line: 4 x 2 x 10 characters + header < 120
MAX_SEQ = 2 ** 24 - 1   # exact in a single-precision REAL
FIRST_LINK_SEQ = 2 ** 23  # journal numbers below, the link's own commands from here up
MAX_INT = 2 ** 24 - 1
MAX_MM = 99_999.999
CHECK_MODULUS = 999_983         # point_check: a prime < 2**20, sums stay exact in REALs
CHECK_OFFSET_UM = 600_000       # makes coordinates positive before summing

# flags of a path (PB)
FLAG_VALVE = 1   # raise the valve-controller trigger for the path (deposition)
FLAG_LASER = 2   # raise the laser trigger for the path (measurement)
FLAG_PARK = 4    # a park motion (a stop's lift): run and reported (DN), not last_done

# tools of a path (PB): which tool point the path was planned for
TOOLS = ("part", "scaffold", "laser", "none")


@dataclass(frozen=True)
class Message:
    """One row of the table: ``code`` (two letters on the wire), ``name`` (a Python /
    V+ identifier stem), who sends it (``"host"`` or ``"robot"``), its fields as (name,
    kind) pairs after SEQ, and an optional repeated group (name, kind) pairs sent
    ``count`` times, ``count`` being the value of the field named ``repeat_count``."""

    code: str
    name: str
    sender: str
    fields: tuple[tuple[str, str], ...]
    group: tuple[tuple[str, str], ...] = ()
    repeat_count: str = ""
    max_repeat: int = 0
    doc: str = ""


MESSAGES: tuple[Message, ...] = (
    # host -> robot
    Message("HI", "hello", "host", (("version", "int"),), doc="open a session"),
    Message("LB", "layer_begin", "host", (("layer", "int"), ("z_um", "int")),
            doc="a layer starts (toolpaths layer index, nominal top height)"),
    Message("PB", "path_begin", "host",
            (("layer", "int"), ("index", "int"), ("flags", "int"), ("tool", "int"),
             ("width", "real"), ("npts", "int"), ("dt_us", "int"), ("z_um", "int")),
            doc="path header: triggers (flags), tool, width, point count, time step, z"),
    Message("PP", "path_points", "host", (("first", "int"), ("n", "int")),
            group=(("x", "mm"), ("y", "mm")), repeat_count="n", max_repeat=POINTS_PER_LINE,
            doc="points first .. first + n - 1 of the path being uploaded"),
    Message("PE", "path_end", "host", (("npts", "int"), ("check", "int")),
            doc="end of the upload: point count and point_check"),
    Message("GO", "go", "host", (), doc="run the oldest stored path (its SEQ)"),
    Message("LE", "layer_end", "host", (("layer", "int"),), doc="the layer is done"),
    Message("AB", "abort", "host", (), doc="stop now, triggers off, stored paths dropped"),
    Message("ST", "status", "host", (), doc="ask for the state"),
    # robot -> host
    Message("HI", "hello_reply", "robot",
            (("version", "int"), ("max_points", "int"), ("max_paths", "int")),
            doc="protocol version, points per path, paths stored at once"),
    Message("OK", "ok", "robot", (), doc="the command with this SEQ was accepted"),
    Message("DN", "done", "robot", (("points", "int"),),
            doc="the path with this SEQ was run to its end (points moved through)"),
    Message("ER", "error", "robot", (("code", "int"),), doc="refused (ERRORS)"),
    Message("SS", "state", "robot",
            (("state", "int"), ("stored", "int"), ("last_done", "int"), ("cut", "int")),
            doc="state, paths stored, last path done, last path cut (SEQ, 0: none)"),
)

#: error codes of ``ER`` replies
ERRORS = {1: "malformed message", 2: "sequence: points or end of another path than the "
          "one being uploaded", 3: "no room: the controller already stores max_paths "
          "paths", 4: "too many points for one path (max_points)", 5: "point count or "
          "check sum differs from what arrived", 6: "GO names a path that is not the "
          "oldest stored one", 7: "not allowed now (moving, or no upload open)",
          8: "a point is out of the robot's reach", 9: "unsupported protocol version",
          10: "a point is off the virtual cell's surface (icefab cell serve --grid-for or "
              "--bounds: start it over the part)",
          11: "the path's number, a build's (below FIRST_LINK_SEQ), is at or below the "
              "last path done: a number runs once",
          12: "the cell failed and runs no more paths (a virtual cell: its state folder's "
              "cell.log says why, e.g. a full disk)"}

#: refusals that the same command sent again would meet again (the others: a damaged
#: line, a full store, a motion under way, may pass after a new session settles)
PERMANENT_ERRORS = frozenset({4, 8, 9, 10, 11, 12})

#: robot states of ``SS`` replies
STATES = {0: "idle", 1: "moving", 2: "aborted"}

BY_KEY = {(m.sender, m.code): m for m in MESSAGES}
BY_NAME = {m.name: m for m in MESSAGES}


def _fmt(value: float, kind: str, what: str) -> str:
    if kind == "int":
        v = int(value)
        if v != value or not 0 <= v <= MAX_INT:
            raise CellError(f"robot message field {what} = {value!r}: expected an integer "
                            f"0..{MAX_INT}")
        return str(v)
    v = float(value)
    if kind == "real":
        if not abs(v) <= MAX_MM:
            raise CellError(f"robot message field {what} = {value!r}: expected a finite "
                            f"number within +-{MAX_MM}")
        return repr(v + 0.0)
    if not abs(v) <= MAX_MM:  # also NaN
        raise CellError(f"robot message field {what} = {value!r}: expected a finite length "
                        f"within +-{MAX_MM} mm")
    text = f"{v:.3f}"
    return "0.000" if text == "-0.000" else text


def encode(name: str, seq: int, *values: float, group: tuple = ()) -> bytes:
    """One message as its wire line (CR LF included).

    name: a :data:`MESSAGES` name; seq: 1..MAX_SEQ; values: the fields in table order;
    group: for a message with a repeated group, a sequence of tuples (one per repeat).
    Raises CellError for a value out of its field's range or a wrong field count.
    """
    m = BY_NAME[name]
    if not 0 <= int(seq) <= MAX_SEQ:
        raise CellError(f"robot message {m.code}: sequence number {seq} out of 0..{MAX_SEQ}")
    if len(values) != len(m.fields):
        raise CellError(f"robot message {m.code}: {len(values)} fields given, the table has "
                        f"{len(m.fields)}")
    parts = [m.code, str(int(seq))]
    parts += [_fmt(v, kind, f"{m.code}.{f}") for v, (f, kind) in zip(values, m.fields)]
    if m.group:
        count = values[[f for f, _ in m.fields].index(m.repeat_count)]
        if len(group) != count or not 0 < count <= m.max_repeat:
            raise CellError(f"robot message {m.code}: {len(group)} repeats for "
                            f"{m.repeat_count} = {count} (1..{m.max_repeat})")
        for rep in group:
            parts += [_fmt(v, kind, f"{m.code}.{f}") for v, (f, kind) in zip(rep, m.group)]
    line = ",".join(parts)
    if len(line) > MAX_LINE:
        raise CellError(f"robot message {m.code}: {len(line)} characters, the limit is "
                        f"{MAX_LINE}")
    return line.encode("ascii") + b"\r\n"


@dataclass(frozen=True)
class Decoded:
    """A received message: its table row, SEQ, field values by name (ints as int, mm as
    float) and the repeated group's values (tuples in group order)."""

    message: Message
    seq: int
    values: dict
    group: tuple = ()

    @property
    def name(self) -> str:
        return self.message.name

    def __getitem__(self, key: str):
        return self.values[key]


def _parse(text: str, kind: str, what: str) -> float:
    try:
        if kind == "int":
            if not text.isdigit():
                raise ValueError
            v = int(text)
            if v > MAX_INT:
                raise ValueError
            return v
        if not text or text.strip() != text or "_" in text:
            raise ValueError
        v = float(text)
        if not abs(v) <= MAX_MM:
            raise ValueError
        return v
    except ValueError:
        raise CellError(f"malformed robot message: field {what} = {text[:20]!r} is not "
                        f"{'an integer 0..' + str(MAX_INT) if kind == 'int' else 'a number'}"
                        ) from None


def decode(line: bytes | str, sender: str) -> Decoded:
    """Parse one line (with or without its CR LF) sent by ``sender`` (``"host"`` or
    ``"robot"``). Raises CellError naming what is wrong for a malformed line."""
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError:
            raise CellError("malformed robot message: bytes that are not ASCII") from None
    line = line.rstrip("\r\n")
    if len(line) > MAX_LINE:
        raise CellError(f"malformed robot message: {len(line)} characters, the limit is "
                        f"{MAX_LINE}")
    parts = line.split(",")
    m = BY_KEY.get((sender, parts[0]))
    if m is None or len(parts) < 2:
        raise CellError(f"malformed robot message: unknown type {parts[0][:8]!r} from the "
                        f"{sender}")
    seq = int(_parse(parts[1], "int", f"{m.code}.seq"))
    rest = parts[2:]
    if len(rest) < len(m.fields):
        raise CellError(f"malformed robot message {m.code}: {len(rest)} fields, expected "
                        f"{len(m.fields)}")
    values = {f: _parse(t, kind, f"{m.code}.{f}") for t, (f, kind) in zip(rest, m.fields)}
    extra = rest[len(m.fields):]
    group: list[tuple] = []
    if m.group:
        count = values[m.repeat_count]
        if not 0 < count <= m.max_repeat or len(extra) != count * len(m.group):
            raise CellError(f"malformed robot message {m.code}: {len(extra)} values for "
                            f"{m.repeat_count} = {count} repeats of {len(m.group)}")
        k = len(m.group)
        for r in range(count):
            group.append(tuple(_parse(t, kind, f"{m.code}.{f}")
                               for t, (f, kind) in zip(extra[r * k:(r + 1) * k], m.group)))
    elif extra:
        raise CellError(f"malformed robot message {m.code}: {len(rest)} fields, expected "
                        f"{len(m.fields)}")
    return Decoded(message=m, seq=seq, values=values, group=tuple(group))


def point_um(value_mm: float) -> int:
    """A coordinate as the controller reads it: the ``%.3f`` text sent, in micrometres."""
    return int(_fmt(value_mm, "mm", "point").replace(".", ""))


def point_check(x_mm, y_mm) -> int:
    """Check sum of a path's points as the controller computes it while they arrive:
    ``c = (c + (X + 600000) + (Y + 600000)) mod 999983`` over the points in order, X and Y
    the coordinates in micrometres as sent (:func:`point_um`; the Cobra's reach keeps
    them above -600 mm). Every intermediate value stays below 2**24, so V+'s
    single-precision REALs compute it exactly."""
    c = 0
    for a, b in zip(x_mm, y_mm):
        c = (c + (point_um(a) + CHECK_OFFSET_UM) + (point_um(b) + CHECK_OFFSET_UM)) \
            % CHECK_MODULUS
    return c
