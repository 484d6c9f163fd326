"""Valve layer files: every program of a layer in one streamable file (issue 10: one file
per path made 56 000 files), and the drop-spacing figures of icefab valves' path table."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, seed, settings
from hypothesis import strategies as st

from icefab.core import Trajectory, ValveProgram
from icefab.errors import StackFileError
from icefab.flow import (LayerProgram, decode_valve_layer, encode_valve_layer,
                         encode_valve_program, format_valve_layer, parse_valve_layer,
                         read_valve_layer, write_valve_layer)


def _program(ticks, widths=None, pieces=()):
    return ValveProgram(ticks=np.asarray(ticks, np.uint16), tick_s=0.002, duration=1.5,
                        widths_us=None if widths is None else np.asarray(widths, np.uint16),
                        pieces=pieces)


programs = st.lists(st.tuples(
    st.integers(0, 10_000), st.sampled_from(["part", "scaffold"]),
    st.lists(st.integers(0, 65535), max_size=30).map(sorted), st.booleans()), max_size=6)


@seed(1313)
@settings(max_examples=60, deadline=None)
@given(st.integers(0, 100_000), programs)
def test_layer_files_round_trip_in_both_forms(layer, specs):
    progs = [LayerProgram(path, mat, _program(t, t if pwm else None))
             for path, mat, t, pwm in specs]
    for got_layer, got in (decode_valve_layer(encode_valve_layer(layer, progs)),
                           parse_valve_layer(format_valve_layer(layer, progs))):
        assert got_layer == layer and len(got) == len(progs)
        for a, b in zip(got, progs):
            assert (a.path, a.material) == (b.path, b.material)
            assert a.program.ticks.tolist() == b.program.ticks.tolist()
            assert (a.program.widths_us is None) == (b.program.widths_us is None)


def test_binary_records_hold_the_per_program_layout_unchanged():
    p = _program([1, 5, 9], pieces=(_program([2, 3]),))
    data = encode_valve_layer(7, [LayerProgram(4, "scaffold", p)])
    assert data[:4] == b"ICVL" and int.from_bytes(data[8:12], "little") == 7
    assert int.from_bytes(data[16:20], "little") == 4 and data[20] == 1  # path, valve
    length = int.from_bytes(data[24:28], "little")
    assert data[28:28 + length] == encode_valve_program(p) and len(data) == 28 + length


@seed(77)
@settings(max_examples=80, deadline=None)
@given(st.integers(0, 200), st.integers(0, 255))
def test_a_damaged_layer_file_is_a_stack_file_error(tmp_path_factory, at, xor):
    data = bytearray(encode_valve_layer(3, [LayerProgram(0, "part", _program([1, 2, 3])),
                                            LayerProgram(2, "scaffold", _program([4]))]))
    if at < len(data):
        data[at] ^= xor
    else:
        data = data[:at % len(data)]
    f = tmp_path_factory.mktemp("v") / "layer.bin"
    f.write_bytes(bytes(data))
    try:
        read_valve_layer(f)
    except StackFileError as exc:
        assert str(exc).startswith(str(f))


def test_write_and_read_layer_file(tmp_path):
    progs = [LayerProgram(1, "part", _program([10, 20]))]
    for form in ("bin", "txt"):
        write_valve_layer(5, progs, tmp_path / f"l.{form}", fmt=form)
        assert read_valve_layer(tmp_path / f"l.{form}")[0] == 5
    with pytest.raises(StackFileError, match="not found"):
        read_valve_layer(tmp_path / "none.bin")


def test_drop_spacing_of_evenly_spaced_pulses_on_a_straight_line():
    """50 mm/s along x for 2 s, a pulse every 0.05 s: drops 2.5 mm apart (analytic)."""
    from icefab.cli.valves_cmd import _drop_spacing

    dt = 0.01
    t = np.arange(201) * dt
    traj = Trajectory(dt=dt, xy=np.column_stack([50.0 * t, np.zeros_like(t)]),
                      joints=np.zeros((201, 0)), speed=np.full(201, 50.0), duration=2.0)
    prog = ValveProgram(ticks=(10 + 25 * np.arange(40)).astype(np.uint16),  # every 0.05 s
                        tick_s=0.002, duration=2.0)
    length, gap, sparse = _drop_spacing(traj, prog, min_drops_per_mm=1.0)
    assert length == pytest.approx(100.0)
    assert gap == pytest.approx(2.5)
    assert sparse == pytest.approx(39 * 2.5)          # every one of the 39 spacings
    assert _drop_spacing(traj, prog, min_drops_per_mm=0.3)[2] == 0.0   # 3.33 mm allowed
    # the same as a continuous tour on for 0.4-0.9 s and 1.2-2 s (25 + 40 mm): its drops
    # over those spans only, the 15 mm of travel between no spacing of them
    tour = dataclasses.replace(traj, on_spans=np.array([[0.4, 0.9], [1.2, 2.0]]))
    length, gap, sparse = _drop_spacing(tour, prog, min_drops_per_mm=1.0)
    assert length == pytest.approx(65.0)
    assert gap == pytest.approx(2.5)
    # 0.4-0.9 s holds the pulses at 0.42 .. 0.87 s (10, 9 spacings), 1.2-2 s those at
    # 1.22 .. 1.97 s (16, 15 spacings)
    assert sparse == pytest.approx((9 + 15) * 2.5)


def test_the_valves_summary_says_the_drop_spacing_once_for_all_materials():
    """Two kinds of too-few-drops finding (part and scaffold): the drop spacing, one figure
    over every material's paths, follows the last of them only."""
    from icefab import Job
    from icefab.cli.valves_cmd import _summary, _Volume

    found = [(0, "layer 0 part fill path: fewer than flow.min_drops_per_mm = 1 drops per mm "
                 "(0.2) at 3 samples"),
             (1, "layer 1 scaffold fill path: fewer than flow.min_drops_per_mm = 1 drops per "
                 "mm (0.3) at 2 samples"),
             (1, "layer 1 scaffold fill path: fewer than flow.min_drops_per_mm = 1 drops per "
                 "mm (0.3) at 5 samples")]
    totals = dict(paths=3, pulses=10, pieces=3, findings=3, length=2000.0, sparse=500.0)
    lines = _summary("out", 2, ("bin",), totals, 2, 3.0, 1.5, found, Job(), _Volume())
    assert sum("min_drops_per_mm" in line for line in lines) == 2     # two kinds
    said = [k for k, line in enumerate(lines) if "volume cost" in line]
    assert len(said) == 1
    assert "min_drops_per_mm" in lines[said[0] - 1] and said[0] == len(lines) - 1
    assert "affected, all materials: 0.50 m of 2.00 m deposited (25.0 %) on 2 paths" in \
        lines[said[0]]
    assert "the widest spacing, 3.00 mm, exceeds its path's width 1.50 mm" in lines[said[0]]
