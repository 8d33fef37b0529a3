"""`millsense replay CAPTURE --config FILE`: the live pipeline on a capture, JSON lines out.

Same `PipelineCore` (estimator + alarms) as `millsense run`, fed as fast as the
file can be read. One JSON object per line on stdout, `"type": "estimate"` or
`"type": "alarm"` (and `"type": "process"`, one per finished process, with learned limits on), in the payload formats of interfaces.md with `machine`.
`t` is the time of the revolution's last sample (of the deciding sample, for
an alarm) in seconds after the capture's first sample: sample-index difference
over the sample rate, so results are reproducible. Alarms carry
`"interlock": null`: nothing is driven.

A corrupt or truncated capture is decoded as far as it goes (the stream
decoder drops bad bytes and hunts for the next sync, exactly as live); the
counts of what was dropped go to stderr, one line, after the output. After it,
one warning line each for what the live daemon would raise: the wiring check
(`power_check.py`), and fault `signals` where it is raised and cleared (live,
the daemon is blind then, and holds the feed under `[interlock] on_blind =
"hold"`).

`--plot OUT.png` also draws the run (`daemon/plot.py`: rpm, torque, force,
depths, alarms, lost-sample spans) once the input is read; stdout is the same
with or without it. matplotlib is the optional `plot` extra: it is checked
before anything is read, so a missing extra is one error line and exit 1.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

CHUNK_BYTES = 1 << 20
JOIN_SAMPLES = 16384  # a joined block: numpy's per-call overhead spread over more samples, still a small array
PROG = "millsense replay"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", metavar="CAPTURE", help="a capture file (the DAQ byte stream)")
    parser.add_argument("--config", "-c", metavar="FILE", required=True, help="the daemon's configuration file")
    parser.add_argument("--plot", metavar="OUT.png", default=None,
                        help="also draw rpm, torque, force and depths over time, alarms marked, to a PNG "
                             "(needs the plot extra: pip install 'millsense[plot]')")


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.config.load import load_config

    settings = load_config(args.config)  # ConfigError -> exit 78 in the CLI
    from millsense.daemon.logging_setup import configure_logging

    # stdout is the JSON lines: anything a module logs goes to stderr, warnings and worse only
    configure_logging("warning", "console", sys.stderr, nonblocking=False)
    path = Path(args.capture)
    plot = None
    if args.plot:
        from millsense.daemon.plot import PlotUnavailable, ReplayPlot, require_matplotlib

        try:
            require_matplotlib()
        except PlotUnavailable as exc:
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return 1
        if not Path(args.plot).resolve().parent.is_dir():
            print(f"{PROG}: error: --plot {args.plot}: no such directory", file=sys.stderr)
            return 1
        plot = ReplayPlot()
    try:
        fh = path.open("rb")
    except OSError as exc:
        print(f"{PROG}: error: cannot read {path}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    with fh:
        replay = Replay(settings, sys.stdout, on_payload=plot.add if plot else None)
        while chunk := fh.read(CHUNK_BYTES):
            replay.feed(chunk)
    sys.stdout.flush()
    print(f"{PROG}: {replay.summary()}", file=sys.stderr)
    for warning in replay.warnings:
        print(f"{PROG}: warning: {warning}", file=sys.stderr)
    if replay.core.descriptor is None:
        print(f"{PROG}: error: {path}: no DAQ descriptor frame found (is this a millsense capture?)", file=sys.stderr)
        return 1
    if plot is not None:
        try:
            plot.write(args.plot, title=f"millsense replay {path.name} ({replay.machine})")
        except OSError as exc:
            print(f"{PROG}: error: cannot write {args.plot}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        print(f"{PROG}: wrote {args.plot}", file=sys.stderr)
    return 0


class Replay:
    """Bytes in (any chunking), JSON lines out."""

    def __init__(self, settings, out, on_payload=None):
        from millsense.daemon.pipeline.run_core import PipelineCore
        from millsense.drivers.base import IndexTracker
        from millsense.drivers.protocol import StreamDecoder

        self.settings = settings
        self.machine = str(settings.machine)
        self.core = PipelineCore(settings)
        self.decoder = StreamDecoder()
        self.tracker = IndexTracker()
        self.out = out
        self.on_payload = on_payload        # e.g. the --plot recorder; sees every payload written
        self.first_seq: int | None = None
        self.rate: float | None = None
        self.counts = {"estimates": 0, "invalid_estimates": 0, "alarms": 0, "processes": 0, "discontinuities": 0,
                       "lost_samples": 0}
        self._context = None  # the DAQ repeats its CONTEXT once a second: only a change is news
        from millsense.daemon.pipeline.power_check import PowerSignCheck

        self.power_check = PowerSignCheck()
        self.loss_check = None              # the share of the stream lost (loss_check.py), from the descriptor's rate
        self.phase_check = None             # the currents against each other and the voltages (phase_check.py)
        self.warnings: list[str] = []       # what the live daemon would raise: the wiring check, fault `signals`
        # contiguous SAMPLES runs joined into one block (seq, first index, lost before, discontinuity, parts)
        self._pending: tuple[int, int, int, bool, list] | None = None
        self._pending_n = 0

    def feed(self, data: bytes) -> None:
        """Decode `data` and process it. Consecutive SAMPLES runs are joined into blocks of up to
        `JOIN_SAMPLES` (the estimates do not depend on where blocks are cut: tests/estimator/
        test_vectorised.py); a block is closed before every other frame, which acts from the next sample."""
        from millsense.drivers.protocol import Context, Descriptor, Samples, Status

        lines: list[bytes] = []
        for frame in self.decoder.feed(data):
            if isinstance(frame, Samples):
                if self.core.estimator is None:
                    continue
                n = len(frame.counts)
                seq, lost, disc = self.tracker.update(frame.first_index, n)
                if self.first_seq is None:
                    self.first_seq = seq
                self.counts["lost_samples"] += lost
                self.counts["discontinuities"] += int(disc)
                if self.loss_check is not None:   # frame by frame, as the live daemon's blocks come
                    self._note_fault_change("signals", seq, self.loss_check.update(seq, n, lost, disc))
                if lost or disc or self._pending_n + n > JOIN_SAMPLES:
                    self._flush(lines)
                if self._pending is None:
                    self._pending = (seq, frame.first_index, lost, disc, [frame.counts])
                else:
                    self._pending[4].append(frame.counts)
                self._pending_n += n
                continue
            if isinstance(frame, Descriptor):
                if frame == self.core.descriptor:
                    continue  # the DAQ's once-a-second repeat
                self._flush(lines)
                if self.core.descriptor is not None:
                    self.tracker.mark_discontinuity()
                if self.core.on_descriptor(frame):  # ConfigError: the capture does not fit the config
                    self.rate = float(frame.sample_rate_hz)
                    from millsense.daemon.pipeline.loss_check import LossCheck

                    last_loss, last_phase = self.loss_check, self.phase_check   # the new ones go on from them
                    self.loss_check = LossCheck(self.rate, faulted=last_loss is not None and last_loss.faulted)
                    from millsense.daemon.pipeline.phase_check import PhaseCheck

                    self.phase_check = PhaseCheck(self.settings, frame,
                                                  faulted=last_phase is not None and last_phase.faulted)
                continue
            if isinstance(frame, Context):  # protocol 2: what the CNC does from frame.index on
                if frame != self._context:
                    self._flush(lines)
                    self._context = frame
                    self._write_items(self.core.on_context(frame).items, lines)
                continue
            if isinstance(frame, Status):  # the CNC's applied feed override, as the live daemon notes it
                self._flush(lines)
                self.core.on_status(frame)
                continue
        self._flush(lines)
        if lines:
            self.out.write(b"\n".join(lines).decode() + "\n")

    def _flush(self, lines: list[bytes]) -> None:
        """Process the joined SAMPLES runs waiting, if any."""
        if self._pending is None:
            return
        import numpy as np

        from millsense.drivers.base import SampleBlock

        seq, index, lost, disc, parts = self._pending
        self._pending, self._pending_n = None, 0
        counts = parts[0] if len(parts) == 1 else np.concatenate(parts)
        # The phase check first (it reads only the raw samples): while it holds fault `signals`, every
        # revolution is invalid, `invalid: "phase"`, as live (runner.py `_set_stream_problem`). A joined block
        # is up to 16 s, so it is cut where the check changed (the estimates do not depend on where blocks are
        # cut) rather than judged a block late as the live daemon's 0.1-s blocks are.
        pieces: list[tuple[int, bool]] = []   # (end of a piece, the check faulted within it)
        if self.phase_check is not None:
            faulted = self.phase_check.faulted
            self.phase_check.update(counts, lost, disc)
            for at, verdict in self.phase_check.changes:   # every change: a large block may raise and clear it
                self._note_fault_change("signals", seq + at, verdict)
                pieces.append((at + 1, faulted))
                faulted = bool(verdict)
            pieces.append((len(counts), faulted))
        else:
            pieces.append((len(counts), False))
        start = 0
        for end, faulted in pieces:
            if end <= start:
                continue
            self.core.stream_problem = self._stream_problem(faulted)
            first = start == 0
            step = self.core.process(SampleBlock(seq + start, (index + start) & 0xFFFFFFFF, counts[start:end],
                                                 lost if first else 0, disc and first))
            self._write_items(step.items, lines)
            self._note_faults(step)
            start = end
        self.core.stream_problem = self._stream_problem(self.phase_check is not None and self.phase_check.faulted)

    def _stream_problem(self, phase_faulted: bool) -> str | None:
        """As live (runner.py `_set_stream_problem`, without the rate check a capture cannot make): the power
        check's fault from the next block on (it judges the estimates a block makes)."""
        return "phase" if phase_faulted else "wiring" if self.power_check.faulted else None

    def _note_faults(self, step) -> None:
        """The faults the live daemon would raise or clear, at the sample where each was decided."""
        for kind, seq, reason in step.fault_changes:
            self._note_fault_change(kind, seq, reason)

    def _note_fault_change(self, kind: str, seq: int, reason: str | None) -> None:
        """A reason: raised at `seq`; "": cleared; None: no change."""
        if reason is None:
            return
        t = self._t(seq)
        at = "?" if t is None else f"{t:.3f}"
        self.warnings.append(f"fault {kind} from t={at} s: {reason}" if reason else f"fault {kind} cleared at t={at} s")

    def _write_items(self, items: list, lines: list[bytes]) -> None:
        from millsense.daemon.pipeline.alarms import alarm_payload
        from millsense.daemon.pipeline.run_core import estimate_payload, process_payload
        from millsense.daemon.publish.payload import dumps

        for kind, item in items:
            if kind == "estimate":
                if verdict := self.power_check.update(item):
                    self.warnings.append(f"from rev {item.get('rev')}: {verdict}")
                payload = estimate_payload(item, self.machine, self._t(item.get("seq_end")), kind="estimate")
                self.counts["estimates"] += 1
                self.counts["invalid_estimates"] += int(not item.get("valid", True))
            elif kind == "process":
                payload = {"type": "process", **process_payload(item, self.machine, self._t(item.get("seq_end")))}
                self.counts["processes"] += 1
            else:
                payload = {"type": "alarm", **alarm_payload(item, self.machine, self._t(item.seq), None)}
                self.counts["alarms"] += 1
            lines.append(dumps(payload))
            if self.on_payload is not None:
                self.on_payload(payload)

    def _t(self, seq: int | None) -> float | None:
        if seq is None or self.first_seq is None or not self.rate:
            return None
        return round((int(seq) - self.first_seq) / self.rate, 6)

    def summary(self) -> str:
        s = self.decoder.stats
        fields = {
            "frames": s.frames,
            "samples": s.samples,
            **self.counts,
            "bad_crc": s.bad_crc,
            "dropped_bytes": s.dropped_bytes,
            "unknown_type": s.unknown_type,
            "bad_length": getattr(s, "bad_length", 0),
            "descriptor_mismatch": s.descriptor_mismatch,
            "samples_before_descriptor": s.samples_before_descriptor,
            "truncated_bytes": self.decoder.buffered,  # an unfinished last frame
        }
        return " ".join(f"{k}={v}" for k, v in fields.items())
