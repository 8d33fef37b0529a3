"""DAQ front end: quantisation, saturation, noise behind (and without) the anti-alias filter, offsets."""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.sim import Plant, channel_scales
from millsense.sim.sensors import quantise

from .helpers import SCALES, physical

pytestmark = pytest.mark.quick


def test_scales_are_the_datasheet():
    """channel_scales() is the table of docs/architecture.md."""
    table = channel_scales()
    for name, scale in SCALES.items():
        assert table[name]["scale"] == scale
        assert table[name]["offset"] == 0
    assert table["sp_enc"]["counts_per_rev"] == 4096
    assert table["ix_feed"]["kind"] == "feed_current"


def test_quantise_rounds_and_saturates():
    x = np.array([0.0, 0.0009, 0.0011, -0.0011, 65.534, 65.5360, 1e6, -65.536, -65.538, -1e6])
    np.testing.assert_array_equal(quantise(x, 0.002), [0, 0, 1, -1, 32767, 32767, 32767, -32768, -32768, -32768])
    assert quantise(x, 0.002).dtype == np.int16


def test_crash_currents_saturate_at_the_rails_without_wrapping():
    plant = Plant("crash", noise_scale=0.0)
    counts = plant.step(round(plant.duration_s * 1000)).astype(int)
    i_u = counts[:, plant.descriptor.names.index("i_u")]
    assert (i_u == 32767).any() and (i_u == -32768).any()
    # a wrapped int16 would jump by ~65536 between neighbouring samples
    assert np.abs(np.diff(i_u)).max() < 40_000


def _noise(cutoff, seed=4):
    a = Plant("aircut-high", seed=seed, filter_cutoff_hz=cutoff)
    b = Plant("aircut-high", seed=seed, filter_cutoff_hz=cutoff, noise_scale=0.0)
    xa, xb = physical(a, a.step(3000)), physical(b, b.step(3000))
    return {k: xa[k] - xb[k] for k in ("i_u", "i_v", "i_w", "v_uv")}


def test_noise_is_filtered_or_aliases():
    """White hall noise of σ = 0.05 A: behind the 200 Hz filter σ·sqrt(ENBW/(fs_int/2)) with
    ENBW = fc·(π/4)/sin(π/4) for a 2nd-order Butterworth; without a filter, all of it aliases."""
    enbw = 200 * (math.pi / 4) / math.sin(math.pi / 4)
    filtered = _noise(200.0)["i_u"]
    raw = _noise(0.0)["i_u"]
    assert np.std(filtered) == pytest.approx(0.05 * math.sqrt(enbw / 5000), rel=0.12)
    assert np.std(raw) == pytest.approx(0.05, rel=0.08)


def test_offsets_bounded_and_fixed_per_seed():
    offs = []
    for seed in (1, 2):
        d = _noise(0.0, seed)
        offs.append(np.array([d[k].mean() for k in ("i_u", "i_v", "i_w")]))
        assert np.all(np.abs(offs[-1]) <= 0.05 + 0.004)  # ±0.05 A, plus the mean of 3000 noise samples
    assert not np.allclose(offs[0], offs[1], atol=0.002)
    again = _noise(0.0, 1)
    np.testing.assert_allclose([again[k].mean() for k in ("i_u", "i_v", "i_w")], offs[0])
