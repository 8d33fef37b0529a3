"""Tools by number (issue 14): feed per tooth, force and depth use the tool in the spindle.

`Estimator.tool_at` says which CNC tool holds at a revolution's last sample; a
`[tools.N]` table gives that tool's geometry, `[tool]` stays the default for a
tool the configuration does not list (or an unknown one).

(a) The simulator's `fig5` cut ([D]'s 4-flute φ16 cutter) under a configuration
whose `[tool]` is [P]'s 20 mm 2-flute cutter and whose `[tools.7]` is the fig5
cutter: with tool 7 in the spindle every number equals the run whose `[tool]` is
the fig5 cutter, and agrees with the plant's truth; with no tool or an unlisted
one every number equals the `[tool]`-only run.
(b) A synthetic block whose revolutions change tool midway: each revolution
uses its own tool, number for number as a run with that tool throughout.
"""

from __future__ import annotations

import numpy as np
import pytest

from millsense.daemon.config.load import load_config
from millsense.daemon.commands.capture_reader import iter_capture_blocks
from millsense.daemon.pipeline.estimator import Estimator
from millsense.drivers.base import SampleBlock

from . import configs, simcase, synthetic

TOOL_NUMBER = 7
UNLISTED = 8
TORQUE_REL, TORQUE_ABS_NM = 0.02, 0.03    # docs/accuracy.md: steady torque within 2 % + 0.03 N·m
DEPTH_REL = 0.05                          # docs/accuracy.md: depths within 5 %


def _scenario_tools():
    from millsense.sim.machine import TOOL_P
    from millsense.sim.scenarios import SCENARIOS

    return SCENARIOS["fig5"], TOOL_P


def _fig5_settings(tmp, name: str, method: str, tool, cf, tools_toml: str = ""):
    """What an operator writes for fig5's cut (simcase.settings_for), with the `[tool]` given, plus tables."""
    sc, _ = _scenario_tools()
    m = sc.material
    dyn = method == "dynamometer"
    text = configs.toml_text(
        filter_cutoff_hz=sc.filter_cutoff_hz, tool=tool, cf=cf,
        material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp), mode=sc.mode, method=method,
        extra_channels=simcase.D_CHANNELS.format(ix_offset=0.0) if dyn else "",
        feed_force=simcase.FEED_FORCE if dyn else "",
        feed_mm_min=None if dyn else sc.feed_segments[0][1],
        axial_depth_mm=None if dyn else max(d for _, d in sc.axial_profile),
    )
    path = tmp / f"{name}-{method}.toml"
    path.write_text(text + tools_toml)
    return load_config(path)


def _replay(capture, settings, tool_at=None) -> list[dict]:
    est, out = None, []
    for desc, block in iter_capture_blocks(capture):
        if est is None:
            est = Estimator(settings, desc, desc.sample_rate_hz)
            est.tool_at = tool_at
        out += est.process(block).estimates
    return out


@pytest.fixture(scope="module")
def fig5(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tools-fig5")
    cap, truth = simcase.capture(tmp, "fig5", seed=11)
    return tmp, cap, simcase.read_truth(truth)


@pytest.mark.parametrize("method", ["torque-only", "dynamometer"])
def test_fig5_with_its_cutter_as_tool_7_reads_as_if_it_were_the_tool(fig5, method):
    tmp, cap, truth = fig5
    sc, tool_p = _scenario_tools()
    fig5_tool = (sc.tool.diameter_mm, sc.tool.flutes)
    # [tool] is [P]'s cutter with a fixed C_f; tool 7 is fig5's with C_f from the model: both differ
    tools_toml = (f"\n[tools.{TOOL_NUMBER}]\ndiameter_mm = {fig5_tool[0]}\nflutes = {fig5_tool[1]}\n"
                  f'cf = "model"\n')
    by_number = _fig5_settings(tmp, "by-number", method, (tool_p.diameter_mm, tool_p.flutes), 1.075, tools_toml)
    as_default = _fig5_settings(tmp, "as-default", method, fig5_tool, "model")
    p_only = _fig5_settings(tmp, "p-only", method, (tool_p.diameter_mm, tool_p.flutes), 1.075)
    assert set(by_number.tools) == {TOOL_NUMBER}

    with_7 = _replay(cap, by_number, lambda seq: TOOL_NUMBER)
    reference = _replay(cap, as_default)
    assert len(with_7) >= 250
    assert with_7 == reference                                # number for number, every field

    # the truth: the settled revolutions of the cut (simcase.settled)
    ok = simcase.settled(truth, "fig5")
    pairs = [(e, t) for e, t in simcase.match(with_7, truth, 1) if t["rev"] in ok and e["valid"]]
    assert len(pairs) >= 30
    radius_m = sc.tool.radius_mm * 1e-3
    for e, t in pairs:
        assert e["depth_status"] == "ok", (e, t)
        assert e["radial_depth_mm"] == pytest.approx(t["radial_depth_mm"], rel=DEPTH_REL), (e, t)
        assert e["axial_depth_mm"] == pytest.approx(t["axial_depth_mm"], rel=DEPTH_REL), (e, t)
        assert e["feed_per_tooth_mm"] == pytest.approx(t["feed_per_tooth_mm"], rel=0.01), (e, t)
        bound_n = (TORQUE_REL * abs(t["torque_nm"]) + TORQUE_ABS_NM) / radius_m
        assert abs(e["force_tangential_n"] - t["force_tangential_n"]) <= bound_n, (e, t)

    # with [P]'s cutter the same torque is another force: the check above tells the tools apart
    wrong = {e["seq_end"]: e for e in _replay(cap, p_only)}
    assert all(abs(wrong[e["seq_end"]]["force_tangential_n"] - t["force_tangential_n"])
               > (TORQUE_REL * abs(t["torque_nm"]) + TORQUE_ABS_NM) / radius_m for e, t in pairs)

    # no tool known, or one the configuration does not list: [tool], exactly as without [tools.7]
    only_default = _replay(cap, p_only)
    assert _replay(cap, by_number) == only_default
    assert _replay(cap, by_number, lambda seq: UNLISTED) == only_default
    assert _replay(cap, by_number, lambda seq: None) == only_default


# ------------------------------------------------------------------------------------------- (b)
SYNTH_TOOLS = """
[tools.3]
diameter_mm = 10.0
flutes = 3
flute_length_mm = 40.0   # the synthetic torque is a 36 mm deep slot for this cutter: a long-series one

[tools.5]
diameter_mm = 16.0
flutes = 4
cf = 1.2
"""
CHANGE_SEQ = 2500          # the tool change falls inside the one large block below


def _synthetic_run(settings, tool_at):
    """A steady slot at 600 rpm: 1000 samples in small blocks, then one block of 3000 samples."""
    raw = synthetic.counts(synthetic.Machine(), 4000)
    blocks = [SampleBlock(a, a, raw[a : a + 10], 0, False) for a in range(0, 1000, 10)]
    blocks.append(SampleBlock(1000, 1000, raw[1000:], 0, False))
    est = Estimator(settings, synthetic.descriptor(), 1000)
    est.tool_at = tool_at
    out = []
    for b in blocks[:-1]:
        out += est.process(b).estimates
    last = est.process(blocks[-1]).estimates
    return out, last


def test_a_block_that_changes_tool_uses_each_tool_for_its_own_revolutions(tmp_path):
    path = tmp_path / "synthetic.toml"
    path.write_text(configs.toml_text() + SYNTH_TOOLS)
    settings = load_config(path)

    def changing(seq):
        return 3 if seq < CHANGE_SEQ else 5

    head, block = _synthetic_run(settings, changing)
    before = [e for e in block if e["seq_end"] < CHANGE_SEQ]
    after = [e for e in block if e["seq_end"] >= CHANGE_SEQ]
    assert len(before) >= 10 and len(after) >= 10          # one block, both tools
    assert all(e["valid"] and e["cutting"] for e in block)

    # number for number as a run with that tool throughout
    head_3, block_3 = _synthetic_run(settings, lambda seq: 3)
    _, block_5 = _synthetic_run(settings, lambda seq: 5)
    assert head == head_3
    assert before == block_3[: len(before)]
    assert after == block_5[len(before):]

    # and the physics of each tool, from its table: F_t = T/R (eq. 16), t_c = f/(N·n), slot: d_r = D
    feed_mm_min = settings.cut.feed_mm_min
    for revs, number in ((before, 3), (after, 5)):
        tool = settings.tools[number]
        cf = settings.tool.cf if tool.cf is None else tool.cf
        torque = np.array([e["torque_nm"] for e in revs])
        rpm = np.array([e["spindle_rpm"] for e in revs])
        tangential = np.array([e["force_tangential_n"] for e in revs])
        np.testing.assert_allclose(tangential, torque / (tool.diameter_mm / 2e3), rtol=1e-12)
        np.testing.assert_allclose([e["force_n"] for e in revs], cf * tangential, rtol=1e-12)
        np.testing.assert_allclose([e["feed_per_tooth_mm"] for e in revs], feed_mm_min / (tool.flutes * rpm),
                                   rtol=1e-12)
        assert all(e["depth_status"] == "ok" for e in revs)
        np.testing.assert_allclose([e["radial_depth_mm"] for e in revs], tool.diameter_mm, rtol=1e-12)
