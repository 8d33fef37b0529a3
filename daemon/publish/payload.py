"""JSON for the wire: strict JSON (no NaN / Infinity tokens), numpy scalars welcome.

interfaces.md says "`null` where a quantity cannot be estimated"; the estimator
writes NaN there, and `json.dumps` would emit the non-JSON token `NaN`, which
JavaScript and Go subscribers refuse. So non-finite floats become `null`.
"""

from __future__ import annotations

import json
import math
from typing import Any

JSON_ENCODING = "application/json"

# The largest query payload the daemon reads. Every request it understands is
# under 1 KiB; a larger one is refused by its length, before any parsing, so a
# flood of 100 KB queries costs one length check each.
MAX_QUERY_BYTES = 4096


def _plain(value: Any) -> Any:
    """numpy scalars and arrays → Python values (used by json.dumps' `default`)."""
    tolist = getattr(value, "tolist", None)  # numpy scalars and arrays
    if tolist is not None:
        return tolist()
    if isinstance(value, (set, frozenset)):
        return sorted(value, key=repr)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def finite_or_null(value: Any) -> Any:
    """A copy of `value` with every NaN / ±inf float replaced by None, recursively."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    if value is None or isinstance(value, (str, int, bool)):
        return value
    return finite_or_null(_plain(value))


# One encoder for every payload: `json.dumps` with options builds a new `JSONEncoder` per call (about
# 0.5 of the ~8 µs of a 30-field estimate; replay writes one per revolution, the floats' repr is the
# rest). `encode` keeps no state between calls, so threads may share it.
_encode = json.JSONEncoder(allow_nan=False, separators=(",", ":"), default=_plain).encode


def dumps(payload: Any) -> bytes:
    """Strict JSON bytes. The fast path is one encoding; NaN takes a second pass."""
    try:
        return _encode(payload).encode()
    except ValueError:  # "Out of range float values are not JSON compliant"
        return _encode(finite_or_null(payload)).encode()


def loads_object(data: bytes) -> dict[str, Any]:
    """Parse a JSON object from bytes; ValueError with a short reason otherwise."""
    try:
        value = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ValueError(f"payload is not UTF-8 ({exc.reason} at byte {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"payload is not JSON ({exc.msg} at char {exc.pos})") from None
    except RecursionError:
        raise ValueError("payload is nested too deeply") from None
    if not isinstance(value, dict):
        raise ValueError(f"payload must be a JSON object, not {type(value).__name__}")
    return value
