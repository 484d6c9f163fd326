"""CLI framework: one-line errors, exit codes, atomic output folders, progress."""
import io

import pytest

from icefab.cli import main
from icefab.cli.common import Progress, output_dir


def test_output_dir_appears_only_on_success(tmp_path):
    target = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with output_dir(target) as d:
            (d / "half.txt").write_text("x")
            raise RuntimeError("stage failed")
    assert not target.exists()
    assert list(tmp_path.iterdir()) == []
    with output_dir(target) as d:
        (d / "a.txt").write_text("1")
    assert (target / "a.txt").read_text() == "1"


def test_output_dir_keeps_old_results_when_a_rerun_fails(tmp_path):
    target = tmp_path / "out"
    with output_dir(target) as d:
        (d / "a.txt").write_text("old")
    with pytest.raises(ValueError):
        with output_dir(target) as d:
            (d / "a.txt").write_text("new")
            raise ValueError
    assert (target / "a.txt").read_text() == "old"


def test_progress_prints_final_line():
    stream = io.StringIO()
    p = Progress("slicing", stream=stream)
    for i in range(1, 101):
        p(i, 100)
    lines = stream.getvalue().splitlines()
    assert lines[-1].startswith("slicing: 100/100 (100 %")


def test_help_lists_the_subcommands(capsys):
    with pytest.raises(SystemExit) as ex:
        main(["--help"])
    assert ex.value.code == 0
    assert "COMMAND" in capsys.readouterr().out


def test_parse_layers():
    import pytest as _pytest

    from icefab.cli.common import parse_layers
    from icefab.errors import ConfigError

    assert parse_layers(None, 101) == [0, 33, 67, 100]
    assert parse_layers("5, 7", 10) == [5, 7]
    assert parse_layers(None, 0) == []
    for bad in ("a,b", "10", "-1", ","):
        with _pytest.raises(ConfigError, match="--layers"):
            parse_layers(bad, 10)
