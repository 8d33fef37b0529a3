"""A tiny TOML writer and a valid base configuration for the config tests."""

from __future__ import annotations

import copy
import json
import math
import tomllib
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[2]
DEMO_TOML = REPO / "daemon" / "demo.toml"


def base() -> dict[str, Any]:
    """The demo configuration as a dict: valid, and matching the simulator's sensors."""
    return copy.deepcopy(tomllib.loads(DEMO_TOML.read_text()))


def _key(k: str) -> str:
    return k if k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k) else _str(k)


def _str(s: str) -> str:
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def _value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _str(v)
    if isinstance(v, list):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_key(k)} = {_value(x)}" for k, x in v.items()) + "}"
    if hasattr(v, "isoformat"):
        return v.isoformat()
    raise TypeError(type(v))


def dumps(doc: dict[str, Any]) -> str:
    """TOML text for `doc`: scalars first, then [tables] and [[arrays of tables]]."""
    lines: list[str] = []

    def table(d: dict[str, Any], prefix: list[str]) -> None:
        subs = []
        for k, v in d.items():
            if isinstance(v, dict):
                subs.append(("table", k, v))
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                subs.append(("array", k, v))
            else:
                lines.append(f"{_key(k)} = {_value(v)}")
        for kind, k, v in subs:
            name = ".".join(_key(p) for p in prefix + [k])
            if kind == "table":
                lines.append(f"\n[{name}]")
                table(v, prefix + [k])
            else:
                for item in v:
                    lines.append(f"\n[[{name}]]")
                    table(item, prefix + [k])

    table(doc, [])
    return "\n".join(lines) + "\n"


def write(tmp_path: Path, doc: dict[str, Any] | str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(doc if isinstance(doc, str) else dumps(doc), encoding="utf-8")
    return path
