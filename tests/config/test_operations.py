"""`[operations."P/T/O"]`, `[materials.NAME]`, `[learning] operations_file` (issue 41), and
`millsense limits import-operations`: every problem names its section.key (and a CSV's row), exit 78."""

from __future__ import annotations

import subprocess
import tomllib

import pytest

from millsense.daemon.config.load import ConfigError, load_config, load_config_text
from tests.config.helpers import REPO, base, dumps
from tests.e2e.helpers import CMD

KEY = "1001/5/1"
HEADER = "program,tool,operation,ae_mm,ap_mm,fz_mm,vf_mm_min,mode,engagement,material,spindle_rpm"


def doc(**op):
    d = base()
    d["tools"] = {"5": {"diameter_mm": 8.0, "flutes": 3, "flute_length_mm": 12.0}}
    d["materials"] = {"alu": {"ks": 300.0, "ks_exp": -0.3}}
    d["operations"] = {KEY: {"ap_mm": 2.0, "fz_mm": 0.1, "mode": "slot", "engagement": "constant", **op}}
    return d


def problems(d) -> list[str]:
    with pytest.raises(ConfigError) as info:
        load_config_text(dumps(d))
    return info.value.problems


def test_an_operation_loads_with_its_tool_and_material():
    s = load_config_text(dumps(doc(material="alu")))
    op = s.operations[KEY]
    assert (op.ap_mm, op.fz_mm, op.mode, op.material) == (2.0, 0.1, "slot", "alu")
    assert s.learning.physics_tolerance_pct > 0


def test_an_iso_group_letter_names_the_handbook_law_and_a_section_of_that_name_comes_first():
    from millsense.daemon.config.operations import operation_cut
    from millsense.daemon.physics.materials import ISO_GROUPS

    cut = operation_cut(load_config_text(dumps(doc(material="M"))), KEY)
    assert cut.material == ISO_GROUPS["M"].material and cut.material != ISO_GROUPS["P"].material
    d = doc(material="M")
    d["materials"]["M"] = {"ks": 2222.0, "ks_exp": -0.2}
    assert operation_cut(load_config_text(dumps(d)), KEY).material.ks == 2222.0   # the plant's own measured "M"


@pytest.mark.parametrize("change, expected", [
    ({"fz_mm": None}, 'operations."1001/5/1".fz_mm: give exactly one of fz_mm'),
    ({"vf_mm_min": 300.0}, 'operations."1001/5/1".fz_mm: give exactly one of fz_mm'),
    ({"fz_mm": 0.0}, 'operations."1001/5/1".fz_mm:'),
    ({"ap_mm": -1.0}, 'operations."1001/5/1".ap_mm:'),
    ({"ap_mm": 13.0}, 'operations."1001/5/1".ap_mm: 13 is above tools.5.flute_length_mm = 12'),
    ({"ae_mm": 4.0}, 'operations."1001/5/1".ae_mm: 4 with mode = "slot" is not tools.5.diameter_mm = 8'),
    ({"mode": "up"}, 'operations."1001/5/1".ae_mm: missing (mode = "up" needs the maximum radial depth'),
    ({"mode": "up", "ae_mm": 9.0}, 'operations."1001/5/1".ae_mm: 9 is above tools.5.diameter_mm = 8'),
    ({"engagement": "sometimes"}, 'operations."1001/5/1".engagement:'),
    ({"material": "steel"}, 'operations."1001/5/1".material: "steel" is no [materials.NAME] section (known: alu) and no ISO group (P, M, K, N, S)'),
    ({"depth": 3}, 'operations."1001/5/1".depth: unknown key'),
])
def test_each_problem_names_section_and_key(change, expected):
    d = doc()
    op = d["operations"][KEY]
    for k, v in change.items():
        if v is None:
            op.pop(k)
        else:
            op[k] = v
    found = problems(d)
    assert any(p.startswith(expected) for p in found), found


def test_a_key_that_is_not_program_tool_operation_is_refused():
    d = doc()
    d["operations"]["1001/5"] = d["operations"].pop(KEY)
    assert any(p.startswith('operations."1001/5": \'1001/5\' is not PROGRAM/TOOL/OPERATION') for p in problems(d))


def test_a_tool_not_in_the_table_takes_tool():
    d = doc()
    d["operations"] = {"1001/9/1": {"ap_mm": 50.0, "fz_mm": 0.1, "mode": "slot", "engagement": "constant"}}
    (p,) = problems(d)
    assert p.startswith('operations."1001/9/1".ap_mm: 50 is above tool.flute_length_mm (unset: 2 × diameter_mm) = 40')


def test_check_config_exits_78_naming_the_key(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(dumps(doc(ae_mm=4.0)))
    out = subprocess.run(CMD + ["check-config", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 78
    assert 'operations."1001/5/1".ae_mm' in out.stderr and "Traceback" not in out.stderr


def test_the_operations_file_is_read_and_a_key_in_both_places_refused(tmp_path):
    d = doc()
    d["learning"] = {"operations_file": "ops.toml"}
    (tmp_path / "ops.toml").write_text('[operations."1001/5/2"]\nap_mm = 1.0\nvf_mm_min = 300.0\nmode = "slot"\n'
                                       'engagement = "varying"\n')
    (tmp_path / "c.toml").write_text(dumps(d))
    s = load_config(tmp_path / "c.toml")
    assert set(s.operations) == {KEY, "1001/5/2"} and s.operations["1001/5/2"].vf_mm_min == 300.0
    (tmp_path / "ops.toml").write_text(f'[operations."{KEY}"]\nap_mm = 1.0\nfz_mm = 0.1\nmode = "slot"\n'
                                       'engagement = "varying"\n')
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "c.toml")
    assert info.value.problems[0].startswith(f'operations."{KEY}": in both the configuration and learning.operations_file')
    (tmp_path / "ops.toml").write_text('[alarms]\ntorque_limit_nm = 1.0\n')
    with pytest.raises(ConfigError) as info:
        load_config(tmp_path / "c.toml")
    assert "has alarms" in info.value.problems[0]


# -- millsense limits import-operations --------------------------------------------------------------

def imp(tmp_path, csv_text: str, *extra: str, ops_file: str | None = "ops.toml", d=None):
    d = d or doc()
    d["operations"] = {}
    if ops_file is not None:
        d["learning"] = {"operations_file": ops_file}
    (tmp_path / "c.toml").write_text(dumps(d))
    (tmp_path / "ops.csv").write_text(csv_text)
    return subprocess.run(CMD + ["limits", "import-operations", str(tmp_path / "ops.csv"), "--config",
                                 str(tmp_path / "c.toml"), *extra], capture_output=True, text=True, timeout=60)


def test_import_writes_the_operations_file_the_daemon_loads_and_merges_by_key(tmp_path):
    out = imp(tmp_path, f"{HEADER}\n1001,5,1,,2,0.1,,slot,constant,alu,3000\n1001,5,2,4,1.5,,300,down,varying,,\n")
    assert out.returncode == 0, out.stderr
    s = load_config(tmp_path / "c.toml")
    assert s.operations[KEY].material == "alu" and s.operations[KEY].spindle_rpm == 3000.0
    assert s.operations["1001/5/2"].ae_mm == 4.0 and s.operations["1001/5/2"].vf_mm_min == 300.0
    # a second sheet: its key replaces its own, the others stay
    (tmp_path / "ops2.csv").write_text(f"{HEADER}\n1001,5,2,4,1.0,,300,down,varying,,\n")
    out = subprocess.run(CMD + ["limits", "import-operations", str(tmp_path / "ops2.csv"), "--config",
                                str(tmp_path / "c.toml")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "1 replaced" in out.stdout, out.stderr
    ops = tomllib.loads((tmp_path / "ops.toml").read_text())["operations"]
    assert set(ops) == {KEY, "1001/5/2"} and ops["1001/5/2"]["ap_mm"] == 1.0


def test_import_refuses_bad_rows_naming_row_and_key_and_writes_nothing(tmp_path):
    out = imp(tmp_path, f"{HEADER}\n1001,5,1,,2,0.1,,slot,constant,,\n1001,5,2,,2,0.1,300,slot,constant,,\n"
                        "1001,5,3,,20,0.1,,slot,constant,,\n1001,5,4,,x,0.1,,slot,constant,,\n")
    assert out.returncode == 78, out.stdout
    err = out.stderr
    assert 'row 3: operations."1001/5/2".fz_mm: give exactly one of fz_mm' in err
    assert 'row 4: operations."1001/5/3".ap_mm: 20 is above tools.5.flute_length_mm = 12' in err
    assert 'row 5: operations."1001/5/4".ap_mm: "x" is not a number' in err
    assert "Traceback" not in err and not (tmp_path / "ops.toml").exists()


def test_import_refuses_a_header_that_is_not_exact_and_a_config_without_operations_file(tmp_path):
    out = imp(tmp_path, "program,tool,operation,ae,ap\n1,2,3,4,5\n")
    assert out.returncode == 78 and "row 1: the header is" in out.stderr
    out = imp(tmp_path, f"{HEADER}\n1001,5,1,,2,0.1,,slot,constant,,\n", ops_file=None)
    assert out.returncode == 78 and "learning.operations_file: not set" in out.stderr


def test_import_print_writes_nothing(tmp_path):
    out = imp(tmp_path, f"{HEADER}\n1001,5,1,,2,0.1,,slot,constant,,\n", "--print")
    assert out.returncode == 0 and '[operations."1001/5/1"]' in out.stdout
    assert not (tmp_path / "ops.toml").exists()


def test_the_example_sheet_imports_into_the_example_config(tmp_path):
    text = (REPO / "config" / "part-program.toml").read_text()
    assert '# operations_file = "operations-p1001.toml"' in text
    (tmp_path / "p.toml").write_text(text.replace('# operations_file = ', 'operations_file = '))
    out = subprocess.run(CMD + ["limits", "import-operations", str(REPO / "config" / "operations-p1001.csv"),
                                "--config", str(tmp_path / "p.toml")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    s = load_config(tmp_path / "p.toml")
    assert set(s.operations) == {"1001/11/10", "1001/4/20", "1001/27/30"}
    checked = subprocess.run(CMD + ["check-config", str(tmp_path / "p.toml")], capture_output=True, text=True,
                             timeout=60)
    assert checked.returncode == 0 and f"3 operations with an expected band (±{s.learning.physics_tolerance_pct:g} %)" in checked.stdout, checked


@pytest.mark.parametrize("section, change, key", [("learning", {"enabled": False}, "learning.enabled"),
                                                   ("context", {"source": "off"}, "context.source")])
def test_operations_that_nothing_can_arm_are_warned(section, change, key):
    from millsense.daemon.config.warnings import config_warnings

    d = doc()
    d.setdefault(section, {}).update(change)
    warned = [w for w in config_warnings(load_config_text(dumps(d))) if "[operations]" in w]
    assert len(warned) == 1 and warned[0].startswith(key), warned
    assert not [w for w in config_warnings(load_config_text(dumps(doc()))) if "[operations]" in w]


def test_import_refuses_a_key_the_main_configuration_already_has(tmp_path):
    d = doc()
    keep = dict(d["operations"])
    d["learning"] = {"operations_file": "ops.toml"}
    (tmp_path / "c.toml").write_text(dumps(d))
    (tmp_path / "ops.csv").write_text(f"{HEADER}\n1001,5,1,,1,0.1,,slot,varying,,\n")
    out = subprocess.run(CMD + ["limits", "import-operations", str(tmp_path / "ops.csv"), "--config",
                                str(tmp_path / "c.toml")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 78 and f'operations."{KEY}": also in' in out.stderr, out.stderr
    assert not (tmp_path / "ops.toml").exists() and tomllib.loads((tmp_path / "c.toml").read_text())["operations"] == keep
