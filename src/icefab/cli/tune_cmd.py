"""``icefab tune``: stability and optimal gains of the SMF PID controller (thesis 5.5-5.7).

Examples::

    icefab tune                                   # the thesis' design disturbance
    icefab tune --layers 100 --pulse 0.5@60 --step 0.2@30 --json
    icefab tune --fix-kp --fix-ki                 # optimise Kd* only (eq. 5.39)
    icefab tune --gains 1,0.33,0.45               # evaluate: unstable, max pole 1.05
    icefab tune --noise 0.05 -o tune_out          # also writes tune_out/error_response.png

Optimised gains stay strictly inside the gain-stable volume: every pole within
|z| <= 1 - 0.01 (``--pole-margin``). ``--json`` prints strict JSON: ``rms`` is null when
the error response of the given gains diverges; for ``--gains`` ``optimised`` is false and
``converged`` null (no optimiser ran).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings

from icefab.report import plot_error_response
from icefab.cli.common import add_job_argument, job_from_args, output_dir
from icefab.errors import ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "tune", help="stability and optimal gains of the SMF PID controller",
        description="Simulate the 1D surface-mapping-feedback model (thesis 5.4) for a "
                    "disturbance profile, find the gains (Kp, Ki*, Kd*) minimising the RMS "
                    "error (eq. 5.27), or evaluate given gains; report stability and the "
                    "largest pole modulus (eq. 5.22). Amplitudes are in measurement "
                    "intervals, layers are measurement layers. Without --pulse/--step/--noise "
                    "the thesis' disturbance is used (pulse 0.5@60, step 0.2@30: 64 layers or "
                    "more, one fewer per fixed gain, 60 to evaluate --gains). Every "
                    "disturbance must start at least one layer per optimised gain, plus "
                    "one, before the end.")
    add_job_argument(p)
    p.add_argument("--layers", type=str, default="100", metavar="N",
                   help="number of measurement layers simulated (default 100)")
    p.add_argument("--pulse", action="append", default=[], metavar="AMPLITUDE@LAYER",
                   help="a one-layer disturbance (eq. 5.30); repeatable")
    p.add_argument("--step", action="append", default=[], metavar="AMPLITUDE@LAYER",
                   help="a lasting disturbance from LAYER on (eq. 5.31); repeatable")
    p.add_argument("--noise", type=str, default=None, metavar="AMPLITUDE",
                   help="random disturbance d_r (RN - 0.5) at every layer (eq. 5.32)")
    p.add_argument("--seed", type=str, default="0", help="seed of the random disturbance")
    p.add_argument("--fix-kp", nargs="?", const="job", default=None, metavar="KP",
                   help="hold Kp (at KP, else the job's feedback.kp) and optimise the others")
    p.add_argument("--fix-ki", nargs="?", const="job", default=None, metavar="KI",
                   help="hold Ki* (at KI, else the job's feedback.ki)")
    p.add_argument("--fix-kd", nargs="?", const="job", default=None, metavar="KD",
                   help="hold Kd* (at KD, else the job's feedback.kd)")
    p.add_argument("--gains", metavar="KP,KI,KD",
                   help="only evaluate these normalised gains (no optimisation)")
    p.add_argument("--start", metavar="KP,KI,KD", default="1,1,0",
                   help="initial gains of the optimisation (default 1,1,0 as thesis Table 5-2)")
    p.add_argument("--unconstrained", action="store_true",
                   help="search outside the gain-stable volume too (BFGS instead of SLSQP)")
    p.add_argument("--pole-margin", default=None, metavar="EPS",
                   help="constrained search: every pole within |z| <= 1 - EPS (to 1e-6), "
                        "so the result is strictly stable (default 0.01); not with "
                        "--unconstrained")
    p.add_argument("--json", action="store_true",
                   help="print one JSON object with kp, ki, kd, rms, max_pole, stable, "
                        "optimised, converged, converged_by_check (the last two null for "
                        "--gains: no optimiser ran)")
    p.add_argument("-o", "--out", metavar="DIR",
                   help="write DIR/error_response.png and DIR/tune.json")
    p.set_defaults(func=run)


def _number(text: str, what: str, *, integer: bool = False, lo: float | None = None,
            hi: float | None = None) -> float:
    try:
        v = int(text) if integer else float(text)
    except ValueError:
        kind = "an integer" if integer else "a number"
        raise ConfigError(f"{what} = {text!r}: expected {kind}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{what} = {text!r}: must be finite")
    if lo is not None and v < lo:
        raise ConfigError(f"{what} = {text!r}: must be >= {lo:g}")
    if hi is not None and v > hi:
        raise ConfigError(f"{what} = {text!r}: must be <= {hi:g}")
    return v


def _at(text: str, option: str, n_layers: int) -> tuple[float, int]:
    amp, sep, layer = text.partition("@")
    if not sep:
        raise ConfigError(f"{option} {text!r}: expected AMPLITUDE@LAYER, e.g. 0.5@60")
    a = _number(amp, f"{option} amplitude")
    k = int(_number(layer, f"{option} layer", integer=True))
    if not 1 <= k <= n_layers:
        raise ConfigError(f"{option} {text!r}: layer must be in 1..{n_layers} (--layers)")
    return a, k


def _gain(v: float) -> str:
    """Four decimals, or four digits for a value too large or small for them (1e200 was
    printed with 200 digits)."""
    return f"{v:.4f}" if 1e-4 <= abs(v) < 1e6 or v == 0.0 else f"{v:.4g}"


def _triple(text: str, option: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise ConfigError(f"{option} {text!r}: expected three numbers KP,KI,KD")
    kp, ki, kd = (_number(x, f"{option} {n}") for x, n in zip(parts, ("KP", "KI", "KD")))
    return kp, ki, kd


def _pole_margin(args: argparse.Namespace) -> float | None:
    """--pole-margin as a number in (0, 1), None when not given; refused with
    --unconstrained, whose BFGS search has no constraints to keep it (it was ignored: a
    margin of 0.5 returned a largest pole of 0.672)."""
    if args.pole_margin is None:
        return None
    if args.unconstrained:
        raise ConfigError("--pole-margin keeps the constrained search's poles within "
                          "|z| <= 1 - EPS; --unconstrained has no constraints: give one or "
                          "the other")
    margin = _number(args.pole_margin, "--pole-margin", lo=0.0)
    if not 0.0 < margin < 1.0:
        raise ConfigError(f"--pole-margin = {args.pole_margin!r}: must be in (0, 1)")
    return margin


def _thesis_last_layer() -> int:
    """The layer of the thesis' disturbance's last part: its pulse 0.5@60 (the step 0.2@30
    comes first)."""
    from icefab.feedback import Disturbance

    thesis = Disturbance()
    return max(layer for _amp, layer in thesis.pulses + thesis.steps)


def _layers_for_thesis_disturbance(args: argparse.Namespace) -> int:
    """The fewest --layers that take the thesis' disturbance whole: its pulse's layer to
    evaluate --gains; to optimise, one more per free gain plus one (feedback's horizon
    rule: 64 for all three gains)."""
    if args.gains is not None:
        return _thesis_last_layer()
    fixed = sum(v is not None for v in (args.fix_kp, args.fix_ki, args.fix_kd))
    return _thesis_last_layer() + max(3 - fixed, 1) + 1


def run(args: argparse.Namespace) -> int:
    from icefab.feedback import (MAX_LAYERS, UNIT_CIRCLE_TOL, Disturbance, evaluate_gains,
                                 tune_gains)

    job = job_from_args(args)
    n_layers = int(_number(args.layers, "--layers", integer=True, lo=1, hi=MAX_LAYERS))
    pulses = tuple(_at(t, "--pulse", n_layers) for t in args.pulse)
    steps = tuple(_at(t, "--step", n_layers) for t in args.step)
    noise = 0.0 if args.noise is None else _number(args.noise, "--noise", lo=0.0)
    seed = int(_number(args.seed, "--seed", integer=True, lo=0))
    if not pulses and not steps and args.noise is None:
        needed = _layers_for_thesis_disturbance(args)
        if n_layers < needed:   # it dropped the pulse (and the step) and tuned against nothing
            raise ConfigError(f"--layers {n_layers}: the thesis' disturbance has its pulse at "
                              f"layer {_thesis_last_layer()}; give --layers {needed} or more, "
                              "or your own --pulse, --step or --noise")
        dist = Disturbance(n_layers=n_layers)   # its defaults are the thesis' disturbance
    else:
        dist = Disturbance(n_layers=n_layers, pulses=pulses, steps=steps, noise=noise,
                           seed=seed)
    fb = job.feedback
    fix: dict[str, float] = {}
    for name, val in (("kp", args.fix_kp), ("ki", args.fix_ki), ("kd", args.fix_kd)):
        if val is not None:
            fix[name] = float(getattr(fb, name)) if val == "job" else \
                _number(val, f"--fix-{name}", lo=0.0)
    if len(fix) == 3:
        raise ConfigError("--fix-kp, --fix-ki and --fix-kd hold every gain: nothing to "
                          "optimise; evaluate them with --gains KP,KI,KD")
    if args.gains is not None:
        if fix:
            raise ConfigError("--gains evaluates given gains; it cannot be combined with "
                              "--fix-kp/--fix-ki/--fix-kd")
        result = evaluate_gains(_triple(args.gains, "--gains"), dist)
        mode = "given, not optimised"
    else:
        start = _triple(args.start, "--start")
        result = tune_gains(dist, x0=start, fix=fix, constrained=not args.unconstrained,
                            pole_margin=_pole_margin(args))
        mode = "optimised" + (f" (fixed: {', '.join(fix)})" if fix else "")
        if result.converged_by_check:   # SLSQP's own flag said no: say why it is taken
            mode += (f"; the optimiser stopped ({result.message.split(';')[0]}) at a point "
                     "that a restart and probes around it could not better")
        if not result.converged:   # they were called "optimised" (hunt P)
            mode = (f"not optimised: the optimiser stopped after {result.iterations} "
                    f"iterations, {result.message.rstrip('.')}; try another --start")
    data = result.as_dict()
    # gains the optimiser did not reach are no result: a script must not take them for
    # the optimum (hunt P), so nothing is written and the exit status says so
    failed = args.gains is None and not result.converged
    if args.out and not failed:
        with output_dir(args.out, "tune") as tmp, warnings.catch_warnings():
            if result.diverges:  # huge values expected: matplotlib's overflow notes are noise
                warnings.simplefilter("ignore", RuntimeWarning)
            plot_error_response(result, dist, job, tmp / "error_response.png", mode)
            (tmp / "tune.json").write_text(json.dumps(
                {"format": "icefab-tune", "version": 1, **data, "mode": mode,
                 "n_layers": n_layers, "pulses": dist.pulses,
                 "steps": dist.steps, "noise": dist.noise, "seed": dist.seed}, indent=2,
                allow_nan=False) + "\n")
    if args.json:  # rms is null when the response diverges: strict JSON, no Infinity
        print(json.dumps(data, allow_nan=False))
        return _not_converged(args) if failed else 0
    print(f"gains ({mode}): Kp = {_gain(result.kp)}, Ki* = {_gain(result.ki)}, "
          f"Kd* = {_gain(result.kd)}")
    repeated = result.repeated_pole
    if repeated is not None:   # its computed modulus may be 1 + 1e-8: the rounding's
        print(f"RMS error sigma_p*: none, the error response diverges (a repeated pole at "
              f"z = {repeated:g} on the unit circle grows without bound)")
    elif result.diverges and result.max_pole > 1.0:
        print(f"RMS error sigma_p*: none, the error response diverges (a pole at "
              f"|z| = {result.max_pole:.10g} > 1 grows without bound)")
    elif result.diverges:
        print("RMS error sigma_p*: none, too large to compute (the disturbance's size)")
    else:
        print(f"RMS error sigma_p* = {result.rms:.4g} measurement intervals over {n_layers} "
              "layers")
    on_circle = not result.stable and abs(result.max_pole - 1.0) <= UNIT_CIRCLE_TOL
    verdict = ("UNSTABLE (a repeated pole on the unit circle: its error diverges)"
               if repeated is not None else
               "UNSTABLE (marginal: a pole on the unit circle, its error never decays)"
               if on_circle else "stable" if result.stable else "UNSTABLE")
    print(f"{verdict}: largest pole modulus {_gain(result.max_pole)}")
    if failed:
        return _not_converged(args)
    if args.out:
        print(f"wrote {args.out}/error_response.png, {args.out}/tune.json", file=sys.stderr)
    return 0


def _not_converged(args: argparse.Namespace) -> int:
    """Exit status 1 for an optimisation that did not converge, with a line on stderr."""
    kept = f"; nothing written to {args.out}" if args.out else ""
    print(f"icefab tune: the optimiser did not converge{kept} (exit status 1)",
          file=sys.stderr)
    return 1


