"""Issue 12 item 6: a configured feed that disagrees with a measured one is said, once, and not used.

`config/depth-of-cut-d.toml` carried fig5's feed (250 mm/min); on fig6 (500 mm/min) its depths read
d_r -18 % and d_a +73 % with no warning. With a feed-rate channel the measured feed is used; the daemon
now also logs `feed.mismatch` with both values, once, and again only after the two have agreed a while.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from millsense.daemon.pipeline.per_revolution import FEED_AGREE_REVS, FEED_MISMATCH_REL, FeedCheck

from . import configs, simcase


def _d_config(feed_mm_min, scenario="fig6"):
    """[D]'s set-up (tool, SB40, down milling), feed-rate channel fx_rate, configured feed as given."""
    from millsense.sim.scenarios import get_scenario

    sc = get_scenario(scenario)
    m = sc.material
    return configs.toml_text(tool=(sc.tool.diameter_mm, sc.tool.flutes), mode=sc.mode, cf="model",
                             material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp), feed_mm_min=feed_mm_min,
                             extra_channels=simcase.D_CHANNELS.format(ix_offset=0.0), feed_force=simcase.FEED_FORCE,
                             method="feed-drive").replace('scenario = "step"', f'scenario = "{scenario}"')


def test_warns_once_then_rearms_after_agreeing_a_while():
    check = FeedCheck(250.0)
    for _ in range(5):
        check.update(500.0, True)
    (event,) = check.take()
    assert event[0] == "feed.mismatch"
    assert event[1]["configured_mm_min"] == 250.0 and event[1]["measured_mm_min"] == 500.0
    assert event[1]["off_pct"] == 100.0
    # agreeing for less than FEED_AGREE_REVS, then off again: still the same episode, no new warning
    for _ in range(FEED_AGREE_REVS - 2):
        check.update(251.0, True)
    check.update(500.0, True)
    check.update(500.0, True)
    assert check.take() == []
    for _ in range(FEED_AGREE_REVS + 1):
        check.update(250.0, True)
    check.update(400.0, True)   # the first steady revolution of the new feed only sets the reference
    check.update(400.0, True)
    assert [e for e, _ in check.take()] == ["feed.mismatch"]


def test_only_steady_cutting_revolutions_are_judged():
    off = 250.0 * (1 + 2 * FEED_MISMATCH_REL)
    close = 250.0 * (1 + 0.5 * FEED_MISMATCH_REL)
    check = FeedCheck(250.0)
    for _ in range(10):
        check.update(8000.0, False)      # a rapid in air: not the cutting feed
        check.update(close, True)        # within the threshold
    for feed in (300.0, 350.0, 400.0):   # the feed changing under the revolution: its mean is no feed
        check.update(feed, True)
    assert check.take() == []
    check.update(off, True)
    check.update(off, True)
    assert [e for e, _ in check.take()] == ["feed.mismatch"]
    assert FeedCheck(None).take() == [] and FeedCheck(250.0).take() == []


def test_a_feed_held_at_zero_override_is_not_judged():
    """The operator turns the feed override to 0 % with the tool in the cut: the axes stop, the spindle turns
    on (rubbing: torque over the cutting threshold) and the feed-rate channel reads its noise. Zero
    configured feed is no feed to compare with. Before, the warning's `off_pct` divided by it: a
    ZeroDivisionError in the estimator thread, found by tests/estimator/test_one_revolution.py."""
    check = FeedCheck(250.0)
    for _ in range(5):
        check.update(0.4, True, 0.0)
    assert check.take() == [] and not check.warned
    for _ in range(2):                   # the knob back to 100 %: judged again
        check.update(500.0, True, 100.0)
    assert [e for e, _ in check.take()] == ["feed.mismatch"]


@pytest.fixture(scope="module")
def fig6(tmp_path_factory):
    return simcase.capture(tmp_path_factory.mktemp("fig6"), "fig6", seed=3)


def test_fig6_with_fig5s_feed_warns_and_uses_the_measured_feed(tmp_path, fig6):
    from millsense.daemon.config.load import load_config

    cap, truth_path = fig6
    path = tmp_path / "d.toml"
    path.write_text(_d_config(250))
    estimates, est = simcase.run(cap, load_config(path))
    (event,) = est.physics.feed_check.take()
    assert event[0] == "feed.mismatch" and event[1]["configured_mm_min"] == 250
    from millsense.sim.scenarios import get_scenario

    programmed = get_scenario("fig6").feed_segments[0][1]
    assert event[1]["measured_mm_min"] == pytest.approx(programmed, rel=0.01)
    # the feed per tooth is the measured one: the truth's t_c, not the configured 250/(4·600)
    pairs = [(e, t) for e, t in simcase.match(estimates, simcase.read_truth(truth_path)) if t["cutting"] and t["steady"]]
    assert len(pairs) > 50
    for e, t in pairs:
        assert e["feed_per_tooth_mm"] == pytest.approx(t["feed_per_tooth_mm"], rel=0.01)


def test_matching_feed_says_nothing(tmp_path, fig6):
    from millsense.daemon.config.load import load_config

    cap, _ = fig6
    path = tmp_path / "d.toml"
    path.write_text(_d_config(500))
    _, est = simcase.run(cap, load_config(path))
    assert est.physics.feed_check.take() == []


@pytest.mark.slow
def test_daemon_logs_feed_mismatch_once(tmp_path):
    """`millsense run` on the simulated fig6 with fig5's feed configured: one `feed.mismatch` log line."""
    path = tmp_path / "d.toml"
    path.write_text('machine = "feed-01"\n' + _d_config(250).replace('machine = "test-mill"', "") +
                    '\n[interlock]\nenabled = false\n\n[zenoh]\nmode = "peer"\nlisten = []\nconnect = []\n'
                    'multicast_scouting = false\n\n[log]\nformat = "json"\n')
    proc = subprocess.Popen([sys.executable, "-m", "millsense.daemon", "run", "--config", str(path), "--seconds", "12"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    events = [json.loads(ln) for ln in (out + err).splitlines() if ln.startswith("{")]
    mismatch = [e for e in events if e.get("event") == "feed.mismatch"]
    assert len(mismatch) == 1, [e.get("event") for e in events]
    assert mismatch[0]["level"] == "warning" and mismatch[0]["configured_mm_min"] == 250
    assert mismatch[0]["measured_mm_min"] == pytest.approx(500, rel=0.01)


def test_each_example_config_names_the_scenario_it_fits_and_fits_it():
    """Every config/*.toml says which `millsense sim --scenario` it fits; its tool, material, mode and
    feed are that scenario's (read from the TOML itself: some examples need a token file to load)."""
    import re
    import tomllib
    from pathlib import Path

    from millsense.sim import PROGRAMS
    from millsense.sim.scenarios import get_scenario

    examples = sorted((Path(__file__).resolve().parents[2] / "config").glob("*.toml"))
    assert examples
    for path in examples:
        text = path.read_text()
        named = re.search(r"^# Fits `millsense sim --scenario ([\w-]+)`", text, re.M)
        assert named, f"{path.name}: no 'Fits `millsense sim --scenario NAME`' in its header"
        assert "feed" in text[: text.index("\nmachine")], f"{path.name}: the header says nothing of the feed"
        if named.group(1) in PROGRAMS:
            continue  # a part program's tools, speeds and feeds: tests/sim/test_part_program.py checks them
        sc = get_scenario(named.group(1))
        cfg = tomllib.loads(text)
        assert (cfg["tool"]["diameter_mm"], cfg["tool"]["flutes"]) == (sc.tool.diameter_mm, sc.tool.flutes), path.name
        m = cfg["material"]
        assert (m["ks"], m["ks_exp"], m["r1"], m["r1_exp"], m["r2"], m["r2_exp"]) == pytest.approx(
            (sc.material.ks, sc.material.ks_exp, sc.material.r1, sc.material.r1_exp, sc.material.r2,
             sc.material.r2_exp)), path.name
        assert cfg["cut"]["mode"] == sc.mode, path.name
        assert cfg["cut"]["feed_mm_min"] == pytest.approx(sc.feed_segments[0][1], rel=0.01), path.name
        rpm = sc.spindle_schedule[0][1]
        assert any(g["max_spindle_rpm"] >= rpm for g in cfg["gears"]), path.name
