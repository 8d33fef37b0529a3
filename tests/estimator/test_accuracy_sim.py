"""Estimates against the simulator's truth, revolution by revolution.

Acceptance: steady torque within 2 % + 0.03 N·m in both gears, with and without
the anti-alias filter; radial and axial depth within 5 % by the feed-drive,
dynamometer and torque-only methods. Revolutions are paired by their last
sample (seq_end <-> index_end; ±1 sample where a boundary falls on a sample).
Every test runs on captures of three seeds (sensor noise, offsets and the
plant's disturbances differ by seed), so a pass is not one lucky draw.
"""

from __future__ import annotations

import numpy as np
import pytest

from . import simcase


SEEDS = (11, 12, 13)


@pytest.fixture(scope="module", params=SEEDS, ids=lambda s: f"seed{s}")
def caps(request, tmp_path_factory):
    tmp = tmp_path_factory.mktemp(f"caps-{request.param}")
    seed = request.param

    def get(scenario, filter_cutoff_hz=None):
        return simcase.capture(tmp, scenario, seed=seed, filter_cutoff_hz=filter_cutoff_hz)

    get.tmp = tmp
    return get


def _torque_pairs(caps, scenario, fc, encoder=True):
    cap, truth_path = caps(scenario, fc)
    settings = simcase.settings_for(scenario, caps.tmp, filter_cutoff_hz=fc, encoder=encoder)
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    # speed-integrated revolutions start wherever the angle origin fell: nearest truth end
    pairs = simcase.match(est, truth, 1 if encoder else 200)
    steady = [(e, t) for e, t in pairs if t["steady"] and e["valid"]]
    return est, truth, steady


@pytest.mark.parametrize("scenario", ["step", "step-1200"])
def test_steady_torque_within_2pct_behind_the_filter(caps, scenario):
    """Every steady revolution, cutting or not, in each gear."""
    _, _, steady = _torque_pairs(caps, scenario, 200.0)
    assert sum(t["cutting"] for _, t in steady) >= 100
    for e, t in steady:
        assert abs(e["torque_nm"] - t["torque_nm"]) <= 0.02 * abs(t["torque_nm"]) + 0.03, (e, t)
        assert e["gear"] == t["gear"]


@pytest.mark.parametrize("scenario", ["step", "step-1200"])
def test_steady_torque_without_filter(caps, scenario):
    """No anti-alias filter: the sensor noise aliases undiminished into the samples.

    The per-revolution error is then noise, not bias: its floor is σ_P/ω ([P]
    eq. 20), about 0.018 N·m per revolution at 600 rpm with the simulated
    sensors, so an air-cut revolution passes 0.03 N·m now and then (~1 in 15).
    Checked: every steady segment's mean error within 2 % + 0.03 N·m, at least
    90 % of single revolutions within it, and none beyond 4 reported sigmas.
    """
    _, _, steady = _torque_pairs(caps, scenario, 0.0)
    assert sum(t["cutting"] for _, t in steady) >= 100
    err = np.array([e["torque_nm"] - t["torque_nm"] for e, t in steady])
    truth = np.array([t["torque_nm"] for _, t in steady])
    sigma = np.array([e["torque_sigma_nm"] for e, _ in steady])
    bound = 0.02 * np.abs(truth) + 0.03
    assert np.mean(np.abs(err) <= bound) >= 0.90
    assert np.all(np.abs(err) <= bound + 4 * sigma)
    for level in np.unique(np.round(truth, 1)):
        seg = np.round(truth, 1) == level
        if seg.sum() >= 10:
            assert abs(err[seg].mean()) <= bound[seg].min(), level
    assert all(e["gear"] == t["gear"] for e, t in steady)


def test_speed_channel_alone_matches_truth(caps):
    """No encoder: the angle integrated from sp_rpm. Revolutions start elsewhere but hold a whole turn."""
    est, truth, steady = _torque_pairs(caps, "step", None, encoder=False)
    by_rev = {t["rev"]: t for t in truth}
    checked = 0
    for e, t in steady:
        prev = by_rev.get(t["rev"] - 1)
        if t["cutting"] and prev is not None and prev["steady"] and abs(prev["torque_nm"] - t["torque_nm"]) < 0.01:
            assert abs(e["torque_nm"] - t["torque_nm"]) <= 0.02 * abs(t["torque_nm"]) + 0.03
            checked += 1
    assert checked >= 100


def test_encoder_and_speed_integration_agree(caps):
    cap, _ = caps("step-1200")
    enc, _ = simcase.run(cap, simcase.settings_for("step-1200", caps.tmp))
    spd, _ = simcase.run(cap, simcase.settings_for("step-1200", caps.tmp, encoder=False))
    rpm_e = np.array([e["spindle_rpm"] for e in enc if e["valid"]][5:])
    rpm_s = np.array([e["spindle_rpm"] for e in spd if e["valid"]][5:])
    assert abs(len(rpm_e) - len(rpm_s)) <= 1
    # the simulated sp_rpm sensor has an offset of up to 0.2 rpm (its datasheet: 0): 0.02 %
    assert abs(rpm_e.mean() - rpm_s.mean()) < 0.25


def _depth_pairs(caps, scenario, method, known=None):
    """Settled revolutions of a cut (see simcase.settled). Feed-drive: the feed-current
    sensor zeroed on the air feed first (its simulated offset is up to 4.75 N)."""
    cap, truth_path = caps(scenario)
    zero = simcase.zero_feed_current(cap, scenario, caps.tmp) if method == "feed-drive" else 0.0
    settings = simcase.settings_for(scenario, caps.tmp, method=method, known=known, ix_offset_counts=zero)
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    ok = simcase.settled(truth, scenario)
    return [(e, t) for e, t in simcase.match(est, truth, 1) if t["rev"] in ok and e["valid"]]


@pytest.mark.parametrize(
    "scenario,method,known",
    [
        ("fig5", "feed-drive", None),
        ("fig6", "feed-drive", None),
        ("fig7", "feed-drive", None),
        ("fig5", "dynamometer", None),
        ("fig7", "dynamometer", None),
        ("fig5", "torque-only", "axial"),
        ("fig7", "torque-only", "axial"),
        ("fig6", "torque-only", "radial"),
        ("step", "torque-only", None),      # slot: radial = diameter, axial from torque
        ("step-1200", "torque-only", None),  # the high gear: its own friction, ratio and speed
        ("step-1800", "torque-only", None),
    ],
)
def test_depths_within_5pct(caps, scenario, method, known):
    pairs = _depth_pairs(caps, scenario, method, known)
    assert len(pairs) >= 30, len(pairs)
    for e, t in pairs:
        assert e["depth_status"] == "ok", (e, t)
        assert e["radial_depth_mm"] == pytest.approx(t["radial_depth_mm"], rel=0.05), (e, t)
        assert e["axial_depth_mm"] == pytest.approx(t["axial_depth_mm"], rel=0.05), (e, t)


def test_feed_force_and_feed_per_tooth(caps):
    pairs = _depth_pairs(caps, "fig7", "feed-drive")
    for e, t in pairs:
        assert e["feed_per_tooth_mm"] == pytest.approx(t["feed_per_tooth_mm"], rel=0.01)
        assert e["force_feed_n"] == pytest.approx(t["force_x_n"], rel=0.03, abs=5.0)


def test_air_cut_revolutions_say_so(caps):
    cap, truth_path = caps("step")
    est, _ = simcase.run(cap, simcase.settings_for("step", caps.tmp))
    pairs = simcase.match(est, simcase.read_truth(truth_path), 1)
    air = [e for e, t in pairs if t["steady"] and not t["cutting"] and e["valid"]]
    assert len(air) >= 10
    assert all(e["depth_status"] == "air_cut" and e["cutting"] is False for e in air)
    assert all(abs(e["torque_nm"]) < 0.05 for e in air)


def test_damaged_capture_flags_revolutions_and_conserves_lost_samples(caps, tmp_path):
    """Cut bytes out of a real capture: the decoder resyncs, the gap is lost samples."""
    from millsense.daemon.commands.capture_reader import iter_capture_blocks
    from millsense.daemon.pipeline.estimator import Estimator

    cap, _ = caps("step")
    data = bytearray(cap.read_bytes())
    for at in (200_000, 420_000, 421_000):
        del data[at : at + 3000]
    bad = tmp_path / "damaged.bin"
    bad.write_bytes(bytes(data))
    settings = simcase.settings_for("step", caps.tmp)
    est, out, reported = None, [], 0
    for desc, block in iter_capture_blocks(bad):
        est = est or Estimator(settings, desc, desc.sample_rate_hz)
        reported += block.lost_before
        out += est.process(block).estimates
    assert reported > 0
    invalid = [e for e in out if not e["valid"]]
    assert 1 <= len(invalid) <= 3
    assert all(e["torque_nm"] is None and e["lost_samples"] > 0 for e in invalid)
    assert sum(e["lost_samples"] for e in out) + est.lost_samples_idle + est.lost_samples_pending == reported
