"""The envelope of one process key: learned from good processes, adjusted by the operator. Pure.

From N good processes, each a per-revolution array indexed by `process_rev`
(revolutions since entry), for every k:

    mean_k, std_k                       over the processes that reached k (std: ddof 1)
    h_k   = max(sigma·std_k, min_width_pct/100·|mean_k|, min_width_nm)     (high side)
    h'_k  = max(sigma·std_k, min_width_low_pct/100·|mean_k|, min_width_nm) (low side)
    high_k = max_{j=k-1..k+1} (mean_j + h_j)
    low_k  = max(0, min_{j=k-1..k+1} (mean_j − h'_j))

Why the neighbours: entry is found to the revolution, so a later process may
be one revolution early or late against the learned mean, which at a depth
step is a whole step of torque; the band at k is the union of the bands of
k−1 … k+1. Why a separate low-side width: the width in % on the high side must
exceed the wear warning (`wear_rise_pct`) so that a wearing tool warns before
it trips; the low side has no wear to absorb (wear only raises torque) and a
broken flute lowers torque by only 15–25 % ([D] eq. 9, the next flute takes a
double chip at a lower specific force), so its width in % is narrower
(`min_width_low_pct`, default half of `min_width_pct`).

Force gets a band where every learned process that reached k knew its force.
Also learned: the length (median, the lower middle one), the entry offset
(revolutions from process start to entry: mean, std, max) and the cutting
energy baseline (mean, std).
"""

from __future__ import annotations

import math
import statistics
from array import array
from dataclasses import dataclass, field
from typing import Any

import numpy as np

FALSE_ALARM_MARGIN_PCT = 10.0   # a value marked as a false alarm fits with this much room
MAX_ADJUSTMENTS = 50            # adjustments remembered per key (the newest)


def setting(section: Any, name: str, default: Any) -> Any:
    value = getattr(section, name, None) if section is not None else None
    return default if value is None else value


@dataclass(frozen=True)
class Widths:
    """The width settings of `[learning]` for one quantity."""

    sigma: float = 4.0
    pct: float = 25.0            # high side, % of |mean|
    low_pct: float = 12.5        # low side, % of |mean|
    floor: float = 0.5           # N·m (torque) or N (force)
    low_revolutions: int = 3

    @classmethod
    def of(cls, learning: Any, quantity: str = "torque_nm") -> "Widths":
        pct = float(setting(learning, "min_width_pct", 25.0))
        floor_name = "min_width_n" if quantity == "force_n" else "min_width_nm"
        return cls(float(setting(learning, "sigma", 4.0)), pct,
                   float(setting(learning, "min_width_low_pct", pct / 2.0)),
                   float(setting(learning, floor_name, 50.0 if quantity == "force_n" else 0.5)),
                   int(setting(learning, "low_revolutions", 3)))


@dataclass
class Taught:
    """One good process kept for learning."""

    torque_nm: np.ndarray   # per process_rev, NaN where the revolution was invalid
    force_n: np.ndarray     # NaN where the force was not known
    entry_rev: int          # revolutions from the process's start to its entry
    energy_j: float

    def to_dict(self) -> dict[str, Any]:
        return {"torque_nm": json_list(self.torque_nm), "force_n": json_list(self.force_n),
                "entry_rev": int(self.entry_rev), "energy_j": float(self.energy_j)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Taught":
        return cls(_array(d["torque_nm"]), _array(d["force_n"]), int(d["entry_rev"]), float(d["energy_j"]))


def json_list(a: np.ndarray) -> list[float | None]:
    """JSON-safe: NaN (no value) as None."""
    return [None if not math.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).tolist()]


def _array(values: Any) -> np.ndarray:
    return np.array([math.nan if v is None else float(v) for v in values], dtype=float)


@dataclass
class Band:
    """The band of one quantity along process_rev; NaN where there is none."""

    mean: np.ndarray
    std: np.ndarray
    h_high: np.ndarray
    h_low: np.ndarray
    floor_high: np.ndarray    # the configured floors: `narrow` never goes below them
    floor_low: np.ndarray
    # per k, NaN where there is no band: array('d') is 8 bytes a value (a list of floats 32) and
    # indexes to a Python float (one lookup per revolution, no numpy call)
    high_nan: array = field(init=False)
    low_nan: array = field(init=False)

    def __post_init__(self) -> None:
        self.refresh()

    def bounds(self, k: int) -> tuple[float | None, float | None]:
        """(low, high) at process_rev k; None where there is no band."""
        low, high = self.low_nan[k], self.high_nan[k]
        return (None, None) if high != high else (low, high)   # NaN != NaN

    @property
    def high(self) -> list[float | None]:
        return [None if v != v else v for v in self.high_nan]

    @property
    def low(self) -> list[float | None]:
        return [None if v != v else v for v in self.low_nan]

    @classmethod
    def learn(cls, mean: np.ndarray, std: np.ndarray, w: Widths) -> "Band":
        floor_high = np.maximum(w.pct / 100.0 * np.abs(mean), w.floor)
        floor_low = np.maximum(w.low_pct / 100.0 * np.abs(mean), w.floor)
        return cls(mean, std, np.maximum(w.sigma * std, floor_high), np.maximum(w.sigma * std, floor_low),
                   floor_high, floor_low)

    def refresh(self) -> None:
        """high/low from mean and half-widths, each the union over k−1 … k+1 (see the module doc)."""
        up = self.mean + self.h_high
        down = self.mean - self.h_low
        n = len(self.mean)
        high = array("d", [math.nan]) * n
        low = array("d", [math.nan]) * n
        for k in range(n):
            if math.isnan(self.mean[k]):
                continue
            high[k] = float(np.nanmax(up[max(k - 1, 0): k + 2]))
            low[k] = max(float(np.nanmin(down[max(k - 1, 0): k + 2])), 0.0)
        self.high_nan, self.low_nan = high, low

    def scale(self, factor: float) -> None:
        """Widen (factor > 1) or narrow (< 1) every half-width, never below the floors."""
        self.h_high = np.maximum(self.h_high * factor, self.floor_high)
        self.h_low = np.maximum(self.h_low * factor, self.floor_low)
        self.refresh()

    def fit(self, level: str, observed: dict[int, float], margin_pct: float) -> None:
        """Widen at the revolutions observed so that each value fits with `margin_pct` to spare."""
        m = margin_pct / 100.0
        for k, v in observed.items():
            if not 0 <= k < len(self.mean) or math.isnan(self.mean[k]):
                continue
            if level == "envelope_high":
                self.h_high[k] = max(self.h_high[k], v + m * abs(v) - self.mean[k])
            else:
                self.h_low[k] = max(self.h_low[k], self.mean[k] - (v - m * abs(v)))
        self.refresh()

    def to_dict(self) -> dict[str, Any]:
        return {name: json_list(getattr(self, name)) for name in ("mean", "std", "h_high", "h_low", "floor_high", "floor_low")}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Band":
        return cls(*(_array(d[name]) for name in ("mean", "std", "h_high", "h_low", "floor_high", "floor_low")))


@dataclass
class Envelope:
    """What was learned for one process key, with the operator's adjustments."""

    n: int                    # processes learned from
    length: int               # learned length in revolutions from entry
    torque: Band
    force: Band | None
    entry_mean: float
    entry_std: float
    entry_max: int
    entry_margin: float       # revolutions past the latest learned entry before "no entry"
    entry_floor: float
    energy_mean_j: float
    energy_std_j: float
    energy_h_j: float         # the energy band's low half-width
    energy_floor_j: float
    adjustments: list[dict[str, Any]] = field(default_factory=list)

    # -- checks ------------------------------------------------------------
    @property
    def entry_deadline(self) -> int:
        """A process with no entry by this revolution (counted from its start) misses its part or tool."""
        return int(math.ceil(self.entry_max + self.entry_margin))

    @property
    def cut_length(self) -> int:
        """Revolutions from entry to the last one where the band expects cutting (low > 0)."""
        return max((k + 1 for k, low in enumerate(self.torque.low_nan) if low > 0), default=0)   # NaN > 0 is False

    @property
    def energy_low_j(self) -> float:
        return self.energy_mean_j - self.energy_h_j

    # -- operator adjustments ---------------------------------------------
    def widen(self, pct: float) -> None:
        self._scale(1.0 + pct / 100.0)
        self._note({"action": "widen", "pct": float(pct)})

    def narrow(self, pct: float) -> None:
        self._scale(1.0 - pct / 100.0)
        self._note({"action": "narrow", "pct": float(pct)})

    def _scale(self, factor: float) -> None:
        for band in (self.torque, self.force):
            if band is not None:
                band.scale(factor)
        self.entry_margin = max(self.entry_margin * factor, self.entry_floor)
        self.energy_h_j = max(self.energy_h_j * factor, self.energy_floor_j)

    def false_alarm(self, level: str, quantity: str, observed: dict[int, float],
                    margin_pct: float = FALSE_ALARM_MARGIN_PCT) -> None:
        """The operator says an alarm was false: widen where it was raised so that what was seen fits.

        `observed`: process_rev → value for torque/force; for "entry" {0: revolutions
        without entry}; for "cutting_energy_j" {0: the process's energy}.
        """
        m = margin_pct / 100.0
        if quantity == "entry":
            seen = max(observed.values(), default=0.0)
            self.entry_margin = max(self.entry_margin, seen * (1.0 + m) + 1.0 - self.entry_max)
        elif quantity == "cutting_energy_j":
            seen = min(observed.values(), default=self.energy_mean_j)
            self.energy_h_j = max(self.energy_h_j, self.energy_mean_j - seen * (1.0 - m))
        else:
            band = self.force if quantity == "force_n" else self.torque
            if band is not None:
                band.fit(level, observed, margin_pct)
        ks = sorted(observed)
        self._note({"action": "false_alarm", "level": level, "quantity": quantity,
                    "revs": [ks[0], ks[-1]] if ks else []})

    def _note(self, adjustment: dict[str, Any]) -> None:
        self.adjustments.append(adjustment)
        del self.adjustments[:-MAX_ADJUSTMENTS]

    # -- persistence -------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n, "length": self.length, "torque": self.torque.to_dict(),
            "force": None if self.force is None else self.force.to_dict(),
            "entry": {"mean": self.entry_mean, "std": self.entry_std, "max": self.entry_max,
                      "margin": self.entry_margin, "floor": self.entry_floor},
            "energy": {"mean_j": self.energy_mean_j, "std_j": self.energy_std_j, "h_j": self.energy_h_j,
                       "floor_j": self.energy_floor_j},
            "adjustments": [dict(a) for a in self.adjustments],
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Envelope":
        entry, energy = d["entry"], d["energy"]
        return cls(int(d["n"]), int(d["length"]), Band.from_dict(d["torque"]),
                   None if d.get("force") is None else Band.from_dict(d["force"]),
                   float(entry["mean"]), float(entry["std"]), int(entry["max"]), float(entry["margin"]),
                   float(entry["floor"]), float(energy["mean_j"]), float(energy["std_j"]), float(energy["h_j"]),
                   float(energy["floor_j"]), [dict(a) for a in d.get("adjustments", [])])


def _stats(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column: mean, std (ddof 1; 0 with fewer than 2 values), count of finite values."""
    finite = np.isfinite(rows)
    count = finite.sum(axis=0)
    total = np.where(finite, rows, 0.0).sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
        dev = np.where(finite, rows - mean, 0.0)
        var = np.where(count > 1, (dev ** 2).sum(axis=0) / np.maximum(count - 1, 1), 0.0)
    return mean, np.sqrt(var), count


def _sample_std(values: list[float]) -> float:
    return statistics.stdev(values) if len(values) > 1 else 0.0


def learn(taught: list[Taught], learning: Any) -> Envelope:
    """The envelope of N good processes (N ≥ 1), with the `[learning]` settings."""
    if not taught:
        raise ValueError("an envelope needs at least one process")
    length = int(statistics.median_low([len(t.torque_nm) for t in taught]))
    torque = np.full((len(taught), length), np.nan)
    force = np.full((len(taught), length), np.nan)
    for i, t in enumerate(taught):
        n = min(len(t.torque_nm), length)
        torque[i, :n] = t.torque_nm[:n]
        force[i, :n] = t.force_n[:n]
    mean, std, count = _stats(torque)
    w_torque = Widths.of(learning, "torque_nm")
    torque_band = Band.learn(mean, std, w_torque)
    # force only where every process that has a torque at k also knew its force there
    reached = np.isfinite(torque)
    known = np.all(np.isfinite(force) | ~reached, axis=0) & (count > 0)
    force_band = None
    if known.any():
        f_mean, f_std, _ = _stats(np.where(known, force, np.nan))
        force_band = Band.learn(f_mean, f_std, Widths.of(learning, "force_n"))
    entries = [float(t.entry_rev) for t in taught]
    energies = [float(t.energy_j) for t in taught]
    entry_mean, entry_std = statistics.fmean(entries), _sample_std(entries)
    energy_mean, energy_std = statistics.fmean(energies), _sample_std(energies)
    # entry: as late as the latest learned one, plus room for the spread (never less than low_revolutions)
    entry_floor = float(w_torque.low_revolutions)
    entry_margin = max(entry_floor, w_torque.sigma * entry_std, w_torque.pct / 100.0 * entry_mean)
    energy_floor = w_torque.low_pct / 100.0 * abs(energy_mean)
    return Envelope(len(taught), length, torque_band, force_band, entry_mean, entry_std, int(max(entries)),
                    entry_margin, entry_floor, energy_mean, energy_std,
                    max(w_torque.sigma * energy_std, energy_floor), energy_floor)
