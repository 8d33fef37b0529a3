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

The operator's adjustments (`widen`, `narrow`, `false_alarm`) are bounded on
both sides, after every change and at restore (`Envelope.bound`):

- every half-width at most MAX_WIDENING times the one learned (widening since
  the last relearn is capped; a `widen` past it is refused, `WideningCapped`);
- the high side never above the fixed `[alarms]` limit of its quantity
  (`torque_limit_nm`, `force_limit_n`: that limit trips every cut anyway);
- the low side, and the energy band's, never more than LOW_MAX_FRACTION below the
  learned mean (unless it was learned lower): a broken flute (15-25 %) or a missing
  tool still fall below it; turning `envelope_low` off is its own command.
A stored envelope is checked value by value when it is read (`from_dict`): a
number that is missing, of the wrong type, not finite or beyond MAX_MAGNITUDE
raises ValueError naming the field.
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
# Operator adjustments never take a half-width past this multiple of the one learned (docs/learning.md): a band
# widened 4x is already 100 % above the mean at the default 25 % floor. Before, 400 `widen --pct 500` overflowed
# every width to inf, stored as null, and the daemon could no longer start.
MAX_WIDENING = 4.0
# ... and never take the low side more than this share of the learned mean below it (unless learned lower): a
# broken flute of a two-flute cutter (about 25 % less torque, [D] eq. 9) and a missing tool (none) stay below it.
LOW_MAX_FRACTION = 0.20
MAX_MAGNITUDE = 1e9             # a stored number beyond this (N·m, N, J, revolutions) is not a learned value


class WideningCapped(ValueError):
    """A `widen` that would pass MAX_WIDENING since the last relearn (refused, nothing changed)."""


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
    def from_dict(cls, d: Any, where: str = "taught") -> "Taught":
        """A stored process, every value checked (ValueError naming the field)."""
        d = _mapping(d, where)
        torque = _checked_array(d.get("torque_nm"), f"{where}.torque_nm")
        return cls(torque, _checked_array(d.get("force_n"), f"{where}.force_n", len(torque)),
                   _whole(d.get("entry_rev"), f"{where}.entry_rev"), _number(d.get("energy_j"), f"{where}.energy_j"))


def json_list(a: np.ndarray) -> list[float | None]:
    """JSON-safe: NaN (no value) as None."""
    return [None if not math.isfinite(x) else float(x) for x in np.asarray(a, dtype=float).tolist()]


@dataclass
class Band:
    """The band of one quantity along process_rev; NaN where there is none."""

    mean: np.ndarray
    std: np.ndarray
    h_high: np.ndarray
    h_low: np.ndarray
    floor_high: np.ndarray    # the configured floors: `narrow` never goes below them
    floor_low: np.ndarray
    sigma: float = 4.0        # the sigma it was learned with: the learned half-widths are max(sigma·std, floor)
    ceiling: float | None = None   # the fixed [alarms] limit of its quantity (not stored: the config's)
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
                   floor_high, floor_low, float(w.sigma))

    @property
    def learned_high(self) -> np.ndarray:
        """The half-widths as learned (high side): what MAX_WIDENING multiplies."""
        return np.maximum(self.sigma * self.std, self.floor_high)

    @property
    def learned_low(self) -> np.ndarray:
        return np.maximum(self.sigma * self.std, self.floor_low)

    def widening(self) -> float:
        """The largest half-width over the one learned (1.0 as learned), over both sides."""
        ratios = [_ratio(h, h0) for h, h0 in ((self.h_high, self.learned_high), (self.h_low, self.learned_low))]
        return max(ratios)

    def bound(self) -> None:
        """Hold every half-width within its bounds (module doc), then recompute high/low."""
        mean = self.mean
        with np.errstate(invalid="ignore"):
            cap_high = MAX_WIDENING * self.learned_high
            if self.ceiling is not None:
                cap_high = np.minimum(cap_high, np.maximum(self.ceiling - mean, 0.0))
            h0_low = self.learned_low
            cap_low = np.minimum(MAX_WIDENING * h0_low, np.maximum(h0_low, LOW_MAX_FRACTION * np.abs(mean)))
            self.h_high = np.minimum(self.h_high, cap_high)
            self.h_low = np.minimum(self.h_low, cap_low)
        self.refresh()

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
        """Widen (factor > 1) or narrow (< 1) every half-width, never below the floors, within the bounds."""
        self.h_high = np.maximum(self.h_high * factor, self.floor_high)
        self.h_low = np.maximum(self.h_low * factor, self.floor_low)
        self.bound()

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
        self.bound()

    def fits(self, level: str, observed: dict[int, float]) -> bool:
        """Every value observed inside the band on the side of `level` (after a `fit`, unless bounded)."""
        for k, v in observed.items():
            if not 0 <= k < len(self.mean) or math.isnan(self.mean[k]):
                continue
            low, high = self.bounds(k)
            if high is not None and (v > high if level == "envelope_high" else low > 0 and v < low):
                return False
        return True

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {name: json_list(getattr(self, name)) for name in _BAND_ARRAYS}
        out["sigma"] = self.sigma
        return out

    @classmethod
    def from_dict(cls, d: Any, length: int, sigma: float, where: str) -> "Band":
        """A stored band, every value checked (ValueError naming the field); `sigma`: for a band stored
        before it was kept (the config's)."""
        d = _mapping(d, where)
        arrays = [_checked_array(d.get(name), f"{where}.{name}", length) for name in _BAND_ARRAYS]
        known = np.isfinite(arrays[0])
        for name, values in zip(_BAND_ARRAYS[1:], arrays[1:]):
            if not np.all(np.isfinite(values[known]) & (values[known] >= 0.0)):
                raise ValueError(f"{where}.{name}: not a finite number >= 0 where the mean is known")
        sigma = _number(d.get("sigma", sigma), f"{where}.sigma", 0.0, MAX_MAGNITUDE)
        return cls(*arrays, sigma=sigma)


_BAND_ARRAYS = ("mean", "std", "h_high", "h_low", "floor_high", "floor_low")


def _ratio(h: np.ndarray, h0: np.ndarray) -> float:
    """max(h / h0) where both are known and h0 > 0; 1.0 where nothing compares."""
    with np.errstate(invalid="ignore", divide="ignore"):
        ok = np.isfinite(h) & np.isfinite(h0) & (h0 > 0)
        return float(np.max(h[ok] / h0[ok])) if ok.any() else 1.0


def _scalar_ratio(h: float, h0: float) -> float:
    return h / h0 if h0 > 0 else 1.0


def _mapping(d: Any, where: str) -> dict[str, Any]:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: not an object ({type(d).__name__})")
    return d


def _number(value: Any, where: str, low: float = -MAX_MAGNITUDE, high: float = MAX_MAGNITUDE) -> float:
    """A stored number: int or float (not bool), finite, within [low, high]; ValueError naming it otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where}: not a number ({'missing' if value is None else type(value).__name__})")
    number = float(value) if not isinstance(value, int) or abs(value) <= 2 * MAX_MAGNITUDE else math.inf
    if not math.isfinite(number) or not low <= number <= high:
        raise ValueError(f"{where}: {value!r} is not a finite number in {low:g} … {high:g}")
    return number


def _whole(value: Any, where: str, low: int = 0, high: int = 10**9) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{where}: {value!r} is not a whole number in {low} … {high}")
    return value


def _checked_array(values: Any, where: str, length: int | None = None) -> np.ndarray:
    """A stored per-revolution list: numbers or null (no value), finite; `length` long when given."""
    if not isinstance(values, list):
        raise ValueError(f"{where}: not a list ({'missing' if values is None else type(values).__name__})")
    if length is not None and len(values) != length:
        raise ValueError(f"{where}: {len(values)} values, not {length}")
    return np.array([math.nan if v is None else _number(v, f"{where}[{i}]") for i, v in enumerate(values)],
                    dtype=float)


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
    entry_margin_learned: float = math.nan   # as learned: what MAX_WIDENING multiplies (NaN: the current one)
    energy_h_learned_j: float = math.nan

    def __post_init__(self) -> None:
        if math.isnan(self.entry_margin_learned):
            self.entry_margin_learned = self.entry_margin
        if math.isnan(self.energy_h_learned_j):
            self.energy_h_learned_j = self.energy_h_j

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

    # -- bounds (module doc) -----------------------------------------------
    def set_ceilings(self, torque_nm: float | None, force_n: float | None) -> None:
        """The fixed [alarms] limits the high side never passes; the envelope is bounded at once."""
        self.torque.ceiling = torque_nm
        if self.force is not None:
            self.force.ceiling = force_n
        self.bound()

    def bound(self) -> None:
        """Every half-width within its bounds: MAX_WIDENING × learned, the fixed limit, the low floor."""
        for band in (self.torque, self.force):
            if band is not None:
                band.bound()
        self.entry_margin = min(self.entry_margin, MAX_WIDENING * self.entry_margin_learned)
        h0 = self.energy_h_learned_j
        self.energy_h_j = min(self.energy_h_j, MAX_WIDENING * h0, max(h0, LOW_MAX_FRACTION * abs(self.energy_mean_j)))

    def widening(self) -> float:
        """How far the widest half-width is from the one learned (1.0: as learned; at most MAX_WIDENING)."""
        ratios = [band.widening() for band in (self.torque, self.force) if band is not None]
        ratios += [_scalar_ratio(self.entry_margin, self.entry_margin_learned),
                   _scalar_ratio(self.energy_h_j, self.energy_h_learned_j)]
        return max(ratios)

    # -- operator adjustments ---------------------------------------------
    def widen(self, pct: float) -> None:
        """Every half-width × (1 + pct/100), within the bounds; WideningCapped (nothing changed) past MAX_WIDENING."""
        factor = 1.0 + pct / 100.0
        now = self.widening()
        if not math.isfinite(factor) or factor <= 0 or now * factor > MAX_WIDENING * (1.0 + 1e-9):
            room = max(math.floor((MAX_WIDENING / now - 1.0) * 100.0 + 1e-6), 0) if now > 0 else 0
            raise WideningCapped(
                f"widening is capped at {MAX_WIDENING:g}× the learned width since the last relearn "
                f"(now {now:.2f}×, {pct:g} % more would make {now * factor:.2f}×): "
                + (f"at most {room} % more" if room >= 1 else "no more") + ", or relearn it")
        self._scale(factor)
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
        self.bound()

    def false_alarm(self, level: str, quantity: str, observed: dict[int, float],
                    margin_pct: float = FALSE_ALARM_MARGIN_PCT) -> bool:
        """The operator says an alarm was false: widen where it was raised so that what was seen fits.

        `observed`: process_rev → value for torque/force; for "entry" {0: revolutions
        without entry}; for "cutting_energy_j" {0: the process's energy}. Within the
        bounds: False when they kept what was seen from fitting (the alarm may come again).
        """
        m = margin_pct / 100.0
        observed = {k: v for k, v in observed.items() if v is not None and math.isfinite(v)}
        fits = True
        if quantity == "entry":
            seen = max(observed.values(), default=0.0)
            self.entry_margin = max(self.entry_margin, seen * (1.0 + m) + 1.0 - self.entry_max)
            self.bound()
            fits = self.entry_deadline > seen
        elif quantity == "cutting_energy_j":
            seen = min(observed.values(), default=self.energy_mean_j)
            self.energy_h_j = max(self.energy_h_j, self.energy_mean_j - seen * (1.0 - m))
            self.bound()
            fits = self.energy_low_j <= seen
        else:
            band = self.force if quantity == "force_n" else self.torque
            if band is not None:
                band.fit(level, observed, margin_pct)
                fits = band.fits(level, observed)
        ks = sorted(observed)
        self._note({"action": "false_alarm", "level": level, "quantity": quantity,
                    "revs": [ks[0], ks[-1]] if ks else []})
        return fits

    def _note(self, adjustment: dict[str, Any]) -> None:
        self.adjustments.append(adjustment)
        del self.adjustments[:-MAX_ADJUSTMENTS]

    # -- persistence -------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "n": self.n, "length": self.length, "torque": self.torque.to_dict(),
            "force": None if self.force is None else self.force.to_dict(),
            "entry": {"mean": self.entry_mean, "std": self.entry_std, "max": self.entry_max,
                      "margin": self.entry_margin, "floor": self.entry_floor,
                      "margin_learned": self.entry_margin_learned},
            "energy": {"mean_j": self.energy_mean_j, "std_j": self.energy_std_j, "h_j": self.energy_h_j,
                       "floor_j": self.energy_floor_j, "h_learned_j": self.energy_h_learned_j},
            "adjustments": [dict(a) for a in self.adjustments],
        }

    @classmethod
    def from_dict(cls, d: Any, widths: Widths | None = None) -> "Envelope":
        """A stored envelope, every value checked (ValueError naming the field, never another error).

        `widths` (the `[learning]` settings): the learned widths of an envelope stored before they
        were kept, as `learn` makes them. The result is bounded (no ceilings yet: `set_ceilings`).
        """
        w = widths or Widths()
        d = _mapping(d, "envelope")
        entry, energy = _mapping(d.get("entry"), "envelope.entry"), _mapping(d.get("energy"), "envelope.energy")
        length = _whole(d.get("length"), "envelope.length")
        torque = Band.from_dict(d.get("torque"), length, w.sigma, "envelope.torque")
        force = None if d.get("force") is None else Band.from_dict(d["force"], length, w.sigma, "envelope.force")
        entry_mean = _number(entry.get("mean"), "envelope.entry.mean", 0.0)
        entry_std = _number(entry.get("std"), "envelope.entry.std", 0.0)
        energy_mean = _number(energy.get("mean_j"), "envelope.energy.mean_j")
        energy_std = _number(energy.get("std_j"), "envelope.energy.std_j", 0.0)
        entry_floor = _number(entry.get("floor"), "envelope.entry.floor", 0.0)
        energy_floor = _number(energy.get("floor_j"), "envelope.energy.floor_j", 0.0)
        margin0 = entry.get("margin_learned")
        margin0 = (max(entry_floor, w.sigma * entry_std, w.pct / 100.0 * entry_mean) if margin0 is None
                   else _number(margin0, "envelope.entry.margin_learned", 0.0))
        h0 = energy.get("h_learned_j")
        h0 = (max(w.sigma * energy_std, energy_floor) if h0 is None
              else _number(h0, "envelope.energy.h_learned_j", 0.0))
        adjustments = d.get("adjustments", [])
        if not isinstance(adjustments, list) or not all(isinstance(a, dict) for a in adjustments):
            raise ValueError("envelope.adjustments: not a list of objects")
        env = cls(_whole(d.get("n"), "envelope.n", 1), length, torque, force,
                  entry_mean, entry_std, _whole(entry.get("max"), "envelope.entry.max"),
                  _number(entry.get("margin"), "envelope.entry.margin", 0.0), entry_floor,
                  energy_mean, energy_std, _number(energy.get("h_j"), "envelope.energy.h_j", 0.0), energy_floor,
                  [dict(a) for a in adjustments[-MAX_ADJUSTMENTS:]], margin0, h0)
        env.bound()
        return env


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
    env = Envelope(len(taught), length, torque_band, force_band, entry_mean, entry_std, int(max(entries)),
                   entry_margin, entry_floor, energy_mean, energy_std,
                   max(w_torque.sigma * energy_std, energy_floor), energy_floor)
    env.bound()
    return env
