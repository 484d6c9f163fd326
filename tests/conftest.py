"""Shared test fixtures: where the real meshes are, and hypothesis profiles."""
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

settings.register_profile("ci", max_examples=100, deadline=None,
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
