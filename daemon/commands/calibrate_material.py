"""`millsense calibrate CAPTURE... --material --ae-mm A --ap-mm P [--mode M] --config FILE --out FILE`.

Fits the material of [D] eq. (9), K_s = k·t_a^p, from a test cut with a known radial and axial depth
(and milling mode) on the configured tool ([tool]). The captures go through the real estimator, with the
configuration's friction and inertia (calibrate them first: an air cut), so each revolution's cutting
torque is the daemon's own ([P] eq. 13). The feed per tooth is the estimator's: the feed-rate channel,
else `[cut] feed_mm_min` times the override the CNC applied.

Steady revolutions (`STEADY_*`): cutting, the spindle not running up or braking, and the feed per tooth
and the torque within a few per cent over the revolutions around it — not the entry, the exit, a feed
change. They are grouped by feed per tooth into levels; each level's median torque gives K_s at its chip
(`calibration.specific_force_from_torque`, [D] eqs. 7–8). Levels whose chips span a ratio of 1.25 or more
fit k and p (`calibration.fit_material`); one level fits k with p from the nearest ISO group of
`physics/materials.py`, which the output says. Where every level has the feed-drive force (a `[feed_force]`
entry for the DAQ's feed-current channel), each level's median force over its tangential force gives r₁ at its
chip, [D] eq. (12) solved for r₁ (`calibration.radial_ratio_from_feed_force`), and the levels fit r1 and r1_exp
the same way (one level: r1 with the configuration's exponent). The output gives the fit and how far it would
move √(1 + r₁²), C_f's factor, at the test cut; `--fit-r1` writes it, else r1 and r1_exp stay the
configuration's (a usage error with edge coefficients in [material]: the feed-drive depth then takes the split
law, physics.md §5b E5, not [D]'s eq. 12). Why not always: r₁ fitted from the feed force is the one the feed-drive
depth (eq. 12) needs,
but on a cut whose forces are not [D]'s sin φ shape it is not the one the resultant needs (physics.md §5a,
accuracy.md: the radial depth 26 % off mended, the force 3–5 % low after, 1–6 % high before). r2 is always the
configuration's (no channel here sees the axial force).

Refused, exit 1, nothing written, with the reason and the capture that would do: no steady cut, a level
with too few revolutions, a torque near the noise and friction floor, an exponent no material has, a feed-drive
force that gives no positive r₁ at the stated engagement.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from pathlib import Path

STEADY_SPAN = 3          # revolutions either side that must agree with a steady one
STEADY_FEED_REL = 0.005  # their feed per tooth within 0.5 % (a feed change moves it by its whole step)
STEADY_TORQUE_REL = 0.02  # their torque within 2 % (entry, exit and a feed change move it by far more a revolution)
LEVEL_REL = 0.02         # feeds per tooth within 2 % are one level
# The edge term is not fitted, at any number of feeds (physics.md §5b): the mean force against the chip is a line
# whose intercept is the edge term only where the chip term is linear (Altintas ch. 2); with Kienzle's size
# effect in the chip term a line's intercept on the simulated test cuts is 56-75 N/mm for a true 20, and a
# chip power law plus an edge constant through three levels moves K_te over 6-31 N/mm for 0.2 % of torque.
EDGE_NOTE = ("  edge term (edge_t_n_mm, edge_r_n_mm): not fitted: the feed levels' torque cannot split the law into a "
             "chip and an edge term to better than tens of N/mm (physics.md 5b); the configuration's are kept")
RECORD = ("a capture of one test cut at constant a_e and a_p on the configured tool, each feed held for "
          "10 or more revolutions in full engagement (several feeds, 1:2 or wider, to fit the exponent too)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options `millsense calibrate` adds for a material fit (additive)."""
    parser.add_argument("--material", action="store_true",
                        help="fit [material] (K_s = ks*t_a^ks_exp, [D] eq. 9) from a test cut with known "
                             "--ae-mm, --ap-mm and --mode; the configured friction is used (calibrate it first)")
    parser.add_argument("--ae-mm", type=float, metavar="MM", help="--material: the test cut's radial depth")
    parser.add_argument("--ap-mm", type=float, metavar="MM", help="--material: the test cut's axial depth")
    parser.add_argument("--mode", choices=("slot", "down", "up"),
                        help="--material: the test cut's milling mode (default: [cut] mode)")
    parser.add_argument("--fit-r1", action="store_true",
                        help="--material: write r1 and r1_exp fitted from the feed-drive force ([D] eq. 12; needs "
                             "a [feed_force] entry) instead of the configuration's: the feed-drive depth then "
                             "fits the test cut, and C_f moves by what the output says (physics.md 5a)")


def _usage_problem(args, settings) -> str | None:
    if args.dynamometer:
        return "--material and --dynamometer are two different fits: run them apart"
    if args.ae_mm is None or args.ap_mm is None:
        return "--material needs the test cut's --ae-mm and --ap-mm"
    diameter = float(settings.tool.diameter_mm)
    mode = args.mode or settings.cut.mode
    if not 0.0 < args.ae_mm <= diameter:
        return f"--ae-mm {args.ae_mm:g}: the radial depth must be above 0 and at most the tool's diameter {diameter:g} mm"
    if mode == "slot" and abs(args.ae_mm - diameter) > 1e-6 * diameter:
        return f"--ae-mm {args.ae_mm:g} with a slot: a slot's radial depth is the tool's diameter {diameter:g} mm"
    if not args.ap_mm > 0.0:
        return f"--ap-mm {args.ap_mm:g}: the axial depth must be above 0"
    if args.fit_r1 and (settings.material.edge_t_n_mm > 0.0 or settings.material.edge_r_n_mm > 0.0):
        return ("--fit-r1 with edge coefficients in [material]: with them the feed-drive depth takes the law split "
                "into chip and edge (physics.md 5b, E5), which r1 fitted by [D] eq. 12 is not for; calibrate "
                "without --fit-r1, or take edge_t_n_mm and edge_r_n_mm out")
    return None


def steady_cut(revs: list[dict]) -> list[dict]:
    """The revolutions of `revs` (one capture, in order) inside a steady stretch of cut (module docstring)."""
    out = []
    for i, r in enumerate(revs):
        window = revs[max(0, i - STEADY_SPAN): i + STEADY_SPAN + 1]
        if len(window) < 2 * STEADY_SPAN + 1:
            continue
        if not all(w["cutting"] and w["feed_per_tooth_mm"] and not w.get("accelerating") for w in window):
            continue
        fz, t = r["feed_per_tooth_mm"], r["torque_nm"]
        if all(abs(w["feed_per_tooth_mm"] - fz) <= STEADY_FEED_REL * fz
               and abs(w["torque_nm"] - t) <= STEADY_TORQUE_REL * t for w in window):
            out.append(r)
    return out


def feed_levels(revs: list[dict]) -> list[list[dict]]:
    """Steady revolutions grouped by feed per tooth: each level's feeds within LEVEL_REL of its first."""
    levels: list[list[dict]] = []
    for r in sorted(revs, key=lambda r: r["feed_per_tooth_mm"]):
        if levels and r["feed_per_tooth_mm"] <= (1.0 + LEVEL_REL) * levels[-1][0]["feed_per_tooth_mm"]:
            levels[-1].append(r)
        else:
            levels.append([r])
    return levels


def _collect(captures, settings) -> tuple[list[dict], int]:
    """The steady cutting revolutions of every capture, and how many cutting revolutions had no feed per tooth."""
    from millsense.daemon.commands.capture_reader import CaptureError, iter_capture_blocks
    from millsense.daemon.pipeline.estimator import Estimator

    steady, feedless = [], 0
    for path in captures:
        est, descriptor, revs = None, None, []
        for desc, block in iter_capture_blocks(path):
            if est is None:
                est, descriptor = Estimator(settings, desc, desc.sample_rate_hz), desc
            elif desc != descriptor:
                raise CaptureError(f"{path}: the DAQ descriptor changes inside the capture; split it")
            revs.extend(est.process(block).estimates)
        good = [r for r in revs if r["valid"] and r["torque_nm"] is not None]
        feedless += sum(1 for r in good if r["cutting"] and not r["feed_per_tooth_mm"])
        steady += steady_cut(good)
    return steady, feedless


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.commands.capture_reader import CaptureError
    from millsense.daemon.config.load import load_config
    from millsense.daemon.physics.calibration import (
        MATERIAL_MIN_CHIP_RATIO,
        MATERIAL_MIN_REVS,
        MATERIAL_MIN_TORQUE_NM,
        Refusal,
        fit_material,
        fit_radial_ratio,
        judge_material,
        judge_radial,
        radial_ratio_from_feed_force,
        specific_force_from_torque,
    )
    from millsense.daemon.physics.materials import nearest_group

    settings = load_config(args.config)
    problem = _usage_problem(args, settings)
    if problem:
        print(f"millsense calibrate: error: {problem}", file=sys.stderr)
        return 2
    for path in args.captures:
        if not Path(path).is_file():
            print(f"millsense calibrate: {path}: no such capture file", file=sys.stderr)
            return 1
    try:
        steady, feedless = _collect(args.captures, settings)
    except CaptureError as exc:
        print(f"millsense calibrate: {exc}", file=sys.stderr)
        return 1

    mode = args.mode or settings.cut.mode
    radius = float(settings.tool.diameter_mm) / 2.0
    flutes = int(settings.tool.flutes)
    refusals: list[Refusal] = []
    levels = []
    print(f"material from a test cut, K_s = k*t_a^p ([D] eq. 9): a_e {args.ae_mm:g} mm, a_p {args.ap_mm:g} mm, "
          f"{mode}, tool {2 * radius:g} mm {flutes} flutes")
    for group in feed_levels(steady):
        fz = statistics.median(r["feed_per_tooth_mm"] for r in group)
        torque = statistics.median(r["torque_nm"] for r in group)
        if len(group) < MATERIAL_MIN_REVS:
            print(f"  f_z {fz:.4f} mm: {len(group)} steady revolutions, fewer than {MATERIAL_MIN_REVS}: left out")
            continue
        if not torque >= MATERIAL_MIN_TORQUE_NM:
            refusals.append(Refusal("material", f"f_z {fz:.4f} mm: steady torque {torque:.3g} N·m, under "
                                                f"{MATERIAL_MIN_TORQUE_NM:g} N·m: too near the noise and friction "
                                                f"floor (0.03 N·m, docs/accuracy.md)",
                                    RECORD + ", deeper or at a larger feed"))
            continue
        chip, ks = (float(x) for x in specific_force_from_torque(torque, fz, args.ae_mm / radius, args.ap_mm,
                                                                  radius, flutes, mode))
        r1 = None
        if all(r.get("force_feed_n") is not None for r in group):
            feed_n = statistics.median(r["force_feed_n"] for r in group)
            r1 = float(radial_ratio_from_feed_force(feed_n, torque, args.ae_mm / radius, radius, mode))
        levels.append((fz, chip, ks, len(group), torque, r1))
        print(f"  f_z {fz:.4f} mm: t_a {chip:.4f} mm, torque {torque:.4g} N·m (median of {len(group)}), "
              f"K_s {ks:.5g} N/mm²" + ("" if r1 is None else f", r1 {r1:.4g} (feed-drive force {feed_n:.4g} N)"))
    if not levels and not refusals and feedless and not steady:
        refusals.append(Refusal("material", f"{feedless} cutting revolutions but no feed per tooth (no feed-rate "
                                            f"channel, no [cut] feed_mm_min)", "the test cut with [cut] feed_mm_min "
                                            "set to its programmed feed, or with the DAQ's feed-rate channel"))
    if not levels and not refusals:
        refusals.append(Refusal("material", f"no feed level with {MATERIAL_MIN_REVS} or more steady cutting "
                                            f"revolutions ({len(steady)} steady in all)", RECORD))
    if refusals:
        _refuse(refusals)
        return 1

    chips = [lv[1] for lv in levels]
    borrowed = None
    if max(chips) / min(chips) < MATERIAL_MIN_CHIP_RATIO:
        best = max(levels, key=lambda lv: lv[3])
        levels = [best]
        group = nearest_group(best[2], best[1])
        borrowed = group
        fit = fit_material([best[1]], [best[2]], borrowed_exp=group.material.ks_exp)
        print(f"  one feed level: the exponent is ISO group {group.letter}'s ({group.name}, "
              f"m_c {-group.material.ks_exp:g}; {group.source}); k fits K_s at t_a {best[1]:.4f} mm only")
    else:
        fit = fit_material(chips, [lv[2] for lv in levels])
        worst = max(abs(x) for x in fit.residuals_rel)
        print(f"  {fit.levels} feed levels: k = {fit.ks:.5g} N/mm², p = {fit.ks_exp:.4f}; "
              f"worst level {100 * worst:.2f} % off the line")
    found = judge_material(fit, RECORD)
    radial = None
    if all(lv[5] is not None for lv in levels):
        try:
            radial = fit_radial_ratio([lv[1] for lv in levels], [lv[5] for lv in levels],
                                      borrowed_exp=float(settings.material.r1_exp) if len(levels) == 1 else None)
        except ValueError as exc:
            radial_found = [Refusal("material", str(exc).split(": ", 1)[1], RECORD + ", with --mode and --ae-mm "
                                    "those of the cut, and the feed-force channel zeroed in air")]
        else:
            radial_found = judge_radial(radial, RECORD)
            print(f"  r1 = {radial.r1:.5g}·t_a^{radial.r1_exp:.4f} from the feed-drive force ([D] eq. 12)"
                  + (" with the configuration's exponent (one feed level)" if radial.exp_borrowed else
                     f"; worst level {100 * max(abs(x) for x in radial.residuals_rel):.2f} % off the line"))
            _say_cf_change(radial, settings.material, levels, args.fit_r1)
        if args.fit_r1:
            found += radial_found
        else:   # not asked for: a feed force that fits no radial law does not stop the K_s fit, it is said
            for r in radial_found:
                print(f"  r1 not fitted: {r.problem}")
            radial = None
    elif args.fit_r1:
        found.append(Refusal("material", "--fit-r1 without the feed-drive force on every feed level (a [feed_force] "
                                         "entry for the DAQ's feed-current channel)", RECORD + ", with the "
                                         "feed-current channel and its [feed_force] entry"))
    else:
        print("  r1, r1_exp: the configuration's (no feed-drive force: the torque does not see r1; a [feed_force] "
              "entry for the feed-current channel lets the test cut fit them)")
    print(EDGE_NOTE)
    if found:
        _refuse(found)
        return 1
    try:
        _write(Path(args.out), fit, settings.material, args, mode, radius, flutes, levels, borrowed, radial)
    except OSError as exc:
        print(f"millsense calibrate: error: cannot write {args.out}: {exc.strerror or exc}; nothing written",
              file=sys.stderr)
        return 1
    print(f"wrote {args.out}")
    return 0


def _say_cf_change(radial, configured, levels, written: bool) -> None:
    """How far the fitted r₁ moves √(1 + r₁²), C_f's factor ([P] eq. 17), at the test cut's chip."""
    chip = max(levels, key=lambda lv: lv[3])[1]
    old = float(configured.r1) * chip ** float(configured.r1_exp)
    new = radial.r1 * chip ** radial.r1_exp
    change = 100.0 * (((1.0 + new * new) / (1.0 + old * old)) ** 0.5 - 1.0)
    edged = float(configured.edge_t_n_mm) > 0.0 or float(configured.edge_r_n_mm) > 0.0
    kept = ("not written: the configuration has edge coefficients, so its feed-drive depth takes the split law "
            "(physics.md 5b, E5) with r1 as configured" if edged else
            "not written: the configuration's r1 kept (--fit-r1 writes it)")
    print(f"  at t_a {chip:.4f} mm r1 {new:.4g} against the configuration's {old:.4g}: C_f's factor "
          f"sqrt(1 + r1^2) {change:+.2f} %; " + ("written (--fit-r1)" if written else kept))


def _edge_lines(configured) -> list[str]:
    """The configuration's edge coefficients, kept: the fitted law is the whole average law whatever its split
    (physics.md §5b), and the torque cannot tell the split (module doc, EDGE_NOTE)."""
    edge_t, edge_r = float(getattr(configured, "edge_t_n_mm", 0.0)), float(getattr(configured, "edge_r_n_mm", 0.0))
    if edge_t <= 0.0 and edge_r <= 0.0:
        return []
    return ["# edge_t_n_mm, edge_r_n_mm: the configuration's (not fitted: physics.md 5b)",
            f"edge_t_n_mm = {edge_t:.6g}", f"edge_r_n_mm = {edge_r:.6g}"]


def _refuse(refusals) -> None:
    for r in refusals:
        print(f"millsense calibrate: refused: {r.gear}: {r.problem}; record {r.record}", file=sys.stderr)
    print("millsense calibrate: nothing written", file=sys.stderr)


def _write(path: Path, fit, configured, args, mode, radius, flutes, levels, borrowed, radial=None) -> None:
    how = (f"one feed level: ks_exp is ISO group {borrowed.letter}'s -m_c ({borrowed.source})" if borrowed
           else f"{fit.levels} feed levels, least squares on log K_s = log ks + ks_exp*log t_a")
    lines = [
        "# written by `millsense calibrate --material`: [D] eq. 9, K_s = ks*t_a^ks_exp (N/mm², t_a in mm),",
        f"# from a test cut: a_e {args.ae_mm:g} mm, a_p {args.ap_mm:g} mm, {mode}, tool {2 * radius:g} mm, {flutes} flutes;",
        f"# {how}.",
        *(f"#   f_z {fz:.4f} mm: t_a {chip:.4f} mm, K_s {ks:.5g} N/mm² ({n} revolutions)"
          + ("" if r1 is None else f", r1 {r1:.4g}") for fz, chip, ks, n, _, r1 in levels),
        ("# r1, r2: the configuration's (the torque does not see them)." if radial is None else
         "# r1, r1_exp from the feed-drive force ([D] eq. 12)" + (", r1_exp the configuration's (one feed level)"
                                                                  if radial.exp_borrowed else "")
         + "; r2: the configuration's.") + " Copy this [material] into the configuration.",
        "",
        "[material]",
        f"ks = {fit.ks:.6g}",
        f"ks_exp = {fit.ks_exp:.6g}",
        f"r1 = {float(configured.r1 if radial is None else radial.r1):.6g}",
        f"r1_exp = {float(configured.r1_exp if radial is None else radial.r1_exp):.6g}",
        f"r2 = {float(configured.r2):.6g}",
        f"r2_exp = {float(configured.r2_exp):.6g}",
        *_edge_lines(configured),
        "",
    ]
    text = "\n".join(lines)
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text)
        tmp.replace(path)
    except OSError:
        tmp.unlink(missing_ok=True)
        raise
    print(text[text.index("\n[material]") + 1:].rstrip())
