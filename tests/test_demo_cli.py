"""`icefab demo` end to end (on the first layers of the mug, to keep CI short)."""
import json

import pytest

from icefab.cli import main


def test_demo_writes_every_stage(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--layers", "24", "--sim-layers", "24"]) == 0
    for name in ("demo-mug.stl", "stack.npz", "toolpaths.npz", "trajectories.npz",
                 "layers.png", "summary.json", "report.html", "simulation/rms_vs_height.png",
                 "valves/layer_0000.txt"):
        assert (out / name).stat().st_size > 0, name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["slice"]["layers"] == 24
    assert summary["valves"]["pulses"] > 0
    # valve-limit findings condensed to one line per kind, printed as they are saved
    text = capsys.readouterr().out
    assert all(f"  {line}" in text for line in summary["valves"]["findings"])
    assert summary["motion"]["build_s"] > 0 and summary["motion"]["samples"] > 0
    sim = summary["simulation"]
    assert sim["final_rms_smf_mm"] < sim["final_rms_open_loop_mm"]
    assert "wrote" in text
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 3  # self-contained: pictures embedded


def test_demo_rejects_negative_layers(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path / "x"), "--layers", "-1"]) == 2
    assert "--layers -1" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_a_simulation_without_a_measurement_is_refused_before_any_work(tmp_path):
    """feedback.interval_layers beyond the simulated layers: SMF would never act (the
    settings walk found an IndexError after the whole pipeline); one line, nothing
    written, before slicing."""
    import subprocess
    import sys

    job = tmp_path / "job.toml"
    job.write_text("[feedback]\ninterval_layers = 1000\n")
    r = subprocess.run([sys.executable, "-m", "icefab", "demo", "-c", str(job), "--layers",
                        "4", "--sim-layers", "4", "-o", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and len(r.stderr.splitlines()) == 1, r.stderr
    assert "feedback.interval_layers = 1000" in r.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("layers", [1, 2])
def test_demo_of_one_or_two_layers(tmp_path, capsys, layers):
    """The pictures pick their layers among those built (one layer: a traceback before)."""
    out = tmp_path / "d"
    assert main(["demo", "-o", str(out), "--layers", str(layers), "--sim-layers", "0"]) == 0
    speed = sorted(p.name for p in out.glob("speed_layer_*.png"))
    assert speed == ["speed_layer_0.png"] if layers == 1 else ["speed_layer_1.png"]
    assert "report.html" in {p.name for p in out.iterdir()}
