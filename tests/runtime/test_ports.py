"""What the Runner takes (runtime/ports.py) against the real parts that `millsense run` hands it: every method a
port declares exists on the real class with the same parameter names and defaults, so the Protocols say what
the runtime really calls and cannot drift from the parts they describe."""

from __future__ import annotations

import inspect

import pytest

from millsense.daemon.history.store import HistoryStore
from millsense.daemon.publish.sink import ZenohSink
from millsense.daemon.runtime import ports
from millsense.daemon.runtime.latch_store import LatchStore
from millsense.drivers.base import Driver

pytestmark = pytest.mark.quick


def _shape(fn: object) -> list[tuple[str, object]]:
    return [(p.name, p.default) for p in inspect.signature(fn).parameters.values()]


@pytest.mark.parametrize("port, real", [(ports.BatchedDriver, Driver), (ports.Sink, ZenohSink),
                                        (ports.History, HistoryStore), (ports.LatchStore, LatchStore)])
def test_each_port_is_what_the_real_part_offers(port, real):
    declared = {name: fn for klass in port.__mro__ if klass.__module__ == ports.__name__
                for name, fn in vars(klass).items() if callable(fn) and not name.startswith("_")}
    assert declared
    for name, fn in declared.items():
        assert callable(getattr(real, name, None)), f"{real.__name__} has no {name}()"
        assert _shape(getattr(real, name)) == _shape(fn), f"{real.__name__}.{name}: {_shape(getattr(real, name))}"
