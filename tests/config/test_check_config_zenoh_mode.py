"""`check-config` summarises the Zenoh mode the daemon will run in, a `config_file`'s too (issue 39).

With `[zenoh] config_file` and no `mode` in the TOML, the session takes the JSON5 file's mode
(daemon/publish/session.py); the summary said `zenoh peer` (the TOML key's default) for a file whose
mode is client. `millsense check-config` as a real subprocess on the shipped JSON5 files, read by
Zenoh's own loader.
"""

from __future__ import annotations

import json
import subprocess

import pytest
import zenoh

from tests.config.helpers import REPO, base, write

pytestmark = pytest.mark.quick

SUMMARY_ZENOH = "zenoh "


def doc_with_zenoh(zenoh_section: dict) -> dict:
    doc = base()
    doc["zenoh"] = zenoh_section
    doc.setdefault("interlock", {})["reset"] = "off"  # a config_file defaults to "token": no token needed here
    return doc


def summary_modes(cmd: list[str], path) -> list[str]:
    p = subprocess.run(cmd + ["check-config", str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    last = p.stdout.splitlines()[-1]
    assert last.startswith(f"{path}: OK (") and last.endswith(")"), last
    return [part.removeprefix(SUMMARY_ZENOH) for part in last[:-1].split(", ") if part.startswith(SUMMARY_ZENOH)]


def file_mode(path) -> str:
    return json.loads(zenoh.Config.from_file(str(path)).get_json("mode"))


@pytest.mark.parametrize("json5", ["zenoh-daemon.json5", "zenoh-operator.json5", "zenoh-tls.json5"])
def test_the_summary_says_the_config_files_mode(millsense_cmd, tmp_path, json5):
    path = REPO / "config" / json5
    config = write(tmp_path, doc_with_zenoh({"config_file": str(path)}))
    assert summary_modes(millsense_cmd, config) == [file_mode(path)]


def test_a_client_file_is_summarised_as_a_client(millsense_cmd, tmp_path):
    # The newcomer's case: the file is a client, the TOML says nothing of the mode.
    path = REPO / "config" / "zenoh-daemon.json5"
    assert file_mode(path) == "client"
    config = write(tmp_path, doc_with_zenoh({"config_file": str(path), "multicast_scouting": False}))
    assert summary_modes(millsense_cmd, config) == ["client"]


def test_a_mode_written_in_the_toml_wins_over_the_file_as_in_the_session(millsense_cmd, tmp_path):
    path = REPO / "config" / "zenoh-daemon.json5"
    zenoh_section = {"config_file": str(path), "mode": "peer", "connect": ["tcp/127.0.0.1:7447"]}
    config = write(tmp_path, doc_with_zenoh(zenoh_section))
    assert summary_modes(millsense_cmd, config) == ["peer"]


def test_a_config_file_zenoh_cannot_read_is_refused_naming_the_key(millsense_cmd, tmp_path):
    # `run` refuses it (exit 78): check-config must not call it OK.
    (tmp_path / "broken.json5").write_text("{ mode: \"client\", connect: { endpoints: [ }\n")
    config = write(tmp_path, doc_with_zenoh({"config_file": "broken.json5"}))
    p = subprocess.run(millsense_cmd + ["check-config", str(config)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 78, p.stdout
    (line,) = p.stderr.splitlines()
    assert line.startswith(f"zenoh.config_file: {tmp_path / 'broken.json5'} is not a valid Zenoh config"), line
    # One line saying where, without Zenoh's caret drawing or its Rust source path.
    assert ": line 1, column " in line and ".rs" not in line, line
