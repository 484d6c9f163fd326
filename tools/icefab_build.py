"""icefab's build backend: setuptools', and at an editable install (``pip install -e .``,
the README's set-up) the numba kernels compiled into the checkout, so that a fresh
install's first ``icefab`` command loads them instead of compiling them for a minute
(issue 10: ``icefab demo`` within 30 s on a fresh install).

numba caches a compiled kernel beside its source (``src/icefab/__pycache__``) under the
source file's time stamp and size, the numba version and the CPU. An editable install runs
the checkout's sources, so what compiles here is what the first run finds, provided the
build environment's numba is the installed one: both resolve the newest version
``pyproject.toml`` allows (its ``[build-system] requires`` lists the package's
dependencies for this). Anything else (another numba, a failed warm-up) only means the
first run compiles as it would have: the install never fails for it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from setuptools import build_meta as _setuptools
from setuptools.build_meta import *  # noqa: F401,F403 - the other PEP 517 hooks as they are

WARM_UP = "from icefab.cli.warm_up import warm_up_main; warm_up_main()"
#: Longest the warm-up may take, s (about a minute on 2 cores).
WARM_UP_TIMEOUT_S = 900


def build_editable(wheel_directory, config_settings=None, metadata_directory=None):
    name = _setuptools.build_editable(wheel_directory, config_settings, metadata_directory)
    compile_kernels(Path.cwd())
    return name


def compile_kernels(checkout: Path) -> bool:
    """Run :func:`icefab.cli.warm_up.warm_up` on the checkout's sources; says on stderr
    what happened (pip shows it with ``-v``). False when it did not work."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(checkout / "src")] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    print("icefab: compiling the numba kernels for the first run (about a minute)...",
          file=sys.stderr, flush=True)
    try:
        r = subprocess.run([sys.executable, "-c", WARM_UP], cwd=checkout,
                           env=env, capture_output=True, text=True, timeout=WARM_UP_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as exc:
        print(f"icefab: kernels not compiled ahead ({exc}); the first run compiles them",
              file=sys.stderr)
        return False
    if r.returncode:
        tail = (r.stderr or r.stdout).strip().splitlines()[-1:] or ["no output"]
        print(f"icefab: kernels not compiled ahead (exit {r.returncode}: {tail[0]}); the "
              "first run compiles them", file=sys.stderr)
        return False
    print(r.stdout.strip(), file=sys.stderr)
    return True
