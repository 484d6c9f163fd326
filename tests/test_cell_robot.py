"""The robot link: host side (icefab.cell.robot) against the virtual C40."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from icefab.cell import robot_protocol as rp
from icefab.cell.robot import RobotLink, RobotPath
from icefab.cell.virtual_robot import VirtualRobot
from icefab.errors import CellError


class Recorder:
    """Hooks that record what the robot did; a path takes its time at time_factor."""

    def __init__(self):
        self.events = []
        self.paths = []

    def layer_begin(self, layer, z):
        self.events.append(("layer_begin", layer, z))

    def layer_end(self, layer):
        self.events.append(("layer_end", layer))

    def path_run(self, seq, path, stop, time_factor):
        self.events.append(("triggers_on", seq, path.flags))
        self.paths.append((seq, path))
        if time_factor > 0 and stop.wait(path.duration_s / time_factor):
            self.events.append(("stopped", seq))
            return False
        self.events.append(("triggers_off", seq))
        return True

    def abort(self):
        self.events.append(("abort",))


@pytest.fixture
def robot():
    hooks = Recorder()
    vr = VirtualRobot(hooks, max_points=64, max_paths=2).start()
    yield vr, hooks
    vr.stop()


def _path(n=10, flags=rp.FLAG_VALVE, layer=3, index=0, dt=0.016):
    t = np.linspace(0, 1, n)
    xy = np.column_stack([300 + 20 * np.cos(t), -100.25 + 20 * np.sin(t)])
    return RobotPath(xy=xy, dt_s=dt, z_mm=1.5, flags=flags, tool="part", width_mm=1.2,
                     layer=layer, index=index)


def test_paths_arrive_as_sent_and_report_their_sequence_numbers(robot):
    vr, hooks = robot
    with RobotLink.connect("127.0.0.1", vr.port, timeout_s=5) as link:
        info = link.hello()
        assert (info.version, info.max_points, info.max_paths) == (rp.VERSION, 64, 2)
        link.begin_layer(3, 1.5)
        sent = [_path(n=n, index=i) for i, n in enumerate((1, 4, 5, 33))]
        seqs = []
        for p in sent:
            seq = link.upload(p)
            link.go(seq)
            done = link.wait_done(seq)
            assert done.seq == seq and done.points == len(p.xy)
            seqs.append(seq)
        link.end_layer(3)
        assert link.status() == {"state": "idle", "stored": 0, "last_done": seqs[-1],
                                 "cut": 0}
    assert len(set(seqs)) == len(seqs)
    for (seq, got), want, s in zip(hooks.paths, sent, seqs):
        assert seq == s
        np.testing.assert_allclose(got.xy, want.xy, atol=5e-4)   # %.3f mm on the wire
        assert (got.dt_s, got.z_mm, got.flags, got.tool, got.width_mm, got.layer,
                got.index) == (0.016, 1.5, rp.FLAG_VALVE, "part", 1.2, 3, want.index)
    assert hooks.events[0] == ("layer_begin", 3, 1.5)
    # LE is acknowledged when queued behind the motion; its hook runs on the motion thread
    deadline = time.monotonic() + 5
    while hooks.events[-1] != ("layer_end", 3) and time.monotonic() < deadline:
        time.sleep(0.01)
    assert hooks.events[-1] == ("layer_end", 3)


def test_next_path_uploads_while_one_moves_and_storage_is_bounded(robot):
    vr, _ = robot
    vr.time_factor = 1.0     # path a takes 2 s: long enough to upload and be refused during it
    with RobotLink.connect("127.0.0.1", vr.port, timeout_s=5) as link:
        link.hello()
        a = link.upload(_path(n=64, dt=0.032))
        link.go(a)
        b = link.upload(_path(n=32, index=1))        # while a moves
        with pytest.raises(CellError, match="error 3"):
            c = link.upload(_path(n=4, index=2))      # a and b stored: full
        with pytest.raises(CellError, match="error 7"):
            link.go(b)                                 # a still moving
        link.wait_done(a)
        link.go(b)
        link.wait_done(b)


def test_abort_stops_the_motion_and_drops_stored_paths(robot):
    vr, hooks = robot
    vr.time_factor = 0.5     # a 0.5 s path takes 1 s
    with RobotLink.connect("127.0.0.1", vr.port, timeout_s=5) as link:
        link.hello()
        a = link.upload(_path(n=32))
        link.go(a)
        b = link.upload(_path(n=32, index=1))
        time.sleep(0.1)
        link.abort()
        with pytest.raises(CellError, match="no reply"):
            link.wait_done(a, timeout_s=1.5)
        st = link.status()
        assert st["state"] == "aborted" and st["cut"] == a    # a was stopped mid-motion
        with pytest.raises(CellError, match="error 6"):
            link.go(b)                                 # dropped by the abort
    assert ("stopped", a) in hooks.events and ("abort",) in hooks.events
    assert ("triggers_off", a) not in hooks.events


def test_a_wrong_check_sum_or_count_is_refused(robot):
    vr, _ = robot
    # the socket and its file both closed (an open file keeps the socket: ResourceWarning)
    with socket.create_connection(("127.0.0.1", vr.port), timeout=5) as s, \
            s.makefile("rb") as f:
        pts = [(1.0, 2.0), (3.0, 4.0)]
        s.sendall(rp.encode("path_begin", 7, 0, 0, 1, 0, 1.0, 2, 16000, 500)
                  + rp.encode("path_points", 7, 0, 2, group=pts)
                  + rp.encode("path_end", 7, 2, rp.point_check([1, 3], [2, 4]) + 1))
        assert rp.decode(f.readline(), "robot").values == {"code": 5}
        s.sendall(b"PB,8,1,2\r\n")                      # too few fields
        msg = rp.decode(f.readline(), "robot")
        assert (msg.name, msg.seq, msg["code"]) == ("error", 8, 1)
        s.sendall(rp.encode("go", 9))                      # nothing stored
        assert rp.decode(f.readline(), "robot")["code"] == 6


def test_a_repeated_command_gets_the_same_reply_and_runs_once(robot):
    vr, hooks = robot
    with socket.create_connection(("127.0.0.1", vr.port), timeout=5) as s, \
            s.makefile("rb") as f:
        up = (rp.encode("path_begin", 5, 0, 0, 1, 0, 1.0, 2, 16000, 500)
              + rp.encode("path_points", 5, 0, 2, group=[(1.0, 2.0), (3.0, 4.0)])
              + rp.encode("path_end", 5, 2, rp.point_check([1, 3], [2, 4])))
        s.sendall(up)
        assert rp.decode(f.readline(), "robot").name == "ok"
        s.sendall(rp.encode("path_end", 5, 2, rp.point_check([1, 3], [2, 4])))  # repeat
        assert rp.decode(f.readline(), "robot").name == "ok"
        s.sendall(rp.encode("status", 6))
        assert rp.decode(f.readline(), "robot")["stored"] == 1      # stored once


def test_unreachable_robot_is_one_clear_error():
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    port = srv.getsockname()[1]
    srv.close()
    with pytest.raises(CellError, match=f"robot at 127.0.0.1:{port}: cannot connect"):
        RobotLink.connect("127.0.0.1", port, timeout_s=1)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.binary(max_size=130))
def test_decode_refuses_garbage_with_a_cell_error(data):
    try:
        rp.decode(data, "robot")
    except CellError:
        pass


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.lists(st.tuples(st.floats(-600, 600), st.floats(-600, 600)), min_size=1,
                max_size=4), st.integers(1, rp.MAX_SEQ))
def test_points_round_trip_to_the_micrometre(points, seq):
    line = rp.encode("path_points", seq, 0, len(points), group=points)
    msg = rp.decode(line, "host")
    assert msg.seq == seq and len(line) <= rp.MAX_LINE + 2
    np.testing.assert_allclose(np.array(msg.group), np.array(points), atol=5.0001e-4)


def test_point_check_matches_a_hand_computed_value():
    # (1000 + 600000) + (2000 + 600000) = 1203000 -> mod 999983 = 203017; then
    # 203017 + (-1 + 600000) + (0 + 600000) = 1403016 -> 403033
    assert rp.point_check([1.0, -0.001], [2.0, 0.0]) == 403033


@settings(max_examples=200, deadline=None, derandomize=True)
@given(st.floats(0, 1000, allow_nan=False))
def test_a_width_travels_exactly(width):
    line = rp.encode("path_begin", 3, 0, 0, rp.FLAG_VALVE, 0, width, 10, 16000, 250)
    assert rp.decode(line, "host")["width"] == width


def test_a_number_runs_once_and_the_last_done_never_goes_back(robot):
    # a tester's client ran paths 5, 5 and 3: each got OK and DN, and SS then said the last
    # done was 3, so a resume would have run 4 and 5 again
    vr, hooks = robot

    def upload(s, f, seq):
        s.sendall(rp.encode("path_begin", seq, 0, 0, 1, 0, 1.0, 2, 16000, 500)
                  + rp.encode("path_points", seq, 0, 2, group=[(1.0, 2.0), (3.0, 4.0)])
                  + rp.encode("path_end", seq, 2, rp.point_check([1, 3], [2, 4])))
        return rp.decode(f.readline(), "robot")

    with socket.create_connection(("127.0.0.1", vr.port), timeout=5) as s, \
            s.makefile("rb") as f:
        assert upload(s, f, 5).name == "ok"
        s.sendall(rp.encode("go", 6))
        assert rp.decode(f.readline(), "robot")["code"] == 6     # not the stored path
        s.sendall(rp.encode("go", 5))
        assert rp.decode(f.readline(), "robot").name == "ok"
        assert rp.decode(f.readline(), "robot").name == "done"
        for seq in (5, 3):
            s.sendall(rp.encode("path_begin", seq, 0, 0, 1, 0, 1.0, 2, 16000, 500))
            msg = rp.decode(f.readline(), "robot")
            assert (msg.name, msg.seq, msg["code"]) == ("error", seq, 11)
        assert 11 in rp.PERMANENT_ERRORS
        s.sendall(rp.encode("status", 9))
        msg = rp.decode(f.readline(), "robot")
        assert msg["last_done"] == 5 and msg["stored"] == 0
    assert [seq for seq, _ in hooks.paths] == [5]
    # the link's own numbers (not a build's) start at random each session: not refused
    with RobotLink.connect("127.0.0.1", vr.port, timeout_s=5) as link:
        link.hello()
        link._seq = rp.FIRST_LINK_SEQ + 10
        a = link.upload(_path(n=4))
        link.go(a)
        link.wait_done(a)
    with RobotLink.connect("127.0.0.1", vr.port, timeout_s=5) as link:
        link.hello()
        link._seq = rp.FIRST_LINK_SEQ + 2       # a later session that drew a lower start
        b = link.upload(_path(n=4))
        link.go(b)
        link.wait_done(b)
        assert b < a and link.status()["last_done"] == a      # the highest run


class FailsAfterRunning(Recorder):
    """A cell model whose path runs (deposits) and then fails: the virtual cell's surface
    save on a full disk."""

    def path_run(self, seq, path, stop, time_factor):
        super().path_run(seq, path, stop, time_factor)
        raise OSError(28, "No space left on device")


def test_a_cell_that_fails_after_a_path_ran_cuts_it_and_runs_no_more():
    """A hunt's virtual cell on a full disk: the path ran, the save failed, the robot sent
    no reply and kept no cut, and the build sent the same path again, 21 times. The path is
    now cut (never run again), the GO refused at once with error 12, and every later path
    refused with it too (a permanent refusal: the build stops, naming it)."""
    from icefab.errors import CellRefused

    hooks = FailsAfterRunning()
    vr = VirtualRobot(hooks, max_points=64, max_paths=2).start()
    try:
        with RobotLink.connect("127.0.0.1", vr.port, timeout_s=5) as link:
            link.hello()
            a = link.upload(_path())
            link.go(a)
            with pytest.raises(CellRefused, match="error 12 .*runs no more paths"):
                link.wait_done(a, timeout_s=5)
            assert link.status()["cut"] == a
            with pytest.raises(CellRefused, match="error 12"):
                link.upload(_path(index=1))
        assert [p[0] for p in hooks.paths] == [a]
    finally:
        vr.stop()
