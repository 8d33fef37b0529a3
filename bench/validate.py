"""Accuracy report with figures: the papers' experiments replayed, and what a user must get right.

Simulates every scenario of the two papers, replays each capture through
`millsense replay` (a real subprocess, the product's own command), pairs every
estimate with the simulator's truth revolution, and writes docs/validation.md
with PNG figures in docs/validation/. Then a sensitivity study: the same
replays with one user input wrong at a time. Every number and figure in the
report comes from this run; the report is regenerated from scratch each time, except
the sections other benches write between their markers (learned limits: validate_learning.py; adaptive feed
control: validate_afc.py), which are carried over as they are, with their figures.

    .venv/bin/python bench/validate.py [--seed 11] [--jobs 2] [--out docs]

Needs the plot extra (matplotlib). Captures go to a temporary directory
(`--workdir DIR` keeps them, for debugging).
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import validate_cases as vc  # noqa: E402
import validate_runs as vr  # noqa: E402

REPO = vr.REPO


def _capture_job(args):
    cap, workdir = args
    vr.make_capture(cap, workdir)
    return cap


def _replay_job(args):
    case, workdir, calibration = args
    return vr.replay(case, workdir, calibration)


def run_all(seed: int, jobs: int, workdir: Path) -> dict:
    """Every capture, the calibration, every replay; returns what the report needs."""
    paper = vc.paper_cases(seed)
    groups = vc.sensitivity_cases(seed)
    cases = vc.unique(paper + [c for g in groups.values() for c in g])
    captures = vc.all_captures(cases, seed)
    timings = {}
    with multiprocessing.get_context("fork").Pool(jobs) as pool:
        t = time.perf_counter()
        # longest first, so that the two workers finish together
        order = sorted(captures, key=lambda c: -vc.SCENARIOS[c.scenario].duration_s)
        for _ in pool.imap_unordered(_capture_job, [(c, workdir) for c in order]):
            pass
        timings["captures"] = (len(captures), time.perf_counter() - t)
        t = time.perf_counter()
        calibration, calibration_text = vr.calibrate(workdir, seed)
        timings["calibrate"] = (1, time.perf_counter() - t)
        t = time.perf_counter()
        order = sorted(cases, key=lambda c: -vc.SCENARIOS[c.scenario].duration_s)
        results = {r.case.key: r for r in pool.imap_unordered(_replay_job, [(c, workdir, calibration) for c in order])}
        timings["replays"] = (len(cases), time.perf_counter() - t)
    truths = {c.capture: vr.read_truth(c, workdir) for c in cases}
    return {"paper": paper, "groups": groups, "results": results, "truths": truths, "workdir": workdir,
            "calibration_text": calibration_text, "calibration_path": calibration, "timings": timings}


def machine_info() -> dict[str, str]:
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO), "status", "--porcelain"], capture_output=True, text=True,
                               timeout=10).stdout.strip()
        commit += " (with uncommitted changes)" if dirty else ""
    except (OSError, subprocess.SubprocessError):
        commit = "unknown"
    import matplotlib
    import numpy
    import scipy

    return {"cpu": f"{cpu}, {os.cpu_count()} cores", "os": platform.platform(),
            "python": platform.python_version(), "numpy": numpy.__version__, "scipy": scipy.__version__,
            "matplotlib": matplotlib.__version__, "commit": commit}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=11, help="simulator seed of every capture")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    parser.add_argument("--out", type=Path, default=REPO / "docs", help="folder of validation.md")
    parser.add_argument("--workdir", type=Path, default=None, help="keep captures here instead of a temp dir")
    args = parser.parse_args()
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        print("bench/validate.py needs matplotlib: pip install 'millsense[plot]'", file=sys.stderr)
        return 1
    import validate_report

    start = time.perf_counter()
    started = datetime.now(timezone.utc)
    command = shlex.join([Path(sys.executable).name, os.path.relpath(__file__, REPO), *sys.argv[1:]])
    with tempfile.TemporaryDirectory(prefix="millsense-validate-") as tmp:
        workdir = args.workdir or Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        run = run_all(args.seed, args.jobs, workdir)
        for name, (n, s) in run["timings"].items():
            print(f"{name}: {n} in {s:.1f} s", file=sys.stderr)
        meta = {"command": command, "date": started.strftime("%Y-%m-%d %H:%M UTC"), "seed": args.seed,
                "jobs": args.jobs, **machine_info()}
        elapsed = validate_report.write(run, args.out, meta, start)
    print(f"wrote {args.out / 'validation.md'} and {args.out / 'validation'}/*.png; elapsed {elapsed:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
