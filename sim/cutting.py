"""Instantaneous end-milling forces by axial slices (the process the estimator only averages).

Each flute is cut into axial slices ``dz``; on slice j of tooth k at spindle angle
θ the immersion angle is ``φ = θ + k·2π/N − z_j·tanβ/R`` (helix lag).  Inside the
engagement ``[φ_entry, φ_exit]`` the chip is ``h = m_k·t_c·sin φ`` ([D] eq. 1;
``m_k`` is 1 for a sound tooth, 0 for a broken one and 2 for the tooth after it)
and the elemental forces are ([D] eqs. 2-4)

    dF_t = K_s·h·dz,  dF_r = r1·dF_t,  dF_a = r2·dF_t
    dF_x =  dF_t·cos φ + dF_r·sin φ     (x = feed direction)
    dF_y = −dF_t·sin φ + dF_r·cos φ
    dF_z =  dF_a

The coefficients follow the power laws of [D] eqs. (8)-(9) evaluated at the
average chip thickness ``t_a`` of the current engagement (of each tooth).  That
is the quantity [D] Table 2 was identified against, so with one coefficient set
per instant the model's per-tooth-period averages are exactly [D] eq. (7).

With ``CutGeometry.effects`` set, the plant models what that average approximates instead
(``cut_effects.py``): the size effect at the instantaneous chip, edge forces, runout of one
tooth, static tool deflection and wear.

The axial depth is looked up where the cutting edge is, ``x = s + R·sin φ``
(s = tool centre along the path), so a tool entering a step or the part meets
the new depth gradually over its radius instead of in one jump.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from millsense.sim.cut_effects import CutEffects, calibration, effect_forces, runout_offsets_mm, tool_stiffness_n_mm
from millsense.sim.machine import Material, Tool

MIN_SLICES = 20
MAX_SLICE_MM = 1.0


def engagement_rad(radial_depth_mm: np.ndarray, radius_mm: float, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit immersion angles for down, up milling or a slot ([D] §2)."""
    rr = np.clip(np.asarray(radial_depth_mm, dtype=float) / radius_mm, 0.0, 2.0)  # R_r
    if mode == "slot":
        return np.zeros_like(rr), np.full_like(rr, math.pi)
    if mode == "down":
        return np.arccos(rr - 1.0), np.full_like(rr, math.pi)
    if mode == "up":
        return np.zeros_like(rr), np.arccos(1.0 - rr)
    raise ValueError(f"unknown milling mode {mode!r} (down, up or slot)")


def average_chip_mm(feed_per_tooth_mm: np.ndarray, entry_rad: np.ndarray, exit_rad: np.ndarray) -> np.ndarray:
    """t_a = t_c·(cos φ_st − cos φ_ex)/(φ_ex − φ_st), [D] eq. (8)."""
    span = np.maximum(exit_rad - entry_rad, 1e-9)
    return feed_per_tooth_mm * (np.cos(entry_rad) - np.cos(exit_rad)) / span


def tooth_chip_factors(flutes: int, broken: tuple[int, ...] = ()) -> np.ndarray:
    """m_k: 0 for a broken tooth, 1 + (broken teeth just ahead of it) for a sound one.

    Tooth k sits at θ + k·2π/N, so tooth k+1 passes a point just before tooth k;
    when k+1 is broken, tooth k removes both chips."""
    m = np.zeros(flutes)
    broken_set = {b % flutes for b in broken}
    if len(broken_set) == flutes:
        return m
    for k in range(flutes):
        if k in broken_set:
            continue
        j, extra = (k + 1) % flutes, 0
        while j in broken_set:
            extra, j = extra + 1, (j + 1) % flutes
        m[k] = 1 + extra
    return m


@dataclass
class CutGeometry:
    """Tool, material, milling mode and the workpiece's depth profiles along the path."""

    tool: Tool
    material: Material
    mode: str
    axial_xp_mm: np.ndarray  # axial depth profile: d_a(x) by np.interp, 0 outside the part
    axial_fp_mm: np.ndarray
    radial_xp_mm: np.ndarray  # radial depth profile at the tool centre
    radial_fp_mm: np.ndarray
    max_axial_mm: float
    effects: CutEffects | None = None  # None: [D]'s average model exactly; else the plant's (cut_effects.py)

    def __post_init__(self) -> None:
        self.slices = max(MIN_SLICES, math.ceil(self.max_axial_mm / MAX_SLICE_MM))
        self.dz_mm = self.max_axial_mm / self.slices
        self.z_low_mm = np.arange(self.slices) * self.dz_mm
        z_mid = self.z_low_mm + self.dz_mm / 2
        r = self.tool.radius_mm
        self.lag_rad = z_mid * math.tan(math.radians(self.tool.helix_deg)) / r
        self.tooth_rad = np.arange(self.tool.flutes) * 2 * math.pi / self.tool.flutes
        if self.effects is not None:
            self.chip_law = calibration(self.material, self.effects)
            self.runout_mm = runout_offsets_mm(self.tool.flutes, self.effects)
            self.stiffness_n_mm = tool_stiffness_n_mm(self.tool, self.effects)

    def axial_depth_mm(self, x_mm: np.ndarray) -> np.ndarray:
        return np.interp(x_mm, self.axial_xp_mm, self.axial_fp_mm, left=0.0, right=0.0)

    def radial_depth_mm(self, x_mm: np.ndarray) -> np.ndarray:
        if self.mode == "slot":
            return np.full(np.shape(x_mm), self.tool.diameter_mm)
        return np.interp(x_mm, self.radial_xp_mm, self.radial_fp_mm)


def _interval_means(phi, span, entry, exit_):
    """Means of sin φ, sin φ·cos φ, sin²φ over [φ, φ + Δ] ∩ [entry, exit], divided by Δ.

    Elements wholly inside the engagement (the many) get sin/cos of φ + Δ by rotation;
    only the few that straddle the entry or exit angle need their own trig."""
    phi = np.where(phi > 2 * math.pi - span, phi - 2 * math.pi, phi)  # an interval across 2π starts below 0
    sp, cp = np.sin(phi), np.cos(phi)
    sd, cd = np.sin(span), np.cos(span)
    sh, ch = sp * cd + cp * sd, cp * cd - sp * sd
    inv = 1.0 / np.maximum(span, 1e-12)
    full = (phi >= entry) & (phi + span <= exit_)
    i_s = np.where(full, (cp - ch) * inv, 0.0)
    i_sc = np.where(full, 0.5 * (sh * sh - sp * sp) * inv, 0.0)
    i_ss = np.where(full, 0.5 - 0.5 * (sh * ch - sp * cp) * inv, 0.0)
    x_edge = sp * np.cos(0.5 * span) + cp * np.sin(0.5 * span)  # sin of the interval's middle
    part = ~full & (phi < exit_) & (phi + span > entry)
    if part.any():
        shape = phi.shape
        ent = np.broadcast_to(entry, shape)[part]
        ext = np.broadcast_to(exit_, shape)[part]
        p0 = phi[part]
        sp_ = np.broadcast_to(span, shape)[part]
        lo = np.maximum(p0, ent)
        hi = np.minimum(p0 + sp_, ext)
        s_lo, c_lo, s_hi, c_hi = np.sin(lo), np.cos(lo), np.sin(hi), np.cos(hi)
        inv_p = 1.0 / sp_
        i_s[part] = (c_lo - c_hi) * inv_p
        i_sc[part] = 0.5 * (s_hi**2 - s_lo**2) * inv_p
        i_ss[part] = (0.5 * (hi - lo) - 0.5 * (s_hi * c_hi - s_lo * c_lo)) * inv_p
        x_edge[part] = np.sin(0.5 * (lo + hi))  # where the edge cuts (inside the engagement)
    return i_s, i_sc, i_ss, x_edge


def _edge_depth_mm(geom: CutGeometry, position_mm: np.ndarray, x_edge: np.ndarray) -> np.ndarray:
    """Axial depth where each edge element is, x = s + R·sin φ.

    Where the profile is one straight segment across the tool (no breakpoint within
    ±R) the depth is linear in sin φ; only the rows near a wall or a corner of the
    profile need the full look-up."""
    xp, fp, r = geom.axial_xp_mm, geom.axial_fp_mm, geom.tool.radius_mm
    inside = np.searchsorted(xp, position_mm + r, "left") - np.searchsorted(xp, position_mm - r, "right") > 0
    j = np.searchsorted(xp, position_mm, "right") - 1
    on_segment = (j >= 0) & (j < len(xp) - 1)
    jc = np.clip(j, 0, len(xp) - 2)
    slope = np.where(on_segment, (fp[jc + 1] - fp[jc]) / (xp[jc + 1] - xp[jc]), 0.0)
    d_s = geom.axial_depth_mm(position_mm)
    depth = d_s[:, None, None] + (slope * r)[:, None, None] * x_edge
    if inside.any():
        rows = np.flatnonzero(inside)
        depth[rows] = geom.axial_depth_mm(position_mm[rows, None, None] + r * x_edge[rows])
    return depth


def cutting_forces(
    geom: CutGeometry,
    theta_rad: np.ndarray,
    position_mm: np.ndarray,
    feed_per_tooth_mm: np.ndarray,
    chip_factors: np.ndarray,
    dtheta_rad: np.ndarray | float = 0.0,
) -> dict[str, np.ndarray]:
    """Forces on the tool (tool frame, N): ``fx_n, fy_n, fz_n, ft_n``.

    With ``dtheta_rad = 0`` the forces at the angles ``theta_rad``; with
    ``dtheta_rad > 0`` their exact means while the spindle turns from θ to θ + Δθ
    (each element's sin φ, sin φ·cos φ, sin²φ integrated in closed form over
    its part of the interval inside the engagement).  The means make revolution
    averages exact on a coarse grid although a flute enters the cut with a jump
    (down milling), and they are the box-filtered force a sampler should see.

    Cutting torque at the spindle is ``R·ft_n`` ([P] eq. 15).  ``chip_factors`` is
    (N,) or (n, N) (tooth breakage mid-block).  Work is (n, N, slices) elements.

    A geometry with ``effects`` is computed by ``cut_effects.effect_forces`` instead (the size effect at
    the instantaneous chip, edge forces, runout, deflection, wear), with the same outputs."""
    if geom.effects is not None:
        return effect_forces(geom, theta_rad, position_mm, feed_per_tooth_mm, chip_factors, dtheta_rad)
    tool, mat = geom.tool, geom.material
    r = tool.radius_mm
    theta = np.asarray(theta_rad, dtype=float)
    n = theta.shape[0]
    tc = np.maximum(np.asarray(feed_per_tooth_mm, dtype=float), 0.0)
    entry, exit_ = engagement_rad(geom.radial_depth_mm(position_mm), r, geom.mode)
    m = np.broadcast_to(np.asarray(chip_factors, dtype=float), (n, tool.flutes))
    # [D] eqs. (8)-(9) at each tooth's own average chip (a tooth after a broken one cuts m_k·t_c)
    ta = np.maximum(average_chip_mm(tc, entry, exit_)[:, None] * np.maximum(m, 1.0), 1e-6)
    ks = mat.ks * ta**mat.ks_exp
    r1 = mat.r1 * ta**mat.r1_exp
    r2 = mat.r2 * ta**mat.r2_exp
    span = np.broadcast_to(np.asarray(dtheta_rad, dtype=float), (n,))[:, None, None]
    phi = np.mod(theta[:, None, None] + geom.tooth_rad[None, :, None] - geom.lag_rad[None, None, :], 2 * math.pi)
    entry3, exit3 = entry[:, None, None], exit_[:, None, None]
    if np.any(span > 0):
        i_s, i_sc, i_ss, x_edge = _interval_means(phi, span, entry3, exit3)
    else:
        x_edge = np.sin(phi)
        in_cut = (phi >= entry3) & (phi <= exit3)
        i_s = np.where(in_cut, x_edge, 0.0)
        i_sc = i_s * np.cos(phi)
        i_ss = i_s * x_edge
    depth = _edge_depth_mm(geom, np.asarray(position_mm, dtype=float), x_edge)
    weight = np.clip((depth - geom.z_low_mm) / geom.dz_mm, 0.0, 1.0)  # part of the slice inside the work
    # dF_t = K_s·h·dz with h = m_k·t_c·sin φ, [D] eqs. (1)-(2)
    scale = (ks * m * tc[:, None] * geom.dz_mm)[:, :, None] * weight
    ft_k = (scale * i_s).sum(axis=2)
    fx_t = (scale * i_sc).sum(axis=2)  # Σ dF_t·cos φ
    fy_t = (scale * i_ss).sum(axis=2)  # Σ dF_t·sin φ
    # dF_r = r1·dF_t, dF_a = r2·dF_t with per-tooth coefficients, [D] eqs. (3)-(4)
    fx = (fx_t + r1 * fy_t).sum(axis=1)
    fy = (-fy_t + r1 * fx_t).sum(axis=1)
    fz = (r2 * ft_k).sum(axis=1)
    return {"fx_n": fx, "fy_n": fy, "fz_n": fz, "ft_n": ft_k.sum(axis=1)}
