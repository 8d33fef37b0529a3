"""bench/skew_tolerance.py: the skew figures docs/hardware.md quotes come from a delay that is what it says.

The bench shifts the current columns of a real simulator capture by a fraction of a
sample and runs the real estimator. Checked here: the shift lands on the currents only
and by the fraction asked (a sine of the current channel moves by exactly Δt, the
voltages not at all), and the torque error it causes behaves as δ = 2π·f_e·Δt says:
none at Δt = 0, odd in Δt, proportional to it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.quick

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench"))

import skew_tolerance as bench  # noqa: E402


@pytest.fixture(scope="module")
def stream(tmp_path_factory):
    return bench.load("step", tmp_path_factory.mktemp("skew"), seed=11)


def test_the_delay_moves_only_the_currents_by_the_fraction_asked(stream):
    rate = stream.descriptor.sample_rate_hz
    n = len(stream.counts)
    t = np.arange(n) / rate
    f = 50.0 * rate / n * round(n / rate)            # a whole number of periods in the stream: no wrap edge
    wave = np.rint(10000 * np.sin(2 * np.pi * f * t)).astype(np.int16)
    counts = np.repeat(wave[:, None], stream.counts.shape[1], axis=1)
    probe = bench.Stream(stream.descriptor, counts, stream.blocks, stream.truth)
    out = bench.skewed(probe, 250.0)                  # a quarter sample at 1 kHz
    cur = bench.current_columns(stream.descriptor)
    assert len(cur) == 3
    expected = 10000 * np.sin(2 * np.pi * f * (t + 250e-6))
    for c in range(counts.shape[1]):
        if c in cur:
            assert np.max(np.abs(out[:, c] - expected)) <= 2.0     # rounding to counts, and the int16 input's
        else:
            assert np.array_equal(out[:, c], counts[:, c])


def test_the_torque_error_is_odd_and_proportional_to_the_skew(stream, tmp_path):
    r = {s: bench.measure(stream, s, "step", tmp_path) for s in (0.0, 10.0, 20.0, -10.0)}
    assert all(x.n > 50 and x.invalid == 0 for x in r.values())
    assert abs(r[0.0].mean_pct) < 1.0                 # the estimator itself, skew-free
    e10, e20, em10 = (r[s].mean_nm - r[0.0].mean_nm for s in (10.0, 20.0, -10.0))
    assert e10 > 0.1                                  # a current read late looks in phase: more power
    assert e20 == pytest.approx(2 * e10, rel=0.05)
    assert em10 == pytest.approx(-e10, rel=0.05)
