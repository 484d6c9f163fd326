"""The demo mug: closed, watertight, the right size and volume, with holes and overhang."""
from __future__ import annotations

import math

import numpy as np
import trimesh

from icefab.demo import (HANDLE_OFFSET_MM, HANDLE_RADIUS_MM, HANDLE_TUBE_MM, MUG_HEIGHT_MM,
                         MUG_RADIUS_MM, demo_job, demo_mug, demo_mug_volume_estimate)
from icefab.mesh import check_mesh


def test_mug_is_watertight_and_small():
    mug = demo_mug()
    report = check_mesh(mug)
    assert report.watertight, report
    assert report.volume > 0
    assert mug.faces.dtype == np.int64 and mug.vertices.dtype == np.float64
    assert 1000 < mug.n_faces < 50_000


def test_mug_size():
    lo, hi = demo_mug().bounds
    assert lo[2] == 0.0
    assert math.isclose(hi[2] - lo[2], 125.0, rel_tol=1e-6)
    # round body of ~80 mm diameter; handle to +x
    assert math.isclose(hi[1] - lo[1], 2 * MUG_RADIUS_MM, rel_tol=1e-6)
    assert math.isclose(lo[0], -MUG_RADIUS_MM, rel_tol=1e-6)
    assert math.isclose(hi[0], HANDLE_OFFSET_MM + HANDLE_RADIUS_MM + HANDLE_TUBE_MM,
                        rel_tol=1e-3)


def test_mug_volume_matches_analytic_estimate():
    mug = demo_mug()
    estimate = demo_mug_volume_estimate()
    # 96-gon bodies and the handle/body junction: within 1 %
    assert abs(check_mesh(mug).volume - estimate) < 0.01 * estimate
    # an independent library agrees with our volume
    tm = trimesh.Trimesh(mug.vertices, mug.faces, process=False)
    assert tm.is_watertight
    assert math.isclose(tm.volume, check_mesh(mug).volume, rel_tol=1e-9)


def _section_rings(tm, z):
    """Shapely polygons of the closed rings of a section at height z, with containment."""
    from shapely.geometry import Polygon
    sec = tm.section(plane_origin=[0, 0, z], plane_normal=[0, 0, 1])
    rings = [Polygon(d[:, :2]) for d in sec.discrete]
    inside = [sum(1 for j, o in enumerate(rings) if j != i and o.contains(r))
              for i, r in enumerate(rings)]
    return rings, inside


def test_mug_has_through_hole_and_open_top():
    mug = demo_mug()
    tm = trimesh.Trimesh(mug.vertices, mug.faces, process=False)
    # genus 1 (handle through-hole) -> Euler characteristic 0
    assert tm.euler_number == 0
    # mid-height: body outer ring, the cavity nested in it, the handle's outer arc (its
    # inner arc lies in the cavity and was cut away)
    rings, inside = _section_rings(tm, 62.5)
    assert len(rings) == 3
    assert sorted(inside) == [0, 0, 1]
    # near the rim the cavity is still a hole: the top is open
    rings, inside = _section_rings(tm, MUG_HEIGHT_MM - 0.5)
    assert sorted(inside) == [0, 1]
    # the bottom is solid
    rings, inside = _section_rings(tm, 3.0)
    assert inside == [0]
    # the handle's lower arc overhangs: downward-facing faces well above the base
    normals = tm.face_normals
    centres = tm.triangles_center
    assert np.any((normals[:, 2] < -0.7) & (centres[:, 2] > 20.0)
                  & (centres[:, 0] > MUG_RADIUS_MM))


def test_demo_job_is_default():
    from icefab.config import Job
    assert demo_job() == Job()


def test_shipped_mug_is_the_manifold3d_build():
    """The demo mug ships as data (no Boolean operations at run time); it is exactly what
    manifold3d builds (manifold3d, a runtime dependency for hole closing)."""
    from icefab.demo import build_demo_mug

    shipped, built = demo_mug(), build_demo_mug()
    assert np.array_equal(shipped.vertices, built.vertices)
    assert np.array_equal(shipped.faces, built.faces)
    assert shipped.vertices.dtype == np.float64 and shipped.faces.dtype == np.int64
