"""Zenoh config from settings, and opening a session: client retry, peer opens anyway."""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import pytest
import zenoh

from millsense.daemon.publish.session import (
    MAX_MESSAGE_BYTES,
    MAX_PEER_SESSIONS,
    ZenohConfigError,
    ZenohUnavailable,
    open_session,
    zenoh_config,
)

from .helpers import tcp, wait_for, zsettings


def _get(conf: zenoh.Config, key: str):
    return json.loads(conf.get_json(key))


def test_config_keys_come_from_settings(port):
    conf = zenoh_config(zsettings("client", connect=[tcp(port), "tcp/10.0.0.5:7447"], listen=[tcp(port + 1)]))
    assert _get(conf, "mode") == "client"
    assert _get(conf, "connect/endpoints") == [tcp(port), "tcp/10.0.0.5:7447"]
    assert _get(conf, "listen/endpoints") == [tcp(port + 1)]
    assert _get(conf, "scouting/multicast/enabled") is False


def test_whole_settings_object_and_defaults_are_accepted():
    # A Settings-like object with a .zenoh part; missing fields take the documented defaults.
    conf = zenoh_config(SimpleNamespace(machine="m1", zenoh=SimpleNamespace(mode="peer")))
    assert _get(conf, "mode") == "peer"
    assert _get(conf, "scouting/multicast/enabled") is True


@pytest.mark.parametrize(
    ("settings", "names"),
    [
        (zsettings("router-ish"), "zenoh.mode"),
        (zsettings(connect=["not an endpoint"]), "zenoh.connect"),
        (zsettings(config_file="/nonexistent/zenoh.json5"), "zenoh.config_file"),
    ],
)
def test_bad_settings_name_the_key(settings, names):
    with pytest.raises(ZenohConfigError) as err:
        zenoh_config(settings)
    assert str(err.value).startswith(names + ":")


def test_json5_file_is_loaded_first_and_explicit_keys_win(tmp_path, port):
    f = tmp_path / "z.json5"
    f.write_text(
        """{ // a comment, JSON5 style
          mode: "client",
          connect: { endpoints: ["tcp/10.9.9.9:7447"] },
          scouting: { multicast: { enabled: false } },
          queries_default_timeout: 1234,
        }"""
    )
    # Only `listen` and `connect` were written by the user: the file's mode and scouting stay.
    zs = zsettings("peer", listen=[tcp(port)], connect=[tcp(port + 1)], config_file=str(f))
    zs.multicast_scouting = True
    zs.model_fields_set = {"listen", "connect", "config_file"}
    conf = zenoh_config(zs)
    assert _get(conf, "mode") == "client"
    assert _get(conf, "scouting/multicast/enabled") is False
    assert _get(conf, "queries_default_timeout") == 1234
    assert _get(conf, "connect/endpoints") == [tcp(port + 1)]
    assert _get(conf, "listen/endpoints") == [tcp(port)]

    # Written explicitly, mode wins over the file.
    zs.model_fields_set = {"mode", "config_file"}
    conf = zenoh_config(zs)
    assert _get(conf, "mode") == "peer"
    assert _get(conf, "connect/endpoints") == [tcp(port + 1)]  # non-empty endpoints always apply


def test_invalid_json5_file_is_a_config_error(tmp_path):
    f = tmp_path / "bad.json5"
    f.write_text('{ transport: { link: { tls: { no_such_key: 1 } } } }')
    with pytest.raises(ZenohConfigError, match="zenoh.config_file: .*no_such_key"):
        zenoh_config(zsettings(config_file=str(f)))


@pytest.mark.serial
def test_client_without_router_gives_up_with_one_waiting_event(port):
    events = []
    started = time.monotonic()
    with pytest.raises(ZenohUnavailable) as err:
        open_session(
            zsettings("client", connect=[tcp(port)]),
            retry_for_s=0.6,
            first_delay_s=0.05,
            on_waiting=lambda event, fields: events.append((event, fields)),
        )
    assert time.monotonic() - started < 5.0
    assert tcp(port) in str(err.value) and "client" in str(err.value)
    assert [e for e, _ in events] == ["zenoh.waiting_for_router"]  # once, not per attempt
    assert events[0][1]["connect"] == [tcp(port)]


def test_client_retries_until_the_router_comes_up(port):
    router_box = {}

    def start_router_later():
        time.sleep(0.7)
        router_box["s"] = open_session(zsettings("router", listen=[tcp(port)]), retry_for_s=0)

    t = threading.Thread(target=start_router_later)
    t.start()
    waited = []
    try:
        session = open_session(
            zsettings("client", connect=[tcp(port)]),
            retry_for_s=10.0,
            first_delay_s=0.05,
            max_delay_s=0.2,
            on_waiting=lambda e, f: waited.append(e),
        )
        try:
            assert waited == ["zenoh.waiting_for_router"]
            wait_for(lambda: len(list(session.info.routers_zid())) == 1, 5.0, "client linked to router")
        finally:
            session.close()
    finally:
        t.join(10)
        if "s" in router_box:
            router_box["s"].close()


@pytest.mark.serial
def test_stop_event_ends_the_wait(port):
    stop = threading.Event()
    threading.Timer(0.3, stop.set).start()
    started = time.monotonic()
    with pytest.raises(ZenohUnavailable):
        open_session(zsettings("client", connect=[tcp(port)]), retry_for_s=None, first_delay_s=0.05, stop=stop)
    assert time.monotonic() - started < 3.0


def test_peer_opens_even_when_nothing_answers(port):
    session = open_session(zsettings("peer", connect=[tcp(port)]), retry_for_s=0)
    try:
        assert not session.is_closed()
        assert list(session.info.peers_zid()) == []
    finally:
        session.close()


def test_settings_from_the_toml_config(tmp_path, port):
    from millsense.daemon.config import load as config

    demo = config.demo_config()
    zs = demo.zenoh.model_copy(update={"mode": "client", "connect": [tcp(port)], "multicast_scouting": False})
    conf = zenoh_config(zs)
    assert _get(conf, "mode") == "client"
    assert _get(conf, "connect/endpoints") == [tcp(port)]


# -- bounds on what a remote node can make the daemon allocate (issue 11, finding 5) -------------------------


def test_shared_memory_is_off_unless_configured():
    assert _get(zenoh_config(zsettings("peer")), "transport/shared_memory/enabled") is False
    assert _get(zenoh_config(zsettings("peer", shared_memory=True)), "transport/shared_memory/enabled") is True
    # from the TOML model too: the key's default is off
    from millsense.daemon.config import load as config

    assert _get(zenoh_config(config.demo_config().zenoh), "transport/shared_memory/enabled") is False


def test_shared_memory_off_even_when_a_json5_file_is_silent_or_says_on(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ transport: { shared_memory: { enabled: true } } }')
    assert _get(zenoh_config(zsettings(config_file=str(f))), "transport/shared_memory/enabled") is False


def test_message_and_session_bounds(tmp_path):
    peer = zenoh_config(zsettings("peer"))
    assert _get(peer, "transport/link/rx/max_message_size") == MAX_MESSAGE_BYTES
    assert _get(peer, "transport/unicast/max_sessions") == MAX_PEER_SESSIONS
    client = zenoh_config(zsettings("client", connect=["tcp/127.0.0.1:7447"]))
    assert _get(client, "transport/link/rx/max_message_size") == MAX_MESSAGE_BYTES
    router = zenoh_config(zsettings("router"))  # relays others' traffic: Zenoh's limits, the plant's to change
    assert _get(router, "transport/link/rx/max_message_size") == _get(zenoh.Config(), "transport/link/rx/max_message_size")
    assert _get(router, "transport/unicast/max_sessions") == _get(zenoh.Config(), "transport/unicast/max_sessions")
    # a plant that needs more says so in its JSON5 file, and that wins
    f = tmp_path / "z.json5"
    f.write_text('{ transport: { unicast: { max_sessions: 200 }, link: { rx: { max_message_size: 4194304 } } } }')
    conf = zenoh_config(zsettings(config_file=str(f)))
    assert _get(conf, "transport/unicast/max_sessions") == 200
    assert _get(conf, "transport/link/rx/max_message_size") == 4194304


# A process standing in for the daemon: millsense's own session helper, a queryable that refuses.
_SERVER = r"""
import json, sys, time
from types import SimpleNamespace
from millsense.daemon.publish.session import open_session
zs = SimpleNamespace(mode="peer", listen=[sys.argv[1]], connect=[], multicast_scouting=False, config_file="",
                     shared_memory=sys.argv[2] == "on")
s = open_session(zs, retry_for_s=0)
q = s.declare_queryable("millsense/mem-01/cmd/reset", lambda q: q.reply(q.key_expr, b'{"ok": false}'))
print("ready", flush=True)
while True:
    time.sleep(1)
"""


def _rss_growth_kb_through_local_peers(port: int, shm: str, sessions: int = 20, queries: int = 20) -> tuple[int, int]:
    """RSS growth of a millsense session while `sessions` local peers each send `queries` 64 KB queries."""
    import os
    import subprocess
    import sys

    from tests.procstat import proc_kb

    server = subprocess.Popen([sys.executable, "-c", _SERVER, tcp(port), shm], stdout=subprocess.PIPE, text=True)
    answered = 0
    try:
        assert server.stdout.readline().strip() == "ready"
        blob = os.urandom(65536)
        # one peer first, so the growth counts sessions, not the first-use warm-up of the runtime
        warm = open_session(zsettings("peer", connect=[tcp(port)], shared_memory=True), retry_for_s=0)
        wait_for(lambda: list(warm.get("millsense/mem-01/cmd/reset", payload=blob, timeout=2.0)), 10.0, "first answer")
        warm.close()
        rss0 = proc_kb(server.pid)
        for _ in range(sessions):
            # The peers are as an attacker's would be: shared memory on, on their side.
            peer = open_session(zsettings("peer", connect=[tcp(port)], shared_memory=True), retry_for_s=0)
            try:
                wait_for(lambda p=peer: list(p.info.peers_zid()), 5.0, "peer linked")
                for _ in range(queries):
                    answered += len(list(peer.get("millsense/mem-01/cmd/reset", payload=blob, timeout=5.0)))
            finally:
                peer.close()
        return proc_kb(server.pid) - rss0, answered
    finally:
        server.kill()
        server.wait(5)


def test_local_peers_with_large_queries_do_not_grow_memory(port):
    growth_kb, answered = _rss_growth_kb_through_local_peers(port, "off")
    print(f"RSS growth through 20 local peer sessions x 20 queries of 64 KB: {growth_kb} kB")
    assert answered == 400  # every query reached the queryable: the load was real
    # Generous (the bench budget is 10 MB): with shared memory on, each session added ~8-16 MB (170 MB in all).
    assert growth_kb < 40_000, f"RSS grew by {growth_kb} kB"
