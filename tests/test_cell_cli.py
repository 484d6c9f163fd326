"""``icefab cell serve``: bad input is one line and exit 2, before any device starts."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import pytest

from icefab.cli import main


@pytest.mark.parametrize("argv, message", [
    ([], "no surface yet; give --grid-for TRAJECTORIES or --bounds"),
    (["--grid-for", "missing.npz"], "--grid-for missing.npz: trajectories file not found"),
    (["--bounds", "1,2,3"], "--bounds '1,2,3': expected X0,Y0,X1,Y1 in mm"),
    (["--bounds", "5,0,1,1"], "expected X0 < X1 and Y0 < Y1"),
    (["--bounds", "0,0,1,1", "--time-factor", "-1"], "--time-factor -1.0: expected 0"),
    (["--bounds", "0,0,1,1", "--port", "70000"], "--port 70000: expected 0..65535"),
    (["--bounds", "0,0,1,1", "--grid-for", "x.npz"], "give one of them"),
])
def test_serve_bad_input_is_one_line_and_exit_2(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(["cell", "serve", "--state", "st", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "st" / "endpoints.json").exists()


def test_serve_that_cannot_start_its_firmware_leaves_no_state(tmp_path, capsys):
    # a "firmware" that announces no pty: one line, exit 2, and the new state folder (its
    # surface was written before the devices started) goes
    state = tmp_path / "st"
    assert main(["cell", "serve", "--state", str(state), "--bounds", "0,0,10,10",
                 "--firmware", "/bin/true"]) == 2
    err = capsys.readouterr().err
    assert "no pty announced" in err and len(err.strip().splitlines()) == 1
    assert not state.exists()
    # a firmware that is not there: the message names it
    missing = tmp_path / "no-such-valvectl"
    assert main(["cell", "serve", "--state", str(state), "--bounds", "0,0,10,10",
                 "--firmware", str(missing)]) == 2
    err = capsys.readouterr().err
    assert f"--firmware {missing}: no such file" in err and len(err.strip().splitlines()) == 1
    assert not state.exists()


def test_serve_takes_a_relative_firmware_and_names_why_one_cannot_run(tmp_path, capsys,
                                                                       monkeypatch):
    """'--firmware ./valvectl' was looked up on PATH as 'valvectl'; a folder and a file
    without execute permission were "No such file or directory"; a program that never
    announces its pty hung the start for ever, deaf to Ctrl-C (hunt W)."""
    from icefab.cell import valve_host

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(valve_host, "ANNOUNCE_TIMEOUT_S", 0.5)
    silent = tmp_path / "silent"
    silent.write_text("#!/bin/sh\nexec sleep 30\n")
    silent.chmod(0o755)
    (tmp_path / "adir").mkdir()
    (tmp_path / "noexec").write_text("#!/bin/sh\n")
    for fw, says in (("./silent", f"{silent}: no pty announced within 0.5 s"),
                     ("./adir", "--firmware ./adir: is a folder"),
                     ("./noexec", "--firmware ./noexec: not executable"),
                     ("nosuch-valvectl", "no such program on PATH"),
                     ("silent", "no such program on PATH (give its path; this folder's is "
                                "--firmware ./silent)")):
        assert main(["cell", "serve", "--state", "st", "--bounds", "0,0,10,10",
                     "--firmware", fw]) == 2
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "st").exists()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_serve_waiting_on_a_silent_firmware_hears_a_stop(tmp_path, sig):
    """While the cell waited (10 s) for a firmware that never announces its pty, SIGTERM
    and Ctrl-C only set the serving loop's flag, which nothing read yet: the start went
    on to its timeout (hunt W's leftover). Either ends the start at once, as Ctrl-C ends
    any command, and the new state folder goes."""
    silent = tmp_path / "silent"
    silent.write_text("#!/bin/sh\nexec sleep 30\n")
    silent.chmod(0o755)
    proc = subprocess.Popen([sys.executable, "-m", "icefab", "cell", "serve", "--state", "st",
                             "--bounds", "0,0,10,10", "--firmware", "./silent"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        deadline = time.monotonic() + 30    # the folder is made before the firmware starts
        while not (tmp_path / "st").exists():
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
            time.sleep(0.02)
        time.sleep(0.5)
        t0 = time.monotonic()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == (143 if sig == signal.SIGTERM else 130), err
    assert took < 5.0, f"the start heard the signal after {took:.1f} s"
    assert "no pty announced" not in err
    assert not (tmp_path / "st").exists()


def test_serve_refuses_a_state_that_is_a_file(tmp_path, capsys):
    (tmp_path / "st").write_text("x")
    assert main(["cell", "serve", "--state", str(tmp_path / "st"), "--bounds", "0,0,1,1"]) == 2
    assert "exists and is not a folder" in capsys.readouterr().err


def test_serve_refuses_a_corrupt_surface(tmp_path, capsys):
    (tmp_path / "st").mkdir()
    (tmp_path / "st" / "surface.npz").write_bytes(b"not a zip")
    assert main(["cell", "serve", "--state", str(tmp_path / "st")]) == 2
    err = capsys.readouterr().err
    assert "surface.npz: cannot read" in err and len(err.strip().splitlines()) == 1


def test_endpoints_of_a_cell_that_is_not_running_are_named(tmp_path):
    from icefab.cell.virtual import read_endpoints
    from icefab.errors import CellError

    with pytest.raises(CellError, match="endpoints.json: no endpoints"):
        read_endpoints(tmp_path)
    (tmp_path / "endpoints.json").write_text("{")
    with pytest.raises(CellError, match="malformed endpoints file"):
        read_endpoints(tmp_path)
    # a host that is no string: 'icefab build --cell DIR' asked the robot before planning
    # and ended in getaddrinfo's TypeError traceback
    (tmp_path / "endpoints.json").write_text(json.dumps(
        {"robot": {"host": 5, "port": 7100}, "valve": {"device": "v"},
         "laser": {"device": "l"}}))
    with pytest.raises(CellError, match="malformed endpoints file.*robot host 5"):
        read_endpoints(tmp_path)


def test_check_names_the_device_that_does_not_answer(tmp_path, capsys):
    import socket

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    port = srv.getsockname()[1]
    srv.close()
    assert main(["cell", "check", "--robot", f"127.0.0.1:{port}", "--timeout", "1"]) == 2
    err = capsys.readouterr().err
    assert f"robot at 127.0.0.1:{port}: cannot connect" in err
    assert len(err.strip().splitlines()) == 1
    assert main(["cell", "check", "--laser", str(tmp_path / "tty")]) == 2
    assert "cannot open the serial port" in capsys.readouterr().err
    assert main(["cell", "check", "--robot", "nohostport"]) == 2
    assert "expected HOST:PORT" in capsys.readouterr().err
    # port 99999 reached whatever listened on 34463; a timeout of 1e300 s was a traceback
    # (hunt W)
    assert main(["cell", "check", "--robot", "127.0.0.1:99999"]) == 2
    assert "the port 1..65535" in capsys.readouterr().err
    assert main(["cell", "check", "--robot", f"127.0.0.1:{port}", "--timeout", "1e300"]) == 2
    assert "at most 3600" in capsys.readouterr().err


def test_check_names_the_robot_whose_replies_are_malformed(capsys):
    """An echo service on the robot's port: "malformed robot message HI: ..." named no
    device, where every other failure does (hunt W)."""
    import socket
    import threading

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)
    port = srv.getsockname()[1]

    def echo():
        c, _ = srv.accept()
        with c:
            c.sendall(c.recv(1024))
            c.recv(1024)

    t = threading.Thread(target=echo, daemon=True)
    t.start()
    try:
        assert main(["cell", "check", "--robot", f"127.0.0.1:{port}", "--timeout", "2"]) == 2
        err = capsys.readouterr().err
        assert f"robot at 127.0.0.1:{port}: malformed robot message" in err
    finally:
        srv.close()


@pytest.mark.parametrize("timeout", [0.6, 2.4])
def test_check_waits_for_a_silent_valve_controller_as_long_as_timeout(timeout, capsys):
    # a serial port nobody answers on: the valve link waited 3 s whatever --timeout said
    import os
    import time

    master, slave = os.openpty()
    try:
        t0 = time.monotonic()
        assert main(["cell", "check", "--valve", os.ttyname(slave),
                     "--timeout", str(timeout)]) == 2
        took = time.monotonic() - t0
    finally:
        os.close(master)
        os.close(slave)
    assert "no answer" in capsys.readouterr().err
    assert timeout * 0.9 <= took <= timeout + 1.0, took


def test_check_a_virtual_robot_and_laser(capsys):
    from icefab.cell.laser_emulator import PtyLaser
    from icefab.cell.virtual_robot import VirtualRobot

    class Idle:
        def layer_begin(self, *a): pass
        def layer_end(self, *a): pass
        def path_run(self, *a): return True
        def abort(self): pass

    vr = VirtualRobot(Idle()).start()
    pty = PtyLaser().start()
    try:
        assert main(["cell", "check", "--robot", f"127.0.0.1:{vr.port}", "--laser",
                     pty.path]) == 0
    finally:
        vr.stop()
        pty.stop()
    out = capsys.readouterr().out
    assert "protocol 2, 8192 points x 4 paths, idle" in out and "storage stopped" in out
    # and whether a build may start there without --platform-cleared
    assert "0 stored, no command completed since its program started" in out
