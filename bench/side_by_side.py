"""Two live daemons side by side: this checkout's code and a git revision's, on one emulator, in the same minutes.

The box's speed drifts (the bare `recv` loop measured 0.25 % of a core one
session and 0.45 % the next), so a change to the live path is judged against
the code before it run at the same moments, not against figures from another
day. Both daemons read the same `millsense sim --tcp --realtime` stream (the
`step` scenario, 1 kHz, 10-sample frames) with the environment their systemd
unit gives them; the base revision's `daemon/` and `drivers/` are exported with
`git archive` and put first on its daemon's `PYTHONPATH` (it uses this venv's
libraries). A bare blocking `recv` loop on the same stream is the baseline.

Per run and daemon: CPU in % of one core (user + system from /proc over the
window), the reader's and the estimator's threads, the per-revolution latency
(status `latency_ms`: the closing frame taken by the estimator → its estimate
handed to the sink) and lost samples.

Run: .venv/bin/python bench/side_by_side.py [--base HEAD] [--seconds 60] [--runs 3] [--scenario step]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.against_base import PACKAGES, package_dir  # noqa: E402
from bench.against_base import loaded_from as where_imported  # noqa: E402
from bench.daemon_budget import _BARE_RECV, thread_cpu  # noqa: E402
from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import CMD, Procs, Subscriber, tcp, wait_for, write_config  # noqa: E402
from tests.ops.unit_file import unit_environment  # noqa: E402
from tests.procstat import proc_cpu_s  # noqa: E402


def export_base(rev: str, into: Path) -> Path:
    """The packages of `rev` (`daemon/`, `drivers/`, and `sim/` where it has one), laid out as the package
    `millsense` (against_base.package_dir); returns the directory to put on PYTHONPATH."""
    tree = into / "tree"
    tree.mkdir()
    listed = subprocess.run(["git", "-C", str(REPO), "ls-tree", "--name-only", rev], check=True,
                            capture_output=True, text=True).stdout.split()
    archive = subprocess.run(["git", "-C", str(REPO), "archive", "--format=tar", rev,
                              *[p for p in PACKAGES if p in listed]], check=True, capture_output=True).stdout
    tar_path = into / "base.tar"
    tar_path.write_bytes(archive)
    with tarfile.open(tar_path) as tar:
        tar.extractall(tree, filter="data")
    return package_dir(tree, into)


def loaded_from(pythonpath: str | None) -> str:
    """Where `millsense.daemon` is imported from under that PYTHONPATH (the check that the base is the base)."""
    return where_imported({**os.environ, "PYTHONPATH": pythonpath} if pythonpath is not None else dict(os.environ))


def one_run(pkg: Path, seconds: float, scenario: str) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="millsense-side-"))
    daq_port = free_tcp_port()
    with Procs(tmp) as procs:
        procs.start("sim", ["sim", "--scenario", scenario, "--loop", "--tcp", f"127.0.0.1:{daq_port}", "--realtime"])
        time.sleep(0.5)
        daemons, subs = {}, {}
        for name in ("base", "this"):
            z_port = free_tcp_port()
            cfg = write_config(tmp / f"{name}.toml", machine=name,
                               daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
                               zenoh_listen=[tcp(z_port)], extra="")
            env = {**unit_environment(), "XDG_STATE_HOME": str(tmp / f"state-{name}")}
            if name == "base":
                env["PYTHONPATH"] = str(pkg)
            daemons[name] = procs.start(name, ["run", "--config", str(cfg)], env_extra=env)
            subs[name] = Subscriber([tcp(z_port)], name)
        bare = subprocess.Popen([sys.executable, "-c", _BARE_RECV, str(daq_port)])
        try:
            for name in daemons:
                wait_for(lambda name=name: len(subs[name].get("estimate")) >= 5, 30.0, f"estimates from {name}")
            time.sleep(3.0)  # warm-up
            threads0 = {n: thread_cpu(d.pid) for n, d in daemons.items()}
            cpu0 = {n: proc_cpu_s(d.pid) for n, d in daemons.items()}
            bare0, t0 = proc_cpu_s(bare.pid), time.monotonic()
            time.sleep(seconds)
            threads1 = {n: thread_cpu(d.pid) for n, d in daemons.items()}
            cpu1 = {n: proc_cpu_s(d.pid) for n, d in daemons.items()}
            bare1, t1 = proc_cpu_s(bare.pid), time.monotonic()
            out = {"window_s": t1 - t0, "bare_pct": 100.0 * (bare1 - bare0) / (t1 - t0)}
            for name in daemons:
                status = subs[name].query(f"millsense/{name}/status")[0]

                def thread_pct(prefix: str, name: str = name) -> float:
                    return sum(100.0 * (cpu - threads0[name].get(t, (0.0, 0))[0]) / (t1 - t0)
                               for t, (cpu, _) in threads1[name].items() if t.startswith(prefix))

                out[name] = {"cpu_pct": 100.0 * (cpu1[name] - cpu0[name]) / (t1 - t0),
                             "reader_pct": thread_pct("ms-daq"), "estimator_pct": thread_pct("ms-estimator"),
                             "latency": status.get("latency_ms", {}), "lost": status.get("lost_samples")}
        finally:
            for sub in subs.values():
                sub.close()
            bare.kill()
            bare.wait(5)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--base", default="HEAD", help="the git revision to compare with (default HEAD: the last commit)")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--scenario", default="step")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="millsense-base-") as d:
        pkg = export_base(args.base, Path(d))
        base_from, this_from = loaded_from(str(pkg)), loaded_from(None)
        if not base_from.startswith(str(pkg)) or this_from.startswith(str(pkg)):
            print(f"the base's daemon would not run its own code: {base_from} / {this_from}", file=sys.stderr)
            return 1
        print(f"side by side, {args.runs} run(s) of {args.seconds:.0f} s, scenario {args.scenario}, 1 kHz real time:"
              f" base {args.base} against this checkout")
        print("run | bare recv | CPU base → this | reader | estimator | per-rev p50 | per-rev p99 | lost")
        for k in range(1, args.runs + 1):
            r = one_run(pkg, args.seconds, args.scenario)
            b, t = r["base"], r["this"]
            print(f"{k:3d} | {r['bare_pct']:.2f} % | {b['cpu_pct']:.2f} → {t['cpu_pct']:.2f} % | "
                  f"{b['reader_pct']:.2f} → {t['reader_pct']:.2f} % | {b['estimator_pct']:.2f} → {t['estimator_pct']:.2f} % | "
                  f"{b['latency'].get('p50')} → {t['latency'].get('p50')} ms | "
                  f"{b['latency'].get('p99')} → {t['latency'].get('p99')} ms | {b['lost']} / {t['lost']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
