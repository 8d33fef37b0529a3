"""The `Controls` protocol (daemon/controls.py) and its one implementation (runtime/controls.py) held together.

Both front doors (the Zenoh queryables, the local socket) are written against the protocol; the live daemon
answers through `OperatorControls`. A member added to one and not the other, or a signature that drifts
(a renamed argument, a new default), fails here rather than at an operator's command.
"""

from __future__ import annotations

import inspect
from types import SimpleNamespace
from typing import Protocol, get_type_hints

import pytest

from millsense.daemon.config.load import demo_config
from millsense.daemon.controls import Controls
from millsense.daemon.runtime.controls import OperatorControls
from millsense.daemon.runtime.runner import Runner
from millsense.drivers.protocol import Descriptor
from millsense.sim.emulator.ramp import RAMP_CHANNELS

pytestmark = pytest.mark.quick


def _protocol_methods(proto: type) -> dict[str, object]:
    return {name: member for name, member in vars(proto).items()
            if callable(member) and not name.startswith("_")}


def test_every_member_of_the_protocol_is_implemented_with_the_same_signature():
    assert Controls in OperatorControls.__mro__   # the implementation names the protocol it implements
    assert Protocol in Controls.__mro__
    methods = _protocol_methods(Controls)
    assert {"status", "config", "reset", "test_trip", "limits", "limits_command", "afc_command",
            "on_context_payload"} <= set(methods)
    for name, declared in methods.items():
        implemented = vars(OperatorControls).get(name)   # defined there, not inherited from the protocol's stub
        assert callable(implemented), f"OperatorControls has no {name}()"
        assert inspect.signature(implemented) == inspect.signature(declared), (
            f"{name}: {inspect.signature(implemented)} != the protocol's {inspect.signature(declared)}")


def test_the_runner_builds_one_controls_with_the_protocol_s_attributes():
    daq = SimpleNamespace(descriptor=Descriptor(1000, RAMP_CHANNELS), link_up=True, last_status=None)
    runner = Runner(demo_config(), daq)   # not started: only what it built is looked at
    controls = runner.controls
    assert isinstance(controls, OperatorControls)
    for name in get_type_hints(Controls):   # the annotated attributes: `settings`, `audit`
        assert hasattr(controls, name), f"OperatorControls has no attribute {name}"
    assert controls.audit is runner.audit and controls.settings is runner.settings
    # the status the controls answer is the status the status thread publishes
    assert set(controls.status()) == set(runner.report.payload())
