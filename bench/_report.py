"""Shared by the benchmarks: replace one section of BENCHMARKS.md with new figures."""
from __future__ import annotations

import re
from pathlib import Path

from icefab.atomic import write_atomic

BENCHMARKS = Path(__file__).resolve().parents[1] / "BENCHMARKS.md"


def write_section(heading: str, text: str, path: Path = BENCHMARKS) -> None:
    """Replace the section that starts with ``heading`` (up to the next ``## ``) by
    ``text``, or append it when the heading is missing. ``text`` starts with the heading."""
    doc = path.read_text(encoding="utf-8")
    start = doc.find(heading)
    if start < 0:
        doc = doc.rstrip("\n") + "\n\n" + text
    else:
        m = re.search(r"^## ", doc[start + len(heading):], flags=re.M)
        end = start + len(heading) + m.start() if m else len(doc)
        doc = doc[:start] + text + "\n" + doc[end:]
    write_atomic(path, doc)
