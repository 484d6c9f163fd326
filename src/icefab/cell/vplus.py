"""The V+ programs for the Adept C40 (thesis 2.1, 4.3, 5.2.1): ``icefab export vplus``.

**Untested on a controller**: no C40 was available. The text follows the V+ language as
documented by Adept (``.PROGRAM``/``.END``, ``AUTO`` and ``GLOBAL`` declarations,
``DURATION ... ALWAYS``, ``MOVES``, ``BREAK``, ``BRAKE``, ``SIGNAL``, ``EXECUTE``,
``ATTACH``/``FCMND``/``READ``/``WRITE`` on a TCP logical unit); the tests check what can be
checked without one: every ``.PROGRAM`` closed by ``.END``, blocks balanced, every variable
declared (``AUTO`` in its program, ``GLOBAL`` in ``ice.globals``) before use, and the
message parsing and replies generated from :data:`icefab.cell.robot_protocol.MESSAGES`, the
same table the host side encodes with. The TCP calls (``ice.comm``'s ``FCMND`` 501
server open) are the part most likely to need adjusting on a real controller's V+
version.

What it does (the thesis' cycle, Fig. 2-5): ``ice.server`` (task 0, robot attached) starts
``ice.comm`` on task 1, which serves one client on a TCP port and stores uploaded paths in
a ring of ``max_paths`` slots (``ice.px``/``ice.py``; the upload task only counts
``ice.nup`` up and the motion task only ``ice.ndone``, so the two tasks never write the
same counter: ``AB`` asks the motion task to drop the stored paths, ``ice.dropreq``, and
waits until it has). On ``GO`` the motion task moves to
the path's first point (``ice.approach`` mm/s, then ``BREAK``: at rest), raises the valve
trigger (deposition) or the laser trigger (measurement) on its digital output, moves
through every point with ``DURATION dt ALWAYS`` and ``MOVES`` (constant point-to-point
duration: the speed lives in the point spacing, thesis 4.3), ``BREAK``s, drops the
triggers and reports ``DN`` with the path's sequence number. ``AB`` from the client:
``BRAKE`` (stops the motion at once), both triggers off, stored paths dropped.

Points arrive in the base frame (mm); the program makes ``TRANS(x, y, ice.zbase + z, 0,
180, ice.yaw)`` locations: ``ice.zbase`` is the height of the build platform in the base
frame and ``ice.yaw`` the end effector's fixed orientation (joint 4, thesis eq. 4.11),
both given at export (``--zbase``, ``--yaw``) and to be taught on the cell.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from icefab.cell import robot_protocol as rp
from icefab.robots import CONTROLLER_PATH_POINTS

__all__ = ["VplusSettings", "vplus_program", "V_KEYWORDS", "vplus_name"]


@dataclass(frozen=True)
class VplusSettings:
    """Export settings of the V+ server.

    port: TCP port the C40 listens on. valve_output, laser_output: digital output numbers
    (V+ ``SIGNAL``; the C40's outputs are 97-104 on its XDIO connector) wired to the valve
    controller's trigger input and the laser controller's timing input. zbase_mm: build
    platform height in the base frame, mm. yaw_deg: fixed end-effector orientation.
    approach_mm_s: speed of the move to a path's first point. max_points, max_paths:
    storage (points per path, paths stored at once; 8192 points = 131 s at 16 ms).
    """

    port: int = 7100
    valve_output: int = 97
    laser_output: int = 98
    zbase_mm: float = 0.0
    yaw_deg: float = 0.0
    approach_mm_s: float = 100.0
    max_points: int = CONTROLLER_PATH_POINTS
    max_paths: int = 4


def vplus_name(message: rp.Message) -> str:
    """The V+ program stem of a message (``ice.h.pb`` handles PB, ``ice.r.dn`` sends DN)."""
    return message.code.lower()


def _field_var(name: str) -> str:
    return "f." + name.replace("_", "")[:12]


# --------------------------------------------------------------------------- generated

def _handler_call(m: rp.Message) -> list[str]:
    """Parse the fields of one host message (in table order) and call its handler."""
    out = [f'        IF $type == "{m.code}" THEN']
    args = ["seq"]
    for f, _ in m.fields:
        out.append(f"            CALL ice.field($line, {_field_var(f)}, ok)")
        args.append(_field_var(f))
    if m.group:
        # the repeated group is parsed by the handler, point after point
        out.append(f"            CALL ice.h.{vplus_name(m)}($line, {', '.join(args)}, ok)")
    else:
        out.append('            IF ok AND (LEN($line) <> 0) THEN')
        out.append("                ok = FALSE")
        out.append("            END")
        out.append("            IF ok THEN")
        out.append(f"                CALL ice.h.{vplus_name(m)}({', '.join(args)})")
        out.append("            END")
    out.append("            known = TRUE")
    out.append("        END")
    return out


def _reply_program(m: rp.Message) -> list[str]:
    """``ice.r.XX(seq, fields...)``: format one reply line, remember it, send it."""
    params = ["seq"] + [_field_var(f) for f, _ in m.fields]
    expr = [f'"{m.code},"', "/I0", "seq"]
    for f, _ in m.fields:
        expr += ['","', "/I0", _field_var(f)]
    return [f".PROGRAM ice.r.{vplus_name(m)}({', '.join(params)})",
            f"    ; reply {m.code}: {m.doc} (generated from robot_protocol.MESSAGES)",
            "    AUTO $out",
            f"    $out = $ENCODE({', '.join(expr)})",
            "    CALL ice.send($out, seq)",
            ".END", ""]


def _auto_lines(names: list[str], per_line: int = 6) -> list[str]:
    return [f"    AUTO REAL {', '.join(names[i:i + per_line])}"
            for i in range(0, len(names), per_line)]


def _parse_program() -> list[str]:
    host = [m for m in rp.MESSAGES if m.sender == "host"]
    lines = [".PROGRAM ice.parse($line)",
             "    ; one received line: TYPE,SEQ,FIELD,... (generated from",
             "    ; robot_protocol.MESSAGES: the fields in the host's order)",
             "    AUTO $type, $sep",
             "    AUTO REAL seq, ok, known",
             *_auto_lines(sorted({_field_var(f) for m in host for f, _ in m.fields})),
             "    ok = TRUE",
             "    known = FALSE",
             '    $type = $DECODE($line, ",", 0)',
             '    $sep = $DECODE($line, ",", 1)',
             "    CALL ice.field($line, seq, ok)",
             "    IF ok THEN",
             "        ; a repeat of the last command (its reply was lost): same reply again",
             "        IF (seq == ice.lastseq) AND ($type == $ice.lasttype) AND ($type <> \"PP\") THEN",
             "            CALL ice.resend()",
             "            RETURN",
             "        END",
             "        $ice.curtype = $type"]
    for m in host:
        lines += _handler_call(m)
    lines += ["        IF NOT known THEN",
              "            ok = FALSE",
              "        END",
              "    END",
              "    IF NOT ok THEN",
              "        IF ice.uopen AND ($type == \"PP\") THEN",
              "            ice.uopen = FALSE",
              "        END",
              "        CALL ice.r.er(seq, 1)",
              "    END",
              ".END", ""]
    return lines


# --------------------------------------------------------------------------- fixed parts

_GLOBALS = {
    "REAL": ["ice.port", "ice.vsig", "ice.lsig", "ice.zbase", "ice.yaw", "ice.appspd",
             "ice.maxpts", "ice.maxpaths", "ice.lun", "ice.handle", "ice.quit", "ice.abort",
             "ice.state", "ice.nup", "ice.ndone", "ice.dropreq", "ice.uopen", "ice.uslot",
             "ice.useq", "ice.urecv", "ice.ucheck", "ice.gopend", "ice.goseq", "ice.dnpend",
             "ice.dnseq", "ice.dnpts", "ice.lastseq", "ice.lastdone", "ice.cut", "ice.layer",
             "ice.px[]", "ice.py[]", "ice.pn[]", "ice.pdt[]", "ice.pz[]", "ice.pflags[]",
             "ice.pseq[]"],
    "STRING": ["$ice.lasttype", "$ice.lastrep", "$ice.curtype"],
}


def _globals_program(s: VplusSettings) -> list[str]:
    out = [".PROGRAM ice.globals()",
           "    ; every global of the server, declared and set once"]
    for kind, names in _GLOBALS.items():
        for i in range(0, len(names), 6):
            out.append(f"    GLOBAL {kind} {', '.join(names[i:i + 6])}")
    out.append("    AUTO REAL i, j")
    out += [f"    ice.port = {int(s.port)}",
            f"    ice.vsig = {int(s.valve_output)}",
            f"    ice.lsig = {int(s.laser_output)}",
            f"    ice.zbase = {s.zbase_mm:.3f}",
            f"    ice.yaw = {s.yaw_deg:.3f}",
            f"    ice.appspd = {s.approach_mm_s:.3f}",
            f"    ice.maxpts = {int(s.max_points)}",
            f"    ice.maxpaths = {int(s.max_paths)}",
            # every slot at its full size before the upload task starts: V+ extends a
            # global array as elements are set, and one task extending it while another
            # reads it can crash the controller to DDT (V+ Language User's Guide, "Global
            # Array Access Restriction"; a review's: the ring grew point by point)
            "    ; every path slot at full size now: V+ may crash to DDT when one task",
            "    ; extends a global array while another reads it",
            "    FOR i = 0 TO ice.maxpaths-1",
            "        ice.pn[i] = 0",
            "        ice.pdt[i] = 0",
            "        ice.pz[i] = 0",
            "        ice.pflags[i] = 0",
            "        ice.pseq[i] = -1",
            "        FOR j = 0 TO ice.maxpts-1",
            "            ice.px[i,j] = 0",
            "            ice.py[i,j] = 0",
            "        END",
            "    END",
            "    ice.lun = 0",
            "    ice.handle = 0",
            "    ice.quit = FALSE",
            "    CALL ice.reset()",
            "    ice.lastseq = -1",
            '    $ice.lasttype = ""',
            '    $ice.lastrep = ""',
            '    $ice.curtype = ""',
            "    ice.lastdone = 0",
            "    ice.cut = 0",
            "    ice.layer = -1",
            ".END", ""]
    return out


_FIXED = r"""
.PROGRAM ice.reset()
    ; both triggers off, no path stored or running (power-up and AB)
    SIGNAL -ice.vsig, -ice.lsig
    ice.abort = FALSE
    ice.state = 0
    ice.nup = 0
    ice.ndone = 0
    ice.dropreq = FALSE
    ice.uopen = FALSE
    ice.uslot = 0
    ice.useq = 0
    ice.urecv = 0
    ice.ucheck = 0
    ice.gopend = FALSE
    ice.goseq = 0
    ice.dnpend = FALSE
    ice.dnseq = 0
    ice.dnpts = 0
.END

.PROGRAM ice.server()
    ; main program, task 0 with the robot attached: runs the paths ice.comm stores
    AUTO REAL slot, i, n
    AUTO LOC pt
    CALL ice.globals()
    EXECUTE 1 ice.comm()
    WHILE NOT ice.quit DO
        WAIT ice.gopend OR ice.quit OR ice.dropreq
        IF ice.dropreq THEN
            ; AB (task 1) drops the stored paths: only this task writes ice.ndone
            ice.ndone = ice.nup
            ice.dropreq = FALSE
        END
        IF ice.gopend AND NOT ice.quit THEN
            slot = ice.ndone MOD ice.maxpaths
            n = ice.pn[slot]
            ice.state = 1
            ; to the first point at the approach speed, then at rest (thesis 4.3)
            DURATION 0 ALWAYS
            SPEED ice.appspd MMPS ALWAYS
            SET pt = TRANS(ice.px[slot,0], ice.py[slot,0], ice.zbase+ice.pz[slot], 0, 180, ice.yaw)
            MOVES pt
            BREAK
            ; triggers at the path's time zero (thesis 2.3.1, 2.3.2)
            IF (ice.pflags[slot] BAND 1) AND NOT ice.abort THEN
                SIGNAL ice.vsig
            END
            IF (ice.pflags[slot] BAND 2) AND NOT ice.abort THEN
                SIGNAL ice.lsig
            END
            ; constant point-to-point duration: the speed is in the spacing (thesis 4.3)
            SPEED 100 ALWAYS
            DURATION ice.pdt[slot] ALWAYS
            i = 1
            WHILE (i < n) AND NOT ice.abort DO
                SET pt = TRANS(ice.px[slot,i], ice.py[slot,i], ice.zbase+ice.pz[slot], 0, 180, ice.yaw)
                MOVES pt
                i = i+1
            END
            BREAK
            SIGNAL -ice.vsig, -ice.lsig
            DURATION 0 ALWAYS
            IF NOT ice.abort THEN
                ice.ndone = ice.ndone+1
                ice.dnseq = ice.pseq[slot]
                ice.dnpts = i
                IF NOT (ice.pflags[slot] BAND {PARK}) THEN
                    IF ice.pseq[slot] > ice.lastdone THEN
                        ice.lastdone = ice.pseq[slot]
                    END
                END
                ice.dnpend = TRUE
                ice.state = 0
            END
            ice.gopend = FALSE
        END
    END
    SIGNAL -ice.vsig, -ice.lsig
.END

.PROGRAM ice.comm()
    ; task 1: the TCP server; one client at a time, one line per READ
    AUTO REAL stat
    AUTO $line
    ice.lun = 0
    ATTACH (ice.lun, 4) "TCP"
    IF IOSTAT(ice.lun) < 0 THEN
        TYPE "icefab: cannot attach the TCP device: ", $ERROR(IOSTAT(ice.lun))
        ice.quit = TRUE
        RETURN
    END
    ; open a server socket on ice.port, one client, default buffers
    FCMND (ice.lun, 501) $INTB(ice.port)+$INTB(1)+$INTB(0)
    IF IOSTAT(ice.lun) < 0 THEN
        TYPE "icefab: cannot open TCP port ", /I0, ice.port, ": ", $ERROR(IOSTAT(ice.lun))
        ice.quit = TRUE
        RETURN
    END
    WHILE NOT ice.quit DO
        ; no-wait read: a whole line, or nothing yet
        READ (ice.lun, ice.handle, 1) $line
        stat = IOSTAT(ice.lun)
        IF stat > 0 THEN
            CALL ice.parse($line)
        END
        IF ice.dnpend THEN
            ice.dnpend = FALSE
            CALL ice.r.dn(ice.dnseq, ice.dnpts)
        END
        WAIT
    END
    DETACH (ice.lun)
.END

.PROGRAM ice.field($line, value, ok)
    ; next comma-separated number of $line into value (ok = FALSE if it is not one: VAL
    ; alone reads "abc" as 0, so every character must be one a number is written with)
    AUTO $tok, $sep
    AUTO REAL i
    IF NOT ok THEN
        RETURN
    END
    $tok = $DECODE($line, ",", 0)
    $sep = $DECODE($line, ",", 1)
    IF LEN($tok) == 0 THEN
        ok = FALSE
        RETURN
    END
    FOR i = 1 TO LEN($tok)
        IF POS("0123456789+-.Ee", $MID($tok, i, 1), 1) == 0 THEN
            ok = FALSE
            RETURN
        END
    END
    value = VAL($tok)
.END

.PROGRAM ice.send($out, seq)
    ; send one reply line and remember it for a repeated command
    WRITE (ice.lun, ice.handle) $out
    ice.lastseq = seq
    $ice.lasttype = $ice.curtype
    $ice.lastrep = $out
.END

.PROGRAM ice.resend()
    WRITE (ice.lun, ice.handle) $ice.lastrep
.END

.PROGRAM ice.h.hi(seq, f.version)
    IF f.version <> {VERSION} THEN
        CALL ice.r.er(seq, 9)
        RETURN
    END
    CALL ice.r.hi(seq, {VERSION}, ice.maxpts, ice.maxpaths)
.END

.PROGRAM ice.h.lb(seq, f.layer, f.zum)
    ice.layer = f.layer
    CALL ice.r.ok(seq)
.END

.PROGRAM ice.h.le(seq, f.layer)
    CALL ice.r.ok(seq)
.END

.PROGRAM ice.h.pb(seq, f.layer, f.index, f.flags, f.tool, f.width, f.npts, f.dtus, f.zum)
    ; open the upload of one path into the next free slot (no reply unless refused)
    IF ice.uopen THEN
        CALL ice.r.er(seq, 7)
        RETURN
    END
    IF ice.nup-ice.ndone >= ice.maxpaths THEN
        CALL ice.r.er(seq, 3)
        RETURN
    END
    IF (f.npts < 1) OR (f.npts > ice.maxpts) THEN
        CALL ice.r.er(seq, 4)
        RETURN
    END
    IF (NOT (f.flags BAND {PARK})) AND (seq < {FIRSTLINK}) AND (seq <= ice.lastdone) THEN
        CALL ice.r.er(seq, 11)
        RETURN
    END
    ice.uslot = ice.nup MOD ice.maxpaths
    ice.useq = seq
    ice.urecv = 0
    ice.ucheck = 0
    ice.pn[ice.uslot] = f.npts
    ice.pdt[ice.uslot] = f.dtus/1000000
    ice.pz[ice.uslot] = f.zum/1000
    ice.pflags[ice.uslot] = f.flags
    ice.pseq[ice.uslot] = seq
    ice.uopen = TRUE
.END

.PROGRAM ice.h.pp($line, seq, f.first, f.n, ok)
    ; n points (x, y) of the path being uploaded; the check sum grows as they arrive
    AUTO REAL k, x, y, xu, yu
    IF NOT ice.uopen THEN
        RETURN
    END
    IF (seq <> ice.useq) OR (f.first <> ice.urecv) OR (f.n < 1) OR (f.n > {PER_LINE}) THEN
        ice.uopen = FALSE
        CALL ice.r.er(seq, 2)
        RETURN
    END
    IF ice.urecv+f.n > ice.pn[ice.uslot] THEN
        ice.uopen = FALSE
        CALL ice.r.er(seq, 5)
        RETURN
    END
    FOR k = 1 TO f.n
        CALL ice.field($line, x, ok)
        CALL ice.field($line, y, ok)
        IF NOT ok THEN
            ice.uopen = FALSE
            CALL ice.r.er(seq, 1)
            RETURN
        END
        ice.px[ice.uslot,ice.urecv] = x
        ice.py[ice.uslot,ice.urecv] = y
        xu = INT(x*1000+0.5*SIGN(x))
        yu = INT(y*1000+0.5*SIGN(y))
        ice.ucheck = (ice.ucheck+(xu+{OFFSET})+(yu+{OFFSET})) MOD {MODULUS}
        ice.urecv = ice.urecv+1
    END
    IF LEN($line) <> 0 THEN
        ice.uopen = FALSE
        CALL ice.r.er(seq, 1)
    END
.END

.PROGRAM ice.h.pe(seq, f.npts, f.check)
    ; end of an upload: stored if count and check sum agree
    IF NOT ice.uopen THEN
        RETURN
    END
    ice.uopen = FALSE
    IF seq <> ice.useq THEN
        CALL ice.r.er(seq, 2)
        RETURN
    END
    IF (f.npts <> ice.urecv) OR (f.npts <> ice.pn[ice.uslot]) OR (f.check <> ice.ucheck) THEN
        CALL ice.r.er(seq, 5)
        RETURN
    END
    ice.nup = ice.nup+1
    CALL ice.r.ok(seq)
.END

.PROGRAM ice.h.go(seq)
    ; run the oldest stored path; it must be the one named
    IF ice.gopend THEN
        CALL ice.r.er(seq, 7)
        RETURN
    END
    IF ice.nup-ice.ndone < 1 THEN
        CALL ice.r.er(seq, 6)
        RETURN
    END
    IF ice.pseq[ice.ndone MOD ice.maxpaths] <> seq THEN
        CALL ice.r.er(seq, 6)
        RETURN
    END
    ice.abort = FALSE
    ice.goseq = seq
    ice.gopend = TRUE
    CALL ice.r.ok(seq)
.END

.PROGRAM ice.h.ab(seq)
    ; stop at once (BRAKE works from any task), triggers off, everything dropped; a path
    ; under way is reported cut (SS) so the host never sends it again
    IF ice.gopend THEN
        ice.cut = ice.goseq
    END
    ice.abort = TRUE
    BRAKE
    SIGNAL -ice.vsig, -ice.lsig
    ; the motion task drops the stored paths (ice.ndone is its counter: written here as
    ; well, an AB that came as a path ended left ice.ndone past ice.nup, a stored count
    ; of -1 and every later GO refused); a DN it set meanwhile goes too
    ice.dropreq = TRUE
    WAIT (NOT ice.dropreq) OR ice.quit
    ice.uopen = FALSE
    ice.dnpend = FALSE
    ice.state = 2
    CALL ice.r.ok(seq)
.END

.PROGRAM ice.h.st(seq)
    CALL ice.r.ss(seq, ice.state, ice.nup-ice.ndone, ice.lastdone, ice.cut)
.END
"""


def vplus_program(settings: VplusSettings | None = None) -> str:
    """The whole V+ program file (text, CR-free) for the given export settings."""
    s = settings or VplusSettings()
    fixed = (_FIXED.replace("{VERSION}", str(rp.VERSION))
             .replace("{PER_LINE}", str(rp.POINTS_PER_LINE))
             .replace("{OFFSET}", str(rp.CHECK_OFFSET_UM))
             .replace("{MODULUS}", str(rp.CHECK_MODULUS))
             .replace("{PARK}", str(rp.FLAG_PARK))
             .replace("{FIRSTLINK}", str(rp.FIRST_LINK_SEQ)))
    head = ["; icefab V+ server for the Adept C40 (robot link protocol version "
            f"{rp.VERSION}).",
            "; Generated by icefab (icefab.cell.vplus). UNTESTED ON A CONTROLLER.",
            "; Load with LOAD, start with EXECUTE ice.server (robot attached to task 0).",
            ""]
    out = head + _globals_program(s) + _parse_program()
    for m in rp.MESSAGES:
        if m.sender == "robot":
            out += _reply_program(m)
    return "\n".join(out) + fixed


#: V+ words the declaration check does not count as variables (keywords, instructions,
#: functions used above)
V_KEYWORDS = frozenset("""
PROGRAM END AUTO GLOBAL REAL LOC STRING IF THEN ELSE WHILE DO FOR TO STEP CALL RETURN
AND OR NOT BAND MOD TRUE FALSE SIGNAL WAIT DURATION ALWAYS SPEED MMPS SET TRANS MOVES
BREAK BRAKE EXECUTE ATTACH DETACH FCMND READ WRITE IOSTAT TYPE ERROR INTB DECODE
ENCODE LEN VAL INT SIGN I0 TCP POS MID
""".split())


def identifiers(statement: str) -> list[str]:
    """Names in one V+ statement (strings and comments removed), ``$``-prefixed kept."""
    s = re.sub(r'"[^"]*"', " ", statement.split(";", 1)[0])
    return re.findall(r"\$?[A-Za-z][A-Za-z0-9._]*", s)
