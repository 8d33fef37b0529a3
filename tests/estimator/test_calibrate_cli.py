"""`millsense calibrate` as a real subprocess on simulated air cuts."""

from __future__ import annotations

import subprocess
import tomllib

import pytest

from . import configs, simcase

# [P] Table 2: friction referred to the spindle, per gear (the simulated machine uses it)
TABLE2 = {"low-speed": (2.6629, 0.0400), "high-speed": (1.6160, 0.0022)}


def _run(cmd, timeout=150):
    """A CLI subprocess: (exit code, stdout, stderr); killed after `timeout` s (test_calibrate_material too)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, out, err


@pytest.fixture(scope="module")
def aircuts(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("aircut")
    return [simcase.capture(tmp, name, seed=7)[0] for name in ("aircut-low", "aircut-high")]


def test_calibration_recovers_table2_friction(tmp_path, aircuts, millsense_cmd):
    cfg = tmp_path / "mill.toml"
    # start from a wrong friction: the fit must not depend on it
    cfg.write_text(configs.toml_text(gears=configs.GEARS.replace("2.6629", "1.0").replace("1.6160", "0.5")))
    out_file = tmp_path / "cal.toml"
    code, out, err = _run([*millsense_cmd, "calibrate", *map(str, aircuts), "--config", str(cfg), "--out", str(out_file)])
    assert code == 0, err
    assert "R2" in out and "residuals" in out
    cal = tomllib.loads(out_file.read_text())
    fitted = {g["name"]: g for g in cal["gears"]}
    assert set(fitted) == set(TABLE2)
    for name, (t_f, b) in TABLE2.items():
        g = fitted[name]
        assert g["friction_torque_nm"] == pytest.approx(t_f, rel=0.02), name
        assert g["viscous_nms"] == pytest.approx(b, rel=0.02), name
        assert g["samples"] >= 20 and g["r2"] > 0.9
        # J from the run-ups between the plateaus: the plant's rotor·ratio² + spindle (machine data)
        assert g["inertia_kgm2"] == pytest.approx(configs.PLANT_INERTIA_KGM2[name], rel=0.05), name
    assert "J =" in out
    # the file is a calibration the daemon loads: J reaches the gears
    from millsense.daemon.config.load import load_config

    cfg.write_text(cfg.read_text().replace("machine =", f'calibration = "{out_file}"\nmachine =', 1))
    assert {g.name: g.inertia_kgm2 for g in load_config(cfg).gears} == {
        name: fitted[name]["inertia_kgm2"] for name in TABLE2}


def _steady_air(tmp_path, rpms):
    """Air cuts each at one held speed (no run-up between): `aircut-low` cut into separate captures."""
    import dataclasses

    from millsense.sim import write_capture
    from millsense.sim.scenarios import get_scenario

    caps = []
    for rpm in rpms:
        steady = dataclasses.replace(get_scenario("aircut-low"), name=f"air-{rpm:.0f}", duration_s=4.0,
                                     spindle_schedule=((0.0, rpm),))
        caps.append(tmp_path / f"air-{rpm:.0f}.bin")
        if not caps[-1].exists():
            write_capture(steady, str(caps[-1]), seed=7)
    return caps


def _refused_and_nothing_written(code, out, err, out_file):
    assert code == 1, out + err
    assert "refused: gear " in err and "nothing written" in err and "Traceback" not in err
    assert not out_file.exists()
    assert not list(out_file.parent.glob("*.tmp")), "a refusal leaves no temporary file either"


def test_no_speed_change_friction_written_without_inertia(tmp_path, millsense_cmd):
    """Three steady air cuts (300, 600, 900 rpm, no run-up between): friction can be fitted, J cannot.

    The friction is written and J left out (the config's own value stays), with a warning that says
    which capture would fit it: refusing the whole file would throw away a good friction fit.
    """
    caps = _steady_air(tmp_path, (300.0, 600.0, 900.0))
    cfg = tmp_path / "mill.toml"
    cfg.write_text(configs.toml_text())
    out_file = tmp_path / "cal.toml"
    code, out, err = _run([*millsense_cmd, "calibrate", *map(str, caps), "--config", str(cfg), "--out", str(out_file)])
    assert code == 0, out + err
    assert "warning" in err and "inertia not fitted" in err and "aircut-low" in err and "Traceback" not in err
    assert "T_f'" in out
    written = tomllib.loads(out_file.read_text())
    assert written["gears"] and all("inertia_kgm2" not in g and g["friction_torque_nm"] > 0 for g in written["gears"])
    cfg.write_text(cfg.read_text().replace("machine =", f'calibration = "{out_file}"\nmachine =', 1))
    from millsense.daemon.config.load import load_config

    assert load_config(cfg).gears  # the file loads


def test_two_speeds_are_refused(tmp_path, millsense_cmd):
    """A line through two speeds has no check on it: issue 12 item 4 wants three per gear."""
    caps = _steady_air(tmp_path, (300.0, 600.0))
    cfg = tmp_path / "mill.toml"
    cfg.write_text(configs.toml_text())
    out_file = tmp_path / "cal.toml"
    code, out, err = _run([*millsense_cmd, "calibrate", *map(str, caps), "--config", str(cfg), "--out", str(out_file)])
    _refused_and_nothing_written(code, out, err, out_file)
    assert "gear low-speed: only 2 steady speeds (300, 600 rpm)" in err
    assert ">= 3 speeds across 300-900 rpm" in err


def test_cutting_capture_at_one_speed_is_refused(tmp_path, millsense_cmd):
    """Issue 12 item 4: a cut at one speed fitted T_f' = 3994 N.m, B' = -63, wrote it and exited 0."""
    cut, _ = simcase.capture(tmp_path, "step", seed=7)
    cfg = tmp_path / "mill.toml"
    cfg.write_text(configs.toml_text())
    out_file = tmp_path / "cal.toml"
    code, out, err = _run([*millsense_cmd, "calibrate", str(cut), "--config", str(cfg), "--out", str(out_file)])
    _refused_and_nothing_written(code, out, err, out_file)
    assert "gear low-speed: only 1 steady speed (600 rpm)" in err
    assert "gear low-speed: cutting found in an air capture" in err and "600 rpm" in err
    assert ">= 3 speeds across 300-900 rpm" in err


def test_air_captures_with_a_cut_among_them_are_refused(tmp_path, aircuts, millsense_cmd):
    """Good air cuts of both gears plus a constant slot at 1500 rpm given as air: the high gear has
    enough speeds, but the slot's revolutions sit far above the air revolutions of its approach."""
    cut, _ = simcase.capture(tmp_path, "speed-1500", seed=7)
    cfg = tmp_path / "mill.toml"
    cfg.write_text(configs.toml_text())
    out_file = tmp_path / "cal.toml"
    code, out, err = _run([*millsense_cmd, "calibrate", *map(str, aircuts), str(cut), "--config", str(cfg),
                           "--out", str(out_file)])
    _refused_and_nothing_written(code, out, err, out_file)
    assert "gear high-speed: cutting found in an air capture" in err and "1500 rpm" in err
    assert "gear low-speed" not in err   # the low gear's air cut is fine: only the gear at fault is named


def test_calibration_without_filter_correction_is_biased(tmp_path, aircuts, millsense_cmd):
    """Telling the fit there is no anti-alias filter (there is, at 200 Hz) must spoil B' of the
    low gear, whose f_e reaches 144 Hz: the gain |H(f_e)|^2 cannot be absorbed by friction."""
    cfg = tmp_path / "nofilter.toml"
    cfg.write_text(configs.toml_text(filter_cutoff_hz=0))
    out_file = tmp_path / "cal.toml"
    code, _, err = _run([*millsense_cmd, "calibrate", *map(str, aircuts), "--config", str(cfg), "--out", str(out_file)])
    assert code == 0, err
    low = {g["name"]: g for g in tomllib.loads(out_file.read_text())["gears"]}["low-speed"]
    assert abs(low["viscous_nms"] / TABLE2["low-speed"][1] - 1.0) > 0.05


def test_bad_config_exits_78_and_names_the_key(tmp_path, aircuts, millsense_cmd):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(configs.toml_text().replace("[tool]\n", "[tool]\nradius_mm = 3\n"))
    code, out, err = _run([*millsense_cmd, "calibrate", str(aircuts[0]), "--config", str(cfg), "--out", str(tmp_path / "x.toml")])
    assert code == 78
    assert "radius_mm" in err and "Traceback" not in err
    assert not (tmp_path / "x.toml").exists()


def test_missing_capture_is_a_clear_error(tmp_path, millsense_cmd):
    cfg = tmp_path / "mill.toml"
    cfg.write_text(configs.toml_text())
    code, _, err = _run([*millsense_cmd, "calibrate", str(tmp_path / "nope.bin"), "--config", str(cfg), "--out", str(tmp_path / "x.toml")])
    assert code == 1 and "nope.bin" in err and "Traceback" not in err


def test_dynamometer_calibration_fits_cf(tmp_path, millsense_cmd):
    """Air cuts with force channels plus a [D] cut: friction from the air, C_f from the cut."""
    air, _ = simcase.capture(tmp_path, "aircut-low", seed=7, extra_channels=True)
    cut, truth_path = simcase.capture(tmp_path, "fig6", seed=7)
    radius_m = 8.0e-3
    truth = [t for t in simcase.read_truth(truth_path) if t["steady"] and t["cutting"] and t["torque_nm"] > 1.0]
    cf_truth = sum(t["force_n"] * radius_m / t["torque_nm"] for t in truth) / len(truth)
    cfg = tmp_path / "dyn.toml"
    cfg.write_text(configs.toml_text(tool=(16.0, 4), mode="down", feed_mm_min=None,
                                     extra_channels=simcase.D_CHANNELS.format(ix_offset=0.0)))
    out_file = tmp_path / "cal.toml"
    code, out, err = _run([*millsense_cmd, "calibrate", str(air), str(cut), "--config", str(cfg),
                           "--out", str(out_file), "--dynamometer"])
    assert code == 0, err
    cal = tomllib.loads(out_file.read_text())
    assert cal["tool"]["cf"] == pytest.approx(cf_truth, rel=0.02)
    low = {g["name"]: g for g in cal["gears"]}["low-speed"]
    assert low["friction_torque_nm"] == pytest.approx(TABLE2["low-speed"][0], rel=0.02)
    assert low["viscous_nms"] == pytest.approx(TABLE2["low-speed"][1], rel=0.02)
