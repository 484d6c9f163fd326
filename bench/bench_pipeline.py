"""The whole pipeline through the CLI, as a user runs it: mesh -> valve programs (issue 17).

For each part, runs ``icefab slice``, ``icefab paths``, ``icefab plan`` and ``icefab valves``
one after the other (each reads the previous one's file), each as its own process, and
prints per command the wall time, the peak resident memory of the command and its worker
processes (``wait4``'s ``ru_maxrss``: the largest of the process and its reaped children)
and the size of what it wrote; then the whole.

    python3 bench/bench_pipeline.py [bunny] [rocker-arm] [mug] [--keep DIR]

``bunny`` and ``rocker-arm`` are the ~1 M-facet, 300 mm benchmark meshes of
``bench/meshes.py`` (built once, with trimesh); ``mug`` is the demo mug (written by
``icefab demo --layers 2``'s STL). The job is the default Cobra 600 cell with the
end-effector origin at (340, 0) mm for the 300 mm parts (at the default origin they leave
joint 1's range) and a 400 mm stroke (they are taller than the Cobra's 210 mm); for every
part ``flow.out_of_range = "clamp"`` (the default fill leaves SMF no headroom).

The peer, in the same run: PrusaSlicer's whole G-code job on the same mesh (Debian's
``prusa-slicer``, ``apt-get install prusa-slicer``; skipped with a line when it is not
installed): 0.25 mm layers, 100 % rectilinear infill, support material on, a 400 x 400 x
400 mm build volume, its own threads on both cores.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

#: The 300 mm parts: origin (340, 0) keeps them in joint 1's range, and the stroke is
#: raised from the Cobra's 210 mm so that they fit (as in bench_adaptive and bench_fitting).
JOB_300MM = "[cell]\nee_origin_mm = [340.0, 0.0]\nstroke_mm = 400.0\n\n"
#: Every part: the valve programs clamp what the valve cannot give (the default job's fill at
#: 125 mm/s leaves no room for SMF's 30 % and 'icefab valves' refuses it, naming this).
JOB_ALL = "[flow]\nout_of_range = \"clamp\"\n"
STEPS = (("slice", "stack.npz"), ("paths", "toolpaths.npz"), ("plan", "trajectories.npz"),
         ("valves", "valves"))


def _size(p: Path) -> int:
    if p.is_file():
        return p.stat().st_size
    return sum(f.stat().st_size for f in p.rglob("*") if f.is_file())


#: Runs a command (argv[2:]) and writes its peak RSS (kB, wait4: it and its reaped
#: children) to the file descriptor argv[1].
#: A small process of its own starts the command: a child forked straight from this one
#: would count this process's resident memory (the meshes it built, 0.6 GB) in its peak,
#: since Linux carries the peak across the exec.
_LAUNCH = ("import os, sys\n"
           "pid = os.fork()\n"
           "if pid == 0:\n"
           "    os.execvp(sys.argv[2], sys.argv[2:])\n"
           "_, status, usage = os.wait4(pid, 0)\n"
           "os.write(int(sys.argv[1]), str(usage.ru_maxrss).encode())\n"
           "sys.exit(os.waitstatus_to_exitcode(status))\n")


def _run(cmd: list[str], cwd: Path) -> tuple[float, float]:
    """Wall s and peak RSS GB of a command and its reaped children; RuntimeError with the
    command's error line if it fails."""
    r, w = os.pipe()
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", _LAUNCH, str(w), *cmd], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, pass_fds=(w,))
    os.close(w)
    out = proc.stdout.read()
    proc.wait()
    wall = time.perf_counter() - t0
    with os.fdopen(r, "rb") as fh:
        peak_kb = int(fh.read() or 0)
    if proc.returncode:
        errors = [ln for ln in out.decode(errors="replace").splitlines() if "error:" in ln]
        raise RuntimeError(errors[-1] if errors else out.decode(errors="replace")[-500:])
    return wall, peak_kb / 1e6  # kB -> GB


def _part(name: str, root: Path) -> tuple[Path, str]:
    """The mesh file of a part and its job text."""
    if name == "mug":
        subprocess.run([sys.executable, "-m", "icefab", "demo", "--layers", "2",
                        "--sim-layers", "0", "-o", str(root / "mug-demo")], check=True,
                       stdout=subprocess.DEVNULL)
        return root / "mug-demo" / "demo-mug.stl", ""
    from meshes import big_mesh
    return big_mesh(name), JOB_300MM


def run_part(name: str, root: Path) -> None:
    mesh, job_text = _part(name, root)
    d = root / name
    d.mkdir()
    job = d / "job.toml"
    job.write_text(job_text + JOB_ALL)
    print(f"## {name}: {mesh.name} ({mesh.stat().st_size / 1e6:.0f} MB)")
    print("| command | wall s | peak memory GB | output |")
    print("| --- | --- | --- | --- |")
    total = 0.0
    peak = 0.0
    src = mesh
    for cmd, out in STEPS:
        args = [sys.executable, "-m", "icefab", cmd, str(src), "-c", str(job), "-o",
                str(d / cmd)]
        try:
            wall, gb = _run(args, d)
        except RuntimeError as exc:  # refused (a budget, a setting): the rest cannot run
            print(f"| `icefab {cmd}` | refused | | {exc} |")
            run_peer(mesh, d)
            return
        total += wall
        peak = max(peak, gb)
        written = d / cmd / out
        print(f"| `icefab {cmd}` | {wall:.1f} | {gb:.2f} | {out} {_size(written) / 1e6:.1f} MB"
              + (f" in {sum(1 for _ in written.glob('*'))} files" if written.is_dir() else "")
              + " |", flush=True)
        src = written
    print(f"| whole | **{total:.1f}** | **{peak:.2f}** | |")
    run_peer(mesh, d)


def run_peer(mesh: Path, d: Path) -> None:
    """PrusaSlicer's whole job on the mesh (module docstring), as one more table row."""
    exe = shutil.which("prusa-slicer")
    if exe is None:
        print("| peer: PrusaSlicer | not installed (apt-get install prusa-slicer) | | |")
        return
    lines = subprocess.run([exe, "--help"], capture_output=True, text=True).stdout
    version = next((ln.split(" ")[0] for ln in lines.splitlines()
                    if ln.startswith("PrusaSlicer-")), "PrusaSlicer")
    out = d / "peer.gcode"
    args = [exe, "--export-gcode", "--output", str(out), "--layer-height", "0.25",
            "--first-layer-height", "0.25", "--bed-shape", "0x0,400x0,400x400,0x400",
            "--max-print-height", "400", "--center", "200,200", "--fill-density", "100%",
            "--fill-pattern", "rectilinear", "--support-material", str(mesh)]
    try:
        wall, gb = _run(args, d)
    except RuntimeError as exc:
        print(f"| peer: {version} | failed | | {exc} |")
        return
    print(f"| peer: {version}, whole G-code job | {wall:.1f} | {gb:.2f} | G-code "
          f"{_size(out) / 1e6:.1f} MB |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("parts", nargs="*", default=["bunny"],
                    choices=["bunny", "rocker-arm", "mug"])
    ap.add_argument("--keep", type=Path, help="keep the outputs here")
    args = ap.parse_args()
    root = args.keep or Path(tempfile.mkdtemp(prefix="icefab-pipeline-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"# machine: {os.uname().machine}, {os.cpu_count()} cores, Python "
          f"{sys.version.split()[0]}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"load average {os.getloadavg()[0]:.1f}")
    try:
        for name in args.parts:
            run_part(name, root)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)


if __name__ == "__main__":
    main()
