"""`millsense calibrate CAPTURE... --config FILE --out FILE [--dynamometer]`.

Fits the friction of [P] eq. (13) per gear: with no cut, `P_g/ω = T_f' + B'·ω`
is a straight line in spindle speed, so air cuts at several speeds give
`T_f'` and `B'` by least squares ([P] §3). The captures are run through the
real estimator with friction set to zero, so the fitted quantity is exactly
the one the daemon will subtract from (same filter-gain correction, same
slip-free power speed, same revolution averaging). Only revolutions in steady
stretches are used: while the spindle accelerates, `P_g/ω` also carries the
inertia torque `J·dω/dt`, which is not friction.

Then the inertia J per gear, referred to the spindle (the J·dω/dt term the
daemon adds to eq. 13): over every air revolution, steady or not, what the
friction line leaves of `P_g/ω` is `J·Δω/Δt`, fitted through the origin
against the revolution's acceleration as the daemon measures it (the speed
reading's rise over the revolution). It needs run-ups: captures in which the
speed steps in air, in each gear fitted (`millsense sim --scenario aircut-low
--capture F`; on a machine, S-word changes in air). Captures with no speed
change say nothing of J: the friction is written without it, with a warning
naming the capture that would fit it.

A fit the captures cannot support is refused, exit 1, no file written: each
refusal names the gear and the capture to record (`calibration.judge_*`):
fewer than three distinct steady speeds in a gear, a negative T_f' or B',
residuals large against the friction torque the line explains, cutting found
in an air capture (not with --dynamometer, which sorts cuts out by force), a J
that is negative or poorly determined. All of them are reported at once.

With `--dynamometer` (captures with fx, fy channels), revolutions the
dynamometer sees as cutting are kept out of the friction fit and used to fit
`C_f` of [P] eq. (18) against the measured mean resultant force.

With `--material --ae-mm A --ap-mm P [--mode M]` (additive), the captures are a
test cut instead, and the fit is the material's K_s law of [D] eq. (9), written
as a `[material]` section: `calibrate_material.py`.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

PLATEAU_REL = 0.005     # consecutive revolutions within 0.5 % of each other's speed: one plateau
MIN_PLATEAU_S = 1.0     # shorter plateaus are transients
END_DROP = 2            # revolutions dropped at a plateau's end
OUTLIER_MADS = 5.0      # robust outlier limit within a plateau
AIR_FORCE_N = 20.0      # dynamometer mean resultant below this: no cut
SETTLE_S = 1.0          # the air check skips a plateau's first second: the speed loop's settling
                        # (simulated MCH-10: torque 1 % high 0.9 s after a step) is not a cut
RUN_UP_HINT = ("an air cut in which the spindle speed steps, in each gear (e.g. `millsense sim --scenario "
               "aircut-low --capture F` and aircut-high; on the machine, S-word changes of 100 rpm or more "
               "with nothing cut)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture files (air cuts; trial cuts with --dynamometer)")
    parser.add_argument("--config", "-c", required=True, metavar="FILE", help="the daemon's configuration (channels, motor, gears, tool)")
    parser.add_argument("--out", required=True, metavar="FILE", help="calibration TOML file to write")
    parser.add_argument("--dynamometer", action="store_true",
                        help="captures carry fx, fy: exclude cutting revolutions from the friction fit and fit C_f")
    from millsense.daemon.commands import calibrate_material

    calibrate_material.add_arguments(parser)


def plateaus(rpm: list[float], t_s: list[float]) -> list[tuple[int, int]]:
    """Index ranges [start, stop) of constant-speed plateaus: runs of revolutions each within
    PLATEAU_REL of the previous one, lasting at least MIN_PLATEAU_S."""
    out = []
    start = 0
    for k in range(1, len(rpm) + 1):
        if k < len(rpm) and abs(rpm[k] - rpm[k - 1]) <= PLATEAU_REL * abs(rpm[k - 1]):
            continue
        if t_s[k - 1] - t_s[start] >= MIN_PLATEAU_S:
            out.append((start, k))
        start = k
    return out


def steady_mask(rpm: list[float], t_s: list[float], load_nm: list[float]) -> list[bool]:
    """True for revolutions in the settled part of a constant-speed plateau.

    Dropped from each plateau:
    - its first half: after a speed step the drive's speed loop settles for a
      second or more, and meanwhile `P_g/ω` carries inertia torque `J·dω/dt`
      although the speed already looks constant to 0.3 % (simulated MCH-10: 1 %
      high 0.9 s after a step);
    - its last END_DROP revolutions: the next speed step starts inside them, its
      torque at once, its speed change not yet visible;
    - revolutions whose load lies more than OUTLIER_MADS robust deviations from
      the plateau's median (anything else that is not friction).
    """
    keep = [False] * len(rpm)
    for start, stop in plateaus(rpm, t_s):
        half = 0.5 * (t_s[start] + t_s[stop - 1])
        idx = [j for j in range(start, stop - END_DROP) if t_s[j] >= half]
        if idx:
            loads = sorted(load_nm[j] for j in idx)
            med = loads[len(loads) // 2]
            mad = sorted(abs(x - med) for x in loads)[len(loads) // 2]
            for j in idx:
                keep[j] = abs(load_nm[j] - med) <= OUTLIER_MADS * 1.4826 * mad + 1e-9
    return keep


def settled_plateaus(rpm: list[float], t_s: list[float]) -> list[list[int]]:
    """Per plateau, its revolutions after SETTLE_S and before the last END_DROP, outliers kept: what
    the air check looks at (the first half, which the fit drops, is often where an approach in air is)."""
    return [[j for j in range(start, stop - END_DROP) if t_s[j] - t_s[start] >= SETTLE_S]
            for start, stop in plateaus(rpm, t_s)]


def collect(captures, settings, dynamometer: bool):
    """Per gear: (omega_rad_s, P_g/ω) of steady air revolutions; (omega, P_g/ω, dω/dt) of every air
    revolution (for J); cut revolutions for C_f; per gear, (rpm, P_g/ω of its revolutions) of each
    settled plateau (for the air check; empty with a dynamometer)."""
    import numpy as np

    from millsense.daemon.commands.capture_reader import CaptureError, iter_capture_blocks
    from millsense.daemon.pipeline.estimator import Estimator

    air: dict[str, tuple[list[float], list[float]]] = {}
    runs: dict[str, list[tuple[float, float, float]]] = {}
    cuts: list[tuple[str, float, float, float]] = []      # gear, omega, P_g/ω, mean |F|
    settled: dict[str, list[tuple[float, list[float]]]] = {}
    for path in captures:
        est = None
        descriptor = None
        revs: list[dict] = []
        for desc, block in iter_capture_blocks(path):
            if est is None or desc is not descriptor:
                if est is not None and desc != descriptor:
                    raise CaptureError(f"{path}: the DAQ descriptor changes inside the capture; split it")
                if est is None:
                    est = Estimator(settings, desc, desc.sample_rate_hz, friction_zero=True,
                                    force_magnitude=dynamometer)
                descriptor = desc
            revs.extend(est.process(block).estimates)
        if est is None:
            print(f"{path}: no samples", file=sys.stderr)
            continue
        good = [r for r in revs if r["valid"] and r["torque_nm"] is not None]
        rate = float(descriptor.sample_rate_hz)
        rpm, t_s = [r["spindle_rpm"] for r in good], [r["seq_end"] / rate for r in good]
        steady = steady_mask(rpm, t_s, [r["torque_nm"] for r in good])
        for idx in settled_plateaus(rpm, t_s) if not dynamometer else ():
            if idx:
                settled.setdefault(good[idx[0]]["gear"], []).append(
                    (float(np.median([rpm[j] for j in idx])), [good[j]["torque_nm"] for j in idx]))
        for r, ok in zip(good, steady):
            omega = 2 * math.pi * r["spindle_rpm"] / 60.0
            force = r.get("force_measured_n")
            is_cut = dynamometer and force is not None and force > AIR_FORCE_N
            if not is_cut and r.get("spindle_accel_rad_s2") is not None:
                runs.setdefault(r["gear"], []).append((omega, r["torque_nm"], r["spindle_accel_rad_s2"]))
            if not ok:
                continue
            if is_cut:
                cuts.append((r["gear"], omega, r["torque_nm"], force))
                continue
            w, t = air.setdefault(r["gear"], ([], []))
            w.append(omega)
            t.append(r["torque_nm"])
    return air, runs, cuts, settled


def gear_ranges_rpm(gears) -> dict[str, tuple[float, float]]:
    """Spindle speeds each gear covers, for the advice: from the gear below's top speed (the lowest
    gear: a third of its own, where friction is still measurable) to its max_spindle_rpm."""
    out, lo = {}, None
    for g in sorted(gears, key=lambda g: g.max_spindle_rpm):
        hi = float(g.max_spindle_rpm)
        out[g.name] = (hi / 3.0 if lo is None else lo, hi)
        lo = hi
    return out


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from millsense.daemon.config.load import load_config
    from millsense.daemon.physics.calibration import (
        fit_cf,
        fit_friction,
        judge_air,
        judge_friction,
        judge_speeds,
        speed_levels_rpm,
    )
    from millsense.daemon.commands.capture_reader import CaptureError

    out_problem = _out_problem(Path(args.out))
    if out_problem:  # before the fitting: a typo in --out should not cost the whole run
        print(f"millsense calibrate: error: {out_problem}", file=sys.stderr)
        return 2
    if getattr(args, "material", False):   # a material from a test cut (calibrate_material.py)
        from millsense.daemon.commands import calibrate_material

        return calibrate_material.run(args)
    settings = load_config(args.config)
    for path in args.captures:
        if not Path(path).is_file():
            print(f"millsense calibrate: {path}: no such capture file", file=sys.stderr)
            return 1
    try:
        air, runs, cuts, settled = collect(args.captures, settings, args.dynamometer)
    except CaptureError as exc:
        print(f"millsense calibrate: {exc}", file=sys.stderr)
        return 1

    radius_mm = float(settings.tool.diameter_mm) / 2.0
    ranges = gear_ranges_rpm(settings.gears)
    fits, refusals = {}, []
    print("friction per gear, P_g/w = T_f' + B' w  ([P] eq. 13 with T_c = 0):")
    for gear in settings.gears:
        refusals += judge_air(gear.name, settled.get(gear.name, []), ranges[gear.name])
        if gear.name not in air:
            print(f"  {gear.name}: no steady air revolutions in the captures - left as configured")
            continue
        omega, load = (np.asarray(x) for x in air[gear.name])
        rpm = omega * 60.0 / (2 * math.pi)
        found = judge_speeds(gear.name, rpm, ranges[gear.name])
        if found:   # a line through fewer speeds is noise, whatever least squares returns
            refusals += found
            continue
        fit = fit_friction(omega, load)
        res = np.asarray(fit.residuals_nm)
        print(f"  {gear.name}: T_f' = {fit.friction_torque_nm:.4f} N.m  B' = {fit.viscous_nms:.5f} N.m.s/rad"
              f"  R2 = {fit.r2:.4f}  samples = {fit.samples}")
        print(f"      residuals: rms {np.sqrt(np.mean(res**2)):.4f} N.m, max {np.max(np.abs(res)):.4f} N.m;"
              f" speeds ~{', '.join(f'{s:.0f}' for s, _ in speed_levels_rpm(rpm)[:12])} rpm")
        found = judge_friction(gear.name, omega, fit, ranges[gear.name])
        refusals += found
        if not found:
            fits[gear.name] = fit
    if not refusals and not fits:
        print("millsense calibrate: no gear had steady air-cut revolutions to fit; record "
              "an air cut at 3 or more speeds in each gear", file=sys.stderr)
        return 1

    inertia = _fit_inertia(runs, settings, fits, refusals)
    if refusals:
        _refuse(refusals)
        return 1

    cf_value = None
    if args.dynamometer:
        cf_value = _fit_cf(cuts, settings, fits, radius_mm, fit_cf)

    try:
        _write_toml(Path(args.out), fits, inertia, cf_value)
    except OSError as exc:
        print(f"millsense calibrate: error: cannot write {args.out}: {exc.strerror or exc}; nothing written",
              file=sys.stderr)
        return 1
    print(f"wrote {args.out}")
    return 0


def _refuse(refusals) -> None:
    """Every refusal, one line each, and what was (not) done."""
    for r in refusals:
        print(f"millsense calibrate: refused: {r}", file=sys.stderr)
    print("millsense calibrate: nothing written (on the simulator: `millsense sim --scenario aircut-low "
          "--capture F`, and aircut-high, record such captures)", file=sys.stderr)


def _fit_inertia(runs, settings, fits, refusals: list) -> dict:
    """J per gear fitted (friction just fitted); a J the captures do not determine goes to `refusals`."""
    import numpy as np

    from millsense.daemon.physics.calibration import fit_inertia, judge_inertia

    out = {}
    if fits:
        print("inertia per gear, P_g/w - T_f' - B' w = J dw/dt  (eq. 13 with inertia, air revolutions):")
    for gear in settings.gears:
        if gear.name not in fits:
            continue   # nothing fitted for this gear: leave it all as configured
        rows = np.asarray(runs.get(gear.name, []), dtype=float).reshape(-1, 3)
        fit = fits[gear.name]
        left_nm = rows[:, 1] - fit.friction_torque_nm - fit.viscous_nms * rows[:, 0]
        try:
            j = fit_inertia(rows[:, 2], left_nm)
        except ValueError as exc:
            # No run-up in the captures: nothing says what J is, and nothing contradicts the friction fit.
            # The friction is written; J is left as the config has it (config.warnings says when it has none).
            print(f"millsense calibrate: warning: gear {gear.name}: inertia not fitted ({exc}); friction is "
                  f"written without it; to fit J, add {RUN_UP_HINT}", file=sys.stderr)
            continue
        print(f"  {gear.name}: J = {j.inertia_kgm2:.4f} kg.m2 (+/- {j.sigma_kgm2:.4f})  R2 = {j.r2:.4f}"
              f"  revolutions = {j.samples}, {j.changing} changing speed")
        found = judge_inertia(gear.name, j, RUN_UP_HINT)
        refusals += found
        if not found:
            out[gear.name] = j
    return out


def _fit_cf(cuts, settings, fits, radius_mm, fit_cf):
    """C_f of [P] eq. (18) from cutting revolutions: measured mean |F| against T_c/R."""
    import numpy as np

    gears = {g.name: g for g in settings.gears}
    torque, force = [], []
    for gear, omega, p_over_w, f in cuts:
        fit = fits.get(gear)
        t_f = fit.friction_torque_nm if fit else gears[gear].friction_torque_nm
        b = fit.viscous_nms if fit else gears[gear].viscous_nms
        torque.append(p_over_w - t_f - b * omega)
        force.append(f)
    if len(torque) < 3:
        print(f"C_f: {len(torque)} steady cutting revolutions - not enough, left as configured")
        return None
    fit = fit_cf(np.asarray(force), np.asarray(torque), radius_mm)
    print(f"C_f ([P] eq. 18): {fit.cf:.4f}  R2 = {fit.r2:.4f}  samples = {fit.samples}")
    return float(fit.cf)


def _write_toml(path: Path, fits: dict, inertia: dict, cf: float | None) -> None:
    lines = ["# written by `millsense calibrate`: friction and inertia per gear ([P] eq. 13 with J dw/dt),",
             "# referred to the spindle", ""]
    for name, fit in fits.items():
        lines += [
            "[[gears]]",
            f'name = "{name}"',
            f"friction_torque_nm = {fit.friction_torque_nm:.6f}",
            f"viscous_nms = {fit.viscous_nms:.8f}",
            *([f"inertia_kgm2 = {inertia[name].inertia_kgm2:.6f}"] if name in inertia else []),
            f"samples = {int(fit.samples)}",
            f"r2 = {fit.r2:.6f}",
            "",
        ]
    if cf is not None:
        lines += ["[tool]", f"cf = {cf:.6f}", ""]
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text("\n".join(lines))
        tmp.replace(path)
    except OSError:
        tmp.unlink(missing_ok=True)  # no half-written .tmp left beside the target
        raise


def _out_problem(path: Path) -> str | None:
    """Why `--out` cannot be written as a file, or None."""
    if path.is_dir():
        return f"--out {path} is a directory: give a file name, e.g. {path / 'calibration.toml'}"
    parent = path.parent
    if not parent.is_dir():
        return f"--out {path}: the folder {parent} does not exist"
    return None
