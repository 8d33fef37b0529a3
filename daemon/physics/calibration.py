"""Least-squares calibration of friction and C_f ([P] §4.2, Table 2; eq. 13, eq. 18).

Friction, per gear: with the cutting torque known (0 in an air cut, a
dynamometer's value in a trial cut), eq. (13) rearranges into a straight line in
the spindle speed,

    P_g/ω_sp − T_c = T_f' + B'·ω_sp,

fitted by linear least squares on ``[1, ω_sp]``. At least two distinct speeds are
needed for a line. C_f: eq. (18) is a line through the origin, ``F_res = C_f·(T_c/R)``.

Inertia, per gear (beyond [P], whose eq. 13 assumes a steady speed): in an air
cut whose speed changes, what the friction line leaves over is the rotating
masses' share, ``P_g/ω_sp − T_f' − B'·ω_sp = J·dω_sp/dt``, per revolution
``J·Δω/Δt`` — a line through the origin in the revolution's acceleration, fitted
by least squares. Only revolutions that speed up or slow down tell anything
about J; a capture without them cannot fit it.

Judging a fit (``judge_*``): least squares always returns numbers, even from a
capture that cannot determine them (a cut at one speed gave T_f' = 3994 N·m,
B' = −63). Each judge returns `Refusal`s — the gear, what is wrong in numbers,
and the capture that would fix it — and the caller writes nothing while any
stands. One mechanism for friction, inertia and the air check alike.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from millsense.daemon.physics.force import tangential_force_n


class FrictionFit(NamedTuple):
    friction_torque_nm: float  # T_f', referred to the spindle
    viscous_nms: float  # B', N·m·s/rad, referred to the spindle
    r2: float  # coefficient of determination (nan if the load does not vary)
    residuals_nm: np.ndarray  # measured − fitted load torque, per sample
    samples: int


class InertiaFit(NamedTuple):
    inertia_kgm2: float  # J referred to the spindle
    sigma_kgm2: float  # standard error of J
    r2: float  # uncentred: share of the left-over torque the J·α line explains
    residuals_nm: np.ndarray
    samples: int  # revolutions in the fit
    changing: int  # of which with |α| at or over the minimum


class Refusal(NamedTuple):
    gear: str
    problem: str  # what is wrong, with the numbers that show it
    record: str  # the capture that would fix it

    def __str__(self) -> str:
        return f"gear {self.gear}: {self.problem}; record {self.record}"


# Friction: a line needs speeds far enough apart to separate T_f' from B'·ω. Speeds closer than
# DISTINCT_SPEED_REL are one speed (a held speed wanders < 0.1 %; the aircut scenarios step 12–50 %).
MIN_SPEEDS = 3
DISTINCT_SPEED_REL = 0.05
MIN_REVS_PER_SPEED = 3
# Residual RMS against the mean friction torque the line explains, not R²: in the high gear B'·ω
# spans ~0.3 N·m of a 2 N·m friction, so scatter that R² calls "R² ≈ 0" is still a fine fit. The
# simulated air cuts leave 0.1–0.3 %; a real spindle's friction drifts a few % as it warms within a
# capture. Over 5 %, the captures hold something other than friction (a cut, a crash, a bad gear).
RESIDUAL_REL_MAX = 0.05
# Inertia: J's standard error over 10 % of J says the run-ups do not determine it.
J_REL_SIGMA_MAX = 0.1
# Air check: cutting only ever adds torque, so in a settled air plateau every revolution sits on the
# plateau's floor (its 10th percentile: robust to a few low transients, and an air capture spends more
# than a tenth of each plateau in air). Simulated air plateaus stay within 0.6 % of their floor; a
# 1 mm slot adds 40 %. A revolution more than CUT_REL (at least CUT_FLOOR_NM, ~5 per-revolution noise
# sd) above the floor is load; CUT_MIN_REVS of them in a plateau are a cut, not a glitch.
AIR_FLOOR_PCT = 10.0
CUT_REL = 0.10
CUT_FLOOR_NM = 0.05
CUT_MIN_REVS = 3


def speed_levels_rpm(rpm) -> list[tuple[float, int]]:
    """Distinct held speeds: (median rpm, revolutions), speeds within DISTINCT_SPEED_REL joined."""
    speeds = np.sort(np.asarray(rpm, dtype=float).ravel())
    levels: list[list[float]] = []
    for s in speeds:
        if levels and s - levels[-1][-1] <= DISTINCT_SPEED_REL * levels[-1][-1]:
            levels[-1].append(s)
        else:
            levels.append([s])
    return [(float(np.median(lv)), len(lv)) for lv in levels]


def air_cut_advice(range_rpm: tuple[float, float]) -> str:
    lo, hi = range_rpm
    return (f"an air cut (nothing in contact) at >= {MIN_SPEEDS} speeds across {lo:.0f}-{hi:.0f} rpm, "
            f"each held 2 s or more")


def judge_speeds(gear: str, steady_rpm, range_rpm: tuple[float, float]) -> list[Refusal]:
    """Refused unless MIN_SPEEDS distinct speeds each have MIN_REVS_PER_SPEED steady revolutions."""
    held = [(s, n) for s, n in speed_levels_rpm(steady_rpm) if n >= MIN_REVS_PER_SPEED]
    if len(held) >= MIN_SPEEDS:
        return []
    listed = ", ".join(f"{s:.0f}" for s, _ in held) or "none held"
    return [Refusal(gear, f"only {len(held)} steady speed{'' if len(held) == 1 else 's'} ({listed} rpm), "
                          f"{MIN_SPEEDS} needed to fit T_f' + B'·w", air_cut_advice(range_rpm))]


def judge_friction(gear: str, spindle_omega_rad_s, fit: FrictionFit, range_rpm: tuple[float, float]) -> list[Refusal]:
    """Negative terms (no physical friction), or residuals large against the friction they explain."""
    out = []
    if fit.friction_torque_nm < 0.0 or fit.viscous_nms < 0.0:
        out.append(Refusal(gear, f"negative friction (T_f' = {fit.friction_torque_nm:.4g} N·m, "
                                 f"B' = {fit.viscous_nms:.4g} N·m·s/rad): physically impossible",
                           air_cut_advice(range_rpm)))
        return out   # the residual ratio means nothing against a negative line
    omega = np.asarray(spindle_omega_rad_s, dtype=float)
    mean_friction_nm = float(np.mean(fit.friction_torque_nm + fit.viscous_nms * omega))
    rms_nm = float(np.sqrt(np.mean(np.asarray(fit.residuals_nm) ** 2)))
    if not mean_friction_nm > 0.0 or rms_nm > RESIDUAL_REL_MAX * mean_friction_nm:
        out.append(Refusal(gear, f"residuals rms {rms_nm:.3g} N·m against a mean friction torque of "
                                 f"{mean_friction_nm:.3g} N·m (limit {RESIDUAL_REL_MAX:.0%}): not a friction line",
                           air_cut_advice(range_rpm) + ", with the spindle warmed up"))
    return out


def judge_inertia(gear: str, fit: InertiaFit, run_up: str) -> list[Refusal]:
    """A J that is not positive, or not determined to J_REL_SIGMA_MAX, says the run-ups are wrong."""
    if fit.inertia_kgm2 > 0.0 and fit.sigma_kgm2 <= J_REL_SIGMA_MAX * abs(fit.inertia_kgm2):
        return []
    return [Refusal(gear, f"inertia J = {fit.inertia_kgm2:.4g} +/- {fit.sigma_kgm2:.2g} kg·m²: negative or not "
                          f"determined to {J_REL_SIGMA_MAX:.0%}", run_up)]


def judge_air(gear: str, plateaus, range_rpm: tuple[float, float]) -> list[Refusal]:
    """Cutting in an air capture. `plateaus`: (rpm, load torques) of each settled constant-speed stretch."""
    found = []
    for rpm, load in plateaus:
        load = np.asarray(load, dtype=float)
        if load.size < CUT_MIN_REVS:
            continue
        floor_nm = float(np.percentile(load, AIR_FLOOR_PCT))
        above = load - floor_nm > max(CUT_REL * abs(floor_nm), CUT_FLOOR_NM)
        if int(np.count_nonzero(above)) >= CUT_MIN_REVS:
            found.append(f"{int(np.count_nonzero(above))} of {load.size} revolutions at {rpm:.0f} rpm up to "
                         f"{float(np.max(load)) - floor_nm:.3g} N·m above the air level {floor_nm:.3g} N·m")
    if not found:
        return []
    return [Refusal(gear, "cutting found in an air capture (" + "; ".join(found) + ")",
                    air_cut_advice(range_rpm) + ", with the tool clear of the part (or trial cuts with "
                    "force channels and --dynamometer)")]


class CfFit(NamedTuple):
    cf: float
    residuals_n: np.ndarray  # measured − fitted resultant force, per sample
    r2: float
    samples: int


def _finite_pair(x, y, what: str) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    if x.shape != y.shape:
        raise ValueError(f"{what}: {x.size} speeds/torques but {y.size} values; they must pair up")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise ValueError(f"{what}: inputs contain nan or inf")
    return x, y


def _r2(y: np.ndarray, residuals: np.ndarray) -> float:
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    return 1.0 - float(np.sum(residuals**2)) / ss_tot if ss_tot > 0.0 else float("nan")


def fit_friction(spindle_omega_rad_s, load_torque_nm) -> FrictionFit:
    """T_f' and B' from ``load_torque_nm = P_g/ω_sp − T_c`` at several spindle speeds ([P] eq. 13).

    Raises ValueError unless there are at least two distinct speeds (relative spread > 1e-6).
    """
    omega, load = _finite_pair(spindle_omega_rad_s, load_torque_nm, "fit_friction")
    if omega.size < 2 or np.ptp(omega) <= 1e-6 * max(float(np.max(np.abs(omega))), 1e-12):
        raise ValueError("fit_friction: needs samples at two or more distinct spindle speeds to fit T_f' + B'·ω")
    design = np.column_stack([np.ones_like(omega), omega])
    (t_f, b), *_ = np.linalg.lstsq(design, load, rcond=None)
    residuals = load - design @ np.array([t_f, b])
    return FrictionFit(float(t_f), float(b), _r2(load, residuals), residuals, int(omega.size))


def fit_inertia(accel_rad_s2, inertia_torque_nm, min_accel_rad_s2: float = 5.0, min_changing: int = 3) -> InertiaFit:
    """J from ``inertia_torque_nm ≈ J·accel_rad_s2`` per revolution, least squares through the origin.

    ``inertia_torque_nm``: P_g/ω_sp less the friction line (T_c = 0, an air cut).
    Raises ValueError when fewer than ``min_changing`` revolutions change speed at
    ``min_accel_rad_s2`` or more (above the speed reading's noise, ~0.6 rad/s² at
    900 rpm): the fit would be noise. A negative or poorly determined J is the
    caller's to judge (sigma_kgm2).
    """
    accel, torque = _finite_pair(accel_rad_s2, inertia_torque_nm, "fit_inertia")
    changing = int(np.count_nonzero(np.abs(accel) >= min_accel_rad_s2))
    if changing < min_changing:
        raise ValueError(f"fit_inertia: {changing} revolutions change speed by {min_accel_rad_s2:g} rad/s² or more, "
                         f"{min_changing} needed: the capture has no speed change to fit J to")
    sxx = float(np.dot(accel, accel))
    j = float(np.dot(accel, torque)) / sxx
    residuals = torque - j * accel
    dof = max(accel.size - 1, 1)
    sigma = float(np.sqrt(float(np.dot(residuals, residuals)) / dof / sxx))
    syy = float(np.dot(torque, torque))
    r2 = 1.0 - float(np.dot(residuals, residuals)) / syy if syy > 0.0 else float("nan")
    return InertiaFit(j, sigma, r2, residuals, int(accel.size), changing)


def fit_cf(mean_resultant_force_n, torque_nm, tool_radius_mm: float) -> CfFit:
    """C_f of eq. (18) by least squares through the origin: ``F_res ≈ C_f·T_c/R``.

    r² is the usual centred one (1 − SS_res/SS_tot), nan when the forces do not vary.
    """
    force, torque = _finite_pair(mean_resultant_force_n, torque_nm, "fit_cf")
    x = tangential_force_n(torque, tool_radius_mm)
    sxx = float(np.dot(x, x))
    if sxx <= 0.0:
        raise ValueError("fit_cf: needs at least one revolution with non-zero cutting torque")
    cf = float(np.dot(x, force)) / sxx
    residuals = force - cf * x
    return CfFit(cf, residuals, _r2(force, residuals), int(force.size))


# ----------------------------------------------------------------------------- the material of a test cut
# K_s = k·t_a^p ([D] eq. 9) from the steady torque of a cut with known a_e, a_p and feed per tooth: eq. (7)'s
# F_at = (N/2π)·K_s(t_a)·t_c·d_a·c, with F_at = T_c/R ([P] eq. 16), solved for K_s at the cut's t_a (eq. 8).
# Several feeds give K_s at several chips: log K_s = log k + p·log t_a, a line (least squares). One feed gives
# K_s at one chip only: p is borrowed (the nearest ISO group's −m_c) and k = K_s/t_a^p.
MATERIAL_MIN_REVS = 8          # steady revolutions a feed level needs (its median torque; tooth ripple averaged)
MATERIAL_MIN_CHIP_RATIO = 1.25  # feed levels whose chips span less than this give one K_s, not a slope
# A level's torque at least this: docs/accuracy.md's steady torque budget is 2 % + 0.03 N·m, the 0.03 N·m
# being what noise (eq. 20) and friction leave in air; at 1.5 N·m that floor is 2 % more of K_s, beyond
# which a level says more about the floor than the material. (σ_T of a revolution is no floor in a cut:
# it carries the tooth ripple, 0.483·T/√samples, docs/accuracy.md.)
MATERIAL_MIN_TORQUE_NM = 1.5
MATERIAL_EXP_RANGE = (-0.8, 0.0)  # p of every published law: m_c 0.14–0.45 (tool-makers' tables), [D] −0.44


class MaterialFit(NamedTuple):
    ks: float                  # k of [D] eq. 9, N/mm² at t_a = 1 mm
    ks_exp: float              # p
    levels: int                # feed levels (distinct chips) used
    chips_mm: np.ndarray       # t_a of each level
    ks_n_mm2: np.ndarray       # K_s measured at each level
    residuals_rel: np.ndarray  # K_s measured / fitted − 1, per level
    exp_borrowed: bool         # True: one level, p given


def specific_force_from_torque(torque_nm, feed_per_tooth_mm, radial_ratio, axial_depth_mm, tool_radius_mm: float,
                               flutes: int, mode: str):
    """(t_a in mm, K_s in N/mm²) of a cut from its mean cutting torque: [D] eqs. 7–8 with [P] eq. 16 solved for K_s.

    ``K_s = 2π·T_c / (R·N·t_c·d_a·c)``, R in metres for T_c/R (N), c = cos θ₁ − cos θ₂ of the engagement.
    """
    from millsense.daemon.physics.milling import average_chip_thickness_mm, engagement_angles_rad

    entry, exit_ = engagement_angles_rad(radial_ratio, mode)
    c = np.cos(entry) - np.cos(exit_)
    t_c = np.asarray(feed_per_tooth_mm, dtype=float)
    tangential_n = np.asarray(torque_nm, dtype=float) / (tool_radius_mm * 1e-3)             # [P] eq. 16
    ks = 2.0 * np.pi * tangential_n / (flutes * t_c * axial_depth_mm * c)                    # [D] eq. 7
    return average_chip_thickness_mm(t_c, entry, exit_), ks                                  # [D] eq. 8


def fit_material(chips_mm, ks_n_mm2, borrowed_exp: float | None = None) -> MaterialFit:
    """k, p of K_s = k·t_a^p from K_s measured at chips t_a (one per feed level).

    Two or more chips: least squares on log K_s = log k + p·log t_a. One chip: p = ``borrowed_exp`` (required).
    """
    t = np.asarray(chips_mm, dtype=float).ravel()
    ks = np.asarray(ks_n_mm2, dtype=float).ravel()
    if t.size == 0 or t.size != ks.size or not (np.all(t > 0) and np.all(ks > 0)):
        raise ValueError("fit_material: needs positive chips and K_s, one each per feed level")
    if t.size == 1:
        if borrowed_exp is None:
            raise ValueError("fit_material: one feed level fixes K_s at one chip only; give the exponent")
        p = float(borrowed_exp)
        k = float(ks[0] / t[0] ** p)
    else:
        design = np.column_stack([np.ones_like(t), np.log(t)])
        (log_k, p), *_ = np.linalg.lstsq(design, np.log(ks), rcond=None)
        k, p = float(np.exp(log_k)), float(p)
    residuals = ks / (k * t**p) - 1.0
    return MaterialFit(k, p, int(t.size), t, ks, residuals, t.size == 1)


# ----------------------------------------------------------------------------- r₁ from the feed-drive force
# [D] eq. (12): f_xt = F_ax/F_at = (a + r₁·b)/c at the test cut's engagement (a, b, c of eq. 4), so the feed-drive
# force over the spindle's tangential force gives r₁ at the cut's chip: r₁ = (f_xt·c − a)/b (b > 0 over any
# arc). The torque cannot see r₁; the feed-direction force can, and it is what the `feed-drive` depth method
# inverts, so a law fitted here is the law that method needs. Levels as for K_s: several chips fit r1 and r1_exp
# (log r₁ = log r1 + q·log t_a), one chip fits r1 with the configuration's exponent.
# r₁ grows as the chip thins (the edge's rubbing weighs more: [D] Table 2's q = −0.2667); a slope outside
# this range says the levels hold something besides the material's radial law (a sign or scale of the
# feed-force channel, a wrong engagement). The upper end allows 0.1 above a law with no size effect.
RADIAL_EXP_RANGE = (-0.8, 0.1)


def radial_ratio_from_feed_force(feed_force_n, torque_nm, radial_ratio, tool_radius_mm: float, mode: str):
    """r₁ of [D] eq. (9) at a cut from its mean feed-drive force and cutting torque: eq. (12) solved for r₁.

    ``r₁ = (f_xt·c − a)/b`` with ``f_xt = F_feed/F_at``, ``F_at = T_c/R`` ([P] eq. 16); a, b, c of eq. (4).
    """
    from millsense.daemon.physics.milling import NP, _integrals_xp, engagement_angles_rad

    entry, exit_ = engagement_angles_rad(radial_ratio, mode)
    a, b, c = _integrals_xp(NP, entry, exit_)
    tangential_n = np.asarray(torque_nm, dtype=float) / (tool_radius_mm * 1e-3)              # [P] eq. 16
    f_xt = np.asarray(feed_force_n, dtype=float) / tangential_n                             # [D] eq. 12
    return (f_xt * c - a) / b


class RadialFit(NamedTuple):
    r1: float                  # k₁ of [D] eq. 9, r₁ at t_a = 1 mm
    r1_exp: float              # q
    levels: int
    chips_mm: np.ndarray
    r1_measured: np.ndarray    # r₁ at each level
    residuals_rel: np.ndarray  # measured / fitted − 1, per level
    exp_borrowed: bool         # True: one level, q given


def _power_law(t: np.ndarray, y: np.ndarray, borrowed_exp: float | None) -> tuple[float, float]:
    """(scale, exponent) of y = scale·t^exponent: least squares in logs, or the exponent given (one point)."""
    if t.size == 1:
        return float(y[0] / t[0] ** borrowed_exp), float(borrowed_exp)
    design = np.column_stack([np.ones_like(t), np.log(t)])
    (log_k, p), *_ = np.linalg.lstsq(design, np.log(y), rcond=None)
    return float(np.exp(log_k)), float(p)


def fit_radial_ratio(chips_mm, r1_measured, borrowed_exp: float | None = None) -> RadialFit:
    """r1, q of r₁ = r1·t_a^q ([D] eq. 9) from r₁ measured at chips t_a (one per feed level).

    Raises ValueError unless every r₁ is positive (a feed-drive force of the wrong sign for the milling mode
    gives a negative one: no radial law can), or for one level without ``borrowed_exp``.
    """
    t = np.asarray(chips_mm, dtype=float).ravel()
    r1 = np.asarray(r1_measured, dtype=float).ravel()
    if t.size == 0 or t.size != r1.size or not np.all(t > 0):
        raise ValueError("fit_radial_ratio: needs positive chips, one r1 per feed level")
    if not np.all(r1 > 0):
        raise ValueError("fit_radial_ratio: r1 = " + ", ".join(f"{x:.3g}" for x in r1) + " at the feed levels: "
                         "not positive, so the feed-drive force does not fit this engagement and milling mode")
    if t.size == 1 and borrowed_exp is None:
        raise ValueError("fit_radial_ratio: one feed level fixes r1 at one chip only; give the exponent")
    k, q = _power_law(t, r1, borrowed_exp)
    return RadialFit(k, q, int(t.size), t, r1, r1 / (k * t**q) - 1.0, t.size == 1)


def judge_radial(fit: RadialFit, record: str) -> list[Refusal]:
    """A slope outside RADIAL_EXP_RANGE says the levels hold something besides the material's radial law."""
    lo, hi = RADIAL_EXP_RANGE
    if fit.exp_borrowed or lo <= fit.r1_exp <= hi:
        return []
    return [Refusal("material", f"r1 = {fit.r1:.4g}·t_a^{fit.r1_exp:.3f} from the feed-drive force: an exponent "
                                f"outside {lo}…{hi}: the feed levels do not follow one radial law (check the "
                                f"feed-force channel's newton_per_amp and friction_n, and the milling mode)", record)]


def judge_material(fit: MaterialFit, record: str) -> list[Refusal]:
    """A slope outside every published law's range says the levels hold something besides the material."""
    lo, hi = MATERIAL_EXP_RANGE
    if fit.exp_borrowed or lo <= fit.ks_exp <= hi:
        return []
    return [Refusal("material", f"K_s = {fit.ks:.4g}·t_a^{fit.ks_exp:.3f}: an exponent outside {lo}…{hi} "
                                f"(published m_c 0.14–0.45): the feed levels do not follow one material law",
                    record)]
