"""Estimator accuracy against the simulator's truth: scenario x quantity, mean / p95 / max error.

Each scenario is simulated with sensor noise (seed fixed), written as a capture,
decoded by the real `StreamDecoder` and run through the `Estimator`; every
estimate is paired with the truth revolution that ends on the same sample.
Torque and force are compared on steady revolutions (truth `steady`), depths on
settled revolutions of a cut (tests/estimator/simcase.py `settled`: away from
entry, exit and steps). Errors: torque in N·m, the rest in % of the truth.

    .venv/bin/python bench/accuracy.py [--seed 11]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.estimator import simcase  # noqa: E402

# (scenario, label, settings options, capture filter (None = scenario's))
CASES = (
    ("step", "600 rpm slot, 200 Hz filter", {}, None),
    ("step", "600 rpm slot, no filter", {"filter_cutoff_hz": 0.0}, 0.0),
    ("step", "600 rpm slot, speed channel only", {"encoder": False}, None),
    ("step", "600 rpm slot, C_f from r1(t_a)", {"cf": "model"}, None),
    ("step-1200", "1200 rpm slot (high gear)", {}, None),
    ("step-1200", "1200 rpm slot, no filter", {"filter_cutoff_hz": 0.0}, 0.0),
    ("step-1800", "1800 rpm slot", {}, None),
    ("diagonal-step", "diagonal slot 45 deg", {}, None),
    ("fig5", "[D] fig5 feed-drive", {"method": "feed-drive"}, None),
    ("fig6", "[D] fig6 feed-drive", {"method": "feed-drive"}, None),
    ("fig7", "[D] fig7 feed-drive", {"method": "feed-drive"}, None),
    ("fig5", "[D] fig5 dynamometer", {"method": "dynamometer"}, None),
    ("fig7", "[D] fig7 torque-only, d_a known", {"method": "torque-only", "known": "axial"}, None),
    ("fig6", "[D] fig6 torque-only, d_r known", {"method": "torque-only", "known": "radial"}, None),
)


def _stats(err: np.ndarray) -> tuple[float, float, float]:
    a = np.abs(err)
    return float(err.mean()), float(np.percentile(a, 95)), float(a.max())


def evaluate(scenario, opts, fc, seed, tmp):
    cap, truth_path = simcase.capture(tmp, scenario, seed=seed, filter_cutoff_hz=fc)
    opts = dict(opts)
    if opts.get("method") == "feed-drive":
        opts["ix_offset_counts"] = simcase.zero_feed_current(cap, scenario, tmp)
    settings = simcase.settings_for(scenario, tmp, **opts)
    est, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    pairs = simcase.match(est, truth, 1 if opts.get("encoder", True) else 200)
    rows = []
    steady = [(e, t) for e, t in pairs if t["steady"] and e["valid"]]
    if steady:
        err = np.array([e["torque_nm"] - t["torque_nm"] for e, t in steady])
        rows.append(("torque_nm [N.m]", len(err), *_stats(err)))
        cut = [(e, t) for e, t in steady if t["cutting"] and t["torque_nm"] > 0.5]
        if cut:
            rel = np.array([(e["torque_nm"] - t["torque_nm"]) / t["torque_nm"] * 100 for e, t in cut])
            rows.append(("torque_nm [%] cutting", len(rel), *_stats(rel)))
            rel = np.array([(e["force_n"] - t["force_n"]) / t["force_n"] * 100 for e, t in cut if e["force_n"]])
            cf = opts.get("cf", 1.075)
            rows.append((f"force_n [%] (C_f {cf})", len(rel), *_stats(rel)))
    if opts.get("method"):
        ok = simcase.settled(truth, scenario)
        settled = [(e, t) for e, t in pairs if t["rev"] in ok and e["valid"]]
        given = {"axial": "axial_depth_mm", "radial": "radial_depth_mm"}.get(opts.get("known"))
        for q in ("radial_depth_mm", "axial_depth_mm"):
            if q == given:
                continue                      # configured, not estimated
            vals = [(e[q], t[q]) for e, t in settled if e[q] is not None]
            if vals:
                rel = np.array([(a - b) / b * 100 for a, b in vals])
                rows.append((f"{q} [%]", len(rel), *_stats(rel)))
        bad = sum(1 for e, _ in settled if e["depth_status"] != "ok")
        if bad:
            rows.append((f"depth_status != ok: {bad}", 0, 0.0, 0.0, 0.0))
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    print(f"estimator accuracy vs simulator truth (seed {args.seed}); error = estimate - truth")
    print(f"{'scenario':<14} {'case':<34} {'quantity':<26} {'n':>4} {'mean':>8} {'p95|e|':>8} {'max|e|':>8}")
    with tempfile.TemporaryDirectory() as tmp:
        for scenario, label, opts, fc in CASES:
            for q, n, mean, p95, mx in evaluate(scenario, opts, fc, args.seed, Path(tmp)):
                print(f"{scenario:<14} {label:<34} {q:<26} {n:>4} {mean:>+8.3f} {p95:>8.3f} {mx:>8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
