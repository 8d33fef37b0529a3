"""check-config's warnings about context, tools by number and learned limits (daemon/config/warnings.py)."""

from __future__ import annotations

import pytest

from millsense.daemon.config.load import load_config_text
from millsense.daemon.config.warnings import config_warnings
from tests.config.helpers import base, dumps

pytestmark = pytest.mark.quick


def warnings_of(doc: dict) -> list[str]:
    return [w for w in config_warnings(load_config_text(dumps(doc))) if not w.startswith("interlock.")]


def test_defaults_warn_of_nothing():
    assert warnings_of(base()) == []


def test_tool_tables_without_context_are_never_used():
    doc = base()
    doc["tools"] = {"12": {"diameter_mm": 6.0, "flutes": 3}, "7": {"diameter_mm": 16.0, "flutes": 4}}
    doc["context"] = {"source": "off"}
    doc["learning"] = {"enabled": False}
    (warning,) = warnings_of(doc)
    assert warning.startswith("context.source:") and "[tools.7], [tools.12]" in warning


def test_learning_without_context_learns_nothing():
    doc = base()
    doc["context"] = {"source": "off"}
    (warning,) = warnings_of(doc)
    assert warning.startswith("learning.enabled:") and "fixed [alarms] limits" in warning


def test_an_envelope_narrower_than_the_wear_rise_races_the_wear_warning():
    doc = base()
    doc["learning"] = {"min_width_pct": 15.0, "wear_rise_pct": 15.0}
    (warning,) = warnings_of(doc)
    assert warning.startswith("learning.min_width_pct:")
    doc["learning"] = {"min_width_pct": 15.5, "wear_rise_pct": 15.0}
    assert warnings_of(doc) == []
