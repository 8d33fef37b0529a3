"""Whoever closes the driver is who the log says is stopping (issue 39).

`millsense record` logged `daq.link_down ... detail='the driver is closing, as asked (the daemon is
stopping)'` when its `--seconds` ran out: record is not the daemon. A real `record` subprocess on the
simulated DAQ says that record stopped; the daemon still logs what it did (the demo's run,
tests/e2e/test_cli_run.py).
"""

from __future__ import annotations

import json
import subprocess

from tests.config.helpers import DEMO_TOML
from tests.e2e.helpers import CMD


def _link_down_details(text: str) -> list[str]:
    """The `detail` of each `daq.link_down` line, JSON (into a pipe) or console."""
    details = []
    for line in text.splitlines():
        if "daq.link_down" not in line:
            continue
        try:
            details.append(json.loads(line).get("detail", ""))
        except ValueError:
            details.append(line.partition("detail=")[2])
    return details


def test_record_says_record_stopped_not_the_daemon(tmp_path):
    out = tmp_path / "cap.bin"
    p = subprocess.run(CMD + ["record", "--config", str(DEMO_TOML), "--out", str(out), "--seconds", "1"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    said = p.stdout + p.stderr  # its log lines, wherever they go
    (detail,) = _link_down_details(said)
    assert "daemon" not in said, said
    assert "closing, as asked" in detail and "millsense record is stopping" in detail, detail
