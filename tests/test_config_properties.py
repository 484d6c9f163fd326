"""Property and meta tests of the job configuration."""
import dataclasses

from hypothesis import given, strategies as st

from icefab import Job
from icefab.config import job_from_dict, to_dict
from icefab.errors import ConfigError


def _settings(obj, prefix=""):
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            yield from _settings(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, value


ALL = list(_settings(Job()))


def test_every_setting_is_documented():
    undocumented = [name for name, f, _ in ALL if not f.metadata.get("help")]
    assert undocumented == []


def test_defaults_satisfy_their_own_ranges():
    # Job() validates on construction; building it from its own dict must give an equal job.
    assert job_from_dict(to_dict(Job())) == Job()


toml_values = st.one_of(
    st.none(), st.booleans(), st.integers(-10**6, 10**6),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8),
    st.lists(st.one_of(st.integers(-5, 5), st.floats(-1e3, 1e3), st.text(max_size=4)),
             max_size=4),
)


@given(st.sampled_from([name for name, _, _ in ALL]), toml_values)
def test_any_value_gives_a_job_or_a_config_error(name, value):
    data: dict = {}
    node = data
    *head, last = name.split(".")
    for key in head:
        node = node.setdefault(key, {})
    node[last] = value
    try:
        job = job_from_dict(data)
    except ConfigError as exc:
        assert name.split(".")[-1] in str(exc)
    else:
        # An accepted value is stored (coerced) and the job stays valid.
        got = job
        for key in name.split("."):
            got = getattr(got, key)
        assert got is not None
