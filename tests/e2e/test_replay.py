"""`millsense replay`: a capture from `millsense sim --capture` through the live pipeline, JSON lines out."""

from __future__ import annotations

import json
import re
import subprocess

import numpy as np
import pytest

from tests.e2e.helpers import CMD, write_config
from tests.e2e.truth import truth_revs


@pytest.fixture(scope="module")
def capture(step_capture, tmp_path_factory):
    cap, truth_lines = step_capture
    cfg = write_config(
        tmp_path_factory.mktemp("replay") / "r.toml", machine="replay-01", daq='transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = 1'
    )
    return cap, cfg, truth_lines


def _replay(cap, cfg):
    p = subprocess.run(CMD + ["replay", str(cap), "--config", str(cfg)], capture_output=True, text=True, timeout=120)
    lines = [json.loads(x) for x in p.stdout.splitlines()]
    return p, lines


def _counts(stderr: str) -> dict[str, int]:
    return {k: int(v) for k, v in re.findall(r"(\w+)=(\d+)", stderr)}


def test_replay_estimates_every_revolution_with_index_time(capture):
    cap, cfg, truth = capture
    p, lines = _replay(cap, cfg)
    assert p.returncode == 0, p.stderr
    est = [x for x in lines if x["type"] == "estimate"]
    assert est and all(x["machine"] == "replay-01" for x in est)
    revs = [x["rev"] for x in est]
    assert revs == list(range(1, len(revs) + 1))
    # t is the time of the revolution's last sample after the first sample: the truth's revolution ends
    ends = np.array([r["t_end_s"] for r in truth_revs(truth)])
    t = np.array([x["t"] for x in est])
    nearest = np.abs(ends[None, :] - t[:, None]).min(axis=1)
    assert np.median(nearest) <= 0.0015, f"median |t - truth end| = {np.median(nearest) * 1e3:.2f} ms"
    assert abs(len(est) - len(ends)) <= 2, (len(est), len(ends))
    c = _counts(p.stderr)
    assert c["estimates"] == len(est) and c["bad_crc"] == 0 and c["truncated_bytes"] == 0


def test_replay_is_deterministic(capture):
    cap, cfg, _ = capture
    a, _ = _replay(cap, cfg)
    b, _ = _replay(cap, cfg)
    assert a.returncode == b.returncode == 0
    assert a.stdout == b.stdout and a.stdout


def test_corrupt_and_truncated_capture_is_read_as_far_as_it_goes(capture, tmp_path):
    cap, cfg, _ = capture
    data = bytearray(cap.read_bytes())
    rng = np.random.default_rng(3)
    for pos in rng.integers(len(data) // 4, 3 * len(data) // 4, size=40):
        data[pos] ^= 0xFF
    bad = tmp_path / "bad.cap"
    bad.write_bytes(bytes(data[: len(data) - 37]))
    good_p, good = _replay(cap, cfg)
    p, lines = _replay(bad, cfg)
    assert p.returncode == 0, p.stderr
    c = _counts(p.stderr)
    assert c["bad_crc"] > 0 and c["dropped_bytes"] > 0 and c["truncated_bytes"] > 0, p.stderr
    est = [x for x in lines if x["type"] == "estimate"]
    assert len(est) >= 0.8 * len([x for x in good if x["type"] == "estimate"])
    invalid = [x for x in est if x.get("valid") is False]
    assert invalid and all(x["torque_nm"] is None for x in invalid)
    assert "Traceback" not in p.stderr


def test_unusable_captures_give_one_clear_error(tmp_path, capture):
    _, cfg, _ = capture
    p = subprocess.run(CMD + ["replay", str(tmp_path / "nope.cap"), "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "cannot read" in p.stderr and "Traceback" not in p.stderr
    junk = tmp_path / "junk.cap"
    junk.write_bytes(np.random.default_rng(1).bytes(20000))
    p = subprocess.run(CMD + ["replay", str(junk), "--config", str(cfg)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 1 and "no DAQ descriptor" in p.stderr and "Traceback" not in p.stderr


def test_a_signals_fault_is_reported_where_the_live_daemon_raises_it(capture, tmp_path):
    """What makes the live daemon blind (fault `signals`: with `[interlock] on_blind = "hold"` it holds the
    feed) is said on stderr, with where it was raised and cleared; a sound capture says nothing of it."""
    _, cfg, _ = capture
    clean, _ = _replay(capture[0], cfg)
    assert "fault" not in clean.stderr, clean.stderr
    cap = tmp_path / "pinned.bin"
    sim = subprocess.run(CMD + ["sim", "--scenario", "step", "--capture", str(cap), "--duration-s", "4",
                                "--pin", "i_u=0", "--faults-from-s", "1.5"], capture_output=True, text=True, timeout=120)
    assert sim.returncode == 0, sim.stderr
    p, lines = _replay(cap, cfg)
    assert p.returncode == 0, p.stderr
    said = re.findall(r"^millsense replay: warning: fault signals from t=([0-9.]+) s: (.*)$", p.stderr, re.M)
    assert len(said) == 1, p.stderr
    t, reason = float(said[0][0]), said[0][1]
    assert 1.5 <= t <= 2.6 and reason.startswith("i_u: "), said   # raised within RAISE_S..1 s of the pin
    assert all(x["valid"] is False for x in lines if x["type"] == "estimate" and x["t"] > 1.7)
