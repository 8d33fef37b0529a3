"""The part-program scenario: its timeline and context, per-process truth, wear and the three faults.

Expectations come from the program's definition (sim/program.py PROGRAMS) and from the
plant's own signals (sensor counts, per-revolution truth), never from numbers copied out of a run.
"""

from __future__ import annotations

import json
import math
import subprocess

import numpy as np
import pytest

from millsense.drivers.protocol import CTX_AFC_ALLOWED, CTX_CYCLE, CTX_MONITOR
from millsense.sim.machine import MATERIALS
from millsense.sim.program import PART_GAP_S, PROGRAMS, ProgramFaults
from millsense.sim.program_plant import ProgramPlant

from .helpers import physical

PROGRAM = PROGRAMS["part-program"]
OPS = PROGRAM.operations


def _run(parts: int, faults: ProgramFaults | None = None) -> dict:
    plant = ProgramPlant(parts=parts, faults=faults)
    counts = plant.step(round(plant.scenario.duration_s * 1000))
    return {"plant": plant, "sig": physical(plant, counts), "changes": plant.drain_context(),
            "procs": plant.processes(), "revs": plant.truth.revolutions(), "events": plant.truth.events()}


@pytest.fixture(scope="module")
def good() -> dict:
    return _run(2)


@pytest.fixture(scope="module")
def faulty() -> dict:
    # part 2: a flute of T11 breaks; part 3: no material; part 4: the wrong cutter for T27; T4 wears 10 %/part
    t11, t4, t27 = (op.tool_number for op in OPS)
    return _run(4, ProgramFaults(wear_pct=((t4, 10.0),), broken_flute=((2, t11),), missing_part=(3,),
                                 wrong_tool=((4, t27),)))


def _proc(run: dict, part: int, op) -> dict:
    (found,) = [p for p in run["procs"] if p["part"] == part and p["operation"] == op.number]
    return found


def _revs_in(run: dict, proc: dict) -> list[dict]:
    """Revolutions wholly inside the process: from the first one closing after its first sample."""
    revs = [r for r in run["revs"] if proc["first_index"] <= r["index_end"] <= proc["last_index"]]
    return revs[1:]  # the first began before the monitor came on


def test_the_context_walks_through_each_part_op_by_op(good):
    prog = PROGRAM.number
    expected = []
    for _ in range(2):
        for op in OPS:
            expected += [(prog, op.tool_number, op.number, CTX_CYCLE),  # the tool change
                         (prog, op.tool_number, op.number,
                          CTX_CYCLE | CTX_MONITOR | (CTX_AFC_ALLOWED if op.afc_allowed else 0)),  # the cut
                         (prog, op.tool_number, op.number, CTX_CYCLE)]  # spindle stops
        expected.append((prog, OPS[-1].tool_number, 0, 0))  # cycle off: the part is swapped
    plant = good["plant"]
    assert plant.context() == expected[-1]
    assert [ctx for _, ctx in good["changes"]] == expected
    indices = [k for k, _ in good["changes"]]
    assert indices == sorted(indices) and indices[0] == round(PART_GAP_S * 1000)  # cycle off before part 1
    # between parts the cycle is off for PART_GAP_S, then the first tool change
    off = [k for k, ctx in good["changes"] if ctx[3] == 0]
    assert indices[indices.index(off[0]) + 1] - off[0] == round(PART_GAP_S * 1000)


def test_processes_are_the_monitored_spans_and_the_spindle_stops_for_every_tool_change(good):
    sig, changes, procs = good["sig"], good["changes"], good["procs"]
    on = [k for k, ctx in changes if ctx[3] & CTX_MONITOR]
    off = [k for (k, ctx), (_, before) in zip(changes[1:], changes[:-1], strict=True)
           if before[3] & CTX_MONITOR and not ctx[3] & CTX_MONITOR]
    assert [p["first_index"] for p in procs] == on
    assert [p["last_index"] + 1 for p in procs] == off
    assert [(p["part"], p["operation"], p["tool"]) for p in procs] == [
        (part, op.number, op.tool_number) for part in (1, 2) for op in OPS]
    currents = np.abs(np.stack([sig[c] for c in ("i_u", "i_v", "i_w")])).max(axis=0)
    start = (0, (PROGRAM.number, OPS[-1].tool_number, 0, 0))  # before part 1: the last tool in the spindle
    tool_changes = [k for (k, ctx), (_, before) in zip(changes, [start, *changes[:-1]], strict=True)
                    if ctx[3] == CTX_CYCLE and ctx[1:3] != before[1:3]]
    assert len(tool_changes) == 2 * len(OPS)
    for k in tool_changes:  # the spindle stands, the drive is off (no current)
        window = slice(k, k + 200)
        assert np.abs(sig["sp_rpm"][window]).max() < 2.0
        assert currents[window].max() < 0.5
    for p, op in zip(procs, OPS * 2, strict=True):
        window = slice(p["first_index"], p["last_index"] + 1)
        speed = sig["sp_rpm"][window]
        assert abs(np.median(speed) / op.rpm - 1) < 0.005  # turning at the operation's speed throughout
        assert p["first_index"] < p["entry_index"] < p["last_index"]  # an approach in air, then the cut
        feed = sig["fx_rate"][window]
        assert abs(np.median(feed[feed > 1]) / op.feed_mm_min - 1) < 0.01


def test_each_cut_steps_down_once_and_its_energy_is_the_integral_of_torque_and_speed(good):
    for p, op in zip(good["procs"], OPS * 2, strict=True):
        revs = _revs_in(good, p)
        steady_depths = sorted({round(r["axial_depth_mm"], 3) for r in revs if r["steady"] and r["cutting"]})
        assert steady_depths == list(op.depths_mm)  # both floors, steady, nothing else
        # one revolution turns 2π: Σ 2π·T over the revolutions, T·ω being nearly constant within one
        energy = sum(2 * math.pi * r["torque_nm"] for r in revs)
        assert p["energy_j"] == pytest.approx(energy, rel=0.01)
        assert p["energy_j"] > 0 and p["fault"] is None and p["wear_factor"] == 1.0
    # the same part twice gives the same energy (the process is repeatable)
    first, second = good["procs"][:3], good["procs"][3:]
    for a, b in zip(first, second, strict=True):
        assert b["energy_j"] == pytest.approx(a["energy_j"], rel=0.002)


def test_wear_compounds_part_by_part(faulty):
    t4 = OPS[1]
    for part in (1, 2, 4):
        assert _proc(faulty, part, t4)["wear_factor"] == pytest.approx(1.1 ** (part - 1))
        for other in (OPS[0], OPS[2]):
            assert _proc(faulty, part, other)["wear_factor"] == 1.0
    e1 = _proc(faulty, 1, t4)["energy_j"]
    # K_s scales the chip's force, so the energy follows the factor: 1.21 in part 3 of compounding
    # (linear would be 1.20); part 3 has no material, part 4 is 1.1³
    assert _proc(faulty, 2, t4)["energy_j"] / e1 == pytest.approx(1.1, rel=0.002)
    assert _proc(faulty, 4, t4)["energy_j"] / e1 == pytest.approx(1.1**3, rel=0.002)
    assert abs(_proc(faulty, 4, t4)["energy_j"] / e1 - 1.3) > 0.02  # not linear


def test_a_broken_flute_drops_the_torque_after_the_break_and_only_in_that_part(faulty, good):
    t11 = OPS[0]
    broken, sound = _proc(faulty, 2, t11), _proc(good, 2, t11)
    assert broken["fault"] == "broken_flute" and sound["fault"] is None
    k = broken["broken_index"]
    assert broken["entry_index"] < k < broken["last_index"]
    (event,) = [e for e in faulty["events"] if e["event"] == "tool_breakage"]
    assert event["index"] == k and event["tool"] == t11.tool_number and event["part"] == 2
    # the same revolutions of the sound part: equal before the break, lower after, by the chip law
    revs_b, revs_s = _revs_in(faulty, broken), _revs_in(good, sound)
    shift = broken["first_index"] - sound["first_index"]
    paired = [(b, s) for b, s in zip(revs_b, revs_s, strict=False) if b["cutting"] and b["steady"]]
    before = [(b, s) for b, s in paired if b["index_end"] < k]
    after = [(b, s) for b, s in paired if b["index_end"] > k + 60_000 / t11.rpm]
    assert before and len(after) >= 3
    for b, s in before:
        assert b["index_end"] - shift == pytest.approx(s["index_end"], abs=2)
        assert b["torque_nm"] == pytest.approx(s["torque_nm"], rel=0.01)
    # 2 flutes, one gone: the other cuts twice the chip at K_s(2·t_a) = 2^ks_exp·K_s(t_a)
    drop = 2 ** MATERIALS["SS41"].ks_exp
    for b, s in after:
        assert b["torque_nm"] / s["torque_nm"] == pytest.approx(drop, rel=0.03)
    assert broken["energy_j"] < sound["energy_j"]
    # the next part has a sound cutter again
    assert _proc(faulty, 3, t11)["broken_index"] is None
    assert _proc(faulty, 4, t11)["energy_j"] == pytest.approx(sound["energy_j"], rel=0.002)


def test_a_missing_part_is_cut_in_air(faulty, good):
    for op in OPS:
        missing = _proc(faulty, 3, op)
        assert missing["fault"] == "missing_part" and missing["entry_index"] is None
        assert missing["energy_j"] == 0.0
        assert not any(r["cutting"] for r in _revs_in(faulty, missing))
        assert _proc(good, 1, op)["energy_j"] > 100 * (missing["energy_j"] + 1.0)


def test_a_wrong_tool_changes_the_energy_while_the_cnc_reports_the_programmed_one(faulty, good):
    t27 = OPS[2]
    wrong, right = _proc(faulty, 4, t27), _proc(good, 1, t27)
    assert wrong["fault"] == "wrong_tool" and wrong["tool"] == t27.tool_number
    assert (wrong["cutter"]["diameter_mm"], wrong["cutter"]["flutes"]) == (
        t27.wrong_cutter.diameter_mm, t27.wrong_cutter.flutes)
    assert (right["cutter"]["diameter_mm"], right["cutter"]["flutes"]) == (t27.tool.diameter_mm, t27.tool.flutes)
    held = [ctx for k, ctx in faulty["changes"] if k <= wrong["first_index"]][-1]
    assert held[1:3] == (t27.tool_number, t27.number)  # the context says T27 all the same
    # slot torque is R·F_t, F_t ∝ K_s(t_a)·t_c·N (same feed per revolution): R and the chip law
    ratio = (t27.wrong_cutter.radius_mm / t27.tool.radius_mm) * (
        (t27.tool.flutes / t27.wrong_cutter.flutes) ** MATERIALS["SS41"].ks_exp)
    assert abs(ratio - 1) > 0.2
    deep = max(t27.depths_mm)

    def steady_deep_nm(run, proc):
        return np.median([r["torque_nm"] for r in _revs_in(run, proc)
                          if r["steady"] and r["axial_depth_mm"] == pytest.approx(deep)])

    assert steady_deep_nm(faulty, wrong) / steady_deep_nm(good, right) == pytest.approx(ratio, rel=0.02)
    # the energy moves the same way (and a little more: the larger cutter also meets the part sooner)
    assert (wrong["energy_j"] / right["energy_j"] - 1) / (ratio - 1) > 0.8


def test_the_truth_file_lists_every_process(tmp_path):
    plant = ProgramPlant(parts=1)
    plant.step(round(plant.scenario.duration_s * 1000))
    path = tmp_path / "truth.jsonl"
    plant.truth.write_jsonl(path)
    lines = [json.loads(x) for x in path.read_text().splitlines()]
    procs = [x for x in lines if "process" in x]
    assert [p["key"] for p in procs] == [f"{PROGRAM.number}/{op.tool_number}/{op.number}" for op in OPS]
    assert {"first_index", "last_index", "energy_j", "wear_factor", "fault", "broken_index"} <= set(procs[0])
    assert all("rev" in x or "event" in x or "process" in x for x in lines)
    assert len(plant.truth.revolutions()) == sum("rev" in x for x in lines)


def test_a_feed_hold_stops_the_program_where_it_is():
    reference = ProgramPlant(parts=1)
    reference.step(round(reference.scenario.duration_s * 1000))
    (ref,) = [p for p in reference.processes() if p["operation"] == OPS[0].number]
    plant = ProgramPlant(parts=1)
    plant.step(round(PART_GAP_S * 1000) + 500)  # the first tool change is under way
    plant.drain_context()
    plant.feed_hold = True  # held during the change and spin-up: the program's timers stop
    plant.step(2000)
    assert plant.drain_context() == []
    plant.feed_hold = False
    plant.step(ref["entry_index"] + 2000 + 500 - plant.index)  # into the cut
    (start,) = [k for k, ctx in plant.drain_context() if ctx[3] & CTX_MONITOR]
    assert start == ref["first_index"] + 2000
    plant.feed_hold = True  # held in the cut: the feed stops, the process goes on
    plant.step(3000)
    assert plant.drain_context() == []
    plant.feed_hold = False
    plant.step(round(plant.scenario.duration_s * 1000))
    (proc,) = [p for p in plant.processes() if p["operation"] == OPS[0].number]
    assert proc["first_index"] == start
    assert proc["last_index"] - proc["first_index"] == pytest.approx(ref["last_index"] - ref["first_index"] + 3000,
                                                                     abs=50)  # + the hold, and its stop and start
    assert proc["energy_j"] == pytest.approx(ref["energy_j"], rel=0.01)  # the same slot, interrupted


def test_faults_are_refused_where_they_mean_nothing(millsense_cmd, tmp_path):
    cap = str(tmp_path / "x.cap")
    cases = [
        (["--scenario", "step", "--wear", "4:5"], "only for a part program"),
        (["--scenario", "part-program", "--wear", "5:5"], "tool 5 is not in program"),
        (["--scenario", "part-program", "--parts", "3", "--missing-part", "4"], "part 4 is not one of"),
        (["--scenario", "part-program", "--wrong-tool", "2"], "PART:TOOL"),
        (["--scenario", "part-program", "--tool", "4"], "sets the tool"),
    ]
    for args, message in cases:
        res = subprocess.run([*millsense_cmd, "sim", *args, "--capture", cap], capture_output=True, text=True,
                             timeout=60)
        assert res.returncode == 2, (args, res.stderr)
        assert message in res.stderr and "Traceback" not in res.stderr, res.stderr


def test_the_example_config_is_this_machine_and_its_magazine():
    from millsense.daemon.config.load import load_config
    from millsense.sim import machine_config
    from tests.config.helpers import REPO

    settings = load_config(REPO / "config" / "part-program.toml")
    plant = machine_config("part-program")
    assert {n: {"diameter_mm": t.diameter_mm, "flutes": t.flutes, "helix_deg": t.helix_deg}
            for n, t in settings.tools.items()} == plant["tools"]
    assert (settings.tool.diameter_mm, settings.tool.flutes) == (plant["tool"]["diameter_mm"], plant["tool"]["flutes"])
    assert {k: getattr(settings.material, k) for k in plant["material"]} == plant["material"]
    gear_keys = ("name", "ratio", "max_spindle_rpm", "friction_torque_nm", "viscous_nms")
    assert [tuple(getattr(g, k) for k in gear_keys) for g in settings.gears] == [
        tuple(g[k] for k in gear_keys) for g in plant["gears"]]
    assert settings.cut.mode == plant["cut"]["mode"] and set(plant["channels"]) <= set(settings.channels)
    assert settings.context.source == "auto" and settings.learning.enabled and settings.history.enabled
    # the fixed limits leave every good cut alone: the heaviest cut's torque with room for wear
    assert settings.alarms.torque_warn_nm > 1.3 * _heaviest_true_torque_nm()


def _heaviest_true_torque_nm() -> float:
    plant = ProgramPlant(parts=1)
    plant.step(round(plant.scenario.duration_s * 1000))
    return max(r["torque_nm"] for r in plant.truth.revolutions())


def test_looping_starts_the_program_over_with_sharp_tools():
    t4 = OPS[1]
    plant = ProgramPlant(parts=2, faults=ProgramFaults(wear_pct=((t4.tool_number, 10.0),)), loop=True)
    plant.step(round(2.2 * plant.program.duration_s(2) * 1000))
    (restart, *_) = [e for e in plant.truth.events() if e["event"] == "scenario_restart"]
    procs = [p for p in plant.processes() if p["operation"] == t4.number]
    assert [(p["pass"], p["part"]) for p in procs][:4] == [(1, 1), (1, 2), (2, 1), (2, 2)]
    assert [p["wear_factor"] for p in procs][:4] == pytest.approx([1.0, 1.1, 1.0, 1.1])
    assert procs[2]["first_index"] > restart["index"] > procs[1]["last_index"]
    assert procs[2]["energy_j"] == pytest.approx(procs[0]["energy_j"], rel=0.002)
