"""A material calibrated from one test cut: the feed-drive depth and the force, before and after.

`millsense calibrate --material` (a real subprocess) fits the material from one test cut on fig6's φ16 4-flute
tool and DAQ: down milling at a_e 2 mm, a_p 6 mm, the feed per tooth stepping 0.1 / 0.2 / 0.3 mm, with the
feed-drive current (`[feed_force]`): K_s from the torque ([D] eq. 7), and with `--fit-r1` r₁ from the feed-drive
force over the tangential force ([D] eq. 12). It is judged on other cuts of the same material through the real
estimator with `depth.method = "feed-drive"` and `cf = "model"`, over their steady revolutions
(simcase.settled). The configuration before the test cut is what an operator has: the ISO table's steel
(group P, physics/materials.py), its r₁ [D] Table 2's as every group's.

- [D]'s own plant (the law it models), the configuration's r₁ at the top of the published range (0.60 at a
  0.1 mm chip, physics.md §5a), `--fit-r1`: on fig6 (a_e 2 mm, a_p 6 / 11 / 16 mm, f_z 0.208 mm: none of the
  test cut's) the radial depth 39–40 % off and the force 13 % before; after, the radial and axial depth and
  the force each within 3 % on every steady revolution (the issue's bound; the estimator's own spread on this
  cut is 2.3 %, accuracy.md). The fit recovers the plant's k, p, r1, q within 0.6 %.
- The effects plant (sim/cut_effects.py, every effect on: Kienzle's law at the instantaneous chip, edge
  forces, 5 µm runout, tool deflection). The radial depth is judged against the depth the tool engages, the
  program's less its mean bend away from the wall (mean F_y over the tool's stiffness,
  cut_effects.tool_stiffness_n_mm: 0.04–0.25 mm), which is what the forces measure; over each steady stretch
  (one a_e, one a_p: the mean, a revolution's own spread being the estimator's).
  - `--fit-r1`, fig6: before, the radial depth 25 % low, the axial 22 % low; after, both within 3 %. Not
    asserted, because it does not hold: the force with the fitted r₁ (3–4 % low) and other engagements
    (docs/accuracy.md: one r₁ of [D]'s law cannot carry the feed force's and the resultant's weighting).
  - The round steel edge pair in the configuration (no `--fit-r1`): K_s fitted, r₁ and the pair kept, the
    feed-drive depth by the split law (edge.py E5): on fig6, fig7 and fig5 (a_e 2–7 mm, a_p 2–16 mm) the
    radial and axial depth and the force within 3 %, from 19–29 % off without the pair.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib

import pytest

from . import configs, simcase
from .test_calibrate_cli import _run

RPM = 600.0
FEEDS_PER_TOOTH_MM = (0.1, 0.2, 0.3)
LEVEL_MM = 30.0                    # of travel at each feed
TEST_AE_MM, TEST_AP_MM = 2.0, 6.0
BOUND = 0.03                       # the issue's: depth and force within 3 % after one test cut
CHECKED = "fig6"                   # a_e 2 mm, a_p 6/11/16 mm, f_z 0.208 mm: another cut at the test cut's engagement


def _effects():
    from millsense.sim.cut_effects import CutEffects

    return CutEffects()            # every effect on, the defaults the docs state


def _test_cut(effects):
    """fig6's tool, material and DAQ, one engagement, the feed stepping through FEEDS_PER_TOOTH_MM."""
    from millsense.sim.scenarios import SCENARIOS

    base = SCENARIOS[CHECKED]
    rate = [fz * base.tool.flutes * RPM for fz in FEEDS_PER_TOOTH_MM]
    segments = ((-math.inf, rate[0]), *((LEVEL_MM * (i + 1), rate[i + 1]) for i in range(len(rate) - 1)))
    end = LEVEL_MM * len(rate)
    duration_s = sum(LEVEL_MM / (r / 60.0) for r in rate) + 3.0      # the approach and the entry
    return dataclasses.replace(base, name="calibrate-depth-test-cut", spindle_schedule=((0.0, RPM),),
                               radial_profile=((0.0, TEST_AE_MM), (end, TEST_AE_MM)),
                               axial_profile=((0.0, TEST_AP_MM), (end, TEST_AP_MM)), feed_segments=segments,
                               duration_s=round(duration_s, 1), effects=effects)


def _test_cut_capture(effects):
    from millsense.sim import write_capture
    from tests import captures

    scenario = _test_cut(effects)

    def build(d):
        write_capture(scenario, str(d / "capture.bin"), str(d / "truth.jsonl"), seed=3)

    d = captures.shared(f"calibrate-depth {scenario!r}", build)
    return d / "capture.bin"


def _table_material(r1_at_0_1_mm=None):
    """ISO group P's law; `r1_at_0_1_mm`: its r₁ scaled to that value at a 0.1 mm chip, the exponent kept."""
    from millsense.daemon.physics.materials import ISO_GROUPS

    m = ISO_GROUPS["P"].material
    r1 = m.r1 if r1_at_0_1_mm is None else r1_at_0_1_mm / 0.1 ** m.r1_exp
    return (m.ks, m.ks_exp, r1, m.r1_exp, m.r2, m.r2_exp)


def _calibrate(tmp_path, millsense_cmd, capture, configured, *, mode="down", fit_r1=True, expect=None, edge=None):
    """The fitted [material] as a tuple, through the CLI with the test cut's own zeroed feed-current sensor;
    with `expect` (an exit code): (stdout, stderr, whether the file was written) instead."""
    from millsense.daemon.config.load import load_config
    from millsense.sim.scenarios import SCENARIOS

    sc = SCENARIOS[CHECKED]

    def text(offset):
        return configs.toml_text(tool=(sc.tool.diameter_mm, sc.tool.flutes), mode=mode, feed_mm_min=None,
                                 material=configured, filter_cutoff_hz=sc.filter_cutoff_hz,
                                 extra_channels=simcase.D_CHANNELS.format(ix_offset=offset),
                                 feed_force=simcase.FEED_FORCE, edge_n_mm=edge)

    cfg = tmp_path / "test-cut.toml"
    cfg.write_text(text(0.0))
    offset = simcase.zero_feed_current(capture, CHECKED, tmp_path, settings=load_config(cfg))
    cfg.write_text(text(offset))
    out = tmp_path / "material.toml"
    code, stdout, err = _run([*millsense_cmd, "calibrate", str(capture), "--material", "--ae-mm", str(TEST_AE_MM),
                              "--ap-mm", str(TEST_AP_MM), "--mode", mode, *(["--fit-r1"] if fit_r1 else []),
                              "--config", str(cfg), "--out", str(out)], 180)
    if expect is not None:
        assert code == expect, stdout + err
        return stdout, err, out.exists()
    assert code == 0, stdout + err
    assert "3 feed levels" in stdout and ("written (--fit-r1)" in stdout) == fit_r1, stdout
    m = tomllib.loads(out.read_text())["material"]
    assert (edge is None) == ("edge_t_n_mm" not in m) and edge in (None, (m.get("edge_t_n_mm"), m.get("edge_r_n_mm")))
    return tuple(m[k] for k in ("ks", "ks_exp", "r1", "r1_exp", "r2", "r2_exp"))


def _errors(tmp_path, material, effects, cut=CHECKED, edge=None, helix=False):
    """Per steady revolution of `cut`: its stretch (a_e, a_p), and (radial vs engaged, axial, resultant force) − 1.
    `edge`: the material's edge pair; `helix`: `[tool] helix_deg` the tool's (else straight flutes)."""
    from millsense.sim.cut_effects import NONE, tool_stiffness_n_mm
    from millsense.sim.scenarios import SCENARIOS

    sc = SCENARIOS[cut]
    cap, truth_path = simcase.capture(tmp_path, cut, effects=effects)
    offset = simcase.zero_feed_current(cap, cut, tmp_path)
    tool = (sc.tool.diameter_mm, sc.tool.flutes, *([sc.tool.helix_deg] if helix else []))
    settings = simcase.settings_for(cut, tmp_path, method="feed-drive", cf="model", material=material,
                                    ix_offset_counts=offset, edge_n_mm=edge, tool=tool)
    estimates, _ = simcase.run(cap, settings)
    truth = simcase.read_truth(truth_path)
    steady = simcase.settled(truth, cut)
    stiffness_n_mm = tool_stiffness_n_mm(sc.tool, effects) if (effects or NONE).deflection else math.inf
    out = []
    for e, t in simcase.match(estimates, truth):
        if t["rev"] not in steady:
            continue
        assert e["depth_status"] == "ok", (e["depth_status"], t)
        # down milling: F_y < 0 pushes the tool off the wall (cut_effects.effect_forces), engaging less
        engaged_mm = t["radial_depth_mm"] + t["force_y_n"] / stiffness_n_mm
        out.append(((round(t["radial_depth_mm"]), t["axial_depth_mm"]), (e["radial_depth_mm"] / engaged_mm - 1.0,
                                          e["axial_depth_mm"] / t["axial_depth_mm"] - 1.0,
                                          e["force_n"] / t["force_n"] - 1.0)))
    assert len(out) > 100, len(out)          # fig6: three axial depths, about 37 steady revolutions each
    return out


def _worst(errors):
    """Per quantity, the largest |error| of any revolution."""
    return [max(abs(e[i]) for _, e in errors) for i in range(3)]


def _worst_stretch(errors):
    """Per quantity, the largest |mean error| of a steady stretch (one a_e to the mm, one a_p)."""
    stretches = {}
    for key, e in errors:
        stretches.setdefault(key, []).append(e)
    return [max(abs(sum(e[i] for e in v) / len(v)) for v in stretches.values()) for i in range(3)]


@pytest.mark.slow
def test_d_plant_one_test_cut_brings_the_depth_within_3_percent(tmp_path, millsense_cmd):
    configured = _table_material(r1_at_0_1_mm=0.60)
    before = _worst(_errors(tmp_path, configured, None))
    assert before[0] > BOUND, before                  # the configured r₁ puts the radial depth off
    fitted = _calibrate(tmp_path, millsense_cmd, _test_cut_capture(None), configured)
    assert fitted[4:] == configured[4:]               # r2: the configuration's, no channel here sees it
    after = _worst(_errors(tmp_path, fitted, None))
    assert after[0] <= BOUND, ("radial", after, before)
    assert after[1] <= BOUND, ("axial", after, before)
    assert after[2] <= BOUND, ("force", after, before)   # r₁ is the plant's again, so C_f is: 13 % off before


@pytest.mark.slow
def test_effects_plant_one_test_cut_brings_the_depth_within_3_percent(tmp_path, millsense_cmd):
    effects = _effects()
    configured = _table_material()
    before = _worst_stretch(_errors(tmp_path, configured, effects))
    assert before[0] > 0.2 and before[1] > 0.15, before    # the table's law: the depths 20-30 % off
    fitted = _calibrate(tmp_path, millsense_cmd, _test_cut_capture(effects), configured)
    after = _worst_stretch(_errors(tmp_path, fitted, effects))
    assert after[0] <= BOUND, ("radial", after, before)
    assert after[1] <= BOUND, ("axial", after, before)


def test_a_feed_force_no_radial_law_fits_refuses_fit_r1_and_only_it(tmp_path, millsense_cmd):
    """The down test cut declared `--mode up`: eq. 12 at up milling's engagement gives no positive r₁ from
    its feed-drive force. `--fit-r1` is refused, nothing written; without it the K_s fit goes on and says why r₁
    was not fitted (the feed force is not what the fit was asked for)."""
    capture = _test_cut_capture(None)
    stdout, err, written = _calibrate(tmp_path, millsense_cmd, capture, _table_material(), mode="up", expect=1)
    assert "refused: material: r1 = " in err and "not positive" in err and not written, stdout + err
    stdout, err, written = _calibrate(tmp_path, millsense_cmd, capture, _table_material(), mode="up",
                                      fit_r1=False, expect=0)
    assert written and "r1 not fitted: r1 = " in stdout, stdout + err


@pytest.mark.slow
def test_with_edge_coefficients_one_test_cut_brings_depth_and_force_within_3_percent_at_every_engagement(
        tmp_path, millsense_cmd):
    """The configuration carries the round steel pair (materials.STEEL_EDGE_N_MM, 25 / 35 N/mm; the plant's is
    20 / 30) and the tool's helix; `calibrate --material` without `--fit-r1` fits K_s from the test cut and keeps
    r₁ and the pair. With edge coefficients the feed-drive depth solves eq. 12 with the split law (edge.py E5):
    the chip at the instantaneous chip, the edge even over the arc. On fig6, fig7 and fig5 (a_e 2-7 mm, a_p 2-16
    mm) the radial depth (against the engaged one), the axial depth and the force within 3 % over every steady
    stretch; the same material without the pair ([D]'s eq. 12) reads the radial depth 17-29 % off."""
    from millsense.daemon.physics.materials import STEEL_EDGE_N_MM

    effects = _effects()
    fitted = _calibrate(tmp_path, millsense_cmd, _test_cut_capture(effects), _table_material(), fit_r1=False,
                        edge=STEEL_EDGE_N_MM)
    assert fitted[2:] == _table_material()[2:]        # r₁, r₂: the configuration's
    # --fit-r1 is for [D]'s eq. 12: with edge coefficients it is a usage error, nothing written
    apart = tmp_path / "fit-r1"
    apart.mkdir()
    stdout, err, written = _calibrate(apart, millsense_cmd, _test_cut_capture(effects), _table_material(),
                                      edge=STEEL_EDGE_N_MM, expect=2)
    assert "--fit-r1 with edge coefficients" in err and "Traceback" not in err and not written, stdout + err
    for cut in ("fig6", "fig7", "fig5"):
        before = _worst_stretch(_errors(tmp_path, fitted, effects, cut, helix=True))
        assert before[0] > 0.15, (cut, before)
        after = _worst_stretch(_errors(tmp_path, fitted, effects, cut, edge=STEEL_EDGE_N_MM, helix=True))
        assert after[0] <= BOUND, (cut, "radial", after, before)
        assert after[1] <= BOUND, (cut, "axial", after, before)
        assert after[2] <= BOUND, (cut, "force", after, before)
