"""Long fuzz run of the inputs a user gives icefab: meshes, TOML jobs, legacy control files.

    python3 bench/fuzz_inputs.py [--cases 10000] [--seed 0] [--classes mesh,toml,legacy]

Every case is generated from (class, seed, index) alone, so any reported case can be
re-run by index (``--only CLASS:INDEX``). Cases run in a worker process under
``RLIMIT_AS`` = 2 GiB (an allocation beyond it fails: counted as a memory failure) with
a 20 s limit per case, enforced by the parent (it kills and restarts a worker that does
not answer in time: counted as a hang, whether Python or a compiled kernel is stuck).

Outcomes per case: ``ok`` (a result), ``refused`` (an IcefabError with one line),
``traceback`` (any other exception, or an IcefabError of several lines), ``warning`` (ok
or refused, but a Python or numpy warning reached the terminal on the way), ``memory``
(MemoryError under the limit), ``hang``, ``crash`` (the worker died). The issue's goal
(issue 10): 0 traceback, 0 warning, 0 memory, 0 hang, 0 crash. Counts go to
BENCHMARKS.md.

What a case does:
* mesh: a valid small file (binary/ASCII STL, PLY in three encodings, OBJ) mutated
  (byte edits, float bit flips, truncation, inflated counts, token swaps, random bytes),
  then ``load_mesh``; a mesh that loads is placed (``prepare_parts``: units, stroke,
  reach) and sliced at 1 mm layers.
* toml: a job of random settings and values (numbers of every size, NaN, inf, strings,
  lists) or the default job's TOML with corrupted bytes, through ``load_job``.
* legacy: the thesis' Table 3-1 or the paper's Table 1 with tokens replaced by numbers,
  words, inf/nan/1e400, lines dropped or repeated, through ``load_job``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import select
import struct
import subprocess
import sys
import tempfile
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
LIMIT_AS = 2 << 30          # bytes of address space per worker
TIMEOUT_S = 20.0            # per case
CLASSES = ("mesh", "toml", "legacy")

# The legacy tables of tests/test_config_legacy.py (a bench must not need the tests).
PAPER_TABLE_1 = """\
1	[int] Number of STL and/or PLY files to import (> 0)
jamesmcgill.stl	[char char] STL and/or PLY file names (no spaces within each name)
0	[1/0 (on/off)] inexact option: used to indicate if common vertices for adjacent triangular facets are not identical
2	[1/2/3] Slicing option: 1, boundary paths are found; 2, boundary and fill paths are formed; 3, 2D option
1	[1/0 (on/off)] scaffolding option
1e-4	[float] Tolerance value for comparing floating-point data (>0)
1.5 1.5 [mm]	[float float] [part support] Deposition path width (> 0)
0.4 [mm]	[float] Slice thickness (> 0)
45 [deg]	[float] Max. angle between path segments that is considered to be smooth (> 0)
0 0 0 0	[1/0 float float float] [(on/off) Sx Sy Sz] Scaling vector (> 0)
1 -90 0 0 [deg]	[1/0 float float float] [(on/off) Rx Ry Rz] Rotation vector (1-2-3 Euler angles)
0 0 0 0 [mm]	[(1/0) Tx Ty Tz] [(on/off) Tx Ty Tz] Translation vector
0 1	[float float] [min max] Part fraction to slice: [0 1] indicates the entire part
0 1	[float float] [min max] Scaffolding subset
1 1 1	[int int int] [p1 p2 p3] Part copy vector: p3 part copies will be built, laid out in a grid
5 [mm]	[float] Scaffolding buffer
"""
THESIS_TABLE_3_1 = """\
CAD PARTS
2	[int] (>0) Number of STL and/or PLY files to import
body.stl handle.ply	[char char] STL and/or PLY file names; no spaces are allowed within each name
COMPUTATION
4	number of CPUs to use in parallel computations
SLICING CONTROL
1.5 1.2 [mm]	[float float] (> 0) [part scaffolding] deposition path width
0.25 [mm]	[float] (> 0) slice thickness
30 [deg]	[float] (> 0) maximum angle between adjacent path segments that is considered to be smooth
3.3 [mm]	[float] Scaffolding buffer
PART TRANSFORMATION
1 2 2 2	[1/0 float float float] (> 0) [(on/off) Sx Sy Sz] Scaling vector
1 -85 0 0 [deg]	[1/0 float float float] [(on/off) Rx Ry Rz] Rotation vector
3 1 2	[int int int] (1-3) Rotation axis order
1 cent orig 5 [mm]	[1/0 float float float] [(on/off) Tx Ty Tz] Translation vector
REFERENCE FRAMES
260 -100 [mm]	[float float] [EEx EEy] origin of the end effector (EE) frame in the Cobra 600 base frame
-0.1 -0.3 [mm]	[float float] [Wx Wy] origin of the water building frame in the EE frame
0.2 8.2 [mm]	[float float] [SCx SCy] origin of the scaffolding building frame in the EE frame
-30 19 [mm]	[float float] [Mx My] origin of the laser measurement frame in the EE frame
"""

WORDS = ["inf", "-inf", "nan", "NaN", "1e400", "-1e400", "1e-400", "0", "-0", "1", "2", "-1",
         "2.5", "1e30", "1e-300", "5e-324", "9" * 40, "cent", "orig", "x.stl", "[mm]",
         "(> 0)", "", "true", "\"", "[", "]", "{", "=", "#", "\\u0000", "\x00", "é", "\t"]


# --------------------------------------------------------------------------- generators


def _valid_meshes() -> dict[str, bytes]:
    """Small valid files of a 30 x 20 x 10 mm box in every format icefab reads."""
    import trimesh
    box = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
    v = np.asarray(box.vertices, np.float32)
    f = np.asarray(box.faces)
    head = ["ply", "format {fmt} 1.0", f"element vertex {len(v)}", "property float x",
            "property float y", "property float z", f"element face {len(f)}",
            "property list uchar int vertex_indices", "end_header"]

    def ply(fmt: str) -> bytes:
        text = ("\n".join(head) + "\n").replace("{fmt}", fmt).encode()
        if fmt == "ascii":
            body = "".join(f"{x} {y} {z}\n" for x, y, z in v.tolist())
            body += "".join(f"3 {a} {b} {c}\n" for a, b, c in f.tolist())
            return text + body.encode()
        e = "<" if fmt == "binary_little_endian" else ">"
        faces = np.zeros(len(f), [("n", "u1"), ("i", e + "i4", (3,))])
        faces["n"] = 3
        faces["i"] = f
        return text + v.astype(e + "f4").tobytes() + faces.tobytes()

    obj = "".join(f"v {x} {y} {z}\n" for x, y, z in v.tolist())
    obj += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f.tolist())
    return {"stl": trimesh.exchange.stl.export_stl(box),
            "stl-ascii": trimesh.exchange.stl.export_stl_ascii(box).encode(),
            "ply-le": ply("binary_little_endian"), "ply-be": ply("binary_big_endian"),
            "ply-ascii": ply("ascii"), "obj": obj.encode()}


def gen_mesh(rng: np.random.Generator, valid: dict[str, bytes]) -> tuple[bytes, str]:
    """Mutated mesh bytes and a file extension."""
    name = list(valid)[int(rng.integers(len(valid)))]
    data = bytearray(valid[name])
    ext = rng.choice([".stl", ".ply", ".obj", ".bin"]) if rng.random() < 0.2 else \
        "." + name.split("-")[0]
    kind = int(rng.integers(7))
    if kind == 0:  # byte edits
        for _ in range(int(rng.integers(1, 9))):
            at = int(rng.integers(len(data)))
            data[at] = int(rng.integers(256))
    elif kind == 1 and name == "stl":  # float bit flips in facets
        for _ in range(int(rng.integers(1, 4))):
            at = 84 + 50 * int(rng.integers(12)) + 12 + 4 * int(rng.integers(9))
            (w,) = struct.unpack_from("<I", data, at)
            struct.pack_into("<I", data, at, w ^ (1 << int(rng.integers(32))))
    elif kind == 2:  # truncation
        data = data[:int(rng.integers(len(data) + 1))]
    elif kind == 3:  # inflated counts
        if name == "stl":
            struct.pack_into("<I", data, 80, int(rng.choice([0, 13, 2**31 - 1, 2**32 - 1,
                                                             int(rng.integers(2**32))])))
        else:
            text = bytes(data)
            for key in (b"element vertex 8", b"element face 12"):
                n = rng.choice([b"0", b"-1", b"99999999999", b"4294967296", b"1e9", b"nan"])
                text = text.replace(key, key.rsplit(b" ", 1)[0] + b" " + n)
            data = bytearray(text)
    elif kind == 4 and name in ("stl-ascii", "ply-ascii", "obj"):  # token swaps
        words = bytes(data).split(b" ")
        for _ in range(int(rng.integers(1, 6))):
            words[int(rng.integers(len(words)))] = str(rng.choice(WORDS)).encode()
        data = bytearray(b" ".join(words))
    elif kind == 5:  # random bytes after a real start
        cut = int(rng.integers(min(len(data), 200)))
        data = data[:cut] + bytearray(rng.integers(0, 256, int(rng.integers(0, 2000)),
                                                   dtype=np.uint8).tobytes())
    else:  # whole lines repeated or dropped (text) / facets duplicated (binary STL)
        if name == "stl":
            k = int(rng.integers(1, 2000))
            body = bytes(data[84:134]) * k
            data = bytearray(data[:80]) + struct.pack("<I", 12 + k) + data[84:] + body
        else:
            lines = bytes(data).split(b"\n")
            for _ in range(int(rng.integers(1, 5))):
                i = int(rng.integers(len(lines)))
                if rng.random() < 0.5:
                    del lines[i]
                else:
                    lines.insert(i, lines[int(rng.integers(len(lines)))])
            data = bytearray(b"\n".join(lines))
    return bytes(data), str(ext)


def _toml_value(rng: np.random.Generator):
    kind = int(rng.integers(8))
    if kind == 0:
        return str(rng.choice(["nan", "inf", "-inf", "1e400", "-1e400", "1e-300", "0", "-0.0"]))
    if kind == 1:
        return f"{rng.uniform(-9.9, 9.9):.3f}e{int(rng.integers(-330, 308))}"
    if kind == 2:
        return str(int(rng.integers(-2**62, 2**62)) * int(rng.choice([1, 10**6])))
    if kind == 3:
        return str(rng.choice(["true", "false"]))
    if kind == 4:
        return '"' + str(rng.choice(["cent", "orig", "", "3d", "hybrid", "/dev/zero", "x"])) + '"'
    if kind == 5:
        return "[" + ", ".join(_toml_value(rng) for _ in range(int(rng.integers(0, 5)))) + "]"
    if kind == 6:
        return repr(float(rng.normal(0, 100)))
    return str(int(rng.integers(-5, 200)))


def gen_toml(rng: np.random.Generator, names: list[str], default: bytes) -> bytes:
    if rng.random() < 0.3:
        data = bytearray(default)
        for _ in range(int(rng.integers(1, 8))):
            at = int(rng.integers(len(data)))
            data[at:at + 1] = bytes(rng.integers(0, 256, int(rng.integers(0, 4)),
                                                 dtype=np.uint8))
        return bytes(data)
    out = []
    for _ in range(int(rng.integers(1, 7))):
        name = names[int(rng.integers(len(names)))]
        if rng.random() < 0.05:
            name = name + "x"
        *table, key = name.split(".")
        out.append(f"[{'.'.join(table)}]\n{key} = {_toml_value(rng)}\n")
    return "".join(out).encode()


def gen_legacy(rng: np.random.Generator) -> bytes:
    lines = (PAPER_TABLE_1 if rng.random() < 0.5 else THESIS_TABLE_3_1).splitlines()
    for _ in range(int(rng.integers(1, 7))):
        i = int(rng.integers(len(lines)))
        words = lines[i].replace("\t", " ").split(" ")
        j = int(rng.integers(len(words)))
        if rng.random() < 0.6:
            words[j] = str(rng.choice(WORDS))
        else:
            words[j] = f"{rng.uniform(-9.9, 9.9):.3f}e{int(rng.integers(-330, 410))}"
        lines[i] = " ".join(words)
    if rng.random() < 0.2 and lines:
        del lines[int(rng.integers(len(lines)))]
    if rng.random() < 0.1:
        lines.insert(int(rng.integers(len(lines) + 1)), lines[int(rng.integers(len(lines)))])
    return ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass")


# --------------------------------------------------------------------------- worker


def _worker() -> None:  # pragma: no cover - runs in the subprocess
    from icefab import Job
    from icefab.config import load_job, to_toml
    from icefab.errors import IcefabError
    from icefab.mesh import load_mesh, prepare_parts
    from icefab.slicing import slice_mesh
    import dataclasses

    valid = _valid_meshes()
    names = []

    def walk(obj, prefix=""):
        for f in dataclasses.fields(obj):
            v = getattr(obj, f.name)
            if dataclasses.is_dataclass(v):
                walk(v, prefix + f.name + ".")
            else:
                names.append(prefix + f.name)
    walk(Job())
    default = to_toml(Job()).encode()
    work = Path(tempfile.mkdtemp(prefix="icefab-fuzz-"))
    # warm up the compiled kernels so their one-off compilation is not timed as a hang
    (work / "warm.stl").write_bytes(valid["stl"])
    job = Job().replace(**{"parts.files": [str(work / "warm.stl")],
                           "slicing.layer_thickness_mm": 1.0, "cell.cpus": 1})
    slice_mesh(prepare_parts(job), job)
    print("ready", flush=True)
    for line in sys.stdin:
        cls, seed, index = line.split()
        rng = np.random.default_rng([int(seed), CLASSES.index(cls), int(index)])
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            try:
                if cls == "mesh":
                    data, ext = gen_mesh(rng, valid)
                    f = work / f"case{ext}"
                    f.write_bytes(data)
                    load_mesh(f)
                    job = Job().replace(**{"parts.files": [str(f)], "cell.cpus": 1,
                                           "slicing.layer_thickness_mm": 1.0})
                    slice_mesh(prepare_parts(job), job)
                else:
                    data = gen_toml(rng, names, default) if cls == "toml" else gen_legacy(rng)
                    f = work / ("job.toml" if cls == "toml" else "control.txt")
                    f.write_bytes(data)
                    load_job(f)
                outcome, detail = "ok", ""
            except IcefabError as exc:
                msg = str(exc)
                outcome, detail = ("refused", "") if "\n" not in msg.strip() else \
                    ("traceback", "multi-line message: " + msg[:200])
            except MemoryError:
                outcome, detail = "memory", ""
            except Exception as exc:  # noqa: BLE001 - counting what escapes is the point
                outcome, detail = "traceback", f"{type(exc).__name__}: {str(exc)[:200]}"
        if said and outcome in ("ok", "refused"):
            # a numpy or Python warning on the user's terminal is a defect too
            w = said[0]
            outcome = "warning"
            detail = f"{w.category.__name__} at {Path(w.filename).name}:{w.lineno}: " \
                     f"{str(w.message)[:160]}"
        dt = time.perf_counter() - t0
        print(json.dumps([outcome, detail, dt]), flush=True)


def _limit() -> None:  # pragma: no cover - runs in the child before exec
    resource.setrlimit(resource.RLIMIT_AS, (LIMIT_AS, LIMIT_AS))


class Runner:
    """One worker subprocess at a time; restarted after a hang or a crash."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker"], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env,
                                     preexec_fn=_limit)
        line = self.proc.stdout.readline()
        if line.strip() != "ready":
            raise RuntimeError(f"worker did not start: {line!r}")

    def run(self, cls: str, seed: int, index: int) -> tuple[str, str, float]:
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        self.proc.stdin.write(f"{cls} {seed} {index}\n")
        self.proc.stdin.flush()
        ready, _, _ = select.select([self.proc.stdout], [], [], TIMEOUT_S)
        if not ready:
            self.stop()
            return "hang", f"no answer in {TIMEOUT_S:g} s", TIMEOUT_S
        line = self.proc.stdout.readline()
        if not line:
            code = self.proc.wait()
            self.proc = None
            return "crash", f"worker exit status {code}", 0.0
        outcome, detail, dt = json.loads(line)
        return outcome, detail, dt

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000, help="cases per class")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--classes", default=",".join(CLASSES))
    ap.add_argument("--only", help="CLASS:INDEX: run one case and print its outcome")
    ap.add_argument("--json", help="write the counts here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        _worker()
        return
    runner = Runner()
    if args.only:
        cls, index = args.only.split(":")
        print(runner.run(cls, args.seed, int(index)))
        runner.stop()
        return
    results: dict[str, dict] = {}
    try:
        for cls in args.classes.split(","):
            counts: Counter[str] = Counter()
            bad: list[tuple[int, str, str]] = []
            slowest = 0.0
            t0 = time.perf_counter()
            for i in range(args.cases):
                outcome, detail, dt = runner.run(cls, args.seed, i)
                counts[outcome] += 1
                slowest = max(slowest, dt)
                if outcome not in ("ok", "refused"):
                    bad.append((i, outcome, detail))
                    print(f"{cls}:{i} {outcome} {detail}", file=sys.stderr, flush=True)
            wall = time.perf_counter() - t0
            results[cls] = {"cases": args.cases, **{k: counts.get(k, 0) for k in
                            ("ok", "refused", "traceback", "warning", "memory", "hang",
                                      "crash")},
                            "slowest_case_s": round(slowest, 3), "wall_s": round(wall, 1),
                            "failures": bad[:50]}
            r = results[cls]
            print(f"{cls}: {args.cases} cases in {wall:.0f} s: ok {r['ok']}, refused "
                  f"{r['refused']}, traceback {r['traceback']}, warning {r['warning']}, "
                  f"memory > 2 GiB {r['memory']}, hang > {TIMEOUT_S:g} s {r['hang']}, "
                  f"crash {r['crash']}; "
                  f"slowest case {slowest:.2f} s", flush=True)
    finally:
        runner.stop()
    if args.json:
        Path(args.json).write_text(json.dumps({"seed": args.seed, "limit_as_bytes": LIMIT_AS,
                                               "timeout_s": TIMEOUT_S, "results": results},
                                              indent=1))


if __name__ == "__main__":
    main()
