"""1D SMF model, stability and gain optimisation against the thesis (Ch. 5.4-5.7)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from icefab.errors import ConfigError
from icefab.feedback import (Disturbance, error_response, evaluate_gains, in_stable_volume,
                             poles, rms_and_gradient, simulate_1d, stability,
                             transfer_function, tune_gains)


def direct_model(gains, d):
    """Eqs. 5.11a-c written out literally (the reference the filter form must match)."""
    kp, ki, kd = gains
    n = len(d)
    e = np.zeros(n + 2)  # e[k] for k = 0..n+1, e_1 = r_0 - 0 = 0
    nu_sum = 0.0
    cf = 37.5
    for k in range(1, n + 1):
        u = kp * e[k] + ki * e[1:k + 1].sum() + (kd * (e[k] - e[k - 1]) if k > 1 else 0.0)
        nu = cf * (u + 1.0)
        nu_sum += nu / cf + d[k - 1]
        e[k + 1] = k - nu_sum  # e_{k+1} = r_k - sum(nu_i / C_f + d_i), r_k = k
    return e[1:n + 1]


@pytest.mark.parametrize("gains", [(1.0, 0.33, 0.03), (0.8, 0.2, 0.1), (1.0, 0.33, 0.45),
                                   (0.3, 0.05, 0.0)])
def test_filter_form_matches_literal_equations(gains):
    d = Disturbance(noise=0.05, seed=3).sequence()
    np.testing.assert_allclose(error_response(gains, d), direct_model(gains, d), atol=1e-12)


def test_thesis_unstable_gains_have_pole_outside_unit_circle():
    stable, m = stability(1.0, 0.33, 0.45)
    assert not stable
    assert m == pytest.approx(1.05, abs=0.005)  # thesis 5.7: "a module of 1.05"
    assert not in_stable_volume(1.0, 0.33, 0.45)
    e = error_response((1.0, 0.33, 0.45), Disturbance(n_layers=300))
    assert np.abs(e[-50:]).max() > 1.0  # oscillation grows (Fig. 5-15)


def test_thesis_optimal_gains_are_stable():
    stable, m = stability(1.0, 0.33, 0.03)
    assert stable and m < 1.0
    assert in_stable_volume(1.0, 0.33, 0.03)
    e = error_response((1.0, 0.33, 0.03), Disturbance(n_layers=200))
    assert abs(e[-1]) < 1e-6  # step disturbance fully rejected (integral action)


def test_deadbeat_triple_pole_at_zero():
    # thesis 5.5: Kp = 1, Ki* = 1, Kd* = 0 produce a triple pole at z = 0
    np.testing.assert_allclose(poles(1.0, 1.0, 0.0), 0.0, atol=1e-12)
    num, den = transfer_function(1.0, 1.0, 0.0)
    np.testing.assert_allclose(den, [1, 0, 0, 0])


def test_pole_on_minus_one_plane():
    # eq. 5.24: Kp/2 + Ki*/4 + Kd* = 1 is a pole at z = -1
    kp, ki = 1.2, 0.4
    kd = 1 - kp / 2 - ki / 4
    p = poles(kp, ki, kd)
    assert np.min(np.abs(p + 1.0)) < 1e-9


@given(st.floats(0.01, 1.99), st.floats(0.01, 3.9), st.floats(0.0, 0.99))
def test_stable_volume_poles_inside_unit_circle_for_small_kd(kp, ki, kd):
    # Inside the planar volume the poles are inside the circle (thesis Fig. 5-12) where
    # the Jury condition |a3^2 - 1| > |a3 a1 - a2| also holds (checked independently).
    if not in_stable_volume(kp, ki, kd):
        return
    a1, a2, a3 = kp + ki + kd - 2, 1 - kp - 2 * kd, kd
    jury = abs(a3 ** 2 - 1) > abs(a3 * a1 - a2)
    stable, m = stability(kp, ki, kd)
    assert stable == jury
    if kd < 0.25:
        assert stable


def test_transfer_function_matches_dlti_impulse():
    from scipy import signal
    g = (1.0, 0.33, 0.03)
    num, den = transfer_function(*g)
    sys = signal.dlti(num, den, dt=1)
    _, (h,) = signal.dimpulse(sys, n=30)
    d = np.zeros(30)
    d[0] = 1.0
    # the filter form starts at e_1, one step after d_1; dlti puts d at index 0
    e = error_response(g, d)
    np.testing.assert_allclose(h[1:30, 0], e[1:30], atol=1e-12)


def test_disturbance_sequence():
    d = Disturbance(n_layers=100).sequence()
    assert d[28] == 0 and d[29] == pytest.approx(0.2)
    assert d[59] == pytest.approx(0.7) and d[60] == pytest.approx(0.2)
    n = Disturbance(pulses=(), steps=(), noise=0.05, noise_from=50, seed=1).sequence()
    assert np.all(n[:49] == 0) and np.all(np.abs(n[49:]) <= 0.025) and np.any(n[49:])
    with pytest.raises(ConfigError, match="layer"):
        Disturbance(n_layers=10, pulses=((0.5, 60),))


@pytest.mark.parametrize("gains", [(1.0, 0.33, 0.03), (0.7, 0.5, 0.1), (1.2, 0.1, 0.2)])
def test_gradient_matches_finite_differences(gains):
    d = Disturbance(noise=0.05, seed=2)
    r, g = rms_and_gradient(gains, d)
    h = 1e-6
    fd = []
    for j in range(3):
        gp = list(gains)
        gm = list(gains)
        gp[j] += h
        gm[j] -= h
        fd.append((rms_and_gradient(tuple(gp), d)[0] - rms_and_gradient(tuple(gm), d)[0])
                  / (2 * h))
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-9)
    assert r == pytest.approx(np.sqrt(np.mean(error_response(gains, d) ** 2)))


@pytest.mark.parametrize("constrained", [True, False])
@pytest.mark.parametrize("x0", [(1.0, 1.0, 0.0), (0.0, 0.0, 0.5)])
def test_table_5_2_optimum(constrained, x0):
    # thesis Table 5-2: k_opt = (1, 0.33, 0), sigma_p* = 0.061 from both k_0
    r = tune_gains(Disturbance(), x0=x0, constrained=constrained)
    assert r.kp == pytest.approx(1.0, abs=2e-3)
    assert r.ki == pytest.approx(0.33, abs=5e-3)
    assert abs(r.kd) < 2e-3
    assert r.rms == pytest.approx(0.061, abs=5e-4)
    assert r.stable


def test_ki_grows_with_step():
    # thesis 5.6: with d_s = 0.5, Ki* = 0.618 (Kp unchanged)
    r = tune_gains(Disturbance(steps=((0.5, 30),)))
    assert r.kp == pytest.approx(1.0, abs=2e-3)
    assert r.ki == pytest.approx(0.618, abs=2e-3)


@pytest.mark.parametrize("dp,kd_opt,rms", [(0.5, 0.0, 0.061), (0.25, 0.023, 0.038),
                                           (0.0, 0.126, 0.027), (-0.5, 0.0, 0.061)])
@pytest.mark.parametrize("kd0", [0.0, 0.2])
def test_table_5_3_kd_optimum(dp, kd_opt, rms, kd0):
    r = tune_gains(Disturbance(pulses=((dp, 60),)), x0=(1.0, 0.33, kd0),
                   fix={"kp": 1.0, "ki": 0.33})
    assert (r.kp, r.ki) == (1.0, 0.33)
    assert r.kd == pytest.approx(kd_opt, abs=1.5e-3)
    assert r.rms == pytest.approx(rms, abs=5e-4)


def test_constrained_stays_in_volume_and_fixed_outside_fails():
    r = tune_gains(Disturbance(steps=((2.0, 30),)), x0=(1.5, 1.5, 0.3))
    assert r.kp / 2 + r.ki / 4 + r.kd < 1.0
    with pytest.raises(ConfigError, match="stable"):
        tune_gains(fix={"kp": 2.5})
    with pytest.raises(ConfigError, match="unknown gain"):
        tune_gains(fix={"kx": 1.0})


def test_simulate_1d_table_5_4():
    # Fig. 5-14(a)/(b): optimal gains reject pulse+step; noise of 0.05 stays small
    s = simulate_1d((1.0, 0.33, 0.03), Disturbance(), n_d=4)
    assert s.rms < 0.07 and abs(s.e[-1]) < 1e-3
    assert s.nu.mean() == pytest.approx(37.5 * (1 + s.u.mean()))
    sn = simulate_1d((1.0, 0.33, 0.03), Disturbance(noise=0.05, noise_from=50, seed=0))
    assert sn.rms < 0.08
    big = simulate_1d((1.0, 0.33, 0.03), Disturbance(pulses=((-2.0, 60),), steps=()))
    assert abs(big.e[-1]) < 1e-3  # Fig. 5-14(c): recovers from a -2 pulse
    ev = evaluate_gains((1.0, 0.33, 0.45), Disturbance())
    assert not ev.stable and ev.max_pole > 1.0


@pytest.mark.parametrize("pulses,steps", [
    (((0.5, 60),), ((0.2, 30),)),   # Table 5-4 (a)
    (((-2.0, 60),), ()),            # Table 5-4 (c)
    ((), ((-2.0, 30),)),            # Table 5-4 (d)
])
def test_table_5_4_optimal_gains_recover(pulses, steps):
    s = simulate_1d((1.0, 0.33, 0.03), Disturbance(n_layers=100, pulses=pulses, steps=steps))
    assert np.abs(s.e[-10:]).max() < 1e-3
    worst = sum(abs(a) for a, _ in pulses) + sum(abs(a) for a, _ in steps)
    assert np.abs(s.e).max() <= worst + 1e-9  # no overshoot beyond the disturbance


@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_table_5_5_unstable_gains_oscillate(noise):
    d = Disturbance(n_layers=100, pulses=((0.5, 60),) if noise == 0 else (),
                    steps=((0.2, 30),) if noise == 0 else (), noise=noise, noise_from=50)
    s = simulate_1d((1.0, 0.33, 0.45), d)
    e = s.e
    first = np.flatnonzero(np.abs(e) > 1e-12)[0]
    late = np.abs(e[-10:]).max()
    early = np.abs(e[first:first + 10]).max()
    assert late > 1.5 * early  # growing oscillation (|pole| = 1.05)
    assert np.count_nonzero(np.diff(np.sign(e[-20:]))) >= 15  # sign flips: pole near -1


def test_stable_volume_edges():
    assert in_stable_volume(1.0, 0.33, 0.0)
    assert not in_stable_volume(1.0, 0.0, 0.1) and not in_stable_volume(0.0, 0.3, 0.0)
    assert stability(1.0, 0.0, 0.1)[1] == pytest.approx(1.0)  # pole on z = 1


@pytest.mark.parametrize("gains,kind", [((1.0, 0.33, 0.03), None),      # the defaults
                                        ((1.0, 0.33, 0.45), "grows"),   # Fig. 5-12
                                        ((1.0, 0.0, 0.0), "stays"),     # no integral
                                        ((0.0, 0.0, 0.0), "grows")])    # no control
def test_a_jobs_gains_verdict(gains, kind):
    from icefab import Job
    from icefab.feedback import gains_verdict

    job = Job().replace(**dict(zip(("feedback.kp", "feedback.ki", "feedback.kd"), gains)))
    got = gains_verdict(job)
    assert (got[0] if got else None) == kind
    assert gains_verdict(job.replace(**{"feedback.enabled": False})) is None
