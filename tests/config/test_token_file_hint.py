"""A config refused for a missing secret file names the command that makes it (issue 39).

`millsense check-config` as a real subprocess on a config whose `[interlock] reset_token_file` or
`[context] adapter_key_file` names a file that is not there: the one-line error ends with the exact
`millsense token new --out FILE` that makes it, and running that command (as a real subprocess too)
makes the same config pass.
"""

from __future__ import annotations

import re
import shlex
import subprocess

import pytest

from tests.config.helpers import base, write

pytestmark = pytest.mark.quick

HINT = re.compile(r"\(.*make one with `(millsense token new --out [^`]+)`\)$")


def doc_naming(key: str, file_name: str) -> dict:
    doc = base()
    if key == "interlock.reset_token_file":
        doc.setdefault("interlock", {}).update({"reset": "token", "reset_token_file": file_name})
    else:
        doc["context"] = {"source": "zenoh", "adapter_key_file": file_name}
    return doc


def check_config(cmd: list[str], path) -> subprocess.CompletedProcess:
    return subprocess.run(cmd + ["check-config", str(path)], capture_output=True, text=True, timeout=60)


@pytest.mark.parametrize("key", ["interlock.reset_token_file", "context.adapter_key_file"])
def test_a_missing_secret_file_names_the_command_that_makes_it(millsense_cmd, tmp_path, key):
    folder = tmp_path / "etc dir"  # a space: the command shown must still be one a shell runs as is
    folder.mkdir()
    config = write(folder, doc_naming(key, "x.secret"))
    missing = folder / "x.secret"

    p = check_config(millsense_cmd, config)
    assert p.returncode == 78, p.stdout
    (line,) = p.stderr.splitlines()
    assert line.startswith(f"{key}: {missing} does not exist ("), line
    hint = HINT.search(line)
    assert hint, f"no `millsense token new --out …` at the end: {line}"
    argv = shlex.split(hint.group(1))
    assert argv[:4] == ["millsense", "token", "new", "--out"] and argv[4:] == [str(missing)], argv

    made = subprocess.run(millsense_cmd + argv[1:], capture_output=True, text=True, timeout=60)
    assert made.returncode == 0, made.stderr
    assert missing.stat().st_mode & 0o077 == 0
    again = check_config(millsense_cmd, config)
    assert again.returncode == 0, again.stderr
    assert again.stdout.splitlines()[-1].startswith(f"{config}: OK ("), again.stdout
