"""Issue 15's closed loop through real processes: the emulator's plant and CNC, the daemon's controller.

`millsense sim` plays a scenario in real time over TCP (protocol 2: the CNC
follows the feed override through its own lag and rate limit, and the plant's
feed follows the CNC); `millsense run` estimates each revolution and, with
`[afc] enabled = true`, commands the override. The subscriber keeps every
estimate the daemon published; the plant's truth says where each depth step
really lies. `step_outcomes()` reads one run against its steps: how many
revolutions after the first revolution past each step the torque stays within
±5 % of the target, the overshoot from that revolution on, and the spread at
the end of each level; on the daemon's estimates (what the controller sees) or,
`truth=True`, on the plant's own revolutions (the cut's true load, what it
holds). Shared by the test (tests/e2e/test_afc_closed_loop.py) and the report
(bench/validate_afc.py).

Estimates and truth are paired by time: the emulator's status log has the
wall time of its first sample (`start`), the truth the plant time of each
revolution's end, and an estimate's `t` is the wall time of its last sample.

`speed` plays the plant and the CNC faster than real time (`millsense sim
--speed K`): K plant seconds a wall second, every lag of the plant and the CNC
on the samples' clock. A wall interval is then K times as long in plant time
(`Loop.plant_time`), the daemon's own reaction included (a command's few wall
ms are K times as many samples), and the daemon runs with `[daq]
check_sample_rate = false` (the samples arrive K times faster than the
descriptor's rate says, on purpose). Speed 1 (the default) is real time with
the check on, as a machine runs.
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from tests import captures
from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, Subscriber, read_jsonl, tcp, wait_for, write_config

SETTLE_BAND = 0.05        # the issue's ±5 % of the target
OVERSHOOT_MAX = 0.15      # the 15 %
# Plant seconds a wall second where pacing is not what a test checks (`run_loop(speed=SPEED)`; docs/testing.md,
# "The AFC loop at speed"): the fastest at which every assertion held with margin, run after run, on the loaded
# 2-core box
SPEED = 2.0
CNC_LAG_MS = 40.0         # the emulator's override response (its default), which the acceptance scales with
# The example configs' breakage check (config/mch10-spindle-power.toml: a 2-flute cutter loses ~25 % with a flute):
# armed in every closed-loop run, so that a feed that moves must not look like a broken tool
ALARMS = "breakage_drop_pct = 20"


@dataclass
class Loop:
    scenario: str
    estimates: list[dict]        # as the daemon published them
    truth: list[dict]            # the plant's revolutions ({"rev": ...} records)
    log: list[dict]              # the emulator's status log
    start_wall: float            # wall time of the emulator's first sample
    daemon_log: str
    alarms: list[dict] = field(default_factory=list)  # as the daemon published them
    events: list[dict] = field(default_factory=list)  # the plant's truth events (tool_breakage, feed_hold, ...)
    speed: float = 1.0           # plant seconds a wall second, as the emulator's `start` event says

    def plant_time(self, est: dict) -> float:
        """Plant time of an estimate's revolution's end. The emulator makes its first sample when the daemon
        connects (--start-on-connect), so the daemon counts the plant's revolutions from the same first one: its
        `rev` is the truth's. Its `t` (the wall time of the revolution's last sample) is the fallback: on a
        loaded host the daemon's sample clock puts a revolution handled behind a backlog early by the backlog ×
        (1 − 1/speed) (it counts samples at the descriptor's rate): at speed 3 that was up to 12 revolutions."""
        t = self._rev_t().get(est.get("rev"))
        return t if t is not None else self.wall_to_plant(float(est["t"]))

    def _rev_t(self) -> dict:
        if getattr(self, "_rev_t_cache", None) is None:
            self._rev_t_cache = {int(r["rev"]): float(r["t_end_s"]) for r in self.truth}
        return self._rev_t_cache

    def wall_to_plant(self, wall_s: float) -> float:
        """Plant time of a wall time (an estimate's or an alarm's `t`): the wall seconds since the first
        sample, `speed` plant seconds each."""
        return (wall_s - self.start_wall) * self.speed

    def mono_of_plant(self, plant_s: float) -> float:
        """The emulator's monotonic time (its status log's `mono`) when the plant was at `plant_s`."""
        start = next(e["mono"] for e in self.log if e.get("event") == "start")
        return start + plant_s / self.speed

    def cutting(self) -> list[dict]:
        return [e for e in self.estimates if e.get("valid", True) and e.get("cutting")]


def daemon_config(path: Path, *, machine: str, daq_port: int, z_port: int, feed_mm_min: float,
                  afc: dict | None, check_sample_rate: bool = True) -> Path:
    """The simulated machine's config with `[afc]` (None: no [afc] section, the controller off);
    `check_sample_rate` false only for a stream played faster than real time (`run_loop(speed=...)`)."""
    extra = f"\n[cut]\nmode = \"slot\"\nfeed_mm_min = {feed_mm_min}\n"
    if afc is not None:
        extra += "\n[afc]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in afc.items())
    daq = f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}'
    if not check_sample_rate:
        daq += "\ncheck_sample_rate = false"
    return write_config(path, machine=machine, daq=daq,
                        zenoh_listen=[tcp(z_port)], interlock="enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000",
                        alarms=ALARMS, extra=extra)


def run_loop(tmp: Path, scenario: str, *, feed_mm_min: float, afc: dict | None, sim_args: tuple[str, ...] = (),
             timeout_s: float = 180.0, speed: float = 1.0) -> Loop:
    """One pass of `scenario` with the daemon closing the loop; returns what both sides saw. `speed`: plant
    seconds a wall second (1: real time; above it, the daemon's sample-rate check is off for this stream)."""
    tmp.mkdir(parents=True, exist_ok=True)
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    machine = f"afc-{scenario}".replace(".", "-")
    cfg = daemon_config(tmp / "daemon.toml", machine=machine, daq_port=daq_port, z_port=z_port,
                        feed_mm_min=feed_mm_min, afc=afc, check_sample_rate=speed == 1.0)
    pace = ("--realtime",) if speed == 1.0 else ("--realtime", "--speed", repr(speed))
    status_log, truth = tmp / "status.jsonl", tmp / "truth.jsonl"
    for old in (status_log, truth):  # the emulator appends to its status log
        old.unlink(missing_ok=True)
    with Procs(tmp) as procs:
        # the daemon first: it waits for the DAQ; the emulator makes its first sample when the daemon connects
        # (--start-on-connect), so a daemon that starts slowly on a loaded host still sees the plant from its start
        daemon = procs.start("daemon", ["run", "--config", str(cfg), "--connect-timeout", "120"])
        sub = Subscriber([tcp(z_port)], machine)
        try:
            sim = procs.start("sim", ["sim", "--scenario", scenario, "--protocol", "2", "--tcp",
                                      f"127.0.0.1:{daq_port}", *pace, "--start-on-connect", "--once",
                                      "--watchdog-ms", "1000",
                                      "--status-log", str(status_log), "--truth", str(truth), *sim_args])
            try:
                sim.wait(timeout_s)
            except subprocess.TimeoutExpired:
                raise AssertionError(f"{scenario}: the emulator did not finish in {timeout_s} s") from None
            assert sim.returncode == 0, procs.text("sim")
            wait_for(lambda: truth.exists(), 10.0, "the plant's truth file")
        finally:
            sub.close()
            if daemon.poll() is None:
                daemon.send_signal(signal.SIGTERM)
                try:
                    daemon.wait(30)
                except subprocess.TimeoutExpired:
                    pass
        log = read_jsonl(status_log)
        start = next((e for e in log if e.get("event") == "start"), None)
        assert start is not None, "the emulator's status log has no start event"
        return Loop(scenario, sub.get("estimate"), [r for r in read_jsonl(truth) if "rev" in r], log,
                    float(start["wall"]), procs.text("daemon"), sub.get("alarm"),
                    [r for r in read_jsonl(truth) if "event" in r], float(start.get("speed", 1.0)))


# ----------------------------------------------------------------------------- reading a run
@dataclass
class StepOutcome:
    level_mm: float              # the depth beyond the step
    first_rev_t: float           # plant time the first revolution after the step ends
    revolutions: int             # estimates from that revolution until the next step (or the exit) reaches the tool
    settle_revs: int | None      # revolutions after the first until the load stays within the band
    allowed_revs: int            # max(5, 3 × the CNC lag in revolutions)
    overshoot: float             # beyond the target, on the side opposite the first error, / target
    final_spread: float          # max |load/target − 1| over the level's last half
    override_pct: tuple[float, float]  # the commanded override's range over the level's last half (truth: applied)


def walls(scenario: str) -> tuple[list[tuple[float, float]], float, float, float]:
    """The scenario's depth steps as (x of the wall, depth beyond it), the part's end, the tool's radius, and
    where the tool's centre starts (the plant's own geometry, sim/scenarios.py)."""
    from millsense.sim.scenarios import get_scenario

    sc = get_scenario(scenario)
    pts = list(sc.axial_profile)
    steps = [(x1, d1) for (x0, d0), (x1, d1) in zip(pts, pts[1:]) if d1 != d0 and x1 - x0 < 1.0]
    return steps, pts[-1][0], sc.tool.radius_mm, sc.start_mm


def leading_edge(loop: Loop) -> list[tuple[float, float, float]]:
    """(plant time the revolution ends, leading edge at its start, at its end) per truth revolution, from the
    plant's own feed integrated from where the scenario starts the tool."""
    _, _, radius, start = walls(loop.scenario)
    out, s, t_prev = [], start, 0.0
    for r in loop.truth:
        t = float(r["t_end_s"])
        s_end = s + float(r.get("feed_mm_min") or 0.0) / 60.0 * (t - t_prev)
        out.append((t, s + radius, s_end + radius))
        s, t_prev = s_end, t
    return out


def truth_rows(loop: Loop) -> list[dict]:
    """The plant's own cutting revolutions in the estimates' keys: the cut's true torque and force, `t_plant` the
    plant time of the revolution's end, and the override the CNC applied over it as `afc.override_pct`."""
    return [{"t_plant": float(r["t_end_s"]), "torque_nm": float(r["torque_nm"]), "force_n": float(r["force_n"]),
             "spindle_rpm": float(r["spindle_rpm"]), "afc": {"override_pct": float(r["feed_override_pct"])}}
            for r in loop.truth if r.get("cutting")]


def levels(loop: Loop, truth: bool = False) -> list[tuple[float, float, float, list[dict]]]:
    """Each depth step as the tool meets it: (x of the wall, depth beyond it, plant time of the first revolution
    after it, the estimates of its level; with `truth`, the plant's own revolutions, `truth_rows`). The leading
    edge reaching the wall is the step: the load changes from there (a slot's edges near the leading side take
    most of the chip). The first revolution after the step is the first that starts with the leading edge past
    the wall; the level lasts until the next wall (or the part's end) reaches the leading edge."""
    steps, part_end, _, _ = walls(loop.scenario)
    edge = leading_edge(loop)
    bounds = [w for w, _ in steps] + [part_end]
    if truth:
        rows, time_of = truth_rows(loop), (lambda r: r["t_plant"])
    else:
        rows, time_of = sorted(loop.cutting(), key=lambda e: e["t"]), loop.plant_time
    out = []
    for (wall, depth), until in zip(steps, bounds[1:]):
        first = next((t for t, lead0, _ in edge if lead0 >= wall), None)
        last = next((t for t, lead0, lead1 in edge if lead1 >= until), None)
        if first is None or last is None:
            continue
        seg = [e for e in rows if first - 0.5 * _rev_s(e) <= time_of(e) <= last - 0.5 * _rev_s(e)]
        out.append((wall, depth, first, seg))
    return out


def step_outcomes(loop: Loop, target: float, quantity: str = "torque_nm", truth: bool = False) -> list[StepOutcome]:
    """Each level of `levels()` against the target: settle, overshoot, the spread at its end. With `truth`, of
    the cut's true load (the plant's revolutions): what the controller holds, where the estimates are what it
    sees (they lag the cut by about a revolution where the load steps: the spindle drive's speed loop)."""
    outcomes = []
    for wall, depth, first, seg in levels(loop, truth):
        if len(seg) < 3:
            continue
        allowed = max(5, math.ceil(3 * CNC_LAG_MS / 1000.0 / _rev_s(seg[0])))
        ratio = [float(e[quantity]) / target - 1.0 for e in seg]
        settle = next((k for k in range(len(ratio)) if all(abs(x) <= SETTLE_BAND for x in ratio[k:])), None)
        # an overshoot lies beyond the target on the side opposite the step's own push: below it after a step
        # into a deeper cut (the load jumps up), above it after a step to a shallower one
        deeper = depth > depth_before(loop.scenario, wall)
        overshoot = max([0.0, *((-x if deeper else x) for x in ratio)])
        half = ratio[len(ratio) // 2:]
        ovr = [float(e["afc"]["override_pct"]) for e in seg[len(seg) // 2:] if e.get("afc")]
        outcomes.append(StepOutcome(depth, first, len(seg), settle, allowed, overshoot, max(abs(x) for x in half),
                                    (min(ovr, default=math.nan), max(ovr, default=math.nan))))
    return outcomes


def level_ratios(loop: Loop, target: float, quantity: str = "torque_nm") -> list[tuple[float, list[float]]]:
    """Each level of `levels()` as (depth beyond the step, load / target − 1 of each estimate): for a run at the
    programmed feed, how far the cut alone stays from the target."""
    return [(depth, [float(e[quantity]) / target - 1.0 for e in seg]) for _, depth, _, seg in levels(loop)]


def depth_before(scenario: str, wall: float) -> float:
    """The scenario's programmed depth just before `wall`."""
    from millsense.sim.scenarios import get_scenario

    return [d for x, d in get_scenario(scenario).axial_profile if x < wall][-1]


def _rev_s(est: dict) -> float:
    rpm = float(est.get("spindle_rpm") or 0.0)
    return 60.0 / rpm if rpm > 0 else 0.1


def cycle_s(loop: Loop) -> float:
    """The cut's length in plant time: first to last truth revolution that cut."""
    cut = [float(r["t_end_s"]) for r in loop.truth if r.get("cutting")]
    return cut[-1] - cut[0] if cut else math.nan


def peak(loop: Loop, quantity: str = "torque_nm", top: int = 5) -> float:
    """The mean of the `top` largest values of the daemon's estimates (one revolution's noise is not the peak)."""
    values = sorted(float(e[quantity]) for e in loop.cutting() if e.get(quantity) is not None)
    return sum(values[-top:]) / len(values[-top:]) if values else math.nan


def torque_at_depth(scenario: str, depth_mm: float, feed_mm_min: float, tmp: Path | None = None) -> float:
    """The daemon's torque at `depth_mm` with the programmed feed, from a fast capture replayed offline."""
    tmp = Path(tempfile.mkdtemp()) if tmp is None else tmp

    def build(d: Path) -> None:
        cap, truth = d / "prog.bin", d / "prog-truth.jsonl"
        captures.sim("--scenario", scenario, "--capture", cap, "--truth", truth, "--fast")
        cfg = daemon_config(tmp / "replay.toml", machine="afc-ref", daq_port=1, z_port=free_tcp_port(),
                            feed_mm_min=feed_mm_min, afc=None)
        out = subprocess.run(CMD + ["replay", str(cap), "--config", str(cfg)], capture_output=True, text=True,
                             timeout=300, check=True)
        (d / "replay.jsonl").write_text(out.stdout)

    # the capture and its replay depend on the scenario and the feed alone: made once per test run and shared
    # by the tests that ask for a level of the same scenario (tests/captures.py)
    d = captures.shared(f"torque_at_depth {scenario} feed_mm_min={feed_mm_min!r}", build)
    truth = d / "prog-truth.jsonl"
    est = [json.loads(line) for line in (d / "replay.jsonl").read_text().splitlines() if line.startswith("{")]
    est = [e for e in est if e.get("type") == "estimate" and e.get("cutting") and e.get("valid", True)]
    # the revolutions with the whole tool inside the level: its centre past the wall before it, and its leading
    # edge not yet at the next one
    steps, part_end, radius, start = walls(scenario)
    bounds = [0.0] + [w for w, _ in steps] + [part_end]
    depths = [d for _, d in steps]
    k = next(k for k, d in enumerate([None, *depths]) if d is not None and abs(d - depth_mm) < 1e-6)
    x0, x1 = bounds[k] + radius, bounds[k + 1]
    probe = Loop(scenario, [], [r for r in read_jsonl(truth) if "rev" in r], [], 0.0, "")
    times = [t for t, lead0, lead1 in leading_edge(probe) if lead0 - radius >= bounds[k] + 1.0 and lead1 < x1]
    assert times and x0 < x1, f"{scenario} has no flat level at {depth_mm} mm"
    t0, t1 = times[0], times[-1]
    # replay's `t` is the revolution's last sample over the sample rate: plant time, as the truth's
    values = [float(e["torque_nm"]) for e in est if e.get("t") is not None and t0 <= float(e["t"]) <= t1 + 1e-3]
    assert len(values) >= 5, f"too few revolutions at {depth_mm} mm in {scenario}"
    values.sort()
    return values[len(values) // 2]


def main() -> int:  # a quick look by hand: python -m tests.e2e.afc_run SCENARIO FEED TARGET
    scenario, feed, target = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])
    loop = run_loop(Path(tempfile.mkdtemp()), scenario, feed_mm_min=feed,
                    afc={"enabled": True, "allow": True, "target_torque_nm": target})
    for o in step_outcomes(loop, target):
        print(o)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
