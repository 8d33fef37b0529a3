"""`millsense record`: save what the configured DAQ sends, as a capture in stream framing.

Whatever the transport, the file holds DESCRIPTOR and SAMPLES frames as the
stream transport would carry them (Modbus data is re-framed), so a capture from
any DAQ replays through the same decoder.  A full disk (or a file-size limit)
is a clear error, exit 1: the file is cut back to the last whole frame that was
written, so it replays to its end, and the counts printed are those of the
file.  The file is written unbuffered, so that what is known written is on disk.
"""

from __future__ import annotations

import argparse
import os
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


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.commands.run import driver_options
    from millsense.daemon.config import load_config
    from millsense.drivers import DriverError, create_driver
    from millsense.drivers.base import LinkEvent, SampleBlock
    from millsense.drivers.protocol import INDEX_MOD, Descriptor, encode_descriptor, encode_samples

    settings = load_config(args.config)
    daq = settings.daq
    try:
        driver = create_driver(daq.transport, **driver_options(daq))
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
        fh = open(args.out, "wb", buffering=0)  # noqa: SIM115 - closed in finally
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
            frames: list[tuple[bytes, int]] = []  # (frame, samples in it)
            lost = 0
            if isinstance(ev, Descriptor):
                frames.append((encode_descriptor(ev), 0))
                written_descriptor = ev
            elif isinstance(ev, SampleBlock):
                if written_descriptor is None and driver.descriptor is not None:
                    written_descriptor = driver.descriptor
                    frames.append((encode_descriptor(written_descriptor), 0))
                for a in range(0, len(ev.counts), FRAME_SAMPLES):
                    part = ev.counts[a : a + FRAME_SAMPLES]
                    frames.append((encode_samples((ev.index + a) % INDEX_MOD, part), len(part)))
                lost = ev.lost_before
            elif isinstance(ev, LinkEvent) and not ev.up:
                print(f"millsense record: DAQ link down: {ev.reason}", file=sys.stderr)
            if not frames:
                continue
            kept, error = _write_frames(fh, frames, counts["bytes"])
            for frame, n in frames[:kept]:
                counts["bytes"] += len(frame)
                counts["samples"] += n
                if n == 0:
                    counts["descriptors"] += 1
            if kept and isinstance(ev, SampleBlock):
                counts["blocks"] += 1
                counts["lost_samples"] += lost
            if error is not None:
                print(f"millsense record: error: writing {args.out}: {error.strerror or error}; the capture ends "
                      "with the last whole frame written", file=sys.stderr)
                code = 1
                break
    finally:
        driver.close()
        try:
            fh.close()
        except OSError as exc:
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


FRAME_SAMPLES = 10


def _write_frames(fh, frames: list[tuple[bytes, int]], at: int) -> tuple[int, OSError | None]:
    """Write whole frames at offset `at`: (how many made it whole, the error that stopped it).

    On an error (ENOSPC, EFBIG) the file is cut back to the end of the last whole
    frame; cutting frees space, so it works on a full disk too.
    """
    data = b"".join(f for f, _ in frames)
    done = 0
    error: OSError | None = None
    while done < len(data):
        try:
            n = fh.write(memoryview(data)[done:])
        except OSError as exc:
            error = exc
            break
        if not n:  # a raw write that took nothing: the device is full
            error = OSError(28, os.strerror(28))
            break
        done += n
    if error is None:
        return len(frames), None
    kept, end = 0, 0
    for f, _ in frames:
        if end + len(f) > done:
            break
        end += len(f)
        kept += 1
    try:
        os.ftruncate(fh.fileno(), at + end)
        fh.seek(at + end)
    except OSError:
        pass  # nothing better to do: the decoder skips a torn last frame anyway
    return kept, error
