"""The estimator on exactly known three-phase waveforms (no simulator involved)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from millsense.daemon.pipeline.estimator import Estimator
from millsense.drivers.base import SampleBlock

from . import configs, synthetic
from .synthetic import Machine

pytestmark = pytest.mark.quick


def _blocks(raw: np.ndarray, size: int = 10, seq0: int = 0):
    for a in range(0, len(raw), size):
        yield SampleBlock(seq0 + a, seq0 + a, raw[a : a + size], 0, False)


def _run(est: Estimator, blocks) -> list[dict]:
    out: list[dict] = []
    for b in blocks:
        out += est.process(b).estimates
    return out


@pytest.mark.parametrize(
    "machine",
    [
        Machine(),                                                      # low gear, 600 rpm, f_e ≈ 98 Hz
        Machine(spindle_rpm=900.0, slip=0.03),                         # f_e ≈ 149 Hz: filter gain 0.77
        Machine(spindle_rpm=2500.0, gear_ratio=1.157, slip=0.01),      # 24 samples a revolution
        Machine(spindle_rpm=900.0, cutoff_hz=0.0),                     # no filter
        Machine(winding="wye"),
    ],
    ids=["600rpm", "900rpm-filter", "2500rpm", "no-filter", "wye"],
)
def test_torque_from_known_waveforms(tmp_path, machine):
    settings = configs.load(tmp_path, filter_cutoff_hz=machine.cutoff_hz, winding=machine.winding)
    est = Estimator(settings, synthetic.descriptor(), 1000)
    out = _run(est, _blocks(synthetic.counts(machine, 6000)))
    good = [e for e in out if e["valid"]][2:]
    assert len(good) >= machine.spindle_rpm / 60 * 5
    gear = settings.gears[0] if machine.gear_ratio > 2 else settings.gears[1]
    truth = machine.torque_nm(gear.friction_torque_nm, gear.viscous_nms)
    torque = np.array([e["torque_nm"] for e in good])
    # quantisation of the counts is the only error left: far below the 2 % acceptance
    assert np.all(np.abs(torque - truth) < 0.002 * abs(truth) + 0.01), (truth, torque.min(), torque.max())
    assert {e["gear"] for e in good} == {gear.name}
    # each boundary is placed to within half an encoder count: 1 count in 4096 per revolution
    np.testing.assert_allclose([e["spindle_rpm"] for e in good], machine.spindle_rpm, rtol=1 / 4096)
    np.testing.assert_allclose([e["p_in_w"] for e in good], machine.p_in_w, rtol=2e-3)
    # payload-ready: plain JSON types, every field of interfaces.md's estimate but machine and t
    text = json.dumps(out, allow_nan=False)
    assert json.loads(text) == out
    fields = {"rev", "spindle_rpm", "gear", "p_in_w", "p_gap_w", "torque_nm", "torque_sigma_nm", "force_n",
              "force_tangential_n", "force_feed_n", "feed_per_tooth_mm", "radial_depth_mm", "axial_depth_mm",
              "depth_status", "cutting", "samples", "lost_samples"}
    assert all(fields | {"seq_end", "valid", "accelerating", "invalid", "saturated"} <= set(e) for e in out)


def test_two_wattmeter_form_with_two_currents_and_two_voltages(tmp_path):
    m = Machine()
    chans = tuple(c for c in synthetic.CHANNELS if c[1] not in ("i_w", "v_wu"))
    settings = configs.load(tmp_path, drop=("i_w", "v_wu"))
    est = Estimator(settings, synthetic.descriptor(chans), 1000)
    assert not est._symmetric
    out = _run(est, _blocks(synthetic.counts(m, 4000, chans)))
    good = [e for e in out if e["valid"]][2:]
    truth = m.torque_nm(2.6629, 0.04)
    torque = np.array([e["torque_nm"] for e in good])
    assert np.all(np.abs(torque - truth) < 0.002 * abs(truth) + 0.01)


def test_an_encoder_count_that_steps_back_at_a_boundary_adds_no_revolutions(tmp_path):
    """The encoder's count wobbling by more than a sample's advance (chatter, a noisy count): each
    revolution is still closed once, at 600 rpm and its torque. Before, each wobble across a boundary
    published one- and two-sample revolutions as valid (50 000 rpm, -127 N·m)."""
    m = Machine()
    raw = synthetic.counts(m, 6000)
    enc = [k for k, (_, name) in enumerate(synthetic.CHANNELS) if name == "sp_enc"][0]
    wobble = np.random.default_rng(11).integers(-60, 61, size=len(raw))   # a sample advances 41 counts
    raw[:, enc] = (raw[:, enc].astype(np.int64) + wobble).astype(np.int16)   # wraps as the DAQ's int16 does
    est = Estimator(configs.load(tmp_path), synthetic.descriptor(), 1000)
    out = _run(est, _blocks(raw))
    assert 55 <= len(out) <= 61   # 6 s at 10 revolutions a second
    assert min(e["samples"] for e in out) >= 97
    good = [e for e in out if e["valid"]][2:]
    np.testing.assert_allclose([e["spindle_rpm"] for e in good], 600.0, rtol=0.04)
    truth = m.torque_nm(2.6629, 0.04)
    assert np.all(np.abs(np.array([e["torque_nm"] for e in good]) - truth) < 0.01 * truth)


@pytest.mark.parametrize("jump_counts", [2048, -2048, 700])
def test_an_encoder_count_that_jumps_for_one_sample_invalidates_its_revolution(tmp_path, jump_counts):
    """One sample of the encoder's count far off (a glitch on its lines): the angle steps faster than any
    gear turns the spindle. Before, the boundary moved to the glitch and a 50-sample revolution at
    "1200 rpm" and a 150-sample one at "400 rpm" were published valid; now the revolution that holds it is
    invalid ("signals": no sample was lost) and every valid one is 600 rpm."""
    m = Machine()
    raw = synthetic.counts(m, 3000)
    enc = [k for k, (_, name) in enumerate(synthetic.CHANNELS) if name == "sp_enc"][0]
    glitches = (1450, 2170)   # half a revolution before a boundary, and a third of one
    for g in glitches:
        raw[g, enc] = np.int16((int(raw[g, enc]) + jump_counts + 32768) % 65536 - 32768)
    est = Estimator(configs.load(tmp_path), synthetic.descriptor(), 1000)
    out = _run(est, _blocks(raw))
    bad = [e for e in out if not e["valid"]]
    assert [e["invalid"] for e in bad] == ["signals", "signals"]
    assert [e["seq_end"] - e["samples"] < g <= e["seq_end"] for e, g in zip(bad, glitches)] == [True, True]
    assert all(e["lost_samples"] == 0 for e in out)
    good = [e for e in out if e["valid"]][2:]
    np.testing.assert_allclose([e["spindle_rpm"] for e in good], 600.0, rtol=1 / 4096 * 10)


def test_without_pole_pairs_the_slip_biases_torque_as_expected(tmp_path):
    """Without pole pairs, P_g/ω_sp over-states T_e·g by 1/(1 - s): the reason to configure them."""
    m = Machine(slip=0.04)
    settings = configs.load(tmp_path, pole_pairs=None)
    est = Estimator(settings, synthetic.descriptor(), 1000)
    good = [e for e in _run(est, _blocks(synthetic.counts(m, 4000))) if e["valid"]][2:]
    omega = 2 * math.pi * m.spindle_rpm / 60
    expected = (m.p_in_w - m.p_cu_w) / omega - 2.6629 - 0.04 * omega
    torque = np.array([e["torque_nm"] for e in good])
    assert np.all(np.abs(torque - expected) < 0.002 * abs(expected) + 0.01)
    assert np.all(torque > m.torque_nm(2.6629, 0.04) * 1.03)


def test_speed_channel_alone_gives_the_same_torque(tmp_path):
    m = Machine(spindle_rpm=1800.0, gear_ratio=1.157, slip=0.01)
    chans = tuple(c for c in synthetic.CHANNELS if c[1] != "sp_enc")
    settings = configs.load(tmp_path, encoder=False)
    est = Estimator(settings, synthetic.descriptor(chans), 1000)
    good = [e for e in _run(est, _blocks(synthetic.counts(m, 4000, chans))) if e["valid"]][2:]
    truth = m.torque_nm(1.616, 0.0022)
    torque = np.array([e["torque_nm"] for e in good])
    assert np.all(np.abs(torque - truth) < 0.002 * abs(truth) + 0.01)


def test_lost_samples_are_flagged_and_counted_once(tmp_path):
    m = Machine()
    raw = synthetic.counts(m, 8000)
    settings = configs.load(tmp_path)
    est = Estimator(settings, synthetic.descriptor(), 1000)
    rng = np.random.default_rng(3)
    # the driver's view: blocks of 1-20 samples, some dropped whole (lost_before on the next)
    out, lost_reported, pos, pending = [], 0, 0, 0
    while pos < len(raw):
        n = int(rng.integers(1, 21))
        if rng.random() < 0.03:
            pending += min(n, len(raw) - pos)
        else:
            blk = SampleBlock(pos, pos, raw[pos : pos + n], pending, False)
            lost_reported += pending
            pending = 0
            out += est.process(blk).estimates
        pos += n
    assert lost_reported > 0
    bad = [e for e in out if not e["valid"]]
    assert bad and all(e["torque_nm"] is None and e["force_n"] is None and e["lost_samples"] > 0 for e in bad)
    assert all(e["lost_samples"] == 0 for e in out if e["valid"])
    assert sum(e["lost_samples"] for e in out) + est.lost_samples_idle + est.lost_samples_pending == lost_reported
    assert est.lost_samples_total == lost_reported
    truth = m.torque_nm(2.6629, 0.04)
    good = [e["torque_nm"] for e in out if e["valid"]][2:]
    assert np.all(np.abs(np.array(good) - truth) < 0.002 * abs(truth) + 0.01)


def test_stopped_spindle_reports_stopped_and_no_revolutions(tmp_path):
    m = Machine(spindle_rpm=20.0)
    settings = configs.load(tmp_path)
    est = Estimator(settings, synthetic.descriptor(), 1000)
    results = [est.process(b) for b in _blocks(synthetic.counts(m, 7000))]
    assert all(not r.estimates for r in results)
    assert results[-1].spindle_stopped and est.spindle_stopped


def test_sample_level_air_gap_power(tmp_path):
    m = Machine(spindle_rpm=900.0, slip=0.03)
    settings = configs.load(tmp_path)
    est = Estimator(settings, synthetic.descriptor(), 1000)
    results = [est.process(b) for b in _blocks(synthetic.counts(m, 3000))]
    late = np.concatenate([r.p_gap_w for r in results[150:]])
    assert results[150].seq == 1500 and len(late) == 1500
    # once a revolution has measured f_e, the filter gain is divided out sample by sample
    np.testing.assert_allclose(late.mean(), m.p_in_w - m.p_cu_w, rtol=3e-3)


def test_missing_channel_is_a_config_error_naming_it(tmp_path):
    from millsense.daemon.config.errors import ConfigError

    chans = tuple(c for c in synthetic.CHANNELS if c[1] != "v_wu")
    settings = configs.load(tmp_path)
    with pytest.raises(ConfigError) as err:
        Estimator(settings, synthetic.descriptor(chans), 1000)
    assert any("v_wu" in p for p in err.value.problems)
