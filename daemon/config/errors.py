"""pydantic's validation errors → one line per problem, `section.key: what is wrong (what is expected)`.

Why by hand: pydantic's own text ("Input should be greater than 0
[type=greater_than, input_value=0, ...]") names neither the TOML section nor
what to write instead, and unknown keys deserve a did-you-mean. The expected
form is derived from the model field itself (type and bounds), so a message
cannot drift from the rule that produced it.
"""

from __future__ import annotations

import datetime as _dt
import difflib
import json
import math
import types
import typing
from typing import Any

import annotated_types as at
from pydantic import BaseModel, SecretStr, ValidationError
from pydantic.fields import FieldInfo


class ConfigError(Exception):
    """The configuration cannot be used. `problems`: every problem found, one line each,
    shaped `section.key: what is wrong (what is expected)`."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems) or ["configuration: invalid (no detail)"]
        super().__init__("\n".join(self.problems))


# ----------------------------------------------------------------------------- locations
def format_loc(loc: tuple[Any, ...] | list[Any]) -> str:
    """('gears', 1, 'ratio') → gears[1].ratio; odd keys are quoted: channels."v uv"."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
            continue
        part = str(part)
        if part == "[key]":
            continue
        text = part if part.replace("_", "a").replace("-", "a").isalnum() and part.isascii() else json.dumps(part)
        out += f".{text}" if out else text
    return out or "configuration"


def _unwrap(ann: Any) -> Any:
    """Strip Optional/Annotated: `float | None` → float (a Literal or model stays)."""
    while True:
        origin = typing.get_origin(ann)
        if origin is typing.Annotated:
            ann = typing.get_args(ann)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(ann) if a is not type(None)]
            if len(args) != 1:
                return ann
            ann = args[0]
        else:
            return ann


def field_at(root: type[BaseModel], loc: tuple[Any, ...]) -> tuple[FieldInfo | None, Any]:
    """The model field and its (unwrapped) annotation at `loc`, or (None, None)."""
    field: FieldInfo | None = None
    ann: Any = root
    parts = [p for p in loc if p != "[key]"]
    i = 0
    while i < len(parts):
        ann = _unwrap(ann)
        part = parts[i]
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            if not isinstance(part, str) or part not in ann.model_fields:
                return None, None
            field = ann.model_fields[part]
            ann = field.annotation
            i += 1
        elif typing.get_origin(ann) in (dict, list):
            args = typing.get_args(ann)
            ann = args[-1] if args else Any
            field = None
            i += 1
        else:
            return None, None
    return field, _unwrap(ann)


def model_at(root: type[BaseModel], loc: tuple[Any, ...]) -> type[BaseModel] | None:
    _, ann = field_at(root, loc) if loc else (None, root)
    return ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None


# ----------------------------------------------------------------------------- expected forms
def _num(x: Any) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _type_word(ann: Any, name: str = "") -> str:
    origin = typing.get_origin(ann)
    if origin is typing.Literal:
        return "one of: " + ", ".join(json.dumps(a) for a in typing.get_args(ann))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_word(_unwrap(a), name) for a in typing.get_args(ann) if a is not type(None))
    if ann is bool:
        return "true or false"
    if ann is int:
        return "an integer"
    if ann is float:
        return "a number"
    if ann in (str, SecretStr):
        return "a string"
    if origin is list:
        return "a list"
    if origin is dict:
        return "a table"
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return f"a [{name}] table" if name else "a table"
    return "a value"


def expected(field: FieldInfo | None, ann: Any, name: str = "") -> str:
    """'an integer ≥ 1', 'a number from 0 to 100', 'one of: "down", "up"' for a field."""
    word = _type_word(ann, name)
    if field is None:
        return word
    lo = hi = None
    for m in field.metadata:
        if isinstance(m, at.Gt):
            lo = f"> {_num(m.gt)}"
        elif isinstance(m, at.Ge):
            lo = f"≥ {_num(m.ge)}"
        elif isinstance(m, at.Lt):
            hi = f"< {_num(m.lt)}"
        elif isinstance(m, at.Le):
            hi = f"≤ {_num(m.le)}"
    if lo and hi:
        return f"{word} {lo} and {hi}"
    return f"{word} {lo or hi}" if (lo or hi) else word


def show(value: Any) -> str:
    """A value as the user wrote it (TOML-ish), short."""
    if isinstance(value, bool):
        text = "true" if value else "false"
    elif isinstance(value, str):
        text = json.dumps(value, ensure_ascii=False)
    elif isinstance(value, float):
        text = "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    elif isinstance(value, int):
        text = str(value)
    elif isinstance(value, dict):
        return "a table"
    elif isinstance(value, list):
        return "a list"
    elif isinstance(value, (_dt.date, _dt.time)):
        text = value.isoformat()
    else:
        text = type(value).__name__
    return text if len(text) <= 48 else text[:45] + "..."


# ----------------------------------------------------------------------------- one error
# pattern -> (what is wrong, what is expected)
_PATTERNS = {
    r"^[A-Za-z0-9_-]+$": ("may only contain letters, digits, '_' and '-'", "a name usable in Zenoh keys, e.g. mch10-01"),
    r"^[A-Za-z0-9_]{1,8}$": ("is not a DAQ channel name", "1–8 ASCII letters, digits or '_', as in the DAQ's descriptor"),
}
_NOT_A = {
    "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
    "float_type": "a number", "float_parsing": "a number", "bool_type": "true or false",
    "bool_parsing": "true or false", "string_type": "a string", "list_type": "a list",
    "dict_type": "a table", "model_type": "a table", "model_attributes_type": "a table",
}


def describe(root: type[BaseModel], err: dict[str, Any]) -> list[str]:
    """One pydantic error dict → problem lines (several for a `millsense_problems` error)."""
    loc = tuple(err.get("loc", ()))
    where = format_loc(loc)
    kind = err.get("type", "")
    ctx = err.get("ctx") or {}
    value = err.get("input")
    if kind == "millsense_problems":
        out = []
        for sub, msg in ctx.get("problems", []):
            out.append(f"{where}{sub}: {msg}" if sub.startswith("[") else f"{where}.{sub}: {msg}")
        return out
    if kind == "extra_forbidden":
        model = model_at(root, loc[:-1])
        allowed = list(model.model_fields) if model else []
        key = str(loc[-1]) if loc else ""
        close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
        hint = f', did you mean "{close[0]}"?' if close else ""
        return [f"{where}: unknown key{hint} (expected one of: {', '.join(allowed) or 'nothing here'})"]
    name = str(loc[-1]) if loc and isinstance(loc[-1], str) else ""
    if loc and loc[-1] == "[key]":
        if kind == "value_error":  # a table name checked by its own validator ([tools.N])
            return [f"{where}: {str(err.get('msg', '')).removeprefix('Value error, ')}"]
        wrong, exp = _PATTERNS.get(ctx.get("pattern", ""), ("is not an allowed name", "a different name"))
        return [f"{where}: {show(value)} {wrong} ({exp})"]
    field, ann = field_at(root, loc)
    exp = expected(field, ann, name)
    if kind == "missing":
        return [f"{where}: missing (required: {exp})"]
    if kind == "value_error":
        msg = str(err.get("msg", "")).removeprefix("Value error, ")
        return [f"{where}: {msg}"]
    if kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        words = {"greater_than": ("above", "gt"), "greater_than_equal": ("at least", "ge"),
                 "less_than": ("below", "lt"), "less_than_equal": ("at most", "le")}[kind]
        return [f"{where}: must be {words[0]} {_num(ctx.get(words[1]))}, not {show(value)} ({exp})"]
    if kind in _NOT_A:
        return [f"{where}: {show(value)} is not {_NOT_A[kind]} ({exp})"]
    if kind == "literal_error":
        return [f"{where}: {show(value)} is not a choice here ({exp})"]
    if kind == "finite_number":
        return [f"{where}: {show(value)} is not a finite number ({exp})"]
    if kind == "string_pattern_mismatch":
        wrong, exp = _PATTERNS.get(ctx.get("pattern", ""), ("has the wrong form", exp))
        return [f"{where}: {show(value)} {wrong} ({exp})"]
    if kind == "string_too_short":
        return [f"{where}: must not be empty ({exp})"]
    if kind == "string_too_long":
        return [f"{where}: longer than {ctx.get('max_length')} characters ({exp})"]
    if kind == "too_short":
        table = {"gears": "[[gears]] table", "channels": "[channels.NAME] table"}.get(name, "entry")
        return [f"{where}: at least {ctx.get('min_length', 1)} {table} needed, found {ctx.get('actual_length', 0)} ({exp})"]
    return [f"{where}: {err.get('msg', 'invalid')} ({exp})"]


def problems_from(root: type[BaseModel], exc: ValidationError, prefix: tuple[Any, ...] = ()) -> list[str]:
    """Every error of a ValidationError as problem lines; never raises."""
    out: list[str] = []
    for err in exc.errors(include_url=False):
        err = dict(err)
        err["loc"] = prefix + tuple(err.get("loc", ()))
        try:
            out.extend(describe(root, err))
        except Exception:  # noqa: BLE001 - a message must never become a traceback
            out.append(f"{format_loc(err['loc'])}: {err.get('msg', 'invalid')} (see the configuration reference)")
    return out
