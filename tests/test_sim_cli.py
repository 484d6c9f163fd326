"""``icefab simulate`` end to end on a small saved build."""
from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_build import annulus_toolpaths  # noqa: E402

import numpy as np  # noqa: E402

from icefab import Job  # noqa: E402
from icefab.cli import main  # noqa: E402
from icefab.motion import plan_toolpaths, save_trajectories  # noqa: E402
from icefab.paths import save_toolpaths  # noqa: E402


@pytest.fixture(scope="module")
def toolpaths_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("build") / "toolpaths.npz"
    save_toolpaths(annulus_toolpaths(Job(), 12), path)
    return path


@pytest.fixture(scope="module")
def trajectories_file(tmp_path_factory):
    """What 'icefab plan' writes for the first 8 annulus layers."""
    job = Job().replace(**{"cell.cpus": 1})
    path = tmp_path_factory.mktemp("plan") / "trajectories.npz"
    save_trajectories(plan_toolpaths(annulus_toolpaths(job, 8), job), path)
    return path


def test_simulate_prints_both_errors_and_writes_the_figures(toolpaths_file, tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(toolpaths_file), "--layers", "8", "--flow-error", "0.2",
                 "--seed", "3", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "RMS open" in text and "RMS SMF" in text and "flow error +20%" in text
    for name in ("rms_vs_height.png", "surfaces.png", "simulation.json", "rms.csv"):
        assert (out / name).stat().st_size > 0
    data = json.loads((out / "simulation.json").read_text())
    # every result file says what it is (README, "Files"; this one did not, a hunt's)
    assert (data["format"], data["version"]) == ("icefab-simulation", 1)
    assert data["open_loop"]["layers"] == [3, 7] and data["smf"]["closed_loop"]
    assert data["settings"]["simulation"]["flow_error"] == 0.2
    assert data["settings"]["simulation"]["seed"] == 3
    assert data["surface_layer"] == 7
    rows = list(csv.DictReader((out / "rms.csv").open()))
    assert [int(r["layer"]) for r in rows] == [3, 7]
    # +20 % flow: after 8 layers (2 mm) the open-loop surface is about 0.4 mm high
    assert float(rows[-1]["rms_open_mm"]) == pytest.approx(0.4, rel=0.15)
    assert float(rows[-1]["rms_smf_mm"]) < float(rows[-1]["rms_open_mm"])


@pytest.mark.parametrize("args,message", [
    (["--layers", "-2"], "--layers"),
    (["--layers", "2"], "no measurement layer"),
    (["--surface-layer", "5"], "--surface-layer 5"),
    (["--flow-error", "-2"], "flow_error"),
])
def test_simulate_errors_leave_no_output(toolpaths_file, tmp_path, capsys, args, message):
    out = tmp_path / "sim"
    assert main(["simulate", str(toolpaths_file), "-o", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_simulate_runs_toolpaths_with_their_own_job_and_refuses_a_contradicting_one(
        tmp_path, capsys):
    """Without -c, a toolpath file runs with the job it was made with (it ran with the
    default job: toolpaths measured every 2nd layer were simulated as if every 4th);
    with -c, a job that measures other layers than the file is refused (a tester's SMF
    corrected 3.5 times less with such a job, without a word)."""
    job = Job().replace(**{"feedback.interval_layers": 2, "cell.cpus": 1})
    src = tmp_path / "toolpaths.npz"
    save_toolpaths(annulus_toolpaths(job, 4), src)
    out = tmp_path / "sim"
    assert main(["simulate", str(src), "-o", str(out), "--layers", "4"]) == 0
    data = json.loads((out / "simulation.json").read_text())
    assert data["open_loop"]["layers"] == [1, 3]
    capsys.readouterr()
    other = tmp_path / "job.toml"
    other.write_text("[feedback]\ninterval_layers = 1\n")
    assert main(["simulate", str(src), "-c", str(other), "-o", str(tmp_path / "s2")]) == 2
    assert "the toolpaths were made with feedback.interval_layers = 2, the job has 1" in \
        capsys.readouterr().err
    assert not (tmp_path / "s2").exists()


def test_simulate_checks_the_surface_layer_before_simulating(toolpaths_file, tmp_path,
                                                           capsys, monkeypatch):
    import icefab.sim

    def no(*args, **kwargs):
        raise AssertionError("simulated before the options were checked")

    monkeypatch.setattr(icefab.sim, "simulate_build", no)
    out = tmp_path / "sim"
    assert main(["simulate", str(toolpaths_file), "--surface-layer", "6", "-o", str(out)]) == 2
    assert "--surface-layer 6: not a measurement layer" in capsys.readouterr().err
    assert not out.exists()


def test_simulate_runs_a_trajectories_file_through_its_valve_programs(trajectories_file,
                                                                      tmp_path, capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(trajectories_file), "--flow-error", "0.2", "-o",
                 str(out)]) == 0
    text = capsys.readouterr().out
    assert "valve pulses along the minimum-time trajectories" in text
    data = json.loads((out / "simulation.json").read_text())
    assert data["settings"]["simulation"]["deposition"] == "valves"
    assert data["open_loop"]["layers"] == [3, 7] and data["open_loop"]["pulses"] > 0
    rows = list(csv.DictReader((out / "rms.csv").open()))
    # +20 % flow through the valves: after 8 layers (2 mm) about 0.4 mm too high
    assert float(rows[-1]["rms_open_mm"]) == pytest.approx(0.4, rel=0.15)
    assert float(rows[-1]["rms_smf_mm"]) < float(rows[-1]["rms_open_mm"])


def test_simulate_says_where_the_valve_saturated_smf(trajectories_file, tmp_path, capsys):
    """-30 % flow: SMF asks up to +30 %. With the valve at most at 400 Hz (94.43 mm^3/s)
    the part's fill at 104 mm/s (77.98 mm^3/s nominal) has room for +21 %: the valve
    saturates the correction there (thesis 5.2.2), the simulation runs on, says so before
    and how much the valve gave with SMF (none open loop); SMF still betters open loop."""
    (tmp_path / "job.toml").write_text("[flow]\nmax_frequency_hz = 400\n")
    assert main(["simulate", str(trajectories_file), "--flow-error", "-0.3", "-c",
                 str(tmp_path / "job.toml"), "-o", str(tmp_path / "sim")]) == 0
    text = capsys.readouterr().out
    assert "warning: feedback headroom" in text and "saturates SMF's correction at +21%" in text
    assert "saturated (open loop" not in text
    line = next(x for x in text.splitlines() if x.startswith("saturated (with SMF"))
    got, asked = (float(v) for v in line.split("delivers ")[1].split(" mm^3")[0]
                  .split(" of "))
    assert 0 < got < asked
    rows = list(csv.DictReader((tmp_path / "sim" / "rms.csv").open()))
    assert float(rows[-1]["rms_smf_mm"]) < float(rows[-1]["rms_open_mm"])


def test_simulate_plans_the_trajectories_of_toolpaths_for_the_valves(toolpaths_file, tmp_path,
                                                                     capsys):
    out = tmp_path / "sim"
    assert main(["simulate", str(toolpaths_file), "--layers", "4", "--deposition", "valves",
                 "-o", str(out)]) == 0
    assert "valve pulses" in capsys.readouterr().out
    assert json.loads((out / "simulation.json").read_text())["smf"]["pulses"] > 0


def _bad_trajectories(kind: str, src: Path, tmp: Path) -> list[str]:
    """Arguments naming a bad trajectory input of the given kind."""
    with np.load(src, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    bad = tmp / "bad.npz"
    if kind == "mismatched job":
        job = tmp / "job.toml"
        job.write_text("[slicing]\nlayer_thickness_mm = 0.5\n")
        return [str(src), "-c", str(job)]
    if kind == "no programs":  # measurement and travel only: nothing for the valves
        keep = np.isin(data["role"], [2, 3])
        data["role"] = np.where(keep, data["role"], 3).astype(np.int8)
    elif kind == "truncated":
        del data["speed_counts_0"]
    elif kind == "not icefab":
        data = {"x": np.zeros(3)}
    np.savez(bad, **data)
    return [str(bad)]


@pytest.mark.parametrize("kind,message", [
    ("mismatched job", "made with slicing.layer_thickness_mm = 0.25, the job has 0.5"),
    ("no programs", "no boundary or fill trajectories in the first 8 layers"),
    ("truncated", "missing arrays speed_counts_0"),
    ("not icefab", "not an icefab toolpath or trajectory file"),
])
def test_bad_trajectory_input_is_one_error_and_no_output(trajectories_file, tmp_path, capsys,
                                                         kind, message):
    out = tmp_path / "sim"
    args = _bad_trajectories(kind, trajectories_file, tmp_path)
    assert main(["simulate", *args, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_simulate_reports_a_missing_input(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "nothing.npz"), "-o", str(tmp_path / "o")]) == 2
    assert "nothing.npz" in capsys.readouterr().err


def _corrupting(monkeypatch, change):
    """Wrap the simulator so both its results are changed by ``change(result) -> result``."""
    import dataclasses

    import icefab.sim

    real = icefab.sim.simulate_open_and_smf

    def wrapped(*a, **k):
        return tuple(change(r, dataclasses) for r in real(*a, **k))

    monkeypatch.setattr(icefab.sim, "simulate_open_and_smf", wrapped)


def test_a_surface_that_overflowed_is_an_error_not_infinity_in_json(toolpaths_file, tmp_path,
                                                                    capsys, monkeypatch):
    """Issue 10: simulate exited 0 writing NaN/Infinity into simulation.json."""
    def overflow(r, dc):
        z = r.height.z.copy()
        z[np.isfinite(z)] = np.inf
        return dc.replace(r, height=dc.replace(r.height, z=z),
                          rms=np.full_like(r.rms, np.nan),
                          volume_deposited=float("inf"))

    _corrupting(monkeypatch, overflow)
    out = tmp_path / "sim"
    assert main(["simulate", str(toolpaths_file), "--layers", "8", "-o", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.strip().splitlines()
           if "error" in line]  # progress lines come before it
    assert len(err) == 1 and "results are not finite" in err[0]
    assert "surface heights are infinite" in err[0] and "nothing was written" in err[0]
    assert not out.exists()


def test_layers_without_a_part_are_strict_json_nulls_with_the_reason(toolpaths_file,
                                                                     tmp_path, monkeypatch):
    def no_part_at_first(r, dc):
        rms, mx = r.rms.copy(), r.max_abs.copy()
        rms[0] = mx[0] = np.nan
        return dc.replace(r, rms=rms, max_abs=mx)

    _corrupting(monkeypatch, no_part_at_first)
    out = tmp_path / "sim"
    assert main(["simulate", str(toolpaths_file), "--layers", "8", "-o", str(out)]) == 0

    def strict(name):
        raise AssertionError(f"not strict JSON: {name}")

    data = json.loads((out / "simulation.json").read_text(), parse_constant=strict)
    assert data["open_loop"]["rms_mm"][0] is None and data["smf"]["max_abs_mm"][0] is None
    assert isinstance(data["open_loop"]["rms_mm"][1], float)
    assert "part footprint is empty" in data["null_means"]


@pytest.mark.parametrize("cpus", [1, 2])
def test_open_loop_and_smf_side_by_side_equal_two_runs_in_a_row(toolpaths_file, cpus):
    from icefab.paths import load_toolpaths
    from icefab.sim import simulate_build, simulate_open_and_smf
    tp = load_toolpaths(toolpaths_file)
    job = tp.job.replace(**{"cell.cpus": cpus})
    pair = simulate_open_and_smf(tp, job, layers=8)
    for closed, res in zip((False, True), pair):
        alone = simulate_build(tp, job, layers=8, closed_loop=closed)
        assert np.array_equal(res.rms, alone.rms, equal_nan=True)
        assert np.array_equal(res.height.z, alone.height.z, equal_nan=True)
    assert not np.array_equal(pair[0].rms, pair[1].rms, equal_nan=True)  # SMF acts


def test_the_final_rms_is_the_last_layer_with_a_part_footprint():
    """A top layer too small for the grid has no RMS: the summary printed 'nan mm'."""
    from types import SimpleNamespace

    from icefab.cli.simulate_cmd import final_rms_line

    def res(rms):
        return SimpleNamespace(layers=np.array([3, 7, 11]), rms=np.array(rms))
    assert final_rms_line(res([0.5, 0.4, 0.3]), res([0.2, 0.1, 0.05])) == \
        "final RMS height deviation: 0.300 mm open loop, 0.050 mm with SMF"
    line = final_rms_line(res([0.5, 0.4, np.nan]), res([0.2, 0.1, np.nan]))
    assert line.startswith("final RMS height deviation: 0.400 mm open loop, 0.100 mm with "
                           "SMF (layer 7, the last measured") and "nan" not in line
    assert "none" in final_rms_line(res([np.nan] * 3), res([np.nan] * 3))


def test_the_final_footprint_figures_are_the_last_layer_that_covers_a_cell():
    """A last measurement layer that covers no cell (its flow drifted to nothing) has no
    footprint RMS: the summary printed 'RMS nan mm' under final_rms_line's layer 7."""
    from types import SimpleNamespace

    from icefab.cli.simulate_cmd import final_footprint_line

    def res(rms):
        return SimpleNamespace(layers=np.array([3, 7, 11]), rms_footprint=np.array(rms),
                               max_abs_footprint=2 * np.array(rms))
    line = final_footprint_line(res([0.5, 0.4, np.nan]), res([0.2, 0.1, np.nan]))
    assert line == ("over the whole footprint (part and scaffold), layer 7: RMS 0.400 mm "
                    "open loop, 0.100 mm with SMF; largest 0.800 / 0.200 mm"), line
    assert "none" in final_footprint_line(res([np.nan] * 3), res([np.nan] * 3))


def test_simulate_honours_feedback_off_as_the_build_does(tmp_path, capsys):
    """Toolpaths made with feedback.enabled = false (no measurement paths): 'icefab build'
    measures nothing, and simulate ran SMF anyway on the laser along the deposition paths
    (0.07 against 0.25 mm on a tester's bunny). Now both builds are the open loop."""
    job = Job().replace(**{"feedback.enabled": False, "cell.cpus": 1,
                           "simulation.flow_error": 0.2})
    src = tmp_path / "toolpaths.npz"
    save_toolpaths(annulus_toolpaths(job, 8, measure=False), src)
    out = tmp_path / "sim"
    assert main(["simulate", str(src), "-o", str(out), "--layers", "8"]) == 0
    text = capsys.readouterr().out
    assert "feedback.enabled = false: the build runs open loop" in text
    data = json.loads((out / "simulation.json").read_text())
    assert data["open_loop"]["rms_mm"] == data["smf"]["rms_mm"]
    assert not data["smf"]["closed_loop"]
    assert data["open_loop"]["rms_mm"][-1] > 0.05    # the flow error, uncorrected


def test_a_layer_without_a_footprint_is_a_dash_not_nan():
    # an adaptive sphere's top measurement layer had no part footprint on the grid: the
    # table printed "97  16.00  nan nan nan nan" and rms.csv held "nan"
    from icefab.cli.simulate_cmd import _csv_value, format_table

    nan = float("nan")
    lines = format_table([[93, 15.0, 0.1, 0.05, 0.3, 0.2], [97, 16.0, nan, nan, nan, nan]])
    assert "nan" not in "\n".join(lines)
    assert lines[2].split() == ["97", "16.00", "-", "-", "-", "-"]
    assert lines[-1] == "  -: no part footprint on the simulator grid at that layer"
    assert len(format_table([[93, 15.0, 0.1, 0.05, 0.3, 0.2]])) == 2
    assert (_csv_value(nan), _csv_value(0.25)) == ("", "0.250000")
    # the whole footprint's columns: a layer covering no cell is a dash, said (a review's)
    lines = format_table([[93, 15.0, 0.1, 0.05, 0.3, 0.2, 0.2, 0.5],
                          [97, 16.0, 0.1, 0.05, 0.3, 0.2, nan, nan]])
    assert lines[2].split()[-2:] == ["-", "-"]
    assert "  - under all: the layer covers no cell of the simulator grid" in lines
    assert "no part footprint" not in "\n".join(lines)


def test_simulate_without_feedback_says_its_valve_findings_are_open_loop(tmp_path, capsys):
    # feedback.enabled = false runs the build open loop once; its valve findings were
    # printed twice, the second time labelled "(with SMF)", and "N pulses with SMF"
    job = Job().replace(**{"feedback.enabled": False, "cell.cpus": 1,
                           "flow.max_frequency_hz": 300.0, "flow.out_of_range": "clamp"})
    src = tmp_path / "t.npz"
    save_trajectories(plan_toolpaths(annulus_toolpaths(job, 4, measure=False), job), src)
    assert main(["simulate", str(src), "-o", str(tmp_path / "sim")]) == 0
    text = capsys.readouterr().out
    assert "clamped (open loop, flow.out_of_range = 'clamp')" in text
    assert "with SMF)" not in text and "pulses with SMF" not in text
    assert "pulses, open loop)" in text
