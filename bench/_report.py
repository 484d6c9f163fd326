"""Shared by the benchmarks: replace one section of BENCHMARKS.md with new figures; pick
layers evenly; count where the robot stands still."""
from __future__ import annotations

import re
from collections import Counter
from pathlib import Path
from typing import Iterable

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


def parse_settings(items: Iterable[str]) -> dict:
    """``SETTING=VALUE`` command-line items as a dict for ``Job.replace`` (values JSON:
    ``false``, ``4.5``, ``[340, 0]``). ValueError naming the item when it is not one."""
    import json
    out = {}
    for item in items:
        key, eq, value = item.partition("=")
        try:
            if not eq or not key:
                raise ValueError
            out[key] = json.loads(value)
        except ValueError:
            raise ValueError(f"{item!r}: expected SETTING=VALUE with a JSON value, e.g. "
                             "materials.part.variable_width=false") from None
    return out


def evenly_spread(n: int, k: int) -> list[int]:
    """``k`` layer indices spread evenly over ``n`` layers, the first and last left out."""
    import numpy as np
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, k + 2)[1:-1]})


def rest_stops(trajectories: Iterable) -> Counter:
    """Where the robot stands still along trajectories: every trajectory and every
    PATHSPLIT piece starts and ends at rest (thesis 4.1.1). Counts "travel moves" (a
    travel trajectory), "path starts" (any other) and "PATHSPLIT corners" (the pieces
    after a path's first)."""
    stops = Counter({"travel moves": 0, "path starts": 0, "PATHSPLIT corners": 0})
    for t in trajectories:
        if t.path is None or t.path.role == "travel":
            stops["travel moves"] += 1
        else:
            stops["path starts"] += 1
            stops["PATHSPLIT corners"] += max(len(t.pieces) - 1, 0)
    return stops
