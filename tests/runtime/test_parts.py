"""The parts the Runner builds are given what they need: none imports `runtime/runner.py` (statically, every import:
at the top, inside a function or under TYPE_CHECKING), and afc/ imports nothing of the runtime."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.quick

DAEMON = Path(__file__).resolve().parents[2] / "daemon"


def _imports(path: Path) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def test_no_part_of_the_runtime_imports_the_runner_and_afc_imports_no_runtime():
    parts = [p for p in sorted((DAEMON / "runtime").glob("*.py")) if p.name != "runner.py"]
    assert {p.name for p in parts} >= {"frame_guard.py", "faults.py", "controls.py", "status.py", "interlock.py",
                                       "latch_store.py", "local_control.py"}
    for path in parts:
        assert "millsense.daemon.runtime.runner" not in _imports(path), path.name
    for path in sorted((DAEMON / "afc").glob("*.py")):
        assert not [m for m in _imports(path) if m.startswith("millsense.daemon.runtime")], path.name
