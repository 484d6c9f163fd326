"""The first run's numba compiling is said plainly on stderr, and nothing when cached."""
from __future__ import annotations

import io
import os
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import numba
import numpy as np
import pytest

from icefab.cli.compiling import FIRST_LINE, compile_notice


def test_compiling_is_announced_once_and_summarised():
    @numba.njit  # a fresh function: compiled on its first call, never cached
    def twice(a):
        return a * 2

    @numba.njit
    def thrice(a):
        return a * 3

    err = io.StringIO()
    with compile_notice(err, interval_s=1e9) as notice:
        twice(np.arange(3))
        thrice(np.arange(3.0))
        twice(np.arange(3))  # already compiled: not counted
    lines = err.getvalue().splitlines()
    assert lines[0] == FIRST_LINE
    assert notice.kernels == 2
    assert lines[-1].startswith("compiled 2 numba kernels in ") and "cached" in lines[-1]
    assert len(lines) == 2


def test_nothing_is_said_when_nothing_compiles():
    @numba.njit
    def once(a):
        return a + 1

    once(1)
    err = io.StringIO()
    with compile_notice(err) as notice:
        assert once(2) == 3
    assert err.getvalue() == "" and notice.kernels == 0


ROOT = Path(__file__).resolve().parents[1]


def test_the_build_environment_holds_every_dependency():
    """The editable install compiles the kernels in pip's build environment: it needs the
    package's dependencies, at the same bounds (so it resolves the numba the install
    resolves, and its cache is the install's)."""
    meta = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    requires = set(meta["build-system"]["requires"])
    missing = [d for d in meta["project"]["dependencies"] if d not in requires]
    assert not missing, f"add to [build-system] requires: {missing}"
    assert meta["build-system"]["build-backend"] == "icefab_build"
    assert (ROOT / meta["build-system"]["backend-path"][0] / "icefab_build.py").is_file()


def _backend():
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import icefab_build
    finally:
        sys.path.remove(str(ROOT / "tools"))
    return icefab_build


def test_a_failed_warm_up_only_warns(monkeypatch, capsys):
    """The install never fails for the warm-up: it says so and the first run compiles."""
    backend = _backend()
    monkeypatch.setattr(backend, "WARM_UP", "import sys; sys.exit('no numba here')")
    assert backend.compile_kernels(ROOT) is False
    said = capsys.readouterr().err
    assert "kernels not compiled ahead (exit 1: no numba here)" in said
    assert "the first run compiles them" in said


@pytest.mark.slow
def test_after_the_install_warm_up_the_demo_compiles_nothing(tmp_path, monkeypatch, capsys):
    icefab_build = _backend()
    cache = tmp_path / "numba-cache"  # an empty cache, not the one the other tests share
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    assert icefab_build.compile_kernels(ROOT)
    said = capsys.readouterr().err
    n = int(re.search(r"compiled (\d+) numba kernels ahead", said).group(1))
    assert n >= 20, said
    (tmp_path / "one.toml").write_text("[cell]\ncpus = 1\n")  # every kernel in one process
    r = subprocess.run([sys.executable, "-m", "icefab", "demo", "-c", "one.toml", "-o", "d",
                        "--layers", "12", "--sim-layers", "8"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=600,
                       env={**os.environ, "ICEFAB_COMPILE_NOTICE": "1"})
    assert r.returncode == 0, r.stderr
    assert FIRST_LINE not in r.stderr, r.stderr      # nothing left to compile


def test_the_sdist_carries_the_build_backend(tmp_path):
    """pyproject.toml's backend lives in tools/: an sdist without it builds no wheel."""
    import shutil
    import tarfile

    # a clean copy: an egg-info left by an earlier build would list the files for it
    src = tmp_path / "src-copy"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(
        "*.egg-info", "__pycache__", ".venv", ".git", "build", "dist", ".cache",
        "icefab-demo", ".hypothesis", ".pytest_cache"))
    code = ("import sys; sys.path.insert(0, 'tools'); import icefab_build; "
            f"print(icefab_build.build_sdist({str(tmp_path)!r}))")
    r = subprocess.run([sys.executable, "-c", code], cwd=src, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    with tarfile.open(tmp_path / r.stdout.strip().splitlines()[-1]) as tar:
        names = tar.getnames()
    assert any(n.endswith("/tools/icefab_build.py") for n in names)
    assert any(n.endswith("/src/icefab/data/demo_mug.npz") for n in names)
