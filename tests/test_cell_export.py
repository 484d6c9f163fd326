"""``icefab export``: the V+ server file and its bad-input answers."""

from __future__ import annotations

import numpy as np
import pytest

from icefab import Job, LayerPaths, Path, Toolpaths
from icefab.cli import main
from icefab.motion import plan_toolpaths, save_trajectories


def small_motion(n_layers=2, job=None):
    """Two materials, a travel and a measurement path per layer, on the default cell."""
    job = job or Job().replace(**{"cell.cpus": 1})
    th = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    layers = []
    for k in range(n_layers):
        z = 0.5 * (k + 1)
        ring = Path(points=np.c_[20 * np.cos(th), 20 * np.sin(th)], z=z, material="part",
                    role="boundary", closed=True, width=1.5, layer=k)
        sq = np.array([[-8.0, -8.0], [8.0, -8.0], [8.0, 8.0], [-8.0, 8.0]])
        fill = Path(points=sq, z=z, material="scaffold", role="fill", closed=True,
                    width=3.0, layer=k)
        travel = Path(points=np.array([[20.0, 0.0], [-8.0, -8.0]]), z=z, role="travel",
                      layer=k)
        layers.append(LayerPaths(index=k, z=z, paths=(ring, travel, fill)))
    return plan_toolpaths(Toolpaths(layers=tuple(layers), job=job), job)


def test_export_vplus_writes_the_server_sized_for_the_trajectories(tmp_path, capsys):
    motion = small_motion()
    save_trajectories(motion, tmp_path / "t.npz")
    assert main(["export", "vplus", str(tmp_path / "t.npz"), "-o", str(tmp_path / "out"),
                 "--port", "7300"]) == 0
    text = (tmp_path / "out" / "icefab_server.v2").read_bytes()
    assert b"\r\n" in text and b"ice.port = 7300" in text and b"ice.maxpts = 1024" in text
    assert "untested on a controller" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--port", "0"], "--port 0: expected 1..65535"),
    (["--valve-output", "98"], "name the same output"),
    (["missing.npz"], "missing.npz: trajectories file not found"),
])
def test_export_vplus_bad_input_is_one_line_and_exit_2(tmp_path, capsys, monkeypatch,
                                                       argv, message):
    monkeypatch.chdir(tmp_path)
    assert main(["export", "vplus", "-o", "out", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_export_vplus_refuses_a_corrupt_trajectories_file(tmp_path, capsys):
    (tmp_path / "bad.npz").write_bytes(b"PK\x03\x04 not really")
    assert main(["export", "vplus", str(tmp_path / "bad.npz"), "-o",
                 str(tmp_path / "out")]) == 2
    assert "bad.npz" in capsys.readouterr().err
