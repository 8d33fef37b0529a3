"""The replays of `bench/validate.py`: the papers' experiments, then one wrong input at a time.

Every wrong input is applied to the configuration only; the plant (the
simulated machine) is always the same, [P] Table 2's MCH-10 with a 200 Hz
2nd-order anti-alias filter, except for the noise study, where the sensors
themselves are noisier.
"""

from __future__ import annotations

from validate_runs import Capture, Case

from millsense.sim.scenarios import SCENARIOS, SWEEP_RPM

P_SCENARIOS = ("step", "taper", "step-1200", "taper-1800", "diagonal-step", "diagonal-taper", "breakage")
D_SCENARIOS = ("fig5", "fig6", "fig7")
SWEEP = tuple(f"speed-{rpm}" for rpm in SWEEP_RPM)
AIRCUTS = ("aircut-low", "aircut-high")
RS_OHM = 0.349
RS_LINE = f"stator_resistance_ohm = {RS_OHM}"
FX_RATE_LINE = "[channels.fx_rate]\nscale = 0.1\n"
FEED_DRIVE = (("method", "feed-drive"),)
SLOT_DEPTHS = ("axial",)          # slot: d_r = tool diameter by definition, d_a from the torque
SIDE_DEPTHS = ("radial", "axial")


def paper_key(scenario: str, method: str = "") -> str:
    return f"paper-{scenario}" + (f"-{method}" if method else "")


def paper_cases(seed: int) -> list[Case]:
    out = [Case(paper_key(s), Capture(s, seed), "C_f 1.075, d_a from torque (slot)", depths=SLOT_DEPTHS)
           for s in P_SCENARIOS]
    for s in D_SCENARIOS:
        out.append(Case(paper_key(s, "feed-drive"), Capture(s, seed), "feed drive + spindle torque (f_xt, eq. 12)",
                        FEED_DRIVE, depths=SIDE_DEPTHS))
        out.append(Case(paper_key(s, "dynamometer"), Capture(s, seed), "dynamometer F_x, F_y (f_x, eq. 10)",
                        (("method", "dynamometer"),), depths=SIDE_DEPTHS))
    return out


def baseline(scenario: str, seed: int) -> Case:
    """The correctly configured case of a scenario (the sweep's, or the paper's)."""
    if scenario in D_SCENARIOS:
        return Case(paper_key(scenario, "feed-drive"), Capture(scenario, seed), "correct", FEED_DRIVE,
                    depths=SIDE_DEPTHS)
    key = paper_key(scenario) if scenario in P_SCENARIOS else f"base-{scenario}"
    return Case(key, Capture(scenario, seed), "correct", depths=SLOT_DEPTHS)


def baseline_key(scenario: str) -> str:
    return baseline(scenario, 0).key


def _variant(base: Case, key: str, label: str, *, options=None, edits=(), calibrated=False) -> Case:
    opts = dict(base.options) | dict(options or {})
    return Case(f"{key}-{base.scenario}", base.capture, label, tuple(opts.items()), tuple(edits), calibrated,
                base.depths)


def sensitivity_cases(seed: int) -> dict[str, list[Case]]:
    """Group -> cases; each group lists its baselines first."""
    groups: dict[str, list[Case]] = {}
    sweep = [baseline(s, seed) for s in SWEEP]

    rs_bases = [*sweep, baseline("step", seed), baseline("fig6", seed)]
    groups["resistance"] = rs_bases + [
        _variant(b, f"rs{k:g}", f"R_s {RS_OHM * k:.4f} Ω ({(k - 1) * 100:+.0f} %)",
                 edits=[(RS_LINE, f"stator_resistance_ohm = {RS_OHM * k:.4f}")])
        for k in (0.9, 1.1) for b in rs_bases]

    groups["filter"] = sweep + [
        _variant(b, f"fc{fc:g}", label, options={"filter_cutoff_hz": fc})
        for fc, label in ((0.0, "filter left out (0)"), (150.0, "cutoff 150 Hz (is 200)"),
                          (300.0, "cutoff 300 Hz (is 200)"))
        for b in sweep]

    cf_bases = [baseline(s, seed) for s in P_SCENARIOS if s != "breakage"]
    groups["cf"] = cf_bases + [_variant(b, "cfmodel", "C_f from r_1(t_a)", options={"cf": "model"})
                               for b in cf_bases]

    noise_bases = [baseline(s, seed) for s in ("step", "step-1200", "fig6")]
    groups["noise"] = noise_bases + [
        Case(f"noise{n:g}-{b.scenario}", Capture(b.scenario, seed, n), f"sensor noise ×{n:g}", b.options,
             depths=b.depths)
        for n in (2.0, 5.0) for b in noise_bases]

    groups["speed"] = sweep + [
        Case(f"noise5-{b.scenario}", Capture(b.scenario, seed, 5.0), "sensor noise ×5", b.options, depths=b.depths)
        for b in sweep]

    fr_bases = [*sweep, baseline("step", seed), baseline("step-1200", seed), baseline("taper-1800", seed)]
    groups["friction"] = fr_bases + [_variant(b, "calib", "friction from air cuts (`millsense calibrate`)",
                                              calibrated=True) for b in fr_bases]

    step, fig6 = baseline("step", seed), baseline("fig6", seed)
    program_feed = SCENARIOS["step"].feed_segments[0][1]
    groups["feed"] = [step, fig6] + [
        _variant(step, f"feed{k:g}", f"feed {program_feed * k:g} mm/min in [cut] ({(k - 1) * 100:+.0f} %)",
                 options={"feed_mm_min": program_feed * k}) for k in (0.9, 1.1)
    ] + [
        _variant(step, f"feedcf{k:g}", f"C_f from r_1(t_a), feed {(k - 1) * 100:+.0f} %",
                 options={"feed_mm_min": program_feed * k, "cf": "model"}) for k in (1.0, 1.1)
    ] + [
        _variant(fig6, f"fxrate{k:g}", f"feed-rate channel scale {0.1 * k:g} (is 0.1, {(k - 1) * 100:+.0f} %)",
                 edits=[(FX_RATE_LINE, f"[channels.fx_rate]\nscale = {0.1 * k:g}\n")]) for k in (0.9, 1.1)
    ]
    return groups


def all_captures(cases: list[Case], seed: int) -> list[Capture]:
    caps = {c.capture: None for c in cases}
    for name in AIRCUTS:
        caps[Capture(name, seed)] = None
    return list(caps)


def unique(cases: list[Case]) -> list[Case]:
    """Cases by key, first wins (baselines appear in several groups)."""
    out: dict[str, Case] = {}
    for c in cases:
        out.setdefault(c.key, c)
    return list(out.values())
