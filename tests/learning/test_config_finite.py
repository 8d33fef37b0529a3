"""No non-finite number in the TOML of the learned and fixed limits (issue 36): `inf` and `nan` are TOML
floats, and a band bounded by an infinite `[alarms]` limit or learned with an infinite `sigma` is no bound.
Every float key of `[learning]` and `[alarms]`, through the real loader; one through `millsense check-config`."""

from __future__ import annotations

import subprocess
import sys
import typing

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config_text
from millsense.daemon.config.models import AlarmSettings, LearningSettings
from tests.config.helpers import base, dumps

pytestmark = pytest.mark.quick


def _float_keys(model) -> list[str]:
    return [name for name, f in model.model_fields.items()
            if f.annotation is float or float in typing.get_args(f.annotation)]


KEYS = [("learning", k) for k in _float_keys(LearningSettings)] + [("alarms", k) for k in _float_keys(AlarmSettings)]


def test_every_float_key_of_both_sections_is_checked_here():
    assert ("learning", "sigma") in KEYS and ("learning", "min_width_low_pct") in KEYS
    assert ("alarms", "torque_limit_nm") in KEYS and ("alarms", "force_limit_n") in KEYS
    assert sum(s == "learning" for s, _ in KEYS) >= 6 and sum(s == "alarms" for s, _ in KEYS) >= 12


@pytest.mark.parametrize("section, key", KEYS)
@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_inf_and_nan_are_a_config_error_naming_section_and_key(section, key, value):
    doc = base()
    doc.setdefault(section, {})[key] = value
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(doc))
    text = "inf" if value == float("inf") else "-inf" if value == float("-inf") else "nan"
    assert [p for p in info.value.problems if p.startswith(f"{section}.{key}: {text} is not a finite number")], \
        info.value.problems


def test_check_config_exits_78_on_inf(tmp_path):
    doc = base()
    doc["learning"] = {"min_width_nm": float("inf")}
    path = tmp_path / "inf.toml"
    path.write_text(dumps(doc))
    p = subprocess.run([sys.executable, "-m", "millsense.daemon", "check-config", str(path)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 78, p.stdout + p.stderr
    assert "learning.min_width_nm: inf is not a finite number" in p.stdout + p.stderr
    assert "Traceback" not in p.stderr
