"""The public API promised by DESIGN.md and the README resolves and is documented."""
import icefab


def test_every_public_name_resolves_and_has_a_docstring():
    for name in icefab.__all__:
        obj = getattr(icefab, name)
        assert (obj.__doc__ or "").strip(), f"icefab.{name} has no docstring"


def test_unknown_names_raise_attribute_error():
    try:
        icefab.no_such_stage
    except AttributeError as exc:
        assert "no_such_stage" in str(exc)
    else:
        raise AssertionError("icefab.no_such_stage resolved")
