"""The slice command end to end, file formats, and the real meshes."""
from __future__ import annotations

import re

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as hs

import icefab
from icefab.cli import main
from icefab.config import Job
from icefab.slicing import load_stack, slice_mesh, slice_report

EXACT = Job().replace(**{"slicing.min_point_spacing_mm": 0.0,
                         "slicing.max_filter_deviation_mm": 0.0,
                         "slicing.layer_thickness_mm": 0.5})


def _tube() -> trimesh.Trimesh:
    tm = trimesh.creation.annulus(r_min=4, r_max=9, height=6, sections=40)
    tm.apply_translation((0, 0, 3))
    return tm


@pytest.fixture(scope="module")
def tube_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("formats")
    tm = _tube()
    files = {}
    for name, kind, kw in [("bin.stl", "stl", {}), ("ascii.stl", "stl_ascii", {}),
                           ("bin.ply", "ply", {"encoding": "binary"}),
                           ("ascii.ply", "ply", {"encoding": "ascii"}),
                           ("mesh.obj", "obj", {})]:
        p = d / name
        p.write_bytes(_export(tm, kind, kw))
        files[name] = p
    return files


def _export(tm, kind, kw) -> bytes:
    data = tm.export(file_type=kind, **kw)
    return data.encode() if isinstance(data, str) else data


def test_same_stack_from_every_format(tube_files):
    stacks = {}
    for name, p in tube_files.items():
        stacks[name] = slice_mesh(icefab.load_mesh(p), EXACT)
    ref = stacks.pop("bin.stl")
    expected = 0.5 * 40 * np.sin(2 * np.pi / 40) * (81 - 16)
    for L in ref:
        # STL stores float32: compare with a float32-sized tolerance
        assert L.part.area == pytest.approx(expected, rel=1e-6)
    for name, st in stacks.items():
        assert slice_report(st).open_chains == 0, name
        for a, b in zip(ref, st):
            assert b.part.area == pytest.approx(a.part.area, rel=1e-6), name
            assert sorted(b.part.depth().tolist()) == [0, 1]


def test_cli_slice_writes_stack_and_picture(tube_files, tmp_path, capsys):
    out = tmp_path / "out"
    rc = main(["slice", str(tube_files["bin.stl"]), "-o", str(out), "--layers", "0,5,11"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "layers: 24" in text and "contours: 48" in text and "warnings: 0" in text
    st = load_stack(out / "stack.npz")
    assert len(st) == 24
    png = (out / "layers.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_filter_count_says_it_precedes_the_unions(tmp_path, capsys):
    """Overlapping shells make a layer the union of its contours, after the filter: the
    summary's 'contours' and its filter count then differ (a teapot: 432 and 446 points)
    and the filter count says it comes first."""
    a = trimesh.creation.box(extents=(20, 20, 4))
    b = trimesh.creation.box(extents=(20, 20, 4))
    b.apply_translation((10, 0, 0))
    both = trimesh.util.concatenate([a, b])
    both.apply_translation((0, 0, 2))
    both.export(tmp_path / "two.stl")
    assert main(["slice", str(tmp_path / "two.stl"), "-o", str(tmp_path / "o")]) == 0
    text = capsys.readouterr().out
    # every layer, as runs: the list stopped at ten with "..." in the warnings file too
    said = "16 layers made as the union of their contours (overlapping shells or gap " \
        "closures): 0-15"
    assert said in text and said in (tmp_path / "o" / "slice-warnings.txt").read_text()
    assert "points (before the unions)" in text
    a.apply_translation((0, 0, 2))
    a.export(tmp_path / "one.stl")
    assert main(["slice", str(tmp_path / "one.stl"), "-o", str(tmp_path / "q")]) == 0
    assert "before the unions" not in capsys.readouterr().out


def _boxes(inner_flipped: bool):
    """A 30 mm box with a 10 mm box inside it: a cavity when the inner box faces in."""
    outer = trimesh.creation.box(extents=(30, 30, 30))
    inner = trimesh.creation.box(extents=(10, 10, 10))
    if inner_flipped:
        inner.invert()
    both = trimesh.util.concatenate([outer, inner])
    both.apply_translation((0, 0, 15))
    return both


@pytest.mark.parametrize("cavity", [True, False])
def test_a_cavity_wound_inside_out_is_named_as_built_solid(tmp_path, capsys, cavity):
    """A hollow part whose cavity's facets face out slices solid (the union of the
    shells): said only as contours running against the facet orientation (a tester's).
    Now the shell is named, with where it is; a cavity facing in slices hollow."""
    _boxes(inner_flipped=cavity).export(tmp_path / "hollow.stl")
    assert main(["slice", str(tmp_path / "hollow.stl"), "-o", str(tmp_path / "o")]) == 0
    text = capsys.readouterr().out
    said = re.search(r"a shell of 12 facets at \(-?5, -?5, (10|20)\) mm lies inside another "
                     r"and faces the same way", text)
    st = load_stack(tmp_path / "o" / "stack.npz")
    middle = st.layers[len(st) // 2].part.area
    if cavity:
        assert not said and middle == pytest.approx(900 - 100)
    else:
        assert said and middle == pytest.approx(900)


def test_winding_number_against_a_convex_hull():
    """Inside a convex polyhedron (an icosphere) exactly where scipy's Delaunay of its
    vertices finds a simplex."""
    from scipy.spatial import Delaunay

    from icefab.mesh.topology import winding_number

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    pts = np.random.default_rng(4).uniform(-7, 7, (300, 3))
    inside = Delaunay(sphere.vertices).find_simplex(pts) >= 0
    assert 0 < inside.sum() < len(pts)
    w = np.array([winding_number(p, sphere.vertices, sphere.faces) for p in pts])
    np.testing.assert_allclose(w, inside.astype(float), atol=1e-9)
    sphere.invert()
    assert winding_number(np.zeros(3), sphere.vertices, sphere.faces) == pytest.approx(-1)


def test_cli_slice_with_job_file(tube_files, tmp_path, capsys):
    job = tmp_path / "job.toml"
    job.write_text(f'[parts]\nfiles = ["{tube_files["bin.stl"]}"]\n\n'
                   "[slicing]\nlayer_thickness_mm = 1.0\n")
    rc = main(["slice", "-c", str(job), "-o", str(tmp_path / "o")])
    assert rc == 0
    assert "layers: 6" in capsys.readouterr().out


@pytest.mark.parametrize("argv,match", [
    (["--layers", "0,99"], "--layers"),
])
def test_cli_bad_input_exits_2(tube_files, tmp_path, capsys, argv, match):
    out = tmp_path / "o"
    rc = main(["slice", str(tube_files["bin.stl"]), "-o", str(out), *argv])
    assert rc == 2
    assert match in capsys.readouterr().err


def test_cli_a_layer_list_of_no_numbers_is_refused_before_slicing(tube_files, tmp_path,
                                                                  capsys):
    # read with the options (argparse's exit 2), not after slicing (a docs hunt's); the
    # range of the numbers needs the layer count and is checked after (above)
    with pytest.raises(SystemExit) as exc:
        main(["slice", str(tube_files["bin.stl"]), "-o", str(tmp_path / "o"),
              "--layers", "a,b"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "argument --layers: 'a,b': expected comma-separated layer numbers" in err
    assert "slicing" not in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("command", ["slice", "paths", "plan"])
def test_cli_a_layer_past_the_stack_is_refused_before_slicing(tube_files, tmp_path,
                                                              monkeypatch, capsys, command):
    """'icefab slice MESH --layers 3,99' was refused only after slicing the whole mesh (a
    review's): the count of uniform layers is the mesh's height over the thickness."""
    import icefab.slicing

    monkeypatch.setattr(icefab.slicing, "slice_mesh", lambda *a, **k: pytest.fail("sliced"))
    rc = main([command, str(tube_files["bin.stl"]), "-o", str(tmp_path / "o"),
               "--layers", "3,99"])
    assert rc == 2
    assert capsys.readouterr().err == (f"icefab {command}: error: --layers '3,99': layer "
                                       "numbers must be between 0 and 23\n")
    assert not (tmp_path / "o").exists()


def test_cli_adaptive_layers_are_counted_by_slicing_and_refused_before_writing(
        tube_files, tmp_path, capsys):
    job = tmp_path / "job.toml"
    job.write_text("[slicing]\ncusp_height_mm = 0.1\n")
    rc = main(["slice", str(tube_files["bin.stl"]), "-c", str(job), "-o",
               str(tmp_path / "o"), "--layers", "3,999"])
    assert rc == 2
    assert "--layers '3,999': layer numbers must be between 0 and" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@settings(max_examples=25, deadline=None)
@given(t=hs.floats(0.05, 2.0), f0=hs.floats(0.0, 0.45), f1=hs.floats(0.55, 1.0),
       z0=hs.floats(-50.0, 50.0))
def test_layer_count_is_the_number_of_layers_slicing_makes(t, f0, f1, z0):
    from icefab.slicing import layer_count

    v = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 6.0]]) + [0, 0, z0]
    mesh = icefab.Mesh(v, np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]), "tet")
    job = Job().replace(**{"slicing.layer_thickness_mm": t, "parts.part_fraction": (f0, f1)})
    assert layer_count(mesh, job) == len(slice_mesh(mesh, job))
    assert layer_count(mesh, job.replace(**{"slicing.cusp_height_mm": 0.1})) is None


def test_cli_no_model_exits_2(tmp_path, capsys):
    assert main(["slice", "-o", str(tmp_path / "o")]) == 2
    assert "no input: give mesh file(s)" in capsys.readouterr().err


def test_cli_missing_file_exits_2(tmp_path, capsys):
    assert main(["slice", str(tmp_path / "nope.stl"), "-o", str(tmp_path / "o")]) == 2
    assert "nope.stl" in capsys.readouterr().err
    assert not (tmp_path / "o" / "stack.npz").exists()


# --------------------------------------------------------------------------- real meshes

REAL = ["fandisk.obj.gz", "igea.ply.gz", "rocker-arm.obj.gz", "spot.obj.gz",
        "stanford-bunny.obj.gz", "teapot.obj.gz"]


def _scaled(mesh: icefab.Mesh, height: float) -> icefab.Mesh:
    v = mesh.vertices - mesh.vertices.min(axis=0)
    return icefab.Mesh(v * (height / v[:, 2].max()), mesh.faces, mesh.name)


@pytest.mark.parametrize("name", REAL)
def test_real_meshes_slice_without_losing_layers(mesh_dir, name):
    from icefab.mesh.holes import close_holes

    mesh, holes = close_holes(_scaled(icefab.load_mesh(mesh_dir / name), 40.0))
    st = slice_mesh(mesh, Job())
    rep = slice_report(st)
    assert len(st) == 160
    assert rep.empty_layers == [], st.warnings[:5]
    for layer in st:
        depth = layer.part.depth()
        assert np.all((layer.part.ring_areas() > 0) == (depth % 2 == 0))
    if name in ("teapot.obj.gz", "stanford-bunny.obj.gz"):  # open: closed in 3D first
        assert len(holes.holes) >= 5 and holes.unclosed_edges == 0
    assert rep.open_chains == 0           # so no layer needs the per-layer chord


def _even_odd_area(rings) -> float:
    import shapely

    region = shapely.Polygon()
    for ring in rings:
        if len(ring) >= 3:
            region = region.symmetric_difference(shapely.Polygon(ring[:, :2]).buffer(0))
    return float(region.area)


@pytest.mark.parametrize("name", ["rocker-arm.obj.gz", "spot.obj.gz"])
def test_real_mesh_areas_match_trimesh_multiplane(mesh_dir, name):
    """Layer areas equal trimesh's section_multiplane + shapely (closed meshes)."""
    mesh = _scaled(icefab.load_mesh(mesh_dir / name), 30.0)
    job = EXACT.replace(**{"slicing.layer_thickness_mm": 0.25})
    st = slice_mesh(mesh, job)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    z = [L.z for L in st]
    secs = tm.section_multiplane(plane_origin=[0, 0, 0], plane_normal=[0, 0, 1], heights=z)
    for layer, sec in zip(st, secs):
        expected = 0.0 if sec is None else _even_odd_area(sec.discrete)
        assert layer.part.area == pytest.approx(expected, rel=1e-6, abs=1e-9), layer.index


def test_demo_mug_volume_from_layers():
    """Sum of layer areas x thickness equals the mesh volume (midpoint rule), the handle
    gives extra contours, nesting has holes."""
    from icefab.demo import demo_mug
    from icefab.mesh import mesh_volume

    mesh = demo_mug()
    st = slice_mesh(mesh, EXACT.replace(**{"slicing.layer_thickness_mm": 0.25}))
    rep = slice_report(st)
    assert rep.open_chains == 0 and rep.empty_layers == []
    vol = sum(L.part.area for L in st) * 0.25
    assert vol == pytest.approx(mesh_volume(mesh.vertices, mesh.faces), rel=2e-3)
    assert max(len(L.part) for L in st) >= 3
    assert any((L.part.depth() % 2 == 1).any() for L in st)


def test_mesh_warnings_reach_the_stack_and_the_summary(tmp_path, capsys):
    """What loading fixed (a duplicate facet, inverted facets) is part of the stack's
    warnings: printed in the slice summary and saved in stack.npz."""
    tm = _tube()
    faces = np.vstack([tm.faces[:, ::-1], tm.faces[:1, ::-1]])  # inside out + a duplicate
    bad = trimesh.Trimesh(tm.vertices, faces, process=False)
    stl = tmp_path / "defects.stl"
    stl.write_bytes(bad.export(file_type="stl"))
    out = tmp_path / "out"
    assert main(["slice", str(stl), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "defects.stl: removed 1 duplicate faces" in text
    assert "all faces flipped" in text
    saved = load_stack(out / "stack.npz").warnings
    assert any("duplicate faces" in w for w in saved)
    assert any("flipped" in w for w in saved)


def test_overlapping_or_apart_shells_are_not_nested():
    from icefab.mesh.topology import nested_same_way

    a = trimesh.creation.box(extents=(20, 20, 4))
    b = trimesh.creation.box(extents=(20, 20, 4))
    b.apply_translation((10, 0, 0))              # overlapping: a corner of b inside a
    c = trimesh.creation.box(extents=(20, 20, 4))
    c.apply_translation((50, 0, 0))              # apart
    for other in (b, c):
        both = trimesh.util.concatenate([a, other])
        assert nested_same_way(both.vertices, both.faces) == []
    nested = _boxes(inner_flipped=False)
    ((n_faces, at),) = nested_same_way(nested.vertices, nested.faces)
    assert n_faces == 12 and np.all(np.abs(at[:2]) == 5)


def test_a_box_bridging_a_u_is_not_called_nested():
    """Its corners inside the U's arms and its box within the U's, its middle outside:
    only face centres tell (a tester's, who was told to flip the bridge)."""
    from shapely.geometry import Polygon

    from icefab.mesh.topology import nested_same_way

    outline = Polygon([(-20, -25), (20, -25), (20, 15), (10, 15), (10, -15), (-10, -15),
                       (-10, 15), (-20, 15)])
    u = trimesh.creation.extrude_polygon(outline, 10.0)
    bridge = trimesh.creation.box(extents=(26, 4, 4))
    bridge.apply_translation((0, 10, 5))           # from arm to arm, across the gap
    both = trimesh.util.concatenate([u, bridge])
    assert nested_same_way(both.vertices, both.faces) == []
