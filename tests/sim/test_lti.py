"""The simulated DAQ's filters (sim/lti.py) against scipy.signal's, the implementation they replace: the same
output to float rounding, whatever the order, the block sizes a stream is cut into, and a primed start."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from millsense.sim.lti import BlockFilter, butterworth_lowpass, first_order

RATE_HZ = 10_000.0


def _close(ours: np.ndarray, theirs: np.ndarray) -> float:
    return float(np.max(np.abs(ours - theirs)) / np.max(np.abs(theirs)))


@pytest.mark.parametrize("order", [1, 2, 3, 4, 7])
@pytest.mark.parametrize("cutoff_hz", [200.0, 1500.0])
def test_the_butterworth_low_pass_is_scipys_in_pieces_of_any_size(order, cutoff_hz):
    rng = np.random.default_rng(order)
    x = 40.0 + 100.0 * rng.standard_normal((5, 3001))
    sos = signal.butter(order, cutoff_hz, fs=RATE_HZ, output="sos")
    zi = signal.sosfilt_zi(sos)[:, None, :] * x[:, 0][None, :, None]
    theirs, _ = signal.sosfilt(sos, x, axis=1, zi=zi)
    ours = BlockFilter(butterworth_lowpass(order, cutoff_hz, RATE_HZ), channels=5)
    ours.prime(x[:, 0])
    cuts = [0, 1, 64, 65, 1000, 1129, 3001]   # under a block, exactly one, a block and a bit, several
    out = np.concatenate([ours(x[:, a:b]) for a, b in zip(cuts, cuts[1:])], axis=1)
    assert _close(out, theirs) < 1e-12


def test_the_gain_at_the_cut_off_is_minus_3_db():
    f = BlockFilter(butterworth_lowpass(2, 200.0, RATE_HZ), channels=1)
    t = np.arange(40_000) / RATE_HZ
    y = f(np.sin(2 * np.pi * 200.0 * t)[None, :])[0, 20_000:]
    assert abs(np.sqrt(2 * np.mean(y**2)) - 1 / np.sqrt(2)) < 1e-3


def test_the_first_order_lag_is_scipys_lfilter():
    a = 0.93
    x = np.random.default_rng(3).standard_normal(2000)
    theirs, _ = signal.lfilter([1 - a], [1, -a], x, zi=np.zeros(1))
    ours = BlockFilter(first_order(1 - a, -a), channels=1)
    out = np.concatenate([ours(x[None, :700])[0], ours(x[None, 700:])[0]])
    assert _close(out, theirs) < 1e-12


def test_an_order_below_one_is_refused():
    with pytest.raises(ValueError, match="order 0"):
        butterworth_lowpass(0, 200.0, RATE_HZ)
