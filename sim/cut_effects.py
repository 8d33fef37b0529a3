"""What the average milling model leaves out: the plant's mechanistic cutting force, element by element.

``cutting.py`` without effects is [D]'s own model in the time domain: the coefficients of [D] eq. (9)
at each tooth's *average* chip t_a, so its revolution means are exactly [D] eq. (7). A real cut is not
that. With ``CutEffects`` on a geometry, each edge element (tooth k, axial slice j, spindle angle θ) of
``cutting_forces`` is computed here instead, from the mechanistic force model of the machining
textbooks (Altintas, *Manufacturing Automation*, 2nd ed. 2012, ch. 2, eqs. 2.35-2.36, "dF = K_c·h·dz
+ K_e·dz"; Kienzle's law for K_c):

    h      = m_k·f_z·sin φ + ρ_k                          chip at the instant, with runout (ρ_k)
    dF_t   = c_t·w·k_s·max(h, h_min)^(ks_exp)·h·dz + w_e·K_te·dz     size effect at h, plus the edge
    dF_r   = c_r·w·r₁·max(h, h_min)^(r1_exp)·(dF_t chip) + w_e·K_re·dz
    dF_a   = r₂·max(h, h_min)^(r2_exp)·(dF_t chip)

projected as [D] eqs. (2)-(4). ``k_s·h^ks_exp`` is Kienzle's k_c = k_c1.1·h^(−m_c) (ks = k_c1.1 in N/mm²
at h = 1 mm, ks_exp = −m_c) at the *instantaneous* chip, not [D] eq. (9)'s at t_a; the edge force
(ploughing, rubbing on the flank) is per unit of engaged edge and independent of the chip; one tooth is
ρ out radially (runout: it takes a chip ρ thicker, the tooth after it one ρ thinner); the tool bends
under the force normal to the wall, so a side-milling cut's engaged radial depth is ae − F_n/k (down
milling pushes the tool off the wall, up milling pulls it in); a tool
used up to a fraction L of its life cuts with edge forces × (1 + g_e·L) and chip forces × (1 + g_c·L)
(flank wear rubs: the edge term grows most).

The handbook's law is what test cuts measured: the chip term's scale and exponent are fitted so that
slots at the two feeds ``reference_fz_mm`` (one tooth, a fresh tool, no runout) have exactly [D] eq. (9)'s
mean tangential and radial force (``calibration``). Elsewhere (other feeds, modes, depths) the plant
departs from the average law by what the average law approximates, which is what bench/first_part.py
measures.

Nothing here imports ``millsense.daemon``: this is the machine, not the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from millsense.sim.machine import Material, Tool

TWO_PI = 2 * math.pi


@dataclass(frozen=True)
class CutEffects:
    """The plant's cutting effects beyond [D]'s average model; each switchable on its own.

    Defaults and where they come from:

    - ``min_chip_mm`` 0.005: Kienzle's law is fitted for chips of about 0.05-1 mm; below a few µm its
      h^(−m_c) would grow without bound while a real edge (radius 5-20 µm) only ploughs, which the edge
      term carries. The coefficient is held at its value at h_min below it.
    - ``edge_tangential_n_mm`` K_te 20 N/mm, ``edge_radial_n_mm`` K_re 30 N/mm: the average-force method
      (Altintas ch. 2; Budak, Altintas & Armarego, J. Manuf. Sci. Eng. 118, 1996, who calibrate Ti6Al4V)
      gives edge coefficients of some tens of N/mm, K_re usually above K_te; for a steel no published table
      was verified here (physics.md §5b): the values are of that order, not one paper's figure.
    - ``runout_um`` 5 µm on tooth 0: a good shrink-fit or hydraulic holder keeps total indicated runout
      within 3-10 µm (holder makers' catalogues; Kline & DeVor, Int. J. Mach. Tool Des. Res. 23, 1983).
    - ``overhang_ratio`` 3 (L/D) and the tool's modulus (``Tool.youngs_gpa``: solid carbide 600, HSS
      210 GPa) with the fluted section's equivalent diameter 0.8·D (Kivanc & Budak, Int. J. Mach. Tools
      Manuf. 44, 2004): cantilever stiffness k = 3EI/L³, I = π(0.8D)⁴/64 (about 27 kN/mm for φ20
      carbide, 7.5 kN/mm for φ16 HSS, 11 kN/mm for φ8 carbide).
    - ``wear_edge_gain`` 0.25, ``wear_chip_gain`` 0.02: a flank wear land rubs on the cut surface, so
      wear grows the edge (ploughing) term most and the chip term little; at the end of its life the edge
      force is taken 1.25 × a sharp one's and the chip force 2 % higher, so a tool at 80 % of its life
      cuts with a few % more force (about 6 % in bench/first_part.py's worn cuts, more where the chip
      is thin).
    """

    size_effect: bool = True            # Kienzle at the instantaneous chip (False: at the average chip)
    min_chip_mm: float = 0.005          # h_min, mm
    edge_tangential_n_mm: float = 20.0  # K_te, N per mm of engaged edge
    edge_radial_n_mm: float = 30.0      # K_re, N per mm of engaged edge
    runout_um: float = 5.0              # ρ of tooth 0, µm (radially out)
    deflection: bool = True             # the engaged radial depth is ae − F_n/k (down, up milling)
    overhang_ratio: float = 3.0         # tool stick-out / diameter
    life_used: float = 0.0              # fraction of the tool's life used, 0..1
    wear_edge_gain: float = 0.25        # edge coefficients × (1 + gain·life_used)
    wear_chip_gain: float = 0.02        # chip coefficients × (1 + gain·life_used)
    reference_fz_mm: tuple[float, float] = (0.05, 0.2)  # the test slots the handbook's law holds at exactly
    sub_points: int = 4                 # angles per interval for the means over [θ, θ + Δθ]

    def __post_init__(self) -> None:
        for name in ("min_chip_mm", "edge_tangential_n_mm", "edge_radial_n_mm", "runout_um", "life_used",
                     "wear_edge_gain", "wear_chip_gain"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"CutEffects.{name} must be >= 0, not {getattr(self, name)!r}")
        if not 0.0 <= self.life_used <= 1.0:
            raise ValueError(f"CutEffects.life_used must be within 0..1, not {self.life_used!r}")
        if not (self.overhang_ratio > 0 and 0 < self.reference_fz_mm[0] < self.reference_fz_mm[1]):
            raise ValueError("CutEffects: overhang_ratio must be > 0 and reference_fz_mm two feeds, low then high")
        if self.sub_points < 1:
            raise ValueError("CutEffects.sub_points must be at least 1")


NONE = CutEffects(size_effect=False, edge_tangential_n_mm=0.0, edge_radial_n_mm=0.0, runout_um=0.0,
                  deflection=False)  # the element model with every effect off (tests: it must equal [D]'s)


def tool_stiffness_n_mm(tool: Tool, effects: CutEffects) -> float:
    """Cantilever stiffness at the tip, N/mm: k = 3·E·I/L³, I = π·(0.8·D)⁴/64, L = overhang·D."""
    d_eq = 0.8 * tool.diameter_mm
    inertia_mm4 = math.pi * d_eq**4 / 64.0
    length_mm = effects.overhang_ratio * tool.diameter_mm
    return 3.0 * tool.youngs_gpa * 1000.0 * inertia_mm4 / length_mm**3


def runout_offsets_mm(flutes: int, effects: CutEffects) -> np.ndarray:
    """ρ_k − ρ_(k+1) per tooth: tooth 0 stands ρ out; tooth k follows tooth k+1 (cutting.tooth_chip_factors),
    so tooth 0 cuts ρ more and tooth N−1, which follows it, ρ less."""
    out = np.zeros(flutes)
    rho = effects.runout_um * 1e-3
    if flutes >= 2 and rho > 0:
        out[0] += rho
        out[flutes - 1] -= rho
    return out


@dataclass(frozen=True)
class ChipLaw:
    """The element model's chip term (the edge term is added apart):
    dF_t = c_t·k_s·max(h, h_min)^q_t·h·dz,  dF_r = c_r·r₁·max(h, h_min)^q_r·dF_t."""

    c_t: float
    q_t: float  # −m_c of the chip term alone (Kienzle)
    c_r: float
    q_r: float


def _slot_means(fz: float, law: ChipLaw, material: Material, effects: CutEffects) -> tuple[float, float]:
    """Mean tangential and radial chip force per unit depth of one tooth over a revolution of a slot."""
    phi = (np.arange(2000) + 0.5) * math.pi / 2000
    h = fz * np.sin(phi)
    h_c = np.maximum(h, effects.min_chip_mm)
    ft = law.c_t * material.ks * h_c**law.q_t * h
    fr = law.c_r * material.r1 * h_c**law.q_r * ft
    return float(ft.mean()) / 2.0, float(fr.mean()) / 2.0  # engaged over [0, π], half the revolution


def _root(f, lo: float, hi: float, xtol: float = 1e-12) -> float:
    """The root of `f` between `lo` and `hi`, where its sign changes, by bisection to `xtol`.

    Not scipy.optimize's brentq: its import (0.4 CPU s) came at a plant's first tool change, in the middle of
    an emulator's stream, and on a loaded box held the samples back past the daemon's 1-s stall check (the
    DAQ's watchdog then held the feed: a live first-part test that never saw its cut). Some 40 halvings of a
    ~2-wide bracket, a few milliseconds a tool change."""
    f_lo = f(lo)
    if f_lo * f(hi) > 0:
        raise ValueError(f"no sign change over [{lo}, {hi}]")
    while hi - lo > xtol:
        mid = 0.5 * (lo + hi)
        f_mid = f(mid)
        if f_mid == 0.0:
            return mid
        if (f_mid > 0) == (f_lo > 0):
            lo, f_lo = mid, f_mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def calibration(material: Material, effects: CutEffects) -> ChipLaw:
    """The chip term fitted so that a slot's mean forces are [D] eq. (9)'s at both reference feeds.

    A handbook's law is identified from the average forces of test cuts over a range of feeds, edge forces
    and all; the mechanistic model splits the same forces into an edge term and a chip term (Altintas
    ch. 2, the linear edge-force identification). So with the edge coefficients given, the chip term's
    scale and exponent (c_t, q_t; c_r, q_r for the radial) are those that reproduce the law's mean forces
    of one tooth over [0, π] at the two ``reference_fz_mm`` (sharp, no runout): t_a = 2f_z/π ([D] eq. 8),
    mean F_t = k_s·t_a^ks_exp·f_z/π, mean F_r = r₁(t_a)·F_t; the edge adds K_te/2, K_re/2. Without
    ``size_effect`` the chip term keeps the law's coefficients at the average chip (q = 0 here, as in
    cutting.py) and only the scale is fitted (at the references' geometric mean)."""
    fzs = effects.reference_fz_mm
    e_t, e_r = effects.edge_tangential_n_mm / 2.0, effects.edge_radial_n_mm / 2.0

    def law(fz: float) -> tuple[float, float]:
        t_a = 2.0 * fz / math.pi
        f_t = material.ks * t_a**material.ks_exp * fz / math.pi
        return f_t, material.r1 * t_a**material.r1_exp * f_t

    if not effects.size_effect:
        fz = math.sqrt(fzs[0] * fzs[1])
        f_t, f_r = law(fz)
        c_t = (f_t - e_t) / f_t
        c_r = (f_r - e_r) / (c_t * f_r)
        if c_t <= 0 or c_r <= 0:
            raise ValueError(f"CutEffects: the edge forces alone exceed {material.name}'s law; lower K_te/K_re")
        return ChipLaw(c_t, 0.0, c_r, 0.0)  # scales on the law at each tooth's t_a (effect_forces)
    (t1, r1), (t2, r2) = law(fzs[0]), law(fzs[1])
    if min(t1 - e_t, t2 - e_t, r1 - e_r, r2 - e_r) <= 0:
        raise ValueError(f"CutEffects: the edge forces alone exceed {material.name}'s law at a reference "
                         f"feed {fzs} mm; lower K_te/K_re")

    def fit_t(q: float) -> float:
        m1, _ = _slot_means(fzs[0], ChipLaw(1.0, q, 1.0, 0.0), material, effects)
        m2, _ = _slot_means(fzs[1], ChipLaw(1.0, q, 1.0, 0.0), material, effects)
        return math.log(m1 / m2) - math.log((t1 - e_t) / (t2 - e_t))

    q_t = _root(fit_t, -0.95, 1.0)
    c_t = (t1 - e_t) / _slot_means(fzs[0], ChipLaw(1.0, q_t, 1.0, 0.0), material, effects)[0]

    def radial(q: float, fz: float) -> float:
        return _slot_means(fz, ChipLaw(c_t, q_t, 1.0, q), material, effects)[1]

    q_r = _root(lambda q: math.log(radial(q, fzs[0]) / radial(q, fzs[1])) - math.log((r1 - e_r) / (r2 - e_r)),
                -0.95, 1.0)
    c_r = (r1 - e_r) / radial(q_r, fzs[0])
    return ChipLaw(float(c_t), float(q_t), float(c_r), float(q_r))


def effect_forces(geom, theta_rad, position_mm, feed_per_tooth_mm, chip_factors, dtheta_rad=0.0):
    """``cutting_forces`` with the geometry's ``effects``: the same outputs (tool frame, N)."""
    from millsense.sim.cutting import _edge_depth_mm, engagement_rad  # noqa: PLC0415 (cutting imports this module)

    eff: CutEffects = geom.effects
    tool, mat = geom.tool, geom.material
    theta = np.asarray(theta_rad, dtype=float)
    n = theta.shape[0]
    pos = np.asarray(position_mm, dtype=float)
    tc = np.maximum(np.asarray(feed_per_tooth_mm, dtype=float), 0.0)
    m = np.broadcast_to(np.asarray(chip_factors, dtype=float), (n, tool.flutes))
    span = np.broadcast_to(np.asarray(dtheta_rad, dtype=float), (n,))
    s = eff.sub_points if np.any(span > 0) else 1
    # the mean over [θ, θ + Δθ] by the midpoints of s equal parts (the element model has no closed form)
    frac = (np.arange(s) + 0.5) / s if s > 1 else np.zeros(1)
    th = (theta[:, None] + span[:, None] * frac).ravel()
    rows = np.repeat(np.arange(n), s)
    radial = geom.radial_depth_mm(pos)
    forces = _element_forces(geom, th, pos[rows], tc[rows], m[rows], radial[rows], eff, _edge_depth_mm,
                             engagement_rad)
    if eff.deflection and geom.mode in ("down", "up"):
        # quasi-static: the tool's first bending mode (kHz) is far above the tooth frequency, so the tool
        # stands where the force at this instant puts it, F_n/k off the wall: down milling pushes it away
        # (the cut loses radial depth, an undercut), up milling pulls it in (an overcut), the classic
        # surface-error result (Kline & DeVor 1983; Altintas ch. 2)
        sign = -1.0 if geom.mode == "down" else 1.0  # the wall: down at y = −R, up at y = +R
        away_mm = sign * forces["fy_n"] / geom.stiffness_n_mm  # > 0: the tool bent away from the wall
        ae_mm = np.clip(radial[rows] - away_mm, 0.0, tool.diameter_mm)
        forces = _element_forces(geom, th, pos[rows], tc[rows], m[rows], ae_mm, eff, _edge_depth_mm, engagement_rad)
        forces["deflection_mm"] = sign * forces["fy_n"] / geom.stiffness_n_mm
    return {k: v.reshape(n, s).mean(axis=1) for k, v in forces.items()}


def _element_forces(geom, theta, pos, tc, m, radial_mm, eff: CutEffects, edge_depth, engagement):
    tool, mat = geom.tool, geom.material
    entry, exit_ = engagement(radial_mm, tool.radius_mm, geom.mode)
    phi = np.mod(theta[:, None, None] + geom.tooth_rad[None, :, None] - geom.lag_rad[None, None, :], TWO_PI)
    sin_phi, cos_phi = np.sin(phi), np.cos(phi)
    in_cut = (phi >= entry[:, None, None]) & (phi <= exit_[:, None, None])
    depth = edge_depth(geom, pos, sin_phi)
    weight = np.clip((depth - geom.z_low_mm) / geom.dz_mm, 0.0, 1.0) * geom.dz_mm  # engaged length of the slice
    offset = (geom.runout_mm * (m > 0))[:, :, None]
    h = np.where(in_cut, m[:, :, None] * tc[:, None, None] * sin_phi + offset, 0.0)
    h = np.maximum(h, 0.0)
    touching = h > 0.0
    life = eff.life_used
    chip_gain, edge_gain = 1.0 + eff.wear_chip_gain * life, 1.0 + eff.wear_edge_gain * life
    law: ChipLaw = geom.chip_law
    if eff.size_effect:  # Kienzle at the instantaneous chip
        h_c = np.maximum(h, eff.min_chip_mm)
        ft_chip = law.c_t * mat.ks * h_c**law.q_t * h
        r1 = law.c_r * mat.r1 * h_c**law.q_r
        r2 = mat.r2 * h_c**mat.r2_exp
    else:  # [D] eq. (9) at each tooth's average chip, as cutting.py without effects
        from millsense.sim.cutting import average_chip_mm  # noqa: PLC0415

        ta = np.maximum(average_chip_mm(tc, entry, exit_)[:, None] * np.maximum(m, 1.0), 1e-6)[:, :, None]
        ft_chip = law.c_t * mat.ks * ta**mat.ks_exp * h
        r1, r2 = law.c_r * mat.r1 * ta**mat.r1_exp, mat.r2 * ta**mat.r2_exp
    ft_chip = chip_gain * ft_chip * weight
    d_ft = ft_chip + np.where(touching, edge_gain * eff.edge_tangential_n_mm, 0.0) * weight
    d_fr = r1 * ft_chip + np.where(touching, edge_gain * eff.edge_radial_n_mm, 0.0) * weight
    d_fa = r2 * ft_chip
    # [D] eqs. (2)-(4): x along the feed, y across it
    fx = (d_ft * cos_phi + d_fr * sin_phi).sum(axis=(1, 2))
    fy = (-d_ft * sin_phi + d_fr * cos_phi).sum(axis=(1, 2))
    return {"fx_n": fx, "fy_n": fy, "fz_n": d_fa.sum(axis=(1, 2)), "ft_n": d_ft.sum(axis=(1, 2))}


def material_batch(material: Material, effects: CutEffects | None, offset_pct: float):
    """(material, effects) of a batch ``offset_pct`` % off the handbook's: K_s and the edge forces alike, so a
    batch 20 % harder cuts with 20 % more force in every cut (the daemon's config keeps the handbook's)."""
    if not -90.0 < offset_pct <= 500.0:
        raise ValueError(f"material offset {offset_pct:g} %: expected more than -90 and at most 500")
    k = 1.0 + offset_pct / 100.0
    if k == 1.0:
        return material, effects
    material = replace(material, ks=material.ks * k)
    if effects is not None:
        effects = replace(effects, edge_tangential_n_mm=effects.edge_tangential_n_mm * k,
                          edge_radial_n_mm=effects.edge_radial_n_mm * k)
    return material, effects
