"""Issue 41's acceptance live: a first-part program (sim/first_part.py) through `millsense sim` and `millsense run`.

The emulator plays one first-part program over TCP (protocol 2: the CNC's context and applied override in its
frames), holding its first sample until the daemon connects (`--start-on-connect`), so the daemon sees every
operation whole; `--truth` writes the plant's per-revolution truth. The daemon's `[operations]` are the
program's *programmed* cuts (`operations_config`); what the plant really cuts differs only by what the run
asks (`--material-offset-pct`, `--axial-scale`, `--radial-scale`). `speed` > 1 plays the stream faster than
real time (`--speed`; the daemon then runs with `[daq] check_sample_rate = false`, the setting for a part
played at speed on a test bench — the rate check of a real DAQ is not touched): for the runs where pacing is
not under test (no alarm expected, the force against the truth). The trip runs go at 1×.

Shared by tests/e2e/test_first_part_acceptance.py and bench/first_part_live.py (the whole sweep).
"""

from __future__ import annotations

import signal
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from millsense.daemon.physics.materials import STEEL_EDGE_N_MM
from millsense.sim.config_view import machine_config
from millsense.sim.first_part import FIRST_PART_PROGRAMS, operations_config
from tests.conftest import free_tcp_port
from tests.config.helpers import dumps
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for
from tests.e2e.learning_run import CONFIG
from tests.e2e.truth import Timebase, match_estimates, truth_revs

SLOW_S = 180.0   # detects a hang; no budget
MIN_TORQUE_NM = tomllib.loads(CONFIG.read_text())["depth"]["min_torque_nm"]   # the runs' "cutting" threshold


def daemon_config(path: Path, program: str, *, daq_port: int, z_port: int, machine: str, at_speed: bool) -> Path:
    """The daemon for a first-part program: config/part-program.toml's machine and sensors, the program's
    magazine as `[tools.N]` (C_f "auto", the default), its `[operations]` as programmed, nothing learned; the
    material's edge coefficients of the round steel pair (unverified, physics.md §5b)."""
    prog = FIRST_PART_PROGRAMS[program]
    view = machine_config(prog)
    doc = tomllib.loads(CONFIG.read_text())
    doc["machine"] = machine
    doc["daq"].update(host="127.0.0.1", tcp_port=daq_port)
    if at_speed:
        doc["daq"]["check_sample_rate"] = False
    doc["tool"].pop("cf", None)   # "auto": the engaged teeth's C_f (docs/config.md)
    # the steel's round edge pair (physics/materials.py STEEL_EDGE_N_MM, unverified; not the plant's
    # own 20 / 30 N/mm): the φ8 3-flute slots' force within 2 % (docs/accuracy.md: 2.2-2.4 % high without)
    doc["material"]["edge_t_n_mm"], doc["material"]["edge_r_n_mm"] = STEEL_EDGE_N_MM
    doc["tools"] = {str(n): t for n, t in view["tools"].items()}
    doc["cut"] = {"mode": view["cut"]["mode"]}
    doc["operations"] = operations_config(prog)
    doc["learning"] = {"processes": 5}   # physics_tolerance_pct: the default
    doc["interlock"] = {"enabled": True, "heartbeat_ms": 50, "watchdog_ms": 1000, "reset": "open"}
    doc["zenoh"] = {"mode": "peer", "listen": [tcp(z_port)], "connect": [], "multicast_scouting": False}
    doc["log"] = {"level": "info", "format": "json"}
    path.write_text(dumps(doc))
    return path


@dataclass
class Run:
    program: str
    truth: list[dict]
    estimates: list[dict]
    alarms: list[dict]
    processes: list[dict]
    status_log: list[dict]
    speed: float
    feed_held: bool = False
    sim_args: list[str] = field(default_factory=list)

    @property
    def truth_processes(self) -> list[dict]:
        return [t for t in self.truth if "process" in t and "first_index" in t]

    def expected_alarms(self) -> list[dict]:
        return [a for a in self.alarms if str(a.get("level", "")).startswith("expected")]


def play(tmp_path: Path, program: str, *, name: str, speed: float = 1.0, sim_args: tuple[str, ...] = (),
         until_alarm: str | None = None) -> Run:
    """One first part through emulator and daemon. Without `until_alarm` the whole program is played and every
    process summary awaited; with it, the run ends once that alarm has held the emulated DAQ's feed."""
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = daemon_config(tmp_path / f"{name}.toml", program, daq_port=daq_port, z_port=z_port, machine=name,
                        at_speed=speed != 1.0)
    log_path, truth_path = tmp_path / f"{name}-status.jsonl", tmp_path / f"{name}-truth.jsonl"
    operations = len(operations_config(program)) if "--only-operation" not in sim_args else \
        sum(a == "--only-operation" for a in sim_args)
    args = ["sim", "--scenario", program, "--tcp", f"127.0.0.1:{daq_port}", "--realtime", "--once", "--start-on-connect",
            "--speed", f"{speed:g}", "--watchdog-ms", "1000", "--status-log", str(log_path), "--truth",
            str(truth_path), *sim_args]
    with Procs(tmp_path) as procs:
        # the daemon first, the subscriber on it (its `alive` token seen), then the emulator, which holds the first
        # sample until the daemon's driver reaches it: the subscriber misses no estimate of the first operation
        env = {"STATE_DIRECTORY": str(tmp_path / f"{name}-state")}
        daemon = procs.start(name, ["run", "--config", str(cfg), "--connect-timeout", "120"], env_extra=env)
        sub = Subscriber([tcp(z_port)], name)
        wait_for(lambda: sub.alive or daemon.poll() is not None, 60.0, "the daemon's alive token")
        assert daemon.poll() is None, procs.text(name)[-3000:]
        sim = procs.start(f"sim-{name}", args)
        held = False
        try:
            if until_alarm is None:
                # (a held feed ends nothing: stop waiting at a hold, which the caller's checks then show)
                wait_for(lambda: len(sub.get("process")) >= operations or daemon.poll() is not None
                         or [a for a in sub.get("alarm") if a.get("interlock")], SLOW_S,
                         f"{operations} process summaries")
                assert daemon.poll() is None, procs.text(name)[-3000:]
            else:
                # (or the part played out, its every process summarised, without it)
                over = wait_for(lambda: [a for a in sub.get("alarm") if a["level"] == until_alarm] or (
                    sim.poll() is not None and len(sub.get("process")) >= operations and "over"), SLOW_S, until_alarm)
                if over == "over":
                    raise AssertionError(f"no {until_alarm}: alarms {sub.get('alarm')}; processes {sub.get('process')}")
                held = bool(wait_for(lambda: [e for e in read_jsonl(log_path)
                                              if e.get("event") == "outputs" and e.get("feed_hold")], 30.0,
                                     "the emulated DAQ's feed-hold output"))
        finally:
            estimates, alarms, processes = sub.get("estimate"), sub.get("alarm"), sub.get("process")
            sub.close()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
            sim.send_signal(signal.SIGTERM)   # a held feed never ends the part: stop it (the truth is written)
            sim.wait(60)
        truth = read_jsonl(truth_path)
    return Run(program, truth, estimates, alarms, processes, read_jsonl(log_path), speed, held, list(args))


def steady_revolution_of_alarm(run: Run, alarm: dict) -> int:
    """Which steady revolution of its cut (the truth's `steady`: docs/validation.md) the alarm came on: 1 for the
    first. Daemon revolutions are paired with the truth's by time (a 1× run: tests/e2e/truth.py); the alarm's
    revolution must be steady cutting in the truth."""
    assert run.speed == 1.0, "time pairing needs the real-time stream"
    tb = Timebase.from_status_log(run.status_log)
    matched = match_estimates(run.estimates, run.truth, tb)
    assert matched, "no estimate paired with the truth"
    # one revolution offset for the whole run (truth.py): the alarm's revolution is found through it, not through its
    # own estimate, which a subscriber on a loaded box may not have received (estimates go out DROP under congestion)
    offset = {int(e["rev"]) - int(r["rev"]) for e, r, _ in matched}
    assert len(offset) == 1, offset
    revs = {int(r["rev"]): r for r in truth_revs(run.truth)}
    at = revs[int(alarm["rev"]) - offset.pop()]
    assert at["steady"] and at["cutting"], at
    # the cut holding it: the truth's cutting revolutions in a row up to it (a held part's process never ends, so
    # the truth has no process line for it)
    k, count = int(at["rev"]), 0
    while k in revs and revs[k]["cutting"]:
        count += bool(revs[k]["steady"])
        k -= 1
    return count


def force_by_operation(run: Run) -> dict[str, dict]:
    """Per operation of constant engagement: the daemon's published force over its steady revolutions against the
    plant's true mean resultant, and the same for the torque.

    The stream may be played at speed, so revolutions are paired within each operation by order: the daemon's
    revolutions of the key in cut (called cutting, or a light cut's over half the true steady torque), less as many at each end as the truth has cutting revolutions outside its
    steady stretch, plus one (the daemon's split is another phase, and it may call the first partial one air),
    lie inside the truth's steady stretch, where the load of a constant cut is constant."""
    out = {}
    revs = truth_revs(run.truth)
    tables = operations_config(run.program)
    for proc in run.truth_processes:
        if tables.get(proc["key"], {}).get("engagement") != "constant":
            continue   # a varying cut's load moves along its path: no pairing by order
        cut = [r for r in revs if proc["first_index"] <= r["index_end"] <= proc["last_index"] and r["cutting"]]
        steady = [i for i, r in enumerate(cut) if r["steady"]]
        if not steady:
            continue
        head, tail = steady[0] + 1, len(cut) - 1 - steady[-1] + 1
        true_f = float(np.mean([cut[i]["force_n"] for i in steady]))
        true_t = float(np.mean([cut[i]["torque_nm"] for i in steady]))
        # the daemon's revolutions in cut: called cutting, or a light cut's under `[depth] min_torque_nm` (never
        # called cutting) with over half the true steady torque; one over the threshold yet not cutting is the
        # spindle running up or braking, not in cut
        mine = _longest_stretch([e for e in run.estimates if e.get("program") == proc["program"]
                                 and e.get("tool") == proc["tool"] and e.get("operation") == proc["operation"]
                                 and e.get("valid", True) and (e.get("cutting") or 0.5 * true_t <= (
                                     e.get("torque_nm") or 0.0) < MIN_TORQUE_NM)])
        inner = mine[head:len(mine) - tail]
        forces = np.array([e["force_n"] for e in inner if e.get("force_n") is not None], dtype=float)
        torques = np.array([e["torque_nm"] for e in inner], dtype=float)
        out[proc["key"]] = {"n": len(inner), "true_force_n": true_f, "force_ratio": forces / true_f,
                            "torque_ratio": torques / true_t, "nulls": len(inner) - len(forces)}
    return out


def _longest_stretch(estimates: list[dict]) -> list[dict]:
    """The longest run of consecutive revolutions (`rev`) among `estimates`: the cut, not a revolution of the
    spindle braking after it whose torque happens to lie in a light cut's band."""
    best: list[dict] = []
    run: list[dict] = []
    for e in estimates:
        rev, last = e.get("rev"), run[-1].get("rev") if run else None
        if rev is None or last is None or rev != last + 1:
            run = []
        run.append(e)
        if len(run) > len(best):
            best = list(run)
    return best
