"""The options record (:class:`gpupro.technique.Options`): frozen, hashable, read by name or by group."""

import pytest

from gpupro.technique import Option, Options, Technique, integer


def _spec():
    return Technique(id="t", title="t", source="s", family="post", status="implemented", apply=lambda *a: None,
                     options=(Option("tile", 8, integer(1), "tile", group="grid"),
                              Option("levels", 2, integer(1), "levels", group=("grid", "lut")),
                              Option("steps", 4, integer(1), "steps")))


def test_the_record_is_checked_completed_and_read_by_name():
    options = _spec().options_of(steps=6)
    assert (options.tile, options["levels"], options.steps) == (8, 2, 6)
    assert list(options) == ["tile", "levels", "steps"]
    with pytest.raises(ValueError, match="tile: expected an integer >= 1"):
        _spec().options_of(tile=0)
    with pytest.raises(AttributeError, match="no option 'tiles'"):
        options.tiles


def test_groups_gather_their_options_in_declaration_order():
    options = _spec().options_of()
    assert options.group("grid") == {"tile": 8, "levels": 2}
    assert options.group("lut") == {"levels": 2}
    with pytest.raises(KeyError, match="groups: grid, lut"):
        options.group("field")


def test_the_record_is_frozen_and_hashable_by_value():
    options = _spec().options_of()
    with pytest.raises(AttributeError, match="frozen"):
        options.tile = 4
    changed = options.replace(tile=16)
    assert changed.tile == 16 and options.tile == 8
    assert changed.group("grid") == {"tile": 16, "levels": 2}
    assert hash(options) == hash(_spec().options_of()) and options != changed
    assert {options: 1}[_spec().options_of()] == 1
    with pytest.raises(AttributeError, match="no options"):
        options.replace(tiles=4)


def test_the_record_passes_as_keywords():
    def takes(*, tile, levels, steps):
        return tile + levels + steps

    assert takes(**Options({"tile": 1, "levels": 2, "steps": 3})) == 6
