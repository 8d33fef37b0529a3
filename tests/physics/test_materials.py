"""ISO material groups (daemon/physics/materials.py): the conversion (M1) and what each group holds."""

from __future__ import annotations

import math
import statistics

import pytest

from millsense.daemon.physics.materials import (
    ISO_GROUPS, REFERENCE_CHIP_MM, from_kienzle, nearest_group, specific_force_n_mm2,
)
from millsense.daemon.physics.milling import SB40_TABLE2

pytestmark = pytest.mark.quick


def test_kienzle_is_d_eq9_with_k_kc11_and_p_minus_mc():
    """k_c = k_c1.1·h^(−m_c) and K_s = k·t_a^p agree at every chip: (M1)."""
    m = from_kienzle(1725.0, 0.24)
    for h in (0.02, 0.1, 0.3, 1.0):
        assert specific_force_n_mm2(m, h) == pytest.approx(1725.0 * h ** -0.24, rel=1e-12)
    assert (m.r1, m.r1_exp, m.r2, m.r2_exp) == (SB40_TABLE2.r1, SB40_TABLE2.r1_exp, SB40_TABLE2.r2, SB40_TABLE2.r2_exp)


def test_every_group_is_the_median_of_its_rows_and_its_spread_holds_them():
    assert set(ISO_GROUPS) == {"P", "M", "K", "N", "S"}
    for letter, group in ISO_GROUPS.items():
        assert group.letter == letter and group.source and group.rows
        assert group.material.ks == statistics.median(r.kc11_n_mm2 for r in group.rows)
        assert group.material.ks_exp == -statistics.median(r.mc for r in group.rows)
        low, high = group.spread_pct
        assert low <= 0.0 <= high
        mid = specific_force_n_mm2(group.material, REFERENCE_CHIP_MM)
        for row in group.rows:
            ks = row.kc11_n_mm2 * REFERENCE_CHIP_MM ** -row.mc
            assert low - 1e-9 <= 100.0 * (ks / mid - 1.0) <= high + 1e-9, (letter, row)
    # the table's order of hardness to cut, at a usual chip: N < K < P < M < S (medians)
    order = sorted(ISO_GROUPS, key=lambda g: specific_force_n_mm2(ISO_GROUPS[g].material, REFERENCE_CHIP_MM))
    assert order == ["N", "K", "P", "M", "S"]


def test_the_nearest_group_is_nearest_in_ratio():
    for letter, group in ISO_GROUPS.items():
        ks = specific_force_n_mm2(group.material, 0.08)
        assert nearest_group(ks, 0.08).letter == letter
    assert nearest_group(1e6, 0.1).letter == "S" and nearest_group(1.0, 0.1).letter == "N"
    assert math.isfinite(specific_force_n_mm2(ISO_GROUPS["P"].material, 0.1))
