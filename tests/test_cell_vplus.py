"""The V+ server text: what can be checked without a C40 (it is untested on one)."""

from __future__ import annotations

import re

import pytest

from icefab.cell import robot_protocol as rp
from icefab.cell.vplus import V_KEYWORDS, VplusSettings, identifiers, vplus_program

TEXT = vplus_program(VplusSettings(port=7200, valve_output=99, laser_output=100))


def _programs(text):
    """{name: (params, body lines)} from .PROGRAM ... .END blocks; fails on nesting."""
    out, cur = {}, None
    for line in text.splitlines():
        s = line.strip()
        if s.startswith(".PROGRAM"):
            assert cur is None, f"{s} opened inside {cur}"
            m = re.fullmatch(r"\.PROGRAM ([a-z0-9.]+)\((.*)\)", s)
            assert m, s
            cur = m.group(1)
            out[cur] = ([p.strip() for p in m.group(2).split(",") if p.strip()], [])
        elif s == ".END":
            assert cur is not None, "an .END without .PROGRAM"
            cur = None
        elif cur is not None:
            out[cur][1].append(s)
        else:
            assert s == "" or s.startswith(";"), f"statement outside a program: {s}"
    assert cur is None, f"{cur} is not closed by .END"
    return out


PROGRAMS = _programs(TEXT)


def test_every_program_is_closed_and_blocks_balance():
    assert TEXT.count(".PROGRAM") == TEXT.count(".END") == len(PROGRAMS)
    for name, (_, body) in PROGRAMS.items():
        depth = 0
        for s in body:
            s = s.split(";", 1)[0].strip()
            if re.match(r"(IF .* THEN|WHILE .* DO|FOR .*)$", s):
                depth += 1
            elif s == "END":
                depth -= 1
            assert depth >= 0, f"{name}: END without a block"
        assert depth == 0, f"{name}: {depth} blocks not closed"


def test_every_called_program_exists():
    for name, (_, body) in PROGRAMS.items():
        for s in body:
            for callee in re.findall(r"(?:CALL|EXECUTE \d+) ([a-z0-9.]+)\(", s):
                assert callee in PROGRAMS, f"{name} calls {callee}, which is not defined"


def test_variables_are_declared_before_use():
    glob = set()
    for s in PROGRAMS["ice.globals"][1]:
        if s.startswith("GLOBAL"):
            glob |= {n.strip().rstrip("[]") for n in s.split(None, 2)[2].split(",")}
    for name, (params, body) in PROGRAMS.items():
        known = set(glob) | {p for p in params}
        for s in body:
            if s.startswith(("AUTO", "GLOBAL")):
                decl = s.split(None, 2)[2] if s.split()[1] in ("REAL", "LOC", "STRING") \
                    else s.split(None, 1)[1]
                known |= {n.strip().rstrip("[]") for n in decl.split(",")}
                continue
            for ident in identifiers(s):
                if ident.lstrip("$").upper() in V_KEYWORDS or ident in PROGRAMS:
                    continue
                assert ident in known, f"{name}: {ident!r} used before it is declared: {s}"


def test_export_settings_reach_the_program():
    body = "\n".join(PROGRAMS["ice.globals"][1])
    assert "ice.port = 7200" in body and "ice.vsig = 99" in body and "ice.lsig = 100" in body


def test_host_messages_are_parsed_in_the_hosts_field_order():
    """ice.parse reads each host message's fields in the table's order and calls a
    handler whose parameters are exactly those fields (so the layouts cannot drift)."""
    parse = PROGRAMS["ice.parse"][1]
    for m in rp.MESSAGES:
        if m.sender != "host":
            continue
        start = parse.index(f'IF $type == "{m.code}" THEN')
        reads, call = [], None
        for s in parse[start + 1:]:
            r = re.fullmatch(r"CALL ice\.field\(\$line, ([a-z.]+), ok\)", s)
            if r:
                reads.append(r.group(1))
            c = re.search(rf"CALL (ice\.h\.{m.code.lower()})\((.*)\)", s)
            if c:
                call = [a.strip() for a in c.group(2).split(",")]
                break
        want = ["f." + f.replace("_", "") for f, _ in m.fields]
        assert reads == want, m.code
        params = PROGRAMS[f"ice.h.{m.code.lower()}"][0]
        assert call == params or call == params, m.code
        assert [p for p in params if p.startswith("f.")] == want, m.code


def test_replies_are_written_in_the_hosts_field_order():
    for m in rp.MESSAGES:
        if m.sender != "robot":
            continue
        params, body = PROGRAMS[f"ice.r.{m.code.lower()}"]
        enc = next(s for s in body if "$ENCODE" in s)
        inner = enc[enc.index("(") + 1:enc.rindex(")")]
        args = [a.strip() for a in re.findall(r'"[^"]*"|[^,"]+', inner) if a.strip()]
        fields = [a for a in args if not a.startswith(('"', "/"))]
        assert args[0] == f'"{m.code},"'
        assert fields == ["seq"] + ["f." + f.replace("_", "") for f, _ in m.fields]
        assert params == fields


def test_motion_uses_constant_duration_and_drops_triggers_after_the_path():
    body = PROGRAMS["ice.server"][1]
    i_dur = body.index("DURATION ice.pdt[slot] ALWAYS")
    i_on = body.index("SIGNAL ice.vsig")
    i_moves = [i for i, s in enumerate(body) if s == "MOVES pt"]
    i_off = body.index("SIGNAL -ice.vsig, -ice.lsig")
    assert i_moves[0] < body.index("BREAK") < i_on < i_dur < i_moves[1] < i_off
    ab = PROGRAMS["ice.h.ab"][1]
    assert ab.index("BRAKE") < ab.index("SIGNAL -ice.vsig, -ice.lsig")


def test_the_check_sum_constants_are_the_hosts():
    pp = "\n".join(PROGRAMS["ice.h.pp"][1])
    assert f"MOD {rp.CHECK_MODULUS}" in pp and f"+{rp.CHECK_OFFSET_UM})" in pp
    assert f"f.n > {rp.POINTS_PER_LINE}" in pp


def test_no_line_is_too_long_for_the_controller_editor():
    assert max(len(line) for line in TEXT.splitlines()) <= 128


def test_a_park_motion_is_not_recorded_as_the_last_path_done_and_an_abort_reports_cut():
    server = "\n".join(PROGRAMS["ice.server"][1])
    guard = f"IF NOT (ice.pflags[slot] BAND {rp.FLAG_PARK}) THEN"
    assert guard in server
    assert server.index(guard) < server.index("ice.lastdone = ice.pseq[slot]")
    # the last done never goes back, and a number at or below it is refused (error 11)
    assert "IF ice.pseq[slot] > ice.lastdone THEN" in server
    pb = "\n".join(PROGRAMS["ice.h.pb"][1])
    assert (f"IF (NOT (f.flags BAND {rp.FLAG_PARK})) AND (seq < {rp.FIRST_LINK_SEQ}) AND "
            "(seq <= ice.lastdone) THEN") in pb
    assert "CALL ice.r.er(seq, 11)" in pb
    ab = "\n".join(PROGRAMS["ice.h.ab"][1])
    assert "ice.cut = ice.goseq" in ab
    st = "\n".join(PROGRAMS["ice.h.st"][1])
    assert "ice.lastdone, ice.cut)" in st


def _reach(root, stop=()):
    """The programs ``root`` runs (CALL), not following into ``stop``."""
    seen, todo = set(), [root]
    while todo:
        p = todo.pop()
        if p in seen or p in stop:
            continue
        seen.add(p)
        for line in PROGRAMS[p][1]:
            todo += re.findall(r"(?:CALL|EXECUTE \d+) ([a-z0-9.]+)\(", line)
    return seen


def test_each_counter_of_the_path_ring_has_one_writer_task():
    """The upload task (ice.comm, task 1) counts ice.nup, the motion task (ice.server,
    task 0) ice.ndone. AB, handled on task 1, also wrote ice.ndone: one that came as a
    path ended left it past ice.nup, a stored count of -1 that broke the link until the
    server restarted (hunt W). AB now asks the motion task to drop the paths."""
    comm = _reach("ice.comm")
    server = _reach("ice.server", stop=("ice.comm", "ice.reset"))
    assert "ice.h.ab" in comm and "ice.h.pe" in comm

    def writers(var, progs):
        return {p for p in progs
                if any(re.match(rf"{re.escape(var)} = ", ln) for ln in PROGRAMS[p][1])}

    assert writers("ice.ndone", comm) == set()
    assert writers("ice.nup", server) == set()
    assert writers("ice.ndone", server) == {"ice.server"}
    ab = PROGRAMS["ice.h.ab"][1]
    assert "ice.dropreq = TRUE" in ab and "WAIT (NOT ice.dropreq) OR ice.quit" in ab
    body = PROGRAMS["ice.server"][1]
    assert "WAIT ice.gopend OR ice.quit OR ice.dropreq" in body
    k = body.index("IF ice.dropreq THEN")
    assert body[k + 2:k + 4] == ["ice.ndone = ice.nup", "ice.dropreq = FALSE"]


def test_a_field_that_is_not_a_number_is_refused_not_read_as_zero():
    """ice.field said it refuses a token that is no number, but V+'s VAL reads "abc" as 0
    and only an empty token was refused (hunt W): every character is checked first."""
    body = PROGRAMS["ice.field"][1]
    check = body.index('IF POS("0123456789+-.Ee", $MID($tok, i, 1), 1) == 0 THEN')
    assert body[check - 1] == "FOR i = 1 TO LEN($tok)"
    assert body[check + 1] == "ok = FALSE" and check < body.index("value = VAL($tok)")


def test_the_path_arrays_are_allocated_whole_before_the_upload_task_starts():
    """V+ extends a global array as its elements are set, and one task extending it while
    another reads it can crash the controller to DDT (V+ Language User's Guide, "Global
    Array Access Restriction"): the upload task grew the path ring point by point while
    the motion task read it. Every array is now set to its full size in ice.globals, which
    the server calls before it starts the upload task."""
    body = PROGRAMS["ice.globals"][1]
    arrays = {n.strip().rstrip("[]") for s in body if s.startswith("GLOBAL")
              for n in s.split(None, 2)[2].split(",") if n.strip().endswith("[]")}
    assert arrays == {"ice.px", "ice.py", "ice.pn", "ice.pdt", "ice.pz", "ice.pflags",
                      "ice.pseq"}
    outer = body.index("FOR i = 0 TO ice.maxpaths-1")
    inner = body.index("FOR j = 0 TO ice.maxpts-1")
    assert outer < inner
    set_in_loop = {s.split("[")[0] for s in body[outer:] if "[" in s and "=" in s}
    assert set_in_loop == arrays
    assert {s for s in body[inner:] if "[" in s} == {"ice.px[i,j] = 0", "ice.py[i,j] = 0"}
    server = PROGRAMS["ice.server"][1]
    assert server.index("CALL ice.globals()") < server.index("EXECUTE 1 ice.comm()")
