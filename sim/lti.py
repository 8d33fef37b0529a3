"""Linear time-invariant filters for the simulated DAQ, run a block of samples at a time with numpy alone.

The plant's analog filters (the anti-alias low-pass, the feed servo's current loop) were scipy.signal's
``butter`` + ``sosfilt`` and ``lfilter``; importing scipy.signal costs about 0.8 CPU s, paid by every
emulator and capture the suite starts (hundreds a run; docs/testing.md). This computes the same
filters exactly (to float rounding; tests/sim/test_lti.py holds them to scipy's) without it.

**The filter as a state space.** A discrete filter is a state ``s`` (M numbers per channel) that each
input sample ``x`` moves on, ``s' = A·s + B·x``, and an output ``y = C·s + D·x``. A biquad section
``(b0, b1, b2; 1, a1, a2)`` in the transposed direct form II that scipy's ``sosfilt`` runs is

    A = [[−a1, 1], [−a2, 0]],   B = [b1 − a1·b0, b2 − a2·b0],   C = [1, 0],   D = b0,

and sections in series are one state space (``series``). **In blocks.** Over a block of L samples the
output is linear in the state at its start and in the block's inputs:

    y[i] = C·Aⁱ·s₀ + D·x[i] + Σ_{j<i} C·A^(i−j−1)·B·x[j],      s_L = A^L·s₀ + Σ_j A^(L−1−j)·B·x[j]

so a whole stream is a few matrix products per block (the L×L lower-triangular Toeplitz matrix of the
impulse response, the state's free response) and one small step per block carrying the state on: no
Python loop over samples. Its cost grows as L per sample, the loop's as 1/L: ``BLOCK`` = 64 sits
between (a 20-s capture at the plant's 10 kHz with 14 channels: about 30 ms).
"""

from __future__ import annotations

import cmath
import math

import numpy as np

BLOCK = 64


class StateSpace:
    """``s' = A·s + B·x``, ``y = C·s + D·x``: A (M, M), B (M,), C (M,), D a number."""

    def __init__(self, a: np.ndarray, b: np.ndarray, c: np.ndarray, d: float) -> None:
        self.a, self.b, self.c, self.d = (np.atleast_2d(np.asarray(a, float)), np.asarray(b, float).ravel(),
                                          np.asarray(c, float).ravel(), float(d))

    @property
    def order(self) -> int:
        return self.b.size


def biquad(b0: float, b1: float, b2: float, a1: float, a2: float) -> StateSpace:
    """One second-order section (a0 = 1) in the transposed direct form II (scipy's ``sosfilt``)."""
    return StateSpace([[-a1, 1.0], [-a2, 0.0]], [b1 - a1 * b0, b2 - a2 * b0], [1.0, 0.0], b0)


def first_order(b0: float, a1: float) -> StateSpace:
    """``y[n] = b0·x[n] − a1·y[n−1]``: scipy's ``lfilter([b0], [1, a1])``."""
    return StateSpace([[-a1]], [-a1 * b0], [1.0], b0)


def series(first: StateSpace, then: StateSpace) -> StateSpace:
    """`first`'s output into `then`'s input, as one state space (the first's state, then the second's)."""
    m1, m2 = first.order, then.order
    a = np.zeros((m1 + m2, m1 + m2))
    a[:m1, :m1] = first.a
    a[m1:, :m1] = np.outer(then.b, first.c)
    a[m1:, m1:] = then.a
    b = np.concatenate([first.b, then.b * first.d])
    c = np.concatenate([then.d * first.c, then.c])
    return StateSpace(a, b, c, then.d * first.d)


def butterworth_lowpass(order: int, cutoff_hz: float, rate_hz: float) -> StateSpace:
    """The digital Butterworth low-pass of scipy's ``butter(order, cutoff_hz, fs=rate_hz)``: the analog
    prototype's poles on a circle, the cut-off pre-warped (``2·fs·tan(π·fc/fs)``) so that the bilinear
    transform puts the −3 dB point exactly at ``cutoff_hz``, every zero at z = −1, unit gain at DC. The
    sections in series, conjugate pole pairs first, each with unit DC gain."""
    if order < 1:
        raise ValueError(f"filter order {order}: expected 1 or more")
    fs2 = 2.0 * rate_hz
    warped = fs2 * math.tan(math.pi * cutoff_hz / rate_hz)
    poles = [warped * cmath.exp(1j * math.pi * (2 * k + order + 1) / (2 * order)) for k in range(order)]
    digital = [(fs2 + p) / (fs2 - p) for p in poles]
    sections = []
    for z in digital:
        if z.imag > 1e-12:   # one of each conjugate pair: the section holds both
            a1, a2 = -2.0 * z.real, abs(z) ** 2
            g = (1.0 + a1 + a2) / 4.0
            sections.append(biquad(g, 2.0 * g, g, a1, a2))
        elif abs(z.imag) <= 1e-12:   # odd order: the real pole, one zero at −1
            a1 = -z.real
            g = (1.0 + a1) / 2.0
            sections.append(biquad(g, g, 0.0, a1, 0.0))
    out = sections[0]
    for s in sections[1:]:
        out = series(out, s)
    return out


class BlockFilter:
    """A state space run over (channels, n) arrays, its state carried from one call to the next."""

    def __init__(self, system: StateSpace, channels: int, block: int = BLOCK) -> None:
        self.sys, self.block = system, int(block)
        m, n = system.order, self.block
        a, b, c = system.a, system.b, system.c
        powers = [np.eye(m)]
        for _ in range(n):
            powers.append(powers[-1] @ a)
        self._a_n = powers[n]                                   # A^L
        self._free = np.stack([c @ powers[i] for i in range(n)])  # (L, M): row i = C·Aⁱ
        h = np.array([c @ powers[k] @ b for k in range(n)])      # impulse response after the first sample
        toeplitz = np.zeros((n, n))
        for i in range(n):
            toeplitz[i, i] = system.d
            toeplitz[i, :i] = h[:i][::-1]
        self._toeplitz = toeplitz                                # (L, L): y from the block's own inputs
        self._drive = np.stack([powers[n - 1 - j] @ b for j in range(n)], axis=1)  # (M, L): s_L from the inputs
        self._powers = powers
        self.state = np.zeros((channels, m))

    def prime(self, x0: np.ndarray) -> None:
        """The state of a filter that has seen the constant input x0 (per channel) for ever (scipy's
        ``sosfilt_zi`` times x0): s = A·s + B·x0."""
        m = self.sys.order
        steady = np.linalg.solve(np.eye(m) - self.sys.a, self.sys.b)
        self.state = np.asarray(x0, dtype=float)[:, None] * steady[None, :]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x: (C, n) → y: (C, n), the state moved on to after the last sample."""
        x = np.asarray(x, dtype=float)
        channels, n = x.shape
        length = self.block
        full = n // length
        y = np.empty_like(x)
        s = self.state
        if full:
            xb = x[:, :full * length].reshape(channels * full, length)   # 2-D: one BLAS product each
            pushed = (xb @ self._drive.T).reshape(channels, full, -1)     # what each block's inputs add
            starts = np.empty((channels, full, s.shape[1]))
            for k in range(full):                                # one small step a block, not a sample
                starts[:, k] = s
                s = s @ self._a_n.T + pushed[:, k]
            y[:, :full * length] = (starts.reshape(channels * full, -1) @ self._free.T
                                    + xb @ self._toeplitz.T).reshape(channels, -1)
        rest = n - full * length
        if rest:
            xr = x[:, full * length:]
            y[:, full * length:] = s @ self._free[:rest].T + xr @ self._toeplitz[:rest, :rest].T
            s = s @ self._powers[rest].T + xr @ self._drive[:, length - rest:].T
        self.state = s
        return y
