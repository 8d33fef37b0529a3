"""[D] Table 3: the published polynomial R_r(f_x, t_c), for comparison only ([D] eq. 11).

    R_r = Σ_{i=0..5} a_i·f_x^i,   a_i = Σ_{j=0..5} b_ji·t_c^j

The paper fits two coefficient sets, split at t_c = 0.08 mm/tooth: in Table 3
the first row of each a_i is "Up: t_c ≥ 0.08", the second "Down: t_c ≤ 0.08".
It was fitted to the SB40 model of [D] Table 2 in down milling and reports
< 10 % error; the daemon inverts eq. (10) exactly instead (``depth.py``).
"""

from __future__ import annotations

import numpy as np

# Rows a_0..a_5, columns b_0..b_5 (coefficient of t_c^0..t_c^5).
_B_HIGH_FEED = np.array(  # t_c >= 0.08 mm/tooth
    [
        [1.0025, 3.4923, -11.623, 21.686, -20.461, 7.5984],
        [1.9136, -0.19059, -0.06742, 0.72142, -0.99634, 0.44387],
        [0.25847, -3.5744, 12.287, -23.303, 22.155, -8.2614],
        [-0.39152, -0.54253, 1.7496, -4.1310, 4.5050, -1.8290],
        [-0.21953, 0.16053, -4.1888, 9.6520, -9.7718, 3.7465],
        [-0.00415, -1.3243, 2.0759, -2.1582, 1.2153, -0.27103],
    ]
)
_B_LOW_FEED = np.array(  # t_c <= 0.08 mm/tooth
    [
        [0.48209, 35.217, -949.34, 15433, -131787, 453367],
        [1.6708, 18.147, -617.33, 10869, -96461, 339318],
        [0.69838, -27.238, 644.45, -9779.0, 80459, -270859],
        [-0.01002, -23.504, 641.61, -9802.3, 78650, -257044],
        [-0.03118, -24.362, 1024.9, -20092, 188567, -685683],
        [-0.32220, 22.946, -816.17, 14382, -127382, 447205],
    ]
)
SPLIT_FEED_PER_TOOTH_MM = 0.08


def table3_coefficients(feed_per_tooth_mm) -> np.ndarray:
    """a_0..a_5 of eq. (11) at each t_c, shape ``t_c.shape + (6,)``."""
    t_c = np.asarray(feed_per_tooth_mm, dtype=float)
    powers = t_c[..., None] ** np.arange(6)  # (..., j)
    high = powers @ _B_HIGH_FEED.T
    low = powers @ _B_LOW_FEED.T
    return np.where((t_c >= SPLIT_FEED_PER_TOOTH_MM)[..., None], high, low)


def radial_ratio_table3(fx, feed_per_tooth_mm):
    """R_r from f_x by [D]'s Table 3 polynomial (eq. 11); no range check, as published."""
    f = np.asarray(fx, dtype=float)
    a = table3_coefficients(feed_per_tooth_mm)
    return np.sum(a * f[..., None] ** np.arange(6), axis=-1)
