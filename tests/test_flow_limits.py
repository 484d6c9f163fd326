"""Valve limits are enforced or recorded on the program, never only logged (thesis 6.1, 2.3.1).

Expected numbers come from the built-in part table (``calibration_part.csv``: 125 Hz passes
30.95 mm^3/s, so one 0.5 ms calibration pulse at 125 Hz is V_ref = 30.95 / 125 mm^3) and the
thesis' PWM rule: at a fixed frequency the pulse width carries the flow, widths in
[min_pulse_ms, period].
"""
from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from icefab import Job
from icefab.errors import ConfigError, FlowError
from icefab.flow import (finding_kind, n_pulses, plan_valves, program_pieces, pulse_times,
                         summarise_findings, valve_frequency)
from icefab.core import Toolpath, Trajectory

V_REF = 30.95 / 125.0  # mm^3 per 0.5 ms pulse at 125 Hz (table row 125 Hz, 30.95 mm^3/s)
PWM = {"flow.mode": "pwm"}


def constant_trajectory(speed, duration=0.8, dt=0.016, width=1.5, role="boundary",
                        material="part"):
    """A straight path at constant speed lasting exactly ``duration`` (a whole number of
    8 ms PWM periods and of time steps), so every PWM period commands the same volume."""
    n = int(round(duration / dt)) + 1
    s = np.arange(n) * dt * speed
    xy = np.column_stack([s, np.zeros(n)]) + np.array([200.0, -100.0])
    path = Toolpath(points=xy[[0, -1]] if n > 1 else xy[[0, 0]], material=material, role=role,
                width=width, layer=7)
    return Trajectory(dt=dt, xy=xy, joints=np.zeros((n, 0)), speed=np.full(n, float(speed)),
                      duration=(n - 1) * dt, path=path)


def volumes(text):
    m = re.search(r"delivers (\S+) of (\S+) mm\^3 commanded", text)
    assert m, text
    return float(m.group(1)), float(m.group(2))


# ----------------------------------------------------------------------------- PWM limits
# width 1.5 mm, layer 0.25 mm: q = 0.375 c mm^3/s, V = q / 125 per pulse, and the needed
# width 0.5 ms * V / V_ref reaches 0.25 ms (half the shortest pulse) at c = 41.27 mm/s and
# 0.5 ms at c = 82.53 mm/s.
C_DROP = 0.25 / 0.5 * V_REF * 125.0 / 0.375
C_RAISE = 0.5 / 0.5 * V_REF * 125.0 / 0.375


def test_boundary_speeds_follow_the_table():
    assert C_DROP == pytest.approx(41.27, abs=0.01) and C_RAISE == pytest.approx(82.53, abs=0.01)


def test_pwm_below_half_the_shortest_pulse_lays_the_volume_in_every_other_period():
    """A tester's bunny in PWM: every period asking a width below min_pulse_ms / 2 got no
    pulse, so a slow path lost its whole volume (-100 %) and icefab valves exited 0 under
    "error"; what each period misses is carried into the next, so half the periods get a
    shortest pulse."""
    traj = constant_trajectory(C_DROP - 0.3)
    prog = plan_valves(traj, "part", Job().replace(**PWM))
    assert n_pulses(prog) == 50 and set(prog.widths_us.tolist()) == {500}
    (w,) = prog.warnings
    assert "50 of 100 pulses dropped" in w and "flow.min_pulse_ms" in w and "layer 7" in w
    delivered, commanded = volumes(w)
    assert commanded == pytest.approx(0.375 * (C_DROP - 0.3) * 0.8, rel=1e-3)
    assert abs(delivered - commanded) <= V_REF / 2        # FM's half a pulse (eq. 6.6)
    assert (prog.commanded_mm3, prog.laid_mm3) == pytest.approx((commanded, delivered),
                                                                rel=1e-3)


def test_pwm_between_half_and_the_shortest_pulse_lays_the_volume_not_twice_it():
    c = C_DROP + 0.3
    prog = plan_valves(constant_trajectory(c), "part", Job().replace(**PWM))
    assert set(prog.widths_us.tolist()) == {500} and 50 <= n_pulses(prog) < 100
    (w,) = prog.warnings
    assert "raised" in w
    delivered, commanded = volumes(w)
    assert commanded == pytest.approx(0.375 * c * 0.8, rel=1e-3)
    assert abs(delivered - commanded) <= V_REF / 2        # was +97 %


@pytest.mark.parametrize("out_of_range", ["error", "clamp"])
@pytest.mark.parametrize("share", [0.02, 0.13, 0.49, 0.51, 0.77, 1.3, 5.5])
def test_a_slow_pwm_path_gets_its_volume_within_half_a_shortest_pulse(out_of_range, share):
    """The bunny's boundaries asked an eighth of a shortest pulse a period: whatever the
    share, the laid volume is within half a shortest pulse of the commanded volume (and
    the width's whole-microsecond rounding), and no pulse is outside [0.5, 8] ms."""
    c = share * C_RAISE
    prog = plan_valves(constant_trajectory(c, duration=2.4), "part",
                       Job().replace(**PWM, **{"flow.out_of_range": out_of_range}))
    commanded = 0.375 * c * 2.4
    laid = prog.widths_us.astype(float).sum() / 1000.0 / 0.5 * V_REF
    assert abs(laid - commanded) <= V_REF / 2 + 300 * 0.0005 / 0.5 * V_REF
    assert prog.laid_mm3 == pytest.approx(laid, rel=1e-9)
    assert prog.commanded_mm3 == pytest.approx(commanded, rel=1e-3)
    assert prog.widths_us.min(initial=500) >= 500 and prog.widths_us.max(initial=0) <= 8000


def test_pwm_just_below_and_above_the_shortest_pulse():
    below = plan_valves(constant_trajectory(C_RAISE - 0.3), "part", Job().replace(**PWM))
    assert any("100 raised" in w for w in below.warnings)
    above = plan_valves(constant_trajectory(C_RAISE + 0.3), "part", Job().replace(**PWM))
    assert above.warnings == ()
    width_ms = above.widths_us.astype(float) / 1000.0
    # whole microseconds, the remainder carried: each within a microsecond of the width asked
    np.testing.assert_allclose(width_ms, 0.5 * 0.375 * (C_RAISE + 0.3) / 125 / V_REF, atol=1e-3)


def test_pwm_above_the_tables_highest_flow_is_cut_and_reported_or_an_error():
    """The PWM model scales a pulse's volume with its width from the table's 0.5 ms pulses;
    fully open at 125 Hz that counted 16 x 30.95 = 495 mm^3/s, 2.5 x the table's highest
    flow (195 mm^3/s at 1000 Hz), and a gantry hunt's G-code was written for 378 mm^3/s.
    The longest pulse now gives the table's highest flow: 0.5 ms x 195 / 30.95 = 3.15 ms."""
    # layer 2 mm, width 1.5 mm: q = 3 c, the table's 195 mm^3/s at 65 mm/s
    c_cut = 195.0 / 3.0
    w_max = 0.5 * 195.0 / 30.95
    job = Job().replace(**PWM, **{"flow.out_of_range": "clamp"})
    ok = plan_valves(constant_trajectory(c_cut - 2), "part", job, layer_thickness=2.0)
    assert ok.warnings == () and ok.widths_us.max() <= w_max * 1000
    cut = plan_valves(constant_trajectory(c_cut + 2), "part", job, layer_thickness=2.0)
    (w,) = cut.warnings
    assert "100 cut to 3.15 ms" in w and "calibration table's highest flow" in w
    assert set(cut.widths_us.tolist()) == {int(w_max * 1000)}
    delivered, commanded = volumes(w)
    assert delivered / commanded == pytest.approx(c_cut / (c_cut + 2), rel=2e-3)
    with pytest.raises(FlowError, match=r"layer 7 .*flow 201 mm\^3/s above the 195 mm\^3/s "
                                        r".*fits at speeds up to 65 mm/s.*"
                                        r"flow.out_of_range = 'clamp'"):
        plan_valves(constant_trajectory(c_cut + 2), "part",
                    job.replace(**{"flow.out_of_range": "error"}), layer_thickness=2.0)


def test_pwm_flow_range_ends_at_the_tables_highest_flow():
    from icefab.flow import calibration_for, pwm_max_width_ms, valve_flow_range

    job = Job().replace(**PWM)
    cal = calibration_for("part", job)
    assert valve_flow_range(cal, job) == pytest.approx((0.0, 195.0))
    assert pwm_max_width_ms(cal, job) == pytest.approx(0.5 * 195.0 / 30.95)
    # 10 Hz: 39 ms of the 100 ms period; 400 Hz: 1.03 ms of 2.5 ms (fully open 472 mm^3/s)
    slow = job.replace(**{"flow.pwm_frequency_hz": 10.0})
    assert pwm_max_width_ms(cal, slow) == pytest.approx(0.5 * 195.0 / 2.5)
    fast = job.replace(**{"flow.pwm_frequency_hz": 400.0})
    assert pwm_max_width_ms(cal, fast) == pytest.approx(0.5 * 195.0 / 94.43)
    # a table whose highest flow is more than the valve passes open all period: the period
    cal2 = dataclasses.replace(cal, flow_mm3_s=cal.flow_mm3_s * np.where(
        cal.frequency_hz >= 1000, 10.0, 1.0))
    assert pwm_max_width_ms(cal2, job) == pytest.approx(8.0)


def test_pwm_volume_is_the_commanded_volume_inside_the_limits():
    """Per-pulse volume = integral of the commanded flow over its period (not a sample)."""
    from test_flow import line_trajectory  # trapezoidal speed: widths vary along the path
    traj = line_trajectory(length=300.0, vmax=125.0, width=3.0)
    prog = plan_valves(traj, "part", Job().replace(**PWM))
    commanded = 3.0 * 0.25 * 300.0
    delivered = prog.widths_us.astype(float).sum() / 1000.0 / 0.5 * V_REF
    # the ramps' first and last pulses are below the shortest pulse: reported, small
    (w,) = prog.warnings
    assert volumes(w)[0] == pytest.approx(delivered, rel=1e-3)
    assert delivered == pytest.approx(commanded, rel=0.01)


@pytest.mark.parametrize("setting,value,match", [
    ("flow.pwm_frequency_hz", 2000.0, r"flow.pwm_frequency_hz = 2000: .*1 / flow.tick_s = 500"),
    ("flow.pwm_frequency_hz", 600.0, r"flow.pwm_frequency_hz = 600: .*1 / flow.tick_s = 500"),
])
def test_pwm_frequency_above_the_valve_or_the_tick_is_rejected(setting, value, match):
    with pytest.raises(ConfigError, match=match):  # the job cannot even be made
        Job().replace(**{**PWM, setting: value})
    # a job built around the check (unvalidated copy) is still refused where it is used
    job = Job().replace(**PWM)
    object.__setattr__(job.flow, "pwm_frequency_hz", value)
    with pytest.raises(ConfigError, match=match):
        plan_valves(constant_trajectory(100.0), "part", job)
    with pytest.raises(ConfigError, match=match):  # also for a path that deposits nothing
        plan_valves(constant_trajectory(100.0, role="travel", width=0.0), "part", job)


def test_pwm_frequency_outside_the_table_is_rejected(tmp_path):
    cal = tmp_path / "c.csv"
    cal.write_text("200,40\n1000,195\n")
    job = Job().replace(**{**PWM, "materials.part.calibration_file": str(cal)})
    with pytest.raises(ConfigError, match=r"flow.pwm_frequency_hz = 125: outside the "
                                          r"calibration table"):
        plan_valves(constant_trajectory(100.0), "part", job)


@settings(max_examples=60, deadline=None)
@given(f=st.floats(20.0, 500.0), dt=st.sampled_from([0.016, 0.005, 0.003, 0.0123]),
       duration=st.floats(0.05, 3.0))
def test_pwm_pulses_never_share_a_tick(f, dt, duration):
    n = max(2, int(duration / dt))
    traj = constant_trajectory(125.0, duration=(n - 1) * dt, dt=dt, width=3.0)
    job = Job().replace(**{**PWM, "flow.pwm_frequency_hz": f, "flow.max_pulses": 97})
    prog = plan_valves(traj, "part", job)
    for piece in program_pieces(prog):
        assert np.all(np.diff(piece.ticks.astype(np.int64)) >= 1)
    assert not any("share" in w for w in prog.warnings)
    assert n_pulses(prog) == int(np.floor(traj.duration * f + 0.5 + 1e-9)) or \
        any("dropped" in w for w in prog.warnings)


# ----------------------------------------------------------------------------- FM limits


def test_fm_frequency_never_above_one_pulse_per_tick():
    """Thesis 2.3.1: pulse instants in 2 ms ticks, so at most 500 pulses/s; the default
    flow.max_frequency_hz agrees (the valve's own 1000 Hz, thesis 6.1, is out of reach),
    and a pair that disagrees is refused naming both settings."""
    job = Job()
    assert job.flow.max_frequency_hz * job.flow.tick_s == pytest.approx(1.0)
    # 3 mm x 0.25 mm at 160 mm/s = 120 mm^3/s: above 115.28 mm^3/s = 500 Hz in the table
    with pytest.raises(FlowError, match="flow.max_frequency_hz"):
        plan_valves(constant_trajectory(160.0, width=3.0), "part", job)
    clamp = job.replace(**{"flow.out_of_range": "clamp"})
    prog = plan_valves(constant_trajectory(160.0, width=3.0), "part", clamp)
    for p in program_pieces(prog):
        assert np.all(np.diff(p.ticks.astype(int)) >= 1)     # no tick holds two pulses
    with pytest.raises(ConfigError, match=r"flow.max_frequency_hz = 1000: above 1 / "
                                          r"flow.tick_s = 500 Hz"):
        Job().replace(**{"flow.max_frequency_hz": 1000.0})
    Job().replace(**{"flow.max_frequency_hz": 1000.0, "flow.tick_s": 0.001})


def test_clamped_flow_reports_the_volume_lost():
    # 3 mm x 1 mm at 100 mm/s = 300 mm^3/s; the table ends at 195 mm^3/s: 35 % short
    traj = constant_trajectory(100.0, width=3.0)
    job = Job().replace(**{"flow.out_of_range": "clamp", "flow.tick_s": 0.001,
                           "flow.max_frequency_hz": 1000.0})   # the whole table usable
    prog = plan_valves(traj, "part", job, layer_thickness=1.0)
    (w,) = [w for w in prog.warnings if "calibration table" in w]
    assert "flow 300 mm^3/s outside the calibration table [0, 195]" in w
    assert "flow.out_of_range = 'clamp'" in w
    delivered, commanded = volumes(w)
    assert commanded == pytest.approx(300 * 0.8, rel=1e-3)
    assert delivered == pytest.approx(195 * 0.8, rel=1e-3)
    assert "-35.0 %" in w


def test_flow_outside_the_table_is_an_error_naming_path_flow_range_and_setting():
    traj = constant_trajectory(100.0, width=3.0)
    job = Job().replace(**{"flow.out_of_range": "error"})
    with pytest.raises(FlowError) as exc:
        plan_valves(traj, "part", job, layer_thickness=1.0)
    msg = str(exc.value)
    for part in ("layer 7 part boundary path", "flow 300 mm^3/s", "[0, 195] mm^3/s",
                 "calibration_part.csv", "flow.out_of_range = 'clamp'"):
        assert part in msg


def test_flow_outside_the_table_is_an_error_by_default():
    with pytest.raises(FlowError, match="outside the calibration table"):
        plan_valves(constant_trajectory(100.0, width=3.0), "part", Job(), layer_thickness=1.0)


def test_zero_flow_is_zero_hertz_for_a_table_not_starting_at_zero(tmp_path):
    cal = tmp_path / "c.csv"
    cal.write_text("10,2.5\n1000,195\n")
    job = Job().replace(**{"materials.part.calibration_file": str(cal),
                           "flow.out_of_range": "error"})
    traj = constant_trajectory(20.0)
    speed = traj.speed.copy()
    speed[[0, -1]] = 0.0  # at rest at both ends: no flow, no pulses, not out of range
    traj = Trajectory(dt=traj.dt, xy=traj.xy, joints=traj.joints, speed=speed,
                      duration=traj.duration, path=traj.path)
    plan = valve_frequency(traj, "part", job)
    assert plan.nu[0] == 0 and plan.nu[-1] == 0 and plan.warnings == ()


# ----------------------------------------------------------------------------- input checks


@pytest.mark.parametrize("duration,dt,match", [
    (5.0, 0.016, r"layer 7 .*duration = 5.0 s disagrees with its 51 samples"),
    (0.0, 0.016, r"duration = 0.0 s disagrees"),
    (0.8, 0.0, r"dt = 0.0 s: must be finite and > 0"),
    (0.8, float("nan"), r"dt = nan s"),
])
def test_inconsistent_trajectory_timing_is_rejected(duration, dt, match):
    good = constant_trajectory(50.0)
    bad = Trajectory(dt=dt, xy=good.xy, joints=good.joints, speed=good.speed,
                     duration=duration, path=good.path)
    with pytest.raises(FlowError, match=match):
        plan_valves(bad, "part", Job())
    with pytest.raises(FlowError, match=match):
        valve_frequency(bad, "part", Job())


def test_consistent_timing_within_a_microsecond_is_accepted():
    good = constant_trajectory(50.0)
    ok = Trajectory(dt=good.dt, xy=good.xy, joints=good.joints, speed=good.speed,
                    duration=good.duration + 5e-7, path=good.path)
    assert n_pulses(plan_valves(ok, "part", Job())) == n_pulses(plan_valves(good, "part", Job()))
    assert pulse_times(plan_valves(ok, "part", Job()))[-1] <= ok.duration


# ----------------------------------------------------------------------------- summaries


def test_findings_are_grouped_by_kind_with_counts():
    a = "layer 3 part fill path: flow 300 mm^3/s outside the calibration table [0, 195]"
    b = "layer 9 part fill path: flow 250.5 mm^3/s outside the calibration table [0, 195]"
    c = "layer 9 scaffold fill path: fewer than flow.min_drops_per_mm = 1 drops per mm (0.4)"
    assert finding_kind(a) == finding_kind(b) != finding_kind(c)
    lines = summarise_findings([(3, a), (9, b), (9, c)])
    assert lines == [f"2 paths in 2 layers (3, 9): {a}", f"1 path in layer 9: {c}"]
    assert summarise_findings([]) == []


@pytest.mark.parametrize("factor,expect", [(2.0, "+100.0 %"), (0.5, "-50.0 %"), (1.04, None)])
def test_speed_that_disagrees_with_the_samples_is_reported(factor, expect):
    """The flow follows ``speed`` (eq. 6.2) while the nozzle follows ``xy``: a speed in the
    wrong unit, or not updated after re-timing, changes the volume per mm."""
    good = constant_trajectory(50.0)  # 40 mm in 0.8 s
    bad = Trajectory(dt=good.dt, xy=good.xy, joints=good.joints, speed=good.speed * factor,
                     duration=good.duration, path=good.path)
    found = [w for w in plan_valves(bad, "part", Job()).warnings if "integrates" in w]
    if expect is None:  # within 5 %: MTTS samples the speed, not the chords
        assert found == []
    else:
        (w,) = found
        assert f"integrates to {40 * factor:g} mm but its samples travel 40 mm" in w
        assert expect in w and "layer 7" in w


def test_pwm_pieces_fit_the_valve_controllers_store():
    """A 40 s PWM path at 125 Hz has 5 000 pulses: the valve controller must hold a PWM
    piece whole (4 n + 8 bytes in its 12 288-byte store, firmware/PROTOCOL.md), so the
    program comes in pieces of at most 2 048 pulses; FM keeps flow.max_pulses (16 384)."""
    traj = constant_trajectory(100.0, duration=40.0)
    pwm = program_pieces(plan_valves(traj, "part", Job().replace(**PWM)))
    assert sum(len(p.ticks) for p in pwm) >= 4900 and len(pwm) >= 2
    assert max(len(p.ticks) for p in pwm) <= 2048
    assert all(4 * len(p.ticks) + 8 <= 12288 for p in pwm)
    fm = program_pieces(plan_valves(traj, "part", Job()))
    assert len(fm) == 1 and len(fm[0].ticks) > 2048


def test_summarised_findings_total_the_volume_each_kind_costs():
    """A tester's bunny in PWM: the summary showed one path per kind ("-100.0 %" of 34.4
    mm^3) and no total; a kind stating volumes now ends with the sum over all its paths."""
    found = [(1, "layer 1 part boundary path: PWM at flow.pwm_frequency_hz = 125 Hz: 8 of 8 "
                 "pulses dropped; delivers 1 of 2 mm^3 commanded (-50.0 %)"),
             (2, "layer 2 part boundary path: PWM at flow.pwm_frequency_hz = 125 Hz: 4 of 9 "
                 "pulses dropped; delivers 3 of 4 mm^3 commanded (-25.0 %)"),
             (2, "layer 2 scaffold fill path: fewer than flow.min_drops_per_mm = 1 drops per "
                 "mm (0.3) at 2 samples")]
    lines = summarise_findings(found)
    assert lines[0].startswith("2 paths in 2 layers (1-2): layer 1 part boundary path")
    assert lines[0].endswith("; in all, delivers 4 of 6 mm^3 commanded (-33.3 %)")
    assert "in all" not in lines[1]


def test_a_piece_lasts_no_longer_than_the_binary_layout_stores(tmp_path):
    """A piece's duration is a uint32 count of microseconds: a 1 mm/s path of 4 500 s at a
    0.1 s tick and flow.max_piece_s = 1e4 (legal, and 65 535 ticks allow 6 553 s) made
    one 4 500 s piece, and writing it ended in struct.error (a hunt's). Pieces now end
    within 4 294.97 s, and the file reads back as planned."""
    from icefab.flow import read_valve_program, write_valve_program

    job = Job().replace(**{"flow.tick_s": 0.1, "flow.max_frequency_hz": 10.0,
                           "flow.max_piece_s": 1e4})
    traj = constant_trajectory(1.0, duration=4500.0, dt=0.1)
    prog = plan_valves(traj, "part", job)
    pieces = program_pieces(prog)
    assert len(pieces) == 2 and max(p.duration for p in pieces) <= (2 ** 32 - 2) / 1e6
    assert sum(p.duration for p in pieces) == pytest.approx(4500.0)
    write_valve_program(prog, tmp_path / "long.bin")
    back = read_valve_program(tmp_path / "long.bin")
    np.testing.assert_allclose(pulse_times(back), pulse_times(prog), atol=1e-6)


@pytest.mark.parametrize("settings, name", [
    ({"flow.tick_s": 1.55e-5}, "flow.tick_s"),
    ({"feedback.controller": "speed", "feedback.saturation": 1.0}, "feedback.saturation")])
def test_settings_the_valve_programs_cannot_keep_are_refused(settings, name):
    """A tick that is no whole number of microseconds was stored rounded in the binary
    programs (1.55e-5 s read back as 1.6e-5 s: pulses up to 32 ms off); the speed
    controller at saturation 1 would stop a path (it failed mid-simulation naming an
    internal argument, 'max_change'). Both are refused up front, naming the setting."""
    with pytest.raises(ConfigError, match=re.escape(name)):
        Job().replace(**settings)


def test_a_table_reaching_absurd_frequencies_is_refused_before_its_pulses(tmp_path):
    """A calibration table with a row at 1e12 Hz: the layer's pass made pulses for every
    sample (~1e11 a step) before refusing them, and 'icefab valves' ran for minutes,
    deaf to SIGTERM (hunt W). The pass now makes pulses only for the paths it programs;
    the path is refused at once, or clamped, as any path beyond the valve."""
    from icefab.flow import _nominal_fm_programs, calibration_for

    cal = tmp_path / "c.csv"
    cal.write_text("frequency_hz,flow_mm3_s\n0,0\n100,8.3\n200,16.7\n1e12,33.3\n")
    traj = constant_trajectory(60.0, duration=8.0)
    for mode in ("error", "clamp"):
        job = Job().replace(**{"materials.part.calibration_file": str(cal),
                               "flow.out_of_range": mode})
        tables = {"part": calibration_for("part", job)}
        assert _nominal_fm_programs([traj], ["part"], 0.25, tables, job) == [None]
    with pytest.raises(FlowError, match="above the limit 500 Hz"):
        plan_valves(traj, "part", job.replace(**{"flow.out_of_range": "error"}))
    prog = plan_valves(traj, "part", job)   # clamped: at most one pulse a tick
    assert n_pulses(prog) <= 8.0 * 500 + 1
