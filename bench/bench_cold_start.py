"""``icefab demo`` on a fresh install: wall time with empty numba caches, then warm.

Issue 10 ("Silence and slowness a user meets first"): the first run of the demo compiles
every numba kernel it uses. This benchmark makes what a user's fresh install is: the
tracked files of this checkout (``git ls-files``) copied to a new folder (no
``__pycache__``, so no numba cache), a new virtual environment there
(``--system-site-packages``: the dependencies are the machine's, so no network; icefab
itself installed with ``pip install --no-deps -e .``, its build environment from PyPI; the
install compiles the kernels, ``tools/icefab_build.py``, and its time is printed), then runs
``icefab demo`` twice: first (as a user's first run after the install) and again. For each run it prints the
wall time, the CPU time of the process tree, the machine's load average, and the time at
which each output line appeared (stdout and stderr, with ``ICEFAB_COMPILE_NOTICE=1`` so
the compile notice shows).

    python3 bench/bench_cold_start.py [--keep DIR] [--demo-args "--sim-layers 60"]

The machine is shared: wall times grow with the load average printed beside them; the CPU
time does not.
"""
from __future__ import annotations

import argparse
import os
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _copy_tracked(dst: Path) -> None:
    names = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], check=True,
                           capture_output=True).stdout.decode().split("\0")
    for name in filter(None, names):
        if not (REPO / name).is_file():
            continue
        (dst / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, dst / name)


def _run_timed(cmd: list[str], cwd: Path, env: dict) -> tuple[float, float, list[str]]:
    """Wall s, CPU s of the children, and the output lines with their times."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, bufsize=1)
    lines = []
    for line in proc.stdout:
        lines.append(f"{time.perf_counter() - t0:7.1f} s  {line.rstrip()}")
    rc = proc.wait()
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    if rc != 0:
        print("\n".join(lines[-20:]))
        raise SystemExit(f"{' '.join(cmd)}: exit {rc}")
    return wall, cpu, lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="make the fresh install here and keep it")
    ap.add_argument("--demo-args", default="", help="extra arguments for icefab demo")
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="icefab-cold-"))
    repo = root / "icefab"
    repo.mkdir(parents=True)
    _copy_tracked(repo)
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(venv)],
                   check=True)
    py = venv / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHONPATH", "NUMBA_"))}
    assert not list(repo.rglob("*.nbi"))
    # the editable install compiles the kernels (tools/icefab_build.py): its time counts
    load = os.getloadavg()[0]
    wall, cpu, lines = _run_timed([str(py), "-m", "pip", "install", "-v", "--no-deps", "-e",
                                   str(repo)], root, env)
    said = [ln for ln in lines if "icefab:" in ln]
    print(f"## install (pip install -e, kernels compiled in it): wall {wall:.1f} s, CPU "
          f"{cpu:.1f} s, load average {load:.1f}; {len(list(repo.rglob('*.nbi')))} numba "
          "cache index files after it")
    for line in said:
        print("   ", line)
    env["ICEFAB_COMPILE_NOTICE"] = "1"
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    for label in ("first", "again"):
        out = root / f"demo-{label}"
        load = os.getloadavg()[0]
        wall, cpu, lines = _run_timed([str(venv / "bin" / "icefab"), "demo", "-o", str(out),
                                       *shlex.split(args.demo_args)], root, env)
        print(f"## {label}: wall {wall:.1f} s, CPU {cpu:.1f} s (process tree), load average "
              f"{load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end; "
              f"{len(list(repo.rglob('*.nbi')))} numba cache index files after it")
        for line in lines:
            if "%," not in line or "100 %" in line:  # stage ends, not every progress step
                print("   ", line)
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
