"""What the commands print about a build says what is true of it: the unfilled area to
the precision of its warning (``icefab paths``), adaptive layers as their range of
thicknesses (``icefab slice``, ``icefab demo``), the measurement interval of adaptive
layers as a height (``icefab simulate``), a thick adaptive layer as the cause of a
flow above the valve (a review's findings)."""

from __future__ import annotations

import pytest
import trimesh

from icefab import Job
from icefab.cli.paths_cmd import PathTally, summary_lines
from icefab.core import area_text
from icefab.resultfiles import LayerHead


@pytest.mark.parametrize("mm2, text", [(0.0, "0"), (0.244, "0.244"), (0.00123, "0.00123"),
                                       (1.5, "1.50"), (12.345, "12.3"), (1234.5, "1234")])
def test_areas_are_printed_to_three_significant_digits(mm2, text):
    assert area_text(mm2) == text


def test_the_paths_summary_prints_a_small_unfilled_area_as_its_warning_does():
    # the summary said "part 0 mm², scaffold 0 mm²" above a warning of 0.244 / 0.178 mm^2
    heads = [LayerHead(0, 0.125, (0.2, 0.1)), LayerHead(1, 0.375, (0.044, 0.078))]
    lines = summary_lines(heads, [], PathTally(Job()))
    assert "unfilled area: part 0.244 mm², scaffold 0.178 mm²" in lines
    none = summary_lines([LayerHead(0, 0.125, (0.0, 0.0))], [], PathTally(Job()))
    assert "unfilled area: part 0 mm², scaffold 0 mm²" in none


def _stack(thicknesses):
    """A stack of empty layers of the given own thicknesses, mm (NaN: the job's)."""
    from icefab.core import Layer, Region, Stack

    layers = tuple(Layer(index=k, z=0.1 * k, part=Region(), thickness=t)
                   for k, t in enumerate(thicknesses))
    return Stack(layers=layers, job=Job(), layer_thickness=0.25)


def test_layer_thickness_text_gives_adaptive_layers_their_range():
    from icefab.cli.common import layer_thickness_text

    nan = float("nan")
    assert layer_thickness_text(_stack([nan, nan])) == "0.25 mm"
    assert layer_thickness_text(_stack([0.5, 0.1, 0.3])) == "0.1 .. 0.5 mm (adaptive)"
    assert layer_thickness_text(_stack([0.5, 0.5])) == "0.5 mm (adaptive)"


def test_the_flow_hint_names_the_layer_cap_of_a_thick_adaptive_layer():
    from icefab.flow import out_of_range_hint

    words = "clamp and report instead"
    uniform = "lower the speed or set flow.out_of_range = 'clamp' to clamp and report instead"
    assert out_of_range_hint(0.25, Job(), words) == uniform
    adaptive = Job().replace(**{"slicing.cusp_height_mm": 0.1,
                                "slicing.max_layer_thickness_mm": 0.5})
    assert out_of_range_hint(0.5, adaptive, words) == (
        "this adaptive layer is 0.5 mm thick: lower the speed or "
        "slicing.max_layer_thickness_mm (now 0.5 mm), or set flow.out_of_range = 'clamp' "
        "to clamp and report instead")
    assert out_of_range_hint(0.1, adaptive, words, above=False) == uniform  # too little


def test_the_demo_on_adaptive_layers_says_so_and_blames_their_thickness(tmp_path, capsys):
    # a review's: "12 layers of 0.25 mm" for 0.5 mm adaptive layers, then a valve frequency
    # error whose hint named the speed only
    from icefab.cli import main

    job = tmp_path / "adaptive.toml"
    job.write_text("[slicing]\ncusp_height_mm = 0.1\nmin_layer_thickness_mm = 0.1\n"
                   "max_layer_thickness_mm = 0.5\n[cell]\ncpus = 1\n")
    rc = main(["demo", "-c", str(job), "--layers", "3", "--sim-layers", "0",
               "-o", str(tmp_path / "d")])
    out, err = capsys.readouterr()
    assert "sliced and scaffolded: 3 layers of 0.5 mm (adaptive), " in out
    assert rc == 2 and "valve frequency" in err
    assert ("this adaptive layer is 0.5 mm thick: lower the speed or "
            "slicing.max_layer_thickness_mm (now 0.5 mm), or set flow.out_of_range") in err


def test_the_measurement_interval_of_adaptive_layers_is_a_height():
    from icefab.cli.simulate_cmd import measurement_interval_text

    nan = float("nan")
    assert measurement_interval_text(Job(), [nan, nan]) == "every 4 layers"
    assert measurement_interval_text(Job(), [0.5, 0.1]) == (
        "every 1 mm of height (adaptive layers: feedback.interval_layers = 4 x "
        "slicing.layer_thickness_mm = 0.25 mm)")


def test_a_trajectory_files_layer_thicknesses_are_read_without_decoding(tmp_path):
    from icefab.cli.simulate_cmd import own_thicknesses
    from icefab.core import BuildMotion, LayerMotion
    from icefab.resultfiles import open_trajectories, save_trajectories

    layers = tuple(LayerMotion(index=k, z=0.25 * k, trajectories=(), thickness=t)
                   for k, t in enumerate([0.5, 0.3, 0.1]))
    save_trajectories(BuildMotion(layers=layers, job=Job()), tmp_path / "t.npz")
    motion = open_trajectories(tmp_path / "t.npz")
    assert own_thicknesses(motion.layers[1:]).tolist() == [0.3, 0.1]
    assert own_thicknesses(layers[:2]).tolist() == [0.5, 0.3]


def test_simulate_on_adaptive_layers_says_it_measures_by_height(tmp_path, capsys):
    # a review's: "every 4 layers" printed above measurements at 1.00 and 2.00 mm of 0.5 mm
    # layers
    from icefab.cli import main

    box = trimesh.creation.box(extents=(20.0, 20.0, 2.5))
    box.apply_translation((0.0, 0.0, 1.25))
    box.export(tmp_path / "box.stl")
    job = tmp_path / "adaptive.toml"
    job.write_text("[slicing]\ncusp_height_mm = 0.1\nmin_layer_thickness_mm = 0.1\n"
                   "max_layer_thickness_mm = 0.5\n[cell]\ncpus = 1\n")
    assert main(["simulate", str(tmp_path / "box.stl"), "-c", str(job),
                 "-o", str(tmp_path / "s")]) == 0
    out = capsys.readouterr().out
    assert "every 1 mm of height (adaptive layers" in out and "every 4 layers" not in out
    heights = [line.split()[1] for line in out.splitlines()
               if line.strip() and line.split()[0] in ("1", "3")]
    assert heights == ["1.00", "2.00"]


def test_the_unfilled_area_warning_has_no_exponent():
    """The paths stage's warning printed ".3g": 1 020 mm^2 read "1.02e+03" (a review's)."""
    from types import SimpleNamespace

    from icefab.paths import paths_warnings

    stack = SimpleNamespace(warnings=())
    layers = [SimpleNamespace(unfilled_mm2=(600.0, 420.4)),
              SimpleNamespace(unfilled_mm2=(0.2, 0.1))]
    (said,) = paths_warnings(stack, layers)
    assert "part 600 mm^2, scaffold 420 mm^2 over 2 layers" in said
    assert "e+" not in said
