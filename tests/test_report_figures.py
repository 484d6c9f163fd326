"""report draws on matplotlib Figure objects: the caller's backend and pyplot state stay."""

from __future__ import annotations

import matplotlib
import numpy as np

from icefab import report


def test_pictures_leave_the_callers_matplotlib_alone(tmp_path):
    before = matplotlib.get_backend()
    matplotlib.use("pdf")  # a caller's choice (any non-Agg backend)
    try:
        fig, axes = report.pyplot().subplots(1, 2, figsize=(4, 2), sharex=True)
        axes[0].plot(np.arange(3), np.arange(3))
        out = report.save_figure(fig, tmp_path / "f.png")
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert matplotlib.get_backend() == "pdf"
        import matplotlib.pyplot as plt
        assert plt.get_fignums() == []  # nothing registered with pyplot
    finally:
        matplotlib.use(before)


def test_an_empty_layer_is_drawn_without_a_warning(tmp_path):
    """A layer with no region and no path (a part scaled to nothing): the picture is
    drawn, and matplotlib's 'No artists with labels found to put in legend' does not reach
    the user's terminal (settings_walk found it at parts.scale = 0.0001)."""
    import warnings

    from icefab.config import Job
    from icefab.core import Layer, LayerPaths, Region, Stack

    job = Job()
    stack = Stack(layers=(Layer(index=0, z=0.125, part=Region(), top_z=0.25),), job=job,
                  layer_thickness=0.25)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report.plot_toolpaths(stack, {0: LayerPaths(index=0, z=0.125, paths=())}, [0],
                              tmp_path / "paths.png")
    assert (tmp_path / "paths.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
