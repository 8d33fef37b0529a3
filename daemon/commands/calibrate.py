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
naming the capture that would fit it. A J that comes out negative, or poorly
determined, says the captures are wrong: refused, exit 1, no file written.

With `--dynamometer` (captures with fx, fy channels), revolutions the
dynamometer sees as cutting are kept out of the friction fit and used to fit
`C_f` of [P] eq. (18) against the measured mean resultant force.
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
J_REL_SIGMA_MAX = 0.1   # refuse a J whose standard error is more than 10 % of it
RUN_UP_HINT = ("an air cut in which the spindle speed steps, in each gear (e.g. `millsense sim --scenario "
               "aircut-low --capture F` and aircut-high; on the machine, S-word changes of 100 rpm or more "
               "with nothing cut)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("captures", nargs="+", metavar="CAPTURE", help="capture files (air cuts; trial cuts with --dynamometer)")
    parser.add_argument("--config", required=True, metavar="FILE", help="the daemon's configuration (channels, motor, gears, tool)")
    parser.add_argument("--out", required=True, metavar="FILE", help="calibration TOML file to write")
    parser.add_argument("--dynamometer", action="store_true",
                        help="captures carry fx, fy: exclude cutting revolutions from the friction fit and fit C_f")


def steady_mask(rpm: list[float], t_s: list[float], load_nm: list[float]) -> list[bool]:
    """True for revolutions in the settled part of a constant-speed plateau.

    A plateau is a run of revolutions each within PLATEAU_REL of the previous one,
    lasting at least MIN_PLATEAU_S. Dropped from it:
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
    start = 0
    for k in range(1, len(rpm) + 1):
        if k < len(rpm) and abs(rpm[k] - rpm[k - 1]) <= PLATEAU_REL * abs(rpm[k - 1]):
            continue
        if t_s[k - 1] - t_s[start] >= MIN_PLATEAU_S:
            half = 0.5 * (t_s[start] + t_s[k - 1])
            idx = [j for j in range(start, k - END_DROP) if t_s[j] >= half]
            if idx:
                loads = sorted(load_nm[j] for j in idx)
                med = loads[len(loads) // 2]
                mad = sorted(abs(x - med) for x in loads)[len(loads) // 2]
                for j in idx:
                    keep[j] = abs(load_nm[j] - med) <= OUTLIER_MADS * 1.4826 * mad + 1e-9
        start = k
    return keep


def collect(captures, settings, dynamometer: bool):
    """Per gear: (omega_rad_s, P_g/ω) of steady air revolutions; (omega, P_g/ω, dω/dt) of every air
    revolution (for J); cut revolutions for C_f."""
    from millsense.daemon.pipeline.capture_reader import CaptureError, iter_capture_blocks
    from millsense.daemon.pipeline.estimator import Estimator

    air: dict[str, tuple[list[float], list[float]]] = {}
    runs: dict[str, list[tuple[float, float, float]]] = {}
    cuts: list[tuple[str, float, float, float]] = []      # gear, omega, P_g/ω, mean |F|
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
        steady = steady_mask([r["spindle_rpm"] for r in good], [r["seq_end"] / rate for r in good],
                             [r["torque_nm"] for r in good])
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
    return air, runs, cuts


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from millsense.daemon.config import load_config
    from millsense.daemon.physics.calibration import fit_cf, fit_friction, fit_inertia
    from millsense.daemon.pipeline.capture_reader import CaptureError

    settings = load_config(args.config)
    for path in args.captures:
        if not Path(path).is_file():
            print(f"millsense calibrate: {path}: no such capture file", file=sys.stderr)
            return 1
    try:
        air, runs, cuts = collect(args.captures, settings, args.dynamometer)
    except CaptureError as exc:
        print(f"millsense calibrate: {exc}", file=sys.stderr)
        return 1

    radius_mm = float(settings.tool.diameter_mm) / 2.0
    fits = {}
    print("friction per gear, P_g/w = T_f' + B' w  ([P] eq. 13 with T_c = 0):")
    for gear in settings.gears:
        if gear.name not in air or len(air[gear.name][0]) < 3:
            n = len(air.get(gear.name, ([],))[0])
            print(f"  {gear.name}: {n} steady air revolutions - not enough, left as configured")
            continue
        omega, load = (np.asarray(x) for x in air[gear.name])
        try:
            fit = fit_friction(omega, load)
        except ValueError as exc:
            print(f"  {gear.name}: cannot fit ({exc}); left as configured")
            continue
        fits[gear.name] = fit
        res = np.asarray(fit.residuals_nm)
        speeds = sorted({round(w * 60 / (2 * math.pi), -1) for w in omega})
        print(f"  {gear.name}: T_f' = {fit.friction_torque_nm:.4f} N.m  B' = {fit.viscous_nms:.5f} N.m.s/rad"
              f"  R2 = {fit.r2:.4f}  samples = {fit.samples}")
        print(f"      residuals: rms {np.sqrt(np.mean(res**2)):.4f} N.m, max {np.max(np.abs(res)):.4f} N.m;"
              f" speeds ~{', '.join(f'{s:.0f}' for s in speeds[:12])} rpm")
    if not fits:
        print("millsense calibrate: no gear had enough steady air-cut revolutions to fit", file=sys.stderr)
        return 1

    inertia = _fit_inertia(runs, settings, fits, fit_inertia)
    if inertia is None:
        return 1

    cf_value = None
    if args.dynamometer:
        cf_value = _fit_cf(cuts, settings, fits, radius_mm, fit_cf)

    _write_toml(Path(args.out), fits, inertia, cf_value)
    print(f"wrote {args.out}")
    return 0


def _fit_inertia(runs, settings, fits, fit_inertia) -> dict | None:
    """J per gear fitted (friction just fitted), or None after saying why a fit was refused."""
    import numpy as np

    out = {}
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
            # The friction is written; J is left as the config has it (config_warnings says when it has none).
            print(f"millsense calibrate: warning: gear {gear.name}: inertia not fitted ({exc}); friction is "
                  f"written without it; to fit J, add {RUN_UP_HINT}", file=sys.stderr)
            continue
        print(f"  {gear.name}: J = {j.inertia_kgm2:.4f} kg.m2 (+/- {j.sigma_kgm2:.4f})  R2 = {j.r2:.4f}"
              f"  revolutions = {j.samples}, {j.changing} changing speed")
        if not j.inertia_kgm2 > 0.0 or j.sigma_kgm2 > J_REL_SIGMA_MAX * abs(j.inertia_kgm2):
            print(f"millsense calibrate: gear {gear.name}: inertia fit refused (J = {j.inertia_kgm2:.4f} "
                  f"+/- {j.sigma_kgm2:.4f} kg.m2: negative or not determined to {J_REL_SIGMA_MAX:.0%}); "
                  f"needs {RUN_UP_HINT}; nothing written", file=sys.stderr)
            return None
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
    tmp.write_text("\n".join(lines))
    tmp.replace(path)
