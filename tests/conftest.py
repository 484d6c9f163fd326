"""Shared test fixtures: where the real meshes are, and hypothesis profiles."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]
# The real meshes live in the shared folder beside the repository (../shared/meshes).
MESH_DIR = Path(os.environ.get("ICEFAB_MESHES", REPO.parent / "shared" / "meshes"))

settings.register_profile("ci", max_examples=100, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=30, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("ci" if os.environ.get("CI") else "dev")


@pytest.fixture(scope="session")
def mesh_dir() -> Path:
    if not MESH_DIR.is_dir():
        pytest.fail(f"real meshes not found at {MESH_DIR}; set ICEFAB_MESHES")
    return MESH_DIR
