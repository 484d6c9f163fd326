"""Input files are regular files of bounded size, refused in one line before reading."""
from __future__ import annotations

import os
import threading

import pytest

from icefab import inputs
from icefab.config import load_job
from icefab.errors import ConfigError, FlowError, MeshError
from icefab.flow import calibration_for, load_calibration
from icefab import Job


def test_dev_zero_is_refused_without_reading(monkeypatch):
    with pytest.raises(ConfigError, match="/dev/zero: job file is a character device"):
        load_job("/dev/zero")
    with pytest.raises(FlowError, match="/dev/zero: calibration table is a character device"):
        load_calibration("/dev/zero")


def test_a_fifo_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "job.toml"
    os.mkfifo(fifo)
    result = []
    t = threading.Thread(target=lambda: result.append(pytest.raises(ConfigError, load_job, fifo)))
    t.start()
    t.join(10)
    assert not t.is_alive(), "load_job blocked on a FIFO"
    assert "FIFO" in str(result[0].value)


def test_a_folder_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="is a folder"):
        load_job(tmp_path)


def test_files_over_the_limit_are_refused_before_reading(tmp_path, monkeypatch):
    f = tmp_path / "big.toml"
    f.write_text("# " + "x" * 100 + "\n")
    monkeypatch.setitem(inputs.MAX_BYTES, "job", 64)
    with pytest.raises(ConfigError, match="larger than the 64 bytes limit for job files"):
        load_job(f)


def test_calibration_file_setting_names_the_setting():
    job = Job().replace(**{"materials.part.calibration_file": "/dev/zero"})
    with pytest.raises(FlowError, match=r"materials.part.calibration_file\) is a character"):
        calibration_for("part", job)


def test_binary_job_file_is_one_line(tmp_path):
    f = tmp_path / "job.toml"
    f.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load_job(f)


def test_mesh_loader_refuses_dev_zero_fifo_and_oversize(tmp_path, monkeypatch):
    from icefab.mesh import load_mesh
    with pytest.raises(MeshError, match="/dev/zero: mesh file is a character device"):
        load_mesh("/dev/zero")
    fifo = tmp_path / "part.stl"
    os.mkfifo(fifo)
    result = []
    t = threading.Thread(target=lambda: result.append(pytest.raises(MeshError, load_mesh, fifo)))
    t.start()
    t.join(10)
    assert not t.is_alive(), "load_mesh blocked on a FIFO"
    assert "FIFO" in str(result[0].value)
    big = tmp_path / "big.stl"
    big.write_bytes(b"\0" * 200)
    monkeypatch.setitem(inputs.MAX_BYTES, "mesh", 100)
    with pytest.raises(MeshError, match="larger than the 100 bytes limit for mesh files"):
        load_mesh(big)


def test_a_file_just_over_the_limit_is_told_in_bytes(tmp_path):
    # "job file is 1 MiB, larger than the 1 MiB limit" (a tester's)
    from icefab.config import load_job

    big = tmp_path / "big.toml"
    big.write_text("[slicing]\nlayer_thickness_mm = 0.25\n" + "#" * (1 << 20))
    with pytest.raises(ConfigError, match=r"big.toml: job file is 1048612 bytes, larger than "
                                          r"the 1 MiB \(1048576 bytes\) limit"):
        load_job(big)
