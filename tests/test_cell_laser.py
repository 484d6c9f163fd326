"""The LK-G laser link: the driver against the emulator on a pty."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from icefab import Job
from icefab.cell import lkg
from icefab.cell.laser import LaserLink, path_samples, sample_times
from icefab.cell.laser_emulator import LaserController, PtyLaser
from icefab.cell.robot import RobotPath
from icefab.errors import CellError


@pytest.fixture
def laser():
    pty = PtyLaser().start()
    link = LaserLink.open(pty.path, timeout_s=2)
    yield link, pty.controller
    link.close()
    pty.stop()


def test_values_stored_on_the_trigger_are_read_back_after_the_path(laser):
    link, dev = laser
    link.clear()
    assert link.status() == (False, 0)
    assert dev.timing_path(np.array([0.5])) == 0          # storage not started: nothing
    link.start()
    vals = np.array([0.01234, -1.5, np.nan, 250.0, -0.00004])
    assert dev.timing_path(vals) == 5
    assert link.status() == (True, 5)
    link.stop()
    got = link.read_stored()
    np.testing.assert_array_equal(np.isnan(got), [False, False, True, True, False])
    np.testing.assert_allclose(got[[0, 1, 4]], [0.0123, -1.5, 0.0], atol=1e-12)
    assert math.isclose(link.current(), -0.00004, abs_tol=1e-4)


def test_error_responses_carry_the_manuals_codes(laser):
    link, _ = laser
    with pytest.raises(CellError, match=r"ZZ refused: error 00 \(command error\)"):
        link.command("ZZ")
    with pytest.raises(CellError, match=r"error 21 \(parameter count error\)"):
        link.command("AO")
    with pytest.raises(CellError, match=r"error 22 \(invalid parameter error\)"):
        link.command("AO,7")
    link.start()
    with pytest.raises(CellError, match=r"AO refused: error 01 \(status error\)"):
        link.read_stored()                                  # still storing
    link.stop()
    link.read_stored()


def test_bytes_already_on_the_line_do_not_fail_the_first_command():
    """Two stray bytes sent to the laser's controller (line noise, a probe on the wrong
    port) came in front of the link's first command: "AN refused: error 00", once, on a
    healthy laser (hunt W). The link ends the partial line and sends it again."""
    import serial

    pty = PtyLaser().start()
    try:
        stray = serial.Serial(pty.path, lkg.BAUD)
        stray.write(b"\x00\x17")
        stray.flush()
        stray.close()
        with LaserLink.open(pty.path, timeout_s=2) as link:
            assert link.status() == (False, 0)
            with pytest.raises(CellError, match="ZZ refused: error 00"):
                link.command("ZZ")          # a command error later is the command's own
    finally:
        pty.stop()


def test_storage_stops_when_full():
    dev = LaserController(capacity=4)
    dev.handle("AS")
    assert dev.timing_path(np.zeros(10)) == 4
    assert dev.handle("AN") == "AN,0,4"


def test_commands_are_case_insensitive_and_length_checked():
    dev = LaserController()
    assert dev.handle("as") == "AS"
    assert dev.handle("A" * 40).endswith(",20")


def test_unopenable_port_is_one_clear_error():
    with pytest.raises(CellError, match="laser at /nonexistent/tty: cannot open"):
        LaserLink.open("/nonexistent/tty")


def test_no_response_is_a_timeout_error():
    import os
    import tty

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        link = LaserLink.open(os.ttyname(slave), timeout_s=0.3)
        with pytest.raises(CellError, match="no response to AN within 0.3 s"):
            link.status()
        link.close()
    finally:
        os.close(master)
        os.close(slave)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.floats(allow_nan=True, allow_infinity=True, width=64))
def test_value_format_round_trips_to_a_tenth_of_a_micrometre(v):
    text = lkg.format_value(v)
    assert len(text) == 8
    back = lkg.parse_value(text)
    if math.isnan(v) or abs(v) > lkg.RANGE_MM:
        assert math.isnan(back)
    else:
        assert abs(back - v) <= 0.5e-4 + 1e-12


@pytest.mark.parametrize("text", ["+1.0E300", "+1e+0999", "+nan    ", "+inf    ",
                                  "+1_2.345", "+0001234", "+12.34.5", "+123.456", " 01.2345"])
def test_a_value_outside_the_lk_g_format_is_a_link_fault(text):
    """A sign and seven characters, digits around one point, within +-99.9999 mm (manual
    p. 5-6): float() alone took "+1.0E300", and a corrupted readout at 1e300 mm drove SMF to
    its limit while the build said it completed (a hunt's)."""
    with pytest.raises(CellError, match="malformed measurement value"):
        lkg.parse_value(text)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.text(alphabet="+-.0123456789eEnaifFX_ ", min_size=8, max_size=8))
def test_every_value_field_is_a_height_within_range_or_refused(text):
    try:
        v = lkg.parse_value(text)
    except CellError:
        return
    assert math.isnan(v) or abs(v) <= lkg.RANGE_MM


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.text(max_size=40))
def test_the_emulator_answers_every_line(line):
    out = LaserController().handle(line.replace("\r", ""))
    assert out and "\r" not in out


def test_samples_are_tagged_along_the_path_in_time():
    job = Job()
    # a straight 1 s path at 100 mm/s along x, laser frame from the job
    xy = np.column_stack([np.linspace(300, 400, 63), np.full(63, -50.0)])
    path = RobotPath(xy=xy, dt_s=1 / 62, z_mm=2.0, flags=2, tool="laser", width_mm=0.0,
                     layer=0, index=0)
    assert len(sample_times(1.0)) == 101
    vals = np.full(101, 0.25)
    vals[3] = np.nan
    s = path_samples(path, vals, job)
    off = np.asarray(job.cell.ee_origin_mm) - np.asarray(job.cell.laser_offset_mm)
    assert s.shape == (100, 3)
    np.testing.assert_allclose(s[:3, 0], 300 - off[0] + np.array([0, 1, 2]), atol=1e-9)
    np.testing.assert_allclose(s[:, 1], -50 - off[1])
    np.testing.assert_allclose(s[:, 2], 2.25)
    with pytest.raises(CellError, match="102 stored values"):
        path_samples(path, np.zeros(102), job)
