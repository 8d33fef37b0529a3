"""The demo's alarm limits against the step cut it plays, computed here from the papers' model.

The step scenario ([P] Table 3, physics.md §6): slot, 600 rpm, 200 mm/min,
axial depth 1 → 2 → 3 mm. Mean cutting torque of a slot ([D] eqs. 7–9, tan β
cancels): T_c = K_s(t_a) · a_p · a_e · v_f / ω with t_a = 2·t_c/π (slot) and
K_s = ks · t_a^ks_exp; |F| = C_f · T_c / R ([P] eq. 18). The demo should warn
on the 3 mm step only and never overload on the plain step cut.
"""

from __future__ import annotations

import math

import pytest

from millsense.daemon.config.load import demo_config

pytestmark = pytest.mark.quick

SPINDLE_RPM = 600.0
DEPTHS_MM = (1.0, 2.0, 3.0)


def step_cut():
    s = demo_config()
    omega_rad_s = SPINDLE_RPM * 2 * math.pi / 60
    feed_per_tooth_mm = s.cut.feed_mm_min / (SPINDLE_RPM * s.tool.flutes)
    t_a_mm = 2 * feed_per_tooth_mm / math.pi  # [D] eq. 8, slot
    ks_n_mm2 = s.material.ks * t_a_mm ** s.material.ks_exp  # [D] eq. 9
    out = []
    for a_p in DEPTHS_MM:
        removal_mm3_s = a_p * s.tool.diameter_mm * s.cut.feed_mm_min / 60
        torque_nm = ks_n_mm2 * removal_mm3_s / 1000 / omega_rad_s  # N·mm/s → W, / ω
        force_n = s.tool.cf * torque_nm / (s.tool.diameter_mm / 2000)
        out.append((torque_nm, force_n))
    return s, out


def test_the_warning_falls_between_the_2_and_3_mm_steps_with_hysteresis_room():
    s, cut = step_cut()
    (t1, f1), (t2, f2), (t3, f3) = cut
    assert 1.9 < t1 < 2.1  # sanity of the model: about 2 N·m per mm of depth here
    a = s.alarms
    keep = 1 - a.hysteresis_pct / 100
    assert t2 < a.torque_warn_nm * keep and a.torque_warn_nm < t3 < a.torque_limit_nm
    assert f2 < a.force_warn_n * keep and a.force_warn_n < f3 < a.force_limit_n


def test_no_power_trip_on_the_plain_step_cut():
    s, cut = step_cut()
    omega_rad_s = SPINDLE_RPM * 2 * math.pi / 60
    low = s.gears[0]
    p_gap_w = (cut[-1][0] + low.friction_torque_nm + low.viscous_nms * omega_rad_s) * omega_rad_s  # [P] eq. 13
    assert p_gap_w < s.alarms.power_limit_w < s.alarms.crash_power_w
