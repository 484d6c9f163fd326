"""A fresh clone passes its own tests: the suite and the benchmarks need nothing outside
the repository (issue 10: a user's clone has no ``../shared/``).

Three checks: no tracked file of src/, tests/, bench/ or .ci/ names a place outside the
repository; every data file the tests and benchmarks read is tracked by git (an untracked
file passes here and is missing from a clone); and the tests that read the real meshes pass
in a copy of the tracked files alone, in a temporary folder with nothing beside it, while an
audit hook fails any attempt to open a file of this checkout (other than the package under
test) or of ``../shared``.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
OUTSIDE = re.compile(r"\.\./shared|shared/meshes|\"shared\" */ *\"meshes\"|ICEFAB_MESHES|"
                     r"/work/")


def _tracked() -> list[str]:
    if not (REPO / ".git").exists():
        pytest.skip("not a git checkout (an unpacked archive): which files a clone carries "
                    "cannot be checked here; CI runs from a clone")
    out = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z"], check=True,
                         capture_output=True).stdout.decode()
    return [f for f in out.split("\0") if f]


def test_no_tracked_file_names_a_place_outside_the_repository():
    here = Path(__file__).relative_to(REPO).as_posix()
    found = []
    for name in _tracked():
        if name == here or not name.startswith(("src/", "tests/", "bench/", ".ci/")):
            continue
        if not name.endswith((".py", ".toml", ".cfg", ".ini", ".sh", ".md")) \
                and name != ".ci/run":
            continue
        for no, line in enumerate((REPO / name).read_text(errors="replace").splitlines(), 1):
            if OUTSIDE.search(line):
                found.append(f"{name}:{no}: {line.strip()}")
    assert not found, "\n".join(found)


def test_the_real_meshes_are_tracked_files():
    sys.path.insert(0, str(REPO / "bench"))
    try:
        import meshes as bench_meshes
    finally:
        sys.path.remove(str(REPO / "bench"))
    from conftest import MESH_DIR

    tracked = set(_tracked())
    data = sorted(p.relative_to(REPO).as_posix() for p in MESH_DIR.iterdir())
    assert len([d for d in data if d.endswith(".gz")]) == 6, data
    assert set(data) <= tracked, set(data) - tracked
    for src, _, _ in bench_meshes.SOURCES.values():
        assert (bench_meshes.SOURCE_DIR / src).relative_to(REPO).as_posix() in tracked


AUDIT = '''
import sys
FORBIDDEN = {forbidden!r}
ALLOWED = {allowed!r}

def _hook(event, args):
    if event != "open" or not args or not isinstance(args[0], str):
        return
    path = args[0]
    if any(path.startswith(a) for a in ALLOWED):
        return
    if any(path == f or path.startswith(f + "/") for f in FORBIDDEN):
        with open({log!r}, "a") as log:
            log.write(path + "\\n")
        raise PermissionError(f"the test suite opened {{path}}, outside the clone")

sys.addaudithook(_hook)
'''


def test_real_mesh_tests_pass_in_a_bare_copy_of_the_tracked_files(tmp_path):
    clone = tmp_path / "clone"
    for name in _tracked():
        dst = clone / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, dst)
    assert not (clone.parent / "shared").exists()
    # the package under test is this checkout's src/ (byte-identical to the copy's: it is a
    # copy), so numba's compiled-kernel cache beside it is reused; everything else the
    # tests open must come from the copy
    src = REPO / "src"
    for f in src.rglob("*.py"):
        if (clone / f.relative_to(REPO)).exists():
            assert (clone / f.relative_to(REPO)).read_bytes() == f.read_bytes()
    hooks = tmp_path / "hooks"
    hooks.mkdir()
    log = tmp_path / "opened-outside.txt"
    (hooks / "sitecustomize.py").write_text(AUDIT.format(
        forbidden=[str(REPO), str(REPO.parent / "shared")],
        # the interpreter's own environment may live inside the checkout (the README's
        # .venv/): its installed packages are not the project's files
        allowed=[str(src) + "/", sys.prefix + "/", sys.base_prefix + "/"], log=str(log)))
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("ICEFAB", "PYTEST_XDIST", "PYTEST_CURRENT"))}
    env["PYTHONPATH"] = os.pathsep.join([str(hooks), str(src)])
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
         "tests/test_mesh.py", "-k", "real_meshes_load or igea or teapot"],
        cwd=clone, env=env, capture_output=True, text=True, timeout=900)
    opened = log.read_text() if log.exists() else ""
    assert res.returncode == 0 and not opened, (opened, res.stdout[-3000:], res.stderr[-2000:])
    assert re.search(r"\b8 passed\b", res.stdout), res.stdout[-500:]
