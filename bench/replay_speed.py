"""Replay speed, whole process: × real time of a 300 s and a 3000 s `step` capture, the
start-up share, the bare imports, and the RSS of the live pipeline.

Budgets (issue 13): a 300 s capture >= 500 × real time, whole process; >= 2000 × with
start-up taken out (the 2700 s between the two captures over the difference of their
wall times). Baselines measured in the same run: `python -c pass` and the bare imports
of `replay` (start-up that no change in the pipeline can remove). Also: `-X importtime`
total of `millsense.daemon.commands.run` and VmRSS/VmHWM after building the live
pipeline (config, PipelineCore, one block), with and without `scipy.optimize` loaded.
Beside the wall times: the replays' CPU time (user + system), which load on a shared
box inflates less than the wall clock.

    .venv/bin/python bench/replay_speed.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "daemon" / "demo.toml"
BUDGET_WHOLE = 500.0
BUDGET_MARGINAL = 2000.0

LIVE_PIPELINE = """
import sys
{pre}
import numpy as np
import millsense.daemon.commands.run
from millsense.daemon.config.load import demo_config
from millsense.daemon.pipeline.run_core import PipelineCore
from millsense.drivers.base import SampleBlock
from millsense.drivers.protocol import Channel, ChannelKind as K, Descriptor
kinds = [K.VOLTAGE] * 3 + [K.CURRENT] * 3 + [K.SPEED, K.ENCODER]
names = ["v_uv", "v_vw", "v_wu", "i_u", "i_v", "i_w", "sp_rpm", "sp_enc"]
core = PipelineCore(demo_config())
core.on_descriptor(Descriptor(1000, tuple(map(Channel, kinds, names))))
core.process(SampleBlock(0, 0, np.ones((1000, 8), np.int16), 0, False))
status = open("/proc/self/status").read()
print(*(re.search(k + r":\\s+(\\d+)", status).group(1) for k in ("VmRSS", "VmHWM")),
      sum(m.startswith("scipy") for m in sys.modules))
"""


CPU: dict[tuple[str, ...], float] = {}   # best child CPU seconds (user + system) of each command timed


def wall(cmd: list[str], repeat: int) -> float:
    """Best wall time of `cmd`; its best CPU time goes to CPU (what a loaded box inflates less)."""
    best = best_cpu = float("inf")
    for _ in range(repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        best = min(best, time.perf_counter() - t0)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        best_cpu = min(best_cpu, after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
    CPU[tuple(cmd)] = best_cpu
    return best


def capture(seconds: int, path: Path) -> None:
    subprocess.run([sys.executable, "-m", "millsense.daemon", "sim", "--scenario", "step", "--loop",
                    "--duration-s", str(seconds), "--capture", str(path), "--fast"], check=True, capture_output=True)


def import_time_ms(module: str) -> float:
    err = subprocess.run([sys.executable, "-X", "importtime", "-c", f"import {module}"],
                         capture_output=True, text=True, check=True).stderr
    total = 0
    for line in err.splitlines():   # top-level entries only: their cumulative time covers the rest
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \| (\S.*)$", line)
        if m and not m.group(2).startswith(" "):
            total += int(m.group(1))
    return total / 1000.0


def live_rss(pre: str) -> tuple[float, float, int]:
    code = "import re\n" + LIVE_PIPELINE.format(pre=pre)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    return int(out[0]) / 1024, int(out[1]) / 1024, int(out[2])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    py = sys.executable
    with tempfile.TemporaryDirectory() as tmp:
        short, long = Path(tmp) / "c300.cap", Path(tmp) / "c3000.cap"
        capture(300, short)
        capture(3000, long)
        replay = [py, "-m", "millsense.daemon", "replay", "-c", str(CONFIG)]
        t_pass = wall([py, "-c", "pass"], args.repeat)
        t_imports = wall([py, "-c", "import millsense.daemon.commands.replay, millsense.daemon.config, "
                                    "millsense.daemon.pipeline.run_core, millsense.daemon.pipeline.estimator"],
                         args.repeat)
        t_short = wall(replay + [str(short)], args.repeat)
        t_long = wall(replay + [str(long)], args.repeat)
    cpu_short, cpu_long = CPU[tuple(replay + [str(short)])], CPU[tuple(replay + [str(long)])]
    marginal = (3000 - 300) / (t_long - t_short)
    whole = 300 / t_short
    startup = t_short - 300 / marginal
    print(f"replay of the step scenario, whole process, best of {args.repeat}:")
    print(f"  300 s capture   {t_short:6.2f} s   {whole:7.0f} x real time   budget >= {BUDGET_WHOLE:.0f}: "
          f"{'met' if whole >= BUDGET_WHOLE else 'MISSED'}")
    print(f"  3000 s capture  {t_long:6.2f} s   {3000 / t_long:7.0f} x real time")
    print(f"  start-up out    {marginal:7.0f} x real time (2700 s / {t_long - t_short:.2f} s)   budget >= "
          f"{BUDGET_MARGINAL:.0f}: {'met' if marginal >= BUDGET_MARGINAL else 'MISSED'}")
    print(f"  CPU time (user + system, best of {args.repeat}; a loaded box inflates it less than the wall): "
          f"300 s {cpu_short:.2f} s, 3000 s {cpu_long:.2f} s, start-up out {2700 / (cpu_long - cpu_short):.0f} x")
    print(f"  start-up share of the 300 s run: {startup:.2f} s ({startup / t_short:.0%}); baselines in this run: "
          f"python -c pass {t_pass:.2f} s, bare imports of replay {t_imports:.2f} s")
    print(f"  -X importtime total of millsense.daemon.commands.run: {import_time_ms('millsense.daemon.commands.run'):.0f} ms")
    rss, hwm, n_scipy = live_rss("")
    rss_opt, hwm_opt, _ = live_rss("import scipy.optimize")
    print(f"  live pipeline built: VmRSS {rss:.1f} MB, VmHWM {hwm:.1f} MB, scipy modules loaded: {n_scipy}; "
          f"with scipy.optimize imported as before: VmRSS {rss_opt:.1f} MB, VmHWM {hwm_opt:.1f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
