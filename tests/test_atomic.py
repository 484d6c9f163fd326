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


def test_report_labels_and_numbers_are_for_people():
    """Issue 10: report.html showed raw keys and 3.524e+04."""
    page = html_report("t", {"motion": {"build_s": 35240.0, "seconds": 2.71649},
                             "simulation": {"final_rms_smf_mm": 0.0491234},
                             "paths": {"unfilled_mm2": 1234.5, "ratio": 1e-05}}, [])
    assert "3.524e+04" not in page and "35,240" in page
    assert "build motion time, minimum-time trajectories, s" in page and "build_s" not in page
    assert "2.716" in page and "0.04912" in page and "1,234" in page
    assert "unfilled, mm²" in page and "1.000e-05" in page


def test_speed_picture_draws_each_nozzle_in_the_part_frame(tmp_path, monkeypatch):
    """The scaffold nozzle's paths were drawn 8.5 mm off (base-frame end effector)."""
    import matplotlib.figure
    import numpy as np

    from icefab import Job
    from icefab.core import Toolpath, Trajectory
    from icefab.frames import to_base_frame
    from icefab.report import plot_speed

    job = Job()
    square = np.array([[0.0, 0], [10, 0], [10, 10], [0, 10], [0, 0]])
    trs = []
    for material in ("part", "scaffold"):
        p = Toolpath(points=square, material=material, role="boundary", width=1.0)
        xy = to_base_frame(square, material, job)
        trs.append(Trajectory(dt=0.1, xy=xy, joints=np.zeros((5, 0)), speed=np.ones(5),
                              duration=0.4, path=p))

    class L:
        index, z, trajectories, n_points, duration = 0, 0.25, tuple(trs), 10, 0.8

    seen = {}

    def keep(fig, *a, **k):
        ax = fig.axes[0]
        seen["segments"] = [c.get_segments() for c in ax.collections if hasattr(
            c, "get_segments")]
        seen["xlabel"] = ax.get_xlabel()

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    plot_speed(L, tmp_path / "s.png", 100.0, job)
    segs = np.concatenate([np.asarray(s) for s in seen["segments"]]).reshape(-1, 2)
    assert segs.min() == 0.0 and segs.max() == 10.0  # both on the same square
    assert "part frame" in seen["xlabel"]


def test_remove_temps_takes_only_what_make_temp_file_leaves(tmp_path):
    # a killed build's half-written report stayed beside its files (a crash hunt's
    # .report.html.<hex>.tmp); a resume holding the build's lock removes such files
    from icefab.atomic import make_temp_file, remove_temps

    left = [make_temp_file(tmp_path / "report.html"), make_temp_file(tmp_path / "status.json")]
    keep = ["report.html", ".hidden", ".report.html.tmp", ".x.0123456g.tmp", "a.1234abcd.tmp",
            ".report.html.1234abcd.npz"]
    for name in keep:
        (tmp_path / name).write_text("x")
    (tmp_path / ".dir.1234abcd.tmp").mkdir()
    assert remove_temps(tmp_path) == 2
    assert not any(f.exists() for f in left)
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted(keep + [".dir.1234abcd.tmp"])
