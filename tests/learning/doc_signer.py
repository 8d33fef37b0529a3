"""The reference signer and the test vector of docs/zenoh.md ("Signed context"), read from the doc itself.

Tests sign with this, not with the daemon's own code, so that what the doc tells an adapter's author is
what the daemon accepts.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

DOC = Path(__file__).resolve().parents[2] / "docs" / "zenoh.md"


def _section() -> str:
    text = DOC.read_text(encoding="utf-8")
    start = text.index("### Signed context")
    end = text.index("\n### ", start + 1)
    return text[start:end]


def signer() -> Callable[..., bytes]:
    """`sign_context(key, machine, run_id, seq, context) -> bytes`, defined by the doc's Python block."""
    blocks = re.findall(r"```python\n(.*?)```", _section(), re.S)
    assert len(blocks) == 1, "docs/zenoh.md's Signed context has one Python block, the reference signer"
    namespace: dict = {}
    exec(compile(blocks[0], f"{DOC}:reference signer", "exec"), namespace)  # noqa: S102 - our own doc
    return namespace["sign_context"]


def vector() -> dict:
    """The test vector as the doc states it: key, machine, run_id, seq, the context's fields, the MAC input, the MAC."""
    sec = _section()
    para = sec[sec.index("**Test vector.**"):]
    para = para[: para.index("**Replay.**")]
    flat = " ".join(para.split())
    m = re.search(r"Adapter key `([^`]+)`, machine `([^`]+)`, run `([0-9a-f]+)`, seq (\d+), program (\d+), "
                  r"tool (\d+), operation (\d+), `afc_allowed` (true|false)", flat)
    assert m, flat
    mac = re.search(r"```\n([0-9a-f]{64})\n```", para)
    msg = re.search(r"the MAC input is `([^`]+)`", flat)
    assert mac and msg, para
    return {"key": m.group(1), "machine": m.group(2), "run_id": m.group(3), "seq": int(m.group(4)),
            "context": {"program": int(m.group(5)), "tool": int(m.group(6)), "operation": int(m.group(7)),
                        "afc_allowed": m.group(8) == "true"},
            "message": msg.group(1).replace("\\n", "\n").encode("utf-8"), "mac": mac.group(1)}
