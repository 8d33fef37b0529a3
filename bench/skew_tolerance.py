"""The inter-channel skew the estimator tolerates: currents sampled later than their voltages.

A DAQ that does not sample its six line channels at the same instant (a
multiplexed ADC scanning the voltages, then the currents) hands the estimator
currents that are Δt late against their voltages. The per-sample power
p = Σ v·i (docs/physics.md §1, [P] eq. 11) then sees a phase shifted by
δ = 2π·f_e·Δt at the motor's electrical frequency f_e, and the mean power moves
by about Q·δ (Q: the motor's reactive power, large against a light cut's active
power: an induction motor's magnetising current is ~30 % of its rated current).

Here each scenario is simulated once (seed fixed, the simulator's noise and
anti-alias filter), written as a capture and decoded by the real `StreamDecoder`;
then the three current columns are shifted by Δt (a band-limited fractional
delay: a phase ramp in the frequency domain, so a fraction of a sample is exact
and the amplitude untouched) and the whole stream goes through the `Estimator`.
Torque is compared with the simulator's truth on steady cutting revolutions
(as bench/accuracy.py does). The wiring check (`phase_check.PhaseCheck`, which
the daemon runs on the same raw samples) is run too: does it notice the skew?

Δt > 0: the current is sampled Δt *after* its voltage (the recorded current at
sample n is the current at t_n + Δt).

    .venv/bin/python bench/skew_tolerance.py [--scenario step --scenario step-1800] [--skew-us 0 10 100]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tests.estimator import simcase  # noqa: E402

SKEWS_US = (0.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0, 250.0, 500.0, 1000.0, -10.0, -100.0)
SCENARIOS = ("step", "step-1800")


@dataclass(frozen=True)
class Stream:
    """A decoded capture held in memory: its descriptor, the counts, and its blocks' boundaries."""

    descriptor: object
    counts: np.ndarray            # (n, C) int16
    blocks: list[tuple[int, int, int, int, bool]]   # (start row, seq, index, lost_before, discontinuity)
    truth: list[dict]


@dataclass(frozen=True)
class Result:
    skew_us: float
    n: int                        # steady cutting revolutions compared
    mean_nm: float                # mean torque error, estimate − truth
    mean_pct: float               # the same, % of the truth
    p95_pct: float                # 95th percentile of |error| %
    invalid: int                  # steady cutting revolutions the estimator published invalid
    phase_fault: bool             # the wiring check raised its fault


def load(scenario: str, tmp: Path, seed: int = 11, duration_s: float | None = None) -> Stream:
    from millsense.daemon.commands.capture_reader import iter_capture_blocks
    from millsense.sim import write_capture

    cap, truth_path = tmp / f"{scenario}-{seed}-{duration_s}.bin", tmp / f"{scenario}-{seed}-{duration_s}.jsonl"
    write_capture(scenario, str(cap), str(truth_path), seed=seed, duration_s=duration_s)
    desc, parts, blocks, row = None, [], [], 0
    for d, b in iter_capture_blocks(cap):
        desc = d
        blocks.append((row, b.seq, b.index, b.lost_before, b.discontinuity))
        parts.append(b.counts)
        row += len(b.counts)
    return Stream(desc, np.concatenate(parts), blocks, simcase.read_truth(truth_path))


def current_columns(descriptor) -> list[int]:
    from millsense.drivers.protocol import ChannelKind

    return [k for k, ch in enumerate(descriptor.channels) if ch.kind == ChannelKind.CURRENT]


def skewed(stream: Stream, skew_us: float) -> np.ndarray:
    """The counts with each current column read `skew_us` later (x[n] -> x(t_n + Δt)), rounded to counts."""
    out = stream.counts.copy()
    if skew_us == 0.0:
        return out
    shift = skew_us * 1e-6 * stream.descriptor.sample_rate_hz          # in samples, may be fractional
    n = len(out)
    ramp = np.exp(2j * np.pi * np.fft.rfftfreq(n) * shift)            # advance by `shift` samples
    for c in current_columns(stream.descriptor):
        x = out[:, c].astype(np.float64)
        y = np.fft.irfft(np.fft.rfft(x) * ramp, n)
        out[:, c] = np.clip(np.rint(y), -32768, 32767).astype(np.int16)
    return out


def measure(stream: Stream, skew_us: float, scenario: str, tmp: Path) -> Result:
    from millsense.daemon.pipeline.estimator import Estimator
    from millsense.daemon.pipeline.phase_check import PhaseCheck
    from millsense.drivers.base import SampleBlock

    settings = simcase.settings_for(scenario, tmp)
    counts = skewed(stream, skew_us)
    est = Estimator(settings, stream.descriptor, stream.descriptor.sample_rate_hz)
    check = PhaseCheck(settings, stream.descriptor)
    estimates, fault = [], False
    ends = [b[0] for b in stream.blocks[1:]] + [len(counts)]
    for (start, seq, index, lost, disc), end in zip(stream.blocks, ends):
        block = counts[start:end]
        estimates += est.process(SampleBlock(seq, index, block, lost, disc)).estimates
        check.update(block, lost, disc)
        fault = fault or check.faulted
    pairs = [(e, t) for e, t in simcase.match(estimates, stream.truth, 1)
             if t["steady"] and t["cutting"] and t["torque_nm"] > 0.5]
    good = [(e, t) for e, t in pairs if e["valid"]]
    if not good:
        return Result(skew_us, 0, float("nan"), float("nan"), float("nan"), len(pairs), fault)
    err = np.array([e["torque_nm"] - t["torque_nm"] for e, t in good])
    rel = np.array([(e["torque_nm"] - t["torque_nm"]) / t["torque_nm"] * 100 for e, t in good])
    return Result(skew_us, len(good), float(err.mean()), float(rel.mean()), float(np.percentile(np.abs(rel), 95)),
                  len(pairs) - len(good), fault)


def electrical_hz(scenario: str) -> float:
    """The motor's electrical frequency in the scenario's cut (spindle rpm × gear ratio × pole pairs / 60)."""
    from millsense.sim.scenarios import SCENARIOS as ALL

    sc = ALL[scenario]
    rpm = max(r for _, r in sc.spindle_schedule)
    return rpm * sc.gear.ratio * sc.machine.motor.pole_pairs / 60.0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", action="append", help=f"default: {', '.join(SCENARIOS)}")
    parser.add_argument("--skew-us", type=float, nargs="+", default=list(SKEWS_US))
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--duration-s", type=float, default=None, help="simulate only the first N seconds")
    args = parser.parse_args()
    print(f"torque error vs simulator truth with the currents sampled Δt after their voltages (seed {args.seed})")
    print("steady cutting revolutions; error = estimate - truth; δ = 2π·f_e·Δt")
    print(f"{'scenario':<10} {'f_e Hz':>6} {'Δt µs':>7} {'δ deg':>6} {'n':>4} {'mean N·m':>9} "
          f"{'mean %':>8} {'p95|e| %':>9} {'invalid':>7} {'phase check':>11}")
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        for scenario in args.scenario or SCENARIOS:
            stream = load(scenario, tmp, args.seed, args.duration_s)
            f_e = electrical_hz(scenario)
            for skew in args.skew_us:
                r = measure(stream, skew, scenario, tmp)
                deg = 360.0 * f_e * skew * 1e-6
                print(f"{scenario:<10} {f_e:>6.1f} {skew:>7.1f} {deg:>6.2f} {r.n:>4} {r.mean_nm:>+9.3f} "
                      f"{r.mean_pct:>+8.2f} {r.p95_pct:>9.2f} {r.invalid:>7} {'FAULT' if r.phase_fault else 'ok':>11}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
