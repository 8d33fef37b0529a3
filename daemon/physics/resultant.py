"""The engaged teeth's forces added as vectors: how much of √(1 + r₁²) the mean resultant keeps.

[P] eq. (17) sizes one tooth's in-plane force, ``|(F_x, F_y)| = √(1 + r₁²)·F_T``. With several
teeth in cut at once (3–4 flutes in a slot, a helix that spreads each edge over an arc) the forces
of the teeth point different ways and partly cancel, so the revolution mean of the *vector sum's*
magnitude is smaller than the sum of the magnitudes. How much smaller is geometry alone.

Per edge element at immersion φ ([D] eqs. 1–4, x along the feed, y normal, coefficients at the
average chip t_a of eq. 8–9 as in eq. 7), written as a complex number F_x + i·F_y:

    dF = K_s·t_c·sin φ·(cos φ + r₁ sin φ − i sin φ + i r₁ cos φ)·dz = K_s·t_c·(1 + i r₁)·g(φ)·dz
    g(φ) = sin φ·e^{−iφ} = (−i/2)·(1 − e^{−2iφ})                                       (R1)

so ``|Σ dF| = √(1 + r₁²)·K_s·t_c·|Σ g·dz|``: r₁ and K_s factor out of the sum, and

    C_f = F_res/F_T = √(1 + r₁²)·η,      η = mean_θ |H(θ)| / mean_θ Σ_k ∫ sin φ dz            (R2)

with H(θ) = Σ_k ∫_{edge k in cut} g(φ) dφ. Edge k of N sits at θ_k = θ + 2πk/N at the tool's tip
and lags by ψ = d_a·tan β/R at the top of the cut (the plant's and [D]'s helix), so it covers the
immersions [θ_k − ψ, θ_k]; its part inside the engagement [θ₁, θ₂] (mod 2π) contributes

    ∫ g dφ = [P(φ)]  over each overlap,   P(φ) = −iφ/2 − e^{−2iφ}/4                       (R3)

and the tangential mean is ψ·N·c/2π with c = cos θ₁ − cos θ₂ ([D] eq. 7's C). Straight flutes
(ψ → 0): H/ψ → Σ_k g(θ_k) over the teeth in cut. η ≤ 1 always (triangle inequality), = 1 while
at most one tooth cuts and ψ = 0, and η(ψ) ≤ η(0): an unknown axial depth or helix taken as ψ = 0
gives the upper bound of the force, never less than the truth of the model.

η depends on N, the span θ₂ − θ₁ and ψ only: up milling [0, s] and down milling [π − s, π] are
mirror images (φ → π − φ maps g to −conj g, an edge's arc to an arc of the same length), a slot is
s = π. So one table per flute count over (s, ψ), built once per process (``overlap_table``), read
by bilinear interpolation (``overlap_factor``): the revolution pays a few float operations.
The table's quadrature (``GAUSS_NODES`` on each smooth piece) and grid are checked against a
fine quadrature and an independent brute-force model in tests/physics/test_resultant.py.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from millsense.daemon.physics.numbers import values

GAUSS_NODES = 6           # Gauss–Legendre points on each smooth piece of a tooth period (mean of |H|)
SPAN_STEPS = 48           # the table's span axis: 0 … π in steps of π/48 (holds π/2, π/3, 2π/3, π/4 …)
LAG_STEP_RAD = math.pi / 24
LAG_MAX_RAD = 2.0 * math.pi   # d_a·tan β/R up to 2π: 5.4 diameters at 30°, 3.1 at 45°; beyond: computed
_CHUNK = 256              # table cells per numpy pass (bounds the build's memory)


def _antiderivative(phi):
    """P(φ) of (R3): ∫ sin φ·e^{−iφ} dφ."""
    return -0.5j * phi - 0.25 * np.exp(-2j * phi)


def exact_overlap_factor(flutes: int, entry_rad, exit_rad, lag_rad, nodes: int = GAUSS_NODES) -> np.ndarray:
    """η of (R2) by quadrature over one tooth period (arrays broadcast; nan for no engagement).

    H(θ) is smooth between the angles where a tooth's tip or the top of its cut crosses θ₁ or θ₂,
    that is θ₁, θ₂, θ₁ + ψ, θ₂ + ψ modulo the tooth period: Gauss–Legendre with `nodes` points on each
    of the (at most five) pieces between them integrates |H| to near machine precision, jumps (ψ = 0)
    and kinks included. The reference the table is built from.
    """
    entry, exit_, lag = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (entry_rad, exit_rad, lag_rad)))
    shape = entry.shape
    entry, exit_, lag = entry.reshape(-1, 1), exit_.reshape(-1, 1), lag.reshape(-1, 1)
    pitch = 2.0 * math.pi / flutes
    breaks = np.mod(np.concatenate([entry, exit_, entry + lag, exit_ + lag], axis=1), pitch)
    edges = np.sort(np.concatenate([np.zeros_like(entry), breaks, np.full_like(entry, pitch)], axis=1), axis=1)
    x, w = np.polynomial.legendre.leggauss(nodes)
    lo_p, width = edges[:, :-1, None], np.diff(edges, axis=1)[:, :, None]
    theta = (lo_p + width * (x + 1.0) / 2.0).reshape(len(entry), -1)                  # (cells, 5·nodes)
    weight = (width * w / 2.0).reshape(len(entry), -1) / pitch                        # mean over the period
    tip = np.mod(theta[:, :, None] + pitch * np.arange(flutes), 2.0 * math.pi)[..., None]
    e4, x4, l4 = entry[:, :, None, None], exit_[:, :, None, None], lag[:, :, None, None]
    copies = -np.arange(int(np.nanmax(lag, initial=0.0) // (2.0 * math.pi)) + 2)
    lo_e, hi_e = e4 + 2.0 * math.pi * copies, x4 + 2.0 * math.pi * copies
    helical = l4 > 0.0
    safe_lag = np.where(helical, l4, 1.0)
    lo = np.maximum(tip - safe_lag, lo_e)
    hi = np.minimum(tip, hi_e)
    inside = hi > lo
    pieces = np.where(inside, _antiderivative(np.where(inside, hi, 0.0)) - _antiderivative(np.where(inside, lo, 0.0)),
                      0.0)
    h = pieces.sum(axis=(2, 3)) / safe_lag[:, :, 0, 0]                                # per unit lag
    straight = np.where((tip >= e4) & (tip <= x4), np.sin(tip) * np.exp(-1j * tip), 0.0)[..., 0].sum(axis=2)
    h = np.where(helical[:, :, 0, 0], h, straight)
    c = (np.cos(entry) - np.cos(exit_))[:, 0]
    tangential = flutes * c / (2.0 * math.pi)
    with np.errstate(invalid="ignore", divide="ignore"):
        eta = (np.abs(h) * weight).sum(axis=1) / tangential
    return np.where(c > 0.0, eta, np.nan).reshape(shape)


@functools.cache
def overlap_table(flutes: int) -> np.ndarray:
    """η over the grid (span i·π/SPAN_STEPS, lag j·LAG_STEP_RAD) for down milling [π − s, π]; row 0 (s = 0)
    is the limit 1 of a vanishing engagement. Built once per flute count and process (~0.1 s)."""
    if flutes < 1:
        raise ValueError(f"flutes {flutes}: at least 1")
    spans = np.arange(SPAN_STEPS + 1) * (math.pi / SPAN_STEPS)
    lags = np.arange(round(LAG_MAX_RAD / LAG_STEP_RAD) + 1) * LAG_STEP_RAD
    s, psi = np.meshgrid(spans[1:], lags, indexing="ij")
    flat_s, flat_psi = s.ravel(), psi.ravel()
    out = np.empty(flat_s.size)
    for a in range(0, flat_s.size, _CHUNK):
        b = a + _CHUNK
        out[a:b] = exact_overlap_factor(flutes, math.pi - flat_s[a:b], math.pi, flat_psi[a:b])
    table = np.ones((SPAN_STEPS + 1, lags.size))
    table[1:] = out.reshape(s.shape)
    table.setflags(write=False)
    return table


_ROWS: dict[int, list[list[float]]] = {}   # overlap_table as lists, for the float path
_PER_SPAN = SPAN_STEPS / math.pi
_PER_LAG = 1.0 / LAG_STEP_RAD
_LAG_LAST = round(LAG_MAX_RAD / LAG_STEP_RAD) - 1e-9


def _rows(flutes: int) -> list[list[float]]:
    rows = _ROWS[flutes] = overlap_table(int(flutes)).tolist()
    return rows


def helix_lag_rad(axial_depth_mm, helix_deg: float | None, tool_radius_mm: float):
    """ψ = d_a·tan β/R: how far the edge at the top of the cut trails its tip (0: helix or depth unknown)."""
    if helix_deg is None:
        return 0.0 if isinstance(axial_depth_mm, float) or axial_depth_mm is None else np.zeros(np.shape(axial_depth_mm))
    tan_beta = math.tan(math.radians(helix_deg))
    if axial_depth_mm is None:
        return 0.0
    d = values(axial_depth_mm)
    if isinstance(d, float):
        return d * tan_beta / tool_radius_mm if math.isfinite(d) and d > 0.0 else 0.0
    return np.where(np.isfinite(d) & (d > 0.0), d, 0.0) * tan_beta / tool_radius_mm


def overlap_factor(flutes: int, span_rad, lag_rad):
    """η of (R2) from the table (a float for floats, else an array): span θ₂ − θ₁ in (0, π], lag ψ ≥ 0.

    nan for a span outside (0, π]; a lag beyond the table's LAG_MAX_RAD is computed by quadrature.
    """
    span, lag = values(span_rad), values(lag_rad)
    if isinstance(span, float) and isinstance(lag, float):   # one revolution: plain floats and lists, no numpy
        rows = _ROWS.get(flutes) or _rows(flutes)
        if not 0.0 < span <= math.pi + 1e-12 or not lag >= 0.0:
            return math.nan
        if lag > LAG_MAX_RAD:
            return float(exact_overlap_factor(int(flutes), math.pi - span, math.pi, lag))
        x = min(span * _PER_SPAN, SPAN_STEPS - 1e-9)
        y = min(lag * _PER_LAG, _LAG_LAST)
        i, j = int(x), int(y)
        fx, fy = x - i, y - j
        row0, row1 = rows[i], rows[i + 1]
        return (row0[j] * (1 - fy) + row0[j + 1] * fy) * (1 - fx) + (row1[j] * (1 - fy) + row1[j + 1] * fy) * fx
    table = overlap_table(int(flutes))
    span, lag = np.broadcast_arrays(np.asarray(span, dtype=float), np.asarray(lag, dtype=float))
    ok = (span > 0.0) & (span <= math.pi + 1e-12) & (lag >= 0.0)
    x = np.clip(np.where(ok, span, 0.0) / (math.pi / SPAN_STEPS), 0.0, SPAN_STEPS - 1e-9)
    y = np.clip(np.where(ok, lag, 0.0) / LAG_STEP_RAD, 0.0, table.shape[1] - 1 - 1e-9)
    i, j = x.astype(int), y.astype(int)
    fx, fy = x - i, y - j
    eta = ((table[i, j] * (1 - fy) + table[i, j + 1] * fy) * (1 - fx)
           + (table[i + 1, j] * (1 - fy) + table[i + 1, j + 1] * fy) * fx)
    beyond = ok & (lag > LAG_MAX_RAD)
    if beyond.any():
        eta[beyond] = exact_overlap_factor(int(flutes), math.pi - span[beyond], math.pi, lag[beyond])
    return np.where(ok, eta, np.nan)
