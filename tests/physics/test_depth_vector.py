"""`depth_from_torque_many`: the torque-only depths of a block of revolutions at once give what
`depth_from_torque` gives one revolution at a time (issue 13: replay's per-revolution loop)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from millsense.daemon.physics.depth import (
    AIR_CUT,
    NO_SECOND_FORCE,
    OK,
    OUT_OF_RANGE,
    depth_from_torque,
    depth_from_torque_many,
)
from millsense.daemon.physics.milling import SB40_TABLE2

pytestmark = pytest.mark.quick

M = SB40_TABLE2
RADIUS_MM, FLUTES = 8.0, 4


def _columns(seed: int, count: int = 300) -> tuple[np.ndarray, np.ndarray]:
    """Torques from below zero to well past any cut, feeds per tooth including 0, negative and nan."""
    rng = np.random.default_rng(seed)
    torque = rng.uniform(-2.0, 60.0, count)
    torque[::17] = 0.0
    torque[5::23] = np.nan
    t_c = rng.uniform(0.005, 0.5, count)
    t_c[3::19] = 0.0
    t_c[7::29] = -0.1
    t_c[11::31] = np.nan
    return torque, t_c


def _one_by_one(torque, t_c, **kw):
    radial, axial, status = [], [], []
    for tq, tc in zip(torque.tolist(), t_c.tolist()):
        d = depth_from_torque(tq, tc, RADIUS_MM, FLUTES, M, **kw)
        radial.append(math.nan if d.radial_depth_mm is None else d.radial_depth_mm)
        axial.append(math.nan if d.axial_depth_mm is None else d.axial_depth_mm)
        status.append(d.status)
    return np.array(radial), np.array(axial), status


@pytest.mark.parametrize("kw", [
    {"mode": "slot"},
    {"mode": "down", "known_radial_mm": 3.0},
    {"mode": "up", "known_radial_mm": 16.0},
    {"mode": "down", "known_axial_mm": 4.0},           # a root per revolution, one by one
    {"mode": "up", "known_axial_mm": 2.0},
    {"mode": "down"},                                  # neither known
    {"mode": "slot", "min_torque_nm": 5.0},
])
@pytest.mark.parametrize("seed", [1, 2])
def test_many_equals_one_by_one(kw, seed):
    torque, t_c = _columns(seed)
    want_r, want_a, want_s = _one_by_one(torque, t_c, **kw)
    got_r, got_a, got_s = depth_from_torque_many(torque, t_c, RADIUS_MM, FLUTES, M, **kw)
    assert got_s == want_s
    np.testing.assert_allclose(got_r, want_r, rtol=1e-12, equal_nan=True)
    np.testing.assert_allclose(got_a, want_a, rtol=1e-12, equal_nan=True)
    # the statuses of interest all occur (the columns above are meant to reach them)
    assert {AIR_CUT} <= set(got_s)
    closed_form = "known_radial_mm" in kw or (kw["mode"] == "slot" and "known_axial_mm" not in kw)
    if closed_form:
        assert {OK, OUT_OF_RANGE} <= set(got_s)
    if kw == {"mode": "down"}:
        assert NO_SECOND_FORCE in got_s


def test_no_revolutions():
    r, a, s = depth_from_torque_many(np.empty(0), np.empty(0), RADIUS_MM, FLUTES, M, "slot")
    assert (len(r), len(a), s) == (0, 0, [])


@pytest.mark.parametrize("kw", [
    {"mode": "down", "known_radial_mm": 17.0},               # wider than the tool
    {"mode": "down", "known_radial_mm": 3.0, "known_axial_mm": 2.0},
    {"mode": "sideways", "known_radial_mm": 3.0},
])
def test_refusals_raise_like_the_scalar_form(kw):
    torque, t_c = np.array([5.0, 6.0]), np.array([0.1, 0.1])
    with pytest.raises(ValueError):
        depth_from_torque(5.0, 0.1, RADIUS_MM, FLUTES, M, **kw)
    with pytest.raises(ValueError):
        depth_from_torque_many(torque, t_c, RADIUS_MM, FLUTES, M, **kw)


@pytest.mark.parametrize("mode", ["down", "up", "slot"])
def test_unit_forces_on_floats_equal_the_numpy_model(mode):
    """`_unit_forces` (eq. 7 on the math kernels, one per solve) against `average_forces_n` on arrays."""
    from millsense.daemon.physics.depth import _unit_forces
    from millsense.daemon.physics.milling import average_forces_n

    r_r = np.array([1e-2, 0.05, 0.3, 1.0, 1.7, 2.0 - 1e-9, 2.0, 0.0, 2.5, -1.0])
    t_c = np.array([0.01, 0.1, 0.7, 0.2, 0.05, 0.3, 0.15, 0.1, 0.1, 0.1])
    want = average_forces_n(r_r, 1.0, t_c, RADIUS_MM, FLUTES, M, mode)
    for i, (r, t) in enumerate(zip(r_r.tolist(), t_c.tolist())):
        got = _unit_forces(r, t, RADIUS_MM, FLUTES, M, mode)
        expect = (want.tangential_n[i], want.x_n[i], want.y_n[i])
        np.testing.assert_allclose(got, expect, rtol=1e-12, atol=1e-9, equal_nan=True)
    assert all(math.isnan(v) for v in _unit_forces(0.5, 0.0, RADIUS_MM, FLUTES, M, mode))   # no chip
