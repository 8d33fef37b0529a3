"""Shared helpers for the plant tests: physical values from raw counts, first-principles formulas.

The scales come from docs/architecture.md ("Simulated sensors"), the datasheet
the simulator promises; the formulas are written out here, not imported from
the daemon or from the plant.
"""

from __future__ import annotations

import math

import numpy as np

SCALES = {"v_uv": 0.02, "v_vw": 0.02, "v_wu": 0.02, "i_u": 0.002, "i_v": 0.002, "i_w": 0.002, "sp_rpm": 0.1,
          "mot_rpm": 0.2, "ix_feed": 0.001, "fx_rate": 0.1, "fx": 0.5, "fy": 0.5, "fz": 0.5}


def physical(plant, counts: np.ndarray) -> dict[str, np.ndarray]:
    out = {}
    for c, name in enumerate(plant.descriptor.names):
        col = counts[:, c]
        out[name] = col.astype(float) * SCALES[name] if name in SCALES else col
    return out


def electrical_hz(v: np.ndarray, fs: float = 1000.0) -> float:
    """Frequency from rising zero crossings (interpolated) of a sampled sinusoid."""
    idx = np.flatnonzero((v[:-1] < 0) & (v[1:] >= 0))
    t = (idx + (-v[idx]) / (v[idx + 1] - v[idx])) / fs
    return (len(t) - 1) / (t[-1] - t[0])


def butterworth2_gain(f_hz: float, fc_hz: float) -> float:
    return 1.0 / math.sqrt(1.0 + (f_hz / fc_hz) ** 4)


def airgap_power_w(sig: dict[str, np.ndarray], r_s: float) -> np.ndarray:
    """Instantaneous p_in − p_cu of a delta machine from line quantities ([P] eq. 11)."""
    vuv, vvw, vwu = sig["v_uv"], sig["v_vw"], sig["v_wu"]
    iu, iv, iw = sig["i_u"], sig["i_v"], sig["i_w"]
    p_in = (vuv * (iu - iv) + vvw * (iv - iw) + vwu * (iw - iu)) / 3
    i_uv, i_vw, i_wu = (iu - iv) / 3, (iv - iw) / 3, (iw - iu) / 3  # delta, no circulating current
    return p_in - r_s * (i_uv**2 + i_vw**2 + i_wu**2)


def steady_cut_revs(revs: list[dict]) -> list[dict]:
    return [r for r in revs if r["steady"] and r["cutting"]]
