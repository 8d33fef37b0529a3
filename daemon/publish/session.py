"""One helper from settings to a Zenoh session, the way zenoh-python's examples do it.

`zenoh_config` turns the `[zenoh]` settings (mode, endpoints, multicast
scouting, an optional JSON5 file for TLS / auth / ACL) into a `zenoh.Config`;
`open_session` opens it. A *client* whose router is unreachable fails at once
inside `zenoh.open` ("Unable to connect to any of [...]"), so the daemon retries
with a doubling back-off and says once that it is waiting; a *peer* opens
anyway and finds its peers later.

Bounds on what a remote node can make this process allocate are applied to
every session (docs/security.md, "Floods and memory"):

- Zenoh shared memory is off unless `[zenoh] shared_memory = true`. With it
  on, every local peer that sends a large enough query makes this process map
  that peer's 16 MB segment, never given back (issue 11, finding 5).
- A peer or client reassembles a fragmented message of at most
  `MAX_MESSAGE_BYTES` (Zenoh's default is 1 GiB per priority and per link);
  a bigger one is dropped inside Zenoh, the link stays up.
- A peer accepts at most `MAX_PEER_SESSIONS` sessions (Zenoh: 1000).
A session in mode "router" keeps Zenoh's limits: it relays other nodes'
traffic, and its limits are the plant's to set in its JSON5 file.
A JSON5 `config_file` that sets one of the last two to something other than
Zenoh's default keeps its value: a plant that needs more says so there.

Settings are duck-typed: anything with `mode`, `connect`, `listen`,
`config_file`, `multicast_scouting`, `shared_memory` attributes (the pydantic `ZenohSettings`
of `millsense.daemon.config`, or a `SimpleNamespace` in a test). A missing
attribute takes the documented default.
"""

from __future__ import annotations

import json
import re
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

MODES = ("peer", "client", "router")

# The settings fields this module reads, with the defaults of interfaces.md.
_DEFAULTS: dict[str, Any] = {
    "mode": "peer",
    "connect": (),
    "listen": (),
    "config_file": "",
    "multicast_scouting": True,
    "shared_memory": False,
}

# Largest message this process reassembles. The daemon receives only queries (a command or status request
# is a few hundred bytes; the command queryables refuse bodies over a few KB before parsing) and
# declarations; `watch` receives estimates of about 1 KB. 1 MiB leaves room and caps a hostile peer at
# 1 MiB per reassembly buffer instead of 1 GiB.
MAX_MESSAGE_BYTES = 1 << 20
# Sessions a peer accepts. A machine's daemon serves a handful of HMIs, a historian and an operator
# console directly, or one router; 64 keeps room for that while bounding per-session buffers
# (each holds at least a 64 KB receive buffer).
MAX_PEER_SESSIONS = 64
# Zenoh 1.10's own defaults for the two bounds above (a JSON5 file that changed them wins).
_ZENOH_DEFAULT_MAX_MESSAGE = 1 << 30
_ZENOH_DEFAULT_MAX_SESSIONS = 1000


class ZenohConfigError(ValueError):
    """The Zenoh part of the configuration cannot be used; the message names the key."""


class ZenohUnavailable(ConnectionError):
    """No Zenoh session could be opened (a client found no router within its retry window)."""


def _field(zs: Any, name: str) -> Any:
    value = getattr(zs, name, None)
    return _DEFAULTS[name] if value is None else value


def _explicit(zs: Any, name: str) -> bool:
    """Was `name` written by the user (so it must win over the JSON5 file)?

    pydantic models know which fields were set; for plain objects every present
    attribute counts as explicit. Empty endpoint lists never override a file.
    """
    fields_set = getattr(zs, "model_fields_set", None)
    if fields_set is not None and name not in fields_set:
        return False
    return getattr(zs, name, None) is not None


def zenoh_settings_of(settings: Any) -> Any:
    """The `[zenoh]` part of a whole `Settings`, or the argument itself."""
    return getattr(settings, "zenoh", settings)


def zenoh_config(zenoh_settings: Any) -> zenoh.Config:
    """Build a `zenoh.Config`: the JSON5 file first, the explicit keys merged over it.

    Keys set from settings: `mode`, `connect/endpoints`, `listen/endpoints`,
    `scouting/multicast/enabled`, `transport/shared_memory/enabled`; then the
    allocation bounds (module docstring). Raises `ZenohConfigError` naming the key.
    """
    zs = zenoh_settings_of(zenoh_settings)
    config_file = str(_field(zs, "config_file") or "")
    if config_file:
        path = Path(config_file)
        if not path.is_file():
            raise ZenohConfigError(f"zenoh.config_file: {config_file} does not exist (a Zenoh JSON5 file)")
        try:
            conf = zenoh.Config.from_file(str(path))
        except Exception as exc:  # zenoh raises ZError with the offending key
            raise ZenohConfigError(f"zenoh.config_file: {config_file} is not a valid Zenoh config: "
                                   f"{zenoh_file_error(exc)}") from exc
    else:
        conf = zenoh.Config()

    mode = str(_field(zs, "mode"))
    if mode not in MODES:
        raise ZenohConfigError(f"zenoh.mode: {mode!r} is not one of {', '.join(MODES)}")
    if not config_file or _explicit(zs, "mode"):
        _insert(conf, "mode", "zenoh.mode", mode)

    for name in ("connect", "listen"):
        endpoints = [str(e) for e in _field(zs, name)]
        if endpoints or (not config_file and _explicit(zs, name)):
            _insert(conf, f"{name}/endpoints", f"zenoh.{name}", endpoints)

    if not config_file or _explicit(zs, "multicast_scouting"):
        _insert(conf, "scouting/multicast/enabled", "zenoh.multicast_scouting", bool(_field(zs, "multicast_scouting")))
    # Always from the TOML key (default off): Zenoh's own default is on, so a JSON5 file cannot say "on" apart
    # from "not mentioned", and the safe reading of silence is off.
    _insert(conf, "transport/shared_memory/enabled", "zenoh.shared_memory", bool(_field(zs, "shared_memory")))
    # A router relays other nodes' traffic: its limits are the plant's to set in its own JSON5 file.
    # A client has one session (its router), so only a peer needs the session bound.
    final_mode = json.loads(conf.get_json("mode"))
    if final_mode != "router":
        _bound(conf, "transport/link/rx/max_message_size", _ZENOH_DEFAULT_MAX_MESSAGE, MAX_MESSAGE_BYTES)
    if final_mode == "peer":
        _bound(conf, "transport/unicast/max_sessions", _ZENOH_DEFAULT_MAX_SESSIONS, MAX_PEER_SESSIONS)
    return conf


def zenoh_file_error(exc: BaseException) -> str:
    """Zenoh's reason a JSON5 file was refused, on one line and without its Rust source path: a parse error
    comes as a multi-line caret drawing (` --> 1:43 ... = expected array, ...`), a field's as
    `JSON error: Message { msg: "...", location: Some(Location { line: 1, column: 9 }) }`."""
    from millsense.daemon.publish.cli_args import strip_rust  # imports this module: not at the top

    text = strip_rust(str(exc))
    where = re.search(r"-->\s*(\d+):(\d+)", text) or re.search(r"line: (\d+), column: (\d+)", text)
    why = re.search(r"^\s*= (.+)$", text, re.M) or re.search(r'msg: "((?:[^"\\]|\\.)*)"', text)
    if where and why:
        return f"line {where.group(1)}, column {where.group(2)}: {why.group(1).strip()}"
    return " ".join(text.split())


def mode_in_effect(zenoh_settings: Any) -> str:
    """The mode a session from these settings runs in: a `config_file`'s own unless the TOML names one
    (read by Zenoh's loader, as `zenoh_config` does). Raises `ZenohConfigError` naming the key."""
    return str(json.loads(zenoh_config(zenoh_settings).get_json("mode")))


def _bound(conf: zenoh.Config, key: str, zenoh_default: int, bound: int) -> None:
    """Set `key` to `bound` unless a JSON5 file already chose a value other than Zenoh's default."""
    if json.loads(conf.get_json(key)) == zenoh_default:
        conf.insert_json5(key, json.dumps(bound))


def _insert(conf: zenoh.Config, key: str, setting: str, value: Any) -> None:
    try:
        conf.insert_json5(key, json.dumps(value))
    except Exception as exc:
        raise ZenohConfigError(f"{setting}: {value!r} refused by Zenoh: {exc}") from exc


def describe(zenoh_settings: Any) -> dict[str, Any]:
    """Mode and endpoints as log fields (no secrets: the JSON5 file is named, not read)."""
    zs = zenoh_settings_of(zenoh_settings)
    return {
        "mode": str(_field(zs, "mode")),
        "connect": list(_field(zs, "connect")),
        "listen": list(_field(zs, "listen")),
        "multicast_scouting": bool(_field(zs, "multicast_scouting")),
        "config_file": str(_field(zs, "config_file") or "") or None,
        "shared_memory": bool(_field(zs, "shared_memory")),
    }


def open_session(
    settings: Any,
    *,
    retry_for_s: float | None = 30.0,
    first_delay_s: float = 0.25,
    max_delay_s: float = 5.0,
    stop: threading.Event | None = None,
    on_waiting: Callable[[str, dict[str, Any]], None] | None = None,
    sleep: Callable[[float], Any] = time.sleep,
) -> zenoh.Session:
    """Open a session; a client retries with doubling back-off while its router is away.

    `retry_for_s=None` retries forever (what a daemon under systemd wants),
    `0` tries once. `on_waiting(event, fields)` is called once, on the first
    failure ("zenoh.waiting_for_router"), so the log says why start-up stalls
    without a line per attempt. `stop` (set by a signal handler) ends the wait.
    Raises `ZenohUnavailable` with the endpoints and the last error, or
    `ZenohConfigError`.
    """
    conf = zenoh_config(settings)
    fields = describe(settings)
    deadline = None if retry_for_s is None else time.monotonic() + retry_for_s
    delay = first_delay_s
    attempts = 0
    while True:
        attempts += 1
        try:
            return zenoh.open(conf)
        except Exception as exc:  # zenoh.ZError: "Unable to connect to any of [...]"
            last_error = str(exc).split(" at /", 1)[0].strip()  # drop the Rust source location
            now = time.monotonic()
            give_up = (deadline is not None and now + delay > deadline) or (stop is not None and stop.is_set())
            if give_up:
                where = ", ".join(fields["connect"]) or "(scouting)"
                raise ZenohUnavailable(
                    f"Zenoh {fields['mode']} could not open a session to {where} after {attempts} attempt(s): {last_error}"
                ) from None
            if attempts == 1 and on_waiting is not None:
                on_waiting("zenoh.waiting_for_router", {**fields, "error": last_error, "retry_s": retry_for_s})
            if stop is not None:
                if stop.wait(delay):
                    continue  # loop once more: give_up is then true and reports
            else:
                sleep(delay)
            delay = min(delay * 2.0, max_delay_s)


def endpoints_arg(values: Sequence[str] | None) -> list[str]:
    """Endpoints given as repeated options or comma lists: `-c a -c b,c` → [a, b, c]."""
    out: list[str] = []
    for v in values or ():
        out.extend(p.strip() for p in v.split(",") if p.strip())
    return out
