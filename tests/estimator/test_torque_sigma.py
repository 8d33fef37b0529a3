"""`torque_sigma_nm` against the scatter it claims to describe.

What it is ([P] eq. 20): σ_P/ω, with σ_P the standard error of the revolution's
mean air-gap power, sqrt(var(p_gap per sample)/N) (per_revolution.py). If the
per-sample power were a constant plus white noise, the estimate − truth torque
error of steady revolutions would scatter with exactly that standard deviation.
Two things make it state more than the scatter, never less:

* ripple that a whole revolution averages out but the per-sample variance counts:
  in a cut the tooth-passing torque (a 2-flute slot with one tooth in cut cuts
  with F_t ∝ |sin θ|: relative standard deviation sqrt(1/2 − 4/π²)/(2/π) = 0.483;
  the helix smooths it, so that is an upper bound), and in any revolution the
  electrical-frequency ripple of the current sensors' offsets;
* with the anti-alias filter, neighbouring samples are correlated.

So in air (no teeth) it matches the scatter closely; in a cut it lies between
the scatter and the scatter plus the tooth ripple's share 0.483·T/√N. Checked on
steady revolutions of both gears and three seeds, per level of the truth's torque
(a step of the part), with and without the filter.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from . import simcase

SEEDS = (11, 12, 13)
RIPPLE_REL = math.sqrt(0.5 - 4.0 / math.pi**2) / (2.0 / math.pi)   # std/mean of |sin θ|
# The sample standard deviation of n ≥ 40 revolutions is itself uncertain by 1/sqrt(2(n−1)) ≈ 11 %;
# 1.5 is 4.5 of those: an honest σ is not refused by chance, a σ that is 10× off is refused.
SCATTER_FACTOR = 1.5
# Without a filter, the per-sample noise is white: only the offsets' electrical ripple inflates σ
# (seen up to ×1.5 at 600 rpm, where the motor's electrical period and the revolution do not
# divide evenly). With the 200 Hz filter the correlation of samples adds to it (up to ×2.1).
AIR_OVERSTATE = {0.0: 2.0, 200.0: 3.0}
MIN_REVS = 40


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("sigma")


def _levels(tmp, scenario, seed, filter_cutoff_hz, cutting):
    """(σ published, estimate − truth) arrays per torque level of steady revolutions."""
    cap, truth_path = simcase.capture(tmp, scenario, seed=seed, filter_cutoff_hz=filter_cutoff_hz)
    settings = simcase.settings_for(scenario, tmp, filter_cutoff_hz=filter_cutoff_hz)
    est, _ = simcase.run(cap, settings)
    pairs = [(e, t) for e, t in simcase.match(est, simcase.read_truth(truth_path), 1)
             if t["steady"] and e["valid"] and t["cutting"] == cutting]
    level = np.round([t["torque_nm"] for _, t in pairs], 1)
    out = []
    for value in np.unique(level):
        seg = [p for p, lv in zip(pairs, level, strict=True) if lv == value]
        if len(seg) >= MIN_REVS:
            out.append((
                np.array([e["torque_sigma_nm"] for e, _ in seg]),
                np.array([e["torque_nm"] - t["torque_nm"] for e, t in seg]),
                np.array([t["torque_nm"] for _, t in seg]),
                np.array([e["samples"] if "samples" in e else 60_000.0 / t["spindle_rpm"] for e, t in seg]),
            ))
    assert out, (scenario, seed, filter_cutoff_hz, cutting, len(pairs))
    return out


@pytest.mark.parametrize("filter_cutoff_hz", [0.0, 200.0], ids=["no-filter", "filter"])
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scenario", ["step", "step-1200"])
def test_sigma_matches_the_scatter_in_air(tmp, scenario, seed, filter_cutoff_hz):
    """Spindle turning, tool out of the part: σ within the scatter's own uncertainty below,
    within the electrical ripple's inflation above."""
    for sigma, err, _, _ in _levels(tmp, scenario, seed, filter_cutoff_hz, cutting=False):
        scatter = err.std(ddof=1)
        assert scatter <= SCATTER_FACTOR * sigma.mean(), (scatter, sigma.mean())
        assert sigma.mean() <= AIR_OVERSTATE[filter_cutoff_hz] * scatter, (scatter, sigma.mean())


@pytest.mark.parametrize("filter_cutoff_hz", [0.0, 200.0], ids=["no-filter", "filter"])
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scenario", ["step", "step-1200"])
def test_sigma_bounds_the_scatter_in_a_cut(tmp, scenario, seed, filter_cutoff_hz):
    """In a cut σ never understates the scatter, and overstates it by no more than the
    tooth ripple allows: σ² ≤ (air inflation · scatter)² + (0.483·T)²/N."""
    for sigma, err, torque, samples in _levels(tmp, scenario, seed, filter_cutoff_hz, cutting=True):
        scatter = err.std(ddof=1)
        assert scatter <= SCATTER_FACTOR * sigma.mean(), (scatter, sigma.mean())
        ripple = RIPPLE_REL * np.abs(torque) / np.sqrt(samples)
        ceiling = np.sqrt((AIR_OVERSTATE[filter_cutoff_hz] * scatter) ** 2 + ripple**2)
        assert np.all(sigma <= ceiling), (sigma.max(), ceiling.min(), scatter)
