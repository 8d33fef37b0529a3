"""`millsense record`: save what the configured DAQ sends, as a capture in stream framing.

Whatever the transport, the file holds DESCRIPTOR and SAMPLES frames as the
stream transport would carry them (Modbus data is re-framed), so a capture from
any DAQ replays through the same decoder.  A full disk is a clear error: the
file is closed and the counts so far are printed.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, metavar="FILE", help="daemon configuration (its [daq] section)")
    parser.add_argument("--out", required=True, metavar="CAPTURE", help="capture file to write")
    parser.add_argument(
        "--seconds", type=float, default=None, help="stop after this many seconds (default: until Ctrl-C)"
    )
    parser.add_argument("--connect-timeout-s", type=float, default=10.0, help="give up if the DAQ is not reachable")


def _driver_options(daq) -> dict:
    names = ("port", "baudrate", "host", "tcp_port", "unit", "scenario", "poll_ms", "seed", "realtime")
    return {name: getattr(daq, name) for name in names if getattr(daq, name, None) is not None}


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.config import load_config
    from millsense.drivers import DriverError, create_driver
    from millsense.drivers.base import LinkEvent, SampleBlock
    from millsense.drivers.protocol import Descriptor, encode_descriptor, encode_sample_frames

    settings = load_config(args.config)
    daq = settings.daq
    try:
        driver = create_driver(daq.transport, **_driver_options(daq))
    except DriverError as exc:
        print(f"millsense record: error: {exc}", file=sys.stderr)
        return 78
    stop = {"now": False}

    def _stop(*_a) -> None:
        stop["now"] = True

    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    counts = {"samples": 0, "blocks": 0, "lost_samples": 0, "descriptors": 0, "bytes": 0}
    code = 0
    try:
        fh = open(args.out, "wb")  # noqa: SIM115 - closed in finally
    except OSError as exc:
        print(f"millsense record: error: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    driver.start()
    try:
        if not driver.wait_connected(args.connect_timeout_s):
            print(f"millsense record: error: DAQ ({daq.transport}) unreachable", file=sys.stderr)
            return 69
        deadline = None if args.seconds is None else time.monotonic() + args.seconds
        written_descriptor = None
        while not stop["now"] and (deadline is None or time.monotonic() < deadline):
            ev = driver.get(timeout=0.1)
            if ev is None:
                continue
            data = b""
            if isinstance(ev, Descriptor):
                data = encode_descriptor(ev)
                written_descriptor = ev
                counts["descriptors"] += 1
            elif isinstance(ev, SampleBlock):
                if written_descriptor is None and driver.descriptor is not None:
                    written_descriptor = driver.descriptor
                    data = encode_descriptor(written_descriptor)
                data += encode_sample_frames(ev.index, ev.counts, 10)
                counts["samples"] += len(ev.counts)
                counts["blocks"] += 1
                counts["lost_samples"] += ev.lost_before
            elif isinstance(ev, LinkEvent) and not ev.up:
                print(f"millsense record: DAQ link down: {ev.reason}", file=sys.stderr)
            if data:
                try:
                    fh.write(data)
                    fh.flush()
                except OSError as exc:
                    print(f"millsense record: error: writing {args.out}: {exc.strerror or exc}", file=sys.stderr)
                    code = 1
                    break
                counts["bytes"] += len(data)
    finally:
        driver.close()
        try:
            fh.close()
        except OSError as exc:  # the last flush can fail on a full disk too
            if code == 0:
                print(f"millsense record: error: closing {args.out}: {exc.strerror or exc}", file=sys.stderr)
            code = 1
        for s, h in old.items():
            signal.signal(s, h)
        print(
            f"millsense record: {counts['samples']} samples in {counts['blocks']} blocks, "
            f"{counts['lost_samples']} lost, {counts['descriptors']} descriptors, "
            f"{counts['bytes']} bytes -> {args.out}",
            file=sys.stderr,
        )
    return code
