"""`millsense calibrate --material` as a real subprocess on simulated test cuts whose material is known.

The plant cuts with the power laws of [D] eq. (9) (sim/machine.py MATERIALS); the configuration given
to `calibrate` carries another material (the SB40 defaults of [D] Table 2), so nothing but the capture
can lead the fit to the plant's. Bounds from docs/accuracy.md's steady torque budget, 2 % + 0.03 N·m,
carried to K_s (eq. 7 is linear in the torque): each feed level's K_s within e = 2 % + 0.03 N·m/T; the
exponent p, the slope through levels whose chips span a ratio ρ, within 2·e/ln ρ.
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib

import pytest

from . import configs, simcase
from .test_calibrate_cli import _run as run_cli

TORQUE_REL = 0.02
TORQUE_ABS_NM = 0.03
FEED_CHANNEL = "[channels.fx_rate]\nscale = 0.1\n"
RPM = 1800.0                       # high-speed gear: 60 revolutions a second, short captures
FEEDS_PER_TOOTH_MM = (0.1, 0.2, 0.3)
LEVEL_MM = 15.0                    # of travel at each feed, after the first's entry


def _run(cmd, timeout=180):
    return run_cli(cmd, timeout)   # the calibrate CLI's subprocess runner (test_calibrate_cli.py)


def _test_cut(name, *, material="SS41", depth_mm=2.0, feeds=FEEDS_PER_TOOTH_MM):
    """A slot of constant depth on the [P] φ20 2-flute tool, the feed per tooth stepping through `feeds`."""
    from millsense.sim.machine import MATERIALS
    from millsense.sim.scenarios import SCENARIOS

    base = SCENARIOS["speed-1500"]
    rate = [fz * base.tool.flutes * RPM for fz in feeds]
    first = base.tool.radius_mm + LEVEL_MM                       # entry plus a level in full engagement
    edges = [first + LEVEL_MM * i for i in range(len(feeds))]
    segments = ((-math.inf, rate[0]), *((edges[i], rate[i + 1]) for i in range(len(feeds) - 1)))
    part_end = edges[-1] + base.tool.radius_mm                 # the last level in full engagement to its end
    start = -(base.tool.radius_mm + 5.0)
    travel_s = sum((min(e, part_end + base.tool.radius_mm) - max(s, start)) / (f / 60.0)
                   for (s, f), e in zip(((start, rate[0]), *((edges[i], rate[i + 1]) for i in range(len(feeds) - 1))),
                                        [*edges[:-1], part_end + base.tool.radius_mm]))
    return dataclasses.replace(base, name=name, material=MATERIALS[material], spindle_schedule=((0.0, RPM),),
                               feed_segments=segments, axial_profile=((0.0, depth_mm), (part_end, depth_mm)),
                               duration_s=round(travel_s + 0.5, 1))


def _capture(scenario):
    from millsense.sim import write_capture
    from tests import captures

    def build(d):
        write_capture(scenario, str(d / "capture.bin"), str(d / "truth.jsonl"), seed=5, extra_channels=True)

    d = captures.shared(f"calibrate-material {scenario.name} {scenario.material.name} {scenario.axial_profile}", build)
    return d / "capture.bin", d / "truth.jsonl"


def _config(tmp_path, *, feed_mm_min=None, channels=FEED_CHANNEL):
    cfg = tmp_path / "mill.toml"
    cfg.write_text(configs.toml_text(tool=(20.0, 2), feed_mm_min=feed_mm_min, mode="slot",
                                     material=(646.08, -0.4362, 0.2201, -0.2667, 0.1244, 0.1702),   # not the plant's
                                     gears=configs.GEARS_WITH_INERTIA, extra_channels=channels))
    return cfg


def _calibrate(millsense_cmd, capture, cfg, out, *extra):
    return _run([*millsense_cmd, "calibrate", str(capture), "--material", "--ae-mm", "20", "--ap-mm", *extra,
                 "--config", str(cfg), "--out", str(out)])


def _plant_ks(material, chip_mm):
    return material.ks * chip_mm ** material.ks_exp


def _steady_torque_nm(truth_path, fz):
    torques = [t["torque_nm"] for t in simcase.read_truth(truth_path)
               if t["steady"] and t["cutting"] and abs(t["feed_per_tooth_mm"] - fz) < 1e-3 * fz]
    return sorted(torques)[len(torques) // 2]


def test_several_feeds_fit_the_plants_material(tmp_path, millsense_cmd):
    scenario = _test_cut("feeds-1800")
    cap, truth = _capture(scenario)
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path), out, "2")
    assert code == 0, stdout + err
    assert "3 feed levels" in stdout
    fitted = tomllib.loads(out.read_text())["material"]
    plant = scenario.material
    worst_e = 0.0
    for fz in FEEDS_PER_TOOTH_MM:
        chip = 2.0 * fz / math.pi                                   # [D] eq. 8, a slot
        e = TORQUE_REL + TORQUE_ABS_NM / _steady_torque_nm(truth, fz)
        worst_e = max(worst_e, e)
        assert fitted["ks"] * chip ** fitted["ks_exp"] == pytest.approx(_plant_ks(plant, chip), rel=e), fz
    span = FEEDS_PER_TOOTH_MM[-1] / FEEDS_PER_TOOTH_MM[0]
    assert fitted["ks_exp"] == pytest.approx(plant.ks_exp, abs=2.0 * worst_e / math.log(span))
    # r1, r2 are the configuration's: the torque does not see them
    assert (fitted["r1"], fitted["r1_exp"], fitted["r2"], fitted["r2_exp"]) == (0.2201, -0.2667, 0.1244, 0.1702)
    # the file's [material] is a configuration's
    from millsense.daemon.config.load import load_config

    cfg = tmp_path / "mill.toml"
    text = cfg.read_text()
    cfg.write_text(text[: text.index("[material]")] + out.read_text() + text[text.index("[cut]"):])
    assert load_config(cfg).material.ks == fitted["ks"]


def test_one_feed_fits_k_with_the_nearest_iso_groups_exponent(tmp_path, millsense_cmd):
    """`millsense sim --scenario speed-1500 --capture F`: one feed (t_c 0.15 mm), SM45C in a 2 mm slot."""
    from millsense.daemon.physics.materials import ISO_GROUPS
    from millsense.sim.scenarios import SCENARIOS

    cap, truth = tmp_path / "speed.bin", tmp_path / "speed.truth"
    code, _, err = _run([*millsense_cmd, "sim", "--scenario", "speed-1500", "--capture", str(cap), "--truth", str(truth),
                         "--seed", "5"])
    assert code == 0, err
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path, feed_mm_min=0.15 * 2 * 1500, channels=""),
                                   out, "2")
    assert code == 0, stdout + err
    fitted = tomllib.loads(out.read_text())["material"]
    letter = re.search(r"ISO group (\w)'s", stdout).group(1)
    assert fitted["ks_exp"] == ISO_GROUPS[letter].material.ks_exp
    assert f"ISO group {letter}" in out.read_text()
    chip = 2.0 * 0.15 / math.pi
    e = TORQUE_REL + TORQUE_ABS_NM / _steady_torque_nm(truth, 0.15)
    plant = SCENARIOS["speed-1500"].material
    assert fitted["ks"] * chip ** fitted["ks_exp"] == pytest.approx(_plant_ks(plant, chip), rel=e)


def _refused(code, stdout, err, out):
    assert code == 1, stdout + err
    assert "refused: material: " in err and "nothing written" in err and "Traceback" not in err
    assert not out.exists()


def test_an_air_cut_is_refused(tmp_path, millsense_cmd):
    cap, _ = simcase.capture(tmp_path, "aircut-high", seed=7)
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path, feed_mm_min=300.0, channels=""), out, "2")
    _refused(code, stdout, err, out)
    assert "no feed level with 8 or more steady cutting revolutions" in err


def test_a_shallow_cut_near_the_noise_is_refused(tmp_path, millsense_cmd):
    scenario = _test_cut("shallow-1800", depth_mm=0.6, feeds=(0.1,))
    cap, truth = _capture(scenario)
    assert 0.5 < _steady_torque_nm(truth, 0.1) < 1.5            # cutting (depth.min_torque_nm), under the floor
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path), out, "0.6")
    _refused(code, stdout, err, out)
    assert "too near the noise" in err


def test_too_few_steady_revolutions_are_refused(tmp_path, millsense_cmd):
    """The capture ends a few revolutions after the tool is in full engagement."""
    cap = tmp_path / "short.bin"
    code, _, err = _run([*millsense_cmd, "sim", "--scenario", "speed-1500", "--capture", str(cap), "--seed", "5",
                         "--duration-s", "2.05"])
    assert code == 0, err
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path, feed_mm_min=450.0, channels=""), out, "2")
    _refused(code, stdout, err, out)
    assert re.search(r"f_z 0\.1500 mm: [1-7] steady revolutions, fewer than 8", stdout), stdout
    assert "no feed level with 8 or more steady cutting revolutions" in err


@pytest.mark.parametrize("extra, says", [
    ([], "needs the test cut's --ae-mm and --ap-mm"),
    (["--ae-mm", "12", "--ap-mm", "2"], "a slot's radial depth is the tool's diameter"),
    (["--ae-mm", "25", "--ap-mm", "2", "--mode", "down"], "at most the tool's diameter"),
])
def test_a_test_cut_not_described_is_a_usage_error(tmp_path, millsense_cmd, extra, says):
    out = tmp_path / "material.toml"
    code, stdout, err = _run([*millsense_cmd, "calibrate", str(tmp_path / "none.bin"), "--material", *extra,
                              "--config", str(_config(tmp_path, feed_mm_min=300.0, channels="")), "--out", str(out)])
    assert code == 2 and says in err and "Traceback" not in err, stdout + err
    assert not out.exists()


def test_a_cut_without_a_feed_per_tooth_is_refused_saying_so(tmp_path, millsense_cmd):
    """No feed-rate channel and no `[cut] feed_mm_min`: K_s cannot be had from the torque (eq. 7 needs t_c)."""
    cap, _ = _capture(_test_cut("feeds-1800"))
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path, feed_mm_min=None, channels=""), out, "2")
    _refused(code, stdout, err, out)
    assert "but no feed per tooth" in err


def test_fit_r1_without_the_feed_drive_force_is_refused(tmp_path, millsense_cmd):
    """`--fit-r1` needs the feed-drive force ([feed_force]): the feed-rate channel alone gives no r₁."""
    cap, _ = _capture(_test_cut("feeds-1800"))
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path), out, "2", "--fit-r1")
    _refused(code, stdout, err, out)
    assert "--fit-r1 without the feed-drive force" in err
    # without --fit-r1 the same capture fits K_s and says why r1 is the configuration's
    code, stdout, err = _calibrate(millsense_cmd, cap, _config(tmp_path), out, "2")
    assert code == 0 and "r1, r1_exp: the configuration's (no feed-drive force" in stdout, stdout + err


def test_the_configured_edge_coefficients_are_kept_not_fitted(tmp_path, millsense_cmd):
    """The fitted law is the whole average law whatever its split; the torque cannot split it (physics.md §5b),
    so the configuration's edge_t_n_mm / edge_r_n_mm are written back as they were, and the output says so."""
    cap, _ = _capture(_test_cut("feeds-1800"))
    cfg = _config(tmp_path)
    cfg.write_text(cfg.read_text().replace("\n[cut]", "edge_t_n_mm = 25.0\nedge_r_n_mm = 35.0\n\n[cut]", 1))
    out = tmp_path / "material.toml"
    code, stdout, err = _calibrate(millsense_cmd, cap, cfg, out, "2")
    assert code == 0, stdout + err
    assert "edge term (edge_t_n_mm, edge_r_n_mm): not fitted" in stdout
    written = tomllib.loads(out.read_text())["material"]
    assert (written["edge_t_n_mm"], written["edge_r_n_mm"]) == (25.0, 35.0)
