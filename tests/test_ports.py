"""The ports tests pick for their listeners are never an outgoing connection's.

A test picks a port, then starts the process that listens on it. CI once failed with "cannot listen on
127.0.0.1:57989: Address already in use": the port came from the kernel's ephemeral range (binding port 0),
and an outgoing connection of the daemon, Zenoh or the emulator took it as its local port in between.
"""

from __future__ import annotations

import socket

import pytest

from tests.conftest import LOWEST_PORT, ephemeral_range, free_tcp_port

pytestmark = pytest.mark.quick


def test_picked_ports_lie_below_the_ephemeral_range_and_are_never_handed_out_twice():
    lo, _ = ephemeral_range()
    assert lo > LOWEST_PORT + 1000, f"this box's ephemeral range starts at {lo}: no room below it"
    ports = [free_tcp_port() for _ in range(50)]
    assert all(LOWEST_PORT <= p < lo for p in ports), ports
    assert len(set(ports)) == len(ports)


def test_outgoing_connections_take_their_local_ports_from_the_ephemeral_range_only():
    """The premise of the above, on this box: many outgoing connections, none below the range."""
    lo, hi = ephemeral_range()
    with socket.create_server(("127.0.0.1", 0)) as server:
        clients = [socket.create_connection(server.getsockname()) for _ in range(64)]
        try:
            local = [c.getsockname()[1] for c in clients]
        finally:
            for c in clients:
                c.close()
    assert all(lo <= p <= hi for p in local), local
