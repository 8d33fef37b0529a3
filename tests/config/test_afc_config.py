"""`[afc]` (issue 15): the adaptive feed controller's section, through the real loader and check-config.

Errors name `afc.key` (or `afc.targets."T/O".key`) and check-config exits 78;
what is valid but will not do what its author expects is a warning.
"""

from __future__ import annotations

import re
import subprocess

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config_text
from millsense.daemon.config.warnings import config_warnings
from millsense.daemon.afc.controller import FeedController
from tests.config.helpers import base, dumps, write

pytestmark = pytest.mark.quick

SHAPE = re.compile(r"^[^\s:][^:]*: .+\(.+\)$")


def with_afc(**afc) -> dict:
    doc = base()
    doc["afc"] = afc
    return doc


def problems_of(doc) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(doc))
    for p in info.value.problems:
        assert SHAPE.match(p), p
    return info.value.problems


def afc_warnings(doc) -> list[str]:
    return [w for w in config_warnings(load_config_text(dumps(doc))) if w.startswith("afc.")]


def test_left_out_it_is_off_with_the_documented_defaults():
    afc = load_config_text(dumps(base())).afc
    assert afc.enabled is False and afc.quantity == "torque"
    assert (afc.min_override_pct, afc.max_override_pct, afc.air_override_pct) == (50.0, 150.0, 100.0)
    assert afc.targets == {} and afc.target_torque_nm is None
    assert FeedController(afc).state == "off"
    assert afc_warnings(base()) == []


def test_targets_by_tool_and_operation_load():
    doc = with_afc(targets={"12/3": {"torque_nm": 18.0}, "12/*": {"torque_nm": 15.0, "allow": True},
                            "4/7": {"allow": False}})
    afc = load_config_text(dumps(doc)).afc
    assert sorted(afc.targets) == ["12/*", "12/3", "4/7"]
    assert afc.targets["4/7"].allow is False and afc.targets["12/3"].torque_nm == 18.0


@pytest.mark.parametrize("key", ["12", "12/", "/3", "12/x", "x/3", "12/3/4", "12/70000", "4294967296/1", "*/3"])
def test_a_target_key_that_is_not_tool_slash_operation_is_named(key):
    (problem,) = problems_of(with_afc(targets={key: {"torque_nm": 10.0}}))
    shown = key if key.isalnum() else f'"{key}"'                       # quoted as TOML quotes it
    assert problem.startswith(f"afc.targets.{shown}: ") and "TOOL/OPERATION" in problem


@pytest.mark.parametrize(
    "afc,named",
    [
        ({"min_override_pct": 0.0}, "afc.min_override_pct"),
        ({"min_override_pct": 100.0}, "afc.min_override_pct"),
        ({"max_override_pct": 99.0}, "afc.max_override_pct"),
        ({"max_override_pct": 201.0}, "afc.max_override_pct"),
        ({"air_override_pct": 40.0}, "afc.air_override_pct"),          # below min_override_pct
        ({"quantity": "speed"}, "afc.quantity"),
        ({"rate_pct_s": 0.0}, "afc.rate_pct_s"),
        ({"target_torque_nm": -1.0}, "afc.target_torque_nm"),
        ({"enable": True}, "afc.enable"),                              # a typo is an error, not a default
        ({"targets": {"12/3": {"torque_nm": 0.0}}}, 'afc.targets."12/3".torque_nm'),
        ({"targets": {"12/3": {"torqe_nm": 5.0}}}, 'afc.targets."12/3".torqe_nm'),
    ],
)
def test_a_bad_value_names_its_key(afc, named):
    (problem,) = problems_of(with_afc(**afc))
    assert problem.split(": ")[0] == named, problem


def test_a_material_whose_load_barely_follows_the_feed_needs_a_process_gain():
    doc = with_afc()
    doc["material"] = {"ks_exp": -0.95}
    (problem,) = problems_of(doc)
    assert problem.startswith("afc.process_gain:")
    doc["afc"] = {"process_gain": 0.5}
    load_config_text(dumps(doc))


@pytest.mark.parametrize(
    "afc,named",
    [
        ({"targets": {"12/x": {"torque_nm": 10.0}}}, 'afc.targets."12/x"'),
        ({"min_override_pct": 100.0}, "afc.min_override_pct"),
    ],
)
def test_check_config_exits_78_naming_the_key(millsense_cmd, tmp_path, afc, named):
    p = subprocess.run(millsense_cmd + ["check-config", str(write(tmp_path, with_afc(**afc)))], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 78, (p.stdout, p.stderr)
    assert "Traceback" not in p.stderr
    lines = p.stderr.strip().splitlines()
    assert [line.split(": ")[0] for line in lines] == [named], lines


def test_an_air_override_above_100_warns():
    (warning,) = afc_warnings(with_afc(air_override_pct=110.0))
    assert warning.startswith("afc.air_override_pct:")
    assert afc_warnings(with_afc(air_override_pct=100.0)) == []


def test_a_target_for_another_quantity_is_never_used_and_says_so():
    doc = with_afc(quantity="force", target_torque_nm=10.0, targets={"12/3": {"torque_nm": 18.0, "force_n": 900.0}})
    warnings = afc_warnings(doc)
    assert [w.split(":")[0] for w in warnings] == ["afc.target_torque_nm", 'afc.targets."12/3".torque_nm'], warnings
    assert afc_warnings(with_afc(quantity="force", targets={"12/3": {"force_n": 900.0}})) == []


def test_a_rate_too_slow_to_follow_a_step_warns():
    (warning,) = afc_warnings(with_afc(rate_pct_s=40.0))              # 100 -> 50 % takes 1.25 s
    assert warning.startswith("afc.rate_pct_s:")
    assert afc_warnings(with_afc(rate_pct_s=50.0)) == []               # exactly 1 s


def test_on_at_start_needs_the_interlock_whose_heartbeat_lets_the_watchdog_reset_the_override():
    doc = with_afc(enabled=True)
    doc["interlock"] = {"enabled": False}
    (problem,) = [p for p in problems_of(doc) if p.startswith("afc.enabled")]
    assert "interlock" in problem and "watchdog" in problem
    doc["interlock"] = {"enabled": True}
    assert load_config_text(dumps(doc)).afc.enabled is True
