"""The calibration file overrides friction and C_f; secrets never leak."""

from __future__ import annotations

import json

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import effective_config_dict, load_config, load_config_text
from tests.config.helpers import base, dumps, write

pytestmark = pytest.mark.quick

# What `millsense calibrate` writes (daemon/commands/calibrate.py `_write_toml`).
CALIBRATION = """# written by `millsense calibrate`
[[gears]]
name = "high-speed"
friction_torque_nm = 1.712345
viscous_nms = 0.00250000
samples = 412
r2 = 0.987654

[tool]
cf = 1.062000
"""


def test_calibration_overrides_gears_by_name_and_cf(tmp_path):
    (tmp_path / "cal.toml").write_text(CALIBRATION)
    doc = base()
    doc["calibration"] = "cal.toml"
    s = load_config(write(tmp_path, doc))
    low, high = s.gears
    assert (low.friction_torque_nm, low.viscous_nms) == (2.6629, 0.0400)  # untouched: not in the file
    assert (high.friction_torque_nm, high.viscous_nms) == (1.712345, 0.0025)
    assert high.ratio == 1.157 and high.max_spindle_rpm == 4500
    assert s.tool.cf == 1.062
    assert s.calibration == str(tmp_path / "cal.toml")


def test_calibration_with_nan_r2_is_accepted(tmp_path):
    (tmp_path / "cal.toml").write_text(CALIBRATION.replace("r2 = 0.987654", "r2 = nan"))
    doc = base()
    doc["calibration"] = "cal.toml"
    assert load_config(write(tmp_path, doc)).gears[1].friction_torque_nm == 1.712345


@pytest.mark.parametrize(
    "content, expected",
    [
        (None, "calibration: {cal} does not exist (a TOML file written by `millsense calibrate`"),
        (CALIBRATION.replace('"high-speed"', '"third"'),
         'calibration: {cal}: gears[0].name: "third" is not a gear of this config (one of: low-speed, high-speed)'),
        (CALIBRATION.replace("1.712345", "-0.5"),
         "calibration: {cal}: gears[0].friction_torque_nm: must be at least 0, not -0.5 (a number ≥ 0)"),
        (CALIBRATION.replace("cf = 1.062000", "cf = 7"), "calibration: {cal}: tool.cf: 7 is outside 0.75–1.5"),
        (CALIBRATION + "\nfriction = 3\n", 'calibration: {cal}: tool.friction: unknown key'),
        ("[[gears]\n", "calibration: TOML syntax error at line 1"),
    ],
)
def test_a_bad_calibration_file_is_a_config_error_naming_calibration(tmp_path, content, expected):
    cal = tmp_path / "cal.toml"
    if content is not None:
        cal.write_text(content)
    doc = base()
    doc["calibration"] = "cal.toml"
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, doc))
    assert len(info.value.problems) == 1
    assert info.value.problems[0].startswith(expected.format(cal=cal)), info.value.problems


def test_reset_token_never_appears_in_repr_dump_or_the_config_queryable(tmp_path):
    secret = "s3cret-Token-9f2c-0123456789abcdef"
    doc = base()
    doc["interlock"].update(reset="token", reset_token=secret)
    s = load_config_text(dumps(doc))
    assert s.interlock.token() == secret
    eff = effective_config_dict(s)
    assert eff["interlock"]["reset_token"] == "***"
    for text in (repr(s), str(s), json.dumps(eff), repr(s.interlock)):
        assert secret not in text
    # the rest of the effective config is the real one
    assert eff["gears"][0]["ratio"] == 4.81 and eff["machine"] == "mch10-demo"


def test_reset_token_file_is_read_at_load_and_masked(tmp_path):
    secret = "from-a-file-77-0123456789abcdefgh"
    (tmp_path / "token").write_text(secret + "\n")
    doc = base()
    doc["interlock"].update(reset="token", reset_token_file="token")
    s = load_config(write(tmp_path, doc))
    assert s.interlock.token() == secret
    assert secret not in repr(s) and secret not in json.dumps(effective_config_dict(s))
    (tmp_path / "token").write_text("\n")
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path, doc))
    assert info.value.problems[0].startswith(f"interlock.reset_token_file: {tmp_path / 'token'} is empty")


def test_token_policy_rules():
    doc = base()
    doc["interlock"]["reset"] = "token"
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(doc))
    assert info.value.problems[0].startswith('interlock.reset_token: missing: reset = "token" needs a secret')
    doc["interlock"].update(reset="open", reset_token="abc")
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(doc))
    assert info.value.problems[0].startswith('interlock.reset_token: set but reset = "open" ignores it')
    # the secret is not echoed in the problem either
    assert "abc" not in " ".join(info.value.problems)
