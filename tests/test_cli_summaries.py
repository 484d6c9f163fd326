"""What the commands print about a build says what is true of it: the unfilled area to
the precision of its warning (``icefab paths``), adaptive layers as their range of
thicknesses (``icefab slice``, ``icefab demo``), the measurement interval of adaptive
layers as a height (``icefab simulate``), a thick adaptive layer as the cause of a
flow above the valve (a review's findings)."""

from __future__ import annotations

import pytest

from icefab import Job
from icefab.cli.paths_cmd import PathTally, area_text, summary_lines
from icefab.resultfiles import LayerHead


@pytest.mark.parametrize("mm2, text", [(0.0, "0"), (0.244, "0.244"), (0.00123, "0.00123"),
                                       (1.5, "1.50"), (12.345, "12.3"), (1234.5, "1234")])
def test_areas_are_printed_to_three_significant_digits(mm2, text):
    assert area_text(mm2) == text


def test_the_paths_summary_prints_a_small_unfilled_area_as_its_warning_does():
    # the summary said "part 0 mm², scaffold 0 mm²" above a warning of 0.244 / 0.178 mm^2
    heads = [LayerHead(0, 0.125, (0.2, 0.1)), LayerHead(1, 0.375, (0.044, 0.078))]
    lines = summary_lines(heads, [], PathTally(Job()))
    assert "unfilled area: part 0.244 mm², scaffold 0.178 mm²" in lines
    none = summary_lines([LayerHead(0, 0.125, (0.0, 0.0))], [], PathTally(Job()))
    assert "unfilled area: part 0 mm², scaffold 0 mm²" in none
