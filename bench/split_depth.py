"""Would the feed-drive depth hold on the effects plant if it were solved with the split law? (issue 41)

The `feed-drive` depth solves [D] eq. 12, f_xt = F_x/F_t = (a + r₁b)/c, for the radial immersion: [D]'s
average law, one r₁ at the mean chip over the whole arc, the forces ∝ sin φ. physics/edge.py already holds
another description of the same material for the force: the law split into a chip term at the instantaneous
chip with its own exponents (E1, E4) and an edge term even over the arc. This script asks, offline, what
radial depth each description reads from the plant's *true* mean forces (the truth file's F_x and F_t of each
steady revolution, so no sensor or estimator error enters): f_xt of the description solved for R_r by
bracketing and Brent, against the programmed radial depth. Plants: sim/cut_effects.py with every effect on,
and the same without the tool's deflection (which changes the engaged depth itself). The material: the
plant's nominal law ([D] SB40), with no edge term (the law at the instantaneous chip only) and with edge
pairs 15/22.5, 20/30 (the plant's) and 25/35 N/mm (STEEL_EDGE_N_MM).

The daemon's feed-drive depth takes (E5) from edge.split_fxt where the material has edge coefficients
(physics.md §5b); this is the offline check of it against the plant's true forces (docs/accuracy.md).
Run: .venv/bin/python bench/split_depth.py   (about a minute; the captures are the tests' shared ones)
"""

from __future__ import annotations

import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from millsense.daemon.physics import edge  # noqa: E402
from millsense.daemon.physics.depth import bracketed_root  # noqa: E402
from millsense.daemon.physics.milling import Material, engagement_angles_rad, force_ratio_fxt  # noqa: E402
from tests.estimator import simcase  # noqa: E402

NODES = 4001   # the arc's quadrature points (the split's f_xt to well under 0.1 %)


def fxt_split(radial_ratio: float, fz: float, material: Material) -> float:
    """F_x/F_t of the split law over a down-milling arc: chip ∝ sin^(1+p_c) φ (radial sin^(1+p_c+q_c) φ),
    each scaled to its mean of E1, plus the edge's K_te, K_re even over the arc (edge.py E1, E4)."""
    entry, exit_ = (float(v) for v in engagement_angles_rad(radial_ratio, "down"))
    parts = edge.split(entry, exit_, fz, material)
    if parts is None:
        return math.nan
    phi = np.linspace(entry, exit_, NODES)[1:-1]
    w_t = np.sin(phi) ** (1.0 + parts.size_exp)
    w_r = np.sin(phi) ** (1.0 + parts.size_exp + parts.r1_exp)
    span = (exit_ - entry) / (2.0 * math.pi)
    f_t = parts.chip_t / span * w_t / w_t.mean() + parts.edge_t / span
    f_r = parts.chip_r / span * w_r / w_r.mean() + parts.edge_r / span
    return float((f_t * np.cos(phi) + f_r * np.sin(phi)).mean() / f_t.mean())   # [D] eqs. 2-4's x


def fxt_d(radial_ratio: float, fz: float, material: Material) -> float:
    return float(force_ratio_fxt(radial_ratio, fz, material, "down"))              # [D] eq. 12


def solve(f, target: float, fz: float, material: Material) -> float:
    """The R_r in 0.05-1.5 where f = target (the first bracket on a grid; down milling's f_xt rises)."""
    grid = np.linspace(0.05, 1.5, 59)
    values = [f(r, fz, material) - target for r in grid]
    for a, b, va, vb in zip(grid, grid[1:], values, values[1:]):
        if va * vb <= 0.0:
            return bracketed_root(lambda r: f(r, fz, material) - target, float(a), float(b))
    return math.nan


def main() -> None:
    from millsense.sim.cut_effects import CutEffects
    from millsense.sim.scenarios import SCENARIOS

    tmp = Path(tempfile.mkdtemp(prefix="split-depth-"))
    m = SCENARIOS["fig6"].material
    law = Material(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp)
    described = {"[D] eq. 12": (fxt_d, law), "law at h, no edge": (fxt_split, law)}
    for pair in ((15.0, 22.5), (20.0, 30.0), (25.0, 35.0)):
        described[f"split {pair[0]:g}/{pair[1]:g}"] = (fxt_split, law._replace(edge_t_n_mm=pair[0],
                                                                                edge_r_n_mm=pair[1]))
    print("radial depth read from the plant's true F_x/F_t, % off the programmed one (median over each steady "
          "stretch)\n" + "cut | " + " | ".join(described))
    for label, effects in (("all effects but deflection", replace(CutEffects(), deflection=False)),
                           ("every effect", CutEffects())):
        print(f"-- {label}")
        for name in ("fig6", "fig7", "fig5"):
            _, truth_path = simcase.capture(tmp, name, effects=effects)
            truth = simcase.read_truth(truth_path)
            steady = simcase.settled(truth, name)
            radius_mm = SCENARIOS[name].tool.radius_mm
            stretches: dict = {}   # fig5 and fig7 ramp the radial depth: stretches to the nearest mm
            for t in truth[::2]:   # every other revolution: the medians are the same, the run half as long
                if t["rev"] not in steady:
                    continue
                target = t["force_x_n"] / t["force_tangential_n"]
                fz = t["feed_per_tooth_mm"]
                cells = [solve(f, target, fz, mat) * radius_mm / t["radial_depth_mm"] - 1.0
                         for f, mat in described.values()]
                key = (round(t["radial_depth_mm"]), t["axial_depth_mm"], round(fz, 3))
                stretches.setdefault(key, []).append(cells)
            for (ae, ap, fz), rows in sorted(stretches.items()):
                cells = np.nanmedian(np.array(rows), axis=0)
                print(f"{name} a_e {ae:g} a_p {ap:g} f_z {fz:.3f} ({len(rows)}) | "
                      + " | ".join(f"{100 * c:+.1f}" for c in cells))


if __name__ == "__main__":
    main()
