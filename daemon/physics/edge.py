"""C_f with the edge (ploughing) forces: a material's average law split into a chip term and an edge term.

[D] eq. (9)'s law, ``K_s = k·t_a^p`` and ``r₁ = k₁·t_a^q``, is fitted to the *average* forces of test cuts,
and a real cut's average force has two parts (Altintas, *Manufacturing Automation*, 2nd ed. 2012, ch. 2,
eqs. 2.35–2.36, the linear edge-force model; Budak, Altintas & Armarego, J. Manuf. Sci. Eng. 118, 1996):
one grows with the chip, one does not — the edge rubbing and ploughing, K_te and K_re newtons per mm of
engaged edge, the same all along the engaged arc. The torque takes them together; the resultant does not:
the chip's force is concentrated where the chip is thick (sin^(1+p) φ), the edge's spread evenly over the
arc, so where several teeth cut at once the edge forces cancel more, and the edge's radial share (K_re is
usually above K_te) turns the resultant towards the normal. resultant.py's η takes the whole law as chip;
this takes the material's edge coefficients out of it first.

Per tooth and revolution and per mm of depth, over the engagement E = [θ₁, θ₂] of span s = θ₂ − θ₁, the
law's mean tangential and radial force ([D] eqs. 7–9) and the edge's:

    T = K_s(t_a)·t_a·s/2π,   R = r₁(t_a)·T,   T_e = K_te·s/2π,   R_e = K_re·s/2π                  (E1)

the chip's are the rest, ``T_c = T − T_e``, ``R_c = R − R_e``, its radial ratio ``r_c = R_c/T_c``, and its
exponents the law's local log-slopes with the constant edge taken out (T ∝ t^(1+p), R ∝ t^(1+p+q)):

    1 + p_c = (1 + p)·T/T_c,   1 + p_c + q_c = (1 + p + q)·R/R_c                                 (E4)

(taking the law's own p, q for the chip instead reads the φ8 3-flute slots 3–4 % low on the plant:
the chip term of a law with an edge grows faster with the chip than the law does). Element
by element (resultant.py R1, R1a), the chip's force at the instantaneous chip with these exponents
(w = sin^(1+p_c) φ) and the edge's constant:

    dF = [(w(φ) + i·r_c·κ·w(φ)·sin^(q_c) φ)·T_c/T̄_c + (K_te + i·K_re)/K_te·T_e/T̄_e]·e^{−iφ}        (E2)

(T̄: the tangential means of the unscaled sums, resultant.py's ``_period_sums``, so that each part carries
its own mean), summed over the teeth in cut with the helix's lag and averaged over a tooth period:

    C_f = mean_θ |Σ_k ∫ dF| / (T_c + T_e)                                                          (E3)

With K_te = K_re = 0 this is resultant.py's η·√(1 + r₁²). An edge term larger than the law's mean at this
chip (T_c ≤ 0 or R_c ≤ 0: the law's exponent says the force of a thin chip is smaller than the edge alone)
is outside what the split can say: None (the caller keeps the chip-only C_f); so is a split whose chip keeps
almost none of the radial force (R_c → 0: q_c of E4 runs to tens and the quadrature to nan).

The same split gives the feed-drive depth its eq. 12 curve, f_xt = F_x/F_t ((E5), ``split_fxt``, below).

Cost: one quadrature (2–10 ms); ``edge_cf`` caches it per cut on a grid (feed per tooth to 0.2 %, radial
depth to 0.5 % of R, axial depth to 1 %): a constant cut pays it once, then a dictionary look-up (5 µs);
depths estimated revolution by revolution fill a few cells of the grid each.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from millsense.daemon.physics.milling import NP, Material, chip_xp, engagement_xp
from millsense.daemon.physics.resultant import GAUSS_NODES, _period_sums, helix_lag_rad, local_exponents

FEED_STEP = 0.002   # the cache's feed per tooth: to 0.2 % (C_f moves by about 0.02 % over it)
EXP_DIGITS = 3      # the chip term's exponents to 0.001 (each value builds resultant.py's S_m table once)
RATIO_STEP = 0.005  # the cache's radial depth: to 0.5 % of the tool radius (C_f moves by under 0.1 % over it)
AXIAL_STEP = 0.01   # the cache's axial depth: to 1 % (it moves the helix's lag alone)


def has_edge(material: Material) -> bool:
    """Does the material carry edge coefficients (either above 0)?"""
    return getattr(material, "edge_t_n_mm", 0.0) > 0.0 or getattr(material, "edge_r_n_mm", 0.0) > 0.0


class Split(NamedTuple):
    """(E1), (E4) at one cut: per tooth-revolution and mm of depth, N; the chip term's exponents."""

    chip_t: float
    chip_r: float
    edge_t: float
    edge_r: float
    size_exp: float   # p_c of (E4)
    r1_exp: float     # q_c of (E4)


def split(entry_rad: float, exit_rad: float, feed_per_tooth_mm: float, material: Material) -> Split | None:
    """The law's mean forces at this cut split into the chip's and the edge's (E1), with the chip term's own
    exponents (E4); None where the edge term exceeds the law's mean or the chip is unknown."""
    span = exit_rad - entry_rad
    if not (span > 0.0 and feed_per_tooth_mm > 0.0):
        return None
    t_a = float(chip_xp(NP, np.asarray(feed_per_tooth_mm), np.asarray(entry_rad), np.asarray(exit_rad)))  # [D] eq. 8
    if not (math.isfinite(t_a) and t_a > 0.0):
        return None
    tangential = material.ks * t_a ** material.ks_exp * t_a * span / (2.0 * math.pi)   # (E1), [D] eq. 9
    radial = material.r1 * t_a ** material.r1_exp * tangential
    edge_t = material.edge_t_n_mm * span / (2.0 * math.pi)
    edge_r = material.edge_r_n_mm * span / (2.0 * math.pi)
    chip_t, chip_r = tangential - edge_t, radial - edge_r
    if not (chip_t > 0.0 and chip_r > 0.0):
        return None
    # (E4): the chip term's own exponents, the law's local log-slopes with the constant edge taken out
    p = round((1.0 + material.ks_exp) * tangential / chip_t - 1.0, EXP_DIGITS)
    q = round((1.0 + material.ks_exp + material.r1_exp) * radial / chip_r - 1.0 - p, EXP_DIGITS)
    return Split(chip_t, chip_r, edge_t, edge_r, p, q)


def split_cf(flutes: int, entry_rad: float, exit_rad: float, lag_rad: float, feed_per_tooth_mm: float,
             material: Material, nodes: int = GAUSS_NODES) -> float | None:
    """C_f of (E3) by quadrature at one cut; None where the edge term exceeds the law's mean (module doc)."""
    parts = split(entry_rad, exit_rad, feed_per_tooth_mm, material)
    if parts is None:
        return None
    p, q = local_exponents(parts.size_exp, parts.r1_exp)
    e, x, g = (np.array([[v]], dtype=float) for v in (entry_rad, exit_rad, lag_rad))
    with np.errstate(invalid="ignore", over="ignore"):   # a degenerate split's nan is caught below
        a_c, b_c, weight, mean_c, _ = _period_sums(int(flutes), e, x, g, nodes, p, q)
        a_e, _, _, mean_e, _ = _period_sums(int(flutes), e, x, g, nodes, -1.0, 0.0)   # sin⁰ φ: the edge, even
        chip = (a_c + 1j * (parts.chip_r / parts.chip_t) * b_c) * (parts.chip_t / mean_c[0])    # (E2)
        edge = (parts.edge_t + 1j * parts.edge_r) * a_e / mean_e[0]
        cf = float((np.abs(chip + edge) * weight).sum()) / (parts.chip_t + parts.edge_t)         # (E3)
    # where the edge takes nearly all the law's radial force, R_c → 0 sends (E4)'s q_c to 45-70 and the sums
    # of sin^q_c φ to nan: the split says nothing there either (None: the caller's chip-only C_f)
    return cf if math.isfinite(cf) else None


def edge_cf(mode: str, flutes: int, tool_radius_mm: float, helix_deg: float | None, feed_per_tooth_mm: float,
            radial_depth_mm: float | None, axial_depth_mm: float | None, material: Material) -> float | None:
    """C_f of (E3) at a cut given as ``force.engaged_cf`` takes it; None where it cannot say (unknown
    engagement or chip, the edge term beyond the law). Cached per cut and feed per tooth to FEED_STEP."""
    if not (math.isfinite(feed_per_tooth_mm) and feed_per_tooth_mm > 0.0):
        return None
    step = round(math.log(feed_per_tooth_mm) / FEED_STEP)
    ratio = 2.0 if mode == "slot" else (math.nan if radial_depth_mm is None else radial_depth_mm / tool_radius_mm)
    if not 0.0 < ratio <= 2.0:
        return None
    # depths estimated revolution by revolution move a little every time: on a grid (RATIO_STEP of R, AXIAL_STEP
    # relative), so that a cut pays the quadrature once per cell, not once per revolution
    cell_r = max(1, round(ratio / RATIO_STEP))
    cell_a = None
    if axial_depth_mm is not None and math.isfinite(axial_depth_mm) and axial_depth_mm > 0.0:
        cell_a = round(math.log(axial_depth_mm) / AXIAL_STEP)
    return _cached(mode, int(flutes), float(tool_radius_mm), helix_deg, step, cell_r, cell_a, material)


@functools.lru_cache(maxsize=4096)
def _cached(mode, flutes, radius_mm, helix_deg, step, cell_r, cell_a, material) -> float | None:
    entry, exit_ = engagement_xp(NP, np.asarray(min(cell_r * RATIO_STEP, 2.0)), mode)
    axial = None if cell_a is None else math.exp(cell_a * AXIAL_STEP)
    lag = float(helix_lag_rad(axial, helix_deg, radius_mm))
    return split_cf(flutes, float(entry), float(exit_), lag, math.exp(step * FEED_STEP), material)


# ----------------------------------------------------------------------------- [D] eq. 12 with the split law
# The feed-drive depth solves f_xt = F_x/F_t for the radial immersion ([D] eq. 12). [D]'s f_xt = (a + r₁b)/c holds
# one r₁ at the mean chip over the whole arc, forces ∝ sin φ. With edge coefficients the material says more: the
# chip term at the instantaneous chip with (E4)'s exponents, the edge even over the arc (E1). Per tooth and mm of
# depth, with T̂ = K_s(t_a)·t_a and R̂ = r₁(t_a)·T̂ the law's mean forces per radian of arc ((E1) over s/2π), the
# chip's T̂_c = T̂ − K_te, R̂_c = R̂ − K_re, and I_m = ∫ sin^m φ dφ over the engagement [θ₁, θ₂] of span s:
#
#     2π·F_x = T̂_c·s·J/I_(1+p_c) + K_te·(sin θ₂ − sin θ₁) + R̂_c·s·I_(2+p_c+q_c)/I_(1+p_c+q_c) + K_re·(cos θ₁ − cos θ₂)
#     2π·F_t = T̂·s,     f_xt = F_x/F_t,     J = ∫ sin^(1+p_c) φ·cos φ dφ = [sin^(2+p_c) φ/(2+p_c)]          (E5)
#
# (with K_te = K_re = 0 and the law's exponents 0 it is (a + r₁b)/c). Where the edge exceeds the law's mean (T̂_c or
# R̂_c ≤ 0: a thin chip, edge_cf's None) the chip term is taken as 0 and the edge as the law's whole mean, which
# meets the split continuously where T̂_c, R̂_c reach 0 (the depth's branches need a continuous curve). On the
# simulator's effects plant (E5) reads the radial depth from the plant's true forces within 2 % where [D]'s eq. 12
# reads it 16-26 % low (bench/split_depth.py, docs/accuracy.md). The axial depth's F_t is the law's either way.
FXT_NODES = 64   # Gauss-Legendre points over the arc: (E5) to 1e-4 against a dense sum (tests/physics/test_edge.py)
_FXT_X, _FXT_W = np.polynomial.legendre.leggauss(FXT_NODES)


def feed_cell(feed_per_tooth_mm: float) -> float:
    """The feed per tooth on the caches' grid (FEED_STEP, 0.2 %): what the depth's (E5) curve is built at, so
    that a steady cut, its measured feed wandering a little, builds the curve once (f_xt moves by under 0.03 %
    over a cell). Not finite or not positive: as given."""
    if not (math.isfinite(feed_per_tooth_mm) and feed_per_tooth_mm > 0.0):
        return feed_per_tooth_mm
    return math.exp(round(math.log(feed_per_tooth_mm) / FEED_STEP) * FEED_STEP)


def split_fxt(radial_ratio, feed_per_tooth_mm: float, material: Material, mode: str) -> np.ndarray:
    """f_xt of (E5) at each radial immersion R_r (array in, array out); nan where there is no chip."""
    r = np.atleast_1d(np.asarray(radial_ratio, dtype=float))
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        entry, exit_ = engagement_xp(NP, r, mode)
        entry, exit_ = np.broadcast_to(entry, r.shape), np.broadcast_to(exit_, r.shape)
        span = exit_ - entry
        t_a = chip_xp(NP, feed_per_tooth_mm, entry, exit_)                                   # [D] eq. 8
        t_hat = material.ks * t_a ** material.ks_exp * t_a                                     # [D] eq. 9, E1
        r_hat = material.r1 * t_a ** material.r1_exp * t_hat
        chip_t, chip_r = np.maximum(t_hat - material.edge_t_n_mm, 0.0), np.maximum(r_hat - material.edge_r_n_mm, 0.0)
        edge_t, edge_r = t_hat - chip_t, r_hat - chip_r
        one_p = np.where(chip_t > 0.0, (1.0 + material.ks_exp) * t_hat / chip_t, 1.0)              # (E4)
        one_pq = np.where(chip_r > 0.0, (1.0 + material.ks_exp + material.r1_exp) * r_hat / chip_r, 1.0)
        phi = (entry + exit_)[:, None] / 2.0 + span[:, None] / 2.0 * _FXT_X[None, :]
        weight = span[:, None] / 2.0 * _FXT_W[None, :]
        sin = np.maximum(np.sin(phi), 0.0)
        i_t = (weight * sin ** one_p[:, None]).sum(axis=1)
        i_r = (weight * sin ** one_pq[:, None]).sum(axis=1)
        i_rs = (weight * sin ** (one_pq[:, None] + 1.0)).sum(axis=1)
        s1, s2 = np.maximum(np.sin(entry), 0.0), np.maximum(np.sin(exit_), 0.0)
        j = (s2 ** (one_p + 1.0) - s1 ** (one_p + 1.0)) / (one_p + 1.0)
        chip_x = np.where(chip_t > 0.0, chip_t * span * j / i_t, 0.0) + \
            np.where(chip_r > 0.0, chip_r * span * i_rs / i_r, 0.0)
        edge_x = edge_t * (np.sin(exit_) - np.sin(entry)) + edge_r * (np.cos(entry) - np.cos(exit_))
        out = (chip_x + edge_x) / (t_hat * span)                                               # (E5)
    return np.where(np.isfinite(out) & (t_a > 0.0), out, np.nan)
