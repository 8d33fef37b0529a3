"""The published resultant force against the plant's, with the engaged teeth added as vectors (issue 41).

Each case is simulated, replayed through the estimator and paired revolution by revolution with the
plant's truth (steady, cutting, valid revolutions; with a depth estimate where the case estimates one).
Error = force_n / truth force_n − 1, in %: bias, p95 of |e|, max |e|, for `cf = "auto"` (the default:
η·√(1 + r₁(t_a)²)) beside `cf = 1.075` ([P]'s constant, the default before) in the same run, and
`auto` with the helix left out of the configuration (η at ψ = 0, the upper bound). "C_f only" is the
estimate's force_n/force_tangential_n against the plant's |F|/F_T: the force model without the
torque's own error (2 % + 0.03 N·m, docs/accuracy.md), which dominates where the torque is small.

The scenarios' own plant is [D]'s average model (K_s, r₁ at each tooth's average chip, constant along its
pass); the rows marked "full plant" cut the same with the first-part programs' plant (sim/cut_effects.py:
Kienzle's law at each instantaneous chip, edge forces, runout, deflection), whose law C_f now models
(resultant.py R1a). Last, what the model leaves out, by brute-force slices: the edge forces.

    .venv/bin/python bench/force_accuracy.py
"""

from __future__ import annotations

import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.estimator import configs, simcase  # noqa: E402  (scenario -> config, shared with the tests)


def _cases():
    from millsense.sim.cut_effects import CutEffects
    from millsense.sim.machine import TOOL_D, TOOL_F
    from millsense.sim.scenarios import SCENARIOS

    s = SCENARIOS
    full = CutEffects()
    return [
        ("full plant: 2 fl slot 1200", replace(s["step-1200"], name="f-2fl", effects=full), {}),
        ("full plant: 4 fl slot 1200", replace(s["step-1200"], name="f-4fl", tool=TOOL_D, effects=full), {}),
        ("full plant: 3 fl slot 1200", replace(s["step-1200"], name="f-3fl", tool=TOOL_F, effects=full), {}),
        ("full plant: up ae 12, 4 fl", replace(s["fig6"], name="f-up", mode="up", effects=full,
                                               radial_profile=((0.0, 12.0), (150.0, 12.0)), extra_channels=()),
         {"method": "torque-only", "radial_depth_mm": 12.0}),
        ("step, 2 fl slot 600 rpm", s["step"], {}),
        ("step-1200, 2 fl slot", s["step-1200"], {}),
        ("step-1800, 2 fl slot", s["step-1800"], {}),
        ("step-1200, 4 fl slot", replace(s["step-1200"], name="b-4fl", tool=TOOL_D), {}),
        ("step-1200, 3 fl slot", replace(s["step-1200"], name="b-3fl", tool=TOOL_F), {}),
        ("step-1800, 4 fl slot", replace(s["step-1800"], name="b-4fl-1800", tool=TOOL_D), {}),
        ("fig6 as up, ae 12, 4 fl", replace(s["fig6"], name="b-up", mode="up", radial_profile=((0.0, 12.0), (150.0, 12.0)),
                                           extra_channels=()), {"method": "torque-only", "radial_depth_mm": 12.0}),
        ("fig6 down, ae 2, 4 fl", replace(s["fig6"], name="b-down", extra_channels=()),
         {"method": "torque-only", "radial_depth_mm": 2.0}),
        ("fig6 down, ae unknown", replace(s["fig6"], name="b-down-u", extra_channels=()), {"method": "off"}),
    ]


def _errors(tmp, scenario, extra, cf, helix=True, ratio=False):
    from millsense.sim import write_capture

    cap, truth_path = tmp / f"{scenario.name}.bin", tmp / f"{scenario.name}.truth"
    if not cap.exists():
        write_capture(scenario, str(cap), str(truth_path), seed=11)
    m = scenario.material
    tool = (scenario.tool.diameter_mm, scenario.tool.flutes) + ((scenario.tool.helix_deg,) if helix else ())
    kwargs = dict(tool=tool, material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp), mode=scenario.mode, cf=cf,
                  feed_mm_min=scenario.feed_segments[0][1], method="auto")
    kwargs.update(extra)
    settings = configs.load(tmp, name=f"{scenario.name}-{cf}-{helix}.toml", **kwargs)
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    def err(a, t):
        if ratio:   # C_f alone: the estimate's force over its tangential force against the plant's
            return 100.0 * (a["force_n"] / a["force_tangential_n"] / (t["force_n"] / t["force_tangential_n"]) - 1.0)
        return 100.0 * (a["force_n"] / t["force_n"] - 1.0)

    e = [err(a, t) for a, t in simcase.match(est, truth, 1)
         if t["steady"] and t["cutting"] and a["valid"] and a["force_n"] is not None
         and (extra.get("method") == "off" or a["depth_status"] in ("ok", None))]
    return np.array(e)


def _part_program(tmp: Path) -> dict:
    """The part program (three tools by number, each with its `[tools.N]` helix) through replay's path, by
    operation: config/part-program.toml as shipped (cf = 1.075) and with its cf lines removed (the default)."""
    import bisect
    import json
    import re
    import subprocess

    from millsense.sim import write_capture

    cap, truth_path = tmp / "pp.bin", tmp / "pp.truth"
    write_capture("part-program", str(cap), str(truth_path), seed=11, parts=1)
    truth = [t for t in simcase.read_truth(truth_path) if "index_end" in t]
    ends = [t["t_end_s"] for t in truth]
    shipped = (REPO / "config" / "part-program.toml").read_text()
    out = {}
    for label, text in (("1.075", shipped), ("auto", re.sub(r"(?m)^cf = .*$", "", shipped))):
        cfg = tmp / f"pp-{label}.toml"
        cfg.write_text(text)
        lines = subprocess.run([sys.executable, "-m", "millsense.daemon", "replay", "--config", str(cfg), str(cap)],
                               capture_output=True, text=True, check=True).stdout.splitlines()
        for e in (json.loads(x) for x in lines):
            if e.get("type") != "estimate" or not e["valid"] or e["force_n"] is None:
                continue
            i = bisect.bisect_left(ends, e["t"] - 0.0015)        # replay's t: seconds after the first sample
            if i >= len(ends) or abs(ends[i] - e["t"]) > 0.0015 or not (truth[i]["steady"] and truth[i]["cutting"]):
                continue
            key = (label, round(truth[i]["spindle_rpm"], -2))
            out.setdefault(key, []).append(100.0 * (e["force_n"] / truth[i]["force_n"] - 1.0))
    return {k: np.array(v) for k, v in out.items()}


def _local_law_cf(flutes: int, local: bool, fz_mm: float = 0.1, p: float = -0.42, q: float = -0.27, r1: float = 0.22,
                  points: int = 20000) -> float:
    """C_f of a straight-fluted slot by brute force: K_s and r₁ at the average chip t_a ([D] eqs. 8–9, what η
    assumes) or at each instantaneous chip h = f_z·sin φ (Kienzle's law applied locally, as the issue-41 plant's
    size effect does, its radial law scaled so that the slot's mean radial over mean tangential force is
    [D] eq. 9's r₁(t_a), as the plant's is fitted); SS41's exponents by default."""
    theta = (np.arange(points) + 0.5) * (2.0 * np.pi / points)
    t_a = 2.0 * fz_mm / np.pi
    parts = []
    for k in range(flutes):
        phi = np.mod(theta + 2.0 * np.pi * k / flutes, 2.0 * np.pi)
        h = np.where(phi <= np.pi, fz_mm * np.sin(phi), 0.0)
        chip = np.maximum(h, 1e-6) if local else t_a
        parts.append((phi, chip**p * h, r1 * chip**q))
    scale = t_a**q * r1 * sum(d.sum() for _, d, _ in parts) / sum((d * r).sum() for _, d, r in parts)
    force = sum(d * (1.0 + 1j * scale * r) * np.exp(-1j * phi) for phi, d, r in parts)
    tangential = sum(d for _, d, _ in parts)
    return float(np.abs(force).mean() / tangential.mean())


def _row(e) -> str:
    if e.size == 0:
        return f"{'-':>5} {'null':>21}"
    a = np.abs(e)
    return f"{e.size:5d} {np.mean(e):+6.2f} {np.percentile(a, 95):6.2f} {np.max(a):6.2f}"


def main() -> int:
    print("resultant force against the plant, % (n, bias, p95 |e|, max |e|), seed 11")
    print(f"{'case':<26} {'cf = auto':>27}   {'cf = 1.075':>27}   {'auto, helix unknown':>27}   "
          f"{'C_f only, auto':>27}")
    worst = 0.0
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        for label, scenario, extra in _cases():
            auto = _errors(tmp, scenario, extra, "auto")
            const = _errors(tmp, scenario, extra, 1.075)
            no_helix = _errors(tmp, scenario, extra, "auto", helix=False)
            cf_only = _errors(tmp, scenario, extra, "auto", ratio=True)
            if extra.get("method") != "off" and cf_only.size:
                worst = max(worst, float(np.max(np.abs(cf_only))))
            print(f"{label:<26} {_row(auto)}   {_row(const)}   {_row(no_helix)}   {_row(cf_only)}")
        print("part program 1001, one part, replay (T11 phi20 2 fl 1500 rpm, T4 phi16 4 fl 1200 rpm, "
              "T27 phi8 3 fl 2000 rpm; slots, depth steps)")
        pp = _part_program(tmp)
        for rpm, tool in ((1500, "T11"), (1200, "T4"), (2000, "T27")):
            print(f"  {f'{tool} {rpm} rpm':<24} {_row(pp.get(('auto', rpm), np.array([])))}   "
                  f"{_row(pp.get(('1.075', rpm), np.array([])))}")
    print(f"worst |e| of C_f with cf = auto where the engagement is known: {worst:.2f} %")
    print("C_f of a straight slot by brute-force slices, SS41: the law at each tooth's average chip ([D]'s, what "
          "η took before), at each instantaneous chip (Kienzle: what η takes now, resultant.py R1a), and the "
          "first-part plant's chip law plus its edge forces (K_te 20, K_re 30 N/mm), against η·√(1 + r₁²) now")
    from millsense.daemon.physics.force import engaged_cf
    from millsense.daemon.physics.milling import Material
    from millsense.sim.machine import MATERIALS

    m = MATERIALS["SS41"]
    material = Material(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp)
    for fz in (0.05, 0.1):
        for flutes in (2, 3, 4):
            at_mean, at_h = _local_law_cf(flutes, False, fz_mm=fz), _local_law_cf(flutes, True, fz_mm=fz)
            edges = _edge_plant_cf(flutes, fz)
            model = float(engaged_cf("slot", flutes, 8.0, None, fz, 16.0, None, material, None))
            print(f"  f_z {fz:.2f}, {flutes} flutes: average chip {at_mean:.4f}, instantaneous {at_h:.4f}, "
                  f"+ edges {edges:.4f}; model {model:.4f}: {100 * (model / at_h - 1):+.2f} % of the local law, "
                  f"{100 * (model / edges - 1):+.2f} % with the edges (before: {100 * (at_mean / edges - 1):+.2f} %)")
    return 0 if math.isfinite(worst) else 1


def _edge_plant_cf(flutes: int, fz_mm: float, points: int = 20000) -> float:
    """C_f of a straight slot with the first-part plant's chip law (fitted with its edge forces,
    sim/cut_effects.calibration) and its edge forces: what the daemon cannot know."""
    from millsense.sim.cut_effects import CutEffects, calibration
    from millsense.sim.machine import MATERIALS

    mat, eff = MATERIALS["SS41"], CutEffects()
    law = calibration(mat, eff)
    theta = (np.arange(points) + 0.5) * (2.0 * np.pi / points)
    force, tangential = np.zeros(points, complex), np.zeros(points)
    for k in range(flutes):
        phi = np.mod(theta + 2.0 * np.pi * k / flutes, 2.0 * np.pi)
        h = np.where(phi <= np.pi, fz_mm * np.sin(phi), 0.0)
        h_c = np.maximum(h, eff.min_chip_mm)
        d_t = law.c_t * mat.ks * h_c**law.q_t * h
        d_r = law.c_r * mat.r1 * h_c**law.q_r * d_t
        cutting = h > 0
        d_t = d_t + np.where(cutting, eff.edge_tangential_n_mm, 0.0)
        d_r = d_r + np.where(cutting, eff.edge_radial_n_mm, 0.0)
        force += (d_t + 1j * d_r) * np.exp(-1j * phi)
        tangential += d_t
    return float(np.abs(force).mean() / tangential.mean())


if __name__ == "__main__":
    raise SystemExit(main())
