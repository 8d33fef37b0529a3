"""Issue 14's acceptance run: a simulated part program through `millsense replay`, read against its truth.

The plant (`millsense sim --scenario part-program`) makes N parts with three
tools; one tool wears, and single parts carry a broken flute, a missing part
and a wrong tool. Its truth lists every process (part, tool, operation,
first and last sample index, true cutting energy, fault). The daemon's replay
of the capture gives estimates, alarms and process summaries. `outcome()`
pairs the two: what was learned when, which alarms came in which part, how
many revolutions after a flute broke, and in which part the wear warning came
against the part where the true energy passed the rise. Shared by the test
(tests/e2e/test_learning_acceptance.py) and the report (bench/validate_learning.py).
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "part-program.toml"
RATE_HZ = 1000.0

# The acceptance run: 30 parts, T4 wearing, one part with each fault (parts numbered from 1).
PARTS = 30
WEAR = (4, 0.7)            # tool, % per part (compounding)
BROKEN_FLUTE = (12, 11)    # part, tool
MISSING_PART = 16
WRONG_TOOL = (20, 27)      # part, tool number the CNC reports while another cutter is in the spindle
FAULT_PARTS = {BROKEN_FLUTE[0], MISSING_PART, WRONG_TOOL[0]}


@dataclass
class Run:
    truth: list[dict]                      # the simulator's processes, in order
    estimates: list[dict]
    alarms: list[dict]
    processes: list[dict]                  # the daemon's process summaries
    config: Path = CONFIG
    first_index: int = 0

    def part_of_seq(self, seq: int) -> dict | None:
        """The truth process whose samples hold `seq` (None: between processes)."""
        for proc in self.truth:
            if proc["first_index"] <= seq <= proc["last_index"]:
                return proc
        return None

    def seq_of_t(self, t: float) -> int:
        return self.first_index + round(t * RATE_HZ)


def simulate_and_replay(workdir: Path, *, parts: int = PARTS, seed: int = 3, config: Path = CONFIG) -> Run:
    """Make the capture and its truth with the real `millsense sim`, replay it with `millsense replay`."""
    capture, truth_path = workdir / "program.bin", workdir / "program.truth.jsonl"
    sim = [sys.executable, "-m", "millsense.daemon", "sim", "--scenario", "part-program", "--parts", str(parts),
           "--seed", str(seed), "--wear", f"{WEAR[0]}:{WEAR[1]}",
           "--broken-flute", f"{BROKEN_FLUTE[0]}:{BROKEN_FLUTE[1]}", "--missing-part", str(MISSING_PART),
           "--wrong-tool", f"{WRONG_TOOL[0]}:{WRONG_TOOL[1]}", "--capture", str(capture), "--truth", str(truth_path)]
    subprocess.run(sim, check=True, capture_output=True, timeout=600)
    out = subprocess.run([sys.executable, "-m", "millsense.daemon", "replay", str(capture), "--config", str(config)],
                         check=True, capture_output=True, text=True, timeout=600)
    estimates, alarms, processes = [], [], []
    for line in out.stdout.splitlines():
        payload = json.loads(line)
        {"estimate": estimates, "alarm": alarms, "process": processes}[payload["type"]].append(payload)
    truth = [json.loads(line) for line in truth_path.read_text().splitlines()]
    return Run([t for t in truth if "process" in t and "first_index" in t], estimates, alarms, processes, config)


@dataclass
class Outcome:
    learned_after_parts: dict[str, int] = field(default_factory=dict)   # key -> part whose process completed it
    false_alarms: list[dict] = field(default_factory=list)              # alarms in good parts
    flute_revolutions: int | None = None   # revolutions from the one holding the break to the alarm's
    flute_alarm: dict | None = None
    flute_envelope_revolutions: int | None = None  # the same for the first envelope alarm alone
    missing_caught: dict[str, dict | None] = field(default_factory=dict)  # key -> first alarm inside its process
    wrong_tool_alarm: dict | None = None
    wear_cross_part: int | None = None     # first part whose true energy passed the rise over the learned parts'
    wear_warn_part: int | None = None
    wear_warnings_other_tools: list[dict] = field(default_factory=list)
    envelope_high_on_wearing_tool_before_warning: list[dict] = field(default_factory=list)


def _alarm_part(run: Run, alarm: dict) -> dict | None:
    return run.part_of_seq(run.seq_of_t(alarm["t"])) if alarm.get("t") is not None else None


def outcome(run: Run, *, learn_parts: int = 5, wear_rise_pct: float = 15.0) -> Outcome:
    out = Outcome()
    truth_by_part: dict[int, list[dict]] = {}
    for proc in run.truth:
        truth_by_part.setdefault(proc["part"], []).append(proc)
    # learning: the summary whose envelope first reads "active", and the part of its process
    for summary in run.processes:
        key = summary["key"]
        if summary.get("envelope") == "active" and key not in out.learned_after_parts:
            truth = run.part_of_seq(run.seq_of_t(summary["t"]))
            out.learned_after_parts[key] = truth["part"] if truth else -1
    problem_alarms = [a for a in run.alarms if a["level"] not in ("clear", "wear")]
    for alarm in problem_alarms:
        proc = _alarm_part(run, alarm)
        if proc is not None and proc["part"] not in FAULT_PARTS:
            out.false_alarms.append(alarm)
    # broken flute: revolutions from the one holding the break to the first alarm after it
    flute = next(p for p in truth_by_part[BROKEN_FLUTE[0]] if p["tool"] == BROKEN_FLUTE[1])
    broken_seq = int(flute["broken_index"])
    after = [a for a in problem_alarms if run.seq_of_t(a["t"]) >= broken_seq and a.get("rev") is not None
             and run.seq_of_t(a["t"]) <= flute["last_index"]]
    if after:
        out.flute_alarm = min(after, key=lambda a: a["t"])
        first_rev = next(e["rev"] for e in run.estimates if run.seq_of_t(e["t"]) >= broken_seq)
        out.flute_revolutions = int(out.flute_alarm["rev"]) - int(first_rev) + 1
        envelope = [a for a in after if a["level"].startswith("envelope")]
        if envelope:
            out.flute_envelope_revolutions = int(min(envelope, key=lambda a: a["t"])["rev"]) - int(first_rev) + 1
    # missing part: every process of the part raises an alarm inside it
    for proc in truth_by_part[MISSING_PART]:
        inside = [a for a in problem_alarms if proc["first_index"] <= run.seq_of_t(a["t"]) <= proc["last_index"]]
        out.missing_caught[proc["key"]] = inside[0] if inside else None
    wrong = next(p for p in truth_by_part[WRONG_TOOL[0]] if p["tool"] == WRONG_TOOL[1])
    inside = [a for a in problem_alarms if wrong["first_index"] <= run.seq_of_t(a["t"]) <= wrong["last_index"]]
    out.wrong_tool_alarm = inside[0] if inside else None
    # wear: the true energy of the wearing tool's process against its mean over the learned parts
    wearing = [p for p in run.truth if p["tool"] == WEAR[0]]
    baseline = sum(p["energy_j"] for p in wearing[:learn_parts]) / learn_parts
    for proc in wearing:
        if proc["part"] not in FAULT_PARTS and proc["energy_j"] >= baseline * (1 + wear_rise_pct / 100.0):
            out.wear_cross_part = proc["part"]
            break
    for alarm in run.alarms:
        if alarm["level"] != "wear":
            continue
        proc = _alarm_part(run, alarm) or run.part_of_seq(run.seq_of_t(alarm["t"]) - 1)
        part = proc["part"] if proc else _part_before(run, alarm)
        if alarm.get("tool") == WEAR[0]:
            if out.wear_warn_part is None:
                out.wear_warn_part = part
        else:
            out.wear_warnings_other_tools.append(alarm)
    for alarm in problem_alarms:
        if alarm["level"] == "envelope_high" and alarm.get("tool") == WEAR[0]:
            proc = _alarm_part(run, alarm)
            if proc is not None and (out.wear_warn_part is None or proc["part"] <= out.wear_warn_part):
                out.envelope_high_on_wearing_tool_before_warning.append(alarm)
    return out


def _part_before(run: Run, alarm: dict) -> int:
    """A wear warning comes when a process ends: the part of the last process that ended before it."""
    seq = run.seq_of_t(alarm["t"])
    ended = [p for p in run.truth if p["last_index"] <= seq]
    return ended[-1]["part"] if ended else -1
