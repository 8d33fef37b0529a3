"""`millsense commission` against the real emulator over TCP: a sound machine passes, each installation fault fails
its own step with its fix, and the prompts work on a real terminal.

The "meter" of these tests is the emulator's sound sensors: the RMS of a capture of the same scenario with no
fault (`sim --capture`), read through the capture reader and the configuration's datasheet scales, as a
clamp meter on the machine reads the true current. The scenario (speed-1000: a constant slot at 1000 rpm)
holds its RMS within about 1 % from second to second.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, read_jsonl, wait_for, write_config
from tests.ops.test_console import Pty

SCENARIO = "speed-1000"
RPM = 1000
WATCHDOG_MS = 300
INTERLOCK = f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = {WATCHDOG_MS}\nreset = "off"'


def _config(tmp_path: Path, port: int, machine: str = "comm", replace: tuple[str, str] | None = None) -> Path:
    cfg = write_config(tmp_path / "c.toml", machine=machine,
                       daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {port}', interlock=INTERLOCK)
    if replace:
        text = cfg.read_text()
        assert replace[0] in text
        cfg.write_text(text.replace(*replace))
    return cfg


@pytest.fixture(scope="module")
def meter(tmp_path_factory) -> dict[str, float]:
    """Each current and voltage channel's true RMS, from a capture of the sound emulator."""
    from millsense.daemon.config.load import load_config
    from millsense.daemon.commands.capture_reader import iter_capture_blocks

    tmp = tmp_path_factory.mktemp("meter")
    capture = tmp / "sound.bin"
    subprocess.run(CMD + ["sim", "--scenario", SCENARIO, "--capture", str(capture), "--duration-s", "3"],
                   check=True, capture_output=True, timeout=120)
    settings = load_config(_config(tmp, 1))
    blocks = [(d, b.counts) for d, b in iter_capture_blocks(str(capture))]
    names = list(blocks[0][0].names)
    counts = np.concatenate([c for _, c in blocks])[1000:]   # the first second: the plant settling
    out = {}
    for name in ("v_uv", "v_vw", "v_wu", "i_u", "i_v", "i_w"):
        ch = settings.channels[name]
        x = (counts[:, names.index(name)] - ch.offset) * ch.scale
        out[name] = round(float(np.sqrt(np.mean(x * x))), 2)
    return out


def _readings(meter: dict[str, float]) -> str:
    return ",".join(f"{k}={v}" for k, v in meter.items())


def _emulator(procs: Procs, port: int, *faults: str):
    sim = procs.start("sim", ["sim", "--scenario", SCENARIO, "--tcp", f"127.0.0.1:{port}",
                              "--status-log", str(procs.tmp / "sim-status.jsonl"),
                              "--watchdog-ms", str(WATCHDOG_MS), "--protocol", "2", *faults])
    wait_for(lambda: "serving" in procs.text("sim") or sim.poll() is not None, 60.0, "emulator serving")
    assert sim.poll() is None, procs.text("sim")
    return sim


def _commission(cfg: Path, tmp_path: Path, *args: str) -> tuple[subprocess.CompletedProcess, dict]:
    report = tmp_path / "report.json"
    p = subprocess.run(CMD + ["commission", "--config", str(cfg), "--report", str(report), *args],
                       capture_output=True, text=True, timeout=120)
    assert "Traceback" not in p.stderr + p.stdout
    record = json.loads(report.read_text()) if report.exists() else {}
    return p, record


def _steps(record: dict) -> dict[str, dict]:
    return {s["step"]: s for s in record["steps"]}


def test_a_sound_machine_is_commissioned_with_every_figure_in_the_report(tmp_path, meter):
    port = free_tcp_port()
    with Procs(tmp_path) as procs:
        _emulator(procs, port)
        p, record = _commission(_config(tmp_path, port), tmp_path, "--readings", _readings(meter),
                                "--spindle-rpm", str(RPM))
    assert p.returncode == 0, p.stdout + p.stderr
    assert "\ncommissioned\n" in p.stdout
    steps = _steps(record)
    assert [s["step"] for s in record["steps"]] == ["descriptor", "scales", "phases", "speed", "test-trip", "watchdog"]
    assert all(s["result"] == "pass" for s in record["steps"]), record
    assert record["commissioned"] is True and record["machine"] == "comm"
    assert record["versions"]["millsense"] and record["versions"]["daq_protocol"] == 2
    d = steps["descriptor"]["figures"]
    assert d["sample_rate_hz"] == 1000 and {"name": "sp_enc", "kind": "encoder"} in d["channels"]
    rows = {r["channel"]: r for r in steps["scales"]["figures"]["channels"]}
    assert set(rows) == set(meter)
    for name, row in rows.items():
        assert row["meter"] == meter[name] and abs(row["off_pct"]) <= 3.0 and row["daq_rms"] > 0
    assert steps["phases"]["figures"]["result"] == "in order"
    assert 0 < steps["phases"]["figures"]["current_lag_deg"] < 90 and steps["phases"]["figures"]["input_power_w"] > 0
    enc = steps["speed"]["figures"]["encoder"]
    assert enc["direction"] == "forward" and enc["counts_per_rev_configured"] == 4096
    assert abs(enc["counts_per_rev_measured"] / 4096 - 1) < 0.03
    trip = steps["test-trip"]["figures"]
    assert trip["daq_confirm_ms"] > 0 and trip["cnc_reports_hold"] and trip["cnc_confirm_ms"] > 0
    assert trip["released"] is True
    wd = steps["watchdog"]["figures"]
    assert WATCHDOG_MS <= wd["hold_after_ms"] and wd["released"] is True
    assert "the DAQ's watchdog holds the feed until the daemon runs" in p.stdout
    # the text report beside it is what was printed
    assert (tmp_path / "report.txt").read_text().strip().splitlines()[-1] in p.stdout


@pytest.mark.parametrize("faults, replace, step, fix", [
    (("--current-gain", "1.5"), None, "scales", r"channels\.i_u\.scale = (0\.00\d+)"),
    (("--swap", "i_v,i_w"), None, "phases", r"swap i_v and i_w"),
    (("--reverse", "i_w"), None, "phases", r"channels\.i_w\.scale = -0\.002"),
    (("--reverse", "sp_enc"), None, "speed", r"swap the encoder's A and B signals .* sp_enc"),
    ((), ("counts_per_rev = 4096", "counts_per_rev = 2048"), "speed", r"channels\.sp_enc\.counts_per_rev = 4\d\d\d"),
    (("--watchdog-broken",), None, "watchdog", r"enable the DAQ's watchdog at 300 ms"),
], ids=["current-gain", "swapped-phases", "reversed-current-sensor", "reversed-encoder", "counts-per-rev",
        "watchdog-broken"])
def test_each_installation_fault_fails_its_step_with_its_fix(tmp_path, meter, faults, replace, step, fix):
    port = free_tcp_port()
    with Procs(tmp_path) as procs:
        _emulator(procs, port, *faults)
        p, record = _commission(_config(tmp_path, port, replace=replace), tmp_path, "--readings",
                                _readings(meter), "--spindle-rpm", str(RPM))
    assert p.returncode == 1, p.stdout + p.stderr
    assert "not commissioned: 1 step failed or not checked" in p.stdout
    steps = _steps(record)
    assert record["commissioned"] is False
    assert [name for name, s in steps.items() if s["result"] != "pass"] == [step], record
    m = re.search(fix, " ".join(steps[step]["fixes"]))
    assert m, steps[step]
    assert re.search(fix, p.stdout.split("not commissioned")[1])   # the fix is said at the end too
    if step == "scales":   # the proposed scale makes the DAQ read what the meter reads
        proposed = float(m.group(1))
        assert abs(proposed / (0.002 / 1.5) - 1) < 0.015, proposed
    if step == "speed" and replace:
        assert abs(steps["speed"]["figures"]["encoder"]["counts_per_rev_measured"] / 4096 - 1) < 0.03
    if step == "watchdog":   # the last words do not promise the stop the watchdog step failed to see
        assert "the DAQ's watchdog holds the feed" not in p.stdout
        assert "the DAQ's watchdog was not proved to hold the feed" in p.stdout.split("not commissioned")[1]


def test_the_prompts_on_a_terminal(tmp_path, meter):
    """Everything typed: each meter reading (one skipped), the spindle speed and Enter once it runs."""
    port = free_tcp_port()
    term = Pty()
    try:
        with Procs(tmp_path) as procs:
            _emulator(procs, port)
            cfg = _config(tmp_path, port)
            report = tmp_path / "typed.json"
            p = subprocess.Popen(CMD + ["commission", "--config", str(cfg), "--report", str(report)],
                                 stdin=term.slave, stdout=term.slave, stderr=subprocess.PIPE,
                                 env={**os.environ, "PYTHONUNBUFFERED": "1"})
            procs.procs.append(p)
            typed = 0
            for name in ("v_uv", "v_vw", "v_wu", "i_u", "i_v", "i_w"):
                wait_for(lambda: term.text().count("(s to skip): ") > typed, 60.0, f"the prompt for {name}")
                assert re.search(rf"{name}: the DAQ reads [0-9.]+ [AV] RMS", term.text())
                os.write(term.master, b"s\n" if name == "v_wu" else f"{meter[name]}\n".encode())
                typed += 1
            wait_for(lambda: "rpm (s to skip): " in term.text(), 60.0, "the spindle speed prompt")
            os.write(term.master, f"{RPM}\n".encode())
            wait_for(lambda: "then press Enter: " in term.text(), 60.0, "run the spindle")
            os.write(term.master, b"\n")
            assert p.wait(60) == 1, term.text() + p.stderr.read().decode()
    finally:
        term.close()
    record = json.loads(report.read_text())
    steps = _steps(record)
    assert steps["scales"]["result"] == "not checked"   # v_wu skipped: not commissioned
    assert steps["scales"]["not_checked"] == ["v_wu: skipped (no meter reading)"]
    assert [r["meter"] for r in steps["scales"]["figures"]["channels"] if r["channel"] == "i_u"] == [meter["i_u"]]
    assert all(steps[n]["result"] == "pass" for n in ("descriptor", "phases", "speed", "test-trip", "watchdog"))
    assert steps["speed"]["figures"]["commanded_rpm"] == RPM


@pytest.mark.quick
def test_refused_beside_a_daemon_of_this_machine(tmp_path):
    from millsense.daemon.state_dir import claim_state_dir, state_dir

    cfg = _config(tmp_path, free_tcp_port(), machine="held")
    lock, busy = claim_state_dir(state_dir("held"))   # as a running daemon holds it
    assert busy is None
    try:
        t0 = time.monotonic()
        p = subprocess.run(CMD + ["commission", "--config", str(cfg), "--connect-timeout", "30"],
                           capture_output=True, text=True, timeout=60)
    finally:
        lock.close()
    assert p.returncode == 1 and time.monotonic() - t0 < 30, p.stderr
    assert p.stderr.count("\n") == 1 and f"pid {os.getpid()}" in p.stderr and "two masters" in p.stderr


@pytest.mark.quick
def test_a_bad_config_names_section_and_key_and_exits_78(tmp_path):
    cfg = _config(tmp_path, free_tcp_port(), replace=("watchdog_ms = 300", "watchdog_ms = 10"))
    p = subprocess.run(CMD + ["commission", "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 78 and p.stderr.startswith("interlock.watchdog_ms:"), p.stderr
    assert "Traceback" not in p.stderr


def _holds(tmp_path: Path) -> list[tuple[bool, str]]:
    """The emulator's feed-hold output, each change in its order: (held, cause)."""
    return [(e["feed_hold"], e["cause"]) for e in read_jsonl(tmp_path / "sim-status.jsonl") if e["event"] == "outputs"]


def test_a_hold_found_is_released_only_when_told_and_asserted_again(tmp_path, meter):
    port = free_tcp_port()
    args = ("--readings", _readings(meter), "--spindle-rpm", str(RPM))
    with Procs(tmp_path) as procs:
        _emulator(procs, port)
        cfg = _config(tmp_path, port)
        first, _ = _commission(cfg, tmp_path, *args)
        assert first.returncode == 0, first.stdout + first.stderr
        # its heartbeats ended with it: the DAQ's watchdog holds the feed, as the command said it would. The second
        # watchdog hold: the first is the watchdog step's own, which the step then released (a loaded emulator may
        # log that release after the command exited: waiting for the first counted it as the untold run's release)
        wait_for(lambda: _holds(tmp_path)[-1:] == [(True, "watchdog")]
                 and _holds(tmp_path).count((True, "watchdog")) >= 2, 30.0, "the watchdog's hold after the command")
        seen = len(_holds(tmp_path))
        untold, record = _commission(cfg, tmp_path, *args)
        assert untold.returncode == 1 and "not commissioned: 2 steps failed or not checked" in untold.stdout
        steps = _steps(record)
        assert steps["test-trip"]["result"] == steps["watchdog"]["result"] == "not checked"
        assert "--release-found-hold" in steps["test-trip"]["not_checked"][0]
        assert "the DAQ holds the feed: it did when commission connected" in untold.stdout
        assert all(held for held, _ in _holds(tmp_path)[seen:]), _holds(tmp_path)   # never released
        answers = tmp_path / "answers.txt"   # the same figures as a file, and the release told there
        answers.write_text("# at the machine\n" + "\n".join(f"{k}={v}" for k, v in meter.items())
                           + f"\nspindle_rpm={RPM}\nrelease_found_hold=yes\n")
        told, record = _commission(cfg, tmp_path, "--answers", str(answers))
        assert all(s["result"] == "pass" for s in record["steps"]), record
        assert told.returncode == 0, told.stdout + told.stderr
        assert "the feed hold found at the start is asserted again, as it was found" in told.stdout
        wait_for(lambda: _holds(tmp_path)[-1][0], 30.0, "the hold asserted again")
    changes = _holds(tmp_path)[seen:]
    assert changes[-1] == (True, "command"), changes   # asserted again by the command, not left to the watchdog


@pytest.mark.serial  # its Ctrl-C must land within the step's 2 s wait for the CNC: a loaded box made it land after
def test_ctrl_c_mid_step_leaves_the_hold_asserted_and_latched(tmp_path, meter):
    """A CNC that takes 5 s to confirm: the test-trip waits with the hold asserted; Ctrl-C comes then."""
    port = free_tcp_port()
    with Procs(tmp_path) as procs:
        _emulator(procs, port, "--cnc-hold-lag-ms", "5000")
        cfg = _config(tmp_path, port, machine="ctrl-c")
        out = tmp_path / "cc.out"
        with open(out, "w") as fh:
            # Ctrl-C at a terminal reaches a foreground command whose SIGINT is as the shell found it: a test run
            # started in the background (`cmd &` from a script) ignores SIGINT, and its children inherit that
            p = subprocess.Popen(CMD + ["commission", "--config", str(cfg), "--readings", _readings(meter),
                                        "--spindle-rpm", str(RPM)], stdout=fh, stderr=subprocess.STDOUT,
                                 env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                 preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
            procs.procs.append(p)
            wait_for(lambda: "asserting the feed hold (test-trip)" in out.read_text(), 60.0, "the test-trip")
            wait_for(lambda: _holds(tmp_path)[-1:] == [(True, "command")], 30.0, "the hold on the DAQ")
            p.send_signal(signal.SIGINT)
            assert p.wait(30) == 130, out.read_text()
        text = out.read_text()
        assert "interrupted: the feed hold this command asserted stays asserted" in text
        assert "`millsense reset` clears it" in text and "Traceback" not in text
        from millsense.daemon.state_dir import state_dir

        latch = json.loads((state_dir("ctrl-c") / "latch.json").read_text())
        assert latch["latched"] is True and latch["reason"] == "commission: test-trip"
        assert not [c for c in _holds(tmp_path) if not c[0]], _holds(tmp_path)   # never released


@pytest.mark.quick
@pytest.mark.parametrize("readings, said", [("i_u=abc", "i_u=abc: expected a positive number"),
                                            ("i_u=inf", "i_u=inf: expected a positive number"),
                                            ("i_x=3", "i_x: no such reading")])
def test_a_bad_reading_is_refused_before_the_daq_is_touched(tmp_path, readings, said):
    cfg = _config(tmp_path, free_tcp_port())   # nothing listens there: a reading is judged first
    p = subprocess.run(CMD + ["commission", "--config", str(cfg), "--readings", readings], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2 and p.stderr == f"millsense commission: error: {said}" + p.stderr.split(said)[1], p.stderr
    assert p.stderr.count("\n") == 1 and p.stdout == ""


@pytest.mark.parametrize("fault, said", [(("--swap", "i_x,i_v"), "cannot swap i_x: the DAQ sends v_uv"),
                                         (("--swap", "i_v,i_v"), "cannot swap i_v with itself"),
                                         (("--reverse", "enc"), "cannot reverse enc: the DAQ sends v_uv")])
def test_the_emulators_wiring_faults_refuse_a_channel_it_does_not_send(fault, said):
    p = subprocess.run(CMD + ["sim", "--scenario", SCENARIO, "--tcp", f"127.0.0.1:{free_tcp_port()}", *fault],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and p.stderr.startswith(f"millsense sim: error: {said}"), p.stderr
    assert p.stderr.count("\n") == 1


@pytest.mark.quick
def test_a_descriptor_that_does_not_fit_fails_first_and_the_signals_are_not_judged(tmp_path, meter):
    port = free_tcp_port()
    with Procs(tmp_path) as procs:
        _emulator(procs, port, "--descriptor-rate", "2000")
        p, record = _commission(_config(tmp_path, port), tmp_path, "--readings", _readings(meter),
                                "--spindle-rpm", str(RPM))
    assert p.returncode == 1, p.stdout + p.stderr
    steps = _steps(record)
    assert steps["descriptor"]["result"] == "fail" and steps["descriptor"]["figures"]["sample_rate_hz"] == 2000
    assert steps["descriptor"]["fixes"][0].startswith("daq.sample_rate_hz: speeds and torques would be off by 2")
    assert [steps[n]["result"] for n in ("scales", "phases", "speed")] == ["not checked"] * 3
    assert steps["test-trip"]["result"] == steps["watchdog"]["result"] == "pass"


def _apply(cfg: Path, fixes: list[str]) -> list[str]:
    """Each `channels.X.key = value` a fix proposes, written into the configuration as a user would."""
    import tomllib

    from tests.config.helpers import dumps

    doc = tomllib.loads(cfg.read_text())
    applied = []
    for fix in fixes:
        for name, key, value in re.findall(r"channels\.(\w+)\.(\w+) = (-?[0-9.e+-]+)", fix):
            doc["channels"][name][key] = int(value) if key == "counts_per_rev" else float(value)
            applied.append(f"channels.{name}.{key} = {value}")
    cfg.write_text(dumps(doc))
    return applied


@pytest.mark.parametrize("faults, replace", [
    (("--current-gain", "1.5"), None),
    (("--reverse", "i_w"), None),
    (("--reverse", "sp_rpm"), None),
    ((), ("counts_per_rev = 4096", "counts_per_rev = 2048")),
], ids=["current-gain", "reversed-current-sensor", "reversed-speed-signal", "counts-per-rev"])
def test_a_configuration_fix_written_into_the_file_commissions_the_same_machine(tmp_path, meter, faults, replace):
    """The fix is the answer, not a hint: the emulator keeps its fault, the file takes the fix, commission passes."""
    port = free_tcp_port()
    cfg = _config(tmp_path, port, replace=replace)
    with Procs(tmp_path) as procs:
        _emulator(procs, port, *faults)
        p, record = _commission(cfg, tmp_path, "--readings", _readings(meter), "--spindle-rpm", str(RPM))
        assert p.returncode == 1, p.stdout + p.stderr
        assert _apply(cfg, [f for s in record["steps"] for f in s["fixes"]]), record
        # the first run's heartbeats ended: the DAQ's watchdog holds the feed, released for the tests when told
        p, record = _commission(cfg, tmp_path, "--readings", _readings(meter), "--spindle-rpm", str(RPM),
                                "--release-found-hold")
    assert p.returncode == 0, p.stdout + p.stderr
    assert "\ncommissioned\n" in p.stdout


def test_crossed_phases_are_fixed_at_the_daqs_inputs_not_in_the_configuration(tmp_path, meter):
    """The DAQ's DESCRIPTOR names its channels; a [channels] table only scales the one of its name. So the fix
    for two crossed phases is their cables (here: the emulator's inputs crossed back), and it says no other."""
    port = free_tcp_port()
    (tmp_path / "crossed").mkdir()
    (tmp_path / "crossed-back").mkdir()
    with Procs(tmp_path / "crossed") as procs:
        _emulator(procs, port, "--swap", "i_v,i_w")
        p, record = _commission(_config(tmp_path, port), tmp_path, "--readings", _readings(meter),
                                "--spindle-rpm", str(RPM))
    fixes = _steps(record)["phases"]["fixes"]
    assert p.returncode == 1 and fixes[0].startswith("swap i_v and i_w: their cables on the DAQ"), fixes
    assert not re.search(r"\(or [^)]*\[channels\] tables' names\)", fixes[0]), fixes   # a rename moves no signal
    port = free_tcp_port()
    with Procs(tmp_path / "crossed-back") as procs:
        _emulator(procs, port, "--swap", "i_v,i_w", "--swap", "i_v,i_w")   # the two cables swapped at the DAQ
        p, record = _commission(_config(tmp_path, port), tmp_path, "--readings", _readings(meter),
                                "--spindle-rpm", str(RPM))
    assert p.returncode == 0 and _steps(record)["phases"]["result"] == "pass", p.stdout + p.stderr


def test_a_second_run_the_same_day_keeps_the_first_runs_report(tmp_path, meter):
    """The default report is the shop's record: the run after a commissioned one (here it finds the hold the
    first left and is not told to release it: not commissioned) writes beside it, never over it."""
    port = free_tcp_port()
    state = tmp_path / "state"
    env = {**os.environ, "STATE_DIRECTORY": str(state)}
    args = CMD + ["commission", "--config", str(_config(tmp_path, port)), "--readings", _readings(meter),
                  "--spindle-rpm", str(RPM)]
    with Procs(tmp_path) as procs:
        _emulator(procs, port)
        first = subprocess.run(args, capture_output=True, text=True, timeout=120, env=env)
        second = subprocess.run(args, capture_output=True, text=True, timeout=120, env=env)
    assert (first.returncode, second.returncode) == (0, 1), first.stdout + second.stdout
    reports = sorted(state.glob("commissioning-comm-*.json"), key=lambda p: len(p.name))   # the first, then -2
    assert [p.name for p in reports] == [f"{reports[0].stem}.json", f"{reports[0].stem}-2.json"], reports
    assert json.loads(reports[0].read_text())["commissioned"] is True
    assert json.loads(reports[1].read_text())["commissioned"] is False
    assert f"report: {reports[1]} and {reports[1].with_suffix('.txt')}" in second.stdout
