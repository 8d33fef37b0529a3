"""Cutting coefficients per ISO material group, converted from published k_c1.1 / m_c (docs/physics.md §5a).

The handbook law is Kienzle's, ``k_c = k_c1.1·h^(−m_c)`` (N/mm², h the chip thickness in mm; for
milling the mean chip h_m). It is [D] eq. (9)'s ``K_s = k·t_a^p`` with

    k = k_c1.1,   p = −m_c,   t_a = h_m  ([D] eq. 8: the mean chip over the engagement)      (M1)

so a group's law drops into ``milling.Material`` as it is. Source of k_c1.1 and m_c: ISCAR's table
"Material groups, based on ISO 513 and VDI 3323" (ISO Materials and Grades user guide), ISCAR boring
systems catalogue 2022, p. 111 (the same table: ISCAR turning catalogue 2017, p. 558, which gives
titanium 1700 / 2110 N/mm² where 2022 gives 1160 / 1245). Each group keeps every row of the table
(``IsoGroup.rows``); its ``material`` takes the median k_c1.1 and the median m_c of the rows, and
``spread_pct`` says how far the rows' K_s at a 0.1 mm chip lie from it (low, high). k_c1.1 is for a
rake angle of 0°: a positive rake lowers it by about 1 % a degree (Sandvik Coromant's correction
1 − γ₀/100), one reason a fitted material (`millsense calibrate --material`) beats the table.

r₁ and r₂ (radial and axial over tangential, [D] eq. 9): no tool-maker's table gives them per ISO
group. Every group takes [D] Table 2's laws, measured in end milling (SB40, 4-flute HSS). Published
radial ratios K_rc/K_tc for aluminium alloys (0.16–0.60: Chinese Journal of Mechanical Engineering
34 (2021), "Milling force model for aviation aluminum alloy", Table 5) bracket [D]'s r₁ at usual
chips (0.49 to 0.34 for t_a 0.05 to 0.2 mm). r₁ enters the force alone (C_f = η·√(1 + r₁²)): r₁ from
0.16 to 0.60 moves it by −6 % to +8 % against [D]'s 0.41 at t_a = 0.1 mm; the torque not at all.

H (hardened steel, chilled cast iron): the table gives k_c1.1 (4500–4700 N/mm²) but no m_c, so
no law is given for it here.

Edge (ploughing) coefficients (edge.py): no tool-maker's table gives them either, so no group carries them.
``STEEL_EDGE_N_MM`` is a round pair for a `[material]` of steel where nothing measured is at hand, some tens
of N per mm of engaged edge, the radial above the tangential: UNVERIFIED, no published steel table of
K_te / K_re has been checked for it (Budak, Altintas & Armarego, J. Manuf. Sci. Eng. 118, 1996, once named
here, calibrate Ti6Al4V, not a steel; Altintas, *Manufacturing Automation* ch. 2, gives the model, E1's K_te·s).
docs/physics.md §5b: what it changes, and how far off the force is with none, with it, and with a pair 25 %
either way, which bounds what a wrong pair costs.
"""

from __future__ import annotations

import statistics
from typing import NamedTuple

from millsense.daemon.physics.milling import SB40_TABLE2, Material

SOURCE = ("ISCAR, Material groups based on ISO 513 and VDI 3323 (ISO Materials and Grades user guide), "
          "boring systems catalogue 2022, p. 111")
REFERENCE_CHIP_MM = 0.1   # the chip at which a group's spread is stated (a usual mean chip in end milling)
STEEL_EDGE_N_MM = (25.0, 35.0)   # (K_te, K_re), N/mm: a round pair, no verified source (module doc)


class TableRow(NamedTuple):
    number: int        # the row of the source table (1-41)
    name: str
    kc11_n_mm2: float  # k_c1.1, N/mm² at h = 1 mm
    mc: float          # m_c


class IsoGroup(NamedTuple):
    letter: str
    name: str
    material: Material                   # [D] eq. 9 laws: median k_c1.1 and m_c (M1), r₁ and r₂ of [D] Table 2
    spread_pct: tuple[float, float]      # the rows' K_s at REFERENCE_CHIP_MM against the material's, %
    rows: tuple[TableRow, ...]
    source: str = SOURCE


_ROWS = {
    "P": ("steel", (
        TableRow(1, "non-alloy steel, < 0.25 % C, annealed", 1350, 0.21),
        TableRow(2, "non-alloy steel, >= 0.25 % C, annealed", 1500, 0.22),
        TableRow(3, "non-alloy steel, < 0.55 % C, quenched and tempered", 1675, 0.24),
        TableRow(4, "non-alloy steel, >= 0.55 % C, annealed", 1700, 0.24),
        TableRow(5, "non-alloy steel, >= 0.55 % C, quenched and tempered", 1900, 0.24),
        TableRow(6, "low-alloy steel, annealed", 1775, 0.24),
        TableRow(7, "low-alloy steel, quenched and tempered, 930 N/mm²", 1675, 0.24),
        TableRow(8, "low-alloy steel, quenched and tempered, 1000 N/mm²", 1725, 0.24),
        TableRow(9, "low-alloy steel, quenched and tempered, 1200 N/mm²", 1800, 0.24),
        TableRow(10, "high-alloy and tool steel, annealed", 2450, 0.23),
        TableRow(11, "high-alloy and tool steel, quenched and tempered", 2500, 0.23),
    )),
    "M": ("stainless steel", (
        TableRow(12, "stainless, ferritic/martensitic", 1875, 0.21),
        TableRow(13, "stainless, martensitic", 1875, 0.21),
        TableRow(14, "stainless, austenitic, duplex", 2150, 0.20),
    )),
    "K": ("cast iron", (
        TableRow(15, "grey cast iron, ferritic/pearlitic", 1150, 0.20),
        TableRow(16, "grey cast iron, pearlitic/martensitic", 1350, 0.28),
        TableRow(17, "nodular cast iron, ferritic", 1225, 0.25),
        TableRow(18, "nodular cast iron, pearlitic", 1350, 0.28),
        TableRow(19, "malleable cast iron, ferritic", 1225, 0.25),
        TableRow(20, "malleable cast iron, pearlitic", 1420, 0.30),
    )),
    "N": ("non-ferrous", (
        TableRow(21, "aluminium wrought alloy, not hardenable", 700, 0.25),
        TableRow(22, "aluminium wrought alloy, hardenable", 800, 0.25),
        TableRow(23, "aluminium cast alloy, <= 12 % Si, not hardenable", 700, 0.25),
        TableRow(24, "aluminium cast alloy, <= 12 % Si, hardenable", 700, 0.25),
        TableRow(25, "aluminium cast alloy, > 12 % Si", 750, 0.25),
        TableRow(26, "copper alloy, > 1 % Pb, free cutting", 700, 0.27),
        TableRow(27, "brass", 700, 0.27),
        TableRow(28, "electrolytic copper", 700, 0.27),
    )),
    "S": ("heat-resistant superalloys and titanium", (
        TableRow(31, "Fe-based high-temperature alloy, annealed", 2600, 0.24),
        TableRow(32, "Fe-based high-temperature alloy, hardened", 3100, 0.24),
        TableRow(33, "Ni- or Co-based alloy, annealed", 3300, 0.24),
        TableRow(34, "Ni- or Co-based alloy, hardened", 3300, 0.24),
        TableRow(35, "Ni- or Co-based alloy, cast", 3300, 0.24),
        TableRow(36, "titanium, pure", 1160, 0.24),
        TableRow(37, "titanium alloy, alpha+beta, hardened", 1245, 0.24),
    )),
}


def specific_force_n_mm2(material: Material, chip_mm: float) -> float:
    """K_s = k·t_a^p ([D] eq. 9), N/mm²."""
    return material.ks * chip_mm ** material.ks_exp


def from_kienzle(kc11_n_mm2: float, mc: float, like: Material = SB40_TABLE2) -> Material:
    """(M1): k = k_c1.1, p = −m_c; r₁ and r₂ taken from `like` ([D] Table 2 unless given)."""
    return Material(float(kc11_n_mm2), -float(mc), like.r1, like.r1_exp, like.r2, like.r2_exp)


def _group(letter: str, name: str, rows: tuple[TableRow, ...]) -> IsoGroup:
    material = from_kienzle(statistics.median(r.kc11_n_mm2 for r in rows), statistics.median(r.mc for r in rows))
    mid = specific_force_n_mm2(material, REFERENCE_CHIP_MM)
    each = [specific_force_n_mm2(from_kienzle(r.kc11_n_mm2, r.mc), REFERENCE_CHIP_MM) / mid - 1.0 for r in rows]
    return IsoGroup(letter, name, material, (100.0 * min(each), 100.0 * max(each)), rows)


ISO_GROUPS: dict[str, IsoGroup] = {letter: _group(letter, name, rows) for letter, (name, rows) in _ROWS.items()}


def nearest_group(ks_n_mm2: float, chip_mm: float) -> IsoGroup:
    """The group whose K_s at `chip_mm` is nearest (in ratio) to `ks_n_mm2`: whose m_c a one-feed fit borrows."""

    def distance(group: IsoGroup) -> float:
        ratio = ks_n_mm2 / specific_force_n_mm2(group.material, chip_mm)
        return max(ratio, 1.0 / ratio)

    return min(ISO_GROUPS.values(), key=distance)
