"""Numbers of `bench/validate.py` drawn from one run: pairing cache, formatting, the papers' checks.

Shared by the report (validate_report.py) and the sensitivity study
(validate_sensitivity.py); nothing here writes a file.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import validate_cases as vc
import validate_runs as vr

from millsense.daemon.physics import depth as depth_mod
from millsense.daemon.physics.milling import SB40_TABLE2, force_ratio_fx
from millsense.daemon.physics.table3 import radial_ratio_table3
from millsense.daemon.pipeline.alarms import BreakageTrack
from millsense.sim.machine import MCH10
from millsense.sim.scenarios import SCENARIOS

FIG_DIR = "validation"
HW_FILTER_HZ, HW_FILTER_ORDER = 200.0, 2          # the simulated DAQ's anti-alias filter
POLE_PAIRS = MCH10.motor.pole_pairs
TABLE3_TC = (0.05, 0.1042, 0.2083, 0.4167)        # the feeds per tooth of [D] Fig. 5-7 and one below the split
BREAKAGE_PCTS = (20.0, 30.0, 40.0, 50.0)
BREAK_WINDOW_S = 0.5                              # 'before the break': its last half second
BREAKAGE_CATCH_S = 0.5                            # an alarm this soon after the flute breaks counts as caught


def bp(s: vr.Stats | None, digits: int = 2) -> str:
    """Bias / p95 of |error| of a Stats, or a dash."""
    return "–" if s is None else f"{s.mean:+.{digits}f} / {s.p95:.{digits}f}"


def bpm(s: vr.Stats | None, digits: int = 2) -> list[str]:
    return ["–"] * 4 if s is None else [str(s.n), f"{s.mean:+.{digits}f}", f"{s.p95:.{digits}f}", f"{s.max:.{digits}f}"]


def table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table; a "|" inside a cell (|F|, |e|) is escaped so it does not split the cell."""
    def cells(r):
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in r) + " |"
    out = [cells(header), "|" + "|".join(" --- " for _ in header) + "|"]
    out += [cells(r) for r in rows]
    return "\n".join(out) + "\n"


def ramp_lead_mm(scenario: str) -> float:
    """A slot cutter engages the part ahead of its centre (cutting edge at x = s + R·sin φ, φ in [0, π]);
    on a taper of slope k the chip-weighted engaged depth exceeds the depth under the centre (what the
    truth file reports) by π·R·k/4. 0 for anything but a slot on one straight ramp."""
    sc = SCENARIOS[scenario]
    if sc.mode != "slot" or len(sc.axial_profile) != 2:
        return 0.0
    (x0, d0), (x1, d1) = sc.axial_profile
    return math.pi * sc.tool.radius_mm * (d1 - d0) / (x1 - x0) / 4.0


def gear_of(rpm: float):
    return MCH10.gear_for_rpm(rpm)


def f_e_hz(rpm: float) -> float:
    return POLE_PAIRS * rpm * gear_of(rpm).ratio / 60.0


class Run:
    """The run's results with their truth, paired once."""

    def __init__(self, run: dict):
        self.raw = run
        self.results: dict[str, vr.Result] = run["results"]
        self.workdir: Path = run["workdir"]
        self._truth = run["truths"]
        self._events: dict = {}
        self._pairs: dict[str, vr.Paired] = {}

    def truth(self, key: str) -> list[dict]:
        return self._truth[self.results[key].case.capture]

    def events(self, key: str) -> list[dict]:
        cap = self.results[key].case.capture
        if cap not in self._events:
            self._events[cap] = vr.read_events(self.results[key].case, self.workdir)
        return self._events[cap]

    def segments(self, key: str) -> dict[int, str]:
        return vr.segment_of(self.truth(key), self.results[key].case.scenario, self.events(key))

    def pairs(self, key: str) -> vr.Paired:
        if key not in self._pairs:
            self._pairs[key] = vr.pair(self.results[key], self.truth(key), self.events(key))
        return self._pairs[key]

    def steady(self, key: str, q: str = "torque", kind: str = "rel") -> vr.Stats | None:
        return self.pairs(key).stats("steady", q, kind)


def paper_main_keys() -> list[str]:
    return [vc.paper_key(s) for s in vc.P_SCENARIOS] + [vc.paper_key(s, m) for s in vc.D_SCENARIOS
                                                         for m in ("feed-drive", "dynamometer")]


def within(p: vr.Paired, q: str, pct: float) -> tuple[float, int]:
    e, t = p.est.get(("steady", q)), p.tru.get(("steady", q))
    if e is None or not e.size:
        return math.nan, 0
    rel = np.abs(e - t) / t * 100.0
    return float(np.mean(rel <= pct) * 100.0), int(rel.size)


def truth_cf(run: Run, key: str) -> np.ndarray:
    """C_f of the simulated cut itself: mean |F| over T/R, steady revolutions ([P] eq. 18 solved for C_f)."""
    r_m = SCENARIOS[run.results[key].case.scenario].tool.radius_mm / 1000.0
    seg = run.segments(key)
    return np.array([t["force_n"] / (t["torque_nm"] / r_m) for t in run.truth(key) if seg[t["rev"]] == "steady"])


def depth_levels(run: Run, key: str) -> list[tuple[float, vr.Stats, float]]:
    """Per true axial depth of the steady revolutions (step cuts): force error, and the cut's own C_f."""
    seg = run.segments(key)
    r_m = SCENARIOS[run.results[key].case.scenario].tool.radius_mm / 1000.0
    groups: dict[float, list[tuple[float, float]]] = {}
    for e, t in vr.paired(run.results[key], run.truth(key)):
        if seg[t["rev"]] == "steady" and e["force_n"] is not None:
            groups.setdefault(round(t["axial_depth_mm"], 3), []).append(
                ((e["force_n"] - t["force_n"]) / t["force_n"] * 100, t["force_n"] / (t["torque_nm"] / r_m)))
    return [(d, vr.Stats.of([a for a, _ in v]), float(np.mean([b for _, b in v]))) for d, v in sorted(groups.items())]


def table3_numbers(run: Run) -> dict:
    """[D] Table 3 against the exact inversion: on a grid, and on the truth forces of Fig. 5-7."""
    grid = {}
    r_r = np.linspace(0.125, 1.99, 300)
    for t_c in TABLE3_TC:
        fx = force_ratio_fx(r_r, t_c, SB40_TABLE2, "down")
        poly = (radial_ratio_table3(fx, t_c) - r_r) / r_r * 100
        exact = np.array([depth_mod.radial_ratio_from_fx(f, t_c, SB40_TABLE2, "down")[0] for f in fx])
        grid[t_c] = (r_r, poly, (exact - r_r) / r_r * 100)
    points = {}
    for scenario in vc.D_SCENARIOS:
        key = vc.paper_key(scenario, "dynamometer")
        seg = run.segments(key)
        radius = SCENARIOS[scenario].tool.radius_mm
        rr, poly, exact = [], [], []
        for t in run.truth(key):
            if seg[t["rev"]] != "steady":
                continue
            fx = t["force_x_n"] / math.hypot(t["force_x_n"], t["force_y_n"])
            true_rr = t["radial_depth_mm"] / radius
            rr.append(true_rr)
            poly.append((float(radial_ratio_table3(fx, t["feed_per_tooth_mm"])) - true_rr) / true_rr * 100)
            sol = depth_mod.radial_ratio_from_fx(fx, t["feed_per_tooth_mm"], SB40_TABLE2, "down")[0]
            exact.append(math.nan if sol is None else (sol - true_rr) / true_rr * 100)
        points[scenario] = (np.array(rr), np.array(poly), np.array(exact))
    return {"grid": grid, "points": points}


def breakage_numbers(run: Run) -> dict:
    """[P]: the breakage shows in the estimate. How much, and whether the daemon's detector can tell."""
    key = vc.paper_key("breakage")
    event = next(e for e in run.events(key) if e["event"] == "tool_breakage")
    p = run.pairs(key)
    pairs = vr.paired(run.results[key], run.truth(key))
    # the level just before the break (the last BREAK_WINDOW_S of the sound 3 mm step, whatever its segment)
    # against the settled level after it
    pre = [(e["torque_nm"], t["torque_nm"]) for e, t in pairs
           if event["t_s"] - BREAK_WINDOW_S <= t["t_end_s"] <= event["t_s"]]
    # the first whole revolution with the flute gone (it starts at or after the break)
    first_e, first_t = next((e, t) for e, t in pairs if t["t_end_s"] - 60.0 / t["spindle_rpm"] >= event["t_s"] - 1e-3)
    gear = next(g for g in MCH10.gears if g.name == first_t["gear"])
    w = 2 * math.pi * first_t["spindle_rpm"] / 60
    out = {"t_s": event["t_s"], "est_before": float(np.mean([a for a, _ in pre])),
           "true_before": float(np.mean([b for _, b in pre])),
           "est_after": float(p.est[("broken", "torque")].mean()), "true_after": float(p.tru[("broken", "torque")].mean()),
           "first_est": first_e["torque_nm"], "first_true": first_t["torque_nm"],
           "first_power_equiv": first_t["airgap_power_w"] / w - gear.friction_torque_nm - gear.viscous_nms * w,
           "thresholds": []}
    keys = [vc.paper_key(s) for s in vc.P_SCENARIOS] + [vc.paper_key(s, "feed-drive") for s in vc.D_SCENARIOS]
    for pct in BREAKAGE_PCTS:            # the daemon's own detector, re-run on the replayed estimates
        caught, false = None, []
        for k in keys:
            track = BreakageTrack(pct, 1.0)
            first = None
            for e in run.results[k].estimates:
                if e["valid"] and e["torque_nm"] is not None and track.update(e["torque_nm"], e["cutting"], e["rev"], None,
                                                                       e.get("spindle_rpm"), e.get("feed_per_tooth_mm")):
                    first = e["t"]
                    break
            if first is None:
                continue
            scenario = run.results[k].case.scenario
            if k == key and event["t_s"] <= first <= event["t_s"] + BREAKAGE_CATCH_S:
                caught = first
            else:
                false.append(f"{scenario} at {first:.2f} s")
        out["thresholds"].append((pct, caught, false))
    return out


def static_sensitivity(run: Run) -> list[dict]:
    rows = []
    for rpm in vc.SWEEP_RPM:
        row = {"rpm": rpm, "gear": gear_of(rpm).name}
        for noise, prefix in ((1.0, "base"), (5.0, "noise5")):
            key = f"{prefix}-speed-{rpm}"
            seg = run.segments(key)
            pairs = [(e, t) for e, t in vr.paired(run.results[key], run.truth(key)) if seg[t["rev"]] == "steady"]
            err = np.array([e["torque_nm"] - t["torque_nm"] for e, t in pairs])
            row[f"std_{noise:g}"] = float(err.std(ddof=1))
            row[f"sigma_{noise:g}"] = float(np.mean([e["torque_sigma_nm"] for e, _ in pairs]))
            row[f"n_{noise:g}"] = len(err)
        rows.append(row)
    return rows


def exponent(rows: list[dict], gear: str, col: str) -> float:
    sel = [r for r in rows if r["gear"] == gear]
    return float(np.polyfit(np.log([r["rpm"] for r in sel]), np.log([r[col] for r in sel]), 1)[0])


def steady_bias(run: Run, key: str, q: str = "torque") -> float:
    s = run.steady(key, q)
    return math.nan if s is None else s.mean
