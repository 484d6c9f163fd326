"""The core types: a Toolpath's own checks, and the ragged-array helpers against numpy's
own forms."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from icefab.core import offsets, split_rows

_counts = st.lists(st.integers(0, 10_000), max_size=300)


@given(_counts)
def test_offsets_are_the_cumulated_counts_from_0(counts):
    want = np.concatenate([[0], np.cumsum(np.array(counts, dtype=np.int64))])
    for given_as in (counts, np.array(counts, dtype=np.int64), tuple(counts)):
        got = offsets(given_as)
        assert got.dtype == np.int64 and got.shape == (len(counts) + 1,)
        np.testing.assert_array_equal(got, want)


@given(st.integers(0, 50), st.lists(st.integers(-5, 60), max_size=12))
def test_split_rows_are_np_split_views(n, cuts):
    a = np.arange(2 * n, dtype=np.float64).reshape(n, 2)
    want = np.split(a, np.array(cuts, dtype=np.int64))
    got = split_rows(a, np.array(cuts, dtype=np.int64))
    assert len(got) == len(want)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
        assert g.shape == w.shape and (g.size == 0 or np.shares_memory(g, a))


@pytest.mark.parametrize("kw", [{"role": "fil"}, {"frame": "world"}, {"material": "oil"},
                                {"tool": "nozzle"}, {"width": -1.5}, {"width": float("nan")},
                                {"width": float("inf")}])
def test_a_toolpath_refuses_names_and_widths_it_does_not_know(kw):
    # a tester's role "fil" was planned and got no pulse, frame "world" was taken as the
    # part frame, a width of -1.5 or NaN as the job's fill width
    from icefab.core import Toolpath
    from icefab.errors import GeometryError

    with pytest.raises(GeometryError, match="Toolpath: "):
        Toolpath(points=np.zeros((3, 2)), **kw)
    Toolpath(points=np.zeros((3, 2)), role="measure", tool="laser", frame="base", width=0.0)


def test_region_depth_climbs_every_ring_and_names_a_circle():
    # a Region a program built with parents in a circle made depth() loop for ever
    from icefab.core import Region
    from icefab.errors import GeometryError

    sq = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert Region((sq,) * 4, np.array([-1, 0, 1, -1])).depth().tolist() == [0, 1, 2, 0]
    with pytest.raises(GeometryError, match="runs in a circle"):
        Region((sq, sq), np.array([1, 0])).depth()
