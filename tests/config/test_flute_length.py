"""`flute_length_mm` of `[tool]` and `[tools.N]` (issue 36, additive): the deepest axial depth a tool can
cut. Left out: twice that tool's own diameter; given: taken as written; not a positive finite number: a
problem naming the key, through the real loader."""

from __future__ import annotations

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config_text
from millsense.daemon.physics import validity
from millsense.daemon.pipeline.per_revolution import tool_geometries
from tests.config.helpers import base, dumps

pytestmark = pytest.mark.quick


def _doc(**tool_extra) -> dict:
    doc = base()
    doc["tools"] = {"12": {"diameter_mm": 6.0, "flutes": 3, **tool_extra}, "3": {"diameter_mm": 10.0, "flutes": 2}}
    return doc


def test_left_out_it_is_twice_each_tools_own_diameter():
    s = load_config_text(dumps(_doc()))
    default, listed = tool_geometries(s)
    assert default.flute_length_mm == validity.FLUTE_LENGTH_PER_DIAMETER * s.tool.diameter_mm
    assert listed[12].flute_length_mm == validity.FLUTE_LENGTH_PER_DIAMETER * 6.0
    assert listed[3].flute_length_mm == validity.FLUTE_LENGTH_PER_DIAMETER * 10.0


def test_given_it_is_taken_for_that_tool_only():
    doc = _doc(flute_length_mm=25)            # a whole number is a length too
    doc["tool"]["flute_length_mm"] = 55.5
    default, listed = tool_geometries(load_config_text(dumps(doc)))
    assert default.flute_length_mm == 55.5 and listed[12].flute_length_mm == 25.0
    assert listed[3].flute_length_mm == validity.FLUTE_LENGTH_PER_DIAMETER * 10.0   # not [tool]'s


@pytest.mark.parametrize("value", [0.0, -1.0, "long"])
def test_a_length_that_is_not_positive_names_the_key(value):
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(_doc(flute_length_mm=value)))
    assert [p for p in info.value.problems if p.startswith("tools.12.flute_length_mm: ")], info.value.problems
