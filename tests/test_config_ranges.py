"""Every numeric setting has a documented, physically meaningful range (issue 10), and the
settings the issue found surviving validation but not the pipeline are refused."""
from __future__ import annotations

import dataclasses
import typing

import pytest

from icefab import Job
from icefab.config import job_from_dict
from icefab.errors import ConfigError


def _numeric_settings(obj, prefix=""):
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _numeric_settings(value, f"{prefix}{f.name}.")
            continue
        items = value if isinstance(value, tuple) else (value,)
        if hints[f.name] is bool or not items:
            continue
        if any(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            yield f"{prefix}{f.name}", f


NUMERIC = list(_numeric_settings(Job()))


def test_there_are_many_numeric_settings():
    assert len(NUMERIC) > 80


@pytest.mark.parametrize("name, f", NUMERIC, ids=[n for n, _ in NUMERIC])
def test_every_numeric_setting_has_both_bounds(name, f):
    meta = f.metadata
    assert meta["lo"] is not None and meta["hi"] is not None, name
    assert meta["lo"] < meta["hi"]
    # a bound that is not self-evident (a fraction, an angle) says what it means
    evident = (meta["lo"], meta["hi"]) in ((0.0, 1.0), (0.0, 90.0), (1, 3), (0.0, 180.0))
    assert evident or meta.get("why"), f"{name}: range {meta['lo']}..{meta['hi']} undocumented"


def _data(name, value):
    data: dict = {}
    node = data
    *head, last = name.split(".")
    for key in head:
        node = node.setdefault(key, {})
    node[last] = value
    return data


# issue 10's list of settings the validator accepted but the pipeline could not survive
@pytest.mark.parametrize("name, value", [
    ("slicing.layer_thickness_mm", 1e-6), ("slicing.layer_thickness_mm", 1e-300),
    ("parts.scale", [1e300, 1e300, 1e300]),
    ("materials.part.fill_width_mm", 1e-6), ("feedback.measure_spacing_mm", 1e-6),
    ("flow.max_piece_s", 1e-6), ("flow.tick_s", 1e-300), ("motion.dt_s", 1e6),
    ("scaffold.buffer_mm", 1e6), ("motion.speed_mm_s", 1e-6),
    ("motion.travel_speed_mm_s", 1e-6), ("motion.measure_speed_mm_s", 1e-6),
    ("motion.boundary_speed_mm_s", 1e-6), ("motion.fill_speed_mm_s", 1e-6),
    ("motion.point_spacing_mm", 1e-6), ("feedback.grid_mm", 1e-6),
    ("simulation.grid_mm", 1e-6), ("parts.copies", [100, 100, 10000]),
    ("cell.reach_mm", [163, 1e300]), ("simulation.debris_rate", 1e300),
    ("flow.layer_scale", 1e-6), ("simulation.noise_mm", 1e300), ("cell.cpus", 1000000),
])
def test_issue_settings_are_refused_with_one_line(name, value):
    with pytest.raises(ConfigError) as err:
        job_from_dict(_data(name, value))
    msg = str(err.value)
    assert msg.startswith(name) and "\n" not in msg


def test_reach_cannot_exceed_the_arm():
    with pytest.raises(ConfigError, match=r"cell.reach_mm .* cell.l1_mm \+ cell.l2_mm = 600"):
        job_from_dict({"cell": {"reach_mm": [163, 700]}})
    assert job_from_dict({"cell": {"reach_mm": [163, 700], "l1_mm": 500}}).cell.reach_mm[1] == 700


def test_a_simulated_liquid_that_flows_less_than_a_grid_cell_is_refused():
    """simulation.spread_mm = 0 ('off') let every layer's bead overlaps and gaps stack up:
    ridges of +16.5 mm and holes of -9.7 mm on the demo mug's first 60 layers (15 mm),
    and 0.25 at a 0.5 mm grid still left -5.7 mm holes; a control review's. The setting's
    range says why, and the grid it must cover."""
    with pytest.raises(ConfigError, match=r"^simulation.spread_mm = 0.0: must be >= 0.1 and "
                                          r"<= 50 \(water and SME spread"):
        job_from_dict({"simulation": {"spread_mm": 0.0}})
    with pytest.raises(ConfigError, match=r"^simulation.spread_mm = 0.25: must be >= "
                                          r"simulation.grid_mm = 0.5 .*lower "
                                          r"simulation.grid_mm"):
        job_from_dict({"simulation": {"spread_mm": 0.25}})
    assert job_from_dict({"simulation": {"spread_mm": 0.25, "grid_mm": 0.25}}
                         ).simulation.spread_mm == 0.25


def test_a_stored_job_from_before_the_spread_bound_still_loads(tmp_path):
    """Result files, build folders and cells store their job; 0 ('no spreading') and
    spreads under a grid cell were valid when they were written, and after the bound every
    later command refused a stack or paths file made with one, though none but the
    simulator reads it (a review's). Read back as stored, such a spread is raised to its
    least valid value; a job file given by the user is still refused; what was never
    valid (negative, NaN, not a number) stays refused."""
    from icefab.config import load_job, stored_job_from_dict
    from icefab.resultfiles import _job_from_toml

    assert stored_job_from_dict({"simulation": {"spread_mm": 0.0}}).simulation.spread_mm \
        == 0.5 == Job().simulation.grid_mm
    assert stored_job_from_dict({"simulation": {"spread_mm": 0.0, "grid_mm": 0.1}}
                                ).simulation.spread_mm == 0.1
    assert stored_job_from_dict({"simulation": {"spread_mm": 0.3, "grid_mm": 1.0}}
                                ).simulation.spread_mm == 1.0
    assert stored_job_from_dict({"simulation": {"spread_mm": 2.0}}).simulation.spread_mm \
        == 2.0
    for bad in (-1.0, float("nan"), "0", True):
        with pytest.raises(ConfigError, match="simulation.spread_mm"):
            stored_job_from_dict({"simulation": {"spread_mm": bad}})
    assert _job_from_toml("[simulation]\nspread_mm = 0.0\n").simulation.spread_mm == 0.5
    f = tmp_path / "job.toml"
    f.write_text("[simulation]\nspread_mm = 0.0\n")
    assert load_job(f, stored=True).simulation.spread_mm == 0.5
    with pytest.raises(ConfigError, match=r"job.toml:2: simulation.spread_mm = 0.0"):
        load_job(f)
