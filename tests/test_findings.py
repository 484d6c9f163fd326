"""Warnings summarised by kind with counts and layer ranges; the full list in a file
(issue 11: an empty layer's warning used to fall into '... and 443 more')."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, strategies as st

from icefab.cli import main
from icefab.core import Mesh
from icefab.findings import summarise_warnings, warning_kind, warning_layer
from icefab.mesh import write_stl


def test_kinds_counts_and_layer_ranges():
    ws = ([f"layer {k} (z = {k * 0.25 + 0.125:.3f} mm): open contour closed across a "
           f"{1 + k / 100:.2f} mm gap at ({k}.00, -3.50)" for k in range(3, 700)]
          + ["layer 153 (z = 38.375 mm): empty cross-section", "bunny: 5 holes closed"])
    assert warning_layer(ws[0]) == 3 and warning_layer(ws[-1]) is None
    assert warning_kind(ws[0]) == "open contour closed across a # mm gap at (#, #)"
    lines = summarise_warnings(ws)
    # each number of the kind as the range it takes ('#' read like an unfilled template)
    assert lines == ["697 x open contour closed across a 1.03..7.99 mm gap at (3.00..699.00, "
                     "-3.50) (697 layers, 3-699)",
                     "layer 153 (z = 38.375 mm): empty cross-section", "bunny: 5 holes closed"]


def test_a_kind_keeps_the_digits_of_units_and_setting_names():
    """'(# mm^# thinner than a path)': the power of a unit is not a number of the
    message, nor is the digit of a setting's name."""
    w = ("layer 40 (z = 10.125 mm): part feature narrower than the path width 1.5 mm near "
         "x = -12.5, y = 3 mm (2.4 mm^2 thinner than a path; cell.l1_mm = 325, +1e-3)")
    assert warning_kind(w) == ("part feature narrower than the path width # mm near x = #, "
                               "y = # mm (# mm^2 thinner than a path; cell.l1_mm = #, #)")


def test_slice_prints_kinds_and_writes_every_warning(tmp_path, capsys):
    """An open tube sliced with consent to the per-layer chord and no 3D closing: one
    warning per layer, all in OUT/slice-warnings.txt, one summary line for the kind."""
    tube = trimesh.creation.annulus(r_min=4.0, r_max=5.0, height=10.0, sections=24)
    walls = np.abs(tube.face_normals[:, 2]) < 0.5
    open_tube = trimesh.Trimesh(tube.vertices, tube.faces[walls], process=False)
    half = open_tube.triangles_center[:, 0] > -4.5          # cut a 1 mm wide slot
    part = trimesh.Trimesh(open_tube.vertices, open_tube.faces[half], process=False)
    part.remove_unreferenced_vertices()
    write_stl(Mesh(part.vertices, part.faces, "slot"), tmp_path / "slot.stl")
    (tmp_path / "job.toml").write_text(
        "[parts]\nclose_holes = false\n[slicing]\nlayer_thickness_mm = 0.25\n"
        "open_contours = \"close\"\n")
    out = tmp_path / "out"
    assert main(["slice", str(tmp_path / "slot.stl"), "-c", str(tmp_path / "job.toml"),
                 "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    listed = (out / "slice-warnings.txt").read_text().splitlines()
    assert listed[0].startswith("# ") and len(listed) > 40
    per_layer = [w for w in listed[1:] if w.startswith("layer ")]
    assert {warning_layer(w) for w in per_layer} == set(range(40))
    assert "(40 layers, 0-39)" in printed and "slice-warnings.txt" in printed
    assert len(printed.splitlines()) < 25                    # one screen


def test_clamped_volume_totals_what_the_valve_could_not_give():
    """Two paths at 160 mm/s, 3 mm x 0.25 mm: 120 mm^3/s commanded, the 2 ms tick's
    500 Hz gives 115.28 mm^3/s (the table's row): clamped, and the totals say so."""
    from test_flow_limits import constant_trajectory

    from icefab import Job
    from icefab.findings import clamped_volume
    from icefab.flow import plan_valves

    job = Job().replace(**{"flow.out_of_range": "clamp"})
    found = []
    for layer in (4, 9):
        traj = constant_trajectory(160.0, width=3.0)
        found += [(layer, w) for w in plan_valves(traj, "part", job).warnings]
    paths, layers, got, asked = clamped_volume(found)
    assert (paths, layers) == (2, 2)
    assert got / asked == pytest.approx(115.28 / 120.0, rel=2e-3)


def test_saturated_volume_totals_what_the_valve_gave_of_what_smf_asked():
    """3 mm x 0.25 mm at 125 mm/s is 93.75 mm^3/s nominal; +30 % asks 121.9, the valve
    gives 115.28 at 500 Hz (its saturation, thesis 5.2.2), under the default 'error'."""
    from test_flow_limits import constant_trajectory

    from icefab import Job
    from icefab.findings import clamped_volume, saturated_volume
    from icefab.flow import plan_valves

    job = Job()
    found = []
    for layer in (4, 9):
        traj = constant_trajectory(125.0, width=3.0)
        u = np.full(len(traj.xy), 0.3)
        found += [(layer, w) for w in plan_valves(traj, "part", job, action=u).warnings]
    paths, layers, got, asked = saturated_volume(found)
    assert (paths, layers) == (2, 2)
    assert got / asked == pytest.approx(115.28 / (1.3 * 93.75), rel=2e-3)
    assert clamped_volume(found) == (0, 0, 0.0, 0.0)


@given(st.lists(st.integers(0, 400), unique=True, max_size=60))
def test_layer_runs_name_every_layer(layers):
    # "0-9, 12, 14-20": expanded back, the runs are the sorted layers, and no two runs touch
    from icefab.core import layer_runs

    ks = sorted(layers)
    text = layer_runs(ks)
    back = []
    for part in filter(None, text.split(", ")):
        a, _, b = part.partition("-")
        back += list(range(int(a), int(b or a) + 1))
    assert back == ks
    assert len(text.split(", ")) == 1 + sum(b - a > 1 for a, b in zip(ks, ks[1:])) if ks \
        else text == ""
