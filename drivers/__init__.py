"""millsense drivers: bytes from a DAQ in, numbered raw samples out; commands back."""

from __future__ import annotations

import importlib

# transport name (the config's daq.transport) -> "module:Class"; imported only when chosen
DRIVERS: dict[str, str] = {
    "serial": "millsense.drivers.serial_driver:SerialDriver",
    "tcp": "millsense.drivers.tcp_driver:TcpDriver",
    "modbus-tcp": "millsense.drivers.modbus_driver:ModbusTcpDriver",
    "modbus-rtu": "millsense.drivers.modbus_driver:ModbusRtuDriver",
    "sim": "millsense.drivers.sim_driver:SimDriver",
}


class DriverError(Exception):
    """A transport could not be created; the message names it."""


def create_driver(transport: str, **options):
    """Build (not start) the driver for ``transport`` with the given options.

    Options a transport does not use are ignored, so a whole ``[daq]`` section can
    be passed through; ``None`` values mean "use the default".
    """
    try:
        target = DRIVERS[transport]
    except KeyError:
        raise DriverError(
            f"unknown DAQ transport {transport!r} (expected one of: {', '.join(DRIVERS)})"
        ) from None
    module_name, class_name = target.split(":")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except ImportError as exc:
        raise DriverError(f"DAQ transport {transport!r} is unavailable: {exc}") from exc
    try:
        return cls.from_options(**{k: v for k, v in options.items() if v is not None})
    except (TypeError, ValueError) as exc:
        raise DriverError(f"DAQ transport {transport!r}: {exc}") from exc
