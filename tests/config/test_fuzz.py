"""Fuzz the loader: whatever the document, the result is Settings or a ConfigError of well-shaped lines.

Three generators: random TOML documents (keys drawn from the real ones and from
noise, random nesting and value types), mutations of a valid configuration
(delete / replace / add / rename a key anywhere), and byte-level damage to
the text of a valid file.
"""

from __future__ import annotations

import datetime as dt
import re
import subprocess
import sys

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import effective_config_dict, load_config_text
from millsense.daemon.config.models import Settings
from tests.config.helpers import DEMO_TOML, base, dumps

SHAPE = re.compile(r'^(?:"(?:[^"\\]|\\.)*"|[^\s:"])+: .+\(.+\)$', re.S)  # location: plain or "quoted" parts
REAL_KEYS = sorted(
    {"machine", "calibration", "daq", "channels", "motor", "gears", "tool", "material", "cut", "depth", "feed_force",
     "alarms", "interlock", "zenoh", "log", "transport", "port", "host", "tcp_port", "scale", "offset", "counts_per_rev",
     "winding", "stator_resistance_ohm", "pole_pairs", "name", "ratio", "max_spindle_rpm", "friction_torque_nm",
     "viscous_nms", "diameter_mm", "flutes", "cf", "mode", "method", "connect", "listen", "reset", "reset_token",
     "v_uv", "ix_feed", "newton_per_amp", "level", "format", "scenario", "watchdog_ms", "heartbeat_ms"}
)
FUZZ = settings(max_examples=int(__import__("os").environ.get("FUZZ_N", "60")), deadline=None, suppress_health_check=[HealthCheck.too_slow])

text = st.text(st.characters(blacklist_categories=("Cs",)), max_size=12)
keys = st.one_of(st.sampled_from(REAL_KEYS), text.filter(bool))
scalars = st.one_of(
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    text,
    st.sampled_from(["sim", "serial", "delta", "model", "peer", "tcp/127.0.0.1:7447", "slot", "token"]),
    st.datetimes(min_value=dt.datetime(1900, 1, 1), max_value=dt.datetime(2200, 1, 1)),
    st.dates(),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(keys, inner, max_size=4)),
    max_leaves=20,
)


def outcome(doc_text: str) -> Settings | ConfigError:
    try:
        return load_config_text(doc_text)
    except ConfigError as exc:
        assert exc.problems
        for p in exc.problems:
            assert isinstance(p, str) and SHAPE.match(p), p
            assert "Traceback" not in p
        return exc


@FUZZ
@given(st.dictionaries(keys, values, max_size=8))
def test_random_documents(doc):
    result = outcome(dumps(doc))
    if isinstance(result, Settings):
        effective_config_dict(result)


def _paths(node, prefix=()):
    yield prefix
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _paths(v, prefix + (i,))


@st.composite
def mutated(draw):
    doc = base()
    for _ in range(draw(st.integers(1, 4))):
        paths = [p for p in _paths(doc) if p]
        path = draw(st.sampled_from(paths))
        parent = doc
        for part in path[:-1]:
            parent = parent[part]
        last = path[-1]
        action = draw(st.sampled_from(["delete", "replace", "add", "rename"]))
        if action == "delete":
            del parent[last]
        elif action == "replace":
            parent[last] = draw(values)
        elif action == "add" and isinstance(parent, dict):
            parent[draw(keys)] = draw(values)
        elif action == "rename" and isinstance(parent, dict):
            new = draw(keys)
            parent[new] = parent.pop(last)
    return doc


@FUZZ
@given(mutated())
def test_mutations_of_a_valid_config(doc):
    outcome(dumps(doc))


@FUZZ
@given(st.data())
def test_damaged_text(data):
    raw = DEMO_TOML.read_text()
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(0, len(raw)))
        j = min(len(raw), i + data.draw(st.integers(0, 8)))
        raw = raw[:i] + data.draw(st.text(st.sampled_from('=[]"{}.,# \n01ax-'), max_size=4)) + raw[j:]
    outcome(raw)


def test_a_fuzz_found_document_through_the_real_cli(tmp_path, millsense_cmd):
    """The same guarantee end to end: a hostile file gives exit 78 and no traceback."""
    doc = base()
    doc["gears"] = [{"name": {"x": [1, dt.date(2020, 1, 1)]}, "ratio": "inf"}, 7]
    doc["channels"] = {"v_uv": [], "\u00e9\u00e9": {"scale": float("nan")}}
    doc["zenoh"] = "peer"
    path = tmp_path / "hostile.toml"
    path.write_text(dumps(doc), encoding="utf-8")
    p = subprocess.run(millsense_cmd + ["check-config", str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 78 and "Traceback" not in p.stderr
    lines = p.stderr.splitlines()
    assert len(lines) >= 5 and all(SHAPE.match(ln) for ln in lines), p.stderr
    assert sys.executable  # the CLI ran under this interpreter (millsense_cmd)
