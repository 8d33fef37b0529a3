"""Physics acceptance figures: [D] Table 3 vs the exact model, the closed form vs brute-force
integration, C_f on [P]'s trial grid, solve time.

Run: .venv/bin/python bench/physics_table3.py
"""

from __future__ import annotations

import time

import numpy as np

from millsense.daemon.physics import depth
from millsense.daemon.physics.force import slot_cf
from millsense.daemon.physics.milling import SB40_TABLE2 as M, force_ratio_fx, force_ratio_fxt
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


def brute_force_forces(radial_ratio: float, t_c: float, flutes: int = 4, angles: int = 1_000_000):
    """Revolution-mean (F_x, F_y, F_t) per unit K_s·d_a, summed tooth by tooth over `angles` spindle angles.

    Nothing of the closed form is used: each tooth k at φ = θ + 2πk/N cuts while φ lies in the down-milling
    engagement [arccos(R_r − 1), π], with chip t_c·sin φ ([D] eq. 1) and dF_t = K_s·h, dF_r = r₁·dF_t,
    dF_x = dF_t cos φ + dF_r sin φ, dF_y = −dF_t sin φ + dF_r cos φ ([D] eqs. 2-4), K_s and r₁ at t_a
    ([D] eqs. 8-9). Midpoint rule over θ; the helix only shifts each slice's phase, so over a whole
    revolution it drops out and one slice stands for all.
    """
    entry, exit_ = np.arccos(radial_ratio - 1.0), np.pi
    t_a = t_c * (np.cos(entry) - np.cos(exit_)) / (exit_ - entry)
    ks, r1 = M.ks * t_a**M.ks_exp, M.r1 * t_a**M.r1_exp
    theta = (np.arange(angles) + 0.5) * (2.0 * np.pi / angles)
    fx = fy = ft = 0.0
    for k in range(flutes):
        phi = np.mod(theta + 2.0 * np.pi * k / flutes, 2.0 * np.pi)
        d_ft = np.where((phi >= entry) & (phi <= exit_), ks * t_c * np.sin(phi), 0.0)
        fx += np.mean(d_ft * (np.cos(phi) + r1 * np.sin(phi)))
        fy += np.mean(d_ft * (-np.sin(phi) + r1 * np.cos(phi)))
        ft += np.mean(d_ft)
    return fx, fy, ft


def closed_form_vs_brute_force() -> None:
    print("\nClosed form ([D] eqs. 7, 10, 12) vs brute-force integration of the per-tooth forces "
          "(down milling, SB40, 4 flutes, 10^6 angles a revolution)")
    # absolute differences: f_x and f_xt pass through 0 inside the range, where a relative one means nothing
    d_fx = d_fxt = d_rr = 0.0
    for t_c in (0.05, 0.1042, 0.2083, 0.4167):
        for r_r in (0.125, 0.25, 0.5, 1.0, 1.5, 1.99):
            fx, fy, ft = brute_force_forces(r_r, t_c)
            closed_fx = float(force_ratio_fx(r_r, t_c, M, "down"))
            d_fx = max(d_fx, abs(fx / np.hypot(fx, fy) - closed_fx))
            d_fxt = max(d_fxt, abs(fx / ft - float(force_ratio_fxt(r_r, t_c, M, "down"))))
            # what Table 3 reads from either: the same radial ratio, so its error is the polynomial's
            d_rr = max(d_rr, abs(float(radial_ratio_table3(fx / np.hypot(fx, fy), t_c))
                                 - float(radial_ratio_table3(closed_fx, t_c))))
    print(f"  24 points (t_c 0.05..0.4167 mm, R_r 0.125..1.99): max |difference| f_x {d_fx:.1e}, f_xt {d_fxt:.1e};"
          f" Table 3 reads R_r from the two within {d_rr:.1e}")
    print(f"  agreement to {int(-np.log10(max(d_fx, d_fxt)))} decimal places (midpoint rule: a tooth enters with a"
          " jump, so the difference falls as 1/angles)")


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
    closed_form_vs_brute_force()
    cf_range()
    solve_time()
