"""What the DAQ reads, against the machine: scales against a meter, the phase order, the spindle's speed source.

Pure functions on raw counts (n, C) and the configuration, so that a test can hand them any block. The phase
order is judged by the daemon's own `PhaseCheck` (daemon/pipeline/phase_check.py), window by window; its fix
is found by the same check: each swap of two line channels, and each current sensor turned round, is tried on
the same samples, and the one the check passes with the most input power ([P] eq. 11, current and voltage in
step) is the one proposed.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

import numpy as np

from millsense.daemon.commission.report import Step
from millsense.daemon.physics.power import clarke_alpha_beta_v, input_power_symmetric_w
from millsense.daemon.pipeline.phase_check import PhaseCheck
from millsense.daemon.pipeline.safety_check import three_lines
from millsense.daemon.pipeline.scaling import Scaler, line_channels
from millsense.drivers.protocol import ChannelKind

UNITS = {ChannelKind.CURRENT: "A", ChannelKind.VOLTAGE: "V"}


def metered_channels(settings: Any, descriptor: Any) -> list[tuple[str, str]]:
    """(name, unit) of every configured current and voltage channel the DAQ sends, voltages first."""
    kinds = {ch.name: ChannelKind(ch.kind) for ch in descriptor.channels}
    out = [(n, UNITS[kinds[n]]) for n in settings.channels if kinds.get(n) == ChannelKind.VOLTAGE]
    return out + [(n, UNITS[kinds[n]]) for n in settings.channels if kinds.get(n) == ChannelKind.CURRENT]


def rms(settings: Any, descriptor: Any, raw: np.ndarray, name: str) -> float:
    """The true RMS of a channel in its unit, as a true-RMS meter reads it: (raw - offset) * scale."""
    col = descriptor.names.index(name)
    ch = settings.channels[name]
    x = (raw[:, col].astype(np.float64) - float(ch.offset)) * float(ch.scale)
    return float(np.sqrt(np.mean(x * x)))


def judge_scale(name: str, unit: str, daq: float, meter: float, scale: float, tol_pct: float) -> dict[str, Any]:
    """One channel: the DAQ's RMS against the meter's. A fix is the scale that makes them agree."""
    off_pct = (daq / meter - 1.0) * 100.0 if meter > 0 else float("inf")
    row: dict[str, Any] = {"channel": name, "unit": unit, "daq_rms": round(daq, 4), "meter": meter,
                           "off_pct": round(off_pct, 2), "scale": scale, "ok": abs(off_pct) <= tol_pct}
    if not row["ok"] and daq > 0 and meter > 0:
        row["proposed_scale"] = float(f"{scale * meter / daq:.6g}")
    return row


def scale_step(rows: list[dict[str, Any]], tol_pct: float) -> Step:
    step = Step("scales", f"each current and voltage against a meter, within {tol_pct:g} %")
    step.figures["channels"] = rows
    step.figures["tolerance_pct"] = tol_pct
    for row in rows:
        if row.get("skipped"):
            step.not_checked(f"{row['channel']}: skipped (no meter reading)")
        elif not row["ok"]:
            fix = (f"channels.{row['channel']}.scale = {row['proposed_scale']:g}" if "proposed_scale" in row
                   else f"check the sensor and cable of {row['channel']}")
            step.fail(f"{row['channel']}: the DAQ reads {row['daq_rms']:g} {row['unit']}, the meter "
                      f"{row['meter']:g} {row['unit']} ({row['off_pct']:+.1f} %)", fix)
    return step


# ----------------------------------------------------------------------------- phases
def phase_step(settings: Any, descriptor: Any, raw: np.ndarray) -> Step:
    step = Step("phases", "phase order (the daemon's phase check) and current-voltage alignment (the current "
                          f"lags its voltage by {LAG_DEG[0]:g}..{LAG_DEG[1]:g} degrees, as a motor's does)")
    check = PhaseCheck(settings, descriptor)
    if not check.usable:
        step.not_checked("fewer than two line voltages or currents configured: nothing to judge")
        return step
    lc = line_channels(settings, descriptor)
    windows = [raw[k:k + check.window] for k in range(0, len(raw) - check.window + 1, check.window)]
    found = _verdicts(check, windows)
    power_w, lag_deg = _power(settings, descriptor, raw, lc)
    step.figures.update(windows=len(windows), judged=len(found), input_power_w=round(power_w, 1),
                        current_lag_deg=round(lag_deg, 1))
    if not found:
        step.not_checked("the drive was not running (no current swinging, or the voltages standing still): run "
                         "the spindle and commission again")
        return step
    problems = [p for p in found if p]
    if len(problems) * 2 <= len(found) and _lagging(power_w, lag_deg):
        step.figures["result"] = "in order"
        return step
    problem = problems[0] if len(problems) * 2 > len(found) else (
        f"{', '.join(lc.i_names)} against {', '.join(lc.v_names)}: the phase order fits, but the current lags its "
        f"voltage by {lag_deg:.0f} degrees (a motor's by 0..90; input power {power_w:.0f} W): the currents are on "
        "other phases than the voltages (each moved one on)")
    step.figures["result"] = problem
    fix, fixed = _find_fix(settings, descriptor, raw, check, windows, lc)
    if fixed is not None:
        step.figures["after_fix"] = {"input_power_w": round(fixed[0], 1), "current_lag_deg": round(fixed[1], 1)}
    step.fail(problem, fix or "more than one thing is wrong: check each current sensor's arrow (towards the "
                              "motor) and that i_u, i_v, i_w and v_uv, v_vw, v_wu are the same phases in order")
    return step


LAG_DEG = (0.0, 90.0)   # an induction motor draws magnetising current: its current always lags, under 90° motoring


def _lagging(power_w: float, lag_deg: float) -> bool:
    return power_w > 0.0 and LAG_DEG[0] < lag_deg < LAG_DEG[1]


def _verdicts(check: PhaseCheck, windows: list[np.ndarray]) -> list[str]:
    return [v for v in (check.problem(w) for w in windows) if v is not None]


def _power(settings: Any, descriptor: Any, raw: np.ndarray, lc: Any) -> tuple[float, float]:
    """Mean input power ([P] eq. 11) and how far the current lags its phase voltage, degrees: from the space
    vectors, S = v·conj(i); the line-voltage vector leads the phase voltage's by 30°."""
    x = Scaler(settings, descriptor).scale(raw)
    v = three_lines({k: x[n] for k, n in zip(lc.v_keys, lc.v_names)}, ("uv", "vw", "wu"))
    i = three_lines({k: x[n] for k, n in zip(lc.i_keys, lc.i_names)}, ("u", "v", "w"))
    v_a, v_b = clarke_alpha_beta_v(*v)
    i_a, i_b = (2.0 * i[0] - i[1] - i[2]) / 3.0, (i[1] - i[2]) / math.sqrt(3.0)   # Clarke, as the phase check's
    p, q = float(np.mean(v_a * i_a + v_b * i_b)), float(np.mean(v_b * i_a - v_a * i_b))
    lag = (math.degrees(math.atan2(q, p)) - 30.0 + 180.0) % 360.0 - 180.0
    return float(np.mean(input_power_symmetric_w(*v, *i))), lag


def _find_fix(settings, descriptor, raw, check, windows, lc) -> tuple[str | None, tuple[float, float] | None]:
    """Of the single changes the phase check passes and that leave the current lagging its voltage, the one it
    lags most (in air a motor's current lags by 60..85°; a fix one phase off lags 60° less): (its words, (power,
    lag) after it). Swapping two currents or two voltages both reverse the order: only the lag tells them apart."""
    cols = {name: k for k, name in enumerate(descriptor.names)}
    tries: list[tuple[str, Any]] = []
    for names in (lc.i_names, lc.v_names):
        for a, b in itertools.combinations(names, 2):
            tries.append((f"swap {a} and {b}: their cables on the DAQ (the DAQ names its inputs: renaming [channels] tables moves no signal)",
                          lambda r, a=a, b=b: _swapped(r, [(cols[a], cols[b])])))
        if len(names) == 3:
            for shift in (1, 2):
                moved = names[shift:] + names[:shift]
                tries.append((f"move the cables one phase on: {', '.join(f'{a} to where {b} is' for a, b in zip(names, moved))}"
                              f" (the currents measured on other phases than the voltages)",
                              lambda r, n=names, m=moved: _moved(r, [cols[x] for x in n], [cols[x] for x in m])))
    for name, off, scale in zip(lc.i_names, lc.i_offsets, lc.i_scales):
        tries.append((f"channels.{name}.scale = {-scale:g} (the sensor is turned round: turn it to point towards "
                      f"the motor and keep the scale, or negate the scale)",
                      lambda r, c=cols[name], off=off: _negated(r, c, off)))
    best: tuple[str | None, tuple[float, float] | None] = (None, None)
    for words, change in tries:
        verdicts = _verdicts(check, [change(w) for w in windows])
        if verdicts and not any(verdicts):
            after = _power(settings, descriptor, change(raw), lc)
            if _lagging(*after) and (best[1] is None or after[1] > best[1][1]):
                best = (words, after)
    return best


def _swapped(raw: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    out = raw.copy()
    for a, b in pairs:
        out[:, [a, b]] = raw[:, [b, a]]
    return out


def _moved(raw: np.ndarray, cols: list[int], to: list[int]) -> np.ndarray:
    """Each column's samples put where the next one of its kind is (the cables moved one phase on)."""
    out = raw.copy()
    out[:, to] = raw[:, cols]
    return out


def _negated(raw: np.ndarray, col: int, offset: float) -> np.ndarray:
    out = raw.astype(np.int32)
    out[:, col] = np.rint(2.0 * offset - out[:, col]).astype(np.int32)
    return out


# ----------------------------------------------------------------------------- speed
def speed_step(settings: Any, descriptor: Any, raw: np.ndarray, commanded_rpm: float | None, tol_pct: float) -> Step:
    step = Step("speed", f"the spindle's direction and speed source against the commanded speed, within {tol_pct:g} %")
    if commanded_rpm is None:
        step.not_checked("no commanded spindle speed given (--spindle-rpm, or type it at the prompt)")
        return step
    step.figures["commanded_rpm"] = commanded_rpm
    roles = Scaler(settings, descriptor).roles
    seconds = len(raw) / float(descriptor.sample_rate_hz)
    if roles.encoder is not None:
        col, cpr = descriptor.names.index(roles.encoder), int(settings.channels[roles.encoder].counts_per_rev)
        steps = np.diff(raw[:, col].astype(np.int64))
        counts = float(((steps + 32768) % 65536 - 32768).sum())   # int16 wrap of each step, as scaling.py
        rpm = counts / seconds * 60.0 / cpr
        per_rev = abs(counts) / seconds * 60.0 / commanded_rpm
        step.figures["encoder"] = {"channel": roles.encoder, "counts": counts, "seconds": round(seconds, 3),
                                   "counts_per_rev_configured": cpr, "counts_per_rev_measured": round(per_rev, 1),
                                   "rpm": round(rpm, 2), "direction": "forward" if counts > 0 else "reverse"}
        if counts <= 0:
            step.fail(f"{roles.encoder}: the encoder counts backwards ({counts:.0f} counts in {seconds:.2f} s) with "
                      f"the spindle turning forward",
                      f"swap the encoder's A and B signals (or set the DAQ's counting direction) for {roles.encoder}")
        elif abs(rpm / commanded_rpm - 1.0) * 100.0 > tol_pct:
            step.fail(f"{roles.encoder}: {rpm:.1f} rpm with counts_per_rev = {cpr}, the spindle runs at "
                      f"{commanded_rpm:g} rpm", f"channels.{roles.encoder}.counts_per_rev = {int(round(per_rev))}")
    if roles.spindle_speed is not None:
        name = roles.spindle_speed
        ch = settings.channels[name]
        col = descriptor.names.index(name)
        rpm = float(np.mean((raw[:, col].astype(np.float64) - float(ch.offset)) * float(ch.scale)))
        step.figures["speed_channel"] = {"channel": name, "rpm": round(rpm, 2), "scale": float(ch.scale)}
        if rpm == 0.0 or abs(rpm / commanded_rpm - 1.0) * 100.0 > tol_pct:
            proposed = float(f"{float(ch.scale) * commanded_rpm / rpm:.6g}") if rpm else None
            step.figures["speed_channel"]["proposed_scale"] = proposed
            step.fail(f"{name}: reads {rpm:.1f} rpm, the spindle runs at {commanded_rpm:g} rpm"
                      + (" (the other way round)" if rpm < 0 else ""),
                      f"channels.{name}.scale = {proposed:g}" if proposed else f"check {name}'s signal and cable")
    return step
