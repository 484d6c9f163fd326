"""``icefab valves`` end to end on a small trajectory file."""
from __future__ import annotations

import csv
import re

import numpy as np
import pytest

from icefab import Job
from icefab.cli import main
from icefab.flow import decode_valve_program as read_valve_program_bytes
from icefab.flow import n_pulses, plan_valves, read_valve_layer
from icefab.motion import BuildMotion, LayerMotion, save_trajectories

from test_flow import line_trajectory


@pytest.fixture()
def traj_file(tmp_path):
    layers = []
    for k in range(2):
        trs = (line_trajectory(y=0.0 + k), line_trajectory(role="travel", width=0.0),
               line_trajectory(vmax=100.0, role="fill", material="scaffold", y=5.0))
        layers.append(LayerMotion(index=k, z=0.25 * (k + 1), trajectories=trs))
    f = tmp_path / "trajectories.npz"
    save_trajectories(BuildMotion(layers=tuple(layers), job=Job()), f)
    return f


def test_valves_refuses_a_job_that_contradicts_the_trajectories(tmp_path, traj_file,
                                                                capsys):
    """The volume per mm is width x thickness: trajectories of 0.25 mm layers given a job of
    0.5 mm ones are refused, not given twice the water (a tester's bunny); a valve
    setting may differ."""
    job = tmp_path / "job.toml"
    job.write_text("[slicing]\nlayer_thickness_mm = 0.5\n")
    out = tmp_path / "out"
    assert main(["valves", str(traj_file), "-c", str(job), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "the trajectories were made with slicing.layer_thickness_mm = 0.25, the job " \
        "has 0.5" in err
    assert not out.exists()
    job.write_text("[flow]\nmode = \"pwm\"\n")
    assert main(["valves", str(traj_file), "-c", str(job), "-o", str(out)]) == 0


def test_valves_writes_programs(tmp_path, traj_file, capsys):
    out = tmp_path / "out"
    rc = main(["valves", str(traj_file), "-o", str(out), "--format", "both"])
    assert rc == 0
    text = capsys.readouterr().out
    assert text.splitlines()[0].startswith("valve programs: 4 paths in 2 layers")
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*"))
    # one file per layer and form, not one per path (--format both wrote 56 000 files)
    assert [f for f in files if f.startswith("valves/")] == [
        "valves/layer_0000.bin", "valves/layer_0000.txt", "valves/layer_0001.bin",
        "valves/layer_0001.txt"]
    for form in ("bin", "txt"):
        layer, programs = read_valve_layer(out / "valves" / f"layer_0001.{form}")
        assert layer == 1
        # travel (trajectory 1) has no valve program; build order and valves kept
        assert [(lp.path, lp.material) for lp in programs] == [(0, "part"), (2, "scaffold")]
    a = read_valve_layer(out / "valves" / "layer_0000.bin")[1][0].program
    b = read_valve_layer(out / "valves" / "layer_0000.txt")[1][0].program
    np.testing.assert_array_equal(a.ticks, b.ticks)
    ref = plan_valves(line_trajectory(), "part", Job())
    assert n_pulses(a) == n_pulses(ref)
    # each record's bytes are the per-program binary layout, unchanged
    data = (out / "valves" / "layer_0000.bin").read_bytes()
    assert data[:4] == b"ICVL" and data[28:32] == b"ICEV"
    assert read_valve_program_bytes(data[28:28 + int.from_bytes(data[24:28], "little")]
                                    ).ticks.tolist() == ref.ticks.tolist()
    assert "per layer:" in (out / "valves-summary.txt").read_text()
    rows = list(csv.DictReader((out / "valves-paths.csv").open()))
    assert [(r["layer"], r["path"], r["material"]) for r in rows] == [
        ("0", "0", "part"), ("0", "2", "scaffold"), ("1", "0", "part"), ("1", "2", "scaffold")]
    # the line is 100 mm long (line_trajectory): the table's length is the samples' length
    assert float(rows[0]["length_mm"]) == pytest.approx(100.0, rel=1e-6)


def test_valves_bad_input(tmp_path, traj_file, capsys):
    assert main(["valves", str(tmp_path / "none.npz"), "-o", str(tmp_path / "o")]) == 2
    assert main(["valves", str(traj_file), "-o", str(tmp_path / "o"), "--layers", "7"]) == 2
    err = capsys.readouterr().err
    assert "not found" in err and "--layers" in err
    assert not (tmp_path / "o").exists()


@pytest.fixture()
def fast_file(tmp_path):
    """Two layers with one fill path commanding 3 x 0.25 x 400 = 300 mm^3/s (table: 195)."""
    layers = tuple(LayerMotion(index=k, z=0.25 * (k + 1), trajectories=(
        line_trajectory(length=600, vmax=400.0, accel=4000.0, width=3.0, role="fill", y=k),
        line_trajectory(y=5.0 + k))) for k in range(2))
    f = tmp_path / "fast.npz"
    save_trajectories(BuildMotion(layers=layers, job=Job()), f)
    return f


def test_valves_prints_each_kind_of_finding_once_with_its_count(tmp_path, fast_file, capsys):
    out = tmp_path / "out"
    rc = main(["valves", str(fast_file), "-o", str(out), "--out-of-range", "clamp"])
    text = capsys.readouterr().out
    assert rc == 0
    summary = (out / "valves-summary.txt").read_text()
    assert summary.startswith(text.strip())
    assert len(text.splitlines()) <= 25  # one screen
    kind = [ln for ln in text.splitlines() if "outside the calibration table" in ln]
    assert len(kind) == 1  # two paths, one line
    assert re.match(r"2 paths in 2 layers \(0-1\): layer \d+ part fill path: flow 300 mm\^3/s "
                    r"outside the calibration table \[0, 195\] mm\^3/s", kind[0].lstrip())
    assert "clamped (flow.out_of_range = 'clamp')" in kind[0] and "commanded (-" in kind[0]
    assert "(mode fm, tick 2 ms" in text and "flow.out_of_range = 'clamp')" in text


def test_valves_out_of_range_error_names_path_flow_and_setting(tmp_path, fast_file, capsys):
    rc = main(["valves", str(fast_file), "-o", str(tmp_path / "o"), "--out-of-range", "error"])
    out, err = capsys.readouterr()
    assert rc == 2 and not (tmp_path / "o").exists()
    assert re.search(r"layer \d+, path 0 \(part fill\): flow 300 mm\^3/s outside the "
                     r"calibration table \[0, 195\] mm\^3/s", err)
    assert "flow.out_of_range = 'clamp'" in err and err.count("\n") == 1


def test_valves_error_names_the_path_by_its_index_in_the_layer(tmp_path, capsys):
    # a docs hunt's: "layer 3 part fill path: valve frequency 400.1 Hz above the limit"
    # left a layer's fill paths to guess from; motion names "layer 0, path 1"
    layers = tuple(LayerMotion(index=k, z=0.25 * (k + 1), trajectories=(
        line_trajectory(y=5.0 + k),
        line_trajectory(length=300, vmax=100.0, accel=4000.0, width=3.0, role="fill", y=k)))
        for k in range(2))
    f = tmp_path / "t.npz"
    save_trajectories(BuildMotion(layers=layers, job=Job()), f)
    job = tmp_path / "j.toml"
    job.write_text("[flow]\nmax_frequency_hz = 200\n")
    assert main(["valves", str(f), "-o", str(tmp_path / "o"), "-c", str(job)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and not (tmp_path / "o").exists()
    assert re.match(r"icefab valves: error: layer 0, path 1 \(part fill\): valve frequency "
                    r"\S+ Hz above the limit 200 Hz \(flow.max_frequency_hz", err[0]), err


@pytest.mark.parametrize("cpus", [1, 2])
def test_build_valves_in_batches_equal_the_paths_one_by_one(cpus):
    """plan_build_valves (worker pool) and iter_build_valves (batches of layers) give every
    depositing path the program plan_valves gives it alone, in order."""
    from icefab.flow import iter_build_valves, plan_build_valves, plan_valves
    job = Job().replace(**{"cell.cpus": cpus})
    layers = tuple(LayerMotion(index=k, z=0.25 * (k + 1), trajectories=(
        line_trajectory(y=float(k)), line_trajectory(role="travel", width=0.0),
        line_trajectory(vmax=100.0, role="fill", material="scaffold", y=5.0 + k)))
        for k in range(11))
    whole = plan_build_valves(layers, job)
    seen = []
    batches = list(iter_build_valves(layers, job, progress=lambda d, t: seen.append((d, t)),
                                     batch=4))
    assert [lm.index for lm, _ in batches] == list(range(11)) and seen[-1] == (11, 11)
    for lm, progs, ref in zip(layers, (p for _, p in batches), whole):
        assert [lp.path for lp in progs] == [0, 2] == [lp.path for lp in ref]
        for lp, r in zip(progs, ref):
            alone = plan_valves(lm.trajectories[lp.path], lp.material, job)
            assert np.array_equal(lp.program.ticks, alone.ticks)
            assert np.array_equal(r.program.ticks, alone.ticks) and lp.material == r.material


def _blocked_file(tmp_path, n=9, fast_layer=None):
    """n layers in a trajectory file of blocks of about one layer each (the bunny's hold
    about 100): the workers of ``icefab valves`` take a block each. ``fast_layer``: that
    layer's part path commands 300 mm^3/s (the table's top is 195)."""
    layers = []
    for k in range(n):
        first = (line_trajectory(length=600, vmax=400.0, accel=4000.0, width=3.0,
                                 role="fill", y=float(k)) if k == fast_layer
                 else line_trajectory(y=float(k)))
        layers.append(LayerMotion(index=k, z=0.25 * (k + 1), trajectories=(
            first, line_trajectory(role="travel", width=0.0),
            line_trajectory(vmax=100.0, role="fill", material="scaffold", y=5.0 + k))))
    f = tmp_path / "blocked.npz"
    save_trajectories(BuildMotion(layers=tuple(layers), job=Job()), f, block_samples=100)
    return f


def _cpus_job(tmp_path, cpus):
    f = tmp_path / f"cpus{cpus}.toml"
    f.write_text(f"[cell]\ncpus = {cpus}\n")
    return f


def test_valves_on_two_workers_write_what_one_writes(tmp_path, capsys):
    """The file's blocks shared out to two workers: the same layer files, rows, summary
    and printed lines, byte for byte, as one process reading the blocks in turn."""
    from icefab.motion import TrajectoryFile
    f = _blocked_file(tmp_path)
    with TrajectoryFile(f) as motion:
        assert len(motion.blocks()) >= 5
        assert motion.blocks({3}) == [k for k in motion.blocks()
                                      if 3 in [lm.index for lm in motion.iter_block(k)]]
    printed = {}
    for cpus in (1, 2):
        out = tmp_path / f"out{cpus}"
        assert main(["valves", str(f), "-o", str(out), "-c", str(_cpus_job(tmp_path, cpus)),
                     "--format", "both"]) == 0
        printed[cpus] = capsys.readouterr().out.replace(str(out), "OUT")
    assert printed[1] == printed[2]
    one = sorted(p.relative_to(tmp_path / "out1") for p in (tmp_path / "out1").rglob("*")
                 if p.is_file())
    two = sorted(p.relative_to(tmp_path / "out2") for p in (tmp_path / "out2").rglob("*")
                 if p.is_file())
    assert one == two and len([p for p in one if p.parts[0] == "valves"]) == 18
    for rel in one:
        a, b = (tmp_path / "out1" / rel).read_bytes(), (tmp_path / "out2" / rel).read_bytes()
        if rel.name == "valves-summary.txt":
            a, b = a.replace(b"out1", b"OUT"), b.replace(b"out2", b"OUT")
        assert a == b, rel
    rows = list(csv.DictReader((tmp_path / "out2" / "valves-paths.csv").open()))
    assert [int(r["layer"]) for r in rows] == [k for k in range(9) for _ in range(2)]
    # some layers only: the blocks that hold them, each layer once, in build order
    out = tmp_path / "some"
    assert main(["valves", str(f), "-o", str(out), "-c", str(_cpus_job(tmp_path, 2)),
                 "--layers", "7,2,3"]) == 0
    rows = list(csv.DictReader((out / "valves-paths.csv").open()))
    assert [int(r["layer"]) for r in rows] == [2, 2, 3, 3, 7, 7]
    assert sorted(p.name for p in (out / "valves").iterdir()) == [
        "layer_0002.bin", "layer_0003.bin", "layer_0007.bin"]
    for name in ("layer_0002.bin", "layer_0007.bin"):
        assert (out / "valves" / name).read_bytes() == \
            (tmp_path / "out1" / "valves" / name).read_bytes()


def test_valves_on_two_workers_stop_at_the_first_bad_layer(tmp_path, capsys):
    """A flow beyond the table in layer 6 stops the command with the error one process
    gives (the layers after it, planned by the other worker meanwhile, change nothing),
    and nothing is written."""
    f = _blocked_file(tmp_path, fast_layer=6)
    errors = {}
    for cpus in (1, 2):
        out = tmp_path / f"o{cpus}"
        rc = main(["valves", str(f), "-o", str(out), "-c", str(_cpus_job(tmp_path, cpus)),
                   "--out-of-range", "error"])
        # the error, without the progress lines (their elapsed seconds vary)
        errors[cpus] = [line for line in capsys.readouterr().err.splitlines()
                        if not re.match(r"\S+: \d+/\d+ \(", line)]
        assert rc == 2 and not out.exists()
    assert errors[1] == errors[2] and "layer 6, path 0 (part fill): flow 300" in \
        "\n".join(errors[1])


def test_valves_summary_counts_the_volume_of_paths_rounded_to_no_pulse(tmp_path, capsys):
    """Short thin paths whose volume is under half a pulse get none (eq. 6.6);
    the summary said "volume cost: none (... the volume per mm is as commanded)". It now
    states the volume the pulses lay against the volume commanded and counts those paths."""
    layers = []
    for k in range(2):   # 0.5 mm x 0.25 mm x 0.8 mm = 0.1 mm^3, 0.4 of a 0.25 mm^3 pulse
        trs = tuple(line_trajectory(length=0.8, vmax=5.0, width=0.5, role="fill", y=2.0 * i)
                    for i in range(3))
        layers.append(LayerMotion(index=k, z=0.25 * (k + 1), trajectories=trs))
    f = tmp_path / "trajectories.npz"
    save_trajectories(BuildMotion(layers=tuple(layers), job=Job()), f)
    assert main(["valves", str(f), "-o", str(tmp_path / "out")]) == 0
    text = capsys.readouterr().out
    assert "valve programs: 6 paths in 2 layers, 0 pulses" in text
    assert "volume cost: none" not in text
    (volume,) = [line for line in text.splitlines() if line.startswith("volume: ")]
    assert re.search(r"the pulses lay 0 of 0\.6\d* mm\^3 commanded \(-100\.0 %\)", volume)
    assert "6 paths get no pulse (their volume is under half of the valve's smallest " \
        "pulse" in volume
    (cost,) = [line for line in text.splitlines() if "volume cost" in line]
    assert "6 paths get no pulse" in cost


def test_valves_summary_volume_of_long_paths_is_within_half_a_pulse_each(tmp_path, traj_file,
                                                                          capsys):
    assert main(["valves", str(traj_file), "-o", str(tmp_path / "out")]) == 0
    (volume,) = [line for line in capsys.readouterr().out.splitlines()
                 if line.startswith("volume: ")]
    assert "the pulses lay 150 of 150 mm^3 commanded (-0.0 %)" in volume
    assert volume.endswith("every path gets a pulse")
