"""Fuzz of the inputs a user writes: TOML jobs, legacy control files, and meshes all the way
through placement and slicing. The only outcomes allowed are a result or the documented
error (:class:`IcefabError`, one line naming the file or setting). Seeded and bounded
(the CI profile of tests/conftest.py); the 10 000-case runs under a memory limit and a
timeout are bench/fuzz_inputs.py (BENCHMARKS.md)."""
from __future__ import annotations

import math
import struct
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, seed, strategies as st

from icefab import Job
from icefab.config import load_job, to_toml
from icefab.errors import IcefabError
from icefab.mesh import prepare_parts, write_stl
from icefab.core import Mesh
from icefab.slicing import slice_mesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_config_legacy import PAPER_TABLE_1, THESIS_TABLE_3_1  # noqa: E402
from test_config_properties import ALL  # noqa: E402

NAMES = [name for name, _, _ in ALL]

numbers = st.one_of(
    st.integers(-10**30, 10**30), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -0.0, 1e-300, 1e300, 5e-324, 2**63, -2**63 - 1, 1e-6, 1e6]))
scalars = st.one_of(numbers, st.booleans(), st.text(max_size=6),
                    st.sampled_from(["cent", "orig", "3d", "zigzag", "/dev/zero", ""]))
values = st.one_of(scalars, st.lists(scalars, max_size=4))


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) \
            else repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return '"' + v.encode("unicode_escape").decode().replace('"', '\\"') + '"'
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def _check_job_file(path: Path) -> None:
    try:
        job = load_job(path)
    except IcefabError as exc:
        msg = str(exc)
        assert "\n" not in msg and str(path) in msg, msg
    else:
        assert isinstance(job, Job)


@given(st.lists(st.tuples(st.sampled_from(NAMES), values), min_size=1, max_size=6))
def test_toml_jobs_of_random_settings(tmp_path_factory, entries):
    lines = []
    for name, value in entries:
        *table, key = name.split(".")
        lines.append(f"[{'.'.join(table)}]\n{key} = {_toml_value(value)}\n" if table
                     else f"{key} = {_toml_value(value)}\n")
    f = tmp_path_factory.mktemp("toml") / "job.toml"
    f.write_text("".join(lines))
    _check_job_file(f)


DEFAULT_TOML = to_toml(Job()).encode()


@given(st.lists(st.tuples(st.integers(0, len(DEFAULT_TOML) - 1), st.binary(max_size=4)),
                min_size=1, max_size=8))
def test_toml_jobs_with_corrupted_bytes(tmp_path_factory, edits):
    data = bytearray(DEFAULT_TOML)
    for at, new in edits:
        data[at:at + len(new)] = new
    f = tmp_path_factory.mktemp("tomlb") / "job.toml"
    f.write_bytes(bytes(data))
    _check_job_file(f)


legacy_tokens = st.one_of(
    st.sampled_from(["inf", "-inf", "nan", "1e400", "-1e400", "0", "1", "2", "-1", "2.5",
                     "1e30", "cent", "orig", "x.stl", "[mm]", "(> 0)", "", "1e-300"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr), st.text(max_size=5))


@given(st.sampled_from([PAPER_TABLE_1, THESIS_TABLE_3_1]),
       st.lists(st.tuples(st.integers(0, 40), st.integers(0, 6), legacy_tokens),
                min_size=1, max_size=6),
       st.lists(st.integers(0, 40), max_size=2))
def test_legacy_control_files_with_corrupted_entries(tmp_path_factory, table, edits, drops):
    lines = table.splitlines()
    for line_no, tok_no, token in edits:
        words = lines[line_no % len(lines)].split(" ")
        words[tok_no % len(words)] = token
        lines[line_no % len(lines)] = " ".join(words)
    for d in drops:
        if lines:
            del lines[d % len(lines)]
    f = tmp_path_factory.mktemp("legacy") / "control.txt"
    f.write_text("\n".join(lines) + "\n")
    _check_job_file(f)


_BOX = trimesh.creation.box(extents=(30.0, 20.0, 10.0))
_BOX_MESH = Mesh(np.asarray(_BOX.vertices), np.asarray(_BOX.faces, np.int64), "box")


@given(st.lists(st.tuples(st.integers(0, 12 * 9 - 1), st.integers(0, 31)), min_size=1,
                max_size=3))
def test_bit_flipped_stl_coordinates_slice_or_are_refused(tmp_path_factory, flips):
    """A bit flip in a binary STL coordinate (issue 10: loaded fine, then slicing failed
    with 'Maximum allowed size exceeded') goes through placement and slicing."""
    d = tmp_path_factory.mktemp("flip")
    f = d / "part.stl"
    write_stl(_BOX_MESH, f)
    data = bytearray(f.read_bytes())
    for k, bit in flips:
        at = 84 + 50 * (k // 9) + 12 + 4 * (k % 9)
        (word,) = struct.unpack_from("<I", data, at)
        struct.pack_into("<I", data, at, word ^ (1 << bit))
    f.write_bytes(bytes(data))
    job = Job().replace(**{"parts.files": [str(f)], "slicing.layer_thickness_mm": 1.0,
                           "cell.cpus": 1})
    try:
        stack = slice_mesh(prepare_parts(job), job)
    except IcefabError as exc:
        assert "\n" not in str(exc)
    else:
        assert 1 <= len(stack) <= 210
