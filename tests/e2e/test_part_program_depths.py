"""Issue 36's acceptance, finding 4: the part-program scenario publishes no valid depth outside the
tool's geometry, claims no cut while the spindle runs up or brakes around a tool change, and still
gives the real cuts their depths.

Found on main: with the shipped config/part-program.toml, the revolutions of the spindle running up
and braking around each tool change (axes stopped, t_c ≈ 2·10⁻⁵ mm) came out `depth_status: "ok"`,
`cutting: true`, `axial_depth_mm` 50–935 mm on φ8–φ20 cutters (281 of 1 598 revolutions).

The real path: `millsense sim` writes the capture (protocol 2: the CNC's context names each tool) and
its truth, `millsense replay` runs it through the daemon's pipeline with the shipped configuration;
each estimate is matched to the simulator's revolution that ends on the same sample.
"""

from __future__ import annotations

import bisect
import json
import subprocess

from millsense.daemon.config.load import load_config
from millsense.daemon.physics import validity
from tests.e2e.helpers import CMD
from tests.e2e.learning_run import CONFIG, RATE_HZ
from tests.e2e.truth import truth_revs

PARTS = 3                 # three tool changes a part: nine run-ups and brakings
DEPTH_REL = 0.10          # [D] reports its depths within 10 % while the cut holds steady
MIN_SHARE = 0.90          # of the simulator's steady cutting revolutions, carrying such a depth
RAMP_FRAC = 0.01          # the truth's speed moving more than this from one revolution to the next


def _run(tmp_path):
    cap, truth_path = tmp_path / "p.bin", tmp_path / "p.truth.jsonl"
    subprocess.run(CMD + ["sim", "--scenario", "part-program", "--parts", str(PARTS), "--protocol", "2",
                          "--capture", str(cap), "--truth", str(truth_path)],
                   check=True, capture_output=True, timeout=300)
    out = subprocess.run(CMD + ["replay", str(cap), "--config", str(CONFIG)],
                         check=True, capture_output=True, text=True, timeout=300)
    estimates = [p for p in map(json.loads, out.stdout.splitlines()) if p["type"] == "estimate"]
    truth = truth_revs([json.loads(line) for line in truth_path.read_text().splitlines()])
    return estimates, truth


def _matched(estimates, truth):
    """(estimate, its truth revolution, the truth revolution before or None), by the last sample."""
    ends = [t["index_end"] for t in truth]
    pairs = []
    for e in estimates:
        end = e["t"] * RATE_HZ
        i = bisect.bisect_left(ends, end)
        j = min((k for k in (i - 1, i) if 0 <= k < len(ends)), key=lambda k: abs(ends[k] - end))
        if abs(ends[j] - end) <= 1.5:
            pairs.append((e, truth[j], truth[j - 1] if j else None))
    assert len(pairs) >= 0.95 * len(estimates)   # the replay's revolutions are the simulator's
    return pairs


def test_the_part_program_publishes_no_valid_depth_outside_the_tools_geometry(tmp_path):
    estimates, truth = _run(tmp_path)
    settings = load_config(CONFIG)
    listed = dict(settings.tools)
    pairs = _matched(estimates, truth)
    assert {e["tool"] for e, _, _ in pairs} >= {11, 4, 27}     # every tool of the program was in the spindle

    # 1. no valid depth outside the geometry of the tool in the spindle
    outside = []
    for e, _, _ in pairs:
        if not e["valid"] or e["axial_depth_mm"] is None:
            continue
        tool = listed.get(e["tool"], settings.tool)   # a tool not listed: [tool]
        flute_mm = tool.flute_length_mm or validity.default_flute_length_mm(tool.diameter_mm)
        if e["radial_depth_mm"] > tool.diameter_mm or e["axial_depth_mm"] > flute_mm:
            outside.append((e["rev"], e["tool"], e["axial_depth_mm"], e["depth_status"]))
    assert outside == []

    # 2. no depth where the simulator's axes stand, and none but with depth_status "ok"
    standing = [(e["rev"], e["axial_depth_mm"]) for e, t, _ in pairs
                if t["feed_per_tooth_mm"] < validity.FEED_PER_TOOTH_MIN_MM and e["axial_depth_mm"] is not None]
    assert standing == []
    assert all((e["axial_depth_mm"] is None) == (e["depth_status"] != "ok") for e, _, _ in pairs)

    # 3. no cut claimed while the spindle only runs up or brakes (the simulator cuts nothing, its speed moves)
    ramps = [(e, t) for e, t, before in pairs if before is not None and not t["cutting"]
             and abs(t["spindle_rpm"] - before["spindle_rpm"]) > RAMP_FRAC * t["spindle_rpm"]]
    assert len(ramps) >= 6 * PARTS                              # run-ups and brakings were there to judge
    claimed = [(e["rev"], round(e["spindle_rpm"]), e["torque_nm"]) for e, _ in ramps if e["cutting"]]
    assert claimed == []
    assert all(e["depth_status"] in (validity.SPEED_CHANGING, "air_cut") for e, _ in ramps)

    # 4. the real cuts still carry their depths: the simulator's steady cutting revolutions
    steady = [(e, t) for e, t, _ in pairs if t["cutting"] and t["steady"] and e["valid"]]
    assert len(steady) >= 30 * PARTS
    near = [e for e, t in steady if e["depth_status"] == "ok" and e["cutting"]
            and abs(e["axial_depth_mm"] / t["axial_depth_mm"] - 1.0) <= DEPTH_REL
            and abs(e["radial_depth_mm"] / t["radial_depth_mm"] - 1.0) <= DEPTH_REL]
    assert len(near) >= MIN_SHARE * len(steady), (len(near), len(steady))
