"""The demo part: a beer mug with a handle, generated in code (no input file needed).

The mug exercises what a slicer must get right: an open cup (a solid bottom, then a ring
with a hole in every layer above it), a handle that forms a through-hole with the body
(nested contours: two outer rings and holes), and the lower arc of the handle, which
overhangs and needs scaffold. Built with manifold3d (exact, watertight Boolean operations,
:func:`build_demo_mug`) and shipped as data (``icefab/data/demo_mug.npz``, 31 kB), so
the demo needs no Boolean operations at run time; the tests check the data against a fresh
build.

Dimensions (mm): body outer radius 40, wall 4, bottom 6, height 125; handle: a torus of
centre-line radius 30 and tube radius 7 in the x-z plane, its centre 45 mm from the axis
at mid height, so it sticks out about 42 mm from the body.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from icefab.config import Job
from icefab.core import Mesh
from icefab.errors import ConfigError

MUG_HEIGHT_MM = 125.0
MUG_RADIUS_MM = 40.0
MUG_WALL_MM = 4.0
MUG_BOTTOM_MM = 6.0
HANDLE_RADIUS_MM = 30.0      # centre-line radius of the handle ring
HANDLE_TUBE_MM = 7.0         # radius of the handle's circular cross-section
HANDLE_OFFSET_MM = 45.0      # distance of the ring centre from the mug axis
HANDLE_Z_MM = 62.5           # height of the ring centre


DEMO_SEGMENTS = 96
_DATA = Path(__file__).resolve().parent / "data" / "demo_mug.npz"


def demo_mug(segments: int = DEMO_SEGMENTS) -> Mesh:
    """A closed, watertight beer mug, about 125 mm tall and 80 mm in diameter (+ handle).

    segments: number of segments around the body and the handle ring (the handle tube
        uses a third of it); the default mug is read from the package data, another
        count is built with :func:`build_demo_mug` (needs manifold3d). The mug stands on
        z = 0, its axis is the z axis, the handle points to +x. Returns a Mesh (vertices
        float64 mm, faces int64), < 50k faces for segments <= 128.
    """
    if isinstance(segments, bool) or not isinstance(segments, (int, np.integer)) \
            or not 3 <= segments <= 4096:
        # demo_mug("96") was manifold3d's TypeError, 10**9 asked for all memory
        raise ConfigError(f"demo_mug: segments = {segments!r}: expected a whole number "
                          "from 3 to 4096")
    if segments != DEMO_SEGMENTS:
        return build_demo_mug(int(segments))
    with np.load(_DATA, allow_pickle=False) as data:
        vertices = np.ascontiguousarray(data["vertices"], dtype=np.float64)
        faces = np.ascontiguousarray(data["faces"], dtype=np.int64)
    return Mesh(vertices, faces, "demo-mug")


def build_demo_mug(segments: int = DEMO_SEGMENTS) -> Mesh:
    """The demo mug built with manifold3d (``pip install manifold3d``; the test extra has
    it): how ``icefab/data/demo_mug.npz`` was made, with ``segments`` as in
    :func:`demo_mug`."""
    try:
        import manifold3d as m3
    except ImportError:
        raise ConfigError(f"a demo mug of {segments} segments is built with manifold3d, which "
                          "is not installed (pip install manifold3d); the default "
                          f"{DEMO_SEGMENTS} needs nothing") from None

    body = m3.Manifold.cylinder(MUG_HEIGHT_MM, MUG_RADIUS_MM, MUG_RADIUS_MM, segments)
    cavity_h = MUG_HEIGHT_MM - MUG_BOTTOM_MM + 1.0  # pokes through the top: open cup
    cavity = m3.Manifold.cylinder(cavity_h, MUG_RADIUS_MM - MUG_WALL_MM,
                                  MUG_RADIUS_MM - MUG_WALL_MM, segments)
    cavity = cavity.translate((0.0, 0.0, MUG_BOTTOM_MM))
    tube = m3.CrossSection.circle(HANDLE_TUBE_MM, max(12, segments // 3))
    ring = tube.translate((HANDLE_RADIUS_MM, 0.0)).revolve(segments)  # torus about z
    ring = ring.rotate((90.0, 0.0, 0.0)).translate((HANDLE_OFFSET_MM, 0.0, HANDLE_Z_MM))
    mug = (body + ring) - cavity
    out = mug.to_mesh()
    vertices = np.asarray(out.vert_properties, dtype=np.float64)[:, :3]
    faces = np.asarray(out.tri_verts, dtype=np.int64)
    # manifold3d rounds through float32 on output; snap the base exactly onto z = 0
    vertices[np.abs(vertices[:, 2]) < 1e-4, 2] = 0.0
    return Mesh(np.ascontiguousarray(vertices), np.ascontiguousarray(faces), "demo-mug")


def demo_mug_volume_estimate() -> float:
    """Analytic estimate of the mug volume, mm^3 (round body, handle ring outside it).

    Body: outer cylinder minus cavity. Handle: Pappus' torus volume 2 pi^2 R r^2 times
    the fraction of the centre line lying outside the body (x > body radius).
    """
    body = math.pi * MUG_RADIUS_MM ** 2 * MUG_HEIGHT_MM
    cavity = math.pi * (MUG_RADIUS_MM - MUG_WALL_MM) ** 2 * (MUG_HEIGHT_MM - MUG_BOTTOM_MM)
    torus = 2.0 * math.pi ** 2 * HANDLE_RADIUS_MM * HANDLE_TUBE_MM ** 2
    # centre-line points x = offset + R cos(t) outside the body radius
    c = (MUG_RADIUS_MM - HANDLE_OFFSET_MM) / HANDLE_RADIUS_MM
    fraction = math.acos(c) / math.pi if -1.0 < c < 1.0 else float(c < -1.0)
    return body - cavity + torus * fraction


def demo_job():
    """The default job (Cobra 600 cell) used by ``icefab demo``."""
    return Job()
