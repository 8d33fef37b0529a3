"""A Modbus DAQ that restarts while the link stays up is given its watchdog period again.

A board behind a Modbus TCP gateway (or on a serial line whose adapter stays powered) can restart between two
polls with the link never dropping: the gateway answers for it, the TCP connection lives on. The restarted
board comes back with its power-up watchdog period (its own setting, or none), and the daemon's period was
written only at each connect: with no link event, nothing wrote it again, and a daemon that then hung left
the feed running. The driver sees the restart (its ring's head went back) and writes the period again.

The emulator's real Modbus server in-process, the real driver over loopback TCP; the restart is a fresh
device model behind the same server.
"""

from __future__ import annotations

import asyncio
import threading

from millsense.sim.emulator.device import DeviceModel
from millsense.sim.emulator.modbus_server import ModbusDeviceServer
from millsense.sim.emulator.pacing import Pacer
from millsense.sim.emulator.source import make_source
from millsense.drivers.modbus_driver import ModbusTcpDriver
from tests.conftest import free_tcp_port
from tests.e2e.helpers import wait_for


def test_a_board_that_restarted_under_a_live_link_is_given_its_watchdog_period_again():
    device = DeviceModel(make_source("step", seed=3, loop=True), watchdog_ms=0)
    port = free_tcp_port()
    server = ModbusDeviceServer(device, Pacer(device.sample_rate_hz, realtime=True), "127.0.0.1", port)
    loop = asyncio.new_event_loop()
    ready = threading.Event()

    async def main():
        await server.open()
        ready.set()
        await server.run()

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    drv = ModbusTcpDriver("127.0.0.1", port, unit=1, poll_ms=20)
    try:
        assert ready.wait(10)
        drv.start()
        assert drv.wait_connected(10)
        drv.set_watchdog_ms(1000)   # what the interlock's start does
        wait_for(lambda: device.watchdog_ms == 1000, 10.0, "the watchdog period written")
        wait_for(lambda: device.head > 500 and drv.stats()["modbus_requests"] > 20, 10.0, "the driver polling")
        links = drv.stats()["link_changes"]

        restarted = DeviceModel(make_source("step", seed=3, loop=True), watchdog_ms=0)   # as at power-up
        swapped = threading.Event()

        def restart():
            server.device = restarted
            swapped.set()

        loop.call_soon_threadsafe(restart)
        assert swapped.wait(10)
        wait_for(lambda: restarted.watchdog_ms == 1000, 10.0, "the restarted board given its watchdog period")
        assert drv.stats()["link_changes"] == links   # the link never dropped: no reconnect wrote it
    finally:
        drv.close()
        loop.call_soon_threadsafe(server.stop.set)
        thread.join(5)
