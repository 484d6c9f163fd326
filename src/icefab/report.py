"""Pictures and the HTML build report.

Figures are written atomically (temporary file, then rename) so an interrupted command
never leaves a half-written picture. The HTML report is one self-contained file: every
picture is embedded, so it can be mailed or archived as it is.
"""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

from icefab.atomic import atomic_path


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | os.PathLike, *, dpi: int = 110) -> Path:
    """Write a matplotlib figure as PNG to ``path`` atomically and close it."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        pyplot().close(fig)
    return Path(path)


def _rows(data: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    rows: list[tuple[str, str]] = []
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            rows += _rows(value, name + " / ")
        elif isinstance(value, float):
            rows.append((name, f"{value:,.4g}"))
        elif isinstance(value, int) and not isinstance(value, bool):
            rows.append((name, f"{value:,}"))
        else:
            rows.append((name, str(value)))
    return rows


def html_report(title: str, summary: Mapping[str, Any],
                pictures: Sequence[tuple[str, str | os.PathLike]],
                notes: Sequence[str] = ()) -> str:
    """A self-contained HTML page: the summary as a table, then the captioned pictures.

    summary: nested plain data (e.g. the demo's summary.json); pictures: (caption, PNG
    path) pairs, embedded as base64; notes: warnings or remarks shown as a list.
    """
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;"
        "color:#222}table{border-collapse:collapse}td{padding:2px 12px;border-bottom:1px "
        "solid #ddd}td:last-child{text-align:right;font-variant-numeric:tabular-nums}"
        "figure{margin:2em 0}img{max-width:100%}figcaption{color:#555}</style></head><body>",
        f"<h1>{html.escape(title)}</h1><table>",
    ]
    parts += [f"<tr><td>{html.escape(k)}</td><td>{html.escape(v)}</td></tr>"
              for k, v in _rows(summary)]
    parts.append("</table>")
    if notes:
        parts.append("<h2>Notes</h2><ul>")
        parts += [f"<li>{html.escape(n)}</li>" for n in notes]
        parts.append("</ul>")
    for caption, png in pictures:
        data = base64.b64encode(Path(png).read_bytes()).decode("ascii")
        parts.append(f"<figure><img alt='{html.escape(caption)}' "
                     f"src='data:image/png;base64,{data}'>"
                     f"<figcaption>{html.escape(caption)}</figcaption></figure>")
    parts.append("</body></html>")
    return "\n".join(parts)
