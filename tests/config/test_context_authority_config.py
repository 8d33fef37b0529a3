"""`[context]`'s authority keys (issue 36): the adapter key, `trust`, their errors and check-config's warning.

Errors name `context.key` and check-config exits 78; the key is read from its file like the reset token's,
kept out of repr and the `config` queryable, and must not be the reset token.
"""

from __future__ import annotations

import json
import subprocess

import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import effective_config_dict, load_config, load_config_text
from millsense.daemon.config.warnings import config_warnings
from tests.config.helpers import base, dumps, write

pytestmark = pytest.mark.quick

KEY = "adapter-key-of-at-least-32-characters-0123456789"
TOKEN = "reset-token-of-at-least-32-characters-0123456789"


def doc_with(context: dict | None = None, afc: dict | None = None, interlock: dict | None = None) -> dict:
    doc = base()
    if context is not None:
        doc["context"] = context
    if afc is not None:
        doc["afc"] = afc
    if interlock is not None:
        doc.setdefault("interlock", {}).update(interlock)
    return doc


def problems(doc: dict, tmp_path=None) -> list[str]:
    with pytest.raises(ConfigError) as info:
        if tmp_path is None:
            load_config_text(dumps(doc))
        else:
            load_config(write(tmp_path, doc))
    return info.value.problems


def test_the_adapter_key_file_is_read_relative_to_the_config_and_masked(tmp_path):
    (tmp_path / "adapter.key").write_text(KEY + "\n")
    s = load_config(write(tmp_path, doc_with({"source": "zenoh", "adapter_key_file": "adapter.key"})))
    assert s.context.key() == KEY and s.context.trust == "none"
    assert s.context.adapter_key_file == str(tmp_path / "adapter.key")
    eff = effective_config_dict(s)
    assert eff["context"]["adapter_key"] == "***"
    for text in (repr(s), str(s), json.dumps(eff), repr(s.context)):
        assert KEY not in text


@pytest.mark.parametrize("content, expected", [
    (None, "does not exist"),
    ("\n", "is empty"),
    ("short\n", "holds 5 characters, too short"),
])
def test_a_bad_adapter_key_file_is_an_error_naming_the_key(tmp_path, content, expected):
    if content is not None:
        (tmp_path / "adapter.key").write_text(content)
    (problem,) = problems(doc_with({"adapter_key_file": "adapter.key"}), tmp_path)
    assert problem.startswith(f"context.adapter_key_file: {tmp_path / 'adapter.key'} {expected}"), problem


def test_the_adapter_key_must_not_be_the_reset_token(tmp_path):
    (tmp_path / "adapter.key").write_text(TOKEN + "\n")
    (tmp_path / "reset.token").write_text(TOKEN + "\n")
    doc = doc_with({"adapter_key_file": "adapter.key"}, interlock={"reset": "token", "reset_token_file": "reset.token"})
    (problem,) = problems(doc, tmp_path)
    assert problem.startswith("context.adapter_key_file: holds the reset token"), problem
    inline = doc_with({"adapter_key": TOKEN}, interlock={"reset": "token", "reset_token": TOKEN})
    (problem,) = problems(inline)
    assert problem.startswith("context.adapter_key: holds the reset token"), problem
    (tmp_path / "adapter.key").write_text(KEY + "\n")
    assert load_config(write(tmp_path, doc)).context.key() == KEY   # distinct: fine


@pytest.mark.parametrize("context, named", [
    ({"trust": "everyone"}, "context.trust"),
    ({"trust": True}, "context.trust"),
    ({"adapter_key": "short"}, "context.adapter_key"),
    ({"adapter_key": KEY, "adapter_key_file": "k"}, "context.adapter_key"),
    ({"adapter_kee_file": "k"}, "context.adapter_kee_file"),
])
def test_invalid_authority_keys_are_errors_naming_them(context, named):
    got = problems(doc_with(context))
    assert [p.split(": ")[0] for p in got] == [named], got


def test_check_config_exits_78_naming_the_key(millsense_cmd, tmp_path):
    path = write(tmp_path, doc_with({"source": "zenoh", "adapter_key_file": "missing.key"}))
    p = subprocess.run(millsense_cmd + ["check-config", str(path)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 78, (p.stdout, p.stderr)
    assert "Traceback" not in p.stderr
    assert [line.split(": ")[0] for line in p.stderr.strip().splitlines()] == ["context.adapter_key_file"], p.stderr


def _context_warnings(doc: dict, path=None) -> list[str]:
    settings = load_config(path) if path is not None else load_config_text(dumps(doc))
    return [w for w in config_warnings(settings, path) if w.startswith("context.adapter_key")]


@pytest.mark.parametrize("source", ["zenoh", "auto"])
def test_afc_following_an_unauthenticated_context_warns(source):
    (warning,) = _context_warnings(doc_with({"source": source}, afc={"enabled": True}))
    assert warning.startswith("context.adapter_key_file: not set and trust is \"none\", while afc.enabled is true")
    assert "context not authenticated" in warning and "millsense token new" in warning


@pytest.mark.parametrize("context, afc", [
    ({"source": "zenoh", "adapter_key": KEY}, {"enabled": True}),
    ({"source": "zenoh", "trust": "acl"}, {"enabled": True}),
    ({"source": "daq"}, {"enabled": True}),
    ({"source": "off"}, {"enabled": True}),
    ({"source": "zenoh"}, {"enabled": False}),
])
def test_no_warning_where_afc_cannot_follow_an_unauthenticated_context(context, afc):
    assert _context_warnings(doc_with(context, afc=afc)) == []


def test_an_adapter_key_file_others_can_read_warns(tmp_path):
    key = tmp_path / "adapter.key"
    key.write_text(KEY + "\n")
    key.chmod(0o644)
    path = write(tmp_path, doc_with({"source": "zenoh", "adapter_key_file": "adapter.key"}, afc={"enabled": True}))
    (warning,) = _context_warnings(None, path)
    assert warning == f"context.adapter_key_file: {key} can be read by other users (chmod 600, owner millsense)"
    key.chmod(0o600)
    assert _context_warnings(None, path) == []


@pytest.mark.parametrize("name, section, key, what", [
    ("reset.token", "interlock", "reset_token", "token"),
    ("adapter.key", "context", "adapter_key", "key"),
])
def test_a_secret_other_users_could_read_or_set_warns_for_both_secrets(tmp_path, name, section, key, what):
    """The reset token's file and the adapter key's file are judged by one rule (`_secret_warnings`)."""
    secret = tmp_path / name
    secret.write_text((TOKEN if section == "interlock" else KEY) + "\n")
    doc = doc_with({"source": "zenoh", "adapter_key_file": name} if section == "context" else {"source": "zenoh"},
                   interlock={"reset": "token", "reset_token_file": name} if section == "interlock" else None)
    path = write(tmp_path, doc)
    mine = lambda: [w for w in config_warnings(load_config(path), path) if w.startswith(f"{section}.{key}")]  # noqa: E731
    secret.chmod(0o600)
    assert mine() == []
    secret.chmod(0o666)
    assert mine() == [f"{section}.{key}_file: {secret} can be read by other users (chmod 600, owner millsense)",
                      f"{section}.{key}_file: {secret} can be written by users other than its owner "
                      f"(chmod 600, owner millsense): they could set the {what}"]
    secret.chmod(0o600)
    inline = doc_with({"source": "zenoh", "adapter_key": KEY} if section == "context" else {"source": "zenoh"},
                      interlock={"reset": "token", "reset_token": TOKEN} if section == "interlock" else None)
    path = write(tmp_path, inline)
    path.chmod(0o644)
    assert mine() == [f"{section}.{key}: {path} holds the {what} and other users can read it "
                      f"(chmod 640 {path}, owner root, group millsense; or use {key}_file)"]
