"""`millsense record`: save what the configured DAQ sends, as a capture in stream framing.

Whatever the transport, the file holds DESCRIPTOR and SAMPLES frames as the
stream transport would carry them (Modbus data is re-framed), so a capture from
any DAQ replays through the same decoder.  A full disk (or a file-size limit)
is a clear error, exit 1: the file is cut back to the last whole frame that was
written, so it replays to its end, and the counts printed are those of the
file.  The file is written unbuffered, so that what is known written is on disk.

The capture is written to a hidden file beside `--out` and renamed to it at the
end: a DAQ that never answers, or a stop before it does, leaves nothing (and an
older capture of that name as it was). A device or pipe (`/dev/stdout`) is
written directly; a symbolic link is followed to the file it names (the file is
replaced, the link kept). The log goes to stderr, never into the capture.
"""

from __future__ import annotations

import argparse
import os
import signal
import stat
import sys
import time
from pathlib import Path

PROG = "millsense record"
CONNECT_WINDOW_S = 10.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", required=True, metavar="FILE", help="daemon configuration (its [daq] section)")
    parser.add_argument("--out", required=True, metavar="CAPTURE", help="capture file to write")
    parser.add_argument(
        "--seconds", type=float, default=None, metavar="N", help="stop after N seconds (default: until Ctrl-C)"
    )
    parser.add_argument("--connect-timeout", type=float, default=CONNECT_WINDOW_S, metavar="S",
                        help=f"give up (exit 69) if the DAQ has not connected within S seconds (default {CONNECT_WINDOW_S:g})")
    # the spelling before `run` and `record` agreed: old scripts keep working
    parser.add_argument("--connect-timeout-s", type=float, dest="connect_timeout", default=argparse.SUPPRESS,
                        help=argparse.SUPPRESS)


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.commands.run import _last_error, driver_options, positive_option
    from millsense.daemon.config.load import load_config
    from millsense.drivers import DriverError, create_driver
    from millsense.drivers.base import LinkEvent, SampleBlock
    from millsense.drivers.protocol import INDEX_MOD, Descriptor, encode_descriptor, encode_samples

    problem = positive_option(args.seconds, "--seconds") or positive_option(args.connect_timeout, "--connect-timeout")
    if problem:
        return _fail(problem, 2)
    if Path(args.out).is_dir():
        return _fail(f"--out {args.out} is a directory: give a file name for the capture", 2)
    settings = load_config(args.config)
    from millsense.daemon.logging_setup import configure_logging

    # The log (the DAQ's link up and down) on stderr: stdout may be the capture (`--out /dev/stdout | …`).
    configure_logging("info", "auto", sys.stderr, nonblocking=False)
    daq = settings.daq
    try:
        driver = create_driver(daq.transport, **driver_options(daq))
    except DriverError as exc:
        return _fail(str(exc), 78)
    stop = {"now": False}

    def _stop(*_a) -> None:
        stop["now"] = True

    counts = {"samples": 0, "blocks": 0, "lost_samples": 0, "descriptors": 0, "bytes": 0}
    code = 0
    try:
        out = _Output(args.out)
    except OSError as exc:
        return _fail(f"cannot write {args.out}: {exc.strerror or exc}", 1)
    fh = out.fh
    old = {s: signal.signal(s, _stop) for s in (signal.SIGINT, signal.SIGTERM)}
    driver.start()
    try:
        connect_by = time.monotonic() + args.connect_timeout
        while not driver.wait_connected(0.1):
            if stop["now"] or time.monotonic() >= connect_by:
                out.discard()
                if stop["now"]:
                    return _fail(f"stopped before the DAQ connected; nothing written to {args.out}", 1)
                where = getattr(driver, "address", "?")
                return _fail(f"DAQ unreachable: no connection to {daq.transport} {where} within "
                             f"{args.connect_timeout:g} s{_last_error(driver)}; nothing written to {args.out}", 69)
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
                print(f"{PROG}: error: writing {args.out}: {error.strerror or error}; the capture ends "
                      "with the last whole frame written", file=sys.stderr)
                code = 1
                break
    except BaseException:
        out.discard()  # a bug or Ctrl-C twice: no half-named file left behind
        raise
    finally:
        driver.close(why=f"{PROG} is stopping")
        for s, h in old.items():
            signal.signal(s, h)
    # A full disk mid-way keeps what was recorded (cut to whole frames): samples that cannot be taken again.
    # No sample at all is a failure, not an empty capture.
    try:
        out.finish(keep=counts["samples"] > 0)
    except OSError as exc:
        _fail(f"closing {args.out}: {exc.strerror or exc}", 1)
        code = 1
    if not out.kept:
        if code == 0:
            why = "stopped" if stop["now"] else f"within {args.seconds:g} s"
            _fail(f"the DAQ sent no samples ({why}); nothing written to {args.out}", 1)
        return 1
    print(
        f"{PROG}: {counts['samples']} samples in {counts['blocks']} blocks, "
        f"{counts['lost_samples']} lost, {counts['descriptors']} descriptors, "
        f"{counts['bytes']} bytes -> {args.out}",
        file=sys.stderr,
    )
    return code


class _Output:
    """The capture file: a hidden file beside the target, renamed onto it by `finish`.

    A target that exists and is not a regular file (a device, a pipe) is
    written directly: there is nothing to rename onto it.
    """

    def __init__(self, target: str) -> None:
        self.target = Path(target)
        self.kept = False
        try:
            direct = not stat.S_ISREG(self.target.stat().st_mode)
        except FileNotFoundError:
            direct = False
        # A link is followed to the file it names, which is replaced; the link never is: `--out /dev/stdout`
        # into a file renamed the capture over the host's /dev/stdout (as root), `latest.cap` lost its link.
        self.final = self.target if direct else Path(os.path.realpath(self.target))
        self.path = self.target if direct else self.final.with_name(f".{self.final.name}.{os.getpid()}.tmp")
        flags = os.O_WRONLY | os.O_CREAT | (0 if direct else os.O_EXCL | os.O_TRUNC)
        fd = os.open(self.path, flags, 0o666)
        self.fh = open(fd, "wb", buffering=0)  # noqa: SIM115 - closed in finish/discard

    def finish(self, keep: bool) -> None:
        """Close; then rename onto the target (keep) or remove. Raises the close's OSError after.

        A device or pipe is always kept: what went to it cannot be taken back.
        """
        keep = keep or self.path == self.target
        error = None
        try:
            self.fh.close()
        except OSError as exc:
            error = exc
        if not keep:
            self.discard()
        elif self.path != self.target:
            os.replace(self.path, self.final)
        self.kept = keep
        if error is not None:
            raise error

    def discard(self) -> None:
        try:
            self.fh.close()
        except OSError:
            pass
        if self.path != self.target:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass


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
