"""Variable-flow valve programs (thesis Ch. 6, 2.3.1)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.integrate import quad

from icefab import Job
from icefab.errors import ConfigError, FlowError, StackFileError
from icefab.flow import (DATA_DIR, calibration_for, load_calibration, n_pulses, plan_valves,
                         program_pieces, pulse_instants, pulse_times, read_valve_program,
                         total_duration, valve_frequency, write_valve_program)
from icefab.core import HeightMap, Toolpath, Trajectory, ValveProgram


def line_trajectory(length=100.0, vmax=50.0, accel=500.0, dt=0.016, role="boundary",
                    width=1.5, material="part", y=0.0):
    """Straight path with a trapezoidal speed profile, sampled at constant dt (base frame)."""
    t_acc = vmax / accel
    d_acc = 0.5 * accel * t_acc ** 2
    if 2 * d_acc > length:
        t_acc = np.sqrt(length / accel)
        vmax = accel * t_acc
        d_acc = length / 2
    t_cruise = (length - 2 * d_acc) / vmax
    T = 2 * t_acc + t_cruise
    n = int(np.ceil(T / dt)) + 1
    t = np.minimum(np.arange(n) * dt, T)
    s = np.where(t < t_acc, 0.5 * accel * t ** 2,
                 np.where(t < t_acc + t_cruise, d_acc + vmax * (t - t_acc),
                          length - 0.5 * accel * np.maximum(T - t, 0) ** 2))
    v = np.where(t < t_acc, accel * t, np.where(t < t_acc + t_cruise, vmax,
                                                 accel * np.maximum(T - t, 0)))
    job = Job()
    off = np.asarray(job.cell.ee_origin_mm) - np.asarray(job.materials[material].nozzle_offset_mm)
    xy = np.column_stack([s, np.full(n, y)]) + off
    path = Toolpath(points=np.array([[0.0, y], [length, y]]), material=material, role=role,
                width=width, layer=3)
    return Trajectory(dt=dt, xy=xy, joints=np.zeros((n, 0)), speed=v, duration=(n - 1) * dt,
                      path=path)


def test_builtin_tables_are_valid_and_about_20_points():
    for m in ("part", "scaffold"):
        cal = calibration_for(m, Job())
        assert 15 <= len(cal.frequency_hz) <= 25
        assert np.all(np.diff(cal.frequency_hz) > 0) and np.all(np.diff(cal.flow_mm3_s) > 0)
        assert cal.frequency_hz[0] == 0 and cal.frequency_hz[-1] == 1000
    # thesis 5.7: c_ff = 4 Hz / (mm^3/s) at the typical 25 mm/s boundary speed
    cal = calibration_for("part", Job())
    assert cal.frequency(np.array([1.5 * 0.25 * 25]))[0] == pytest.approx(37.5, rel=0.02)


@pytest.mark.parametrize("text,match", [
    ("frequency_hz,flow_mm3_s\n0,0\n", "at least 2 rows"),
    ("0,0\n100,20\n50,30\n", ":3: frequency must increase"),
    ("0,0\n100,20\n200,20\n", ":3: flow must increase"),
    ("0,0\n100,nan\n", ":2: values must be finite"),
    ("0,0\n100,abc\n", ":2: expected two numbers"),
    ("0,0,1\n", ":1: expected 2 columns"),
    ("0,0\n-5,3\n", ":2: .* >= 0"),
])
def test_calibration_errors_name_file_and_line(tmp_path, text, match):
    p = tmp_path / "cal.csv"
    p.write_text(text)
    with pytest.raises(FlowError, match=match) as exc:
        load_calibration(p)
    assert str(p) in str(exc.value)


def test_calibration_missing_file_named_by_setting(tmp_path):
    job = Job().replace(**{"materials.part.calibration_file": str(tmp_path / "nope.csv")})
    with pytest.raises(FlowError, match="materials.part.calibration_file"):
        calibration_for("part", job)


def test_calibration_reads_header_and_comments(tmp_path):
    p = tmp_path / "c.csv"
    p.write_text("# my valve\nfrequency_hz,flow_mm3_s\n0,0\n100,25 # comment\n500,100\n")
    cal = load_calibration(p)
    np.testing.assert_allclose(cal.frequency(np.array([12.5, 62.5])), [50, 300])


def test_pulse_count_equals_integral_of_frequency_within_one_pulse():
    traj = line_trajectory()
    job = Job()
    plan = valve_frequency(traj, "part", job)
    prog = plan_valves(traj, "part", job)
    # independent integral of the commanded (piecewise-linear) frequency with quad
    f = lambda t: np.interp(t, plan.t, plan.nu)  # noqa: E731
    integral = sum(quad(f, a, b)[0] for a, b in zip(plan.t[:-1], plan.t[1:]))
    assert abs(n_pulses(prog) - integral) <= 0.5 + 1e-9
    # and locally: pulses before any instant match the integral up to it within one pulse
    times = pulse_times(prog)
    for tc in np.linspace(0.1, traj.duration, 7):
        upto = sum(quad(f, a, min(b, tc))[0] for a, b in zip(plan.t[:-1], plan.t[1:]) if a < tc)
        assert abs(np.count_nonzero(times <= tc) - upto) <= 1.0 + 0.5 * 0.002 * plan.nu.max()


def test_frequency_follows_speed_and_flow_formula():
    traj = line_trajectory(vmax=100.0)
    job = Job()
    plan = valve_frequency(traj, "part", job)
    np.testing.assert_allclose(plan.q, 1.5 * 0.25 * traj.speed)  # eq. 6.2
    cal = calibration_for("part", job)
    np.testing.assert_allclose(cal.flow(plan.nu), plan.q, atol=1e-9)
    # constant volume per mm: pulses per mm is constant on the cruise part
    times = pulse_times(plan_valves(traj, "part", job))
    x = np.interp(times, traj.t, traj.xy[:, 0])
    counts, _ = np.histogram(x, bins=np.arange(x.min(), x.max(), 10.0))
    assert counts[1:-1].std() <= 1.0


def test_control_action_scales_flow():
    traj = line_trajectory()
    job = Job()
    base = valve_frequency(traj, "part", job)
    u = np.full(len(traj.xy), 0.2)
    plan = valve_frequency(traj, "part", job, action=u)
    np.testing.assert_allclose(plan.q, 1.2 * base.q)  # eq. 6.3
    # a HeightMap action sampled in the part frame (path along y = 0, x in [0, 100])
    z = np.tile(np.where(np.arange(121) < 60, 0.1, -0.1), (11, 1))
    hm = HeightMap(origin=np.array([-10.0, -5.0]), spacing=1.0, z=z)
    plan = valve_frequency(traj, "part", job, action=hm)
    x = traj.xy[:, 0] - traj.xy[0, 0]
    assert np.allclose(plan.u[x < 45], 0.1) and np.allclose(plan.u[x > 55], -0.1)
    callable_plan = valve_frequency(traj, "part", job, action=lambda xy: 0.1 + 0 * xy[:, 0])
    np.testing.assert_allclose(callable_plan.q, 1.1 * base.q)
    with pytest.raises(FlowError, match="shape"):
        valve_frequency(traj, "part", job, action=np.zeros(3))


def test_ticks_monotone_and_uint16():
    traj = line_trajectory(length=300.0, vmax=125.0)
    prog = plan_valves(traj, "part", Job())
    assert prog.ticks.dtype == np.uint16
    assert np.all(np.diff(prog.ticks.astype(int)) >= 0)
    assert prog.pieces == ()
    assert prog.duration == pytest.approx(traj.duration)


def test_split_at_pulse_limit():
    traj = line_trajectory(length=300.0, vmax=125.0)
    job = Job().replace(**{"flow.max_pulses": 100})
    whole = plan_valves(traj, "part", Job())
    prog = plan_valves(traj, "part", job)
    pieces = program_pieces(prog)
    assert len(pieces) >= int(np.ceil(n_pulses(whole) / 100)) >= 4
    assert all(len(p.ticks) <= 100 for p in pieces)
    assert n_pulses(prog) == n_pulses(whole)
    np.testing.assert_allclose(pulse_times(prog), pulse_times(whole), atol=1e-3 + 1e-9)
    assert total_duration(prog) == pytest.approx(traj.duration)
    # every boundary lies on a trajectory sample
    bounds = np.cumsum([p.duration for p in pieces])[:-1]
    np.testing.assert_allclose(bounds / traj.dt, np.rint(bounds / traj.dt), atol=1e-6)
    for p in pieces:
        assert np.all(np.diff(p.ticks.astype(int)) >= 0)


def test_split_at_time_limit():
    traj = line_trajectory(length=300.0, vmax=20.0, accel=100.0)  # ~15 s
    job = Job().replace(**{"flow.max_piece_s": 4.0})
    prog = plan_valves(traj, "part", job)
    pieces = program_pieces(prog)
    assert len(pieces) == int(np.ceil(traj.duration / 4.0))
    assert all(p.duration <= 4.0 + 1e-9 for p in pieces)
    assert all(int(p.ticks.max()) * 0.002 <= p.duration + 0.001 for p in pieces if len(p.ticks))
    np.testing.assert_allclose(pulse_times(prog), pulse_times(plan_valves(traj, "part", Job())),
                               atol=1e-3 + 1e-9)


def test_default_limits_131_s_and_uint16():
    # a slow 2.7 m path lasting ~270 s must be split at 131.072 s (thesis 2.3.1)
    traj = line_trajectory(length=2700.0, vmax=10.0, accel=100.0, dt=0.05)
    prog = plan_valves(traj, "part", Job())
    pieces = program_pieces(prog)
    assert len(pieces) == 3
    assert all(p.duration <= 131.072 for p in pieces)
    assert all(int(p.ticks.max()) <= 65535 for p in pieces)


def test_non_depositing_path_has_no_pulses():
    traj = line_trajectory(role="travel", width=0.0)
    prog = plan_valves(traj, "part", Job())
    assert len(prog.ticks) == 0 and prog.duration == pytest.approx(traj.duration)


def test_out_of_range_clamp_or_error():
    # a cell with a 1 ms tick can use the whole 1000 Hz table (thesis 6.1)
    ms = Job().replace(**{"flow.tick_s": 0.001, "flow.max_frequency_hz": 1000.0})
    traj = line_trajectory(length=200, vmax=125.0, width=3.0)
    u = np.full(len(traj.xy), 0.9)  # 3 * 0.25 * 125 * 1.9 = 178 mm^3/s, inside
    valve_frequency(traj, "part", ms, action=u)
    fast = line_trajectory(length=400, vmax=300.0, accel=2000.0, width=3.0)
    clamp = ms.replace(**{"flow.out_of_range": "clamp"})
    plan = valve_frequency(fast, "part", clamp, action=np.full(len(fast.xy), 0.3))
    assert plan.clamped > 0 and any("outside the calibration table" in w for w in plan.warnings)
    assert plan.nu.max() <= 1000.0
    with pytest.raises(FlowError, match="calibration table"):  # the default
        valve_frequency(fast, "part", ms, action=np.full(len(fast.xy), 0.3))


def test_min_drops_per_mm_reported():
    traj = line_trajectory()
    job = Job().replace(**{"flow.min_drops_per_mm": 5.0})
    plan = valve_frequency(traj, "part", job)
    assert any("drops per mm" in w for w in plan.warnings)


def test_pwm_mode_constant_period_and_widths():
    traj = line_trajectory(length=200, vmax=125.0, width=3.0)
    job = Job().replace(**{"flow.mode": "pwm"})
    prog = plan_valves(traj, "part", job)
    t = pulse_times(prog)
    gaps = np.diff(prog.ticks.astype(int))
    # 8 ms period in 2 ms ticks (+ rounding); on the ramps, where a period asks less than a
    # shortest pulse, some periods get none (their volume carried on): whole periods apart
    assert np.all(np.abs(gaps - 4 * np.rint(gaps / 4)) <= 1) and gaps.min() >= 3
    assert np.mean(gaps <= 5) > 0.9
    assert prog.widths_us is not None and len(prog.widths_us) == len(t)
    assert prog.widths_us.min() >= 500 and prog.widths_us.max() <= 8000
    # wider pulses where the speed is higher
    v = np.interp(t, traj.t, traj.speed)
    assert np.corrcoef(v, prog.widths_us.astype(float))[0, 1] > 0.9


@pytest.mark.parametrize("fmt", ["bin", "txt"])
@pytest.mark.parametrize("mode", ["fm", "pwm"])
def test_file_round_trip(tmp_path, fmt, mode):
    traj = line_trajectory(length=300.0, vmax=125.0)
    job = Job().replace(**{"flow.max_pulses": 200, "flow.mode": mode})
    prog = plan_valves(traj, "part", job)
    f = tmp_path / f"p.{fmt}"
    write_valve_program(prog, f, fmt=fmt)
    back = read_valve_program(f)
    a, b = program_pieces(prog), program_pieces(back)
    assert len(a) == len(b) > 1
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x.ticks, y.ticks)
        assert y.ticks.dtype == np.uint16
        assert x.duration == pytest.approx(y.duration, abs=1e-6)
        if mode == "pwm":
            np.testing.assert_array_equal(x.widths_us, y.widths_us)
        else:
            assert y.widths_us is None
    assert [p for p in tmp_path.iterdir()] == [f]  # no temp files left


def test_binary_layout_documented(tmp_path):
    import struct
    prog = ValveProgram(ticks=np.array([1, 2, 300], np.uint16), duration=1.5)
    f = tmp_path / "p.bin"
    write_valve_program(prog, f)
    data = f.read_bytes()
    assert data[:4] == b"ICEV"
    assert struct.unpack_from("<HBBII", data, 4) == (1, 0, 0, 2000, 1)
    assert struct.unpack_from("<II", data, 16) == (3, 1500000)
    assert struct.unpack_from("<3H", data, 24) == (1, 2, 300)
    assert len(data) == 30


def test_truncated_or_corrupt_files(tmp_path):
    prog = plan_valves(line_trajectory(), "part", Job())
    f = tmp_path / "p.bin"
    write_valve_program(prog, f)
    f.write_bytes(f.read_bytes()[:-3])
    with pytest.raises(StackFileError, match="truncated"):
        read_valve_program(f)
    t = tmp_path / "p.txt"
    write_valve_program(prog, t, fmt="txt")
    t.write_text("\n".join(t.read_text().splitlines()[:-2]) + "\n")
    with pytest.raises(StackFileError, match="truncated"):
        read_valve_program(t)
    with pytest.raises(StackFileError, match="not found"):
        read_valve_program(tmp_path / "none.bin")
    with pytest.raises(FlowError, match="format"):
        write_valve_program(prog, tmp_path / "x", fmt="hex")


@given(st.lists(st.floats(0.0, 900.0), min_size=2, max_size=60),
       st.floats(0.004, 0.05))
def test_pulse_instants_property(nu, dt):
    nu = np.asarray(nu)
    t = np.arange(len(nu)) * dt
    times = pulse_instants(t, nu)
    total = float(np.sum(0.5 * (nu[1:] + nu[:-1]) * dt))
    assert abs(len(times) - total) <= 0.5 + 1e-9
    assert np.all(np.diff(times) >= -1e-12)
    assert len(times) == 0 or (times[0] >= 0 and times[-1] <= t[-1] + 1e-12)


def test_action_sampled_under_the_nozzle_in_part_frame():
    from icefab.flow import trajectory_part_xy
    from icefab.paths import to_base_frame
    job = Job()
    pts = np.array([[1.0, 2.0], [30.0, -4.0]])
    for m in ("part", "scaffold"):
        base = to_base_frame(pts, m, job)
        tr = Trajectory(dt=0.016, xy=base, joints=np.zeros((2, 0)), speed=np.ones(2),
                        duration=0.016)
        np.testing.assert_allclose(trajectory_part_xy(tr, m, job), pts)


def test_data_files_exist():
    assert (DATA_DIR / "calibration_part.csv").is_file()
    assert (DATA_DIR / "calibration_scaffold.csv").is_file()


@pytest.mark.parametrize("controller", ["flow", "speed"])
def test_replan_valves_volume_per_mm_follows_action(controller):
    from icefab.flow import replan_valves
    job = Job().replace(**{"feedback.controller": controller})
    trajs = [line_trajectory(vmax=50.0, y=0.0), line_trajectory(vmax=50.0, y=10.0),
             line_trajectory(role="travel", width=0.0, y=20.0)]
    # u = +0.2 for y < 5, -0.1 above (part frame)
    hm = HeightMap(origin=np.array([-10.0, -5.0]), spacing=1.0,
                   z=np.where(np.arange(31)[:, None] < 10, 0.2, -0.1) * np.ones((31, 121)))
    out_t, out_p = replan_valves(trajs, job, action=hm)
    nominal = 1.5 * 0.25  # mm^3 per mm
    for tr, u in zip(out_t[:2], (0.2, -0.1)):
        plan = valve_frequency(tr, "part", Job())  # flow that follows the new speed
        prog_plan = valve_frequency(tr, "part", job, action=hm)
        vol = np.trapezoid(prog_plan.q, prog_plan.t)
        assert vol / 100.0 == pytest.approx((1 + u) * nominal, rel=0.01)
        if controller == "speed":
            assert tr.duration == pytest.approx(trajs[0].duration * (1 + u), rel=0.05)
            np.testing.assert_allclose(prog_plan.q, (1 + u) * plan.q, rtol=1e-9)
        else:
            assert tr is trajs[0] or tr is trajs[1]
    assert len(out_p[2].ticks) == 0 and out_t[2] is trajs[2]


_TRAJ = None


@given(st.integers(1, 400), st.floats(0.05, 3.0))
def test_split_property(max_pulses, max_piece_s):
    global _TRAJ
    if _TRAJ is None:
        _TRAJ = line_trajectory(length=150.0, vmax=80.0)
    traj = _TRAJ
    job = Job().replace(**{"flow.max_pulses": max_pulses, "flow.max_piece_s": max_piece_s})
    whole = plan_valves(traj, "part", Job())
    prog = plan_valves(traj, "part", job)
    pieces = program_pieces(prog)
    assert all(len(p.ticks) <= max_pulses for p in pieces)
    assert all(p.duration <= max_piece_s + 1e-9 for p in pieces)
    assert all(p.duration > 0 for p in pieces[:-1])
    assert n_pulses(prog) == n_pulses(whole)
    assert total_duration(prog) == pytest.approx(traj.duration)
    np.testing.assert_allclose(pulse_times(prog), pulse_times(whole), atol=0.001 + 1e-9)


def test_mtts_trajectory_volume_per_mm_is_nominal():
    """On a real minimum-time trajectory (variable speed, a stop at the sharp corner) the
    valve delivers w * dh per mm everywhere (thesis 6.2: volume per distance constant)."""
    from icefab import plan_motion
    from icefab.motion import thesis_test_path
    job = Job()
    pts = thesis_test_path(offset_mm=(-50.0, -30.0))
    path = Toolpath(points=pts, material="part", role="boundary", width=1.5, layer=0)
    traj = plan_motion(path, job)
    assert traj.speed.max() > 2 * np.median(traj.speed[traj.speed > 0]) / 3
    plan = valve_frequency(traj, "part", job)
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    vol = np.trapezoid(plan.q, plan.t)
    assert vol == pytest.approx(1.5 * 0.25 * length, rel=0.01)
    # pulses per mm: flow per pulse is h^-1(nu) / nu, so count the volume of the pulses
    prog = plan_valves(traj, "part", job)
    times = pulse_times(prog)
    cal = calibration_for("part", job)
    nu_at = np.interp(times, plan.t, plan.nu)
    per_pulse = cal.flow(nu_at) / nu_at
    assert per_pulse.sum() == pytest.approx(vol, rel=0.02)
    # and locally, along the path: volume per 10 mm window within 5 % of nominal
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(traj.xy, axis=0), axis=1))])
    s_pulse = np.interp(times, traj.t, s)
    edges = np.arange(10.0, s[-1] - 10.0, 10.0)
    vols, _ = np.histogram(s_pulse, bins=edges, weights=per_pulse)
    np.testing.assert_allclose(vols, 1.5 * 0.25 * 10.0, rtol=0.1)


def test_pwm_drops_per_mm_and_pulse_width_settings():
    traj = line_trajectory(length=300, vmax=200.0, accel=2000.0)
    job = Job().replace(**{"flow.mode": "pwm"})
    plan = valve_frequency(traj, "part", job)
    assert any("pwm_frequency_hz" in w for w in plan.warnings)  # 125 Hz < 200 mm/s
    with pytest.raises(ConfigError, match="flow.calibration_pulse_ms = 0.2: must be at least "
                                          "flow.min_pulse_ms"):
        Job().replace(**{"flow.calibration_pulse_ms": 0.2})


def test_valve_limit_findings_travel_with_the_program():
    """A program that cannot keep one drop per mm says so on the program itself."""
    import numpy as np
    from icefab import Job
    from icefab.flow import plan_valves
    from icefab.core import Toolpath, Trajectory

    job = Job().replace(**{"flow.min_drops_per_mm": 50.0})
    n = 200
    xy = np.column_stack([np.linspace(0, 100, n), np.zeros(n)])
    speed = np.full(n, 100.0)
    path = Toolpath(points=xy[[0, -1]], material="part", role="fill", width=3.0)
    traj = Trajectory(dt=0.005, xy=xy, joints=np.zeros((n, 2)), speed=speed,
                      duration=(n - 1) * 0.005, path=path)
    prog = plan_valves(traj, "part", job)
    assert any("flow.min_drops_per_mm" in w for w in prog.warnings)
    assert plan_valves(traj, "part", Job()).warnings == ()


def test_plan_valves_takes_the_default_job_and_names_a_material_it_does_not_know():
    # a program's plan_valves(tr, "part", None) was an AttributeError (every other stage
    # takes job=None as Job())
    tr = line_trajectory()
    a, b = plan_valves(tr, "part"), plan_valves(tr, "part", Job())
    assert np.array_equal(a.ticks, b.ticks) and len(a.ticks) > 0
    with pytest.raises(FlowError, match="material 'oil'"):
        plan_valves(tr, "oil", Job())


@given(st.integers(0, 2**31), st.sampled_from([0.001, 0.003, 0.005, 0.016]),
       st.floats(0.017, 0.05))
def test_every_pulse_plays_on_the_tick_nearest_its_instant_across_pieces(seed, dt, piece_s):
    """The controller starts piece j at S_j = floor(sum of the earlier pieces' whole
    microseconds / tick + 1/2) (PROTOCOL.md 7) and plays a pulse of tick k at S_j + k. The
    ticks were counted from the unrounded start: a boundary at half a tick put the next
    piece's first pulse a tick late, on the tick of the one before (a firmware review's:
    one drop lost). Read back from the binary layout, every pulse plays on the tick
    nearest its instant (half up), and pulse_times says so."""
    import struct

    from icefab.flow import _split, encode_valve_program, pulse_times

    rng = np.random.default_rng(seed)
    duration = 0.6
    times = np.sort(rng.uniform(0.0, duration, 120))
    job = Job().replace(**{"flow.max_piece_s": piece_s})
    prog = _split(times, None, duration, dt, job)
    data = encode_valve_program(prog)
    tick_us, n_pieces = struct.unpack_from("<II", data, 8)
    at, start_us, played = 16, 0, []
    for _ in range(n_pieces):
        n, dur = struct.unpack_from("<II", data, at)
        ticks = np.frombuffer(data, "<u2", n, at + 8).astype(np.int64)
        played.append((2 * start_us + tick_us) // (2 * tick_us) + ticks)
        start_us += dur
        at += 8 + 2 * n
    assert n_pieces > 1
    nearest = np.floor(times / (tick_us * 1e-6) + 0.5 + 1e-9).astype(np.int64)
    np.testing.assert_array_equal(np.concatenate(played), nearest)
    np.testing.assert_allclose(pulse_times(prog), nearest * tick_us * 1e-6, atol=1e-12)
