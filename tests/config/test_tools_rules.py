"""`[tools.N]` (issue 14): the rules of `[tool]` hold for every listed tool, through the real loader.

Across sections: a known `cut.radial_depth_mm` must fit each listed tool (any of
them may be in the spindle), and a slot's radial depth is each tool's own
diameter; the problem names `tools.N.diameter_mm`. The calibration's C_f was
fitted on `[tool]`'s cutter: it is `[tool]`'s alone. Every problem is
`tools.N.key: ...` and `millsense check-config` exits 78.
"""

from __future__ import annotations

import re
import subprocess

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config, load_config_text
from millsense.daemon.pipeline.per_revolution import tool_geometries
from tests.config.helpers import base, dumps, write

pytestmark = pytest.mark.quick

SHAPE = re.compile(r"^[^\s:][^:]*: .+\(.+\)$")


def problems_of(doc) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(doc))
    for p in info.value.problems:
        assert SHAPE.match(p), p
    return info.value.problems


def with_tools(**tables) -> dict:
    doc = base()
    doc["tools"] = {str(n.removeprefix("t")): t for n, t in tables.items()}
    return doc


def test_listed_tools_load_by_number_and_cf_model_works_per_tool():
    doc = with_tools(t12={"diameter_mm": 6.0, "flutes": 3}, t3={"diameter_mm": 10.0, "flutes": 2, "cf": "model"},
                     t4={"diameter_mm": 8.0, "flutes": 4, "cf": 1.1})
    s = load_config_text(dumps(doc))
    assert sorted(s.tools) == [3, 4, 12]
    default, listed = tool_geometries(s)
    assert (default.radius_mm, default.flutes, default.cf) == (s.tool.diameter_mm / 2, s.tool.flutes, s.tool.cf)
    assert listed[3].cf_model and listed[3].radius_mm == 5.0
    assert listed[4].cf == 1.1 and listed[4].flutes == 4
    assert listed[12].cf == s.tool.cf                  # no cf: [tool]'s


def test_a_known_radial_depth_wider_than_a_listed_tool_names_that_tool():
    doc = with_tools(t12={"diameter_mm": 6.0, "flutes": 3}, t3={"diameter_mm": 10.0, "flutes": 2})
    doc["cut"].update(mode="down", radial_depth_mm=8.0)            # fits [tool] (20 mm) and T3, not T12
    problems = problems_of(doc)
    assert len(problems) == 1
    assert problems[0].startswith("tools.12.diameter_mm: 6 is less than cut.radial_depth_mm 8")
    doc["cut"].update(radial_depth_mm=6.0)
    load_config_text(dumps(doc))                                    # exactly the diameter: fits


def test_a_slot_with_a_radial_depth_contradicts_a_tool_of_another_diameter():
    doc = with_tools(t5={"diameter_mm": 25.0, "flutes": 4})
    doc["cut"].update(mode="slot", radial_depth_mm=20.0)           # [tool]'s diameter: right for [tool]
    problems = problems_of(doc)
    assert len(problems) == 1
    assert problems[0].startswith('tools.5.diameter_mm: 25 contradicts cut.radial_depth_mm 20 with mode = "slot"')
    del doc["cut"]["radial_depth_mm"]                              # a slot: each tool's own diameter
    load_config_text(dumps(doc))


def test_the_rule_for_tool_still_holds_beside_the_tables():
    doc = with_tools(t12={"diameter_mm": 30.0, "flutes": 3})
    doc["cut"].update(mode="down", radial_depth_mm=25.0)
    assert problems_of(doc) == ["cut.radial_depth_mm: 25 is more than the tool diameter 20 (at most tool.diameter_mm)"]


def test_every_key_of_a_table_is_checked_and_named():
    doc = with_tools(t12={"diameter_mm": 0, "flutes": 1.5, "cf": 3, "helix_deg": 95})
    doc["tools"]["T7"] = {"diameter_mm": 6.0, "flutes": 2}
    doc["tools"]["9"] = {"flutes": 2}
    problems = problems_of(doc)
    named = sorted(p.split(":")[0] for p in problems)
    assert named == ["tools.12.cf", "tools.12.diameter_mm", "tools.12.flutes", "tools.12.helix_deg",
                     "tools.9.diameter_mm", "tools.T7"]


CALIBRATION = """# written by `millsense calibrate`
[tool]
cf = 1.062000
"""


def test_the_calibrated_cf_is_tool_s_alone(tmp_path):
    (tmp_path / "cal.toml").write_text(CALIBRATION)
    doc = with_tools(t12={"diameter_mm": 6.0, "flutes": 3}, t3={"diameter_mm": 10.0, "flutes": 2, "cf": 1.1})
    doc["tool"]["cf"] = 1.08
    doc["calibration"] = "cal.toml"
    s = load_config(write(tmp_path, doc))
    assert s.tool.cf == 1.062                         # calibrated on [tool]'s cutter
    assert s.tools[12].cf == 1.08                     # no cf of its own: [tool]'s as written, not the fit
    assert s.tools[3].cf == 1.1
    _, listed = tool_geometries(s)
    assert (listed[12].cf, listed[3].cf) == (1.08, 1.1)


@pytest.mark.parametrize(
    "table,named",
    [
        ({"diameter_mm": 6.0, "flutes": 0}, "tools.12.flutes"),
        ({"diameter_mm": 6.0, "flutes": 3, "cf": "modle"}, "tools.12.cf"),
        ({"diameter_mm": 4.0, "flutes": 3}, "tools.12.diameter_mm"),   # narrower than cut.radial_depth_mm
    ],
)
def test_check_config_exits_78_naming_the_tool_key(millsense_cmd, tmp_path, table, named):
    doc = with_tools(t12=table)
    doc["cut"].update(mode="down", radial_depth_mm=5.0)
    p = subprocess.run(millsense_cmd + ["check-config", str(write(tmp_path, doc))], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 78, (p.stdout, p.stderr)
    assert "Traceback" not in p.stderr
    lines = p.stderr.strip().splitlines()
    assert [line.split(":")[0] for line in lines] == [named], lines
    assert all(SHAPE.match(line) for line in lines), lines
