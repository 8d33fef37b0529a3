"""Crash trip latency, end to end: the frame holding the crash sent by the DAQ → the feed-hold command received by it.

The DAQ is the project's emulator (`drivers/emulator`: device model, wire
emitter, real-time pacer, stream server on a pty or TCP), run in this process
with a pulse source (below), so that both ends are stamped by the emulator on
one clock (`time.monotonic()`): "sent" right after the write of the frame that
holds the pulse's first sample, "received" when the set-outputs command that
asserts feed hold reaches the device (the source's `feed_hold` is set by the
device on that command). The daemon is a real `millsense run` subprocess
reading that stream in 10-sample frames, with the environment its systemd unit gives it.

Pulse source: the simulator's channels, everything at 0 (the spindle stands
still), and on demand one pulse of 10 samples whose air-gap power is ~26 kW
(limit `crash_power_w` 12 kW): the smoothed power crosses the limit at the
pulse's 3rd sample, so the figure is measured from the frame holding the 1st
(never later than the crossing's). The pulse does not rotate (no electrical
frequency against a stopped spindle) and every phase swings (none looks flat),
so the signal checks stay quiet. After each trip the bench resets through the
daemon's local control socket, as an operator at the machine would; the reset
is refused until the daemon has seen a block after the hold (spindle stopped:
the condition is gone), so each cycle takes ~0.1 s.

Budget (issue 13): p99 <= 3 ms over >= 500 trips, serial (pty) and TCP.
Baseline in the same run: the same trips measured to the daemon's own
`last_trip_ms` (frame decoded → output written) where the status says it.
The daemon runs at the unit's CPU priority (`Nice=`), where this process may
set it (root); otherwise at the default, and the bench says so.

`--hog N`: the same on a loaded box. N busy processes at the default priority
compete for the CPUs (a dashboard's browser, a backup), and each transport is
measured twice, the daemon at the unit's priority and, as the baseline, at the
default. This process (the DAQ's stand-in, a device of its own on a real
machine) is raised above both, so that it is not what waits. Needs root.

Run: .venv/bin/python bench/crash_latency.py [--trips 500] [--transport both|serial|tcp] [--hog N]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from millsense.daemon.state_dir import state_dir  # noqa: E402
from millsense.daemon.local_socket import LocalControlError, local_command  # noqa: E402
from millsense.sim.emulator.device import DeviceModel, StatusLog  # noqa: E402
from millsense.sim.emulator.pacing import Pacer  # noqa: E402
from millsense.sim.emulator.ramp import RAMP_CHANNELS  # noqa: E402
from millsense.sim.emulator.stream_server import StreamServer  # noqa: E402
from millsense.sim.emulator.wire import WireEmitter  # noqa: E402
from millsense.drivers.protocol import Descriptor  # noqa: E402
from tests.conftest import free_tcp_port  # noqa: E402
from tests.e2e.helpers import Procs, tcp, write_config  # noqa: E402
from tests.faults.helpers import PULSE  # noqa: E402 - the crash pulse, in counts
from tests.ops.unit_file import unit_environment, unit_options  # noqa: E402 - the daemon as its unit runs it

BUDGET_P99_MS = 3.0
PULSE_SAMPLES = 10


class PulseSource:
    """The emulator's plant interface (descriptor, step, feed_hold) with a crash pulse on demand."""

    description = "all channels 0; a 10-sample crash pulse when armed"

    def __init__(self) -> None:
        self.descriptor = Descriptor(1000, RAMP_CHANNELS)
        self.sample_rate_hz = 1000
        self.duration_s = float("inf")
        self.truth = None
        self._hold = False
        self._armed = False
        self.pulse_in_step = False       # the last step() started a pulse
        self.hold_mono: float | None = None  # when the device took the feed-hold command

    def arm(self) -> None:
        self._armed = True

    @property
    def feed_hold(self) -> bool:
        return self._hold

    @feed_hold.setter
    def feed_hold(self, value: bool) -> None:
        if value and not self._hold:
            self.hold_mono = time.monotonic()
        self._hold = bool(value)

    def history(self, first_index: int, n: int) -> np.ndarray:
        return np.zeros((n, len(RAMP_CHANNELS)), dtype=np.int16)

    def step(self, n: int) -> np.ndarray:
        out = np.zeros((n, len(RAMP_CHANNELS)), dtype=np.int16)
        self.pulse_in_step = self._armed
        if self._armed:
            self._armed = False
            out[: min(n, PULSE_SAMPLES)] = PULSE
        return out


class Emulator:
    """The emulator's stream server on its own asyncio loop, stamping the pulse's frame as it is sent."""

    def __init__(self, transport: str, where: str | tuple[str, int], status_log: Path | None = None):
        self.source = PulseSource()
        self.device = DeviceModel(self.source, status_log=StatusLog(str(status_log) if status_log else None))
        self.server = StreamServer(self.device, WireEmitter(self.device, per_frame=10), Pacer(1000, realtime=True, quantum=10))
        self.sent_mono: float | None = None
        send = self.server._send

        def stamped(data: bytes) -> None:
            send(data)
            if self.source.pulse_in_step and data:
                self.source.pulse_in_step = False
                self.sent_mono = time.monotonic()

        self.server._send = stamped
        self._transport, self._where = transport, where
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        if not self._ready.wait(10):
            raise SystemExit("emulator did not start")

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)

        async def main() -> None:
            if self._transport == "serial":
                self.server.open_pty(self._where)
            else:
                await self.server.open_tcp(*self._where)
            self._ready.set()
            await self.server.run()

        self._loop.run_until_complete(main())

    def pulse(self) -> None:
        self.sent_mono = None
        self.source.hold_mono = None
        self._loop.call_soon_threadsafe(self.source.arm)

    def close(self) -> None:
        self._loop.call_soon_threadsafe(self.server.stop.set)
        self._thread.join(5)


def unit_nice() -> int:
    """The daemon unit's `Nice=` (0 if it sets none)."""
    return int(unit_options().get("Nice", ["0"])[-1])


def may_set_nice(nice: int) -> bool:
    """Can a child of this process run at `nice`? (Below the current one needs root or CAP_SYS_NICE.)"""
    probe = subprocess.run([sys.executable, "-c", f"import os; os.setpriority(os.PRIO_PROCESS, 0, {nice})"],
                           capture_output=True)
    return probe.returncode == 0


def run_trips(transport: str, trips: int, daemon_nice: int | None = None) -> dict:
    tmp = Path(tempfile.mkdtemp(prefix="millsense-crash-bench-"))
    if transport == "serial":
        link = str(tmp / "daq")
        where: str | tuple[str, int] = link
        daq = f'transport = "serial"\nport = "{link}"'
    else:
        port = free_tcp_port()
        where = ("127.0.0.1", port)
        daq = f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {port}'
    device_log = tmp / "device.jsonl"
    emu = Emulator(transport, where, device_log)
    cfg = write_config(tmp / "bench.toml", machine="crashbench", daq=daq, zenoh_listen=[tcp(free_tcp_port())],
                       alarms="crash_power_w = 12000.0\ncrash_current_a = 55.0", interlock="enabled = true")
    sdir = state_dir("crashbench", {"XDG_STATE_HOME": str(tmp / "state")})
    lat_ms: list[float] = []
    own_ms: list[float] = []
    missed = 0
    why: list[str] = []   # of each trip missed
    detail: list[str] = []  # what the device and the daemon said of it
    try:
        with Procs(tmp) as procs:
            at = {} if daemon_nice is None else {"preexec_fn": lambda: os.setpriority(os.PRIO_PROCESS, 0, daemon_nice)}
            procs.start("daemon", ["run", "--config", str(cfg)], env_extra=unit_environment(), **at)
            _wait(lambda: _status(sdir).get("samples_received", 0) > 2000, 60, "the daemon streaming")
            for _ in range(trips):
                held_before = emu.source.feed_hold   # the device's watchdog, say: a hold that is not this trip's
                emu.pulse()
                if not _wait(lambda: emu.source.hold_mono is not None and emu.sent_mono is not None, 2.0):
                    missed += 1
                    why.append("the pulse's frame was never sent" if emu.sent_mono is None else
                               "the feed was already held at the device" if held_before or emu.source.feed_hold else
                               "no feed hold within 2 s")
                    detail.append(_what_held(device_log, procs.text("daemon", "out") + procs.text("daemon")))
                else:
                    lat_ms.append((emu.source.hold_mono - emu.sent_mono) * 1e3)
                if not _wait(lambda: _reset(sdir), 10.0):
                    raise SystemExit(f"{transport}: the daemon refused every reset: {_status(sdir)}")
                # the release reaches the device after the reset's answer: a pulse before it finds the feed
                # still held, and no new hold to time (on a loaded box, "missed")
                _wait(lambda: not emu.source.feed_hold, 10.0, f"{transport}: the feed released at the device")
                own = _status(sdir).get("last_trip_ms")
                if own is not None:
                    own_ms.append(float(own))
                time.sleep(0.02)
    finally:
        emu.close()
    return {"lat": np.array(lat_ms), "own": np.array(own_ms), "missed": missed, "why": why, "detail": detail}


DAEMON_SAYS = ('interlock.feed_hold', 'interlock.reset"', '"fault"', 'recovered')  # a missed trip's log lines


def _what_held(device_log: Path, daemon_log: str) -> str:
    """A missed trip's evidence: the device's last two output changes (their cause: a command, or its
    watchdog) and the daemon's last holds, resets and faults (its log: stdout under the unit's environment)."""
    try:
        lines = device_log.read_text().splitlines()
    except OSError:
        lines = []
    outputs = [line for line in lines if '"event": "outputs"' in line][-2:]
    said = [line for line in daemon_log.splitlines() if any(w in line for w in DAEMON_SAYS)]
    return "\n".join(["device: " + o for o in outputs] + ["daemon: " + d[:300] for d in said[-4:]])


def _status(sdir: Path) -> dict:
    try:
        return local_command(sdir, "status")
    except (LocalControlError, OSError, ValueError):
        return {}


def _reset(sdir: Path) -> bool:
    try:
        return bool(local_command(sdir, "reset").get("ok"))
    except (LocalControlError, OSError, ValueError):
        return False


def _wait(cond, timeout_s: float, what: str | None = None) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.002)
    if what:
        raise SystemExit(f"timed out waiting for {what}")
    return False


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trips", type=int, default=500)
    ap.add_argument("--transport", choices=("both", "serial", "tcp"), default="both")
    ap.add_argument("--hog", type=int, default=0, metavar="N",
                    help="N busy processes compete for the CPUs; the daemon at the unit's priority and at the default")
    args = ap.parse_args()
    nice = unit_nice()
    if not may_set_nice(nice):
        if args.hog:
            raise SystemExit(f"--hog needs root: the daemon at the unit's Nice={nice} and this process above it")
        print(f"(the daemon at the default priority: this process may not give it the unit's Nice={nice})")
        nice = 0
    hogs: list[subprocess.Popen] = []
    if args.hog:
        os.setpriority(os.PRIO_PROCESS, 0, min(nice, 0) - 5)   # the DAQ's stand-in: never what waits
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                                 preexec_fn=lambda: os.setpriority(os.PRIO_PROCESS, 0, 0)) for _ in range(args.hog)]
    print(f"crash trip latency: frame holding the crash sent → feed-hold command received (emulator's clock), "
          f"10-sample frames, {args.trips} trips each; budget p99 <= {BUDGET_P99_MS:g} ms"
          + (f"; {args.hog} busy processes at the default priority" if hogs else ""))
    ok = True
    try:
        for transport in (("serial", "tcp") if args.transport == "both" else (args.transport,)):
            for daemon_nice in ((nice, 0) if hogs else (nice,)):
                label = f"{transport:<6}" + (f" daemon at nice {daemon_nice:>2}" if hogs else "")
                r = run_trips(transport, args.trips, daemon_nice)
                ok = report(label, r) and ok
    finally:
        for h in hogs:
            h.kill()
            h.wait(5)
    return 0 if ok else 1


def report(label: str, r: dict) -> bool:
    lat, own = r["lat"], r["own"]
    if not len(lat):
        print(f"  {label} no trip measured ({r['missed']} missed)")
        return False
    p50, p99 = np.percentile(lat, [50, 99])
    own_txt = (f"   daemon's own share (frame decoded → output written) p50 {np.percentile(own, 50):.2f} "
               f"p99 {np.percentile(own, 99):.2f} ms" if len(own) else "")
    verdict = "OK" if p99 <= BUDGET_P99_MS and r["missed"] == 0 else "OVER BUDGET"
    print(f"  {label} p50 {p50:.2f}  p99 {p99:.2f}  max {lat.max():.2f} ms  ({len(lat)} trips, "
          f"{r['missed']} missed)  {verdict}{own_txt}")
    for reason in sorted(set(r["why"])):
        print(f"    missed {r['why'].count(reason)}: {reason}")
    for d in r.get("detail", []):
        print("      " + d.replace("\n", "\n      "))
    return verdict == "OK"


if __name__ == "__main__":
    sys.exit(main())
