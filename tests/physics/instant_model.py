"""An independent, brute-force instantaneous end-milling model for checking the averages.

Each flute is cut into axial slices; a slice at height z lags the flute tip by
``z·tan β/R``. At every tool angle the slices in cut contribute ``dF_t = K_s·h·dz``
with ``h = t_c·sin φ``, ``dF_r = r₁·dF_t`` ([D] eqs. 1–3). Nothing here uses the
closed-form integrals under test; the coefficients K_s, r₁ are passed in. With ``size_exp`` p and
``r1_exp`` q (Kienzle's law at the instantaneous chip, physics/resultant.py R1a) the slices take
``dF_t = K_s·h^p·h·dz`` and ``dF_r = r₁·h^q·dF_t`` instead.
"""

from __future__ import annotations

import numpy as np


def instantaneous_forces(
    *,
    entry_rad: float,
    exit_rad: float,
    feed_per_tooth_mm: float,
    axial_depth_mm: float,
    tool_radius_mm: float,
    flutes: int,
    helix_deg: float,
    ks_n_mm2: float,
    r1: float,
    angles: int = 2000,
    slices: int = 200,
    size_exp: float = 0.0,
    r1_exp: float = 0.0,
):
    """(F_t, F_x, F_y) over one revolution, N, sampled at ``angles`` tool angles."""
    phi = np.arange(angles) * (2.0 * np.pi / angles)
    dz = axial_depth_mm / slices
    z = (np.arange(slices) + 0.5) * dz
    lag = z * np.tan(np.radians(helix_deg)) / tool_radius_mm
    f_t = np.zeros(angles)
    f_x = np.zeros(angles)
    f_y = np.zeros(angles)
    for k in range(flutes):
        ang = np.mod(phi[:, None] + 2.0 * np.pi * k / flutes - lag[None, :], 2.0 * np.pi)
        in_cut = (ang >= entry_rad) & (ang <= exit_rad)
        h = np.where(in_cut, feed_per_tooth_mm * np.sin(ang), 0.0)
        h_pos = np.where(in_cut, np.maximum(h, 1e-300), 1.0)
        d_t = np.where(in_cut, ks_n_mm2 * h_pos**size_exp * h * dz, 0.0)
        d_r = r1 * h_pos**r1_exp * d_t
        f_t += d_t.sum(axis=1)
        f_x += (d_t * np.cos(ang) + d_r * np.sin(ang)).sum(axis=1)
        f_y += (-d_t * np.sin(ang) + d_r * np.cos(ang)).sum(axis=1)
    return f_t, f_x, f_y
