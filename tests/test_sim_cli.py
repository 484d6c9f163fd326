"""``icefab simulate`` end to end on a small saved build."""
from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from test_sim_build import annulus_toolpaths  # noqa: E402

from icefab import Job  # noqa: E402
from icefab.cli import main  # noqa: E402
from icefab.paths import save_toolpaths  # noqa: E402


@pytest.fixture(scope="module")
def toolpaths_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("build") / "toolpaths.npz"
    save_toolpaths(annulus_toolpaths(Job(), 12), path)
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


def test_simulate_reports_a_missing_input(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "nothing.npz"), "-o", str(tmp_path / "o")]) == 2
    assert "nothing.npz" in capsys.readouterr().err
