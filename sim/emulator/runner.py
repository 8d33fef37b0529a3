"""Builds the device from the CLI options and runs the chosen server until done or signalled."""

from __future__ import annotations

import asyncio
import math
import signal
import sys
import time

from millsense.sim.emulator.device import DeviceModel, StatusLog
from millsense.sim.emulator.pacing import Pacer
from millsense.sim.emulator.source import SourceError, is_program, list_sources, make_source
from millsense.sim.emulator.wire import WireEmitter


class EmulatorError(Exception):
    def __init__(self, message: str, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


def list_text() -> str:
    sources = list(list_sources())
    width = max(len(name) for name, _ in sources)
    return "\n".join(f"{name:<{width}} {desc}" for name, desc in sources)


PROGRAM_OPTIONS = ("parts", "wear", "broken_flute", "missing_part", "wrong_tool", "axial_scale", "radial_scale",
                   "life_used", "only_operation")


def _program_options(args) -> dict | None:
    """The part program's options (None for any other scenario, which refuses them: exit 2)."""
    given = [name for name in PROGRAM_OPTIONS if getattr(args, name, None)]
    if not is_program(args.scenario):
        if given:
            flags = ", ".join("--" + name.replace("_", "-") for name in given)
            raise EmulatorError(f"{flags}: only for a part program (--scenario part-program), "
                                f"not {args.scenario!r}", 2)
        return None
    for name in ("tool", "operation"):
        if getattr(args, name, None) is not None:
            raise EmulatorError(f"--{name}: the part program sets the tool and the operation itself", 2)
    if getattr(args, "afc_allowed", False):
        raise EmulatorError("--afc-allowed: the part program allows adaptive feed per operation itself", 2)
    from millsense.sim.program import ProgramFaults

    faults = ProgramFaults(
        wear_pct=tuple(args.wear or ()),
        broken_flute=tuple(args.broken_flute or ()),
        missing_part=tuple(args.missing_part or ()),
        wrong_tool=tuple(args.wrong_tool or ()),
        axial_scale=tuple(getattr(args, "axial_scale", None) or ()),
        radial_scale=tuple(getattr(args, "radial_scale", None) or ()),
        life_used=tuple(getattr(args, "life_used", None) or ()),
    )
    return {"parts": args.parts, "faults": faults, "program_number": args.program,
            "only": tuple(getattr(args, "only_operation", None) or ())}


def serve(args) -> int:
    program = _program_options(args)
    if args.protocol is None:
        args.protocol = 2 if program is not None else 1  # a part program is there for its CONTEXT
    try:
        source = make_source(
            args.scenario,
            seed=args.seed,
            loop=args.loop,
            start_index=args.start_index,
            filter_cutoff_hz=args.filter_cutoff_hz,
            noise_scale=args.noise_scale,
            program=program,
            material_offset_pct=getattr(args, "material_offset_pct", None),
        )
    except SourceError as exc:
        raise EmulatorError(str(exc), 2) from exc
    source = _with_sensor_faults(source, args)
    if getattr(args, "swap", None) or getattr(args, "reverse", None):
        from millsense.sim.emulator.wiring import WiringFaults

        try:
            source = WiringFaults(source, swap=args.swap, reverse=args.reverse)
        except ValueError as exc:
            raise EmulatorError(str(exc), 2) from exc
    if args.ring_depth < 1:
        raise EmulatorError("--ring-depth must be at least 1", 2)
    for name in ("cnc_override_lag_ms", "cnc_override_rate_pct_s"):
        if not math.isfinite(getattr(args, name)):
            raise EmulatorError(f"--{name.replace('_', '-')}: expected a finite number", 2)
    status_log = StatusLog(args.status_log)
    device = DeviceModel(
        source,
        start_index=args.start_index,
        ring_depth=args.ring_depth,
        watchdog_ms=args.watchdog_ms,
        status_log=status_log,
        protocol=args.protocol,
        program=args.program or 0,
        tool=args.tool or 0,
        operation=args.operation or 0,
        cnc_hold_lag_ms=args.cnc_hold_lag_ms,
        cnc_override_lag_ms=args.cnc_override_lag_ms,
        cnc_override_rate_pct_s=args.cnc_override_rate_pct_s,
        afc_allowed=args.afc_allowed,
    )
    device.watchdog_broken = bool(getattr(args, "watchdog_broken", False))
    speed = float(getattr(args, "speed", None) or 1.0)
    start = dict(first_index=device.head, scenario=args.scenario, protocol=device.protocol,
                 feed_override=device.feed_override if device.protocol >= 2 else None,
                 cnc_override_lag_ms=args.cnc_override_lag_ms,
                 cnc_override_rate_pct_s=args.cnc_override_rate_pct_s, speed=speed)
    if getattr(args, "start_on_connect", False):
        if not (args.tcp or args.modbus_tcp or args.modbus_rtu):
            raise EmulatorError("--start-on-connect waits for a client: give --tcp, --modbus-tcp or --modbus-rtu", 2)
        args.log_start = lambda now: status_log.write("start", now, **start)   # when the first client connects
    else:
        args.log_start = None
        status_log.write("start", **start)
    # the samples come at the source's true rate, whatever its descriptor claims (--descriptor-rate)
    device.sample_rate_hz = int(getattr(source, "sample_rate_hz", device.sample_rate_hz))
    rate = device.sample_rate_hz
    duration_samples = None
    if args.duration_s is not None:
        duration_samples = int(round(args.duration_s * rate))
    elif not args.loop and math.isfinite(getattr(source, "duration_s", math.inf)):
        duration_samples = int(round(source.duration_s * rate))
    realtime = args.realtime if args.realtime is not None else not args.capture
    if speed != 1.0 and not realtime:
        raise EmulatorError("--speed: only for a stream paced by the clock (not --fast or --capture)", 2)
    if args.capture and duration_samples is None:
        raise EmulatorError(f"scenario {args.scenario!r} never ends: give --duration-s for a capture", 2)
    # the framed stream sends whole frames (a Modbus register map fills its ring sample by sample)
    stream = not (args.modbus_tcp or args.modbus_rtu)
    pacer = Pacer(rate, realtime=realtime, quantum=args.per_frame if stream else 1, speed=speed)
    try:
        code = asyncio.run(_main(args, device, pacer, duration_samples))
    except OSError as exc:
        raise EmulatorError(str(exc)) from exc
    finally:
        status_log.write("stop", last_index=device.head)
        status_log.close()
    if args.truth:
        _write_truth(source, args.truth)
    return code


def _with_sensor_faults(source, args):
    """--pin, --current-gain, --clip-currents, --descriptor-rate: the sensors or the DAQ gone wrong
    (the sample faults from --faults-from-s on)."""
    pin = dict(getattr(args, "pin", None) or [])
    gain = getattr(args, "current_gain", None)
    clip = getattr(args, "clip_currents", None)
    rate = getattr(args, "descriptor_rate", None)
    if not pin and gain is None and clip is None and rate is None:
        return source
    from millsense.sim.sensors import SensorFaults

    try:
        return SensorFaults(source, pin=pin, current_gain=gain, clip_currents=clip, descriptor_rate_hz=rate,
                            from_s=float(getattr(args, "faults_from_s", 0.0) or 0.0))
    except ValueError as exc:
        raise EmulatorError(str(exc), 2) from exc


async def _main(args, device, pacer, duration_samples) -> int:
    loop = asyncio.get_running_loop()
    modbus = bool(args.modbus_tcp or args.modbus_rtu)
    if args.modbus_tcp:
        from millsense.sim.emulator.modbus_server import ModbusDeviceServer

        server = ModbusDeviceServer(device, pacer, *args.modbus_tcp, unit=args.unit, duration_samples=duration_samples,
                                    on_first_client=args.log_start)
        where = f"modbus-tcp {args.modbus_tcp[0]}:{args.modbus_tcp[1]}"
    elif args.modbus_rtu:
        from millsense.sim.emulator.modbus_server import ModbusDeviceServer

        server = ModbusDeviceServer(device, pacer, rtu_link=args.modbus_rtu, unit=args.unit,
                                    duration_samples=duration_samples, on_first_client=args.log_start)
        where = f"modbus-rtu {args.modbus_rtu}"
    else:
        from millsense.sim.emulator.stream_server import StreamServer

        emitter = WireEmitter(
            device,
            per_frame=args.per_frame,
            corrupt_fraction=args.corrupt_fraction,
            garbage_bps=args.garbage_bps,
            seed=args.seed,
        )
        server = StreamServer(device, emitter, pacer, duration_samples=duration_samples,
                              on_first_client=args.log_start)
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, server.stop.set)
    capture_fh = None
    try:
        if modbus:
            await server.open()
        elif args.pty:
            server.open_pty(args.pty)
            where = f"pty {args.pty}"
        elif args.tcp:
            await server.open_tcp(*args.tcp)
            where = f"tcp {args.tcp[0]}:{args.tcp[1]}"
        elif args.capture:
            capture_fh = open(args.capture, "wb")  # noqa: SIM115 - closed in finally
            server.open_capture(capture_fh)
            where = f"capture {args.capture}"
        if not args.capture:
            print(f"millsense sim: serving {args.scenario} on {where}", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        await server.run()
        if args.capture:
            print(
                f"millsense sim: wrote {pacer.produced} samples to {args.capture} in {time.monotonic() - t0:.2f} s",
                file=sys.stderr,
            )
    finally:
        if capture_fh is not None:
            capture_fh.close()
    return 0


def _write_truth(source, path: str) -> None:
    """Ask the plant's truth recorder to write itself; the ramp has no truth (empty file)."""
    truth = getattr(source, "truth", None)
    if truth is None:
        open(path, "w").close()
        return
    for name in ("write_jsonl", "write", "dump", "save"):
        fn = getattr(truth, name, None)
        if callable(fn):
            fn(path)
            return
    raise EmulatorError("the plant's truth recorder has no writer method")
