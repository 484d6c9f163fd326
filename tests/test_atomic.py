"""Atomic writes: a failed write leaves the old file (or nothing), never half a file."""
import pytest

from icefab.atomic import atomic_path, write_atomic
from icefab.report import html_report, pyplot, save_figure


def test_failed_write_keeps_the_old_file(tmp_path):
    target = tmp_path / "result.txt"
    write_atomic(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["result.txt"]


def test_figure_and_report(tmp_path):
    plt = pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    png = save_figure(fig, tmp_path / "line.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page = html_report("t <&>", {"a": {"b": 1.5}, "n": 12000}, [("cap", png)], ["note"])
    assert "t &lt;&amp;&gt;" in page and "a / b" in page and "12,000" in page
    assert "data:image/png;base64," in page
