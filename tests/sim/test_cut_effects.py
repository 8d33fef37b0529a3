"""The plant's cutting effects (sim/cut_effects.py): each one shown by a property the plant must have.

The average law is written out here from [D] eqs. (8)-(9), not imported from the daemon or the plant.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from millsense.sim.cut_effects import NONE, CutEffects, material_batch, tool_stiffness_n_mm
from millsense.sim.cutting import CutGeometry, cutting_forces, tooth_chip_factors
from millsense.sim.machine import MATERIALS, Tool

pytestmark = pytest.mark.quick

SS41 = MATERIALS["SS41"]
STRAIGHT_1 = Tool(20.0, 1, 1e-4)  # one tooth, no helix: each instant is one chip
STRAIGHT_2 = Tool(20.0, 2, 1e-4)
EDGES = {"edge_tangential_n_mm": CutEffects().edge_tangential_n_mm, "edge_radial_n_mm": CutEffects().edge_radial_n_mm}


def _geom(tool, effects, mode="slot", depth_mm=3.0, radial_mm=None, material=SS41):
    radial = tool.diameter_mm if radial_mm is None else radial_mm
    return CutGeometry(tool, material, mode, np.array([-1000.0, 1000.0]), np.array([depth_mm, depth_mm]),
                       np.array([-1000.0, 1000.0]), np.array([radial, radial]), depth_mm, effects)


def _rev(geom, fz_mm, n=7200):
    theta = (np.arange(n) + 0.5) * 2 * math.pi / n
    f = cutting_forces(geom, theta, np.zeros(n), np.full(n, fz_mm), tooth_chip_factors(geom.tool.flutes))
    return {k: v.mean() for k, v in f.items()}, f, theta


def _law_slot_ft_n(fz_mm, depth_mm, material=SS41):
    """[D] eqs. (8)-(9), one tooth over [0, π]: mean F_t = K_s(t_a)·f_z·a/π, t_a = 2f_z/π."""
    t_a = 2 * fz_mm / math.pi
    return material.ks * t_a**material.ks_exp * fz_mm * depth_mm / math.pi


def test_with_every_effect_off_the_element_model_is_the_average_model():
    for tool, mode, radial in ((Tool(20.0, 2, 30.0), "slot", None), (Tool(16.0, 4, 30.0), "down", 4.0)):
        plain, _, _ = _rev(_geom(tool, None, mode, 3.0, radial), 0.08)
        off, _, _ = _rev(_geom(tool, NONE, mode, 3.0, radial), 0.08)
        for key in ("ft_n", "fx_n", "fy_n", "fz_n"):
            assert off[key] == pytest.approx(plain[key], rel=1e-9, abs=1e-9), (mode, key)


def test_the_chip_law_is_fitted_so_that_the_handbook_holds_at_the_reference_slots():
    """Edge forces and the size effect at h, yet a slot at either reference feed takes the law's mean force."""
    effects = replace(CutEffects(), runout_um=0.0)
    for fz in effects.reference_fz_mm:
        mean, _, _ = _rev(_geom(STRAIGHT_1, effects), fz)
        assert mean["ft_n"] == pytest.approx(_law_slot_ft_n(fz, 3.0), rel=2e-3)


def test_size_effect_the_specific_force_rises_where_the_instantaneous_chip_is_thin():
    """Along one tooth's pass the chip is f_z·sin φ: with the size effect at h, F_t/h is larger near entry
    (thin chip) than at φ = π/2 (the full chip); at the average chip it would be one constant."""
    effects = replace(NONE, size_effect=True)
    _, f, theta = _rev(_geom(STRAIGHT_1, effects), 0.1)
    h = 0.1 * np.sin(theta)
    thin = (theta > 0.15) & (theta < 0.25)  # h ≈ 0.02 mm
    full = np.abs(theta - math.pi / 2) < 0.05  # h ≈ 0.1 mm
    k_thin = np.mean(f["ft_n"][thin] / h[thin])
    k_full = np.mean(f["ft_n"][full] / h[full])
    # Kienzle at h: (0.02/0.1)^(−m_c), m_c of the fitted chip term, well above a few %
    assert k_thin > 1.3 * k_full


def test_size_effect_the_specific_energy_rises_as_the_feed_falls():
    effects = replace(NONE, size_effect=True)
    energy = [_rev(_geom(STRAIGHT_2, effects), fz)[0]["ft_n"] / fz for fz in (0.02, 0.05, 0.1, 0.2)]
    assert all(a > b for a, b in zip(energy, energy[1:], strict=False))


def test_edge_force_the_torque_tends_to_the_edge_term_not_zero_as_the_feed_vanishes():
    """At f_z → 0 the chip term goes but each engaged edge still rubs: mean F_t → N·K_te·a·(engaged share)."""
    effects = replace(NONE, size_effect=True, **EDGES)  # Kienzle held at h_min: the chip term vanishes with h
    depth = 3.0
    mean, _, _ = _rev(_geom(STRAIGHT_2, effects, depth_mm=depth), 1e-5)
    edge_n = 2 * effects.edge_tangential_n_mm * depth * 0.5  # two teeth, each engaged half the revolution
    assert mean["ft_n"] == pytest.approx(edge_n, rel=0.02)
    # and the radial edge force pushes the part away: the in-plane resultant is at least the tangential one
    _, f, _ = _rev(_geom(STRAIGHT_2, effects, depth_mm=depth), 1e-5)
    assert np.mean(np.hypot(f["fx_n"], f["fy_n"])) > 1.5 * mean["ft_n"]


def test_runout_one_tooth_peaks_above_the_other():
    """Tooth 0 stands ρ out: it takes a chip ρ thicker and the tooth after it one ρ thinner, so the two
    teeth's force peaks in a revolution differ (a sound, true tool: equal)."""
    effects = replace(NONE, runout_um=10.0)
    _, f, theta = _rev(_geom(STRAIGHT_2, effects), 0.1)
    first = f["ft_n"][theta < math.pi].max()  # tooth 0 cuts over φ = θ in [0, π]
    second = f["ft_n"][theta >= math.pi].max()  # tooth 1 (θ + π)
    assert first / second - 1 > 0.8 * 2 * 0.010 / 0.1  # chips 0.11 and 0.09 mm at the peak
    _, g, _ = _rev(_geom(STRAIGHT_2, NONE), 0.1)
    assert g["ft_n"][theta < math.pi].max() == pytest.approx(g["ft_n"][theta >= math.pi].max(), rel=1e-9)


def test_deflection_the_engaged_depth_falls_as_the_force_rises():
    """In side milling the tool bends by F_n/k: down milling pushes it off the wall, so the harder it
    cuts the more of the programmed radial depth it loses; up milling pulls it into the wall (it cuts
    more); a slot (the tool cuts both walls) neither."""
    tool = Tool(8.0, 3, 35.0)  # a slender cutter: about 10 kN/mm
    stiff = tool_stiffness_n_mm(tool, CutEffects())
    assert 5_000 < stiff < 20_000  # 3·E·I/L³ for φ8 carbide at 3·D stick-out
    rigid = replace(NONE, size_effect=True)  # the coefficient at h: the force follows the engaged chip alone
    bent = replace(rigid, deflection=True)
    losses = []
    for fz in (0.03, 0.06, 0.12):
        straight, _, _ = _rev(_geom(tool, rigid, "down", 8.0, 2.0), fz, n=3600)
        mean, f, _ = _rev(_geom(tool, bent, "down", 8.0, 2.0), fz, n=3600)
        losses.append((f["deflection_mm"].mean(), 1 - mean["ft_n"] / straight["ft_n"]))
        up_straight, _, _ = _rev(_geom(tool, rigid, "up", 8.0, 2.0), fz, n=3600)
        up, g, _ = _rev(_geom(tool, bent, "up", 8.0, 2.0), fz, n=3600)
        assert g["deflection_mm"].mean() < 0 and up["ft_n"] > up_straight["ft_n"], fz
    assert 0 < losses[0][0] < losses[1][0] < losses[2][0]  # off the wall, more as the force rises
    assert 0 < losses[0][1] < losses[1][1] < losses[2][1]  # and the cut loses more of its depth
    assert losses[2][0] == pytest.approx(losses[2][1] * 2.0, rel=0.5)  # about (lost share)·ae: F_t ~ engaged ae
    slot_straight, _, _ = _rev(_geom(tool, rigid), 0.06, n=3600)
    slot_bent, _, _ = _rev(_geom(tool, bent), 0.06, n=3600)
    assert slot_bent["ft_n"] == pytest.approx(slot_straight["ft_n"], rel=1e-12)


def test_wear_a_tool_at_80_percent_of_its_life_cuts_with_a_few_percent_more_force():
    sharp = replace(NONE, **EDGES)
    torque = [_rev(_geom(Tool(20.0, 2, 30.0), replace(sharp, life_used=life)), 0.1, n=3600)[0]["ft_n"]
              for life in (0.0, 0.4, 0.8)]
    assert torque[0] < torque[1] < torque[2]
    assert 1.01 < torque[2] / torque[0] < 1.15


def test_a_material_batch_scales_every_force_with_it():
    """A batch 20 % harder: K_s and the edge forces × 1.2, so (no deflection) every force × 1.2 exactly."""
    effects = replace(CutEffects(), deflection=False)
    material, harder = material_batch(SS41, effects, 20.0)
    base, _, _ = _rev(_geom(Tool(16.0, 4, 30.0), effects, "down", 5.0, 3.0), 0.07, n=3600)
    batch, _, _ = _rev(_geom(Tool(16.0, 4, 30.0), harder, "down", 5.0, 3.0, material), 0.07, n=3600)
    for key in ("ft_n", "fx_n", "fy_n"):
        assert batch[key] / base[key] == pytest.approx(1.2, rel=1e-9)
    with pytest.raises(ValueError, match="material offset"):
        material_batch(SS41, effects, -95.0)
