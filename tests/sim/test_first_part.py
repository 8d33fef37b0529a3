"""First-part programs (sim/first_part.py): what each operation programs is what the plant cuts, unless told.

The programmed cut (``operations_config``) is checked against the plant's truth, never against the daemon.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace

import numpy as np
import pytest

from millsense.sim.first_part import FIRST_PART_PROGRAMS, LIFE_USED, operations_config
from millsense.sim.program import PROGRAMS, ProgramFaults
from millsense.sim.program_plant import ProgramPlant


def _run(program, faults=None):
    plant = ProgramPlant(program, faults=faults, noise_scale=0.0)
    while not plant.done:
        plant.step(1000)
    return plant


def _steady(plant, key):
    (proc,) = [p for p in plant.processes() if p["key"] == key]
    return [r for r in plant.truth.revolutions()
            if r["steady"] and r["cutting"] and proc["first_index"] <= r["index_end"] <= proc["last_index"]]


@pytest.mark.quick
def test_thirty_different_constant_cuts_with_their_programmed_parameters():
    tables = {}
    for name in ("first-part-slot", "first-part-down", "first-part-up"):
        assert name in PROGRAMS  # the emulator can play it
        tables.update(operations_config(name))
    assert len(tables) == 30
    cuts = {(t["mode"], t["ae_mm"], t["ap_mm"], t.get("fz_mm"), t.get("vf_mm_min")) for t in tables.values()}
    assert len(cuts) == 30  # thirty different operations, not one repeated
    assert {t["mode"] for t in tables.values()} == {"slot", "down", "up"}
    assert {"fz_mm" in t for t in tables.values()} == {True, False}  # both ways of programming a feed
    for key, t in tables.items():
        assert set(t) in ({"ae_mm", "ap_mm", "fz_mm", "mode", "engagement"},
                          {"ae_mm", "ap_mm", "vf_mm_min", "mode", "engagement"}), key
        assert t["engagement"] == "constant"
    speeds = {op.rpm for name in ("first-part-slot", "first-part-down", "first-part-up")
              for op in PROGRAMS[name].operations}
    assert min(speeds) < 900 < 1000 < max(speeds)  # both gears
    pocket = operations_config("first-part-pocket")
    assert {t["engagement"] for t in pocket.values()} == {"varying"}
    assert all(op.life_used == LIFE_USED for op in PROGRAMS["first-part-worn"].operations)


def test_the_plant_cuts_what_each_operation_programs():
    """Per steady revolution the true axial and radial depth and feed per tooth are the programmed ones."""
    for name, ops in (("first-part-slot", (10, 80)), ("first-part-down", (90,)), ("first-part-up", (20,))):
        program = PROGRAMS[name].only(*ops)
        plant = _run(program)
        for key, table in operations_config(program).items():
            revs = _steady(plant, key)
            assert len(revs) >= 10, key
            op = next(o for o in program.operations if key.endswith(f"/{o.number}"))
            assert np.mean([r["axial_depth_mm"] for r in revs]) == pytest.approx(table["ap_mm"], rel=1e-6), key
            assert np.mean([r["radial_depth_mm"] for r in revs]) == pytest.approx(table["ae_mm"], rel=1e-6), key
            fz = table["fz_mm"] if "fz_mm" in table else table["vf_mm_min"] / (op.rpm * op.tool.flutes)
            assert np.mean([r["feed_per_tooth_mm"] for r in revs]) == pytest.approx(fz, rel=0.01), key


def test_a_scaled_depth_is_cut_while_the_programmed_one_stays():
    program = PROGRAMS["first-part-slot"].only(10, 20)
    before = operations_config(program)
    faults = ProgramFaults(axial_scale=((10, 1.8),), radial_scale=((20, 0.5),))
    plant = _run(program, faults)
    assert operations_config(program) == before  # the config the daemon is given does not move
    deep = _steady(plant, "4101/1/10")
    half = _steady(plant, "4101/1/20")
    assert np.mean([r["axial_depth_mm"] for r in deep]) == pytest.approx(1.8 * before["4101/1/10"]["ap_mm"])
    assert np.mean([r["radial_depth_mm"] for r in half]) == pytest.approx(0.5 * before["4101/1/20"]["ae_mm"])
    reference = _run(program)
    def torque(revs):
        return np.mean([r["torque_nm"] for r in revs])

    ratio_deep = torque(deep) / torque(_steady(reference, "4101/1/10"))
    ratio_half = torque(half) / torque(_steady(reference, "4101/1/20"))
    assert ratio_deep == pytest.approx(1.8, rel=0.03)  # the load follows the real depth
    assert ratio_half == pytest.approx(0.5, rel=0.05)  # half a slot in down milling: half the chips


def test_a_material_batch_off_the_config_moves_the_load_by_its_percentage():
    program = PROGRAMS["first-part-slot"].only(10)
    loads = {}
    for pct in (-20.0, 0.0, 20.0):
        plant = _run(replace(program, material_offset_pct=pct))
        loads[pct] = np.mean([r["torque_nm"] for r in _steady(plant, "4101/1/10")])
    assert loads[20.0] / loads[0.0] == pytest.approx(1.2, rel=2e-3)  # a slot: no deflection, so exactly x1.2
    assert loads[-20.0] / loads[0.0] == pytest.approx(0.8, rel=2e-3)


def test_a_tool_at_80_percent_of_its_life_cuts_harder_than_a_sharp_one():
    worn = PROGRAMS["first-part-worn"].only(10)
    sharp = replace(worn, operations=tuple(replace(op, life_used=0.0) for op in worn.operations))
    t_worn = np.mean([r["torque_nm"] for r in _steady(_run(worn), "4105/1/10")])
    t_sharp = np.mean([r["torque_nm"] for r in _steady(_run(sharp), "4105/1/10")])
    assert 1.01 < t_worn / t_sharp < 1.15
    # --life-used does the same to any first-part tool
    t_cli = np.mean([r["torque_nm"] for r in _steady(_run(sharp, ProgramFaults(life_used=((1, LIFE_USED),))),
                                                       "4105/1/10")])
    assert t_cli == pytest.approx(t_worn, rel=1e-9)


def test_the_pocket_varies_its_engagement_and_is_never_steady_where_it_does():
    program = PROGRAMS["first-part-pocket"]
    plant = _run(program)
    tables = operations_config(program)
    for key, table in tables.items():
        (proc,) = [p for p in plant.processes() if p["key"] == key]
        revs = [r for r in plant.truth.revolutions()
                if r["cutting"] and proc["first_index"] <= r["index_end"] <= proc["last_index"]]
        radial = [r["radial_depth_mm"] for r in revs]
        axial = [r["axial_depth_mm"] for r in revs]
        if table["mode"] == "down":  # the wall with two corners: ae rises towards ae + R and back
            assert max(radial) > 1.5 * np.median(radial)
            assert max(radial) <= table["ae_mm"] + 1e-9
        else:  # the ramp
            assert min(axial) < 0.5 * table["ap_mm"] and max(axial) == pytest.approx(table["ap_mm"], rel=1e-6)
        assert not all(r["steady"] for r in revs)


def test_the_emulator_plays_a_first_part_with_its_options(millsense_cmd, tmp_path):
    cap, truth = tmp_path / "fp.cap", tmp_path / "fp.jsonl"
    res = subprocess.run([*millsense_cmd, "sim", "--scenario", "first-part-slot", "--only-operation", "10",
                          "--axial-scale", "10:1.8", "--material-offset-pct", "-20", "--capture", str(cap),
                          "--truth", str(truth), "--noise-scale", "0"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    lines = [json.loads(x) for x in truth.read_text().splitlines()]
    (proc,) = [x for x in lines if "process" in x]
    assert proc["key"] == "4101/1/10"
    revs = [x for x in lines if "rev" in x and x["steady"] and x["cutting"]
            and proc["first_index"] <= x["index_end"] <= proc["last_index"]]
    assert np.mean([r["axial_depth_mm"] for r in revs]) == pytest.approx(1.8 * 3.0)
    direct = _run(replace(FIRST_PART_PROGRAMS["first-part-slot"].only(10), material_offset_pct=-20.0),
                  ProgramFaults(axial_scale=((10, 1.8),)))
    assert np.mean([r["torque_nm"] for r in revs]) == pytest.approx(
        np.mean([r["torque_nm"] for r in _steady(direct, "4101/1/10")]), rel=1e-6)


def test_first_part_options_are_refused_where_they_mean_nothing(millsense_cmd, tmp_path):
    cap = str(tmp_path / "x.cap")
    cases = [
        (["--scenario", "step", "--axial-scale", "10:1.8"], "only for a part program"),
        (["--scenario", "first-part-slot", "--axial-scale", "11:1.8"], "operation 11 is not in program 4101"),
        (["--scenario", "first-part-slot", "--radial-scale", "10:0"], "expected 0 < K <= 3"),
        (["--scenario", "first-part-slot", "--only-operation", "15"], "operation 15 is not in program 4101"),
        (["--scenario", "part-program", "--life-used", "4:0.8"], "no cutting effects"),
        (["--scenario", "first-part-worn", "--life-used", "1:1.5"], "within 0..1"),
        (["--scenario", "step", "--material-offset-pct", "-95"], "above -90"),
        (["--scenario", "ramp", "--material-offset-pct", "10"], "the ramp cuts nothing"),
        (["--scenario", "first-part-slot", "--speed", "3"], "--speed: only for a stream paced by the clock"),
        (["--scenario", "first-part-slot", "--start-on-connect"], "--start-on-connect waits for a client"),
        (["--scenario", "first-part-slot", "--speed", "0"], "expected a value > 0"),
    ]
    for args, message in cases:
        res = subprocess.run([*millsense_cmd, "sim", *args, "--capture", cap], capture_output=True, text=True,
                             timeout=60)
        assert res.returncode == 2, (args, res.stderr)
        assert message in res.stderr and "Traceback" not in res.stderr, (args, res.stderr)
