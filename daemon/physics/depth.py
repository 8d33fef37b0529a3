"""Depth of cut from average forces by exact root finding ([D] §3, eqs. 10, 12, 13).

[D] fits a polynomial to invert eq. (10) (its Table 3, see ``table3.py``). Here
the 1-D equation ``g(R_r) = measured ratio`` is solved exactly with Brent's
method (``bracketed_root`` below) on brackets that are known to hold one root:

1. The model curve ``g`` over the model's domain ``[MIN_RADIAL_RATIO, 2]`` is cut
   into monotone branches at its extrema (found on a grid, then refined).
2. Each branch whose end values straddle the target holds exactly one root.
3. No root: ``out_of_range``; one: ``ok``; more than one: ``unresolvable`` —
   the measurement fits two immersions and picking one would be a guess.

The branch structure depends only on (function, t_c, material, mode, tool), so
it is cached: in steady cutting the feed per tooth repeats and a solve is one
``bracketed_root`` call.

Down milling: ``f_xt`` is strictly increasing; ``f_x`` turns over at R_r ≈
0.012–0.02, so the small-immersion end of ``f_x`` is ``unresolvable``. Up
milling: both ratios rise then fall, so a large part of their range is
ambiguous — the physics, not the solver. Slot: R_r = 2 by definition.

Statuses (``interfaces.md`` ``depth_status``): ``ok``, ``air_cut``,
``no_second_force``, ``out_of_range``, ``unresolvable``.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Callable, NamedTuple

import numpy as np
from millsense.daemon.physics.edge import feed_cell, has_edge, split_fxt
from millsense.daemon.physics.milling import (
    NP,
    SCALAR,
    Material,
    _integrals_xp,
    _ratios_xp,
    _tangential_per_axial_ratio_xp,
    average_forces_n,
    check_mode,
    chip_xp,
    engagement_xp,
)

OK = "ok"
AIR_CUT = "air_cut"
NO_SECOND_FORCE = "no_second_force"
OUT_OF_RANGE = "out_of_range"
END_ULPS = 64  # how far (in units of the last place) a target may lie past a branch end and still be that end
UNRESOLVABLE = "unresolvable"

# Smallest radial immersion the model is asked to explain: 1 % of the radius
# (0.08 mm on a φ16 tool). Below it the average chip is a few µm, thinner than a
# cutting-edge radius, and the power laws of eq. (9) are pure extrapolation.
# The floor matters for f_x: its falling branch below the turn-over (R_r ≈ 0.012–0.02)
# repeats the values of the rising branch up to R_r ≈ 0.015–0.036 (t_c 0.7–0.01 mm);
# those are reported ``unresolvable``. (With a 0.1 % floor the ambiguous band would
# reach R_r ≈ 0.07–0.14.)
MIN_RADIAL_RATIO = 1e-2
MAX_RADIAL_RATIO = 2.0

# Grid for locating extrema: log-spaced at the small end, dense again near 2,
# where up milling's exit angle arccos(1 − R_r) has an infinite slope.
# (sorted and de-duplicated by hand: np.unique imports numpy.ma, 0.3 MB of the daemon's memory)
_GRID = np.sort(
    np.concatenate(
        [
            np.geomspace(MIN_RADIAL_RATIO, 1.0, 60),
            MAX_RADIAL_RATIO - np.geomspace(1e-6, 1.0, 40),
            [MAX_RADIAL_RATIO],
        ]
    )
)
_GRID = _GRID[np.concatenate(([True], _GRID[1:] != _GRID[:-1]))]


class DepthResult(NamedTuple):
    """Estimated depths in mm (None where unknown) and a status string."""

    radial_depth_mm: float | None
    axial_depth_mm: float | None
    status: str


class _Branch(NamedTuple):
    r_lo: float
    r_hi: float
    g_lo: float
    g_hi: float


# --- the root finder ----------------------------------------------------------------------


def bracketed_root(f: Callable[[float], float], a: float, b: float, *, xtol: float = 2e-12,
                   rtol: float = 4 * np.finfo(float).eps, maxiter: int = 100) -> float:
    """A root of ``f`` in [a, b], where f(a) and f(b) differ in sign: Brent's method.

    Written here so that the daemon does not import ``scipy.optimize`` (45 MB of
    RSS and 0.4 s of start-up for this one call). The method (R. P. Brent,
    *Algorithms for Minimization without Derivatives*, 1973, ch. 4): keep a
    bracket [x, x_blk] with a sign change, x the end with the smaller |f|; try an
    inverse quadratic interpolation through the last three points (a secant step
    when only two are distinct); take the step only if it lands well inside the
    bracket and shrinks faster than the step before last, else bisect. So it
    never does worse than bisection and converges superlinearly on smooth f.
    Stops when the bracket's half-width is below (xtol + rtol·|x|)/2, the same
    tolerance as ``scipy.optimize.brentq`` (tests compare the two).

    Scalar on purpose: each revolution solves one root on plain floats (the
    ``SCALAR`` kernels); numpy on one-element arrays costs several times more per
    evaluation than the whole math-module evaluation.
    """
    x_prev, x = float(a), float(b)
    f_prev, fx = f(x_prev), f(x)
    if f_prev == 0.0:
        return x_prev
    if fx == 0.0:
        return x
    if f_prev * fx > 0.0:
        raise ValueError(f"no sign change of f over [{a}, {b}]")
    x_blk, f_blk = x_prev, f_prev
    step = step_before = 0.0
    for _ in range(maxiter):
        if f_prev * fx < 0.0:          # the sign change lies between x_prev and x: a new bracket end
            x_blk, f_blk = x_prev, f_prev
            step = step_before = x - x_prev
        if abs(f_blk) < abs(fx):       # keep x the better end; x_prev follows it
            x_prev, x, x_blk = x, x_blk, x
            f_prev, fx, f_blk = fx, f_blk, fx
        tol = (xtol + rtol * abs(x)) / 2.0
        half = (x_blk - x) / 2.0       # the bisection step
        if fx == 0.0 or abs(half) < tol:
            return x
        if abs(step_before) > tol and abs(fx) < abs(f_prev):
            if x_prev == x_blk:        # two distinct points: secant
                trial = -fx * (x - x_prev) / (fx - f_prev)
            else:                      # three: inverse quadratic interpolation
                s_prev = (f_prev - fx) / (x_prev - x)
                s_blk = (f_blk - fx) / (x_blk - x)
                trial = -fx * (f_blk * s_blk - f_prev * s_prev) / (s_blk * s_prev * (f_blk - f_prev))
            if 2.0 * abs(trial) < min(abs(step_before), 3.0 * abs(half) - tol):
                step_before, step = step, trial   # interpolation accepted
            else:
                step_before = step = half
        else:
            step_before = step = half
        x_prev, f_prev = x, fx
        x += step if abs(step) > tol else (tol if half > 0.0 else -tol)
        fx = f(x)
    raise RuntimeError(f"bracketed_root: no convergence in {maxiter} iterations on [{a}, {b}]")


# --- the model curves, as functions of R_r (xp = numpy or math) ---------------------------


def _curve(kind: str, t_c: float, material: Material, mode: str, radius_mm: float, flutes: float):
    """g(xp, R_r) for one curve: 'fx' (eq. 10), 'fxt' (eq. 12), or 'ft' (F_at at R_a = 1, eq. 7)."""
    if kind == "fx":
        return lambda xp, r: _ratios_xp(xp, r, t_c, material, mode)[0]
    if kind == "fxt" and has_edge(material):   # the law split into chip and edge (edge.py E5), issue 41
        return lambda xp, r: split_fxt(r, t_c, material, mode) if xp is NP else float(split_fxt(r, t_c, material, mode)[0])
    if kind == "fxt":
        return lambda xp, r: _ratios_xp(xp, r, t_c, material, mode)[1]
    return lambda xp, r: _tangential_per_axial_ratio_xp(xp, r, t_c, radius_mm, flutes, material, mode)


def _refine_extremum(g: Callable[[float], float], r_a: float, r_b: float) -> float:
    """Location of the extremum of g inside [r_a, r_b]: root of the central-difference slope.

    Only the extreme *value* matters for counting roots, and it is insensitive to
    the location (error ∝ location error²). Falls back to the better bracket end.
    """
    h = min(1e-7 * r_b, 1e-3 * (r_b - r_a))
    slope = lambda r: g(min(r + h, MAX_RADIAL_RATIO)) - g(r - h)  # noqa: E731 - sign of g'(r)
    s_a, s_b = slope(r_a), slope(r_b)
    if s_a * s_b < 0.0:
        return bracketed_root(slope, r_a, r_b, xtol=1e-12)
    return r_a if abs(s_a) < abs(s_b) else r_b


@lru_cache(maxsize=4096)
def _branches(kind: str, t_c: float, material: Material, mode: str, radius_mm: float = 1.0, flutes: float = 1.0):
    """Monotone branches of the curve over [MIN_RADIAL_RATIO, 2], cached per operating point."""
    curve = _curve(kind, t_c, material, mode, radius_mm, flutes)
    g = lambda r: curve(SCALAR, r)  # noqa: E731 - scalar form for the refiners
    values = curve(NP, _GRID)
    slope_sign = np.sign(np.diff(values))
    turns = np.nonzero(slope_sign[1:] != slope_sign[:-1])[0] + 1  # grid index of each extremum
    cuts = [float(_GRID[0])]
    for i in turns:
        cuts.append(_refine_extremum(g, float(_GRID[i - 1]), float(_GRID[i + 1])))
    cuts.append(float(_GRID[-1]))
    cuts = sorted(set(cuts))
    return tuple(_Branch(lo, hi, g(lo), g(hi)) for lo, hi in zip(cuts[:-1], cuts[1:]))


def _solve(kind: str, target: float, t_c: float, material: Material, mode: str, radius_mm=1.0, flutes=1.0):
    """(R_r or None, status) solving curve(R_r) = target on every monotone branch."""
    if not (math.isfinite(target) and math.isfinite(t_c) and t_c > 0.0):
        return None, OUT_OF_RANGE
    curve = _curve(kind, t_c, material, mode, radius_mm, flutes)
    roots: list[float] = []
    # A target at a branch end (R_r = 2: a full-width cut) computed by another route (the forces,
    # then their ratio) differs from the curve's own end value in the last bits: that is the end.
    tol = END_ULPS * np.finfo(float).eps * max(1.0, abs(target))
    for br in _branches(kind, t_c, material, mode, radius_mm, flutes):
        if min(br.g_lo, br.g_hi) - tol <= target <= max(br.g_lo, br.g_hi) + tol:
            if abs(target - br.g_lo) <= tol:
                root = br.r_lo
            elif abs(target - br.g_hi) <= tol:
                root = br.r_hi
            else:
                root = bracketed_root(lambda r: curve(SCALAR, r) - target, br.r_lo, br.r_hi, xtol=1e-14)
            if not roots or abs(root - roots[-1]) > 1e-9:  # a root at a shared branch end counts once
                roots.append(root)
    if not roots:
        return None, OUT_OF_RANGE
    if len(roots) > 1:
        return None, UNRESOLVABLE
    return roots[0], OK


# --- radial ratio from a force ratio ------------------------------------------------------


def radial_ratio_from_fx(fx, feed_per_tooth_mm, material: Material, mode: str) -> tuple[float | None, str]:
    """R_r from f_x = F_ax/√(F_ax² + F_ay²) ([D] eq. 10), exact; slot gives 2."""
    if check_mode(mode) == "slot":
        return MAX_RADIAL_RATIO, OK
    return _solve("fx", float(fx), float(feed_per_tooth_mm), material, mode)


def radial_ratio_from_fxt(fxt, feed_per_tooth_mm, material: Material, mode: str) -> tuple[float | None, str]:
    """R_r from f_xt = F_ax/F_at ([D] eq. 12), exact; strictly increasing in down milling."""
    if check_mode(mode) == "slot":
        return MAX_RADIAL_RATIO, OK
    t_c = float(feed_per_tooth_mm)
    if has_edge(material):   # (E5)'s curve is a quadrature: built on edge.py's feed grid, once per steady cut
        t_c = feed_cell(t_c)
    return _solve("fxt", float(fxt), t_c, material, mode)


# --- depths -------------------------------------------------------------------------------


def _axial_ratio(force_n: float, unit_force_n: float) -> float | None:
    """R_a = F / (F at R_a = 1) ([D] eq. 13); None when the model force is not positive."""
    if not (unit_force_n > 0.0 and math.isfinite(unit_force_n)):
        return None
    return force_n / unit_force_n


def _result(r_r: float | None, r_a: float | None, radius_mm: float, status: str) -> DepthResult:
    if status != OK or r_r is None or r_a is None:
        return DepthResult(None, None, status if status != OK else OUT_OF_RANGE)
    return DepthResult(r_r * radius_mm, r_a * radius_mm, OK)


def _check_tool(tool_radius_mm: float, flutes: float) -> None:
    if not (tool_radius_mm > 0.0 and flutes >= 1):
        raise ValueError(f"tool radius {tool_radius_mm} mm and flutes {flutes} must be positive")


def depths_from_forces(
    *,
    tangential_n: float | None = None,
    feed_n: float | None = None,
    fx_n: float | None = None,
    fy_n: float | None = None,
    feed_per_tooth_mm: float,
    tool_radius_mm: float,
    flutes: int,
    material: Material,
    mode: str,
    min_force_n: float = 0.0,
) -> DepthResult:
    """Radial and axial depth from two average forces ([D] §3).

    Dynamometer (``fx_n``, ``fy_n``: average F_x, F_y in [D]'s axes) → f_x, eq. (10);
    else feed-drive force ``feed_n`` (F_ax) with ``tangential_n`` (F_at = T_c/R) → f_xt,
    eq. (12). Then R_a from eq. (13): with f_x from |(F_ax, F_ay)| (the same eq. 7
    ratio, robust where F_ax crosses zero), with f_xt from F_at. f_x drops the sign
    of F_y, so a measured F_y opposite to the model's is ``out_of_range`` (wrong
    axes or wrong mode). In slot mode one force suffices. A force magnitude ≤
    ``min_force_n`` is an air cut.
    """
    check_mode(mode)
    _check_tool(tool_radius_mm, flutes)
    t_c = float(feed_per_tooth_mm)
    if fx_n is not None and fy_n is not None:
        magnitude_n = math.hypot(fx_n, fy_n)
        if not magnitude_n > min_force_n:
            return DepthResult(None, None, AIR_CUT)
        r_r, status = radial_ratio_from_fx(fx_n / magnitude_n, t_c, material, mode)
        if status != OK:
            return DepthResult(None, None, status)
        unit = _unit_forces(r_r, t_c, tool_radius_mm, flutes, material, mode)
        if fy_n * unit[2] < 0.0 and abs(fy_n) > 1e-9 * magnitude_n:
            return DepthResult(None, None, OUT_OF_RANGE)  # f_x fits, but F_y points the wrong way
        return _result(r_r, _axial_ratio(magnitude_n, math.hypot(unit[1], unit[2])), tool_radius_mm, OK)
    if tangential_n is None:
        return DepthResult(None, None, NO_SECOND_FORCE)
    if not tangential_n > min_force_n:
        return DepthResult(None, None, AIR_CUT)
    if feed_n is None:
        if mode != "slot":
            return DepthResult(None, None, NO_SECOND_FORCE)
        r_r, status = MAX_RADIAL_RATIO, OK
    else:
        r_r, status = radial_ratio_from_fxt(feed_n / tangential_n, t_c, material, mode)
    if status != OK:
        return DepthResult(None, None, status)
    unit = _unit_forces(r_r, t_c, tool_radius_mm, flutes, material, mode)
    return _result(r_r, _axial_ratio(tangential_n, unit[0]), tool_radius_mm, OK)


def _unit_forces(r_r, t_c, radius_mm, flutes, material, mode) -> tuple[float, float, float]:
    """(F_at, F_ax, F_ay) at R_a = 1, N, as Python floats: `average_forces_n`'s eq. (7) on the ``SCALAR``
    kernels (one revolution's call on numpy scalars cost more than its root). nan where the model has
    no value (a radial ratio outside (0, 2], no chip)."""
    r_r = MAX_RADIAL_RATIO if mode == "slot" else float(r_r)
    t_c = float(t_c)
    if not (0.0 < r_r <= MAX_RADIAL_RATIO and t_c > 0.0):
        return math.nan, math.nan, math.nan
    entry, exit_ = engagement_xp(SCALAR, r_r, mode)
    a, b, c = _integrals_xp(SCALAR, entry, exit_)
    t_a = chip_xp(SCALAR, t_c, entry, exit_)                                   # eq. (8)
    if not (t_a > 0.0 and math.isfinite(t_a)):
        return math.nan, math.nan, math.nan
    ks, r1 = material.ks * t_a**material.ks_exp, material.r1 * t_a**material.r1_exp   # eq. (9)
    scale_n = flutes / (2.0 * math.pi) * ks * t_c * radius_mm                   # R_a = 1: d_a = R
    return scale_n * c, scale_n * (a + r1 * b), scale_n * (-b + r1 * a)


def _check_depth_args(mode: str, tool_radius_mm: float, flutes: float, known_radial_mm: float | None,
                      known_axial_mm: float | None) -> None:
    """The argument errors both depth-from-torque functions raise before looking at the torque."""
    check_mode(mode)
    _check_tool(tool_radius_mm, flutes)
    if known_radial_mm is not None and known_axial_mm is not None:
        raise ValueError("depth_from_torque: give one known depth (radial or axial), not both")


def depth_from_torque(
    torque_nm: float,
    feed_per_tooth_mm: float,
    tool_radius_mm: float,
    flutes: int,
    material: Material,
    mode: str,
    known_radial_mm: float | None = None,
    known_axial_mm: float | None = None,
    min_torque_nm: float = 0.0,
) -> DepthResult:
    """The unknown depth from spindle torque alone, the other being known ([D] eq. 7 with F_at = T_c/R).

    Known axial depth: F_at/R_a is increasing in R_r, solved exactly. Known radial
    depth (or slot): R_a is linear in F_at. Neither known: ``no_second_force``.
    """
    _check_depth_args(mode, tool_radius_mm, flutes, known_radial_mm, known_axial_mm)
    if not torque_nm > min_torque_nm:
        return DepthResult(None, None, AIR_CUT)
    tangential_n = torque_nm / (tool_radius_mm * 1e-3)  # F_at = T_c/R, R in m
    t_c = float(feed_per_tooth_mm)
    if mode == "slot" or known_radial_mm is not None:
        r_r = MAX_RADIAL_RATIO if mode == "slot" else known_radial_mm / tool_radius_mm
        if not 0.0 < r_r <= MAX_RADIAL_RATIO:
            raise ValueError(f"known radial depth {known_radial_mm} mm is outside (0, tool diameter]")
        if not (math.isfinite(t_c) and t_c > 0.0):
            return DepthResult(None, None, OUT_OF_RANGE)
        unit = _unit_forces(r_r, t_c, tool_radius_mm, flutes, material, mode)
        return _result(r_r, _axial_ratio(tangential_n, unit[0]), tool_radius_mm, OK)
    if known_axial_mm is None:
        return DepthResult(None, None, NO_SECOND_FORCE)
    if not known_axial_mm > 0.0:
        raise ValueError(f"known axial depth {known_axial_mm} mm must be positive")
    r_a = known_axial_mm / tool_radius_mm
    r_r, status = _solve("ft", tangential_n / r_a, t_c, material, mode, float(tool_radius_mm), float(flutes))
    return _result(r_r, r_a, tool_radius_mm, status)


def depth_from_torque_many(
    torque_nm,
    feed_per_tooth_mm,
    tool_radius_mm: float,
    flutes: int,
    material: Material,
    mode: str,
    known_radial_mm: float | None = None,
    known_axial_mm: float | None = None,
    min_torque_nm: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """``depth_from_torque`` over arrays of revolutions: (radial mm, axial mm, statuses), nan where none.

    Known radial depth (or slot) is closed-form, R_a = F_at / F_at(R_a = 1) ([D] eqs. 7, 13), so it runs
    once over the columns (a block of revolutions costs about what one did on numpy scalars). Known
    axial depth needs a root per revolution (eq. 7 inverted in R_r): those go one by one. Argument
    errors raise as in ``depth_from_torque``, but only where it would: after the air-cut test.
    """
    _check_depth_args(mode, tool_radius_mm, flutes, known_radial_mm, known_axial_mm)
    torque = np.asarray(torque_nm, dtype=float)
    t_c = np.asarray(feed_per_tooth_mm, dtype=float)
    count = len(torque)
    radial, axial = np.full(count, np.nan), np.full(count, np.nan)
    cutting = torque > min_torque_nm
    status = np.where(cutting, OK, AIR_CUT).tolist()
    if not cutting.any():
        return radial, axial, status
    if mode != "slot" and known_radial_mm is None:
        if known_axial_mm is None:
            return radial, axial, [NO_SECOND_FORCE if c else AIR_CUT for c in cutting.tolist()]
        for i in np.flatnonzero(cutting).tolist():   # a root each: see above
            d = depth_from_torque(float(torque[i]), float(t_c[i]), tool_radius_mm, flutes, material, mode,
                                  known_axial_mm=known_axial_mm, min_torque_nm=min_torque_nm)
            status[i] = d.status
            if d.status == OK:
                radial[i], axial[i] = d.radial_depth_mm, d.axial_depth_mm
        return radial, axial, status
    r_r = MAX_RADIAL_RATIO if mode == "slot" else known_radial_mm / tool_radius_mm
    if not 0.0 < r_r <= MAX_RADIAL_RATIO:
        raise ValueError(f"known radial depth {known_radial_mm} mm is outside (0, tool diameter]")
    tangential_n = torque / (tool_radius_mm * 1e-3)                  # F_at = T_c/R, R in m ([P] eq. 16)
    usable = cutting & np.isfinite(t_c) & (t_c > 0.0)
    unit_n = average_forces_n(r_r, 1.0, np.where(usable, t_c, 1.0), tool_radius_mm, flutes,
                              material, mode).tangential_n           # F_at at R_a = 1 (eq. 7)
    usable &= np.isfinite(unit_n) & (unit_n > 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_a = tangential_n / unit_n                                  # eq. (13)
    radial[usable] = r_r * tool_radius_mm
    axial[usable] = r_a[usable] * tool_radius_mm
    for i in np.flatnonzero(cutting & ~usable).tolist():
        status[i] = OUT_OF_RANGE
    return radial, axial, status
