"""The systemd unit and sysusers file, checked by systemd's own tools (offline: PID 1 is not systemd here).

`systemd-analyze verify` exits 0 even for a misspelt key (it only warns), so any
output at all is a failure. It also insists that ExecStart's binary exists: the
unit names /usr/local/bin/millsense (where `pip install` puts it on a target),
which does not exist on a build machine, so the test verifies a temporary copy
whose only change is that path, pointing at this venv's `millsense` script.
"""

from __future__ import annotations

import ctypes
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.config.helpers import REPO
from tests.ops.unit_file import UNIT, unit_options

SYSUSERS = REPO / "systemd" / "millsense.sysusers.conf"
INSTALLED = "/usr/local/bin/millsense"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")
needs_systemd = pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze not installed")


def local_copy(tmp_path: Path, text: str | None = None) -> Path:
    script = Path(sys.executable).with_name("millsense")
    assert script.is_file(), "the package's console script (pip install -e .) is missing"
    text = UNIT.read_text() if text is None else text
    assert INSTALLED in text
    path = tmp_path / UNIT.name
    path.write_text(text.replace(INSTALLED, str(script)))
    return path


def verify(unit: Path) -> subprocess.CompletedProcess:
    instance = unit.with_name(unit.name.replace("@.", "@mch10-01."))
    return subprocess.run([SYSTEMD_ANALYZE, "verify", str(instance)], capture_output=True, text=True, timeout=60, cwd=unit.parent)


def test_unit_has_the_required_settings():
    o = unit_options()
    assert o["ExecStart"] == [f"{INSTALLED} run --config /etc/millsense/%i.toml"]
    expected = {
        "Type": "notify", "NotifyAccess": "main", "WatchdogSec": "5", "Restart": "on-failure", "RestartSec": "2",
        "RestartPreventExitStatus": "78", "User": "millsense", "Group": "millsense", "SupplementaryGroups": "dialout",
        "UMask": "0077", "StateDirectory": "millsense/%i", "StateDirectoryMode": "0750", "LogsDirectory": "millsense",
        "NoNewPrivileges": "yes", "ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes",
        "MemoryDenyWriteExecute": "yes", "SystemCallArchitectures": "native", "CapabilityBoundingSet": "",
        "AmbientCapabilities": "", "RestrictAddressFamilies": "AF_UNIX AF_INET AF_INET6 AF_NETLINK", "DevicePolicy": "closed",
        "Nice": "-5",
    }
    for key, value in expected.items():
        assert o.get(key) == [value], key
    assert o["Environment"] == ["PYTHONUNBUFFERED=1", "PYTHONOPTIMIZE=2"]
    assert sorted(o["DeviceAllow"]) == ["char-ttyACM rw", "char-ttyS rw", "char-ttyUSB rw"]
    assert "@system-service" in o["SystemCallFilter"]
    for key in ("ProtectKernelTunables", "ProtectKernelModules", "ProtectKernelLogs", "ProtectControlGroups", "ProtectClock",
                "ProtectHostname", "RestrictNamespaces", "RestrictRealtime", "RestrictSUIDSGID", "LockPersonality"):
        assert o.get(key) == ["yes"], key


def test_the_daemon_comes_before_the_hmi_units_for_the_cpu():
    """The crash check runs on the daemon's reader thread: under load it must not wait behind the dashboard,
    the OPC UA server or the router (bench/crash_latency.py --hog measures what the priority buys)."""
    daemon = int(unit_options()["Nice"][-1])
    for name in ("millsense-dashboard.service", "millsense-opcua.service", "millsense-router.service"):
        assert daemon < int(unit_options(UNIT.parent / name).get("Nice", ["0"])[-1]), name


@needs_systemd
def test_systemd_analyze_verify_prints_nothing(tmp_path):
    p = verify(local_copy(tmp_path))
    assert (p.returncode, p.stdout, p.stderr) == (0, "", "")


@needs_systemd
def test_verify_would_catch_a_typo(tmp_path):
    """The check above can fail: a misspelt key makes verify talk (while still exiting 0)."""
    p = verify(local_copy(tmp_path, UNIT.read_text().replace("UMask=0077", "UMsak=0077")))
    assert "Unknown key 'UMsak'" in p.stdout + p.stderr


@needs_systemd
def test_security_score(tmp_path):
    unit = local_copy(tmp_path)
    instance = unit.with_name("millsense@mch10-01.service")
    p = subprocess.run([SYSTEMD_ANALYZE, "security", "--offline=true", str(instance)], capture_output=True, text=True,
                       timeout=60, cwd=tmp_path)
    m = re.search(r"Overall exposure level for \S+: ([0-9.]+) (\w+)", p.stdout)
    assert m, p.stdout + p.stderr
    score = float(m.group(1))
    print(f"\nsystemd-analyze security --offline=true: {score} {m.group(2)}")
    assert score <= 3.0  # "OK" band; a unit with ~20 options scored 6.4 (libraries.md)


@pytest.mark.skipif(shutil.which("systemd-sysusers") is None, reason="systemd-sysusers not installed")
def test_sysusers_creates_a_system_user_in_dialout(tmp_path):
    root = tmp_path / "root"
    (root / "etc").mkdir(parents=True)
    (root / "etc" / "group").write_text("dialout:x:20:\n")
    (root / "etc" / "passwd").write_text("root:x:0:0:root:/root:/bin/sh\n")
    p = subprocess.run(["systemd-sysusers", f"--root={root}", str(SYSUSERS)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    passwd = (root / "etc" / "passwd").read_text()
    group = (root / "etc" / "group").read_text()
    user = [ln for ln in passwd.splitlines() if ln.startswith("millsense:")]
    assert len(user) == 1 and int(user[0].split(":")[2]) < 1000  # a system user
    assert user[0].split(":")[5] == "/var/lib/millsense"
    assert "dialout:x:20:millsense" in group.splitlines()


def _mdwe_supported() -> bool:
    libc = ctypes.CDLL(None, use_errno=True)
    return sys.platform == "linux" and libc.prctl(66, 0, 0, 0, 0) >= 0  # PR_GET_MDWE


MDWE_EXEC = (
    "import ctypes, os, sys\n"
    "libc = ctypes.CDLL(None, use_errno=True)\n"
    "assert libc.prctl(65, 1, 0, 0, 0) == 0, ctypes.get_errno()  # PR_SET_MDWE, PR_MDWE_REFUSE_EXEC_GAIN\n"
    "os.execv(sys.executable, [sys.executable] + sys.argv[1:])\n"
)
LIBRARIES = (
    "import json, mmap, numpy, scipy.signal, serial, pymodbus.client, zenoh\n"
    "try:\n"
    "    mmap.mmap(-1, 4096, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC); print('W+X allowed')\n"
    "except OSError: print('W+X refused')\n"
    "c = zenoh.Config(); c.insert_json5('scouting/multicast/enabled', 'false')\n"
    "c.insert_json5('listen/endpoints', json.dumps(['tcp/127.0.0.1:0']))\n"
    "s = zenoh.open(c); s.declare_publisher('millsense/t/x').put(b'{}'); s.close()\n"
    "print(float(scipy.signal.butter(2, 0.4)[0][0]) > 0, numpy.fft.rfft(numpy.ones(64)).shape)\n"
)


@pytest.mark.skipif(not _mdwe_supported(), reason="kernel without PR_SET_MDWE (Linux < 6.3)")
def test_memory_deny_write_execute_does_not_break_the_libraries():
    """MemoryDenyWriteExecute=yes is only safe if nothing maps W+X: run the libraries under the kernel's MDWE."""
    p = subprocess.run([sys.executable, "-c", MDWE_EXEC, "-c", LIBRARIES], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split("\n")[:2] == ["W+X refused", "True (33,)"]  # MDWE was really on, and everything ran


@pytest.mark.xdist_group("demo")  # one demo at a time: two (mch10-demo, scouting on) find each other and one exits 78
@pytest.mark.skipif(not _mdwe_supported(), reason="kernel without PR_SET_MDWE (Linux < 6.3)")
def test_the_demo_daemon_runs_under_mdwe(tmp_path):
    """The whole daemon (sim DAQ, pipeline, Zenoh) for a few seconds with W+X refused."""
    args = ["-m", "millsense.daemon", "run", "--seconds", "3"]
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "JOURNAL_STREAM", "INVOCATION_ID")}
    p = subprocess.run([sys.executable, "-c", MDWE_EXEC, *args], capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    if p.returncode != 0:  # say whether W^X is to blame or the demo is broken outright: either fails the test
        plain = subprocess.run([sys.executable, *args], capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
        assert plain.returncode == 0, f"the demo fails without MDWE too (rc {plain.returncode}): {plain.stderr[-2000:]}"
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr
