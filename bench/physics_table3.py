"""Physics acceptance figures: [D] Table 3 vs the exact model, C_f on [P]'s trial grid, solve time.

Run: .venv/bin/python bench/physics_table3.py
"""

from __future__ import annotations

import time

import numpy as np

from millsense.daemon.physics import depth
from millsense.daemon.physics.force import slot_cf
from millsense.daemon.physics.milling import SB40_TABLE2 as M, force_ratio_fx
from millsense.daemon.physics.table3 import radial_ratio_table3


def table3_comparison() -> None:
    r_r = np.linspace(0.125, 1.99, 2000)
    print("[D] Table 3 polynomial vs exact model (down milling, SB40 Table 2), R_r 0.125..1.99")
    print(f"{'t_c mm':>8} {'max rel err':>12} {'at R_r':>7} {'max abs err':>12} {'max rel, R_r>=0.25':>19}")
    for t_c in (0.05, 0.1042, 0.2083, 0.4167):
        err = radial_ratio_table3(force_ratio_fx(r_r, t_c, M, "down"), t_c) - r_r
        rel = np.abs(err) / r_r
        i = int(np.argmax(rel))
        print(f"{t_c:8.4f} {rel[i]:11.2%} {r_r[i]:7.3f} {np.max(np.abs(err)):12.4f} {np.max(rel[r_r >= 0.25]):18.2%}")


def cf_range() -> None:
    grid = [(rpm, f) for rpm in (300, 500, 700, 900) for f in (50, 100, 200)]
    grid += [(rpm, f) for rpm in (1000, 1500, 2000, 2500) for f in (100, 200, 300)]
    t_c = np.array([f / (2 * rpm) for rpm, f in grid])
    cf = slot_cf(t_c, M)
    print("\nC_f = sqrt(1 + r1(t_a)^2), [P] Table 1 grid, 2-flute slot, SB40 coefficients")
    print(f"  t_c {t_c.min():.4f}..{t_c.max():.4f} mm/tooth -> C_f {cf.min():.4f}..{cf.max():.4f} (mean {cf.mean():.4f});"
          f" [P] measured 1.03..1.11 (mean 1.075)")
    inside = (cf >= 1.03) & (cf <= 1.11)
    print(f"  {inside.sum()} of {cf.size} grid points inside [1.03, 1.11]; outside: "
          + ", ".join(f"{rpm} rpm/{f} mm/min={c:.3f}" for (rpm, f), c, ok in zip(grid, cf, inside) if not ok))


def solve_time() -> None:
    rng = np.random.default_rng(0)
    n = 2000
    t_c = rng.uniform(0.02, 0.5, n)
    targets = [float(force_ratio_fx(r, t, M, "down")) for r, t in zip(rng.uniform(0.05, 2.0, n), t_c)]
    depth._branches.cache_clear()
    start = time.perf_counter()
    for f, t in zip(targets, t_c):
        depth.radial_ratio_from_fx(f, t, M, "down")
    cold = (time.perf_counter() - start) / n
    # Steady cutting: a programmed feed repeats its t_c revolution after revolution.
    steady = np.repeat(t_c[:20], n // 20)
    targets = [float(force_ratio_fx(r, t, M, "down")) for r, t in zip(rng.uniform(0.05, 2.0, n), steady)]
    start = time.perf_counter()
    for f, t in zip(targets, steady):
        depth.radial_ratio_from_fx(f, t, M, "down")
    warm = (time.perf_counter() - start) / n
    start = time.perf_counter()
    for f, t in zip(targets, steady):
        depth.depths_from_forces(fx_n=f, fy_n=-np.sqrt(1 - f * f), feed_per_tooth_mm=t, tool_radius_mm=8.0, flutes=4, material=M, mode="down")
    full = (time.perf_counter() - start) / n
    print(f"\nf_x solve, down milling, {n} solves: {cold * 1e3:.3f} ms each with a new t_c (branch search + brentq),"
          f" {warm * 1e3:.3f} ms with a repeated t_c; depths_from_forces (repeated t_c) {full * 1e3:.3f} ms")


if __name__ == "__main__":
    table3_comparison()
    cf_range()
    solve_time()
