"""`millsense sim`: the DAQ emulator on a pty, a TCP port, Modbus TCP, or into a capture file."""

from __future__ import annotations

import argparse
import sys


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def _fraction(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction within 0..1, got {text!r}")
    return value


def _non_negative(text: str) -> float:
    value = float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a value >= 0, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default=None, help="scenario to play ('ramp': a synthetic test ramp)")
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")
    out = parser.add_mutually_exclusive_group()
    out.add_argument("--pty", metavar="LINK", help="serve the stream on a pseudo-terminal; LINK is a symlink to it")
    out.add_argument("--tcp", metavar="HOST:PORT", type=_host_port, help="serve the stream to TCP clients")
    out.add_argument("--modbus-tcp", metavar="HOST:PORT", type=_host_port, help="serve the Modbus register map")
    out.add_argument("--modbus-rtu", metavar="LINK",
                     help="serve the Modbus register map as RTU on a pseudo-terminal; LINK is a symlink to it")
    out.add_argument("--capture", metavar="FILE", help="write the frames to FILE")
    pace = parser.add_mutually_exclusive_group()
    pace.add_argument("--realtime", dest="realtime", action="store_true", default=None,
                      help="pace samples by the clock (default for servers)")
    pace.add_argument(
        "--fast", dest="realtime", action="store_false", help="as fast as possible (default for --capture)"
    )
    parser.add_argument("--truth", metavar="FILE", help="write the per-revolution truth (JSON lines) to FILE")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--loop", action="store_true", help="repeat the scenario forever")
    parser.add_argument(
        "--duration-s", type=_non_negative, default=None, help="stop after this many seconds of samples"
    )
    parser.add_argument("--status-log", metavar="FILE", help="JSON lines of output changes, heartbeats, faults")
    parser.add_argument("--filter-cutoff-hz", type=_non_negative, default=None)
    parser.add_argument("--noise-scale", type=_non_negative, default=None, metavar="K",
                        help="scale the sensors' imperfections, random noise and zero offsets alike (0 = ideal sensors)")
    parser.add_argument("--corrupt-fraction", type=_fraction, default=0.0, metavar="F",
                        help="corrupt this fraction of frames on the wire (fault tests)")
    parser.add_argument("--garbage-bps", type=_non_negative, default=0.0, metavar="N",
                        help="random bytes per second between frames (fault tests)")
    parser.add_argument("--watchdog-ms", type=int, default=0, help="heartbeat watchdog period, 0 = off")
    parser.add_argument("--start-index", type=int, default=0, help="index of the first sample (to test the wrap)")
    parser.add_argument("--ring-depth", type=int, default=4096, help="Modbus ring depth D in samples")
    parser.add_argument("--per-frame", type=int, default=10, help="samples per SAMPLES frame")


def run(args: argparse.Namespace) -> int:
    from millsense.drivers.emulator.runner import EmulatorError, list_text, serve

    if args.list:
        print(list_text())
        return 0
    if not args.scenario:
        print("millsense sim: error: --scenario is required (see --list)", file=sys.stderr)
        return 2
    if not (args.pty or args.tcp or args.modbus_tcp or args.modbus_rtu or args.capture):
        print("millsense sim: error: choose one of --pty, --tcp, --modbus-tcp, --modbus-rtu or --capture",
              file=sys.stderr)
        return 2
    try:
        return serve(args)
    except EmulatorError as exc:
        print(f"millsense sim: error: {exc}", file=sys.stderr)
        return exc.exit_code
