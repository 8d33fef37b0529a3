"""A material from one test cut on the effects plant: the feed-drive depth and the force, before and after.

The numbers of docs/accuracy.md's "A material from one test cut" table. The plant cuts with every effect of
sim/cut_effects.py on (CutEffects()); the configuration before the test cut is ISO group P's law with [D]
Table 2's r₁ (physics/materials.py). `millsense calibrate --material --fit-r1` (a real subprocess, the test's
own helper) fits it from the down test cut of tests/estimator/test_calibrate_depth.py (φ16 4-flute, a_e 2 mm,
a_p 6 mm, f_z 0.1 / 0.2 / 0.3 mm). Then fig6, fig7 and fig5 on the same plant, through the real estimator with
`depth.method = "feed-drive"` and `cf = "model"`: per steady stretch (simcase.settled; one radial and axial
depth), the worst revolution's radial depth against the programmed one and against the engaged one (the
program's less the tool's mean bend, mean F_y over cut_effects.tool_stiffness_n_mm), the axial depth and the
resultant force; then the same with `depth.method = "torque-only"` and the other depth given. Last, the material
fitted without `--fit-r1` (K_s only) from a configuration that carries materials.STEEL_EDGE_N_MM, the tool's
helix configured: its feed-drive depth takes the split law (physics.md §5b, E5). Also with the
plant's own nominal law in the configuration ([D] SB40's, the law the plant's slots were fitted to: the issue's
measurement), which leaves only what the effects add.

Run: .venv/bin/python bench/calibrate_effects.py   (about a minute: the captures are the test run's, shared)
"""

from __future__ import annotations

import sys
import tempfile
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.estimator import simcase  # noqa: E402
from tests.estimator import test_calibrate_depth as case  # noqa: E402

CUTS = ("fig6", "fig7", "fig5")


def stretches(tmp: Path, name: str, material, edge=None, helix=False, **over) -> dict:
    """{(a_e, a_p): [(radial vs programmed, vs engaged, axial, force) − 1 per steady revolution]}."""
    from millsense.sim.cut_effects import tool_stiffness_n_mm
    from millsense.sim.scenarios import SCENARIOS

    effects = case._effects()
    cap, truth_path = simcase.capture(tmp, name, effects=effects)
    offset = simcase.zero_feed_current(cap, name, tmp)
    tool = SCENARIOS[name].tool
    settings = simcase.settings_for(name, tmp, cf="model", material=material, ix_offset_counts=offset,
                                    edge_n_mm=edge, tool=(tool.diameter_mm, tool.flutes, *([tool.helix_deg] if helix
                                                                                           else [])), **over)
    estimates, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    steady = simcase.settled(truth, name)
    stiffness = tool_stiffness_n_mm(SCENARIOS[name].tool, effects)
    out = defaultdict(list)
    for e, t in simcase.match(estimates, truth):
        if t["rev"] not in steady or e["depth_status"] != "ok":
            continue
        engaged = t["radial_depth_mm"] + t["force_y_n"] / stiffness
        out[(round(t["radial_depth_mm"]), t["axial_depth_mm"])].append(
            (e["radial_depth_mm"] / t["radial_depth_mm"] - 1, e["radial_depth_mm"] / engaged - 1,
             e["axial_depth_mm"] / t["axial_depth_mm"] - 1, e["force_n"] / t["force_n"] - 1))
    return out


def worst(rows, i):
    return max((r[i] for r in rows), key=abs)


def main() -> None:
    tmp = Path(tempfile.mkdtemp(prefix="calibrate-effects-"))
    table = case._table_material()
    fitted = case._calibrate(tmp, [sys.executable, "-m", "millsense.daemon"],
                             case._test_cut_capture(case._effects()), table)
    print(f"the table's law {table}\nfitted from the test cut {fitted}")
    from millsense.sim.scenarios import SCENARIOS

    m = SCENARIOS["fig6"].material
    plants = (m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp)
    from millsense.daemon.physics.materials import STEEL_EDGE_N_MM

    (tmp / "edge").mkdir()
    with_edge = case._calibrate(tmp / "edge", [sys.executable, "-m", "millsense.daemon"],
                                case._test_cut_capture(case._effects()), table, fit_r1=False, edge=STEEL_EDGE_N_MM)
    print(f"fitted from the test cut, K_s only, with the steel edge pair {STEEL_EDGE_N_MM}: {with_edge}")
    for label, material, extra in (("the plant's own law ([D] SB40: the issue's case)", plants, {}),
                                   ("law alone (ISO group P)", table, {}), ("calibrated, --fit-r1", fitted, {}),
                                   ("calibrated K_s, the steel edge pair (split law E5), the tool's helix", with_edge,
                                    {"edge": STEEL_EDGE_N_MM, "helix": True})):
        print(f"\nfeed-drive, {label}: worst revolution per stretch, % (radial vs programmed / vs engaged, "
              "axial, force)")
        for name in CUTS:
            for key, rows in sorted(stretches(tmp, name, material, method="feed-drive", **extra).items()):
                print(f"  {name} a_e {key[0]} a_p {key[1]:g} ({len(rows)}): "
                      + "  ".join(f"{100 * worst(rows, i):+.2f}" for i in range(4)))
        print(f"torque-only, {label} (fig6 radial given: axial; fig7, fig5 axial given: radial), worst %")
        for name, known, i in (("fig6", "radial", 2), ("fig7", "axial", 0), ("fig5", "axial", 0)):
            rows = [r for v in stretches(tmp, name, material, method="torque-only", known=known, **extra).values()
                    for r in v]
            print(f"  {name}: {100 * min(r[i] for r in rows):+.2f} … {100 * max(r[i] for r in rows):+.2f}")


if __name__ == "__main__":
    main()
