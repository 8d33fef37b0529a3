"""What the engaged teeth's resultant (physics/resultant.py) costs a revolution, beside the path before it.

The live daemon computes one revolution's force on Python floats (`RevolutionPhysics._force_one`);
replay a block's revolutions as arrays (`_force_many`). Timed here, in the same run:

- `constant`: eq. (18) with a number C_f (`cf = 1.075`), unchanged by issue 41;
- `r1 only`: the C_f of `cf = "model"` before issue 41, √(1 + r₁(t_a)²) (engagement, chip, eq. 9; the
  formulas as they were, restated here as the baseline);
- `η, [D]'s law`: η·√(1 + r₁(t_a)²) with η of the teeth's forces ∝ sin φ (the path before the size
  effect, restated here: η from the p = q = 0 table, bilinear in span and lag);
- `engaged`: `force.engaged_cf` now, η of Kienzle's law at each chip (resultant.py R1a-R2), trilinear in
  span, lag and ±r₁ from the table of the material's exponents;
- the tables' one-off build per flute count and material exponents (functools.cache: once a process;
  the estimator builds those of `[material]` at start, per_revolution.RevolutionPhysics).

    .venv/bin/python bench/force_cost.py [--repeat 20000]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _per_call_us(fn, repeat: int) -> float:
    best = math.inf
    for _ in range(5):
        t0 = time.perf_counter_ns()
        for _ in range(repeat):
            fn()
        best = min(best, (time.perf_counter_ns() - t0) / repeat / 1e3)
    return best


def main() -> int:
    from millsense.daemon.physics import resultant
    from millsense.daemon.physics.force import cf_model, engaged_cf, resultant_force_magnitudes_n
    from millsense.daemon.physics.milling import NP, SCALAR, SB40_TABLE2, chip_xp, engagement_xp

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20000)
    args = parser.parse_args()
    m = SB40_TABLE2
    radius, flutes, helix = 8.0, 4, 30.0
    torque, t_c, radial, axial, noise = 12.0, 0.1, 6.0, 10.0, 0.6

    p, q = resultant.local_exponents(m.ks_exp, m.r1_exp)
    builds, builds_flat, firsts = {}, {}, {}
    resultant.overlap_table(2, p, q)    # the S_m tables (once a process, a few ms) out of the first figure
    for n in (2, 3, 4, 6):
        t0 = time.perf_counter()
        resultant.overlap_table(n, p, q)
        builds[n] = time.perf_counter() - t0
        t0 = time.perf_counter()
        resultant.overlap_table(n)
        builds_flat[n] = time.perf_counter() - t0
        resultant._TABLES.clear()      # what the daemon pays: the cells of one cut, at its first revolution
        t0 = time.perf_counter()
        engaged_cf("down", n, radius, helix, t_c, radial, axial, m, None)
        firsts[n] = time.perf_counter() - t0

    def constant():
        return resultant_force_magnitudes_n(torque, radius, 1.075, noise)

    def r1_only():
        entry, exit_ = engagement_xp(SCALAR, radial / radius, "down")
        cf = cf_model(chip_xp(SCALAR, t_c, entry, exit_), m.r1, m.r1_exp)
        return resultant_force_magnitudes_n(torque, radius, cf, noise)

    def eta_average_law():
        entry, exit_ = engagement_xp(SCALAR, radial / radius, "down")
        cf = cf_model(chip_xp(SCALAR, t_c, entry, exit_), m.r1, m.r1_exp)
        eta = resultant.overlap_factor(flutes, exit_ - entry, resultant.helix_lag_rad(axial, helix, radius))
        return resultant_force_magnitudes_n(torque, radius, eta * cf, noise)

    def engaged():
        cf = engaged_cf("down", flutes, radius, helix, t_c, radial, axial, m, None)
        return resultant_force_magnitudes_n(torque, radius, cf, noise)

    rows = 1000
    rng = np.random.default_rng(1)
    tq, tc = rng.uniform(5, 20, rows), rng.uniform(0.05, 0.3, rows)
    rad, ax = rng.uniform(1, 16, rows), rng.uniform(2, 16, rows)

    def r1_only_many():
        entry, exit_ = engagement_xp(NP, rad / radius, "down")
        cf = cf_model(chip_xp(NP, tc, entry, exit_), m.r1, m.r1_exp)
        return resultant_force_magnitudes_n(tq, radius, cf, noise)

    def engaged_many():
        cf = engaged_cf("down", flutes, radius, helix, tc, rad, ax, m, None)
        return resultant_force_magnitudes_n(tq, radius, cf, noise)

    print("force per revolution, one revolution on floats (the live path); µs, best of 5")
    base = _per_call_us(constant, args.repeat)
    before = _per_call_us(r1_only, args.repeat)
    flat = _per_call_us(eta_average_law, args.repeat)
    after = _per_call_us(engaged, args.repeat)
    print(f"  constant C_f (eq. 18)            {base:7.2f}")
    print(f"  √(1 + r₁²) (cf = model before)    {before:7.2f}")
    print(f"  η·√(1 + r₁²), [D]'s law           {flat:7.2f}")
    print(f"  η·√(1 + r₁²), Kienzle at h (now)  {after:7.2f}   +{after - flat:.2f} µs over [D]'s law's η")
    print(f"{rows} revolutions as arrays (replay); µs per block, best of 5")
    many_before = _per_call_us(r1_only_many, max(args.repeat // 100, 20))
    many_after = _per_call_us(engaged_many, max(args.repeat // 100, 20))
    print(f"  √(1 + r₁²) before                 {many_before:7.1f}")
    print(f"  η·√(1 + r₁²) now                  {many_after:7.1f}")
    print(f"η table of SB40's exponents (p {p:g}, q {q:g}) whole (tests, benches; the daemon never builds it): "
          + ", ".join(f"{n} flutes {s * 1e3:.0f} ms" for n, s in builds.items()))
    print("the daemon's first revolution of a new engagement (its cells computed then, once): "
          + ", ".join(f"{n} flutes {s * 1e3:.1f} ms" for n, s in firsts.items()))
    print("η table of [D]'s law (p = q = 0): " + ", ".join(f"{n} flutes {s * 1e3:.0f} ms"
                                                          for n, s in builds_flat.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
