"""Every shipped example validates; `millsense check-config` as a real subprocess.

Examples that take commands over the network name a reset token file next to
themselves (a relative `reset_token_file`). The repository ships no secret,
so as shipped they are refused until the token is made; the tests install a
copy the way systemd/install.sh does (the file copied verbatim, a token of
43 random characters beside it, mode 0600) and check that copy.
"""

from __future__ import annotations

import re
import secrets
import shutil
import subprocess
import tomllib
from pathlib import Path

import pytest

from millsense.daemon.config.load import demo_config, load_config
from millsense.daemon.config.models import loopback_only
from tests.config.helpers import REPO, base, dumps, write

EXAMPLES = sorted((REPO / "config").glob("*.toml"))
# What `check-config` may print as warnings for each installed example (daemon/config/warnings.py):
# nothing. A shipped file that needs a warning is a shipped file to fix.
EXPECTED_WARNINGS: dict[str, list[str]] = {p.name: [] for p in EXAMPLES}


def install(example: Path, etc: Path) -> Path:
    """Copy `example` into `etc` unchanged and make the token file it names, as install.sh would."""
    etc.mkdir(exist_ok=True)
    target = etc / example.name
    shutil.copyfile(example, target)
    target.chmod(0o640)
    token_file = tomllib.loads(example.read_text()).get("interlock", {}).get("reset_token_file")
    if token_file:
        path = Path(token_file)
        assert not path.is_absolute(), f"{example.name}: keep the token path relative, next to the config"
        token = etc / path
        token.write_text(secrets.token_urlsafe(32) + "\n")  # what `millsense token new` makes: 256 bits
        token.chmod(0o600)
    return target
# docs/architecture.md, "Simulated sensors": physical = (raw - offset) * scale
SIM_SCALES = {"v_uv": 0.02, "v_vw": 0.02, "v_wu": 0.02, "i_u": 0.002, "i_v": 0.002, "i_w": 0.002,
              "sp_rpm": 0.1, "mot_rpm": 0.2, "ix_feed": 0.001, "fx_rate": 0.1, "fx": 0.5, "fy": 0.5, "fz": 0.5}
SHAPE = re.compile(r"^[^\s:][^:]*: .+\(.+\)$")


def check_config(cmd: list[str], path: Path | str) -> subprocess.CompletedProcess:
    return subprocess.run(cmd + ["check-config", str(path)], capture_output=True, text=True, timeout=60)


def test_the_expected_examples_exist():
    names = {p.name for p in EXAMPLES}
    assert {"mch10-spindle-power.toml", "depth-of-cut-d.toml", "modbus.toml", "serial.toml"} <= names


@pytest.mark.parametrize("path", EXAMPLES + [REPO / "daemon" / "demo.toml"], ids=lambda p: p.name)
def test_example_validates_and_uses_the_simulated_sensor_scales(path, tmp_path):
    s = load_config(install(path, tmp_path / "etc"))
    for name, ch in s.channels.items():
        if name == "sp_enc":
            assert ch.counts_per_rev == 4096
        else:
            assert ch.scale == SIM_SCALES[name] and ch.offset == 0, name


def test_paper_set_ups(tmp_path):
    p = load_config(install(REPO / "config" / "mch10-spindle-power.toml", tmp_path / "etc"))
    assert (p.tool.diameter_mm, p.tool.flutes, p.motor.winding, p.motor.stator_resistance_ohm, p.motor.pole_pairs) == (
        20.0, 2, "delta", 0.349, 2)
    assert [(g.ratio, g.max_spindle_rpm, g.friction_torque_nm, g.viscous_nms) for g in p.gears] == [
        (4.81, 900, 2.6629, 0.0400), (1.157, 4500, 1.6160, 0.0022)]  # [P] Table 2
    assert p.cut.mode == "slot" and p.material.ks == 760.0  # SM45C (assumed, architecture.md)
    d = load_config(REPO / "config" / "depth-of-cut-d.toml")
    assert (d.tool.diameter_mm, d.tool.flutes, d.cut.mode, d.depth.method) == (16.0, 4, "down", "feed-drive")
    assert (d.material.ks, d.material.ks_exp, d.material.r1, d.material.r1_exp, d.material.r2, d.material.r2_exp) == (
        646.08, -0.4362, 0.2201, -0.2667, 0.1244, 0.1702)  # [D] Table 2
    ff = d.feed_force["ix_feed"]
    assert (ff.newton_per_amp, ff.friction_n) == (950.0, 120.0)
    assert load_config(install(REPO / "config" / "modbus.toml", tmp_path / "etc")).daq.transport == "modbus-tcp"
    assert load_config(REPO / "config" / "serial.toml").daq.transport == "serial"


def test_demo_config_is_the_simulated_step_cut_on_loopback():
    s = demo_config()
    assert (s.daq.transport, s.daq.scenario, s.zenoh.mode) == ("sim", "step", "peer")
    assert s.zenoh.listen == ["tcp/127.0.0.1:0"] and s.zenoh.connect == []
    assert s.interlock.enabled and s.alarms.torque_limit_nm is not None
    assert s.alarms.torque_warn_nm < s.alarms.torque_limit_nm
    # demo.toml is packaged data, read through importlib.resources (tests/test_packaging.py checks the wheel)
    assert tomllib.loads((REPO / "daemon" / "demo.toml").read_text())["machine"] == s.machine


def test_check_config_accepts_a_good_file(millsense_cmd, tmp_path):
    path = install(REPO / "config" / "mch10-spindle-power.toml", tmp_path / "etc")
    p = check_config(millsense_cmd, path)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines()[-1].startswith(f"{path}: OK (machine mch10-01, daq serial /dev/ttyACM0, 8 channels, 2 gears")
    assert len(p.stdout.splitlines()) == 1 and p.stderr == ""


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_installed_example_passes_check_config_with_the_expected_warnings(millsense_cmd, tmp_path, example):
    path = install(example, tmp_path / "etc")
    p = check_config(millsense_cmd, path)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert lines[-1].startswith(f"{path}: OK (") and p.stderr == ""
    warnings = [line.removeprefix("warning: ") for line in lines[:-1]]
    assert all(line.startswith("warning: ") for line in lines[:-1]), lines
    assert warnings == EXPECTED_WARNINGS[example.name]


@pytest.mark.parametrize("example", EXAMPLES + [REPO / "daemon" / "demo.toml"], ids=lambda p: p.name)
def test_no_shipped_config_is_open_to_other_hosts(example, tmp_path):
    # finding 3: mch10-spindle-power.toml listened on 0.0.0.0 with reset = "open", modbus.toml (a router
    # client) had no reset key
    s = load_config(install(example, tmp_path / "etc"))
    if not loopback_only(s.zenoh):
        assert s.interlock.reset in ("token", "off"), f"{example.name}: reset = {s.interlock.reset!r} off loopback"
        if s.interlock.reset == "token":
            assert s.interlock.token(), f"{example.name}: token mode with no token: nobody could reset over Zenoh"
    else:
        assert s.interlock.reset in ("open", "token", "off")


def test_a_shipped_example_without_its_token_is_refused_and_says_how_to_make_one(millsense_cmd):
    # As shipped (no secret in the repository) the file must not quietly run open: exit 78, naming the key.
    needing = [p for p in EXAMPLES if tomllib.loads(p.read_text()).get("interlock", {}).get("reset_token_file")]
    assert {p.name for p in needing} >= {"mch10-spindle-power.toml", "modbus.toml"}
    for path in needing:
        assert "millsense token new --out" in path.read_text(), f"{path.name}: say how to make the token"
        if (path.parent / tomllib.loads(path.read_text())["interlock"]["reset_token_file"]).exists():
            continue  # someone made the token in their checkout: nothing to refuse
        p = check_config(millsense_cmd, path)
        assert p.returncode == 78, p.stdout
        assert p.stderr.startswith("interlock.reset_token_file: ") and "does not exist" in p.stderr, p.stderr


def test_check_config_lists_every_problem_and_exits_78(millsense_cmd, tmp_path):
    doc = base()
    doc["tool"]["flutes"] = 0
    doc["gears"][1]["max_spindle_rpm"] = 800
    doc["daq"]["transprot"] = "sim"
    p = check_config(millsense_cmd, write(tmp_path, doc))
    assert p.returncode == 78
    lines = p.stderr.splitlines()
    assert lines == [
        'daq.transprot: unknown key, did you mean "transport"? (expected one of: transport, port, baudrate, host, '
        "tcp_port, unit, scenario, poll_ms, timeout_ms, sample_rate_hz, check_sample_rate, filter_cutoff_hz, filter_order)",
        "gears[1].max_spindle_rpm: 800 is not above the previous gear's 900 (strictly increasing: list gears lowest max_spindle_rpm first)",
        "tool.flutes: must be at least 1, not 0 (an integer ≥ 1)",
    ]
    assert p.stdout == ""


@pytest.mark.parametrize(
    "content",
    [None, b"\xff\xfe not utf-8", b'machine = "m"\n[daq\n', b"", b"[[gears]]\nname = 1\n[gears]\n", b"a.b.c.d = 1\n" * 3],
    ids=["missing", "binary", "syntax", "empty", "table-redefined", "duplicate-key"],
)
def test_check_config_never_prints_a_traceback(millsense_cmd, tmp_path, content):
    path = tmp_path / "c.toml"
    if content is not None:
        path.write_bytes(content)
    p = check_config(millsense_cmd, path)
    assert p.returncode == 78, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.strip()
    for line in p.stderr.splitlines():
        assert SHAPE.match(line), line


def test_check_config_usage_error_is_2(millsense_cmd):
    p = subprocess.run(millsense_cmd + ["check-config"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "Traceback" not in p.stderr


def test_a_relative_calibration_is_found_next_to_the_config_not_the_cwd(millsense_cmd, tmp_path):
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "cal.toml").write_text('[[gears]]\nname = "low-speed"\nfriction_torque_nm = 2.5\nviscous_nms = 0.04\n')
    doc = base()
    doc["calibration"] = "cal.toml"
    path = write(tmp_path / "etc", dumps(doc))
    p = subprocess.run(millsense_cmd + ["check-config", str(path)], capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert f"calibration {tmp_path / 'etc' / 'cal.toml'}" in p.stdout
