"""Plant behaviour: feed hold, speed droop, feed drive, determinism, loop, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.sim import Plant

from .helpers import physical, steady_cut_revs


def test_feed_hold_stops_the_cut_and_the_spindle_keeps_turning():
    plant = Plant("step", noise_scale=0.0)
    plant.step(23_000)  # in the 3 mm step
    before = plant.truth.drain()[-1]
    assert before["cutting"] and before["torque_nm"] > 5
    plant.feed_hold = True
    plant.step(2_000)
    held = plant.truth.drain()
    (ev,) = [r for r in held if r.get("event") == "feed_hold"]
    assert ev == {"event": "feed_hold", "on": True, "index": 23_000, "t_s": 23.0}
    held = [r for r in held if "rev" in r]
    assert all(r["feed_hold"] for r in held[1:])
    late = [r for r in held if r["t_end_s"] > 23.3]
    assert late and all(r["feed_per_tooth_mm"] < 1e-6 for r in late)
    assert all(r["torque_nm"] < 0.01 * before["torque_nm"] for r in late)
    assert all(r["spindle_rpm"] == pytest.approx(600, rel=0.01) for r in late)
    first = held[0]  # the revolution during which the hold came: the feed ramps down within ~50 ms
    assert first["feed_per_tooth_mm"] > 0.5 * before["feed_per_tooth_mm"]
    plant.feed_hold = False
    plant.step(1_000)
    resumed = [r for r in plant.truth.drain() if "rev" in r]
    assert resumed[-1]["torque_nm"] == pytest.approx(before["torque_nm"], rel=0.02)
    assert not resumed[-1]["feed_hold"]


def test_speed_droops_under_load_and_recovers():
    plant = Plant("step", noise_scale=0.0)
    plant.step(22_000)
    revs = plant.truth.revolutions()
    entry = [r for r in revs if 15.0 < r["t_end_s"] < 18.5]  # tool meeting the 3 mm step at x = 50
    rpm = np.array([r["spindle_rpm"] for r in entry])
    assert rpm.min() < 600 * (1 - 5e-5)  # it droops ...
    assert rpm.min() > 600 * (1 - 0.01)  # ... slightly
    steady = [r["spindle_rpm"] for r in revs if 20 < r["t_end_s"] < 22]
    assert np.allclose(steady, 600, rtol=2e-5)  # and recovers (PI: no steady-state droop)


def test_feed_drive_current_and_dynamometer_follow_the_force():
    """fig6: current = (F_x + friction)/950 behind the servo bandwidth; fx channel = F_x."""
    plant = Plant("fig6", noise_scale=0.0)
    sig = physical(plant, plant.step(20_000))
    revs = [r for r in steady_cut_revs(plant.truth.revolutions()) if r["axial_depth_mm"] == 16.0]
    assert len(revs) > 20
    a, b = revs[0]["index_end"] + 1, revs[-1]["index_end"] + 1
    fx_truth = np.mean([r["force_x_n"] for r in revs[1:]])
    fy_truth = np.mean([r["force_y_n"] for r in revs[1:]])
    assert sig["fx"][a:b].mean() == pytest.approx(fx_truth, rel=0.01, abs=2)
    assert sig["fy"][a:b].mean() == pytest.approx(fy_truth, rel=0.01, abs=2)
    assert 950 * sig["ix_feed"][a:b].mean() - 120 == pytest.approx(fx_truth, rel=0.01, abs=3)
    assert sig["fx_rate"][a:b].mean() == pytest.approx(0.2083 * 4 * 600, rel=1e-3)


def test_deterministic_per_seed():
    a, b, c = (Plant("breakage", seed=s) for s in (7, 7, 8))
    xa, xb, xc = a.step(3000), b.step(3000), c.step(3000)
    np.testing.assert_array_equal(xa, xb)
    assert not np.array_equal(xa, xc)
    assert a.truth.revolutions() == b.truth.revolutions()


def test_loop_repeats_with_continuous_index_and_angle():
    plant = Plant("crash", loop=True, noise_scale=0.0)
    enc_col = plant.descriptor.names.index("sp_enc")
    duration = 10.6
    counts = plant.step(round(2.2 * duration * 1000))
    assert not plant.done and plant.duration_s == math.inf
    enc = counts[:, enc_col].astype(np.int64)
    step = (np.diff(enc) + 32768) % 65536 - 32768  # unwrap the 16-bit counter
    assert step.min() >= 0 and step.max() < 4096 * 600 / 60 / 1000 * 1.5  # never jumps
    events = plant.truth.events()
    assert [e["event"] for e in events].count("scenario_restart") == 2
    assert [e["event"] for e in events].count("crash_power") == 2  # the crash happens in every pass (8.2 s in)
    idx = [e["index"] for e in events if e["event"] == "crash_power"]
    assert idx[1] - idx[0] == pytest.approx(duration * 1000, abs=150)


def test_not_looping_is_done_at_the_end():
    plant = Plant("aircut-high")
    plant.step(round(plant.duration_s * 1000) - 1)
    assert not plant.done
    plant.step(1)
    assert plant.done


def test_bad_input_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown scenario 'nope'.*step"):
        Plant("nope")
    with pytest.raises(ValueError, match="unknown optional channel.*fq"):
        Plant("step", extra_channels=["fq"])
    with pytest.raises(ValueError, match="noise_scale"):
        Plant("step", noise_scale=-1)
    with pytest.raises(ValueError, match="cut-off"):
        Plant("step", filter_cutoff_hz=6000)


def test_extra_channels_on_demand():
    assert Plant("step").descriptor.names == ("v_uv", "v_vw", "v_wu", "i_u", "i_v", "i_w", "sp_rpm", "sp_enc")
    p = Plant("step", extra_channels=True)
    assert p.descriptor.names[8:] == ("mot_rpm", "ix_feed", "fx_rate", "fx", "fy", "fz")
    assert p.step(5).shape == (5, 14)
    assert "fx" in Plant("fig5").descriptor.names
    assert Plant("fig5", extra_channels=False).descriptor.channel_count == 8
