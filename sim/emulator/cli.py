"""`millsense sim`: the DAQ emulator on a pty, a TCP port, Modbus TCP, or into a capture file.

Serving, the scenario repeats until stopped (`--once`: one pass); a capture is one pass
(`--loop --duration-s N` for a longer one).
"""

from __future__ import annotations

import argparse
import math
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


def _uint(lo: int, hi: int):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"expected a whole number within {lo}..{hi}, got {text!r}")
        return value

    return parse


def _pin(text: str) -> tuple[str, int]:
    name, sep, count = text.partition("=")
    try:
        value = int(count)
    except ValueError:
        value = None
    if not sep or not name or value is None or not -32768 <= value <= 32767:
        raise argparse.ArgumentTypeError(f"expected CHANNEL=COUNT with COUNT in -32768..32767, got {text!r}")
    return name, value


def _pair(first: str, second: str, second_type=int):
    """FIRST:SECOND, e.g. PART:TOOL (whole numbers) or TOOL:PCT (a number after the colon)."""

    def parse(text: str):
        a, sep, b = text.partition(":")
        try:
            return int(a), second_type(b)
        except ValueError:
            pass
        raise argparse.ArgumentTypeError(f"expected {first}:{second}, got {text!r}")

    return parse


PROGRAM_HELP = """\
part programs (--scenario part-program):
  A CNC makes --parts parts (default 30) of program 1001 with three tools: T11 (phi20 2-flute,
  operation 10, 1500 rpm), T4 (phi16 4-flute, operation 20, 1200 rpm), T27 (phi8 3-flute,
  operation 30, 2000 rpm); one slot each with a depth step, the spindle stopped for each tool
  change, the cycle off between parts. The DAQ is protocol 2 by default and sends CONTEXT
  (program, tool, operation; cycle|monitor while a cut is monitored, cycle off between parts)
  just before the first sample it holds for; Modbus input registers 8-15 follow it. Parts
  count from 1; faults apply to the part they name (in every pass, looping):
    --wear TOOL:PCT          K_s of TOOL rises PCT % per part, compounding: x(1+PCT/100)^(part-1)
    --broken-flute PART:TOOL a flute of TOOL breaks on the deeper floor of its slot in PART
    --missing-part PART      no material in PART: every cut is in air
    --wrong-tool PART:TOOL   in PART the spindle holds another cutter while the CNC reports
                             TOOL (for T11 a phi12 2-flute, T4 phi10 2-flute, T27 phi10 4-flute)
  --truth FILE also lists every process, one JSON line each, written when it ends:
    {"process": n, "pass", "part", "program", "tool", "operation", "key": "1001/11/10",
     "first_index", "last_index" (the samples with cycle and monitor set; sample indices count
     from 0 at the first sample, as "index_end" of a revolution: add --start-index for the DAQ's),
     "entry_index" (first sample cutting, null if none), "energy_j" (true cutting energy,
     integral of cutting torque x omega dt over first..last), "wear_factor" (K_s multiplier),
     "fault" (null, "broken_flute", "missing_part" or "wrong_tool"), "broken_index" (the
     sample at which the flute broke, else null), "cutter": {"diameter_mm", "flutes"}}
  Revolution lines have "rev", event lines "event" (tool_breakage, scenario_restart, ...).

first-part programs (issue 41; sim/first_part.py): first-part-slot (4101), first-part-down
  (4102), first-part-up (4103), first-part-pocket (4104), first-part-worn (4105), one part
  each, cut by a plant with the size effect at the instantaneous chip, edge forces, 5 um
  runout, tool deflection and wear (sim/cut_effects.py). Each operation has its programmed
  cut (ae, ap, feed, mode, engagement) for the daemon's [operations."P/T/O"]:
    --material-offset-pct PCT the plant's material PCT % off the config's (any scenario)
    --axial-scale OP:K        operation OP cuts K x its programmed axial depth
    --radial-scale OP:K       ... K x its radial depth (a slot: a down-milling cut K x D wide)
    --life-used TOOL:FRACTION TOOL has cut FRACTION of its life (its forces grow)
    --only-operation OP       play only operation OP (repeatable)
"""


def _offset_pct(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not -90.0 < value <= 500.0:
        raise argparse.ArgumentTypeError(f"expected a percentage above -90 and at most 500, got {text!r}")
    return value


def _names_pair(text: str) -> tuple[str, str]:
    a, sep, b = text.partition(",")
    if not sep or not a.strip() or not b.strip():
        raise argparse.ArgumentTypeError(f"expected CHANNEL,CHANNEL, got {text!r}")
    return a.strip(), b.strip()


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a value > 0, got {text!r}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.epilog = PROGRAM_HELP
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
    parser.add_argument("--speed", metavar="K", type=_positive, default=1.0,
                        help="pace the samples K times as fast as the clock (default 1; the descriptor keeps the "
                             "true rate, so the daemon needs [daq] check_sample_rate = false): a test bench "
                             "playing parts at speed")
    parser.add_argument("--start-on-connect", action="store_true",
                        help="with --tcp, --modbus-tcp or --modbus-rtu: the first sample is made when the first "
                             "client connects (Modbus: its first request; the status log's start event then), so "
                             "a reader that starts late sees the run from its start; a test bench's option, never "
                             "a machine's")
    parser.add_argument("--truth", metavar="FILE", help="write the per-revolution truth (JSON lines) to FILE")
    parser.add_argument("--seed", type=int, default=0)
    passes = parser.add_mutually_exclusive_group()
    passes.add_argument("--once", dest="loop", action="store_false", default=None,
                        help="serve the scenario once, then stop (servers loop by default)")
    # the default for servers now; kept so that command lines written before still work
    passes.add_argument("--loop", dest="loop", action="store_true", help="repeat the scenario forever (the default "
                        "for --pty, --tcp, --modbus-tcp, --modbus-rtu)")
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
    # sensor and DAQ faults (fault tests): sim/sensors.py SensorFaults
    parser.add_argument("--pin", type=_pin, action="append", metavar="CHANNEL=COUNT",
                        help="a stuck sensor: CHANNEL reads COUNT in every sample (repeatable)")
    parser.add_argument("--faults-from-s", type=_non_negative, default=0.0, metavar="S",
                        help="--pin, --current-gain and --clip-currents begin S seconds into the run, as a sensor "
                             "that fails mid-cut (default 0: from the first sample)")
    parser.add_argument("--current-gain", type=_positive, default=None, metavar="K",
                        help="current sensors give K times their datasheet's counts (large K: clipped at the int16 rails)")
    parser.add_argument("--clip-currents", type=_uint(1, 32767), default=None, metavar="COUNTS",
                        help="current sensors saturate at +-COUNTS")
    # wiring mistakes and a DAQ without a working watchdog (`millsense commission` finds each): wiring.py
    parser.add_argument("--swap", type=_names_pair, action="append", metavar="A,B",
                        help="channels A and B wired to each other's inputs, e.g. i_v,i_w (repeatable)")
    parser.add_argument("--reverse", action="append", metavar="CHANNEL",
                        help="a sensor turned round: CHANNEL's counts negated (an encoder counts backwards; "
                             "repeatable)")
    parser.add_argument("--watchdog-broken", action="store_true",
                        help="the DAQ takes heartbeats and the watchdog period but never holds the feed when "
                             "the heartbeats stop (a watchdog that does not work)")
    parser.add_argument("--descriptor-rate", type=_uint(1, 65535), default=None, metavar="HZ",
                        help="the DESCRIPTOR claims HZ while the samples keep their true rate")
    # protocol version 2: the simulated CNC beside the DAQ (context, feed held, feed override)
    parser.add_argument("--protocol", type=int, choices=(1, 2), default=None,
                        help="DAQ protocol version (default 1; 2 for a part program)")
    parser.add_argument("--unit", type=_uint(1, 247), default=1, help="Modbus unit id the device answers (default 1)")
    parser.add_argument("--program", type=_uint(0, 2**32 - 1), default=None,
                        help="protocol 2: the CNC's program number (default 0; a part program's own: 1001)")
    parser.add_argument("--tool", type=_uint(0, 2**32 - 1), default=None,
                        help="protocol 2: the tool in the spindle (default 0; a part program sets its own)")
    parser.add_argument("--operation", type=_uint(0, 65535), default=None,
                        help="protocol 2: the operation number (default 0; a part program sets its own)")
    parser.add_argument("--cnc-hold-lag-ms", type=_non_negative, default=30.0, metavar="MS",
                        help="protocol 2: how long after the feed-hold output the CNC reports the feed held (30)")
    parser.add_argument("--cnc-override-lag-ms", type=_non_negative, default=40.0, metavar="MS",
                        help="protocol 2: the CNC's feed override follows the commanded one with this first-order "
                             "time constant (40)")
    parser.add_argument("--cnc-override-rate-pct-s", type=_non_negative, default=1000.0, metavar="PCT_S",
                        help="protocol 2: the fastest the CNC's feed override moves, percent per second "
                             "(1000; 0 = no limit)")
    parser.add_argument("--afc-allowed", action="store_true",
                        help="protocol 2: the CNC allows adaptive feed in this cut (CONTEXT flag bit 2); "
                             "a part program sets it per operation")
    # the part program (sim/program.py): parts and faults; see below
    parser.add_argument("--parts", type=_uint(1, 100_000), default=None, metavar="N",
                        help="part program: how many parts (default 30)")
    parser.add_argument("--wear", type=_pair("TOOL", "PCT", float), action="append", metavar="TOOL:PCT",
                        help="part program: TOOL's K_s rises PCT %% per part, compounding (repeatable)")
    parser.add_argument("--broken-flute", type=_pair("PART", "TOOL"), action="append", metavar="PART:TOOL",
                        help="part program: a flute of TOOL breaks during its cut in PART (repeatable)")
    parser.add_argument("--missing-part", type=_uint(1, 100_000), action="append", metavar="PART",
                        help="part program: no material in PART (repeatable)")
    parser.add_argument("--wrong-tool", type=_pair("PART", "TOOL"), action="append", metavar="PART:TOOL",
                        help="part program: in PART the spindle holds another cutter than TOOL (repeatable)")
    # issue 41: the plant cutting something else than the config says (sim/first_part.py, sim/cut_effects.py)
    parser.add_argument("--material-offset-pct", type=_offset_pct, default=None, metavar="PCT",
                        help="the plant's material is PCT %% off the one the config is given (machine_config): "
                             "K_s and the edge forces x(1+PCT/100), e.g. -20 or 20 (any scenario)")
    parser.add_argument("--axial-scale", type=_pair("OP", "K", float), action="append", metavar="OP:K",
                        help="part program: operation OP cuts K times its programmed axial depth (repeatable)")
    parser.add_argument("--radial-scale", type=_pair("OP", "K", float), action="append", metavar="OP:K",
                        help="part program: operation OP cuts K times its programmed radial depth; a slot becomes "
                             "a down-milling cut K x D wide (repeatable)")
    parser.add_argument("--life-used", type=_pair("TOOL", "FRACTION", float), action="append",
                        metavar="TOOL:FRACTION", help="first-part program: TOOL has cut FRACTION (0..1) of its "
                        "life: its edge and chip forces grow (sim/cut_effects.py; repeatable)")
    parser.add_argument("--only-operation", type=_uint(0, 65535), action="append", metavar="OP",
                        help="part program: play only operation OP (repeatable; a short stream)")


def run(args: argparse.Namespace) -> int:
    from millsense.sim.emulator.runner import EmulatorError, list_text, serve

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
    if args.loop is None:
        # A server waits for a daemon that may start later, and one that reconnects after a restart:
        # it plays on. A capture is a file of one pass.
        args.loop = not args.capture
    try:
        return serve(args)
    except EmulatorError as exc:
        print(f"millsense sim: error: {exc}", file=sys.stderr)
        return exc.exit_code
