"""Fuzz the three result-file loaders (stack, toolpaths, trajectories) with crafted files.

For each loader, N crafted files (default 10 000) are made from a small good file by one
or more seeded mutations:

* ``bytes``: random bytes flipped and/or the file truncated (zip, zlib and npy damage);
* ``member``: members replaced by arrays of any dtype and shape (NaN, infinities,
  extremes), dropped, joined by unknown members, or single values perturbed (codes out of
  range, negative offsets, NaN coordinates);
* ``header``: ``format``, ``version`` and ``job`` replaced by wrong types or text
  (``"x"``, ``"[slicing\\n"``, another format, a future version);
* ``bomb``: a member whose npy header promises 10^13 rows, or a 3 GiB member of zeros
  (3 MB deflated) added unused or put in place of a used member.

Each case is loaded in this process with a 20 s alarm, and with the address space limited
(``RLIMIT_AS``) to what the process had before the first case plus 2 GB, so any allocation
over 2 GB fails with MemoryError and is counted (untouched memory counts too, unlike RSS).
Counted: loads, StackFileError (the documented error), tracebacks (any other exception),
warnings (a Python or numpy warning on the way), hangs (over 20 s) and allocations over
2 GB; the first few tracebacks and warnings are printed. The exit status is 1 if any
traceback, warning, hang or large allocation occurred.

    python3 bench/fuzz_results.py [--cases 10000] [--seed 1] [--only stack]
"""

from __future__ import annotations

import argparse
import io
import platform
import resource
import signal
import sys
import tempfile
import time
import traceback
import warnings
import zipfile
import zlib
from collections import Counter
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))

from icefab.errors import StackFileError  # noqa: E402
import test_resultfiles as fixtures  # noqa: E402  (the small good files of the unit tests)

HANG_S = 20
BIG_BYTES = 2 << 30
ZERO_BYTES = 3 << 30


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


def _members(data: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _random_array(rng: np.random.Generator) -> np.ndarray:
    ndim = int(rng.integers(0, 4))
    shape = tuple(int(x) for x in rng.integers(0, 7, ndim))
    kind = rng.integers(0, 8)
    n = int(np.prod(shape)) if shape else 1
    if kind == 0:
        a = rng.normal(0, 1e3, n)
        special = rng.random(n) < 0.2
        a[special] = rng.choice([np.nan, np.inf, -np.inf, 1e300, -1e300, 0.0], special.sum())
    elif kind == 1:
        a = rng.integers(-2**62, 2**62, n, dtype=np.int64)
    elif kind == 2:
        a = rng.integers(-128, 128, n).astype(np.int8)
    elif kind == 3:
        a = rng.integers(0, 2**16, n).astype(np.uint16)
    elif kind == 4:
        a = rng.random(n) < 0.5
    elif kind == 5:
        a = np.array([str(x) for x in rng.integers(0, 999, n)], dtype="<U4")
    elif kind == 6:
        a = (rng.normal(size=n) + 1j * rng.normal(size=n)).astype(np.complex64)
    else:
        a = rng.integers(-2, 50, n).astype(np.int64)
    return a.reshape(shape)


def _mutate_members(members: dict[str, np.ndarray], rng: np.random.Generator
                    ) -> dict[str, np.ndarray]:
    out = dict(members)
    names = sorted(members)
    for _ in range(int(rng.integers(1, 4))):
        name = names[int(rng.integers(len(names)))]
        what = rng.choice(["replace", "drop", "add", "perturb", "perturb", "perturb"])
        if what == "drop":
            out.pop(name, None)
        elif what == "add":
            out[f"extra{int(rng.integers(99))}"] = _random_array(rng)
        elif what == "replace":
            out[name] = _random_array(rng)
        elif name in out and out[name].dtype.kind in "fiub" and out[name].size:
            a = out[name].copy()
            i = int(rng.integers(a.size))
            if a.dtype.kind == "f":
                a.flat[i] = rng.choice([np.nan, np.inf, -np.inf, 1e300, -1.0, 0.0,
                                        a.flat[i] * 1e6, a.flat[i] + 1])
            elif a.dtype.kind == "b":
                a.flat[i] = not a.flat[i]
            else:
                info = np.iinfo(a.dtype)
                v = [-1, 0, 1, 99, info.max, info.min, int(a.flat[i]) + 1,
                     int(a.flat[i]) - 1][int(rng.integers(8))]
                a.flat[i] = min(max(v, info.min), info.max)
            out[name] = a
    return out


def _header(members: dict[str, np.ndarray], rng: np.random.Generator) -> dict[str, np.ndarray]:
    out = dict(members)
    name = rng.choice(["format", "version", "job"])
    out[name] = np.array(rng.choice([
        "x", "[slicing\n", "icefab-stack", "icefab-toolpaths", "icefab-trajectories", "",
        "[slicing]\nlayer_thickness_mm = -1\n", "[cell]\ncpus = 1e300\n", "[nope]\n"]))
    if rng.random() < 0.4:
        out[name] = np.array(rng.choice([1, 2, 3, 99, -1, 2**40]))
    return out


def _save(members: dict[str, np.ndarray], path: Path) -> None:
    np.savez_compressed(path, **members)


def _promise(members: dict[str, np.ndarray], victim: str, path: Path) -> None:
    """Member ``victim``'s npy header promises 10^13 rows; its data stays small."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for k, v in members.items():
            b = io.BytesIO()
            if k == victim:
                np.lib.format.write_array_header_1_0(
                    b, {"descr": v.dtype.str, "fortran_order": False,
                        "shape": (10**13,) + v.shape[1:]})
                b.write(v.tobytes())
            else:
                np.lib.format.write_array(b, v)
            z.writestr(k + ".npy", b.getvalue())


def _write_zeros(z: zipfile.ZipFile, name: str) -> None:
    """A 3 GiB float64 npy of zeros as member ``name``, streamed from memory (deflated to
    a few MB)."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        head, {"descr": "<f8", "fortran_order": False, "shape": (ZERO_BYTES // 8,)})
    chunk = bytes(64 << 20)
    with z.open(name, "w", force_zip64=True) as fh:
        fh.write(head.getvalue())
        for _ in range(ZERO_BYTES // len(chunk)):
            fh.write(chunk)


def _zero_bombs(members: dict[str, np.ndarray], tmp: Path, kind: str,
                rng: np.random.Generator) -> list[Path]:
    """Files holding a 3 GiB zero member: unused, and in place of one used member
    (deflating 3 GiB takes seconds, so these are made once and loaded repeatedly)."""
    names = sorted(members)
    out = []
    for j, victim in enumerate([None, names[int(rng.integers(len(names)))]]):
        path = tmp / f"bomb-{kind}-{j}.npz"
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as z:
            for k, v in members.items():
                if k == victim:
                    _write_zeros(z, k + ".npy")
                else:
                    b = io.BytesIO()
                    np.lib.format.write_array(b, v)
                    z.writestr(k + ".npy", b.getvalue())
            if victim is None:
                _write_zeros(z, "unused.npy")
        out.append(path)
    return out


def run(kind: str, cases: int, seed: int, tmp: Path, bomb: bool) -> Counter:
    make, save, load = fixtures.KINDS[kind]
    good = tmp / f"{kind}.npz"
    save(make(), good)
    data = good.read_bytes()
    members = _members(data)
    # crc32, not hash(): str hashes change with every process (PYTHONHASHSEED), and with
    # them the cases of a seed
    rng = np.random.default_rng([seed, zlib.crc32(kind.encode()) % 1000])
    counts: Counter = Counter()
    shown = 0
    path = tmp / f"crafted-{kind}.npz"
    bombs = _zero_bombs(members, tmp, kind, rng) if bomb else []
    t_start = time.perf_counter()
    for i in range(cases):
        r = rng.random()
        target = path
        if r < 0.3:
            b = bytearray(data[:int(rng.integers(1, len(data) + 1))])
            for _ in range(int(rng.integers(1, 8))):
                b[int(rng.integers(len(b)))] = int(rng.integers(256))
            path.write_bytes(bytes(b))
            cls = "bytes"
        elif r < 0.8:
            _save(_mutate_members(members, rng), path)
            cls = "member"
        elif r < 0.95 or not bomb:
            _save(_header(members, rng), path)
            cls = "header"
        else:
            cls = "bomb"
            if rng.random() < 0.5:
                _promise(members, sorted(members)[int(rng.integers(len(members)))], path)
                target = path
            else:
                target = bombs[int(rng.integers(len(bombs)))]
        counts["class " + cls] += 1
        signal.alarm(HANG_S + 5)
        t0 = time.perf_counter()
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            try:
                load(target)
                counts["loaded"] += 1
            except StackFileError as exc:
                counts["StackFileError"] += 1
                if "\n" in str(exc) or str(target) not in str(exc):
                    counts["error not one line naming the file"] += 1
            except _Hang:
                counts["hangs"] += 1
            except MemoryError:
                counts["allocations > 2 GB"] += 1
            except Exception:
                counts["tracebacks"] += 1
                if shown < 3:
                    shown += 1
                    print(f"--- {kind} case {i} ({cls}): traceback", file=sys.stderr)
                    traceback.print_exc()
            finally:
                signal.alarm(0)
        if said:  # a Python or numpy warning on the user's terminal is a defect too
            counts["warnings"] += 1
            if shown < 3:
                shown += 1
                w = said[0]
                print(f"--- {kind} case {i} ({cls}): {w.category.__name__} at "
                      f"{Path(w.filename).name}:{w.lineno}: {w.message}", file=sys.stderr)
        dt = time.perf_counter() - t0
        if dt > HANG_S:
            counts["hangs"] += 1
        counts["max_case_ms"] = max(counts["max_case_ms"], int(dt * 1000))
    counts["seconds"] = int(time.perf_counter() - t_start)
    return counts


def _address_space() -> int:
    """The process' current virtual memory size, bytes (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize in /proc/self/status (Linux only)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", choices=sorted(fixtures.KINDS))
    ap.add_argument("--no-bomb", action="store_true", help="skip the 3 GiB member cases")
    args = ap.parse_args(argv)
    signal.signal(signal.SIGALRM, _alarm)
    print(f"# fuzz_results: {args.cases} cases per loader, seed {args.seed}, "
          f"{platform.python_version()}, numpy {np.__version__}, "
          f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    bad = 0
    with tempfile.TemporaryDirectory(prefix="icefab-fuzz-results-") as tmp:
        tmp = Path(tmp)
        vm = _address_space()
        resource.setrlimit(resource.RLIMIT_AS, (vm + BIG_BYTES, resource.RLIM_INFINITY))
        print(f"# address space before the first case {vm >> 20} MB; limit + 2048 MB")
        for kind in ([args.only] if args.only else sorted(fixtures.KINDS)):
            c = run(kind, args.cases, args.seed, tmp, not args.no_bomb)
            bad += c["tracebacks"] + c["warnings"] + c["hangs"] + c["allocations > 2 GB"] \
                + c["error not one line naming the file"]
            print(f"{kind}: " + ", ".join(f"{k} {v}" for k, v in sorted(c.items())))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
