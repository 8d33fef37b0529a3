"""The engaged teeth's forces added as vectors: how much of √(1 + r₁²) the mean resultant keeps.

[P] eq. (17) sizes one tooth's in-plane force, ``|(F_x, F_y)| = √(1 + r₁²)·F_T``. With several
teeth in cut at once (3–4 flutes in a slot, a helix that spreads each edge over an arc) the forces
of the teeth point different ways and partly cancel, so the revolution mean of the *vector sum's*
magnitude is smaller than the sum of the magnitudes. How much smaller depends on the geometry and on
how each tooth's force grows with its chip.

Per edge element at immersion φ ([D] eqs. 1–4, x along the feed, y normal), written as a complex
number F_x + i·F_y, with tangential force dF_t and radial dF_r = ρ·dF_t:

    dF = (dF_t + i·dF_r)·e^{−iφ}                                                          (R1)

The chip at the instant is h = t_c·sin φ. Kienzle's law, k_c = k_c1.1·h^(−m_c), holds at that
chip (Altintas, *Manufacturing Automation*, ch. 2; the size effect): with [D] eq. (9)'s exponents
p = ks_exp (= −m_c) and q = r1_exp taken at h instead of at the average chip t_a,

    dF_t ∝ h^(1+p)·dz ∝ w(φ)·dz,   w(φ) = sin^(1+p) φ,    ρ(φ) = κ·r₁(t_a)·sin^q φ          (R1a)

where κ = ∫_E w dφ / ∫_E w·sin^q φ dφ over the engagement E = [θ₁, θ₂] keeps [D] eq. (9)'s meaning:
the cut's mean radial over its mean tangential force is r₁(t_a). (p = q = 0 is [D]'s own average
law: dF_t ∝ sin φ, ρ = r₁, and r₁ factors out of the sum, η below is geometry alone.) Then

    C_f = F_res/F_T = √(1 + r₁²)·η,   η = mean_θ |A(θ) + i·r₁·B(θ)| / (√(1 + r₁²)·mean_θ Σ_k ∫ w dz)   (R2)

with A(θ) = Σ_k ∫_{edge k in cut} w(φ)·e^{−iφ} dφ and B(θ) the same with κ·w·sin^q. Edge k of N
sits at θ_k = θ + 2πk/N at the tool's tip and lags by ψ = d_a·tan β/R at the top of the cut (the
plant's and [D]'s helix), so it covers the immersions [θ_k − ψ, θ_k]; its part inside E contributes

    ∫ sin^a φ·e^{−iφ} dφ = [Q_a(φ)] over each overlap,  Q_a(φ) = sin^(a+1) φ/(a + 1) − i·S_(a+1)(φ)   (R3)

with S_m(φ) = ∫₀^φ sin^m t dt (closed for m = 1, 2; else a cubic Hermite table of it, built once) and
a = 1 + p for A, 1 + p + q for B. The tangential mean is ψ·N·S_(1+p)(E)/2π (p = 0: [D] eq. 7's C).
Straight flutes (ψ → 0): A/ψ → Σ_k w(θ_k)·e^{−iθ_k} over the teeth in cut. With q = 0 the
triangle inequality gives η ≤ 1, = 1 while at most one tooth cuts and ψ = 0 (with q ≠ 0 one tooth's
η is a little above 1: ρ varies along the arc and √(1 + ρ²) is convex). η(ψ) ≤ η(0) holds in every
case tested (tests/physics/test_resultant.py): an unknown axial depth or helix taken as ψ = 0 gives
the upper bound of the force.

η depends on N, the span θ₂ − θ₁, ψ, r₁ and the exponents (p, q) only. Up milling [0, s] is the
mirror image of down milling [π − s, π] with r₁ of the other sign: φ → π − φ keeps sin φ and maps
e^{−iφ} to −conj(e^{−iφ}), so A, B become −conj(A), −conj(B) and |A + i·r₁·B| becomes |A − i·r₁·B|
(with q = 0, B = A and the sign does not matter: up and down alike). A slot is down milling with
s = π. So one table per flute count and material exponents over (s, ψ, ±r₁), its cells computed when a
cut first reads them (``_Lazy``; ``overlap_table`` builds it whole for tests and benches), read by
trilinear interpolation (``overlap_factor``): a steady revolution pays a few float operations. The table's quadrature and grid are checked against a fine quadrature and an
independent brute-force model in tests/physics/test_resultant.py.
"""

from __future__ import annotations

import functools
import math

import numpy as np

from millsense.daemon.physics.numbers import values

GAUSS_NODES = 12          # Gauss–Legendre points on each smooth piece of a tooth period (mean of |H|)
SPAN_STEPS = 48           # the table's span axis: 0 … π in steps of π/48 (holds π/2, π/3, 2π/3, π/4 …)
LAG_STEP_RAD = math.pi / 24
LAG_MAX_RAD = 2.0 * math.pi   # d_a·tan β/R up to 2π: 5.4 diameters at 30°, 3.1 at 45°; beyond: computed
R1_STEP = 0.125           # the table's r₁ axis: 0 … R1_MAX (r₁(t_a) of a chip of 1 µm is about 1 for steels)
R1_MAX = 2.0              # beyond: computed
SIN_STEPS = 2048          # S_m(φ)'s Hermite table over [0, π]
_CHUNK = 256              # table cells per numpy pass (bounds the build's memory)


def local_exponents(ks_exp: float, r1_exp: float) -> tuple[float, float]:
    """(p, q) of (R1a) from [D] eq. (9)'s exponents; (0, 0), [D]'s average law, where the local law has no
    finite force (1 + p ≤ 0 or 1 + p + q ≤ 0: the force of the thinnest chip would grow without bound)."""
    p, q = float(ks_exp), float(r1_exp)
    if not (math.isfinite(p) and math.isfinite(q) and 1.0 + p > 0.0 and 1.0 + p + q > 0.0):
        return 0.0, 0.0
    return p, q


@functools.cache
def _sin_power_table(m: float) -> tuple[np.ndarray, np.ndarray]:
    """S_m and its derivative sin^m at SIN_STEPS + 1 points of [0, π]: 16-point Gauss–Legendre per interval."""
    grid = np.linspace(0.0, math.pi, SIN_STEPS + 1)
    x, w = np.polynomial.legendre.leggauss(16)
    h = grid[1] - grid[0]
    t = grid[:-1, None] + h * (x + 1.0) / 2.0
    pieces = (np.sin(t) ** m * w).sum(axis=1) * h / 2.0
    return np.concatenate([[0.0], np.cumsum(pieces)]), np.abs(np.sin(grid)) ** m


def sin_power_integral(m: float, phi):
    """S_m(φ) = ∫₀^φ sin^m t dt for φ in [0, π] (clipped), m > −1: closed for m = 1, 2, else cubic Hermite
    on the table (its derivative sin^m is known exactly)."""
    phi = np.clip(np.asarray(phi, dtype=float), 0.0, math.pi)
    if m == 1.0:
        return 1.0 - np.cos(phi)
    if m == 2.0:
        return phi / 2.0 - np.sin(2.0 * phi) / 4.0
    s, d = _sin_power_table(float(m))
    h = math.pi / SIN_STEPS
    x = phi / h
    j = np.minimum(x.astype(int), SIN_STEPS - 1)
    u = x - j
    d0, d1 = d[j], d[j + 1]
    return ((2 * u**3 - 3 * u**2 + 1) * s[j] + (u**3 - 2 * u**2 + u) * h * d0
            + (-2 * u**3 + 3 * u**2) * s[j + 1] + (u**3 - u**2) * h * d1)


def _antiderivative(a: float, phi):
    """Q_a(φ) of (R3): ∫ sin^a φ·e^{−iφ} dφ on [0, π]."""
    phi = np.clip(phi, 0.0, math.pi)
    return np.sin(phi) ** (a + 1.0) / (a + 1.0) - 1j * sin_power_integral(a + 1.0, phi)


def _period_sums(flutes, entry, exit_, lag, nodes, p, q):
    """A and B of (R2) at the Gauss nodes of one tooth period, their weights, and the tangential mean.

    A(θ) and B(θ) are smooth between the angles where a tooth's tip or the top of its cut crosses θ₁ or θ₂,
    that is θ₁, θ₂, θ₁ + ψ, θ₂ + ψ modulo the tooth period: Gauss–Legendre with `nodes` points on each
    of the (at most five) pieces between them.
    """
    a_w, a_b = 1.0 + p, 1.0 + p + q
    pitch = 2.0 * math.pi / flutes
    breaks = np.mod(np.concatenate([entry, exit_, entry + lag, exit_ + lag], axis=1), pitch)
    edges = np.sort(np.concatenate([np.zeros_like(entry), breaks, np.full_like(entry, pitch)], axis=1), axis=1)
    x, w = np.polynomial.legendre.leggauss(nodes)
    lo_p, width = edges[:, :-1, None], np.diff(edges, axis=1)[:, :, None]
    theta = (lo_p + width * (x + 1.0) / 2.0).reshape(len(entry), -1)                  # (cells, 5·nodes)
    weight = (width * w / 2.0).reshape(len(entry), -1) / pitch                        # mean over the period
    tip = np.mod(theta[:, :, None] + pitch * np.arange(flutes), 2.0 * math.pi)[..., None]
    e4, x4, l4 = entry[:, :, None, None], exit_[:, :, None, None], lag[:, :, None, None]
    shift = 2.0 * math.pi * -np.arange(int(np.nanmax(lag, initial=0.0) // (2.0 * math.pi)) + 2)
    helical = l4 > 0.0
    safe_lag = np.where(helical, l4, 1.0)
    lo = np.maximum(tip - safe_lag, e4 + shift)
    hi = np.minimum(tip, x4 + shift)
    inside = hi > lo
    lo_r, hi_r = lo - shift, hi - shift                                                 # back into E ⊂ [0, π]
    s_w = sin_power_integral(a_w, exit_[:, 0]) - sin_power_integral(a_w, entry[:, 0])
    s_b = sin_power_integral(a_b, exit_[:, 0]) - sin_power_integral(a_b, entry[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        kappa = (s_w / s_b)[:, None]
    sums = []
    hi_in, lo_in = hi_r[inside], lo_r[inside]      # the quadrature's work only where an edge is in cut
    for a in (a_w, a_b):
        pieces = np.zeros(inside.shape, dtype=complex)
        pieces[inside] = _antiderivative(a, hi_in) - _antiderivative(a, lo_in)
        h = pieces.sum(axis=(2, 3)) / safe_lag[:, :, 0, 0]                            # per unit lag
        t = tip[..., 0]
        on = (t >= e4[..., 0]) & (t <= x4[..., 0])
        straight = np.where(on, np.abs(np.sin(np.where(on, t, 1.0))) ** a * np.exp(-1j * t), 0.0).sum(axis=2)
        sums.append(np.where(helical[:, :, 0, 0], h, straight))
    tangential = flutes * s_w / (2.0 * math.pi)
    return sums[0], kappa * sums[1], weight, tangential, s_w


def exact_overlap_factor(flutes: int, entry_rad, exit_rad, lag_rad, nodes: int = GAUSS_NODES, r1=0.0,
                         size_exp: float = 0.0, r1_exp: float = 0.0) -> np.ndarray:
    """η of (R2) by quadrature over one tooth period (arrays broadcast; nan for no engagement).

    ``size_exp``, ``r1_exp``: p and q of (R1a) (``local_exponents``); 0, 0: [D]'s average law. The
    reference the table is built from.
    """
    entry, exit_, lag, r = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (entry_rad, exit_rad, lag_rad,
                                                                                       r1)))
    shape = entry.shape
    a, b, weight, tangential, s_w = _period_sums(int(flutes), entry.reshape(-1, 1), exit_.reshape(-1, 1),
                                                 lag.reshape(-1, 1), nodes, float(size_exp), float(r1_exp))
    r = r.reshape(-1, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        eta = (np.abs(a + 1j * r * b) * weight).sum(axis=1) / (np.sqrt(1.0 + r[:, 0] ** 2) * tangential)
    return np.where(s_w > 0.0, eta, np.nan).reshape(shape)


def _r1_axis() -> np.ndarray:
    steps = round(R1_MAX / R1_STEP)
    return np.arange(-steps, steps + 1) * R1_STEP


def _cell_rows(flutes: int, size_exp: float, r1_exp: float, span_idx: np.ndarray, lag_idx: np.ndarray) -> np.ndarray:
    """η over the r₁ axis at the grid cells (span i·π/SPAN_STEPS, lag j·LAG_STEP_RAD), down milling [π − s, π]:
    an array (cells, r₁). Span index 0 is the limit 1 of a vanishing engagement."""
    rs = _r1_axis()
    out = np.ones((span_idx.size, rs.size))
    cut = span_idx > 0
    flat_s = span_idx[cut] * (math.pi / SPAN_STEPS)
    flat_psi = lag_idx[cut] * LAG_STEP_RAD
    rows = np.empty((flat_s.size, rs.size))
    for i in range(0, flat_s.size, _CHUNK):
        j = i + _CHUNK
        cells = flat_s[i:j].size
        a, b, weight, tangential, _ = _period_sums(
            int(flutes), (math.pi - flat_s[i:j]).reshape(-1, 1), np.full((cells, 1), math.pi),
            flat_psi[i:j].reshape(-1, 1), GAUSS_NODES, float(size_exp), float(r1_exp))
        mag = np.abs(a[:, :, None] + 1j * rs * b[:, :, None])                          # (cells, nodes, r₁)
        rows[i:j] = (mag * weight[:, :, None]).sum(axis=1) / (np.sqrt(1.0 + rs**2) * tangential[:, None])
    out[cut] = rows
    return out


_LAGS = round(LAG_MAX_RAD / LAG_STEP_RAD) + 1


def overlap_table(flutes: int, size_exp: float = 0.0, r1_exp: float = 0.0) -> np.ndarray:
    """η over the whole grid (span i·π/SPAN_STEPS, lag j·LAG_STEP_RAD, r₁ −R1_MAX + k·R1_STEP) for down milling
    [π − s, π]; row 0 (s = 0) is the limit 1 of a vanishing engagement. The daemon never builds it whole
    (0.3–0.75 s a flute count and material): `overlap_factor` computes the cells a cut needs when it first
    needs them (`_Lazy`), with the same `_cell_rows`. Tests and benches read the whole table."""
    if flutes < 1:
        raise ValueError(f"flutes {flutes}: at least 1")
    i, j = np.meshgrid(np.arange(SPAN_STEPS + 1), np.arange(_LAGS), indexing="ij")
    table = _cell_rows(int(flutes), float(size_exp), float(r1_exp), i.ravel(), j.ravel()).reshape(i.shape + (-1,))
    table.setflags(write=False)
    return table


class _Lazy:
    """One flute count's and material's table, filled cell by cell as cuts ask (a steady cut reads the same
    four cells every revolution: the first revolution of a new engagement pays about a millisecond)."""

    def __init__(self, key: tuple[int, float, float]) -> None:
        if key[0] < 1:
            raise ValueError(f"flutes {key[0]}: at least 1")
        self.key = key
        self.table = np.full((SPAN_STEPS + 1, _LAGS, _r1_axis().size), np.nan)
        self.done = np.zeros((SPAN_STEPS + 1, _LAGS), dtype=bool)
        self.quads: dict[tuple[int, int], tuple[list[float], ...]] = {}   # the float path's cells, as lists

    def fill(self, i: np.ndarray, j: np.ndarray) -> None:
        """Compute the cells (i, j) not yet computed (arrays of grid indices, in range)."""
        want = ~self.done[i, j]
        if not want.any():
            return
        cells = np.unique(np.stack([i[want], j[want]], axis=1), axis=0)
        self.table[cells[:, 0], cells[:, 1]] = _cell_rows(*self.key, cells[:, 0], cells[:, 1])
        self.done[cells[:, 0], cells[:, 1]] = True

    def quad(self, i: int, j: int) -> tuple[list[float], ...]:
        """The rows of cells (i, j), (i, j + 1), (i + 1, j), (i + 1, j + 1): what one interpolation reads."""
        q = self.quads.get((i, j))
        if q is None:
            ii, jj = np.array([i, i, i + 1, i + 1]), np.array([j, j + 1, j, j + 1])
            self.fill(ii, jj)
            q = self.quads[(i, j)] = tuple(self.table[a, b].tolist() for a, b in zip(ii, jj))
        return q


_TABLES: dict[tuple[int, float, float], _Lazy] = {}
_PER_SPAN = SPAN_STEPS / math.pi
_PER_LAG = 1.0 / LAG_STEP_RAD
_PER_R1 = 1.0 / R1_STEP
_LAG_LAST = round(LAG_MAX_RAD / LAG_STEP_RAD) - 1e-9
_R1_LAST = 2 * round(R1_MAX / R1_STEP) - 1e-9


def _lazy(key: tuple[int, float, float]) -> _Lazy:
    t = _TABLES.get(key)
    if t is None:
        t = _TABLES[key] = _Lazy(key)
    return t


def mirror_r1(mode: str, r1):
    """The table's r₁ for a milling mode: −r₁ for up milling (the mirror image of down milling), else r₁."""
    return -r1 if mode == "up" else r1


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


def overlap_factor(flutes: int, span_rad, lag_rad, r1=0.0, size_exp: float = 0.0, r1_exp: float = 0.0):
    """η of (R2) from the table (a float for floats, else an array): span θ₂ − θ₁ in (0, π], lag ψ ≥ 0,
    ``r1`` = r₁(t_a) for down milling and slots, −r₁(t_a) for up milling (``mirror_r1``), the material's
    (p, q) of ``local_exponents``.

    nan for a span outside (0, π], a negative lag or an r₁ nan; a lag beyond LAG_MAX_RAD or an |r₁| beyond
    R1_MAX is computed by quadrature.
    """
    span, lag, r = values(span_rad), values(lag_rad), values(r1)
    key = (int(flutes), float(size_exp), float(r1_exp))
    if isinstance(span, float) and isinstance(lag, float) and isinstance(r, float):   # one revolution: floats
        lazy = _TABLES.get(key) or _lazy(key)
        if not 0.0 < span <= math.pi + 1e-12 or not lag >= 0.0 or math.isnan(r):
            return math.nan
        if lag > LAG_MAX_RAD or abs(r) > R1_MAX:
            return float(exact_overlap_factor(key[0], math.pi - span, math.pi, lag, r1=r, size_exp=key[1],
                                              r1_exp=key[2]))
        x = min(span * _PER_SPAN, SPAN_STEPS - 1e-9)
        y = min(lag * _PER_LAG, _LAG_LAST)
        z = min((r + R1_MAX) * _PER_R1, _R1_LAST)
        i, j, k = int(x), int(y), int(z)
        fx, fy, fz = x - i, y - j, z - k
        a0, a1, b0, b1 = lazy.quad(i, j)
        g = 1.0 - fz
        return (((a0[k] * g + a0[k + 1] * fz) * (1 - fy) + (a1[k] * g + a1[k + 1] * fz) * fy) * (1 - fx)
                + ((b0[k] * g + b0[k + 1] * fz) * (1 - fy) + (b1[k] * g + b1[k + 1] * fz) * fy) * fx)
    lazy = _lazy(key)
    table = lazy.table
    span, lag, r = np.broadcast_arrays(np.asarray(span, dtype=float), np.asarray(lag, dtype=float),
                                       np.asarray(r, dtype=float))
    ok = (span > 0.0) & (span <= math.pi + 1e-12) & (lag >= 0.0) & np.isfinite(r)
    x = np.clip(np.where(ok, span, 0.0) * _PER_SPAN, 0.0, SPAN_STEPS - 1e-9)
    y = np.clip(np.where(ok, lag, 0.0) * _PER_LAG, 0.0, table.shape[1] - 1 - 1e-9)
    z = np.clip((np.where(ok, r, 0.0) + R1_MAX) * _PER_R1, 0.0, table.shape[2] - 1 - 1e-9)
    i, j, k = x.astype(int), y.astype(int), z.astype(int)
    fx, fy, fz = x - i, y - j, z - k
    lazy.fill(np.concatenate([i, i, i + 1, i + 1]).ravel(), np.concatenate([j, j + 1, j, j + 1]).ravel())

    def at(ii, jj):
        return table[ii, jj, k] * (1 - fz) + table[ii, jj, k + 1] * fz

    eta = (at(i, j) * (1 - fy) + at(i, j + 1) * fy) * (1 - fx) + (at(i + 1, j) * (1 - fy) + at(i + 1, j + 1) * fy) * fx
    beyond = ok & ((lag > LAG_MAX_RAD) | (np.abs(r) > R1_MAX))
    if beyond.any():
        eta[beyond] = exact_overlap_factor(key[0], math.pi - span[beyond], math.pi, lag[beyond], r1=r[beyond],
                                           size_exp=key[1], r1_exp=key[2])
    return np.where(ok, eta, np.nan)
