"""Smooth contours (icefab.fitting; Zhang & Liou III): fitted rings against the exact
section, measured independently (shapely's Hausdorff distance, trimesh's cross-sections),
corners kept, straight runs straight, and the slicer's setting."""
from __future__ import annotations

import math

import manifold3d as m3
import numpy as np
import pytest
import shapely
import trimesh
from hypothesis import given, settings, strategies as st

from icefab.config import Job, job_from_dict
from icefab.core import Mesh, signed_area
from icefab.errors import ConfigError
from icefab.fitting import fit_ring, fit_rings
from icefab.slicing import slice_mesh

FIT = job_from_dict({"slicing": {"fit_contours": True}})


def mesh_of(solid) -> Mesh:
    m = solid.to_mesh()
    return Mesh(np.asarray(m.vert_properties)[:, :3].astype(np.float64),
                np.asarray(m.tri_verts).astype(np.int64), name="manifold")


def turns_deg(ring: np.ndarray) -> np.ndarray:
    a = ring - np.roll(ring, 1, axis=0)
    b = np.roll(ring, -1, axis=0) - ring
    return np.degrees(np.abs(np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
                                        np.einsum("ij,ij->i", a, b))))


def star(radii) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * math.pi, len(radii), endpoint=False)
    r = np.asarray(radii)
    return np.c_[r * np.cos(t), r * np.sin(t)]


@settings(max_examples=80, deadline=None, derandomize=True)
@given(radii=st.lists(st.floats(2.0, 30.0), min_size=3, max_size=60),
       tol=st.sampled_from([0.005, 0.02, 0.05]), corner=st.floats(10.0, 120.0),
       spacing=st.floats(0.1, 2.0))
def test_fit_stays_within_tolerance(radii, tol, corner, spacing):
    """Any star-shaped ring: the fitted ring is within tol of it both ways (Hausdorff, by
    shapely), keeps every input point, its orientation and its corners, and samples at
    most ``spacing`` apart."""
    ring = star(radii)
    fit = fit_ring(ring, tol, corner, spacing)
    h = shapely.hausdorff_distance(shapely.LinearRing(fit), shapely.LinearRing(ring),
                                   densify=0.05)
    assert h <= tol * (1 + 1e-9) + 1e-12
    near = np.min(np.hypot(*(ring[:, None, :] - fit[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert near.max() < 1e-9  # the section's own points are on the curve
    assert np.sign(signed_area(fit)) == np.sign(signed_area(ring))
    gaps = np.hypot(*(np.roll(fit, -1, axis=0) - fit).T)
    assert gaps.max() <= spacing * (1 + 1e-9)
    # corners: the curve passes through them (above) and leaves along the chords, so the
    # samples turn there by nearly the whole angle (the chord to the next sample cuts the
    # curve's first bend: up to 8 degrees less in 3 000 random rings); a rounded corner
    # would spread the turn over many samples
    sharp = turns_deg(ring) > corner
    for p, turn in zip(ring[sharp], turns_deg(ring)[sharp]):
        i = int(np.argmin(np.hypot(*(fit - p).T)))
        assert turns_deg(fit)[i] > turn - 10.0


def test_straight_runs_stay_straight_and_corners_sharp():
    """A box section: the fit is the rectangle itself (area to 1e-9), its four corners."""
    rect = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 10.0], [0.0, 10.0]])
    fit = fit_ring(rect, 0.02)
    assert signed_area(fit) == pytest.approx(200.0, abs=1e-9)
    assert np.sort(turns_deg(fit))[-4:] == pytest.approx([90.0] * 4)
    assert np.sort(turns_deg(fit))[:-4].max() < 1e-9


def test_faceting_is_smoothed():
    """A 256-gon (a finely meshed circle of radius 30, 1.4 degree turns at its vertices and
    none between): the fit lies on the true circle (within 1e-6 mm) and turns evenly, its
    curvature (turn per mm) everywhere within 1 % of the circle's 1/30 mm^-1."""
    t = np.linspace(0.0, 2.0 * math.pi, 256, endpoint=False)
    ring = 30.0 * np.c_[np.cos(t), np.sin(t)]
    fit = fit_ring(ring, 0.02, spacing=0.4)
    assert np.abs(np.hypot(*fit.T) - 30.0).max() < 1e-6
    chord = np.hypot(*(np.roll(fit, -1, axis=0) - fit).T)
    curvature = np.radians(turns_deg(fit)) / (0.5 * (chord + np.roll(chord, 1)))
    assert np.abs(curvature * 30.0 - 1.0).max() < 0.01


SOLIDS = {
    "coarse cylinder": lambda: m3.Manifold.cylinder(6.0, 20.0, 20.0, 16),
    "coarse sphere": lambda: m3.Manifold.sphere(15.0, 24).translate([0.0, 0.0, 15.0]),
    "box": lambda: m3.Manifold.cube([20.0, 10.0, 3.0]),
}


@pytest.mark.parametrize("name", list(SOLIDS))
def test_sliced_contours_within_the_bound_of_the_exact_section(name):
    """Every fitted ring of every layer within slicing.fit_tolerance_mm of the mesh's exact
    cross-section at its height, computed by trimesh (independent of the slicer)."""
    mesh = mesh_of(SOLIDS[name]())
    stack = slice_mesh(mesh, FIT)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    worst = 0.0
    for layer in stack:
        sec = tm.section(plane_origin=[0.0, 0.0, layer.z], plane_normal=[0.0, 0.0, 1.0])
        exact = shapely.MultiLineString([np.asarray(e) for e in sec.discrete])
        for ring in layer.part.rings:
            worst = max(worst, shapely.hausdorff_distance(shapely.LinearRing(ring), exact,
                                                          densify=0.01))
    assert worst <= FIT.slicing.fit_tolerance_mm
    # and the default slicer is untouched by the setting's existence
    plain = slice_mesh(mesh, Job())
    assert len(plain) == len(stack)


def test_fit_settings_are_checked():
    for key, value in (("fit_tolerance_mm", 0.0), ("fit_tolerance_mm", 0.5),
                       ("corner_angle_deg", 0.0), ("corner_angle_deg", 180.0)):
        with pytest.raises(ConfigError, match=f"slicing.{key}"):
            job_from_dict({"slicing": {key: value}})
    with pytest.raises(ValueError, match="tolerance"):
        fit_ring(star([1.0, 2.0, 3.0]), 0.0)


def sliver(amp, k, gap, n1, n2, phase) -> np.ndarray:
    """A ring between two sinusoids ``gap`` mm apart over x = 0..20 mm, their points
    ``n1`` and ``n2`` (every other one of the upper side shifted by ``phase`` of a step),
    counter-clockwise (a review's generator)."""
    x1, x2 = np.linspace(0.0, 20.0, n1), np.linspace(0.0, 20.0, n2)
    x2 = np.unique(np.clip(x2 + phase * (x2[1] - x2[0]) * (np.arange(n2) % 2), 0.0, 20.0))
    ring = np.r_[np.c_[x1, amp * np.sin(k * x1)], np.c_[x2, amp * np.sin(k * x2) + gap][::-1]]
    return ring if signed_area(ring) > 0 else ring[::-1]


#: the review's sliver 153 (0.046 mm wide), whose fit at 0.02 mm crossed itself
SLIVER_153 = (2.5360357699991627, 0.27175457777310924, 0.04580220355777543, 15, 32,
              0.19686311476052654)


def _simple_within(ring, fit, tol):
    """The fit is simple (shapely), a valid polygon, within ``tol`` of the ring both ways,
    through the ring's points and turning its way."""
    assert shapely.LinearRing(fit).is_simple and shapely.Polygon(fit).is_valid
    h = shapely.hausdorff_distance(shapely.LinearRing(fit), shapely.LinearRing(ring),
                                   densify=0.01)
    assert h <= tol * (1 + 1e-9)
    near = np.min(np.hypot(*(ring[:, None, :] - fit[None, :, :]).transpose(2, 0, 1)), axis=1)
    assert near.max() < 1e-9
    assert np.sign(signed_area(fit)) == np.sign(signed_area(ring))


def test_a_simple_sliver_stays_simple(monkeypatch):
    """A sinusoidal sliver 0.046 mm wide fitted at 0.02 mm: the curves of its two sides
    crossed (a review's; the slicer then unites its layer). The fit at half the tolerance
    is simple; where none is, the ring itself is kept."""
    import icefab.fitting as fitting

    ring = sliver(*SLIVER_153)
    assert shapely.LinearRing(ring).is_simple
    fit = fit_ring(ring, 0.02)
    _simple_within(ring, fit, 0.02)
    assert len(fit) > 3 * len(ring)                    # a fit, not the ring
    pts, off = fit_rings(np.r_[ring, star([5.0] * 16)], np.array([0, len(ring), len(ring) + 16]),
                         0.02)                         # the slicer's: the same per ring
    np.testing.assert_array_equal(pts[:off[1]], fit)
    np.testing.assert_array_equal(pts[off[1]:], fit_ring(star([5.0] * 16), 0.02))
    monkeypatch.setattr(fitting, "SIMPLE_RETRIES", 0)
    np.testing.assert_array_equal(fit_ring(ring, 0.02), ring)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(amp=st.floats(0.5, 3.0), k=st.floats(0.2, 1.0), gap=st.floats(0.002, 0.05),
       n1=st.integers(8, 40), n2=st.integers(8, 40), phase=st.floats(0.0, 1.0),
       tol=st.sampled_from([0.01, 0.02, 0.05]))
def test_simple_slivers_give_simple_fits(amp, k, gap, n1, n2, phase, tol):
    from hypothesis import assume

    ring = sliver(amp, k, gap, n1, n2, phase)
    assume(shapely.LinearRing(ring).is_simple)
    _simple_within(ring, fit_ring(ring, tol), tol)
