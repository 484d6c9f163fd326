"""Shared test fixtures: where the real meshes are, the valve firmware's host build (the
virtual cell needs it), and hypothesis profiles."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]
# The real meshes ship with the repository, gzip-compressed and read through icefab's own
# loader (tests/data/meshes/README.md: what they are and where they come from). Nothing the
# suite reads lies outside the repository (tests/test_self_contained.py proves it).
MESH_DIR = REPO / "tests" / "data" / "meshes"

# CI's examples are fixed per test (derandomize): a commit's CI gives what its rehearsal
# gave (a full run's new random example failed a test on code that had passed it for
# weeks, and a red CI does not land); local runs ('dev') draw new examples every time
settings.register_profile("ci", max_examples=100, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=30, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture(scope="session")
def mesh_dir() -> Path:
    """The folder of the real test meshes (``NAME.obj.gz``, ``igea.ply.gz``)."""
    if not MESH_DIR.is_dir():
        pytest.fail(f"real meshes not found at {MESH_DIR}: they are part of the repository")
    return MESH_DIR


@pytest.fixture(scope="session")
def firmware_tools() -> None:
    """make and a C compiler, which the virtual cell (``icefab cell serve``, ``icefab build
    --virtual``) needs for the valve firmware's host build. Without them the tests say so
    and are skipped on a user's machine; CI (``.ci/run``, ICEFAB_REQUIRE_FIRMWARE_TOOLS=1)
    installs them and fails instead."""
    from icefab.cell import valve_host

    missing = valve_host.missing_tools()
    if missing:
        msg = (f"{', '.join(missing)} not found: the virtual cell needs the valve firmware's "
               "host build (apt-get install gcc make)")
        if os.environ.get("ICEFAB_REQUIRE_FIRMWARE_TOOLS") == "1":
            pytest.fail(msg)
        pytest.skip(msg)


@pytest.fixture(scope="session")
def firmware_exe(firmware_tools, tmp_path_factory) -> Path:
    """The valve firmware's host build (``valvectl``), compiled once per session."""
    from icefab.cell import valve_host

    return valve_host.build_host(tmp_path_factory.mktemp("fw"))


@pytest.fixture
def plan_ahead_at_once(monkeypatch):
    """The build runner plans the next layer ahead at once instead of on its thread, so
    tests that rely on it having been planned do not depend on the machine's load."""
    from concurrent.futures import Future

    from icefab import build as bmod
    from icefab import sim as simmod

    def plan_now(self, j, action, plan_only=False):
        if j < len(self.motion.layers):
            plan = simmod.plan_layer_motion(self.motion.layers[j], self.job)
            lv = None if plan_only else simmod.layer_valves(plan, self.job, action)
            f = Future()
            f.set_result((plan, lv, lv and self._cell_paths(j, lv), action))
            self._ahead = (j, f)
    monkeypatch.setattr(bmod.Runner, "_prefetch", plan_now)
