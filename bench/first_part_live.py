"""Issue 41's acceptance live: every first-part case through `millsense sim` and `millsense run` (the whole sweep).

The test (tests/e2e/test_first_part_acceptance.py) plays a selection; this plays everything, with the same run
code (tests/e2e/first_part_run.py):

- every correct first part: first-part-slot, -down, -up (30 operations), -pocket (corners and a ramp,
  `varying`), -worn (tools at 80 % of their life), each with the plant's material batch −20 %, 0 and +20 %
  off the config's, played at `--speed` (default 3×; pacing is not what they test): alarms raised (none
  expected), processes armed, and the daemon's published force and torque over each operation's steady
  revolutions against the plant's truth;
- every slot of first-part-slot alone at 1× (`--only-operation`): axial 1.8 × at −20 % → `expected_high`,
  axial 0.5 × and radial 0.5 × at +20 % → `expected_low`: on which steady revolution of the cut (the truth's)
  each tripped, and on which revolution the daemon judged it (its steady rule).

Run: .venv/bin/python bench/first_part_live.py [--speed K] [--jobs N] [--no-trips] [--no-parts]
Minutes: about 15 CPU s a batch of parts at 3×, 3 s a trip; `--jobs 2` runs two at once.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from millsense.sim.first_part import FIRST_PART_PROGRAMS  # noqa: E402
from tests.e2e.first_part_run import force_by_operation, play, steady_revolution_of_alarm  # noqa: E402

PROGRAMS = ("first-part-slot", "first-part-down", "first-part-up", "first-part-pocket", "first-part-worn")
BATCHES = (-20, 0, 20)
TRIPS = (("axial 1.8 x", "--axial-scale", 1.8, -20, "expected_high"),
         ("axial 0.5 x", "--axial-scale", 0.5, 20, "expected_low"),
         ("radial 0.5 x", "--radial-scale", 0.5, 20, "expected_low"))


def judged_from(program: str, op: int) -> int:
    o = next(o for o in FIRST_PART_PROGRAMS[program].operations if o.number == op)
    return math.ceil(o.tool.radius_mm / (o.feed_per_tooth_mm * o.tool.flutes) - 1e-9)


def parts(work: Path, speed: float, jobs: int) -> None:
    cases = [(p, b) for b in BATCHES for p in PROGRAMS]

    def one(case):
        program, batch = case
        name = f"fpl-{program[11:]}{'m' if batch < 0 else 'p'}{abs(batch)}"
        for attempt in range(2):   # a run stalled by the box's load (no summary in 180 s) is played once more
            d = work / f"{program}{batch:+d}-{attempt}"
            d.mkdir()
            try:
                return case, play(d, program, name=f"{name}-{attempt}", speed=speed,
                                  sim_args=("--material-offset-pct", str(batch)))
            except AssertionError as exc:
                print(f"  {program} {batch:+d}: run {attempt + 1} failed: {str(exc)[:200]}", flush=True)
        return case, None

    with ThreadPoolExecutor(jobs) as pool:
        runs = {case: run for case, run in pool.map(one, cases) if run is not None}
    print(f"\ncorrect first parts, played at {speed:g}x: alarms and the published force/torque against the truth "
          "(steady revolutions of each operation)")
    print(f"{'program':<18} {'batch':>5} {'ops':>3} {'armed':>5} {'alarms':>6}  {'force bias':>10} {'max':>6}  "
          f"{'torque bias':>11} {'max':>6}")
    every: dict[int, list] = {b: [] for b in BATCHES}
    kinds: dict[str, list] = {}
    per_key: dict[str, dict[int, float]] = {}
    for (program, batch), run in runs.items():
        f = force_by_operation(run)
        fr = np.concatenate([v["force_ratio"] for v in f.values()] or [np.array([])])
        tr = np.concatenate([v["torque_ratio"] for v in f.values()] or [np.array([])])
        every[batch].append((fr, tr))
        for k, v in f.items():
            if len(v["force_ratio"]):
                per_key.setdefault(k, {})[batch] = float(v["force_ratio"].mean())
        for k, v in f.items():
            op = next(o for o in FIRST_PART_PROGRAMS[program].operations if k.endswith(f"/{o.number}"))
            kind = ("worn" if program == "first-part-worn" else "2-flute" if op.tool.flutes == 2
                    else "3-4 flute slots" if (op.mode or "slot") == "slot" else "3-4 flute down/up")
            kinds.setdefault(kind, []).append(v["force_ratio"])
        armed = sum(p.get("expected_band") == "armed" for p in run.processes)
        figures = (f"{100 * (fr.mean() - 1):+9.2f} % {100 * np.abs(fr - 1).max():5.2f} %  "
                   f"{100 * (tr.mean() - 1):+10.2f} % {100 * np.abs(tr - 1).max():5.2f} %") if len(fr) else \
            "(varying engagement: not paired)"
        print(f"{program:<18} {batch:+5d} {len(run.processes):3d} {armed:5d} {len(run.alarms):6d}  {figures}")
        for a in run.alarms:
            print(f"    ALARM {a['level']} {a.get('program')}/{a.get('tool')}/{a.get('operation')}: {a.get('reason')}")
        for p in run.processes:
            if p.get("expected_band") != "armed":
                print(f"    {p['key']}: expected_band {p.get('expected_band')} ({p.get('cutting_revolutions')} "
                      "revolutions called cutting)")
    for b in BATCHES:
        fr = np.concatenate([x[0] for x in every[b]])
        print(f"batch {b:+d} %: force over {len(fr)} revolutions: bias {100 * (fr.mean() - 1):+.2f} %, "
              f"p95 {100 * np.percentile(np.abs(fr - 1), 95):.2f} %, max {100 * np.abs(fr - 1).max():.2f} %")
    for kind, rows in kinds.items():
        fr = np.concatenate(rows)
        print(f"  {kind:<18} {len(fr):5d} revolutions: bias {100 * (fr.mean() - 1):+.2f} %, "
              f"p95 {100 * np.percentile(np.abs(fr - 1), 95):.2f} %, max {100 * np.abs(fr - 1).max():.2f} %")
    print("\nforce / true force per operation (mean over its steady revolutions), batches -20 / 0 / +20 %:")
    for k in sorted(per_key, key=lambda k: [int(x) for x in k.split("/")]):
        v = per_key[k]
        print(f"  {k:<11} " + "  ".join(f"{v.get(b, float('nan')):.4f}" for b in BATCHES))


def trips(work: Path, jobs: int) -> None:
    slot = FIRST_PART_PROGRAMS["first-part-slot"]
    cases = [(label, flag, k, batch, level, op.number) for label, flag, k, batch, level in TRIPS
             for op in slot.operations]

    def one(case):
        label, flag, k, batch, level, op = case
        d = work / f"trip-{flag[2]}{k:g}-{op}"
        d.mkdir()
        try:
            run = play(d, "first-part-slot", name=f"fpt-{flag[2]}{str(k).replace('.', '')}-{op}", until_alarm=level,
                       sim_args=("--only-operation", str(op), flag, f"{op}:{k:g}", "--material-offset-pct", str(batch)))
        except AssertionError as exc:
            return case, None, str(exc)[:300]
        alarm = next(a for a in run.alarms if a["level"] == level)
        return case, (steady_revolution_of_alarm(run, alarm), alarm["process_rev"] - judged_from("first-part-slot", op)
                      + 1, alarm["value"] / alarm["expected"], run.feed_held), ""

    with ThreadPoolExecutor(jobs) as pool:
        results = list(pool.map(one, cases))
    print("\ntrips at 1x, each slot of first-part-slot alone: the steady revolution of the cut (truth) the alarm "
          "came on, the revolution the daemon judged it (its steady rule), measured/expected, feed held")
    for label, *_ in TRIPS:
        rows = [(c, r, e) for c, r, e in results if c[0] == label]
        print(f"  {label} (batch {rows[0][0][3]:+d} %, {rows[0][0][4]}):")
        for (_, _, _, _, _, op), r, err in rows:
            print(f"    op {op:3d}: " + (f"NO TRIP ({err})" if r is None else
                                        f"steady rev {r[0]}, judged rev {r[1]}, ratio {r[2]:.3f}, held {r[3]}"))
        got = [r for _, r, _ in rows if r is not None]
        if got:
            print(f"    tripped {len(got)}/{len(rows)}; steady revolution of the trip: "
                  f"{', '.join(str(r[0]) for r in got)}; within 3: {sum(r[0] <= 3 for r in got)}/{len(rows)}")


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed", type=float, default=3.0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--no-trips", action="store_true")
    ap.add_argument("--no-parts", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="first-part-live-") as tmp:
        work = Path(tmp)
        if not args.no_parts:
            parts(work, args.speed, args.jobs)
        if not args.no_trips:
            trips(work, args.jobs)
    print(f"\n{time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
