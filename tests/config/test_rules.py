"""One test per important rule of the configuration model, through the real loader."""

from __future__ import annotations

import re

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config, load_config_text
from tests.config.helpers import base, dumps, write

pytestmark = pytest.mark.quick

SHAPE = re.compile(r"^[^\s:][^:]*: .+\(.+\)$")


def problems_of(doc) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config_text(doc if isinstance(doc, str) else dumps(doc))
    for p in info.value.problems:
        assert SHAPE.match(p), p
    return info.value.problems


def test_the_base_config_is_valid_and_keeps_every_value():
    s = load_config_text(dumps(base()))
    assert s.machine == "mch10-demo"
    assert [g.name for g in s.gears] == ["low-speed", "high-speed"]
    assert s.gears[0].ratio == 4.81 and s.gears[1].friction_torque_nm == 1.6160
    assert s.channels["i_u"].scale == 0.002 and s.channels["sp_enc"].counts_per_rev == 4096


def test_sections_left_out_take_the_documented_defaults():
    doc = base()
    for section in ("material", "cut", "depth", "alarms", "interlock", "zenoh", "log"):
        doc.pop(section)
    s = load_config_text(dumps(doc))
    # [D] Table 2 (SB40)
    assert (s.material.ks, s.material.ks_exp, s.material.r1, s.material.r1_exp, s.material.r2, s.material.r2_exp) == (
        646.08, -0.4362, 0.2201, -0.2667, 0.1244, 0.1702)
    assert s.cut.mode == "slot" and s.depth.method == "auto"
    assert s.alarms.torque_limit_nm is None and s.alarms.crash_power_w is None  # not armed
    assert (s.alarms.hysteresis_pct, s.alarms.breakage_drop_pct) == (10.0, None)  # breakage: not armed unless set
    # Zenoh left out: a peer on every interface, so commands need the token (secure by default)
    assert s.interlock.enabled is False and s.interlock.reset == "token" and s.interlock.on_blind == "hold"
    assert s.zenoh.mode == "peer" and s.zenoh.multicast_scouting is True and s.zenoh.connect == []
    assert s.log.format == "auto"


def test_flutes_must_be_an_integer_at_least_one():
    doc = base()
    doc["tool"]["flutes"] = 0
    assert problems_of(doc) == ["tool.flutes: must be at least 1, not 0 (an integer ≥ 1)"]
    doc["tool"]["flutes"] = 2.5
    assert problems_of(doc) == ["tool.flutes: 2.5 is not an integer (an integer ≥ 1)"]
    doc["tool"]["flutes"] = "2"
    assert problems_of(doc) == ['tool.flutes: "2" is not an integer (an integer ≥ 1)']


def test_gears_must_increase_and_have_unique_names():
    doc = base()
    doc["gears"][1]["max_spindle_rpm"] = 800
    doc["gears"][1]["name"] = "low-speed"
    probs = problems_of(doc)
    assert "gears[1].max_spindle_rpm: 800 is not above the previous gear's 900 (strictly increasing: list gears lowest max_spindle_rpm first)" in probs
    assert any(p.startswith('gears[1].name: "low-speed" is already the name of gears[0]') for p in probs)


def test_at_least_one_gear():
    doc = base()
    doc["gears"] = []
    assert problems_of(doc)[0].startswith("gears: at least 1 [[gears]] table needed, found 0")


def test_unknown_key_is_named_with_a_did_you_mean():
    doc = base()
    doc["daq"]["transprot"] = doc["daq"].pop("transport")
    probs = problems_of(doc)
    assert len(probs) == 2
    assert any(p.startswith('daq.transprot: unknown key, did you mean "transport"? (expected one of: transport, port,') for p in probs)
    assert 'daq.transport: missing (required: one of: "serial", "tcp", "modbus-tcp", "modbus-rtu", "sim")' in probs


def test_unknown_section_at_top_level():
    doc = base()
    doc["alarm"] = {"torque_limit_nm": 3.0}
    assert problems_of(doc) == [
        "alarm: unknown key, did you mean \"alarms\"? (expected one of: machine, calibration, daq, channels, motor, gears, "
        "tool, tools, material, materials, operations, cut, depth, feed_force, alarms, interlock, signals, context, learning, history, zenoh, log, "
        "afc, opcua)"
    ]


def test_all_problems_are_reported_at_once():
    doc = base()
    doc["tool"]["flutes"] = 0
    doc["motor"]["winding"] = "star"
    doc["alarms"]["torque_warn_nm"] = 50.0
    doc["zenoh"]["connect"] = ["tcp/nohost"]
    probs = problems_of(doc)
    assert [p.split(":")[0] for p in probs] == ["motor.winding", "tool.flutes", "alarms.torque_warn_nm", "zenoh.connect[0]"]


def test_transport_needs_its_address():
    doc = base()
    doc["daq"] = {"transport": "modbus-tcp"}
    probs = problems_of(doc)
    assert [p.split(":")[0] for p in probs] == ["daq.host", "daq.tcp_port"]
    doc["daq"] = {"transport": "serial"}
    assert problems_of(doc)[0].startswith("daq.port: missing (transport \"serial\" needs a serial device")
    doc["daq"] = {"transport": "sim"}
    assert load_config_text(dumps(doc)).daq.scenario == "step"


def test_cf_is_a_sane_number_or_model():
    doc = base()
    doc["tool"]["cf"] = "model"
    assert load_config_text(dumps(doc)).tool.cf == "model"
    doc["tool"]["cf"] = "auto"
    assert load_config_text(dumps(doc)).tool.cf == "auto"
    doc["tool"]["cf"] = 0.8                 # a 4-flute slot's fitted C_f (physics/resultant.py: π/4·√(1 + r₁²))
    assert load_config_text(dumps(doc)).tool.cf == 0.8
    doc["tool"]["cf"] = 2.0
    assert problems_of(doc)[0].startswith("tool.cf: 2.0 is outside 0.75–1.5")
    doc["tool"]["cf"] = "modle"
    assert problems_of(doc)[0].startswith('tool.cf: "modle" is neither a number nor "model"')
    del doc["tool"]["cf"]
    assert load_config_text(dumps(doc)).tool.cf == "auto"     # the default (additive): docs/physics.md §5


def test_nan_and_infinity_are_refused():
    doc = base()
    doc["motor"]["stator_resistance_ohm"] = float("nan")
    doc["gears"][0]["ratio"] = float("inf")
    probs = problems_of(doc)
    assert probs == [
        "motor.stator_resistance_ohm: nan is not a finite number (a number > 0)",
        "gears[0].ratio: inf is not a finite number (a number > 0)",
    ]


def test_channel_scale_must_not_be_zero_and_names_are_daq_names():
    doc = base()
    doc["channels"]["v_uv"]["scale"] = 0.0
    doc["channels"]["much_too_long_name"] = {"scale": 1.0}
    probs = problems_of(doc)
    assert probs[0].startswith("channels.v_uv.scale: must not be 0")
    assert probs[1].startswith('channels.much_too_long_name: "much_too_long_name" is not a DAQ channel name')


def test_dynamometer_needs_force_channels():
    doc = base()
    doc["depth"]["method"] = "dynamometer"
    assert problems_of(doc) == [
        'depth.method: "dynamometer" needs the force channels fx and fy; missing: [channels.fx], [channels.fy] '
        "(two dynamometer channels, [D] eq. 10)"
    ]
    doc["channels"].update(fx={"scale": 0.5}, fy={"scale": 0.5})
    assert load_config_text(dumps(doc)).depth.method == "dynamometer"


def test_feed_drive_needs_a_feed_force_entry_for_a_configured_channel():
    doc = base()
    doc["depth"]["method"] = "feed-drive"
    assert problems_of(doc)[0].startswith('depth.method: "feed-drive" needs a [feed_force] entry')
    doc["feed_force"] = {"ix_feed": {"newton_per_amp": 950.0, "friction_n": 120.0}}
    assert problems_of(doc) == ["feed_force.ix_feed: no [channels.ix_feed] table (a configured feed_current channel)"]
    doc["channels"]["ix_feed"] = {"scale": 0.001}
    s = load_config_text(dumps(doc))
    assert s.feed_force["ix_feed"].newton_per_amp == 950.0


def test_torque_only_needs_a_known_depth_unless_slotting():
    doc = base()
    doc["depth"]["method"] = "torque-only"
    doc["cut"]["mode"] = "down"
    assert problems_of(doc)[0].startswith('depth.method: "torque-only" needs one known depth')
    doc["cut"]["axial_depth_mm"] = 2.0
    assert load_config_text(dumps(doc)).cut.axial_depth_mm == 2.0


def test_radial_depth_is_at_most_the_diameter_and_agrees_with_a_slot():
    doc = base()
    doc["cut"].update(mode="down", radial_depth_mm=25.0)
    assert problems_of(doc) == ["cut.radial_depth_mm: 25 is more than the tool diameter 20 (at most tool.diameter_mm)"]
    doc["cut"].update(mode="slot", radial_depth_mm=4.0)
    assert problems_of(doc)[0].startswith('cut.radial_depth_mm: 4 contradicts mode = "slot"')


def test_zenoh_endpoints_are_validated():
    doc = base()
    good = ["tcp/10.0.0.5:7447", "udp/127.0.0.1:7447", "tls/mch10-01.plant.lan:7447", "quic/[::1]:7447",
            "tcp/127.0.0.1:0#iface=lo", "unixsock-stream//run/zenoh.sock"]
    doc["zenoh"]["connect"] = good
    assert load_config_text(dumps(doc)).zenoh.connect == good
    doc["zenoh"]["connect"] = ["tcp/10.0.0.5", "http/host:80", "tcp/host:70000", "7447"]
    probs = problems_of(doc)
    assert [p.split(":")[0] for p in probs] == [f"zenoh.connect[{i}]" for i in range(4)]
    assert "is not host:port" in probs[0] and 'unknown protocol "http"' in probs[1]
    assert "above 65535" in probs[2] and "is not an endpoint" in probs[3]


def test_alarm_warning_must_be_below_its_limit_and_revolutions_at_least_one():
    doc = base()
    doc["alarms"].update(force_warn_n=2000.0, force_limit_n=1000.0, revolutions=0)
    probs = problems_of(doc)
    assert "alarms.revolutions: must be at least 1, not 0 (an integer ≥ 1)" in probs
    # the warn < limit rule runs once the fields themselves are valid
    doc["alarms"]["revolutions"] = 1
    assert problems_of(doc) == ["alarms.force_warn_n: 2000 is not below force_limit_n = 1000 (a warning level under the limit)"]


def test_interlock_watchdog_longer_than_heartbeat():
    doc = base()
    doc["interlock"].update(heartbeat_ms=200, watchdog_ms=200)
    assert problems_of(doc)[0].startswith("interlock.watchdog_ms: 200 is not above heartbeat_ms = 200")


def test_bad_toml_names_line_and_column(tmp_path):
    path = write(tmp_path, 'machine = "m"\n[daq]\ntransport = serial\n')
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.problems == [
        f"{path}: TOML syntax error at line 3, column 13: Invalid value (a millsense TOML configuration: valid TOML)"
    ]


def test_missing_file_directory_and_non_utf8(tmp_path):
    for path, says in (
        (tmp_path / "nope.toml", "does not exist"),
        (tmp_path, "is a directory"),
    ):
        with pytest.raises(ConfigError) as info:
            load_config(path)
        assert info.value.problems == [f"{path}: {says} (a millsense TOML configuration)"]
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('machine = "Fräse"\n'.encode("latin-1"))
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    assert info.value.problems == [f"{bad}: not UTF-8 text: byte 0xe4 at offset 13 (a millsense TOML configuration, UTF-8 encoded)"]


def test_relative_paths_are_taken_from_the_config_folder(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "zenoh.json5").write_text("{}")
    doc = base()
    doc["zenoh"]["config_file"] = "zenoh.json5"
    s = load_config(write(tmp_path / "sub", doc))
    assert s.zenoh.config_file == str((tmp_path / "sub" / "zenoh.json5").resolve())
    doc["zenoh"]["config_file"] = "missing.json5"
    with pytest.raises(ConfigError) as info:
        load_config(write(tmp_path / "sub", doc))
    assert info.value.problems[0].startswith(f"zenoh.config_file: {(tmp_path / 'sub' / 'missing.json5').resolve()} does not exist")


def test_a_typo_in_daq_does_not_hide_the_transport_rule():
    doc = base()
    doc["daq"] = {"transport": "serial", "baudrat": 115200}
    probs = problems_of(doc)
    assert probs[0].startswith('daq.baudrat: unknown key, did you mean "baudrate"?')
    assert 'daq.port: missing (transport "serial" needs a serial device, e.g. "/dev/ttyACM0")' in probs


def test_modbus_timeout_leaves_room_for_a_heartbeat_before_the_watchdog():
    doc = base()
    doc["daq"] = {"transport": "modbus-tcp", "host": "10.0.0.9", "tcp_port": 502, "timeout_ms": 450}
    doc["interlock"].update(enabled=True, heartbeat_ms=100, watchdog_ms=500)
    (problem,) = problems_of(doc)
    assert problem.startswith("daq.timeout_ms: 450 leaves no room for a heartbeat before the DAQ's watchdog"), problem
    doc["daq"]["timeout_ms"] = 399
    assert load_config_text(dumps(doc)).daq.timeout_ms == 399
    doc["daq"]["timeout_ms"] = 450
    doc["interlock"]["enabled"] = False  # no watchdog to starve
    assert load_config_text(dumps(doc)).daq.timeout_ms == 450
    doc["daq"] = {"transport": "tcp", "host": "10.0.0.9", "tcp_port": 4001, "timeout_ms": 5000}
    doc["interlock"]["enabled"] = True  # a stream DAQ: heartbeats never wait behind a request
    assert load_config_text(dumps(doc)).daq.timeout_ms == 5000


def test_modbus_rtu_timeout_covers_the_longest_answer_at_the_baud_rate():
    doc = base()
    doc["daq"] = {"transport": "modbus-rtu", "port": "/dev/ttyUSB0", "baudrate": 19200, "timeout_ms": 200}
    (problem,) = problems_of(doc)
    assert problem.startswith("daq.timeout_ms: 200 is too short for a 125-register answer at 19200 baud (146 ms"), problem
    doc["daq"]["baudrate"] = 115200
    assert load_config_text(dumps(doc)).daq.baudrate == 115200


@pytest.mark.parametrize("cutoff", [1e-25, 0.5, -1.0, float("inf"), float("nan")])
def test_filter_cutoff_is_zero_or_a_real_filter(cutoff):
    """A cutoff far below any real anti-alias filter made the gain divided out of the power underflow:
    (f_e/f_c)^(2n) overflowed in the one-revolution path (an estimator fault, the feed held)."""
    doc = base()
    doc["daq"]["filter_cutoff_hz"] = cutoff
    probs = problems_of(doc)
    assert len(probs) == 1 and probs[0].startswith("daq.filter_cutoff_hz: "), probs
    for ok in (0.0, 1.0, 200.0):
        doc["daq"]["filter_cutoff_hz"] = ok
        assert load_config_text(dumps(doc)).daq.filter_cutoff_hz == ok
