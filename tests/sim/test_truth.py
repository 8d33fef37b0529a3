"""Truth records: revolution boundaries from the angle, means, flags, events."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from millsense.sim import Plant, SCENARIOS
from millsense.sim.machine import MATERIALS

from .helpers import steady_cut_revs

FIELDS = {"rev", "index_end", "t_end_s", "spindle_rpm", "gear", "torque_nm", "force_n", "force_x_n", "force_y_n",
          "force_z_n", "force_tangential_n", "feed_per_tooth_mm", "radial_depth_mm", "axial_depth_mm", "cutting",
          "steady", "feed_hold"}


def test_revolution_boundaries_follow_the_encoder():
    """index_end is the last sample of the revolution: the encoder (4096/rev, started at 0)
    is below the next multiple of 4096 there and at or above it one sample later."""
    plant = Plant("step-1800", noise_scale=0.0)
    counts = plant.step(4000)
    enc = counts[:, plant.descriptor.names.index("sp_enc")].astype(np.int64)
    unwrapped = np.concatenate(([enc[0]], enc[0] + np.cumsum((np.diff(enc) + 32768) % 65536 - 32768)))
    revs = plant.truth.revolutions()
    assert len(revs) == pytest.approx(4 * 1800 / 60, abs=1)
    for r in revs:
        k = r["index_end"]
        if k + 1 >= len(unwrapped):
            break
        boundary = 4096 * (r["rev"] + 1)
        assert unwrapped[k] < boundary <= unwrapped[k + 1], r
        assert k / 1000 - 1e-6 < r["t_end_s"] <= (k + 1) / 1000 + 1e-6


def test_records_have_the_documented_fields_and_are_json():
    plant = Plant("fig7")
    plant.step(5000)
    revs = plant.truth.revolutions()
    assert revs and all(set(r) >= FIELDS for r in revs)
    assert [r["rev"] for r in revs] == list(range(len(revs)))
    json.loads(json.dumps(list(plant.truth)))
    new = plant.truth.drain()
    assert len(new) == len(plant.truth) and plant.truth.drain() == []


def test_revolution_means_are_exact_for_a_steady_slot():
    """Steady 3 mm slot in SM45C: mean torque = R·K_s(t_a)·t_c·a·N/π, t_a = 2t_c/π, and
    mean resultant = sqrt(1 + r1²)·F_t (2 flutes, one tooth in cut at a time apart from the helix overlap)."""
    plant = Plant("step", noise_scale=0.0)
    plant.step(24_000)
    revs = [r for r in steady_cut_revs(plant.truth.revolutions()) if r["axial_depth_mm"] == 3.0]
    assert len(revs) > 10
    m = MATERIALS["SM45C"]
    tc = 200 / (2 * 600)
    ta = 2 * tc / math.pi
    ks, r1 = m.ks * ta**m.ks_exp, m.r1 * ta**m.r1_exp
    ft = ks * tc * 3.0 * 2 / math.pi
    for r in revs:
        assert r["force_tangential_n"] == pytest.approx(ft, rel=2e-3)
        assert r["torque_nm"] == pytest.approx(ft * 0.010, rel=2e-3)
        assert r["feed_per_tooth_mm"] == pytest.approx(tc, rel=1e-3)
        assert r["force_n"] <= math.sqrt(1 + r1**2) * r["force_tangential_n"] * (1 + 1e-9)
        assert r["force_n"] > 0.95 * math.sqrt(1 + r1**2) * r["force_tangential_n"]
        assert r["force_z_n"] == pytest.approx(m.r2 * ta**m.r2_exp * ft, rel=2e-3)


def test_steady_flag_false_at_entry_and_steps():
    plant = Plant("step", noise_scale=0.0)
    plant.step(round(SCENARIOS["step"].duration_s * 1000))
    revs = plant.truth.revolutions()
    # the tool centre is at s(t) = −15 + 10/3·t mm; the step walls are at 25 and 50 mm, and the leading
    # edge (s + 10) meets them 3 s earlier: nothing there may be steady
    for r in revs:
        s = -15 + 10 / 3 * r["t_end_s"]
        for wall in (0.0, 25.0, 50.0, 75.0):
            if wall - 10 + 0.01 < s <= wall + 0.6:  # and the revolution after the centre passes
                assert not r["steady"], r
    cut = [r for r in revs if r["cutting"]]
    assert sum(r["steady"] for r in cut) > 0.5 * len(cut)


def test_events_crash_and_breakage():
    crash = Plant("crash", noise_scale=0.0)
    crash.step(round(crash.duration_s * 1000))
    (ev,) = [e for e in crash.truth.events() if e["event"] == "crash_power"]
    assert ev["power_w"] >= 15_000
    revs = crash.truth.revolutions()
    before = [r for r in revs if r["t_end_s"] < ev["t_s"] - 0.1]
    assert max(r["airgap_power_w"] for r in before) < 15_000
    assert max(r["airgap_power_w"] for r in revs) > 15_000
    brk = Plant("breakage", noise_scale=0.0)
    brk.step(round(brk.duration_s * 1000))
    (ev,) = [e for e in brk.truth.events() if e["event"] == "tool_breakage"]
    # the tool centre reaches 60 mm at (60 + 15)/(250/60) s
    assert ev["t_s"] == pytest.approx(75 / (250 / 60), abs=0.01)
    steady3 = [r for r in steady_cut_revs(brk.truth.revolutions()) if r["axial_depth_mm"] == 3.0]
    pre = [r["torque_nm"] for r in steady3 if r["t_end_s"] < ev["t_s"]]
    post = [r["torque_nm"] for r in steady3 if r["t_end_s"] > ev["t_s"] + 0.3]
    assert np.mean(post) / np.mean(pre) == pytest.approx(2 ** MATERIALS["SS41"].ks_exp, rel=5e-3)
