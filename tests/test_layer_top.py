"""A layer's top (where the nozzle goes: G-code Z, the build runner's path height and its
stroke check, :meth:`icefab.core.LayerMotion.top`) is the stack's ``top_z``, carried by
the toolpath and trajectory files, and equals what the valves deposit: a part whose height
is not a whole number of layers has a top layer whose cutting plane is clipped to the part
(icefab.slicing.layer_planes), and the top derived from that plane was too low by
``cut_fraction`` times the unfilled height (a review's finding: 1.20 for 1.25 mm)."""

from __future__ import annotations

import dataclasses
import zipfile

import numpy as np
import pytest
import trimesh

from icefab import Job
from icefab.cli import main
from icefab.core import LayerMotion
from icefab.errors import StackFileError
from icefab.flow import plan_layer_valves
from icefab.motion import load_trajectories
from icefab.resultfiles import load_packed_toolpaths, load_stack, load_toolpaths
from icefab.stages import layer_height


def _box_build(tmp_path, height_mm: float) -> tuple[Job, object, object, str]:
    """A 12 x 12 mm box ``height_mm`` tall on a gantry through ``icefab slice``, ``paths``
    and ``plan --gcode``: (job, stack, trajectories, G-code text)."""
    box = trimesh.creation.box(extents=(12.0, 12.0, height_mm))
    box.apply_translation((0.0, 0.0, height_mm / 2.0))
    box.export(tmp_path / "box.stl")
    (tmp_path / "job.toml").write_text('[cell]\nrobot = "gantry"\ncpus = 1\n')
    job = ["-c", str(tmp_path / "job.toml")]
    assert main(["slice", str(tmp_path / "box.stl"), *job, "-o", str(tmp_path / "s")]) == 0
    assert main(["paths", str(tmp_path / "s" / "stack.npz"), *job,
                 "-o", str(tmp_path / "p")]) == 0
    assert main(["plan", str(tmp_path / "p" / "toolpaths.npz"), *job, "-o",
                 str(tmp_path / "t"), "--gcode"]) == 0
    motion = load_trajectories(tmp_path / "t" / "trajectories.npz")
    stack = load_stack(tmp_path / "s" / "stack.npz")
    return motion.job, stack, motion, (tmp_path / "t" / "trajectories.gcode").read_text()


def _commanded(lm: LayerMotion, job: Job) -> list[float]:
    """The volume, mm^3, every depositing path of a layer's valve programs commands."""
    return [lp.program.commanded_mm3 for lp in plan_layer_valves(lm, job)]


def test_a_part_not_a_whole_number_of_layers_tall_tops_its_last_layer_where_deposited(
        tmp_path):
    # 1.15 mm in 0.25 mm layers: 5 layers, the last one deposits 1.00-1.25 (flow's dh is
    # the full layer thickness) while its plane is cut at 1.075, inside the part
    job, stack, motion, gcode = _box_build(tmp_path, 1.15)
    assert len(stack) == len(motion.layers) == 5
    assert stack[4].z == pytest.approx(1.075)
    below = 0.0
    for L, lm in zip(stack, motion.layers):
        top = lm.top(job)
        assert top == L.top_z                                      # the stack's, exactly
        assert top == pytest.approx(below + layer_height(lm.thickness, job))  # deposited
        below = top
    assert motion.layers[4].top(job) == pytest.approx(1.25)
    assert "; layer 4 top z 1.2500 (cut at 1.0750)" in gcode and "G0 Z1.2500 " in gcode
    assert "Z1.2000" not in gcode
    # the valves lay, on the last layer, the height between its top and the one below
    last = motion.layers[4]
    dh = last.top(job) - motion.layers[3].top(job)
    assert _commanded(last, job) == pytest.approx(
        _commanded(dataclasses.replace(last, thickness=dh), job), rel=1e-12)
    # the toolpath file carries it too, whole and as arrays
    tp = tmp_path / "p" / "toolpaths.npz"
    assert [lp.top_z for lp in load_toolpaths(tp).layers] == [L.top_z for L in stack]
    assert [h.top_z for h in load_packed_toolpaths(tp).heads] == [L.top_z for L in stack]


def test_a_whole_number_of_layers_keeps_its_tops(tmp_path):
    # 1.25 mm: every layer full, the top above the plane by (1 - cut_fraction) t as before
    job, stack, motion, gcode = _box_build(tmp_path, 1.25)
    t, c = job.slicing.layer_thickness_mm, job.slicing.cut_fraction
    assert [lm.top(job) for lm in motion.layers] == pytest.approx(
        [lm.z + (1.0 - c) * t for lm in motion.layers], abs=1e-12)
    assert [lm.top(job) for lm in motion.layers] == pytest.approx(
        [0.25, 0.5, 0.75, 1.0, 1.25], abs=1e-12)
    assert "; layer 4 top z 1.2500 (cut at 1.1250)" in gcode


def _without(src, dst, member: str, change: dict | None = None) -> None:
    """Copy the npz ``src`` to ``dst`` without ``member`` (a file written before it), or
    with the members of ``change`` replaced."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            name = info.filename[:-4]
            if change is None and name == member:
                continue
            if change is not None and name in change:
                with zout.open(info.filename, "w") as fh:
                    np.lib.format.write_array(fh, change[name], allow_pickle=False)
                continue
            zout.writestr(info, zin.read(info.filename))


def test_files_without_tops_still_load_and_corrupt_tops_are_refused(tmp_path):
    job, stack, motion, _ = _box_build(tmp_path, 1.15)
    c, t = job.slicing.cut_fraction, job.slicing.layer_thickness_mm
    for src, load in ((tmp_path / "t" / "trajectories.npz", load_trajectories),
                      (tmp_path / "p" / "toolpaths.npz", load_toolpaths)):
        with np.load(src) as f:
            tops, z = f["layer_top_z"], f["layer_z"]
        np.testing.assert_array_equal(tops, [L.top_z for L in stack])
        old = tmp_path / f"old_{src.name}"
        _without(src, old, "layer_top_z")
        layers = load(old).layers
        assert all(np.isnan(lay.top_z) for lay in layers)   # derived from the plane
        if load is load_trajectories:
            assert layers[0].top(job) == pytest.approx(z[0] + (1.0 - c) * t)
        bad = tmp_path / f"bad_{src.name}"
        _without(src, bad, "", {"layer_top_z": np.where(np.arange(len(z)) == 2, z - 0.1,
                                                         tops)})
        with pytest.raises(StackFileError, match="layer_top_z.*below its cutting plane"):
            load(bad)
