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
