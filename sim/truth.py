"""Per-revolution truth: what really happened in the plant, one JSON line per spindle turn.

Revolution boundaries are the instants the true spindle angle crosses a
multiple of 2π (the angle is 0 at sample 0, so revolution r ends when the
4096-count encoder reaches 4096·(r+1)).  ``index_end`` is the revolution's last
1 kHz sample (the one just before the boundary), ``t_end_s`` the exact boundary
time.  Means are integrals of exact interval means (see ``cutting_forces``) split
at the boundary instants, so a boundary between samples gets fractional weights.

``steady``: over this revolution and the one before, the programmed depths at the
tool centre, the feed target and the speed command did not change, no depth step
lay under the tool (centre to leading edge), the feed was within 0.5 % and the
speed within 1 % of constant and within 0.5 % of its command, no feed hold.  A
taper or ramp is therefore never steady.  Events (``{"event": ...}``) are
``crash_power``, ``tool_breakage``, ``feed_hold`` and ``scenario_restart``.
The part program adds one ``{"process": ...}`` line per monitored process
(``sim/program.py``); a revolution is a record with ``rev``.
Only the last ``keep`` records are held (a looping demo runs for days).
"""

from __future__ import annotations

import json
from collections import deque

import numpy as np

MEAN_FIELDS = (
    ("torque_nm", "torque_nm"),
    ("force_n", "force_n"),
    ("force_x_n", "fx_n"),
    ("force_y_n", "fy_n"),
    ("force_z_n", "fz_n"),
    ("force_tangential_n", "ft_n"),
    ("feed_per_tooth_mm", "feed_per_tooth_mm"),
    ("radial_depth_mm", "radial_depth_mm"),
    ("axial_depth_mm", "axial_depth_mm"),
    ("airgap_power_w", "airgap_w"),
    ("feed_mm_min", "feed_mm_min"),  # the feed the machine really moved at (the override's effect)
    ("feed_override_pct", "feed_override_pct"),  # the CNC's applied feed override
)
CUTTING_MIN_N = 0.01  # "cutting" = some tangential force above this (grazing edges leave numerical dust)
# quantities that must not change over a revolution and the one before for it to be steady:
# name -> (absolute tolerance, relative tolerance)
STEADY_TOLERANCES = {
    "axial_mm": (1e-6, 0.0),
    "radial_mm": (1e-6, 0.0),
    "feed_target_mm_s": (1e-9, 0.0),
    "rpm_command": (1e-9, 0.0),
    "feed_mm_s": (1e-6, 0.005),
    "spindle_rpm": (0.0, 0.01),
}
# quantities that must stay below a bound: a depth change between the tool centre and its leading
# edge (the engaged cutting edges are all at x = s + R·sin φ in [s, s + R]) means the tool is entering
# a step or the part; a speed off its command by more than 0.5 % is a transient (ramp, overshoot)
STEADY_MAX = {"axial_jump_mm": 1e-6, "radial_jump_mm": 1e-6, "speed_error": 0.005}


class TruthRecorder:
    """Collects revolution records and events; ``drain()`` hands out the new ones."""

    def __init__(self, gear: str, sample_rate_hz: int, keep: int = 50_000) -> None:
        self.gear = gear
        self.sample_rate_hz = sample_rate_hz
        self.records: deque[dict] = deque(maxlen=keep)
        self._pending: deque[dict] = deque(maxlen=keep)
        self.active = False
        self._rev = 0
        self._prev_t: float | None = None
        self._acc: np.ndarray | None = None
        self._win: dict[str, list[float]] | None = None
        self._prev_win: dict[str, list[float]] | None = None
        self._held = False
        self._cut = False

    # -- public -----------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.records)

    def __iter__(self):
        return iter(list(self.records))

    def revolutions(self) -> list[dict]:
        return [r for r in self.records if "rev" in r]

    def events(self) -> list[dict]:
        return [r for r in self.records if "event" in r]

    def drain(self) -> list[dict]:
        out = list(self._pending)
        self._pending.clear()
        return out

    def write_jsonl(self, path) -> None:
        with open(path, "w", encoding="utf-8") as fh:
            for r in self.records:
                fh.write(json.dumps(r) + "\n")

    # -- fed by the plant -------------------------------------------------------
    def note(self, record: dict) -> None:
        """Another kind of record (the part program's per-process lines), kept in arrival order."""
        self.records.append(record)
        self._pending.append(record)

    def start(self, t_s: float) -> None:
        """Begin recording at a revolution boundary (spindle angle 0) at time t_s."""
        self.active = True
        self._prev_t = float(t_s)
        self._acc = np.zeros(len(MEAN_FIELDS))

    def add_block(self, t0_s: float, dt_s: float, means: dict[str, np.ndarray], tracked: dict[str, np.ndarray],
                  held: np.ndarray, boundaries_s: np.ndarray, last_index: list[int], events: list[dict]) -> None:
        """One block of midpoint samples (interval i is [t0 + i·dt, t0 + (i+1)·dt)); a boundary at
        ``boundaries_s[j]`` closes a revolution whose last 1 kHz sample is ``last_index[j]``."""
        if not self.active:
            return
        keys = [src for _, src in MEAN_FIELDS]
        q = np.stack([np.asarray(means[k], dtype=float) for k in keys])  # (K, n)
        n = q.shape[1]
        cum = np.concatenate([np.zeros((len(keys), 1)), np.cumsum(q * dt_s, axis=1)], axis=1)
        t_mid = t0_s + (np.arange(n) + 0.5) * dt_s
        out: list[dict] = list(events)
        last_c = np.zeros(len(keys))
        last_pos = 0
        for tb, k_last in zip(boundaries_s, last_index, strict=True):
            i = min(max(int((tb - t0_s) // dt_s), 0), n - 1)
            c_b = cum[:, i] + q[:, i] * (tb - (t0_s + i * dt_s))
            pos = int(np.searchsorted(t_mid, tb))
            self._track(tracked, held, q, last_pos, pos)
            if self._prev_t is not None and self._acc is not None:
                integral = self._acc + (c_b - last_c)
                out.append(self._record(tb, k_last, integral / (tb - self._prev_t)))
            self._prev_t = float(tb)
            self._acc = np.zeros(len(keys))
            self._prev_win, self._win = self._win, None
            self._held = self._cut = False
            last_c, last_pos = c_b, pos
        if self._prev_t is not None:
            self._acc = (self._acc if self._acc is not None else 0.0) + (cum[:, -1] - last_c)
            self._track(tracked, held, q, last_pos, n)
        out.sort(key=lambda r: r.get("t_s", r.get("t_end_s", 0.0)))
        self.records.extend(out)
        self._pending.extend(out)

    # -- internals --------------------------------------------------------------
    def _track(self, tracked, held, q, a: int, b: int) -> None:
        if b <= a:
            return
        if self._win is None:
            self._win = {k: [float("inf"), float("-inf")] for k in tracked}
        for k, v in tracked.items():
            seg = v[a:b]
            w = self._win[k]
            w[0] = min(w[0], float(seg.min()))
            w[1] = max(w[1], float(seg.max()))
        self._held = self._held or bool(held[a:b].any())
        ft = q[5, a:b]  # tangential force
        self._cut = self._cut or bool((ft > CUTTING_MIN_N).any())

    def _steady(self) -> bool:
        if self._win is None or self._prev_win is None or self._held or self._prev_held:
            return False
        for k, bound in STEADY_MAX.items():
            if k in self._win and max(self._win[k][1], self._prev_win[k][1]) > bound:
                return False
        for k, (tol_abs, tol_rel) in STEADY_TOLERANCES.items():
            if k not in self._win:
                continue
            lo = min(self._win[k][0], self._prev_win[k][0])
            hi = max(self._win[k][1], self._prev_win[k][1])
            if hi - lo > tol_abs + tol_rel * max(abs(hi), abs(lo)):
                return False
        return True

    _prev_held = False

    def _record(self, tb: float, k_last: int, mean: np.ndarray) -> dict:
        rec = {
            "rev": self._rev,
            "index_end": int(k_last),
            "t_end_s": round(float(tb), 7),
            "spindle_rpm": round(float(60.0 / (tb - self._prev_t)), 4),
            "gear": self.gear,
        }
        for (name, _), value in zip(MEAN_FIELDS, mean, strict=True):
            rec[name] = round(float(value), 6)
        rec["cutting"] = self._cut
        rec["steady"] = self._steady()
        rec["feed_hold"] = self._held
        self._prev_held = self._held
        self._rev += 1
        return rec
