"""The address space of one machine, on a real (not listening) asyncua server, and the inbox's bounds."""

from __future__ import annotations

import asyncio

import pytest

pytest.importorskip("asyncua", reason="the opcua extra (asyncua) is not installed")
from asyncua import Server, ua  # noqa: E402

from millsense.daemon.opcua import fields as F  # noqa: E402
from millsense.daemon.opcua.inbox import MAX_EVENTS, Inbox  # noqa: E402
from millsense.daemon.opcua.machine_nodes import MachineNodes, Namespaces  # noqa: E402


async def _machine(name: str = "m1") -> tuple[Server, MachineNodes]:
    server = Server()
    await server.init()
    ns = await Namespaces.register(server)
    return server, await MachineNodes(server, ns, name).create(server.nodes.objects)


def test_a_null_estimate_is_bad_no_data_not_a_stale_number():
    async def scenario():
        _, m = await _machine()
        torque = m.variables[("Spindle", "torque_nm")]
        before = await torque.read_data_value(raise_on_bad_status=False)
        assert before.StatusCode.value == ua.StatusCodes.BadWaitingForInitialData
        await m.apply("estimate", {"t": 1.7e9, "rev": 5, "torque_nm": 4.25, "valid": True})
        good = await torque.read_data_value(raise_on_bad_status=False)
        assert good.StatusCode.is_good() and good.Value.Value == 4.25
        assert good.SourceTimestamp.timestamp() == pytest.approx(1.7e9)
        await m.apply("estimate", {"t": 1.7e9 + 0.1, "rev": 6, "torque_nm": None, "valid": False})
        null = await torque.read_data_value(raise_on_bad_status=False)
        assert null.StatusCode.value == ua.StatusCodes.BadNoData
        assert (await m.variables[("Spindle", "rev")].read_value()) == 6
        # An older daemon's payload without a field leaves that variable alone.
        await m.apply("estimate", {"rev": 7})
        assert (await torque.read_data_value(raise_on_bad_status=False)).StatusCode.value == ua.StatusCodes.BadNoData
        assert "Afc" not in m.folders
        await m.apply("estimate", {"rev": 8, "afc": {"state": "active", "override_pct": 92.0, "target": 5.0},
                                   "feed_override_pct": 92.0})
        assert await m.variables[("Afc", "state")].read_value() == "active"
        assert await m.variables[("Afc", "override_pct")].read_value() == 92.0

    asyncio.run(scenario())


def test_tool_life_per_tool_number_from_process_summaries():
    async def scenario():
        _, m = await _machine()
        await m.apply("process", {"tool": 12, "tool_processes": 88, "tool_wear_pct": 3.9, "key": "1234/12/3",
                                  "verdict": "good", "energy_j": 9790.3})
        await m.apply("process", {"tool": 7, "tool_processes": 3, "tool_wear_pct": -0.5})
        await m.apply("process", {"tool": 12, "tool_processes": 89, "tool_wear_pct": 4.1})
        assert sorted(m.tools) == [7, 12]
        assert await m.tools[12][0].read_value() == 89
        assert await m.tools[12][1].read_value() == pytest.approx(4.1)
        assert await m.tools[7][0].read_value() == 3
        assert await m.variables[("Process", "last_verdict")].read_value() == "good"

    asyncio.run(scenario())


@pytest.mark.quick
def test_value_conversion_never_writes_a_wrong_type():
    field = {f.name: f for f in F.FIELDS}
    assert F.value_at({"torque_nm": "12"}, field["torque_nm"]) is None
    assert F.value_at({"torque_nm": True}, field["torque_nm"]) is None
    assert F.value_at({}, field["torque_nm"]) is F.ABSENT
    assert F.value_at({"rev": 3.0}, field["rev"]) == 3 and F.value_at({"rev": 3.5}, field["rev"]) is None
    assert F.value_at({"afc": None}, next(f for f in F.FIELDS if f.path == ("afc", "state"))) is F.ABSENT


@pytest.mark.quick
def test_inbox_keeps_the_newest_value_and_bounds_the_events():
    inbox = Inbox()
    for rev in range(1000):
        inbox.put("m1", "estimate", {"rev": rev})
    for n in range(MAX_EVENTS + 10):
        inbox.put("m1", "alarm", {"n": n})
    items = inbox.take()
    estimates = [p for _, k, p in items if k == "estimate"]
    alarms = [p["n"] for _, k, p in items if k == "alarm"]
    assert estimates == [{"rev": 999}]
    assert len(alarms) == MAX_EVENTS and alarms[-1] == MAX_EVENTS + 9 and inbox.dropped == 10
    assert inbox.take() == []

