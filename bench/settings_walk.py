"""Every numeric setting at both ends of its range, on the demo mug (issue 10).

    python3 bench/settings_walk.py [--layers 8] [--timeout 60] [--out walk.jsonl]
                                   [--ends lo,hi,lo+]

A float setting whose range starts at 0 (0 is usually "off") is also run just above it
(end ``lo+``, 1e-300): the "on" branch with a degenerate amount (a fill smoothed within
1e-96 mm once turned rings inside out and asked for all memory).

For each numeric setting of :mod:`icefab.config` (each element of a pair or triple on its
own, the others at their defaults) and each end of its declared range, a job file that
sets only that value is written and ``icefab demo -c JOB --layers N --sim-layers N`` is
run in a subprocess under ``RLIMIT_AS`` = 2 GiB and a wall-clock limit. The demo runs
every stage: placement, slicing, scaffold, paths, minimum-time trajectories, valve
programs and the simulator open loop and with SMF (``--layers`` keeps the first N layers
after slicing so one run takes seconds, not the demo's minutes; slicing and the checks
before it see the whole mug).

Outcomes: ``works`` (exit 0 within the limits), ``refused`` (exit 2 with one line on
stderr naming the setting or what is wrong), ``failed`` (anything else: a traceback,
MemoryError under the 2 GiB limit, a kill by the timeout), ``warned`` (exit 0 or 2, but a
Python or numpy warning on stderr on the way). Each case is appended to the
JSONL file as it finishes, so a partial run still reports what it saw. ``cell.cpus`` is
set to 1 in every case (two cores are shared) except when it is the setting walked.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
import typing
from pathlib import Path

LIMIT_AS = 2 << 30
#: The value just above a range that starts at 0 (end ``lo+``).
TINY = 1e-300


def numeric_settings():
    """(dotted name, element index or None, lo, hi, default) of every numeric setting."""
    from icefab import Job
    out = []

    def walk(obj, prefix=""):
        hints = typing.get_type_hints(type(obj))
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            name = prefix + f.name
            if dataclasses.is_dataclass(v):
                walk(v, name + ".")
                continue
            if hints[f.name] is bool:
                continue
            lo, hi = f.metadata.get("lo"), f.metadata.get("hi")
            if isinstance(v, tuple):
                for i, x in enumerate(v):
                    if isinstance(x, (int, float)) and not isinstance(x, bool):
                        out.append((name, i, lo, hi, v))
            elif isinstance(v, (int, float)):
                out.append((name, None, lo, hi, v))
    walk(Job())
    return out


def _toml(name: str, value) -> str:
    *table, key = name.split(".")
    if isinstance(value, (list, tuple)):
        text = "[" + ", ".join(json.dumps(x) for x in value) + "]"
    else:
        text = json.dumps(value)
    return f"[{'.'.join(table)}]\n{key} = {text}\n"


def _limit() -> None:  # pragma: no cover - runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (LIMIT_AS, LIMIT_AS))


def run_case(job_text: str, layers: int, timeout: float, work: Path) -> dict:
    job = work / "job.toml"
    job.write_text(job_text)
    out = work / "out"
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-m", "icefab", "demo", "-c", str(job), "-o",
                            str(out), "--layers", str(layers), "--sim-layers", str(layers)],
                           capture_output=True, text=True, timeout=timeout, preexec_fn=_limit,
                           env=dict(os.environ, NUMBA_NUM_THREADS="1"))
    except subprocess.TimeoutExpired:
        return {"outcome": "failed", "why": f"timeout {timeout:g} s",
                "seconds": round(time.perf_counter() - t0, 1)}
    dt = round(time.perf_counter() - t0, 1)
    err = [line for line in p.stderr.splitlines() if line.strip()]
    last = err[-1] if err else ""
    # a Python or numpy warning ("file.py:12: RuntimeWarning: ...") is a defect too
    warned = [line for line in err if re.search(r":\d+: \w*Warning: ", line)]
    if warned and p.returncode in (0, 2):
        return {"outcome": "warned", "why": warned[0][:300], "seconds": dt}
    if p.returncode == 0:
        return {"outcome": "works", "seconds": dt}
    if p.returncode == 2 and ": error: " in last and "Traceback" not in p.stderr:
        return {"outcome": "refused", "why": last, "seconds": dt}
    return {"outcome": "failed", "why": f"exit {p.returncode}: {last[:300]}", "seconds": dt}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--layers", type=int, default=8)
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--out", default="settings_walk.jsonl")
    ap.add_argument("--only", help="a substring of the setting names to walk")
    ap.add_argument("--ends", default="lo,hi,lo+",
                    help="which ends to run: lo, hi, lo+ (just above a range starting at 0)")
    ap.add_argument("--first", default="layer_thickness,parts.scale,fill_width,measure_spacing,"
                    "max_piece_s,tick_s,dt_s,buffer_mm,speed_mm_s,point_spacing,grid_mm,"
                    "copies,reach_mm,debris_rate,noise_mm,layer_scale,cpus",
                    help="walk settings whose names contain these first (issue 10's list)")
    args = ap.parse_args()
    done = set()
    out = Path(args.out)
    if out.exists():
        done = {(r["setting"], r["end"]) for r in map(json.loads, out.read_text().splitlines())}
    with tempfile.TemporaryDirectory(prefix="icefab-walk-") as tmp:
        work = Path(tmp)
        base = run_case("[cell]\ncpus = 1\n", args.layers, 600.0, work)
        print(f"defaults: {base}", flush=True)
        first = [w for w in args.first.split(",") if w]
        order = sorted(numeric_settings(),
                       key=lambda c: next((k for k, w in enumerate(first) if w in c[0]),
                                          len(first)))
        for name, i, lo, hi, default in order:
            if args.only and args.only not in name:
                continue
            label = name if i is None else f"{name}[{i}]"
            value_type = type(default if i is None else default[i])
            ends = [("lo", lo), ("hi", hi)]
            if lo == 0 and value_type is float:
                ends.append(("lo+", TINY))
            for end, bound in ends:
                if (label, end) in done or end not in args.ends.split(","):
                    continue
                if bound is None:
                    rec = {"outcome": "failed", "why": "no bound declared"}
                else:
                    value = bound
                    if i is not None:
                        value = list(default)
                        value[i] = bound
                    if i is not None:
                        value = [float(x) if isinstance(d, float) else x
                                 for x, d in zip(value, default)]
                        value[i] = type(default[i])(bound)
                    else:
                        value = type(default)(bound)
                    text = _toml(name, value)
                    if not name.startswith("cell."):
                        text += "[cell]\ncpus = 1\n"
                    elif name != "cell.cpus":
                        text = text.replace("[cell]\n", "[cell]\ncpus = 1\n", 1)
                    rec = run_case(text, args.layers, args.timeout, work)
                rec.update(setting=label, end=end, value=bound)
                with out.open("a") as fh:
                    fh.write(json.dumps(rec) + "\n")
                print(f"{label} {end}={bound}: {rec['outcome']} {rec['seconds'] if 'seconds' in rec else ''} "
                      f"{rec.get('why', '')[:160]}", flush=True)


if __name__ == "__main__":
    main()
