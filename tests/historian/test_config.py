"""`[historian]` is checked by `millsense check-config` like a daemon's file: every problem at once, each named
section.key, exit 78; a password never in the DSN, the passfile libpq would use (mode 0600)."""

from __future__ import annotations

import subprocess

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.historian import load_historian_config

pytestmark = pytest.mark.quick


def write(tmp_path, text: str):
    path = tmp_path / "historian.toml"
    path.write_text(text)
    return path


def passfile(tmp_path, mode: int):
    path = tmp_path / "pgpass"
    path.write_text("db.plant:5432:millsense:historian:s3cret\n")
    path.chmod(mode)
    return path


GOOD = """
[historian]
dsn = "host=db.plant port=5432 dbname=millsense user=historian sslmode=verify-full"
passfile = "pgpass"
machines = "hall2-$*"
spool_dir = "spool"
spool_max_mb = 64
revolutions_for = ["hall2-07"]
[historian.retention_days]
revolutions = 3
[zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:7447"]
multicast_scouting = false
"""


def problems(path) -> list[str]:
    with pytest.raises(ConfigError) as exc:
        load_historian_config(path)
    return exc.value.problems


def test_check_config_takes_a_historian_file_and_refuses_its_errors_with_exit_78(millsense_cmd, tmp_path):
    passfile(tmp_path, 0o600)
    good = write(tmp_path, GOOD)
    p = subprocess.run(millsense_cmd + ["check-config", str(good)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert "historian of machines 'hall2-$*'" in p.stdout and "revolutions 3 d" in p.stdout
    assert f"spool {tmp_path / 'spool'}" in p.stdout   # relative to the file's folder

    (tmp_path / "pgpass").chmod(0o644)
    bad = write(tmp_path, GOOD.replace('user=historian', 'user=historian password=s3cret').replace(
        'machines = "hall2-$*"', 'machines = "hall2/07"'))
    p = subprocess.run(millsense_cmd + ["check-config", str(bad)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 78, (p.stdout, p.stderr)
    lines = p.stderr.strip().splitlines()
    assert [line.split(":", 1)[0] for line in lines] == ["historian.dsn", "historian.machines", "historian.passfile"]
    assert "Traceback" not in p.stderr and "s3cret" not in p.stderr


@pytest.mark.parametrize("dsn", [
    "postgresql://historian:s3cret@db.plant/millsense",
    "postgresql://historian@db.plant/millsense?password=s3cret",
    "host=db.plant user=historian PASSWORD = 's3cret'",
])
def test_a_password_in_the_dsn_is_refused(tmp_path, dsn):
    found = problems(write(tmp_path, f'[historian]\ndsn = "{dsn}"\nspool_dir = "s"\n'))
    assert len(found) == 1 and found[0].startswith("historian.dsn: holds a password"), found


def test_a_uri_without_password_is_taken(tmp_path):
    s = load_historian_config(write(tmp_path, '[historian]\ndsn = "postgresql://historian@db.plant/m"\nspool_dir = "s"\n'))
    assert s.historian.dsn == "postgresql://historian@db.plant/m"


@pytest.mark.parametrize("mode", [0o640, 0o604])
def test_a_passfile_others_can_read_is_refused(tmp_path, mode):
    passfile(tmp_path, mode)
    found = problems(write(tmp_path, GOOD))
    assert found == [f"historian.passfile: {tmp_path / 'pgpass'} has mode {mode:04o}: libpq ignores a password "
                     f"file its group or others can read (chmod 600 {tmp_path / 'pgpass'})"]


def test_a_missing_passfile_dsn_and_spool_dir_are_named(tmp_path, monkeypatch):
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    found = problems(write(tmp_path, '[historian]\npassfile = "nope"\n'))
    assert [f.split(":", 1)[0] for f in found] == ["historian.dsn", "historian.passfile"]
    found = problems(write(tmp_path, '[historian]\ndsn = "host=x"\n'))
    assert [f.split(":", 1)[0] for f in found] == ["historian.spool_dir"]
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "state"))   # systemd's StateDirectory= is the default
    assert load_historian_config(write(tmp_path, '[historian]\ndsn = "host=x"\n')).historian.spool_dir == str(
        tmp_path / "state")


def test_unknown_keys_and_bad_values_are_named(tmp_path):
    found = problems(write(tmp_path, '[historian]\ndsn = "host=x"\nspool_dir = "s"\nspool_max_mb = 0\n'
                                     'revolutions_for = ["a b"]\n[historian.retention_days]\nload_1s = -1\nalarm = 3\n'))
    keys = sorted(f.split(":", 1)[0] for f in found)
    assert keys == ["historian.retention_days.alarm", "historian.retention_days.load_1s",
                    "historian.revolutions_for[0]", "historian.spool_max_mb"], found
