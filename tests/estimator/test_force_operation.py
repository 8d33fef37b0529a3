"""The published force takes the engagement of the operation the CNC reports, where `[operations]` declares its cut.

A machine's `[cut]` describes one cut (here a slot, the machine's usual one); a first-part program runs down- and
up-milling operations beside slots. Where the revolution's context names an operation with a constant programmed
cut, the resultant force's C_f (`cf = "auto"`: the engaged teeth, force.engaged_cf) takes that cut's mode and
depths, so the force is the operation's, within the issue's 2 % of the plant's true mean resultant (found live by
tests/e2e/test_first_part_acceptance.py: 0.73 of the truth in a 4-flute down-milling cut under `[cut] mode =
"slot"`). Replay and the live daemon share the chain (run_core.py), so this runs through `millsense replay` on a
capture of `millsense sim`.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from tests.e2e.first_part_run import Run, daemon_config, force_by_operation
from tests.e2e.helpers import CMD, read_jsonl

PROGRAM = "first-part-down"
OPS = ("10", "90")   # a φ16 4-flute and a φ8 3-flute cutter in down milling (ae 2 and 1 mm)


def _replay(tmp_path, program: str, ops: tuple[str, ...], batch: str = "0") -> Run:
    cap, truth = tmp_path / "fp.cap", tmp_path / "fp.jsonl"
    only = [a for op in ops for a in ("--only-operation", op)]
    sim = subprocess.run(CMD + ["sim", "--scenario", program, *only, "--material-offset-pct", batch,
                                "--capture", str(cap), "--truth", str(truth)], capture_output=True, text=True,
                         timeout=300)
    assert sim.returncode == 0, sim.stderr
    cfg = daemon_config(tmp_path / "d.toml", program, daq_port=5556, z_port=7449, machine="fp", at_speed=False)
    text = cfg.read_text()
    assert '[cut]\nmode = "down"' in text
    cfg.write_text(text.replace('[cut]\nmode = "down"', '[cut]\nmode = "slot"'))   # the machine's usual cut
    out = subprocess.run(CMD + ["replay", str(cap), "--config", str(cfg)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    estimates = [p for p in map(json.loads, out.stdout.splitlines()) if p["type"] == "estimate"]
    return Run(program, read_jsonl(truth), estimates, [], [], [], 1.0)


@pytest.mark.slow
def test_the_force_of_a_down_milling_operation_is_its_own_under_a_slot_cut(tmp_path):
    run = _replay(tmp_path, PROGRAM, OPS)
    forces = force_by_operation(run)
    assert set(forces) == {f"4102/2/{OPS[0]}", f"4102/3/{OPS[1]}"}, forces
    for key, f in forces.items():
        assert f["n"] >= 10 and f["nulls"] == 0, (key, f)
        # the estimate: its mean over the steady revolutions within 2 % of the truth's ...
        assert abs(f["force_ratio"].mean() - 1.0) <= 0.02, (key, f["force_ratio"].mean())
        # ... and each revolution within 2 % plus what the per-revolution torque's noise makes of it
        # (tests/e2e/truth.py: the live torque within 2 % + 0.03 N·m), through C_f/R
        radius_m = {"4102/2/10": 8e-3, "4102/3/90": 4e-3}[key]
        slack = 1.2 * 0.03 / radius_m / f["true_force_n"]   # C_f ≤ 1.2 here
        assert np.all(np.abs(f["force_ratio"] - 1.0) <= 0.02 + slack), (key, f["force_ratio"])
