"""gdpt.reconstruct.registry: a renamed entry's deprecated alias, and messages that name only
current entries."""

from __future__ import annotations

import warnings

import pytest
from gdpt.reconstruct.registry import Registry


@pytest.fixture
def methods() -> Registry[str]:
    """Two entries, ``new`` also known by its former name ``old``."""
    registry: Registry[str] = Registry("method")
    registry.register("new", "entry")
    registry.register("other", "other entry")
    registry.alias("old", "new")
    return registry


def test_alias_is_the_same_entry_and_warns_naming_both(methods):
    with pytest.warns(DeprecationWarning, match="method 'old' is deprecated; use 'new'") as caught:
        assert methods["old"] is methods["new"]
    assert caught[0].filename == __file__  # the warning names the caller's line
    with pytest.warns(DeprecationWarning, match="method 'old' is deprecated; use 'new'"):
        assert methods.resolve("old") == "new"


def test_alias_is_a_member_but_not_listed(methods):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # only a lookup of the alias warns
        assert "old" in methods
        assert methods.resolve("new") == "new" and methods.resolve("nope") == "nope"
        methods.check(["old", "new"])
    assert list(methods) == ["new", "other"] and len(methods) == 2
    assert methods.aliases == {"old": "new"}


def test_unknown_names_list_only_current_names(methods):
    with pytest.raises(KeyError, match=r"unknown method 'nope'; valid names: new, other\W$"):
        methods["nope"]
    with pytest.raises(ValueError, match=r"unknown method 'nope'; valid names: new, other$"):
        methods.check(["nope"])


def test_alias_refuses_a_taken_name_and_an_unknown_target(methods):
    for taken in ("new", "old"):
        with pytest.raises(ValueError, match=f"method '{taken}' is already registered"):
            methods.alias(taken, "other")
    with pytest.raises(ValueError, match="unknown method 'nope'; valid names: new, other$"):
        methods.alias("older", "nope")
    with pytest.raises(ValueError, match="method 'old' is already registered"):
        methods.register("old", "entry")
