"""Every numeric setting at both ends of its declared range (issue 10), fast part: the job
is refused with one line, or it is accepted and the demo mug passes (or is refused in one
line by) every check made before work starts: placement against the cell and the layer
budget. The whole pipeline at both ends, under 2 GiB and a time limit, is
bench/settings_walk.py (results in BENCHMARKS.md)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

import icefab
from icefab import Job
from icefab.errors import ConfigError, IcefabError
from icefab.mesh import transform
from icefab.workload import check_placed_part

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from settings_walk import numeric_settings  # noqa: E402

CASES = [(name, i, end, bound, default)
         for name, i, lo, hi, default in numeric_settings()
         for end, bound in (("lo", lo), ("hi", hi))]
MUG = icefab.demo_mug()


def test_the_walk_covers_every_numeric_setting():
    names = {c[0] for c in CASES}
    assert len(names) > 80 and "cell.stroke_mm" in names and "flow.tick_s" in names


@pytest.mark.parametrize("name, i, end, bound, default", CASES,
                         ids=[f"{c[0]}{'' if c[1] is None else f'[{c[1]}]'}-{c[2]}"
                              for c in CASES])
def test_both_ends_work_or_are_refused_in_one_line(name, i, end, bound, default):
    assert bound is not None
    value = bound
    if i is not None:
        value = list(default)
        value[i] = bound
    try:
        job = Job().replace(**{name: value})
    except ConfigError as exc:
        assert "\n" not in str(exc) and name in str(exc)
        return
    try:
        placed = transform(MUG, job.parts, job)
        check_placed_part(placed.vertices, job)
    except IcefabError as exc:
        assert "\n" not in str(exc)
