"""systemd/millsense-historian.service: systemd's own check says nothing of it, and it runs what the docs say."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO
from tests.ops.test_systemd import INSTALLED, SYSTEMD_ANALYZE, needs_systemd
from tests.ops.unit_file import unit_options

pytestmark = pytest.mark.quick
UNIT = REPO / "systemd" / "millsense-historian.service"


def test_the_unit_runs_the_historian_as_millsense_with_its_spool_in_its_state_directory():
    o = unit_options(UNIT)
    assert o["ExecStart"] == [f"{INSTALLED} historian --config /etc/millsense/historian.toml --log-format json"]
    for key, value in {"Type": "notify", "User": "millsense", "RestartPreventExitStatus": "78",
                       "StateDirectory": "millsense-historian", "StateDirectoryMode": "0700", "UMask": "0077"}.items():
        assert o.get(key) == [value], key
    daemon = int(unit_options()["Nice"][-1])
    assert daemon < int(o["Nice"][-1])   # never before the daemon's crash check for the CPU


@needs_systemd
def test_systemd_analyze_verify_prints_nothing(tmp_path):
    script = Path(sys.executable).with_name("millsense")
    path = tmp_path / UNIT.name
    path.write_text(UNIT.read_text().replace(INSTALLED, str(script)))
    p = subprocess.run([SYSTEMD_ANALYZE, "verify", str(path)], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert (p.returncode, p.stdout, p.stderr) == (0, "", "")
