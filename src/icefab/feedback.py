"""Surface mapping feedback (SMF): measured surface -> spatial PID -> control action.

Thesis Ch. 5. Two halves:

* **The spatial controller** (thesis 5.1-5.2). Laser samples ``(x, y, z)`` taken along
  the measurement paths of a measurement layer become a surface on a regular grid over the
  layer's footprint (:func:`surface_from_samples`, Delaunay-linear like Matlab's
  TriScatteredInterp), then an error matrix normalised by the measurement interval
  (:func:`error_surface`). :func:`smf_update` runs one step of the 3D spatial PID of
  eq. 5.1 with normalised gains (eq. 5.2) on grids whose extent changes between
  measurement layers, with saturation of the output U and of the integral (anti-windup,
  thesis 5.2.2). The control action is applied along the paths of the next n_d layers
  either to the valve flow (nu-controller: flow x (1 + u), see :func:`icefab.flow.plan_valves`)
  or to the speed (c-controller, eq. 5.7-5.10: :func:`retime_trajectory`).

* **The 1D analysis** (thesis 5.4-5.7). The one-pixel model of eqs. 5.11-5.19, its
  transfer function and poles (eq. 5.22), the gain-stable volume (eq. 5.25), simulation
  of the error response to pulse/step/random disturbances (eqs. 5.29-5.32) and the
  optimisation of the gains minimising the RMS error sigma_p* (eq. 5.27) with the analytic
  gradient (eqs. 5.34-5.35, 5.40).

Public functions: :func:`surface_from_samples`, :func:`error_surface`, :func:`smf_update`
(state :class:`SmfState`, result :class:`ControlAction`), :func:`smf_step` (the three in
one), :func:`measured_update` (from laser samples, with :func:`restrict_to_footprint`, or
:func:`held_action` where no surface forms), :func:`action_along` / :func:`action_sampler`,
:func:`retime_trajectory`,
:func:`regrid`, :func:`region_mask`; analysis: :func:`poles`, :func:`stability`,
:func:`in_stable_volume`, :func:`repeated_unit_pole`, :func:`transfer_function`,
:func:`error_response`, :func:`simulate_1d`, :func:`rms_and_gradient`, :func:`tune_gains`,
:func:`evaluate_gains` with :class:`Disturbance` and :class:`TuneResult`. Applying an
action to the next layers' valve programs: :func:`icefab.flow.replan_valves`.

Sign convention (thesis 5.4): the error is ``e = nominal - measured`` normalised by the
measurement interval dh_m, so a positive error means the part is too LOW and a positive
control action ``u`` asks for MORE material (flow x (1 + u), or speed / (1 + u)).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from icefab.config import Job
from icefab.errors import ConfigError, GeometryError
from icefab.core import HeightMap, Region, Trajectory, arc_lengths
from icefab.workload import check_grid

log = logging.getLogger(__name__)

Gains = tuple[float, float, float]


# =========================================================================== 1D analysis


def characteristic_polynomial(kp: float, ki: float, kd: float) -> np.ndarray:
    """(4,) float64 denominator of H(z) (eq. 5.22), highest power of z first.

    z^3 + (Kp + Ki* + Kd* - 2) z^2 + (1 - Kp - 2 Kd*) z + Kd*; gains are the normalised
    gains Kp, Ki* = Ki dh_m, Kd* = Kd / dh_m (eq. 5.2). ConfigError for a gain that is
    not a finite number.
    """
    _check_gains((kp, ki, kd))
    with np.errstate(over="ignore", invalid="ignore"):
        a = np.array([1.0, kp + ki + kd - 2.0, 1.0 - kp - 2.0 * kd, kd], dtype=np.float64)
    if not np.all(np.isfinite(a)):
        # 1e308 + 1e308: numpy's LinAlgError from the roots (a tester's --gains)
        raise ConfigError(f"gains ({kp:.4g}, {ki:.4g}, {kd:.4g}): too large for the model's "
                          "polynomial (eq. 5.22) to be computed")
    return a


def _check_gains(gains: Sequence[float], what: str = "gain") -> None:
    try:
        values = [float(g) for g in gains]
    except (TypeError, ValueError):
        raise ConfigError(f"{what}s {gains!r}: expected three numbers (Kp, Ki*, Kd*)") from None
    if len(values) != 3:
        raise ConfigError(f"{what}s {tuple(gains)!r}: expected three numbers (Kp, Ki*, Kd*)")
    for name, g in zip(("kp", "ki", "kd"), values):
        if not np.isfinite(g):
            raise ConfigError(f"{what} {name} = {g!r}: must be finite")


def transfer_function(kp: float, ki: float, kd: float) -> tuple[np.ndarray, np.ndarray]:
    """Numerator and denominator of H(z) = E(z)/D(z) (eq. 5.22), powers of z descending.

    H(z) = (z - z^2) / (z^3 + (Kp + Ki* + Kd* - 2) z^2 + (1 - Kp - 2 Kd*) z + Kd*).
    Returns ``(num (3,), den (4,))`` usable with ``scipy.signal.dlti(num, den, dt=1)``.
    """
    return np.array([-1.0, 1.0, 0.0]), characteristic_polynomial(kp, ki, kd)


def poles(kp: float, ki: float, kd: float) -> np.ndarray:
    """(3,) complex128 poles of H(z) (eq. 5.22): the roots of its denominator."""
    return np.roots(characteristic_polynomial(kp, ki, kd)).astype(np.complex128)


def stability(kp: float, ki: float, kd: float) -> tuple[bool, float]:
    """Jury criterion (eq. 5.23): ``(stable, max_pole_modulus)``.

    stable is True when every pole lies strictly inside the unit circle, by more than
    :data:`UNIT_CIRCLE_TOL` (a pole on the circle, e.g. at z = -1 for Kp/2 + Ki*/4 + Kd* =
    1, came out at 0.9999999999999998 or 1.0000000000000007 by rounding, "stable" or not
    as it fell); the largest pole modulus tells how far from instability the gains are
    (thesis Fig. 5-12).
    """
    m = float(np.max(np.abs(poles(kp, ki, kd))))
    return bool(m < 1.0 - UNIT_CIRCLE_TOL), m


#: A pole within this of the unit circle is on it (neither decays): not stable.
UNIT_CIRCLE_TOL = 1e-9
#: Poles closer than this to each other at z = 1 or z = -1 are one repeated pole: the
#: response of such a pair grows like k for ~1 / 1e-5 layers, through any run the model
#: allows (:data:`MAX_LAYERS`); gains (1e-9, 0, 0), poles 1 and 1 - 1e-9, gave the open
#: loop's RMS 7.13 over 100 layers as (0, 0, 0) did.
REPEATED_POLE_TOL = 1e-5


def repeated_unit_pole(kp: float, ki: float, kd: float) -> float | None:
    """The repeated pole of H(z) on the unit circle, 1.0 or -1.0, or None when there is none.

    A repeated pole on the circle makes the error grow without bound (like k for a double
    pole: a step under the open loop, gains (0, 0, 0), has E(z) ~ 1 / (z - 1)^2), where a
    single one only never decays. A real cubic cannot have a repeated complex pair, so only
    z = 1 and z = -1 can carry one. The test is on the gains, not on ``numpy.roots``: a
    double root is computed only to ~sqrt(eps) = 1.5e-8 (gains (0, 0, 0.5) gave poles
    0.99999999 and 1.00000001), a triple one to ~eps^(1/3) = 6e-6. Near z0 = +-1 the
    denominator P (eq. 5.22) is P(z0) + P'(z0) (z - z0) + ..., so two of its roots lie
    within tol = :data:`REPEATED_POLE_TOL` of z0 when |P'(z0)| <= tol and |P(z0)| <= tol^2
    (times 1 + |Kp| + |Ki*| + |Kd*|): P(1) = Ki*, P'(1) = Kp + 2 Ki*,
    P(-1) = 2 Kp + Ki* + 4 Kd* - 4, P'(-1) = 8 - 3 Kp - 2 Ki* - 4 Kd*.
    """
    _check_gains((kp, ki, kd))
    tol = REPEATED_POLE_TOL * (1.0 + abs(kp) + abs(ki) + abs(kd))
    at_plus = (ki, kp + 2.0 * ki)
    at_minus = (2.0 * kp + ki + 4.0 * kd - 4.0, 8.0 - 3.0 * kp - 2.0 * ki - 4.0 * kd)
    for z0, (value, slope) in ((1.0, at_plus), (-1.0, at_minus)):
        if abs(value) <= tol * REPEATED_POLE_TOL and abs(slope) <= tol:
            return z0
    return None


def gains_verdict(job: "Job") -> tuple[str, str] | None:
    """What the job's SMF gains (``feedback.kp``, ``ki``, ``kd``) do to the loop, when
    they do not make it stable (thesis 5.5, eq. 5.22): ("grows", text) for a pole outside
    the unit circle or a repeated one on it (:func:`repeated_unit_pole`), the error
    growing from one measurement to the next; ("stays", text) for a single pole on it,
    the error never decaying; None for stable gains or feedback off.
    Only ``icefab tune`` checked gains: a job's unstable ones ran a build and a
    simulation without a word (a control review: the thesis' own unstable example,
    1 / 0.33 / 0.45, oscillated +-0.1 mm on the simulated cell)."""
    fb = job.feedback
    if not fb.enabled:
        return None
    stable, m = stability(fb.kp, fb.ki, fb.kd)
    if stable:
        return None
    gains = f"feedback.kp, ki, kd = {fb.kp:g}, {fb.ki:g}, {fb.kd:g}"
    if m > 1.0 + UNIT_CIRCLE_TOL:
        return "grows", (f"{gains} make the SMF loop unstable (largest pole modulus {m:.4f} "
                         "> 1, thesis 5.5): the height error grows from one measurement to "
                         "the next; 'icefab tune' gives stable gains")
    z0 = repeated_unit_pole(fb.kp, fb.ki, fb.kd)
    if z0 is not None:
        return "grows", (f"{gains} put a repeated pole of the SMF loop at z = {z0:g} "
                         "(thesis 5.5): the height error grows from one measurement to the "
                         "next, as with no control at all (feedback.enabled = false builds "
                         "open loop); 'icefab tune' gives stable gains")
    return "stays", (f"{gains} put a pole of the SMF loop on the unit circle (thesis 5.5): "
                     "the height error never decays; 'icefab tune' gives stable gains")


def in_stable_volume(kp: float, ki: float, kd: float) -> bool:
    """The gain-stable volume of eq. 5.25: Kp > 0, Ki* > 0, Kd* >= 0, Kp/2 + Ki*/4 + Kd* < 1.

    The thesis writes Kd* > 0; Kd* = 0 (its own optimum, Table 5-2) is accepted here since
    the poles stay inside the unit circle there. Ki* = 0 puts a pole on z = 1 and Kp = 0
    (with Kd* = 0) two poles on the circle, so those planes stay excluded. Use
    :func:`stability` for the exact answer (the planes approximate the Jury region).
    """
    return bool(kp > 0 and ki > 0 and kd >= 0 and kp / 2 + ki / 4 + kd < 1.0)


# Rows of g(k) <= 0 (eq. 5.38): the four planes of the gain-stable volume.
STABLE_VOLUME_A = np.array([[0.5, 0.25, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0],
                            [0.0, 0.0, -1.0]])
STABLE_VOLUME_B = np.array([-1.0, 0.0, 0.0, 0.0])

#: Stability margin of the constrained gain optimisation: every pole of H(z) at most
#: ``1 - POLE_MARGIN`` from the origin, so a disturbance's effect shrinks by at least 1 %
#: per measurement layer (e-fold within 100 layers, the thesis' design build). Eq. 5.25 is
#: strict (Ki* > 0, Kp/2 + Ki*/4 + Kd* < 1); without a margin the optimum of a profile
#: that needs no integral action (a lone pulse) slides to Ki* = 0, a pole on z = 1.
POLE_MARGIN = 0.01


def pole_margin_constraints(kp: float, ki: float, kd: float, radius: float
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Jury's criterion (eq. 5.23) for ``max |pole| <= radius`` as smooth inequalities.

    The poles of H(z) lie in the disc |z| <= r exactly when those of the scaled
    denominator P(r z) / r^3 = z^3 + b1 z^2 + b2 z + b3 (b_i = a_i / r^i) lie in the closed
    unit disc, i.e. when all of ``c = (Q(1), -Q(-1), 1 - b3, 1 + b3, 1 - b3^2 - (b3 b1 -
    b2), 1 - b3^2 + (b3 b1 - b2))`` are >= 0 (Q the scaled polynomial). Returns
    ``(c (6,), dc/d(Kp, Ki*, Kd*) (6, 3))``.
    """
    a = characteristic_polynomial(kp, ki, kd)[1:]
    scale = radius ** -np.arange(1.0, 4.0)
    b1, b2, b3 = a * scale
    db = _DA[:, 1:].T * scale[:, None]  # (3 coefficients, 3 gains)
    m = b3 * b1 - b2
    dm = b3 * db[0] + b1 * db[2] - db[1]
    c = np.array([1 + b1 + b2 + b3, 1 - b1 + b2 - b3, 1 - b3, 1 + b3,
                  1 - b3 * b3 - m, 1 - b3 * b3 + m])
    jac = np.vstack([db[0] + db[1] + db[2], -db[0] + db[1] - db[2], -db[2], db[2],
                     -2 * b3 * db[2] - dm, -2 * b3 * db[2] + dm])
    return c, jac


#: Least Kp and Ki* of a constrained search (eq. 5.25: Kp > 0, Ki* > 0; with Ki* fixed at
#: 3.9 the search returned Kp = 0, outside the volume it promised to keep to).
MIN_GAIN = 1e-6
#: Most measurement layers the 1D model is simulated or tuned over: 100 000 (a 25 m part
#: of 0.25 mm layers measured at every layer) take ~3 s to tune; a billion asked for
#: 7.5 GiB and ended in numpy's MemoryError (a hunt's).
MAX_LAYERS = 100_000


@dataclass(frozen=True)
class Disturbance:
    """A disturbance profile d_k for the 1D model (eqs. 5.29-5.32), normalised by dh_m.

    n_layers: number of measurement layers k = 1..n_layers.
    pulses: ``(amplitude, layer)`` pairs: d_k += amplitude at k = layer (eq. 5.30).
    steps: ``(amplitude, layer)`` pairs: d_k += amplitude for k >= layer (eq. 5.31).
    noise: amplitude d_r of the random part d_r (RN - 0.5), RN uniform in [0, 1) (eq. 5.32).
    noise_from: first layer with noise (the thesis' k_r, Table 5-4).
    seed: random seed of the noise (the profile is deterministic for a given seed).

    The default is the thesis' design disturbance (thesis 5.6): a pulse of 0.5 at layer 60
    and a step of 0.2 at layer 30 over 100 layers, for which the thesis finds
    k_opt = (1, 0.33, 0) and sigma_p* = 0.061 (Table 5-2).
    """

    n_layers: int = 100
    pulses: tuple[tuple[float, int], ...] = ((0.5, 60),)
    steps: tuple[tuple[float, int], ...] = ((0.2, 30),)
    noise: float = 0.0
    noise_from: int = 1
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.n_layers, (int, np.integer)) or not (
                1 <= self.n_layers <= MAX_LAYERS):
            raise ConfigError(f"disturbance n_layers = {self.n_layers!r}: must be an "
                              f"integer in 1..{MAX_LAYERS} (measurement layers)")
        for name in ("pulses", "steps"):
            for amp, layer in getattr(self, name):
                if not np.isfinite(amp):
                    raise ConfigError(f"disturbance {name[:-1]} amplitude = {amp!r}: must be "
                                      "finite")
                if (not isinstance(layer, (int, np.integer, float, np.floating))
                        or layer != int(layer) or not 1 <= int(layer) <= self.n_layers):
                    raise ConfigError(f"disturbance {name[:-1]} layer = {layer!r}: must be a "
                                      f"whole number in 1..{self.n_layers} (n_layers)")
        if not np.isfinite(self.noise) or self.noise < 0:
            raise ConfigError(f"disturbance noise = {self.noise!r}: must be a finite "
                              "number >= 0")
        if (not isinstance(self.noise_from, (int, np.integer))
                or not 1 <= self.noise_from <= self.n_layers):
            raise ConfigError(f"disturbance noise_from = {self.noise_from!r}: must be a whole "
                              f"number in 1..{self.n_layers} (n_layers)")

    def sequence(self) -> np.ndarray:
        """(n_layers,) float64: d_1 .. d_n (eq. 5.29)."""
        k = np.arange(1, self.n_layers + 1)
        d = np.zeros(self.n_layers)
        with np.errstate(over="ignore"):   # checked below, in one line
            for amp, layer in self.pulses:
                d[k == int(layer)] += amp
            for amp, layer in self.steps:
                d[k >= int(layer)] += amp
            if self.noise:
                rng = np.random.default_rng(self.seed)
                rn = rng.random(self.n_layers)
                d += np.where(k >= self.noise_from, self.noise * (rn - 0.5), 0.0)
        if not np.all(np.isfinite(d)):
            # 1e308 pulse and step at once: numpy's overflow warnings, then an error
            # naming no option (a hunt's)
            raise ConfigError(f"disturbance: the pulses, steps and noise add up to more "
                              f"than a float holds at layer {int(k[~np.isfinite(d)][0])}: "
                              "give smaller amplitudes")
        return d


def _as_d(disturbance: Disturbance | np.ndarray | Sequence[float]) -> np.ndarray:
    if isinstance(disturbance, Disturbance):
        return disturbance.sequence()
    d = np.asarray(disturbance, dtype=np.float64)
    if d.ndim != 1 or not 1 <= len(d) <= MAX_LAYERS or not np.all(np.isfinite(d)):
        raise ConfigError(f"disturbance: expected a finite (n_layers,) sequence, n_layers in "
                          f"1..{MAX_LAYERS}")
    return d


def error_response(gains: Gains, disturbance: Disturbance | np.ndarray) -> np.ndarray:
    """(n,) float64 normalised errors e_1..e_n of the 1D model for disturbances d_1..d_n.

    Solves the difference equation 5.19 (equivalently eqs. 5.11 with e_1 = 0 and the
    derivative term left out at k = 1) with ``scipy.signal.lfilter``:
    e_{k+1} + a1 e_k + a2 e_{k-1} + a3 e_{k-2} = d_{k-1} - d_k.
    """
    from scipy.signal import lfilter  # 1.4 s to import: only where used
    d = _as_d(disturbance)
    a = characteristic_polynomial(*gains)
    x = np.concatenate([[0.0], d])
    return lfilter([0.0, -1.0, 1.0], a, x)[1:len(d) + 1]


@dataclass(frozen=True, eq=False)
class Sim1D:
    """A 1D SMF simulation (thesis 5.7, Fig. 5-14); arrays are (n_layers,) float64.

    d: disturbance d_k; e: error e_k; u: controller output u_k (eq. 5.11a); nu: valve
    frequency nu_k = C_f (u_k + 1), Hz (eq. 5.11b, 5.14); height_mm: measured height
    h_k - e_k dh_m at measurement layer k; dh_m: measurement interval, mm; rms: sigma_p*
    (inf when the response of unstable gains overflows).
    """

    d: np.ndarray
    e: np.ndarray
    u: np.ndarray
    nu: np.ndarray
    height_mm: np.ndarray
    dh_m: float
    rms: float


def simulate_1d(gains: Gains, disturbance: Disturbance | np.ndarray,
                n_layers: int | None = None, n_d: int = 4, *, dh_d: float = 0.25,
                c_ff: float = 4.0, speed: float = 25.0, width: float = 1.5) -> Sim1D:
    """Simulate the 1D nu-controller (eqs. 5.11) for the given disturbance.

    gains: normalised (Kp, Ki*, Kd*).
    disturbance: a Disturbance or (n,) d_k array (normalised by dh_m).
    n_layers: if given, the disturbance sequence is cut or zero-padded to this length.
    n_d: deposition layers per measurement layer, so dh_m = n_d * dh_d (mm).
    c_ff, speed, width, dh_d: C_f = c_ff * c * w * dh_d (eq. 5.14), defaults of thesis 5.7
        (4 Hz/(mm^3/s), 25 mm/s, 1.5 mm, 0.25 mm).
    """
    d = _as_d(disturbance)
    if n_layers is not None:
        if n_layers < 1:
            raise ConfigError(f"n_layers = {n_layers}: must be >= 1")
        d = np.concatenate([d, np.zeros(max(0, n_layers - len(d)))])[:n_layers]
    _check_gains(gains)
    if not isinstance(n_d, (int, np.integer)) or n_d < 1:
        raise ConfigError(f"n_d = {n_d!r}: must be a whole number >= 1 (layers per "
                          "measurement layer)")
    for name, v in (("dh_d", dh_d), ("c_ff", c_ff), ("speed", speed), ("width", width)):
        if not (np.isfinite(v) and v > 0):
            raise ConfigError(f"simulate_1d {name} = {v!r}: must be a finite number > 0")
    kp, ki, kd = (float(g) for g in gains)
    e = error_response(gains, d)
    c_f = c_ff * speed * width * dh_d
    dh_m = n_d * dh_d
    k = np.arange(1, len(d) + 1)
    with np.errstate(over="ignore", invalid="ignore"):  # unstable gains: e may overflow
        e_prev = np.concatenate([[0.0], e[:-1]])
        u = kp * e + ki * np.cumsum(e) + kd * (e - e_prev)
        return Sim1D(d=d, e=e, u=u, nu=c_f * (u + 1.0), height_mm=(k - e) * dh_m, dh_m=dh_m,
                     rms=_rms(e))


def _rms(e: np.ndarray) -> float:
    """sigma_p* = sqrt(mean(e^2)) (eq. 5.27); inf when the response of unstable gains
    overflows."""
    with np.errstate(over="ignore", invalid="ignore"):
        rms = float(np.sqrt(np.mean(e ** 2)))
    return rms if np.isfinite(rms) else float("inf")


# d a / d (Kp, Ki*, Kd*): derivative of the denominator coefficients (eq. 5.35, 5.40).
_DA = np.array([[0.0, 1.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 1.0, -2.0, 1.0]])


def rms_and_gradient(gains: Gains, disturbance: Disturbance | np.ndarray
                     ) -> tuple[float, np.ndarray]:
    """sigma_p* (eq. 5.27) and its analytic gradient w.r.t. (Kp, Ki*, Kd*) (eq. 5.34).

    The sensitivities grad e_k follow from differentiating eq. 5.19 (eq. 5.35):
    A(q) grad e = -(dA) e, solved with the same recursive filter as e.
    Returns ``(rms, grad (3,) float64)``; ``(inf, nan)`` when the response overflows
    (unstable gains over many layers).
    """
    from scipy.signal import lfilter  # 1.4 s to import: only where used
    d = _as_d(disturbance)
    a = characteristic_polynomial(*gains)
    x = np.concatenate([[0.0], d])
    e_full = lfilter([0.0, -1.0, 1.0], a, x)  # index 0 is e_0 = 0
    e = e_full[1:len(d) + 1]
    n = len(d)
    rms = _rms(e)
    if rms == 0.0:
        return 0.0, np.zeros(3)
    if not np.isfinite(rms):
        return rms, np.full(3, np.nan)
    with np.errstate(over="ignore", invalid="ignore"):
        grad = np.empty(3)
        for j in range(3):
            rhs = -lfilter(_DA[j], [1.0], e_full)
            de = lfilter([1.0], a, rhs)[1:n + 1]
            grad[j] = float(np.dot(e, de)) / (rms * n)
    return rms, grad


@dataclass(frozen=True, eq=False)
class TuneResult:
    """Optimal gains for a disturbance (thesis 5.6, Tables 5-2/5-3).

    kp, ki, kd: normalised gains Kp, Ki*, Kd*. rms: sigma_p* at the optimum (eq. 5.27).
    max_pole: largest pole modulus (eq. 5.22); stable: max_pole < 1.
    iterations: optimiser iterations; converged: the optimiser's success flag, or a stop
    accepted after a check (converged_by_check True: SLSQP found no descent at a feasible
    point that neither a restart nor probes around it could better, :func:`tune_gains`);
    message: the optimiser's message (and the check's); e: (n,) error response at the
    optimum. optimised: False for given gains (:func:`evaluate_gains`), which no
    optimiser ran for: their ``converged`` means nothing (None in :meth:`as_dict`).
    """

    kp: float
    ki: float
    kd: float
    rms: float
    max_pole: float
    stable: bool
    iterations: int = 0
    converged: bool = True
    message: str = ""
    converged_by_check: bool = False
    e: np.ndarray = field(default_factory=lambda: np.zeros(0))
    optimised: bool = True

    @property
    def diverges(self) -> bool:
        """True when the error response grows without bound: a pole outside the unit
        circle (``max_pole > 1``; the error then grows like ``max_pole ** k``, so an RMS
        over any finite number of layers only says how long the run was), a repeated pole
        on it (:func:`repeated_unit_pole`: the error grows like k; the open loop's RMS was
        7.1 over 100 layers, 110 over 1000) or an RMS that overflowed."""
        return (not np.isfinite(self.rms) or self.max_pole > 1.0 + UNIT_CIRCLE_TOL
                or self.repeated_pole is not None)

    @property
    def repeated_pole(self) -> float | None:
        """The repeated pole on the unit circle (1.0 or -1.0), None when there is none."""
        return repeated_unit_pole(self.kp, self.ki, self.kd)

    def as_dict(self) -> dict[str, float | bool | None]:
        """Plain values for JSON: ``rms`` is None when the response diverges
        (:attr:`diverges`), so ``json.dumps(..., allow_nan=False)`` gives valid JSON and a
        diverging response never shows a finite-looking RMS; ``optimised``: whether an
        optimiser found the gains (false for given gains); ``converged``: whether it
        succeeded, ``converged_by_check``: whether only icefab's check of where it stopped
        says so, both None for given gains (they were ``true``/``false``, as if an
        optimiser had run: a review's)."""
        ran = self.optimised
        return {"kp": self.kp, "ki": self.ki, "kd": self.kd,
                "rms": None if self.diverges else float(self.rms),
                "max_pole": self.max_pole, "stable": self.stable, "optimised": ran,
                "converged": bool(self.converged) if ran else None,
                "converged_by_check": bool(self.converged_by_check) if ran else None}


def evaluate_gains(gains: Gains, disturbance: Disturbance | np.ndarray) -> TuneResult:
    """RMS error, stability and the error response of given gains (no optimisation:
    ``optimised`` False)."""
    _check_gains(gains)
    kp, ki, kd = (float(g) for g in gains)
    stable, m = stability(kp, ki, kd)
    d = _as_d(disturbance)
    # linear in d: the response to d scaled to a largest |d_k| of 1, scaled back (a pulse
    # of 1e200 overflowed in e^2 and stable gains were said to diverge)
    size = float(np.max(np.abs(d))) if len(d) else 0.0
    e = error_response((kp, ki, kd), d / size if size > 0 else d)
    with np.errstate(over="ignore", invalid="ignore"):
        rms = _rms(e) * size if size > 0 else 0.0
        e = e * size if size > 0 else e
    return TuneResult(kp, ki, kd, rms if np.isfinite(rms) else float("inf"), m, stable, e=e,
                      optimised=False)


_NAMES = ("kp", "ki", "kd")


def _starts(disturbance: Disturbance | np.ndarray | Sequence[float],
            d: np.ndarray) -> list[tuple[str, int]]:
    """The disturbance's parts as ``(what, first layer)``: each pulse and step of a
    :class:`Disturbance` with an amplitude, and its noise from ``noise_from``; for a
    sequence d_k, which has no parts, the first layer where it is not 0."""
    if isinstance(disturbance, Disturbance):
        parts = [(f"{name} {amp:g}@{int(layer)}", int(layer))
                 for name, given in (("pulse", disturbance.pulses),
                                     ("step", disturbance.steps))
                 for amp, layer in given if amp != 0.0]
        if disturbance.noise:
            parts.append(("noise", int(disturbance.noise_from)))
        if parts:
            return parts
    started = np.flatnonzero(d)
    return [("disturbance", int(started[0]) + 1 if len(started) else len(d) + 1)]


def _check_horizon(starts: list[tuple[str, int]], n_layers: int, n_free: int) -> None:
    """ConfigError unless every part of the disturbance starts at least ``n_free + 1``
    layers before the end, so that the error fixes the free gains and every part counts.

    starts: ``(what, first layer)`` of each part (:func:`_starts`), layers 1..n_layers.

    By eq. 5.19 the first error after a part starts at layer k0 is the part's own whatever
    the gains (H(z) has relative degree 1), and each later layer's brings in one more
    coefficient of the denominator: e_(k0+2) depends on a1 only, e_(k0+3) on a1 and a2,
    e_(k0+4) on all three. With fewer layers than the free gains plus one, a line or plane
    of gains is equally optimal (a pulse at layer 98 of 100: every Kp + Ki* + Kd* = 1; at
    97: a line) and the start gains came back "optimised"; from n_free + 1 layers on,
    multi-start searches agree on one optimum (a control review). Every part is checked,
    not only the first: a pulse on the last layer, after a step, changed nothing in the
    optimum (a docs hunt's: the thesis' pulse 0.5@60 with 60 layers).
    """
    what, k0 = max(starts, key=lambda s: s[1])
    after = n_layers - k0
    if after < n_free + 1:
        raise ConfigError(f"the {what} starts at layer {k0} of {n_layers}, {after} "
                          f"layer{'s' * (after != 1)} after it: optimising {n_free} "
                          f"gain{'s' * (n_free != 1)} needs {n_free + 1} layers after the "
                          "start of every disturbance (eq. 5.19: the first error is the "
                          "disturbance's whatever the gains, each later one brings in one "
                          "more); give more layers or an earlier disturbance")


def tune_gains(disturbance: Disturbance | np.ndarray = Disturbance(), *,
               x0: Gains = (1.0, 1.0, 0.0), fix: dict[str, float] | None = None,
               constrained: bool = True, tol: float = 1e-12,
               pole_margin: float | None = None) -> TuneResult:
    """Gains minimising sigma_p* (eq. 5.27) for a disturbance (thesis 5.6).

    disturbance: Disturbance or (n,) d_k (normalised); the default is the thesis'
        design disturbance, whose optimum is (1, 0.33, 0) with sigma_p* = 0.061.
    x0: initial (Kp, Ki*, Kd*) (the thesis' k_0 = (1, 1, 0), Table 5-2).
    fix: gains held constant, e.g. ``{"kp": 1.0, "ki": 0.33}`` optimises Kd* only
        (eq. 5.39-5.40); the others start from x0.
    constrained: search inside the gain-stable volume (eq. 5.25, 5.38) with SLSQP, kept
        ``pole_margin`` inside the unit circle: every pole of the result has modulus
        <= 1 - pole_margin (Jury's criterion on the scaled polynomial,
        :func:`pole_margin_constraints`; to 1e-6, as a double pole's modulus is computed to
        about the square root of the rounding), so the result is strictly stable, with
        Kp and Ki* at least ``MIN_GAIN`` (eq. 5.25's volume is open there); otherwise
        unconstrained BFGS (the thesis' FMINCON / FMINUNC), which may return unstable
        gains (``stable`` False). Both use the analytic gradient (eq. 5.34-5.35). The
        constrained search starts from x0 and from a few points spread over the volume
        (:func:`_spread_starts`; a held Kd* of 0.9 stopped in a local optimum 28 % worse)
        and keeps x0's result unless another is lower by :data:`RMS_RTOL`; SLSQP stopping
        with no descent counts as converged when a check finds nothing better near the
        point (``converged_by_check``; a margin of 0.99 stopped so at the optimum).
    pole_margin: in (0, 1), default :data:`POLE_MARGIN` (0.01); only for the constrained
        search: BFGS has no constraints to hold it, so giving one with
        ``constrained=False`` is a ConfigError (it was ignored: a margin of 0.5 returned a
        largest pole of 0.672).

    Raises ConfigError when the fixed gains leave no stable choice of the others.
    """
    from scipy.optimize import minimize

    if pole_margin is not None and not constrained:
        raise ConfigError(f"pole_margin = {pole_margin!r}: only the constrained search keeps "
                          "the poles within a margin; the unconstrained one has no constraints")
    if pole_margin is None:
        pole_margin = POLE_MARGIN
    d = _as_d(disturbance)
    # the model is linear in d: the optimum does not depend on its size, but the solvers'
    # tolerances are absolute, so they run on d scaled to a largest |d_k| of 1 (a noise of
    # 1e6 returned the initial gains, a pulse of 1e6 a false "no stable gains")
    size = float(np.max(np.abs(d))) if len(d) else 0.0
    if not size > 0.0:
        raise ConfigError("the disturbance is 0 at every layer: every gain gives no error, "
                          "so there is nothing to optimise (give a pulse, step or noise)")
    d_unit = d / size
    fix = dict(fix or {})
    for k, v in fix.items():
        if k not in _NAMES:
            raise ConfigError(f"fix: unknown gain {k!r}: expected one of kp, ki, kd")
        if not (isinstance(v, (int, float, np.number)) and np.isfinite(v)):
            # it was named as an initial gain ("initial gains (1.0, ...): must be finite")
            raise ConfigError(f"fix: {k} = {v!r}: a fixed gain must be a finite number")
    if constrained and (fix.get("kp", 1.0) <= 0.0 or fix.get("ki", 1.0) <= 0.0
                        or fix.get("kd", 0.0) < 0.0):
        # eq. 5.25's volume: Kp > 0, Ki* > 0, Kd* >= 0 (Kp = 0 was "optimised" outside it)
        raise ConfigError(f"fixed gains {fix}: outside the gain-stable volume (eq. 5.25: "
                          "Kp > 0, Ki* > 0, Kd* >= 0)")
    _check_gains(x0, "initial gain")
    base = np.array([fix.get(n, x0[i]) for i, n in enumerate(_NAMES)], dtype=np.float64)
    if not np.all(np.isfinite(base)):
        raise ConfigError(f"initial gains {tuple(base)}: must be finite")
    free = [i for i, n in enumerate(_NAMES) if n not in fix]
    if not free:
        return evaluate_gains(tuple(base), d)  # type: ignore[arg-type]
    _check_horizon(_starts(disturbance, d), len(d), len(free))

    def full(x: np.ndarray) -> np.ndarray:
        g = base.copy()
        g[free] = x
        return g

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        r, g = rms_and_gradient(tuple(full(x)), d_unit)  # type: ignore[arg-type]
        return r, g[free]

    xs = base[free].copy()
    if constrained:
        problem = _constrained_problem(fun, full, free, base, fix, pole_margin, tol)
        starts = _spread_starts(problem.inside_start(xs), problem)
        res, note = _best_of_starts(problem, starts)
        g = full(res.x)
        worst = float(np.max(np.abs(poles(*g))))
        if not problem.feasible(res.x):
            held = ", ".join(f"{k} = {v:g}" for k, v in fix.items())
            raise ConfigError(f"{f'fixed gains ({held}): ' if fix else ''}no "
                              f"{', '.join(_NAMES[i] for i in free)} "
                              f"found keeping every pole within |z| <= {problem.radius:g} "
                              f"(largest pole modulus {worst:.4g}; pole margin "
                              f"{pole_margin:g}, eq. 5.23/5.25)")
    else:
        with np.errstate(over="ignore", invalid="ignore"):
            res = minimize(fun, xs, jac=True, method="BFGS", options={"gtol": 1e-10,
                                                                      "maxiter": 500})
        g, note = full(res.x), ""
    out = evaluate_gains(tuple(g), d)  # type: ignore[arg-type]
    return dataclasses.replace(out, iterations=int(res.nit), optimised=True,
                               converged=bool(res.success) or bool(note),
                               converged_by_check=bool(note),
                               message=f"{res.message}; {note}" if note else str(res.message))


#: SLSQP's exit mode "Positive directional derivative for linesearch": its line search
#: found no descent from the point, which may well be the optimum (a double pole on the
#: margin's circle, where Jury's constraints are degenerate: ``--pole-margin 0.99`` stopped
#: so at the optimum, RMS 0.072816 against 0.072823 for the best of 200 000 samples). Only
#: this stop is checked (:func:`_check_stop`); the iteration limit, incompatible constraints
#: or a singular subproblem say nothing of the point and stay failures.
SLSQP_NO_DESCENT = 8
#: A point is better than another when its RMS is lower by more than this, relative: the
#: multi-start keeps the earlier start's result otherwise, and a stop is accepted when no
#: point near it is better.
RMS_RTOL = 1e-6
#: SLSQP's ftol for the extra starts of the multi-start, which only tell the basin a start
#: falls in (the RMS is computed for a largest |d_k| of 1).
ROUGH_FTOL = 1e-4


@dataclass(frozen=True, eq=False)
class _Problem:
    """The constrained search over the free gains (eq. 5.38): ``fun(x) -> (rms, grad)``,
    ``full(x)`` the three gains, SLSQP's constraints and lower bounds, the plane's fixed
    part and free coefficients (Kp/2 + Ki*/4 + Kd* < 1), the pole radius, the tolerance."""

    fun: Callable[[np.ndarray], tuple[float, np.ndarray]]
    full: Callable[[np.ndarray], np.ndarray]
    cons: list
    lower: np.ndarray
    fixed: float
    a_free: np.ndarray
    radius: float
    tol: float

    def run(self, x0: np.ndarray, rough: bool = False):
        """One SLSQP search from ``x0`` (scipy's OptimizeResult); ``rough``: to
        :data:`ROUGH_FTOL` only, to see which basin a start falls in."""
        from scipy.optimize import minimize

        ftol, maxiter = (ROUGH_FTOL, 100) if rough else (self.tol, 500)
        with np.errstate(over="ignore", invalid="ignore"):  # trial steps may diverge
            return minimize(self.fun, x0, jac=True, method="SLSQP", constraints=self.cons,
                            bounds=[(lo, None) for lo in self.lower],
                            options={"ftol": ftol, "maxiter": maxiter})

    def feasible(self, x: np.ndarray) -> bool:
        """Within the bounds and the plane, every pole within the radius to 1e-6 (a double
        pole's modulus is computed to about the square root of the rounding)."""
        x = np.asarray(x, dtype=np.float64)
        if not (np.all(np.isfinite(x)) and np.all(x >= self.lower)
                and self.fixed + self.a_free @ x < 1.0):
            return False
        return bool(np.max(np.abs(poles(*self.full(x)))) <= self.radius + 1e-6)

    def inside_start(self, x: np.ndarray) -> np.ndarray:
        """``x`` moved onto the bounds and halfway inside the plane when outside them."""
        x = np.maximum(x, self.lower)
        if self.fixed + self.a_free @ x >= 1.0:
            x = x * (1.0 - self.fixed) / (2 * max(self.a_free @ x, 1e-12))
        return x


def _constrained_problem(fun, full, free: list[int], base: np.ndarray, fix: dict,
                         pole_margin: float, tol: float) -> _Problem:
    """The constrained search's :class:`_Problem`; ConfigError for a margin outside (0, 1)
    or fixed gains outside eq. 5.25's plane.

    Eq. 5.38: the coordinate planes become bounds (Kd* = 0, the thesis' optimum, is
    allowed), the plane Kp/2 + Ki*/4 + Kd* < 1 (pole at z = -1) a linear inequality. The
    planes only approximate the Jury region and their faces Ki* = 0 / Kp = 0 put poles ON
    the unit circle, so the poles are also kept within |z| <= 1 - margin (Jury on the
    scaled polynomial), which makes the optimum strictly stable.
    """
    if not 0.0 < pole_margin < 1.0:
        raise ConfigError(f"pole_margin = {pole_margin!r}: must be in (0, 1)")
    radius = 1.0 - pole_margin
    a = STABLE_VOLUME_A[0]
    fixed = float(sum(a[i] * base[i] for i in range(3) if i not in free))
    a_free = a[free]
    if fixed >= 1.0:
        raise ConfigError(f"fixed gains {fix}: outside the gain-stable volume (eq. 5.25: "
                          "Kp/2 + Ki*/4 + Kd* < 1)")
    # SLSQP meets an active constraint to about 1e-15: kept a hair inside, so that the
    # result's poles are within the margin as printed (0.5000000000000011 at 0.5)
    inside = radius * (1.0 - 1e-12)
    cons = [{"type": "ineq", "fun": lambda x: 1.0 - 1e-9 - fixed - a_free @ x,
             "jac": lambda x: -a_free},
            {"type": "ineq", "fun": lambda x: pole_margin_constraints(*full(x), inside)[0],
             "jac": lambda x: pole_margin_constraints(*full(x), inside)[1][:, free]}]
    lower = np.array([0.0 if _NAMES[i] == "kd" else MIN_GAIN for i in free])
    return _Problem(fun, full, cons, lower, fixed, a_free, radius, tol)


def _spread_starts(x0: np.ndarray, problem: _Problem) -> list[np.ndarray]:
    """``x0`` first, then one start leaning to each vertex of the free gains' slice of the
    gain-stable volume (eq. 5.25: the origin and the axes' ends where the plane
    Kp/2 + Ki*/4 + Kd* = 1 cuts them; Kp = 2, Ki* = 4, Kd* = 1 with no gain held): 0.6 of
    the weight on that vertex, the rest shared by the others, so every start is inside.

    With Kd* held at 0.9 the default start stopped at a local optimum (RMS 0.185) where
    the start leaning to Ki* found 0.133 (a control review).
    """
    n = len(problem.a_free)
    ends = (1.0 - problem.fixed) / problem.a_free
    starts = [x0]
    for j in range(n + 1):          # vertex 0 the origin, j the end of free axis j - 1
        w = np.full(n + 1, 0.4 / n)
        w[j] = 0.6
        starts.append(np.maximum(w[1:] * ends, problem.lower))
    return starts


def _lower(f: float, than: float) -> bool:
    """RMS ``f`` is lower than ``than`` by more than :data:`RMS_RTOL`, relative."""
    return bool(f < than * (1.0 - RMS_RTOL))


def _best_of_starts(problem: _Problem, starts: list[np.ndarray]):
    """The best feasible result of SLSQP over ``starts`` and the note of its check.

    The first start is searched to the full tolerance; the others roughly
    (:data:`ROUGH_FTOL`, a tenth of the cost: 100 000 layers took 28 s with every start
    to 1e-12), and one is finished from where it stopped only when it is lower than the
    best so far by :data:`RMS_RTOL`, or the best did not converge. A result counts when
    feasible and either converged or stopped with no descent (:data:`SLSQP_NO_DESCENT`);
    a later one replaces the best only when lower by :data:`RMS_RTOL` (so the default
    start's gains stay when it finds the optimum), or when it converged where an equal
    best did not. A best that stopped is accepted only after :func:`_check_stop` (note
    non-empty). With nothing counting, the first feasible result (not converged) or else
    the least infeasible one comes back.
    """
    def counts(r) -> bool:
        return problem.feasible(r.x) and (r.success or r.status == SLSQP_NO_DESCENT)

    runs = [problem.run(starts[0])]
    best = runs[0] if counts(runs[0]) else None
    for x in starts[1:]:
        rough = problem.run(x, rough=True)
        if best is not None and best.success and not (
                problem.feasible(rough.x) and _lower(rough.fun, best.fun)):
            continue
        r = problem.run(rough.x)
        runs.append(r)
        if counts(r) and (best is None or _lower(r.fun, best.fun) or (
                r.success and not best.success and not _lower(best.fun, r.fun))):
            best = r
    if best is None:
        feasible = [r for r in runs if problem.feasible(r.x)]
        if feasible:
            return feasible[0], ""
        return min(runs, key=lambda r: np.max(np.abs(poles(*problem.full(r.x))))), ""
    return (best, "") if best.success else _check_stop(problem, best)


def _check_stop(problem: _Problem, res):
    """``(result, note)`` for SLSQP stopped with no descent at a feasible point: the note
    says it is accepted when neither a restart from it nor feasible probes around it find a
    point better by :data:`RMS_RTOL`; empty (not accepted) otherwise, or when neither gave
    a feasible point to compare. A restart that converged to a better point is returned
    instead, as converged by SLSQP itself."""
    again = problem.run(res.x)
    checked = problem.feasible(again.x)
    if checked and _lower(again.fun, res.fun):
        return (again, "") if again.success else (res, "")
    n_probes, better = _probe(problem, res.x, res.fun)
    if better or not (checked or n_probes):
        return res, ""
    return res, (f"accepted: feasible, and a restart and {n_probes} feasible points around "
                 f"it found no RMS lower by {RMS_RTOL:g}")


def _probe(problem: _Problem, x: np.ndarray, f: float) -> tuple[int, bool]:
    """``(feasible probes, one is better)``: points x + h v for v in {-1, 0, 1}^n (not 0)
    and h = 1e-2 .. 1e-8 times max(1, |x|), those feasible compared with RMS ``f``."""
    import itertools

    scale = max(1.0, float(np.max(np.abs(x))))
    n_feasible = 0
    for h in scale * 10.0 ** -np.arange(2, 9):
        for v in itertools.product((-1.0, 0.0, 1.0), repeat=len(x)):
            y = x + h * np.array(v)
            if not any(v) or not problem.feasible(y):
                continue
            n_feasible += 1
            if _lower(problem.fun(y)[0], f):
                return n_feasible, True
    return n_feasible, False


# =========================================================================== surfaces


def grid_over(bounds: np.ndarray, spacing: float) -> tuple[np.ndarray, int, int]:
    """Grid covering ``bounds (2, 2)`` mm with nodes on multiples of ``spacing``.

    Returns ``(origin (2,), nx, ny)``. Snapping to the lattice of ``spacing`` keeps the
    grids of successive measurement layers aligned, so re-gridding between them is exact
    where they overlap.
    """
    if not (np.isfinite(spacing) and spacing > 0):
        raise ConfigError(f"grid spacing = {spacing!r} mm: must be > 0")
    lo = np.floor(np.asarray(bounds[0], dtype=np.float64) / spacing + 1e-9) * spacing
    hi = np.ceil(np.asarray(bounds[1], dtype=np.float64) / spacing - 1e-9) * spacing
    n = np.rint((hi - lo) / spacing).astype(int) + 1
    return lo, int(n[0]), int(n[1])


def region_mask(region: Region, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(len(y), len(x)) bool: nodes of the grid ``x (nx,)`` x ``y (ny,)`` inside ``region``.

    x and y must be evenly spaced and increasing. Even-odd scan-line fill over all rings
    at once (vectorised): every ring edge toggles the nodes to the right of where it
    crosses a grid row, so holes are excluded and islands in holes included (the rings'
    nesting, thesis 3.2). Edges take rows in ``[y_lo, y_hi)``; a node exactly on an edge
    may fall either way.
    """
    nx, ny = len(x), len(y)
    mask = np.zeros((ny, nx), dtype=bool)
    rings = [r for r in region.rings if len(r) >= 3]
    if not rings or nx == 0 or ny == 0:
        return mask
    a = np.concatenate(rings)
    b = np.concatenate([np.roll(r, -1, axis=0) for r in rings])
    sx = float(x[1] - x[0]) if nx > 1 else 1.0
    sy = float(y[1] - y[0]) if ny > 1 else 1.0
    ylo = np.minimum(a[:, 1], b[:, 1])
    yhi = np.maximum(a[:, 1], b[:, 1])
    r0 = np.clip(np.ceil((ylo - y[0]) / sy), 0, ny).astype(np.int64)  # first row >= ylo
    r1 = np.clip(np.ceil((yhi - y[0]) / sy), 0, ny).astype(np.int64)  # first row >= yhi
    cnt = np.maximum(r1 - r0, 0)
    total = int(cnt.sum())
    if total == 0:
        return mask
    edge = np.repeat(np.arange(len(a)), cnt)
    row = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt) + r0[edge]
    yr = y[0] + row * sy
    ea, eb = a[edge], b[edge]
    xi = ea[:, 0] + (yr - ea[:, 1]) * (eb[:, 0] - ea[:, 0]) / (eb[:, 1] - ea[:, 1])
    col = np.clip(np.ceil((xi - x[0]) / sx), 0, nx).astype(np.int64)  # first node >= xi
    toggles = np.zeros((ny, nx + 1), dtype=np.int64)
    np.add.at(toggles, (row, col), 1)
    return (np.cumsum(toggles[:, :nx], axis=1) % 2).astype(bool)


def _nearest_fill(z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """z with every invalid node set to the value of its nearest valid node."""
    from scipy import ndimage

    if np.all(valid) or not np.any(valid):
        return np.where(valid, z, 0.0)
    idx = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return z[tuple(idx)]


#: Samples in the median that tells a spike in the laser samples before they are averaged
#: and gridded: a spike of one or two samples along a path is outvoted, a feature three
#: samples long (1.5 mm at the ice's 50 mm/s and 100 Hz) stays.
DESPIKE_NEIGHBOURS = 5
#: A sample farther from that median than this many robust standard deviations of its
#: neighbours (1.4826 x their median absolute deviation) is a spike (Hampel's filter).
DESPIKE_SIGMAS = 3.0


def _one_per_place(xyz: np.ndarray) -> np.ndarray:
    """Samples at the same x, y (the laser read on while the robot stood) as one, at their
    median height: k-d tree queries slow to a crawl on many equal points (100 000 at one
    place took 30 s, a tester's), and the cell mean that follows would average them."""
    key = np.ascontiguousarray(xyz[:, :2]).view(np.complex128).ravel()
    uniq, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    if len(uniq) == len(xyz):
        return xyz
    order = np.lexsort((xyz[:, 2], inv))          # by place, then by height
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    lo = xyz[order[start + (count - 1) // 2], 2]
    hi = xyz[order[start + count // 2], 2]
    first = order[start]
    return np.column_stack([xyz[first, :2], 0.5 * (lo + hi)])


def _despike(xyz: np.ndarray, k: int = DESPIKE_NEIGHBOURS) -> np.ndarray:
    """Hampel's filter over each sample's ``k`` nearest samples (itself included; by x,
    y): a sample that lies more than :data:`DESPIKE_SIGMAS` robust standard deviations
    from their median takes the median; the others stay as measured, for the cell mean
    to average their noise (replacing every sample by its median cost 1.4 % of the demo
    mug's SMF accuracy). A grid's median alone did not remove a spike: averaged into its
    cell and spread by the triangulation across to the next measurement ring (3 mm), a
    +2 mm spike left 2-3 nodes 0.1-0.27 mm off, wider than a 3 x 3 window removes."""
    from scipy.spatial import cKDTree

    xyz = _one_per_place(xyz)
    k = min(int(k), len(xyz))
    if k < 3:
        return xyz
    _, idx = cKDTree(xyz[:, :2]).query(xyz[:, :2], k=k)
    near = xyz[idx, 2]
    med = np.median(near, axis=1)
    mad = np.median(np.abs(near - med[:, None]), axis=1)
    spike = np.abs(xyz[:, 2] - med) > DESPIKE_SIGMAS * 1.4826 * mad
    out = xyz.copy()
    out[spike, 2] = med[spike]
    return out


def _bin_samples(xyz: np.ndarray, bin_mm: float) -> np.ndarray:
    """Mean of the samples in each ``bin_mm`` square cell: (m, 3), m <= n."""
    cell = np.floor(xyz[:, :2] / bin_mm).astype(np.int64)
    cell -= cell.min(axis=0)
    key = cell[:, 0] * (int(cell[:, 1].max()) + 1) + cell[:, 1]
    _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    out = np.empty((len(count), 3))
    for j in range(3):
        out[:, j] = np.bincount(inv, weights=xyz[:, j]) / count
    return out


def _linear_on_grid(tri, values: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Delaunay-linear interpolation of ``values`` at the grid nodes, NaN outside the hull.

    The same values as ``LinearNDInterpolator(tri, values)`` evaluated at the nodes, but
    computed triangle by triangle (each triangle fills the nodes inside its bounding box
    by their barycentric coordinates, vectorised), which costs O(nodes + triangles)
    instead of a point-location walk per node: 1 000x faster on measurement-ring samples,
    whose long thin triangles make the walk (and the brute-force search for nodes outside
    the hull) slow.
    """
    nx, ny = len(x), len(y)
    z = np.full((ny, nx), np.nan)
    s = float(x[1] - x[0]) if nx > 1 else 1.0
    sy = float(y[1] - y[0]) if ny > 1 else 1.0
    P = tri.points[tri.simplices]  # (t, 3, 2)
    lo, hi = P.min(axis=1), P.max(axis=1)
    ix0 = np.clip(np.ceil((lo[:, 0] - x[0]) / s - 1e-9), 0, nx).astype(np.int64)
    ix1 = np.clip(np.floor((hi[:, 0] - x[0]) / s + 1e-9), -1, nx - 1).astype(np.int64)
    iy0 = np.clip(np.ceil((lo[:, 1] - y[0]) / sy - 1e-9), 0, ny).astype(np.int64)
    iy1 = np.clip(np.floor((hi[:, 1] - y[0]) / sy + 1e-9), -1, ny - 1).astype(np.int64)
    cx = np.maximum(ix1 - ix0 + 1, 0)
    cy = np.maximum(iy1 - iy0 + 1, 0)
    cnt = cx * cy
    total = int(cnt.sum())
    if total == 0:
        return z
    t = np.repeat(np.arange(len(P)), cnt)
    local = np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    jx = ix0[t] + local % cx[t]
    jy = iy0[t] + local // cx[t]
    # barycentric coordinates of node p in triangle (A, B, C): p = A + l1 (B-A) + l2 (C-A)
    A = P[:, 0]
    v0 = P[:, 1] - A
    v1 = P[:, 2] - A
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]  # twice the signed area
    good = np.abs(den) > 1e-12 * (1.0 + np.abs(v0).sum(axis=1) * np.abs(v1).sum(axis=1))
    inv = np.where(good, 1.0 / np.where(good, den, 1.0), 0.0)
    d0 = x[jx] - A[t, 0]
    d1 = y[jy] - A[t, 1]
    l1 = (d0 * v1[t, 1] - v1[t, 0] * d1) * inv[t]
    l2 = (v0[t, 0] * d1 - d0 * v0[t, 1]) * inv[t]
    l0 = 1.0 - l1 - l2
    eps = 1e-9
    inside = good[t] & (l0 >= -eps) & (l1 >= -eps) & (l2 >= -eps)
    v = values[tri.simplices[t]]
    val = l0 * v[:, 0] + l1 * v[:, 1] + l2 * v[:, 2]
    z[jy[inside], jx[inside]] = val[inside]
    return z


def surface_from_samples(xyz: np.ndarray, footprint: Region | Sequence[Region] | None = None,
                         spacing: float = 1.0, *, smoothing: bool = False,
                         smooth_size: int = 3, bin_mm: float | None = None) -> HeightMap:
    """Interpolate laser samples on a regular grid over a footprint (thesis 5.2.1).

    xyz: (n, 3) float64, mm: measured points (part frame), n >= 3, not all collinear.
    footprint: the merged part + scaffold region of the measurement layer (thesis
        Fig. 5-3), or several regions whose union it is (e.g. ``(layer.part,
        layer.scaffold)``); nodes outside it are NaN. None: the samples' convex hull.
    spacing: grid pitch, mm (``job.feedback.grid_mm``); nodes on multiples of it.
    smoothing: robust smoothing, which removes isolated spikes (laser drop-outs,
        specular reflections) without flattening steps the way a mean would: a sample far
        from the median of its :data:`DESPIKE_NEIGHBOURS` nearest samples takes it
        (Hampel's filter, :func:`_despike`), and the grid then a ``smooth_size`` x
        ``smooth_size`` median filter
        (``scipy.ndimage.median_filter``). The thesis smoothed with Garcia's robust N-D
        smoother (penalised least squares with robust weights): medians are what makes
        it robust, not its smoothing parameter, which is not reproduced here.
    bin_mm: the samples are first averaged per square cell of this size (default: the
        grid pitch, the finest detail the grid can show), which lowers the laser noise and
        the triangulation cost (the laser gives several samples per mm); 0 keeps every
        sample.

    Interpolation is Delaunay-linear (``scipy.spatial.Delaunay`` and barycentric
    weights: the values of ``LinearNDInterpolator``, as Matlab's TriScatteredInterp);
    footprint nodes outside the samples' convex hull take the value of the nearest sample.
    """
    from scipy.spatial import Delaunay, QhullError, cKDTree

    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise GeometryError(f"laser samples: expected an (n, 3) array, got shape {xyz.shape}")
    ok = np.all(np.isfinite(xyz), axis=1)
    if np.count_nonzero(ok) < 3:
        raise GeometryError(f"laser samples: {np.count_nonzero(ok)} finite samples, need >= 3")
    if not np.all(ok):
        log.warning("laser samples: %d non-finite samples dropped", int(np.count_nonzero(~ok)))
        xyz = xyz[ok]
    if not (np.isfinite(spacing) and spacing > 0):
        raise ConfigError(f"grid spacing = {spacing!r} mm: must be > 0")
    if smoothing:
        xyz = _despike(xyz)
    b = spacing if bin_mm is None else float(bin_mm)
    if b > 0:
        xyz = _bin_samples(xyz, b)
    xy = xyz[:, :2]
    regions = [] if footprint is None else \
        [r for r in ((footprint,) if isinstance(footprint, Region) else footprint)
         if not r.is_empty]
    if regions:
        bb = np.stack([r.bounds() for r in regions])
        check_grid(bb[:, 0].min(axis=0), bb[:, 1].max(axis=0), spacing,
                   "grid spacing (feedback.grid_mm)")
        origin, nx, ny = grid_over(np.stack([bb[:, 0].min(axis=0), bb[:, 1].max(axis=0)]),
                                   spacing)
    else:
        check_grid(xy.min(axis=0), xy.max(axis=0), spacing, "grid spacing (feedback.grid_mm)")
        origin, nx, ny = grid_over(np.stack([xy.min(axis=0), xy.max(axis=0)]), spacing)
    x = origin[0] + spacing * np.arange(nx)
    y = origin[1] + spacing * np.arange(ny)
    try:
        if len(xy) < 3:
            raise QhullError("fewer than 3 distinct samples")
        tri = Delaunay(xy)
    except QhullError as exc:
        raise GeometryError(f"laser samples: cannot triangulate ({len(xy)} samples, all "
                            f"collinear?): {str(exc).splitlines()[0]}") from None
    z = _linear_on_grid(tri, xyz[:, 2], x, y)
    if regions:
        mask = np.zeros((ny, nx), dtype=bool)
        for r in regions:
            mask |= region_mask(r, x, y)
        z[~mask] = np.nan
        hole = mask & ~np.isfinite(z)
        if np.any(hole):
            hy, hx = np.nonzero(hole)
            _, nearest = cKDTree(xy).query(np.column_stack([x[hx], y[hy]]))
            z[hy, hx] = xyz[nearest, 2]
    else:
        mask = np.isfinite(z)
    if smoothing and np.any(mask):
        from scipy import ndimage

        filled = _nearest_fill(z, mask)
        z = np.where(mask, ndimage.median_filter(filled, size=smooth_size, mode="nearest"),
                     np.nan)
    return HeightMap(origin=origin, spacing=float(spacing), z=z)


def restrict_to_footprint(surface: HeightMap, samples: np.ndarray, footprint: np.ndarray,
                          grid: HeightMap) -> HeightMap:
    """``surface`` (from :func:`surface_from_samples` without a footprint: the samples'
    convex hull) restricted to the layer's deposited footprint, part and scaffold (thesis
    5.1.2, Fig. 5-3: the grid spans the merged regions).

    footprint: (ny, nx) bool on ``grid`` (its origin and spacing, mm; its z unused), e.g.
    the cells a layer's beads cover. A node of ``surface`` whose nearest ``grid`` cell is
    outside becomes NaN: the hull spans the empty platform between a part's arms or
    islands, and the heights interpolated there fed the controller. A node inside but
    outside the hull takes the height of the nearest sample (``samples`` (m, 3), mm).
    Returns a new HeightMap on ``surface``'s grid, mm; all NaN when the samples' grid
    misses the footprint.
    """
    from scipy.spatial import cKDTree

    x, y = surface.grid()
    g = float(grid.spacing)
    ix = np.rint((x - grid.origin[0]) / g).astype(np.int64)
    iy = np.rint((y - grid.origin[1]) / g).astype(np.int64)
    ny, nx = footprint.shape
    okx = (ix >= 0) & (ix < nx)
    oky = (iy >= 0) & (iy < ny)
    inside = footprint[np.clip(iy, 0, ny - 1)][:, np.clip(ix, 0, nx - 1)]
    inside &= oky[:, None] & okx[None, :]
    z = np.where(inside, surface.z, np.nan)
    hole = inside & ~np.isfinite(surface.z)
    if hole.any():
        samples = np.asarray(samples, dtype=np.float64)
        hy, hx = np.nonzero(hole)
        _, nearest = cKDTree(samples[:, :2]).query(np.column_stack([x[hx], y[hy]]))
        z[hy, hx] = samples[nearest, 2]
    return HeightMap(origin=np.asarray(surface.origin, dtype=np.float64),
                     spacing=float(surface.spacing), z=z)


def error_surface(measured: HeightMap, nominal_z: float, interval_mm: float) -> HeightMap:
    """Normalised error E = (nominal - measured) / dh_m on the measured grid (thesis 5.2.1).

    Positive where the part is too low. NaN stays NaN (outside the footprint).
    """
    if not (np.isfinite(interval_mm) and interval_mm > 0):
        raise ConfigError(f"measurement interval = {interval_mm!r} mm: must be > 0")
    return HeightMap(origin=np.asarray(measured.origin, dtype=np.float64),
                     spacing=measured.spacing,
                     z=(float(nominal_z) - measured.z) / float(interval_mm))


def regrid(surface: HeightMap, target: HeightMap) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate ``surface`` on the grid of ``target`` (thesis 5.1.2: F.V = F(X')).

    Returns ``(values (ny, nx) float64, known (ny, nx) bool)``: bilinear interpolation
    (``scipy.interpolate.RegularGridInterpolator``) of the finite nodes, renormalised by
    the weight of the finite corners; nodes with no finite neighbour in ``surface``
    (new grid points) are unknown and get 0, as the thesis proposes for new gridpoints.
    """
    from scipy.interpolate import RegularGridInterpolator

    ty, tx = target.z.shape
    sy, sx = surface.z.shape
    valid = np.isfinite(surface.z)
    # Fast path: same pitch and lattice (the usual case, see grid_over) -> index shift.
    if np.isclose(surface.spacing, target.spacing):
        off = (np.asarray(target.origin) - np.asarray(surface.origin)) / target.spacing
        if np.allclose(off, np.rint(off), atol=1e-6):
            ox, oy = (int(v) for v in np.rint(off))
            vals = np.zeros((ty, tx))
            known = np.zeros((ty, tx), dtype=bool)
            x0, x1 = max(0, -ox), min(tx, sx - ox)
            y0, y1 = max(0, -oy), min(ty, sy - oy)
            if x0 < x1 and y0 < y1:
                src = surface.z[y0 + oy:y1 + oy, x0 + ox:x1 + ox]
                ok = np.isfinite(src)
                vals[y0:y1, x0:x1] = np.where(ok, src, 0.0)
                known[y0:y1, x0:x1] = ok
            return vals, known
    xs, ys = surface.grid()
    xt, yt = target.grid()
    pts = np.stack(np.meshgrid(yt, xt, indexing="ij"), axis=-1).reshape(-1, 2)
    if len(xs) < 2 or len(ys) < 2:
        return np.zeros((ty, tx)), np.zeros((ty, tx), dtype=bool)
    v = RegularGridInterpolator((ys, xs), np.where(valid, surface.z, 0.0), bounds_error=False,
                                fill_value=0.0)(pts).reshape(ty, tx)
    w = RegularGridInterpolator((ys, xs), valid.astype(np.float64), bounds_error=False,
                                fill_value=0.0)(pts).reshape(ty, tx)
    known = w > 1e-9
    return np.where(known, v / np.where(known, w, 1.0), 0.0), known


# =========================================================================== spatial PID


@dataclass(frozen=True, eq=False)
class SmfState:
    """State of the spatial PID between measurement layers (thesis 5.1.2, eq. 5.1).

    integral: the integral term Ki* sum E_i, saturated (anti-windup), on the grid of the
        last measurement layer (NaN outside its footprint); None before the first update.
    previous_error: E_{k-1} on its own grid; None before the first update.
    k: number of measurement layers processed.
    """

    integral: HeightMap | None = None
    previous_error: HeightMap | None = None
    k: int = 0


@dataclass(frozen=True, eq=False)
class ControlAction:
    """The controller output of one measurement layer (thesis Fig. 5-4).

    u: saturated output U' (eq. 5.4), NaN outside the footprint; the nu-controller
        multiplies the flow by (1 + u), the c-controller divides the speed by it.
    unsaturated: U before saturation (eq. 5.1).
    p, i, d: (ny, nx) float64 the three terms (i already saturated).
    saturated: fraction of footprint nodes where U was cut by the saturation planes.
    controller: "flow" or "speed".
    """

    u: HeightMap
    unsaturated: HeightMap
    p: np.ndarray
    i: np.ndarray
    d: np.ndarray
    saturated: float
    controller: str = "flow"
    _filled: np.ndarray | None = field(default=None, repr=False)

    def sample(self, xy: np.ndarray) -> np.ndarray:
        """(n,) u at points ``xy (n, 2)`` mm (see :func:`action_along`)."""
        return action_along(self, xy)


def saturation_limits(job: "Job") -> tuple[float, float]:
    """Lower and upper saturation planes of U (thesis Fig. 5-4(b), 5.2.2).

    nu-controller: +-saturation. c-controller: c = c_nom / (1 + u) must stay within
    +-saturation of c_nom, so u in [1/(1+s) - 1, 1/(1-s) - 1].
    """
    s = float(job.feedback.saturation)
    if job.feedback.controller == "speed":
        return 1.0 / (1.0 + s) - 1.0, (1.0 / (1.0 - s) - 1.0) if s < 1 else np.inf
    return -s, s


def _check_limits(limits, integral_limit) -> None:
    """smf_update's overrides of the planes of U and the integral's bound (a tester's
    reversed limits, or a negative integral limit, flipped the action's sign)."""
    if limits is not None:
        try:
            lo, hi = (float(x) for x in limits)
        except (TypeError, ValueError):
            lo, hi = np.nan, np.nan
        if not lo <= 0.0 <= hi:          # False for NaN too; infinite: no plane
            raise ConfigError(f"limits {limits!r}: expected (lower, upper) planes of U with "
                              "lower <= 0 <= upper")
    if integral_limit is not None:
        try:
            bound = float(integral_limit)
        except (TypeError, ValueError):
            bound = np.nan
        if not bound >= 0.0:             # False for NaN; inf: no anti-windup
            raise ConfigError(f"integral_limit {integral_limit!r}: expected a number >= 0 "
                              "(inf: no bound)")


def _error_grid(error: HeightMap) -> np.ndarray:
    """The error surface's z as a 2-D float64 grid on a positive, finite spacing and a
    finite origin; GeometryError otherwise (a tester's spacing 0 failed in scipy)."""
    try:
        z = np.asarray(error.z, dtype=np.float64)
        spacing = float(error.spacing)
        origin = np.asarray(error.origin, dtype=np.float64)
    except (AttributeError, TypeError, ValueError):
        raise GeometryError(f"error surface {type(error).__name__}: expected a HeightMap "
                            "(origin (2,), spacing mm, z (ny, nx))") from None
    if z.ndim != 2 or origin.shape != (2,) or not (np.isfinite(spacing) and spacing > 0) \
            or not np.isfinite(origin).all():
        raise GeometryError(f"error surface: z {z.shape}, spacing {spacing!r}, origin "
                            f"{origin.tolist()}: expected a 2-D grid, a positive spacing and "
                            "a finite origin")
    return z


def smf_update(state: SmfState, error: HeightMap, job: "Job | None" = None, *,
               gains: Gains | None = None, limits: tuple[float, float] | None = None,
               integral_limit: float | None = None) -> tuple[ControlAction, SmfState]:
    """One step of the 3D spatial PID of eq. 5.1 at a measurement layer.

    state: the state after the previous measurement layer (``SmfState()`` at the start).
    error: normalised error surface E_k (:func:`error_surface`), NaN outside the
        footprint; its grid may differ from the previous layer's.
    job: settings (``job.feedback``: kp, ki, kd normalised gains, saturation,
        integral_saturation, controller); ``Job()`` when None.
    gains, limits, integral_limit: override (Kp, Ki*, Kd*), the (lower, upper) planes of U
        and the +- bound of the integral term.

    U_k = Kp E_k + I_k + Kd* (E_k - E_{k-1}), I_k = clip(I_{k-1} + Ki* E_k, +-integral_limit)
    and, with the job's bound, within the planes of U as well (eq. 5.1 with eq. 5.2;
    clamping the integral term is the anti-windup of thesis 5.2.2: an integral past what U
    can give winds up; the c-controller's planes are uneven, [-0.23, +0.43] at 30 %, and
    its integral reached -0.3), U'_k = clip(U_k, limits). I_{k-1} and E_{k-1} are
    re-evaluated on the new grid (:func:`regrid`); nodes new to the footprint start with
    zero integral and zero derivative contribution, and the derivative is left out at
    k = 1. A node NaN in E_k that the state knows (a laser drop-out, a layer the laser saw
    nothing of) keeps its integral and previous error for the next layer: not measured is
    not "error 0".
    """
    if job is None:
        job = Job()
    fb = job.feedback
    if gains is not None:
        _check_gains(gains)      # a tester's NaN gain made the action NaN
    kp, ki, kd = (float(g) for g in gains) if gains is not None else (fb.kp, fb.ki, fb.kd)
    _check_limits(limits, integral_limit)
    lo, hi = limits if limits is not None else saturation_limits(job)
    isat = float(fb.integral_saturation if integral_limit is None else integral_limit)
    E = _error_grid(error)
    valid = np.isfinite(E)
    Ez = np.where(valid, E, 0.0)
    if state.integral is not None:
        i_prev, i_known = regrid(state.integral, error)
    else:
        i_prev, i_known = np.zeros_like(Ez), np.zeros(Ez.shape, dtype=bool)
    e_prev, e_known = (regrid(state.previous_error, error)
                       if state.previous_error is not None
                       else (np.zeros_like(Ez), np.zeros(Ez.shape, dtype=bool)))
    # the job's integral bound within the planes of U too (an explicit integral_limit is
    # taken as it is: np.inf turns the anti-windup off)
    ilo, ihi = (max(-isat, lo), min(isat, hi)) if integral_limit is None else (-isat, isat)
    I = np.clip(i_prev + ki * Ez, ilo, ihi)
    P = kp * Ez
    D = np.zeros_like(Ez)
    if state.previous_error is not None and state.k >= 1 and kd != 0.0:
        D = np.where(e_known, kd * (Ez - e_prev), 0.0)
    U = P + I + D
    Us = np.clip(U, lo, hi)
    n_valid = int(np.count_nonzero(valid))
    sat = float(np.count_nonzero(valid & (Us != U)) / n_valid) if n_valid else 0.0
    nan = np.nan
    origin = np.asarray(error.origin, dtype=np.float64)
    u_map = HeightMap(origin, error.spacing, np.where(valid, Us, nan))
    action = ControlAction(
        u=u_map,
        unsaturated=HeightMap(origin, error.spacing, np.where(valid, U, nan)),
        p=np.where(valid, P, nan), i=np.where(valid, I, nan), d=np.where(valid, D, nan),
        saturated=sat, controller=fb.controller,
        _filled=_nearest_fill(Us, valid) if n_valid else np.zeros_like(Us))
    # the state keeps its own copy: a caller that refills one buffer each layer made the
    # previous error the current one, and the derivative term 0 (a tester's)
    # (what a node not measured now knew it keeps)
    kept_i = np.where(valid, I, np.where(i_known, i_prev, nan))
    kept_e = np.where(valid, E, np.where(e_known, e_prev, nan))
    new_state = SmfState(integral=HeightMap(origin, error.spacing, kept_i),
                         previous_error=HeightMap(origin.copy(), float(error.spacing), kept_e),
                         k=state.k + 1)
    if sat > 0:
        log.info("SMF layer %d: output saturated on %.1f %% of the footprint", state.k + 1,
                 100 * sat)
    return action, new_state


def measured_update(state: SmfState, samples: np.ndarray, nominal_z: float,
                    interval_mm: float, job: "Job",
                    footprint: tuple[np.ndarray, HeightMap] | None = None
                    ) -> tuple[SmfState, ControlAction | None, str | None]:
    """One SMF step from a measurement layer's laser samples ((m, 3) mm, part frame):
    the surface (:func:`surface_from_samples` on ``feedback.grid_mm``), restricted to the
    layer's ``footprint`` ((mask, grid): :func:`restrict_to_footprint`; None: the samples'
    convex hull), its error against ``nominal_z`` mm normalised by ``interval_mm``
    (:func:`error_surface`), and :func:`smf_update`. Returns (new state, action, None).

    A surface that cannot be formed (too few or collinear samples, none on the footprint):
    (``state`` kept, :func:`held_action`, the reason), the action None before the first
    update (nominal flow). The simulator and the build runner both step so (one sequence:
    it was written in each)."""
    fb = job.feedback

    def held(why: str):
        note = (f"{why}: SMF keeps its state and applies the integral term alone until the "
                "next measurement")
        action = held_action(state, job)
        return state, action, note + ("" if action is not None else
                                      " (none yet: nominal flow)")

    try:
        surf = surface_from_samples(samples, None, fb.grid_mm, smoothing=fb.smoothing)
    except GeometryError as exc:   # e.g. a tiny top layer's few or collinear samples
        return held(f"no surface from {len(samples)} laser samples ({exc})")
    if footprint is not None:
        surf = restrict_to_footprint(surf, samples, *footprint)
        if not np.isfinite(surf.z).any():
            return held("the laser samples miss the layer's footprint")
    action, new = smf_update(state, error_surface(surf, nominal_z, interval_mm), job)
    return new, action, None


def held_action(state: SmfState, job: "Job | None" = None) -> ControlAction | None:
    """The action of a measurement layer whose error surface cannot be formed (too few or
    collinear laser samples, or none on the footprint): the integral term I_{k-1} alone,
    within the planes of U, on the grid of the last update; the caller keeps ``state``.

    Not measured is not "error 0" (as for :func:`smf_update`'s NaN nodes): the P and D
    terms act on this layer's error, which is unknown, and the integral holds the bias of
    a lasting disturbance (a flow error; thesis 5.1.2, 5.2.2), which an action of 0 threw
    away for a whole interval. Dimensionless u, NaN outside the last footprint. None
    before the first update (nominal flow).
    """
    if job is None:
        job = Job()
    if state.integral is None:
        return None
    z = np.asarray(state.integral.z, dtype=np.float64)
    valid = np.isfinite(z)
    if not valid.any():
        return None
    lo, hi = saturation_limits(job)
    us = np.where(valid, np.clip(z, lo, hi), np.nan)
    origin = np.asarray(state.integral.origin, dtype=np.float64)
    u = HeightMap(origin, float(state.integral.spacing), us)
    zero = np.where(valid, 0.0, np.nan)
    return ControlAction(u=u, unsaturated=u, p=zero, i=np.where(valid, z, np.nan), d=zero,
                         saturated=0.0, controller=job.feedback.controller,
                         _filled=_nearest_fill(np.where(valid, us, 0.0), valid))


def smf_step(samples: np.ndarray, footprint: Region | Sequence[Region] | None,
             nominal_z: float, state: SmfState, job: "Job | None" = None
             ) -> tuple[ControlAction, SmfState]:
    """One measurement layer of SMF end to end (thesis Fig. 5-2).

    samples: (n, 3) laser samples, mm, part frame; footprint: the layer's part and
    scaffold regions; nominal_z: nominal height of the measured surface, mm.
    Surface on ``job.feedback.grid_mm`` (smoothing per ``job.feedback.smoothing``), error
    normalised by dh_m = ``interval_layers * layer_thickness_mm``, then :func:`smf_update`.
    """
    if job is None:
        job = Job()
    fb = job.feedback
    surface = surface_from_samples(samples, footprint, fb.grid_mm, smoothing=fb.smoothing)
    dh_m = fb.interval_layers * job.slicing.layer_thickness_mm
    return smf_update(state, error_surface(surface, nominal_z, dh_m), job)


def action_along(action: HeightMap | ControlAction, xy: np.ndarray) -> np.ndarray:
    """(n,) float64 control action u at points ``xy (n, 2)`` mm (thesis eq. 5.5).

    Bilinear interpolation (``scipy.interpolate.RegularGridInterpolator``) in the action
    grid; nodes outside the footprint take their nearest footprint value first, so a path
    along the region edge sees the edge's action, and points outside the grid take the
    value at the nearest point of its edge. The grid spans the laser's samples, and the
    footprint a layer deposits reaches past them (the demo mug's scaffold boundary 2.8 mm
    past its last measurement ring): thesis 5.1.2 spans the grid over the footprint of part
    and scaffold. Points outside the grid got 0 (no correction): 3.6 % of the mug's
    scaffold ran open loop, its rim 0.10 mm high after 80 layers under a +10 % flow error,
    0.72 mm with no spreading (a control review's). For many paths, build the sampler once
    with :func:`action_sampler`.
    """
    return action_sampler(action)(xy)


def action_sampler(action: HeightMap | ControlAction) -> Callable[[np.ndarray], np.ndarray]:
    """A function ``u(xy (n, 2)) -> (n,)`` equal to :func:`action_along` for ``action``,
    with the grid prepared once (for applying one action to many paths)."""
    from scipy.interpolate import RegularGridInterpolator

    if isinstance(action, ControlAction):
        hm = action.u
        filled = action._filled if action._filled is not None else \
            _nearest_fill(hm.z, np.isfinite(hm.z))
    else:
        hm = action
        filled = _nearest_fill(hm.z, np.isfinite(hm.z))
    x, y = hm.grid()
    if len(x) < 2 or len(y) < 2:
        return lambda xy: np.zeros(len(np.asarray(xy).reshape(-1, 2)))
    rgi = RegularGridInterpolator((y, x), filled)
    lo = np.array([y[0], x[0]])
    hi = np.array([y[-1], x[-1]])

    def sample(xy: np.ndarray) -> np.ndarray:
        # outside the grid: its edge's value (clipped onto it; NaN stays NaN)
        return rgi(np.clip(np.asarray(xy, dtype=np.float64).reshape(-1, 2)[:, ::-1], lo, hi))
    return sample


def retime_trajectory(traj: Trajectory, u: np.ndarray, *, max_change: float = 0.3,
                      cap: np.ndarray | None = None) -> Trajectory:
    """The c-controller (thesis 5.2.2, eqs. 5.7, 5.10, Fig. 5-6): speed c_nom / (1 + u).

    traj: constant-dt trajectory; u: (n,) control action at its samples.
    max_change: the speed stays within +-max_change of nominal (thesis: 30 %).
    cap: (n,) the largest speed-up each sample allows under the motion limits
    (:func:`icefab.motion.speedup_cap`); None: only ``max_change`` bounds it.

    The speed factor f = clip(1 / (1 + u), 1 - max_change, 1 + max_change) changes the time
    to cover each segment to dt / f (f averaged over the segment's ends); the path is then
    re-sampled at the SAME dt by linear interpolation in time, so the speed lives in the
    point spacing (Fig. 5-6) instead of in variable point-to-point durations. The time axis
    is stretched by at most dt / duration so the last sample lands exactly on (n'-1) dt
    (with a ``cap``, only lengthened).
    Joints (and a variable-width path's widths) are re-sampled the same way; piece starts
    (``traj.pieces``) move to the sample nearest their new time, a tour's valve switches
    (``traj.on_spans``) to their new instants.
    """
    xy = np.asarray(traj.xy, dtype=np.float64)
    n = len(xy)
    u = np.asarray(u, dtype=np.float64)
    if u.shape != (n,):
        raise ConfigError(f"retime_trajectory: u has shape {u.shape}, expected ({n},)")
    if not (0 <= max_change < 1):
        raise ConfigError(f"max_change = {max_change!r}: must be in [0, 1)")
    if n < 2:
        return traj
    hi = 1.0 + max_change
    if cap is not None:
        cap = np.asarray(cap, dtype=np.float64)
        if cap.shape != (n,):
            raise ConfigError(f"retime_trajectory: cap has shape {cap.shape}, expected ({n},)")
        hi = np.minimum(hi, np.maximum(cap, 1.0))
    f = np.clip(1.0 / np.maximum(1.0 + u, 1e-9), 1.0 - max_change, hi)
    dt = float(traj.dt)
    seg = dt / (0.5 * (f[1:] + f[:-1]))
    T = arc_lengths(seg)
    # the last sample lands on a whole step: the time axis is stretched to it, and with a
    # cap only ever lengthened (a shortened axis would speed the path past the cap)
    steps = np.ceil(T[-1] / dt - 1e-9) if cap is not None else np.rint(T[-1] / dt)
    n_new = max(2, int(steps) + 1)
    T *= (n_new - 1) * dt / T[-1]
    t_new = np.arange(n_new) * dt
    xy_new = np.column_stack([np.interp(t_new, T, xy[:, j]) for j in range(2)])
    speed = np.asarray(traj.speed, dtype=np.float64) * f
    speed_new = np.interp(t_new, T, speed)
    joints = np.asarray(traj.joints, dtype=np.float64)
    if joints.ndim == 2 and len(joints) == n and joints.shape[1] > 0:
        joints_new = np.column_stack([np.interp(t_new, T, joints[:, j])
                                      for j in range(joints.shape[1])])
    else:
        joints_new = np.zeros((n_new, 0))
    pieces = np.asarray(getattr(traj, "pieces", np.zeros(0)), dtype=np.int64)
    if len(pieces):  # piece starts (rest points) move with the time axis
        pieces = np.unique(np.clip(np.rint(T[np.clip(pieces, 0, n - 1)] / dt), 0, n_new - 1)
                           ).astype(np.int64)
    widths = (None if traj.widths is None else
              np.interp(t_new, T, np.asarray(traj.widths, dtype=np.float64)))
    spans = traj.on_spans
    if spans is not None:   # a tour's valve switches where the nozzle passes the same points
        old = np.asarray(spans, dtype=np.float64)
        spans = np.minimum(np.interp(old / dt, np.arange(n), T), (n_new - 1) * dt)
    return Trajectory(dt=dt, xy=xy_new, joints=joints_new, speed=speed_new,
                      duration=(n_new - 1) * dt, path=traj.path, pieces=pieces, widths=widths,
                      on_spans=spans)
