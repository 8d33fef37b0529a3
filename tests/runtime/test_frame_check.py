"""The sample-level crash check on every frame, where it lands (issue 13).

The per-frame check (`safety_check.FrameCheck`) runs on the driver's reader
thread and holds the feed from there; the estimator thread wakes only every
~50 ms or when a revolution is due, and processes the frames as one block.
Checked here: the frame check computes exactly the estimator's sample-level
power and current; a crash inside one 10-sample frame holds the feed while the
estimator thread is stuck (so before any revolution closes and before its batch
runs) through the real emulator over real TCP, and is published once when the
estimator goes on; the reset re-arms it; frames are merged into batches.
"""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest

from millsense.daemon.config.load import demo_config, load_config
from millsense.daemon.pipeline.estimator import Estimator
from millsense.daemon.runtime.blocks import merged
from millsense.daemon.runtime.runner import Runner
from millsense.daemon.pipeline.safety_check import FrameCheck
from millsense.drivers.base import LinkEvent, SampleBlock
from millsense.sim.emulator.device import DeviceModel
from millsense.sim.emulator.pacing import Pacer
from millsense.sim.emulator.ramp import RAMP_CHANNELS
from millsense.sim.emulator.stream_server import StreamServer
from millsense.sim.emulator.wire import WireEmitter
from millsense.drivers.protocol import Descriptor
from millsense.sim import Plant
from millsense.drivers.tcp_driver import TcpDriver
from tests.conftest import free_tcp_port
from tests.e2e.helpers import write_config

pytestmark = pytest.mark.quick

# counts: 300 V line voltages (0.02 V/count), 30 A / 60 A line currents (0.002 A/count), each set summing
# to zero, not rotating: ~26 kW of air-gap power against crash_power_w 12 kW, crossed at the 3rd sample
PULSE = np.array([15000, 15000, -30000, 15000, 15000, -30000, 0, 0], dtype=np.int16)


def wait_for(pred, timeout_s, what):
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out: {what}")
        time.sleep(0.005)


# ---------------------------------------------------------------- the check itself


def _check_as_the_estimator(fc: FrameCheck, est: Estimator, a: int, frame: np.ndarray):
    """`fc.check` on the frame with the filter gain the estimator divided each sample by: a revolution that
    closed inside the frame changes it from the sample after (`Estimator.gain_steps`). Returns the smoothed
    power and current, and the first crash found."""
    steps = est.gain_steps
    power, current, crash = [], [], None
    for k, (start, gain) in enumerate(steps):
        stop = steps[k + 1][0] if k + 1 < len(steps) else a + len(frame)
        if stop == start:   # a revolution that ended on the sample before the frame: its gain from the first
            continue
        found, _ = fc.check(start, frame[start - a : stop - a], 0, False, gain)
        crash = crash or found
        power.append(fc.p_gap_w)
        current.append(fc.current_a)
    return np.concatenate(power), np.concatenate(current), crash


def test_frame_check_computes_the_estimators_sample_level_power_and_current():
    settings = demo_config()
    plant = Plant("crash")
    fc, est = FrameCheck(settings, plant.descriptor), Estimator(settings, plant.descriptor)
    raw = plant.step(20000)
    compared = split = 0
    peak_w = peak_a = 0.0
    for a in range(0, len(raw), 10):
        res = est.process(SampleBlock(a, a, raw[a : a + 10], 0, False))
        split += len(est.gain_steps) > 1
        p_gap_w, current_a, _ = _check_as_the_estimator(fc, est, a, raw[a : a + 10])
        np.testing.assert_allclose(p_gap_w, res.p_gap_w, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(current_a, res.current_a, rtol=1e-12)
        compared += len(res.p_gap_w)
        peak_w, peak_a = max(peak_w, float(np.abs(p_gap_w).max())), max(peak_a, float(current_a.max()))
    assert compared == len(raw)
    assert split > 50  # frames in which a revolution closed: the gain changed inside them
    # the numbers agreed where they decide a trip: through the scenario's crash, over both crash limits (two
    # sides that both read zero, or a comparison that never reached the crash, would agree just as well)
    assert peak_w > settings.alarms.crash_power_w, f"compared up to {peak_w:.0f} W only"
    assert peak_a > settings.alarms.crash_current_a, f"compared up to {peak_a:.1f} A only"


@pytest.mark.parametrize("winding, drop, offsets", [
    ("delta", (), {}),
    ("wye", (), {"i_u": 37.5, "v_vw": -120.0}),
    ("delta", ("i_w",), {"i_v": -12.0}),                 # the third current from the other two
    ("wye", ("i_w", "v_wu"), {"i_u": 5.0, "v_uv": 80.0}),  # the two-wattmeter form
], ids=["delta-3v3i", "wye-3v3i-offsets", "delta-3v2i-offset", "wye-2v2i-offsets"])
def test_the_frame_check_agrees_with_the_estimator_whatever_the_wiring(tmp_path, winding, drop, offsets):
    """The frame's arithmetic is compiled from the physics module's formulas (`_frame_program`): each
    wiring the estimator knows, with offsets, on noisy counts, gives its numbers."""
    from tests.estimator import configs, synthetic

    text = configs.toml_text(winding=winding, drop=drop)
    for name, off in offsets.items():
        scale = 0.02 if name.startswith("v") else 0.002
        text = text.replace(f"[channels.{name}]\nscale = {scale}\n", f"[channels.{name}]\nscale = {scale}\noffset = {off}\n")
    (tmp_path / "t.toml").write_text(text)
    settings = load_config(tmp_path / "t.toml")
    chans = tuple(c for c in synthetic.CHANNELS if c[1] not in drop)
    raw = synthetic.counts(synthetic.Machine(winding=winding), 3000, chans)
    noise = np.random.default_rng(7).integers(-40, 41, size=raw.shape)
    raw = np.clip(raw.astype(np.int32) + noise, -32768, 32767).astype(np.int16)
    desc = synthetic.descriptor(chans)
    fc, est = FrameCheck(settings, desc), Estimator(settings, desc)
    for name in offsets:   # the offsets reached both: a wrong sign or a dropped one would show below
        assert f"{offsets[name]!r}" in fc.program_source or f"{-offsets[name]!r}" in fc.program_source
    for a in range(0, len(raw), 10):
        res = est.process(SampleBlock(a, a, raw[a : a + 10], 0, False))
        p_gap_w, current_a, _ = _check_as_the_estimator(fc, est, a, raw[a : a + 10])
        np.testing.assert_allclose(p_gap_w, res.p_gap_w, rtol=1e-9, atol=1e-6)
        np.testing.assert_allclose(current_a, res.current_a, rtol=1e-12)
    assert np.abs(res.p_gap_w).max() > 100.0 and res.current_a.max() > 5.0   # a running motor was compared


def test_the_frame_check_finds_the_crash_the_estimators_safety_check_finds():
    from millsense.daemon.pipeline.alarms import AlarmEngine
    from millsense.daemon.pipeline.safety_check import SafetyCheck

    settings = demo_config()
    plant = Plant("crash")
    fc, est = FrameCheck(settings, plant.descriptor), Estimator(settings, plant.descriptor)
    engine, safety = AlarmEngine(settings.alarms), SafetyCheck(settings.alarms, 1000.0)
    raw = plant.step(40000)
    old = new = None
    for a in range(0, len(raw), 10):
        res = est.process(SampleBlock(a, a, raw[a : a + 10], 0, False))
        events = safety.on_block(res, engine).events
        old = old or (events[0] if events else None)
        _, _, crash = _check_as_the_estimator(fc, est, a, raw[a : a + 10])
        new = new or crash
        if old and new:
            break
    assert old is not None, "the scenario's crash was not found by the old check"
    assert new is not None and (new.seq, new.quantity) == (old.seq, old.quantity)
    assert new.value == pytest.approx(old.value, rel=1e-9)


def test_the_first_crash_sample_of_a_frame_latches_until_rearmed():
    settings = demo_config()
    desc = Descriptor(1000, RAMP_CHANNELS)
    fc = FrameCheck(settings, desc)
    quiet = np.zeros((10, 8), dtype=np.int16)
    frame = quiet.copy()
    frame[4:] = PULSE
    assert fc.check(0, quiet) == (None, False)
    crash, high = fc.check(10, frame)
    assert crash is not None and crash.quantity == "p_gap_w" and crash.level == "crash"
    # the mean over 5 samples passes 12 kW at the pulse's 3rd sample: index 10 + 4 + 2
    assert crash.seq == 16 and crash.value > settings.alarms.crash_power_w
    assert high  # the current is over stall_current_a: the estimator must look at once
    assert fc.check(20, np.repeat(PULSE[None], 10, axis=0))[0] is None  # latched: one crash per latch
    fc.rearm()
    assert fc.check(30, np.repeat(PULSE[None], 10, axis=0))[0] is not None


def test_a_current_at_its_sensor_limit_after_swinging_high_is_a_crash_one_stuck_there_is_not():
    settings = demo_config()
    settings.alarms.crash_power_w = None  # the current alone decides here
    settings.channels["i_u"].raw_min, settings.channels["i_u"].raw_max = -20000, 20000  # a ±40 A sensor
    desc = Descriptor(1000, RAMP_CHANNELS)
    t = np.arange(60)
    swing = np.zeros((60, 8), dtype=np.int16)
    swing[:, 3] = (15000 * np.sin(2 * np.pi * t / 20)).astype(np.int16)  # i_u swings ±30 A
    swing[:, 4] = -swing[:, 3]
    fc = FrameCheck(settings, desc)
    for a in range(0, 60, 10):
        assert fc.check(a, swing[a : a + 10])[0] is None
    clipped = swing[50:60].copy()
    clipped[3, 3] = 20000  # its limit, after swinging a quarter of the range: saturated by a crash
    crash, _ = fc.check(60, clipped)
    assert crash is not None and crash.quantity == "current_a" and crash.seq == 63
    assert crash.value < settings.alarms.crash_current_a  # below the limit: the clip alone decided

    stuck = np.zeros((10, 8), dtype=np.int16)
    stuck[:, 3] = 20000  # pinned at its limit from the start: a sensor fault, not a crash
    fresh = FrameCheck(settings, desc)
    for a in range(0, 100, 10):
        assert fresh.check(a, stuck)[0] is None


def test_contiguous_frames_become_one_block_and_a_gap_or_an_event_starts_another():
    def blk(seq, n=10, lost=0, checked=True):
        return SampleBlock(seq, seq, np.full((n, 8), seq, dtype=np.int16), lost, False, checked, 100.0 + seq)

    link = LinkEvent(True, "connected")
    out = merged([blk(0), blk(10), blk(20), link, blk(30), blk(45, lost=5), blk(55, checked=False)])
    kinds = [(type(ev).__name__, getattr(ev, "seq", None), len(getattr(ev, "counts", ()))) for ev, _ in out]
    assert kinds == [("SampleBlock", 0, 30), ("LinkEvent", None, 0), ("SampleBlock", 30, 10),
                     ("SampleBlock", 45, 10), ("SampleBlock", 55, 10)]
    first, parts = out[0]
    assert parts == [(0, 10, 100.0), (10, 10, 110.0), (20, 10, 120.0)]  # each frame's own arrival
    assert np.array_equal(first.counts[:, 0], np.repeat([0, 10, 20], 10)) and first.checked
    assert out[3][0].lost_before == 5


# ---------------------------------------------------------------- the live path, real emulator over TCP


class PulseSource:
    """The emulator's plant interface: every channel 0 (spindle still), a 10-sample crash pulse on demand."""

    def __init__(self):
        self.descriptor = Descriptor(1000, RAMP_CHANNELS)
        self.sample_rate_hz = 1000
        self.duration_s = float("inf")
        self.truth = None
        self.armed = False
        self.held = threading.Event()  # the device took a set-outputs command with feed hold
        self._hold = False

    @property
    def feed_hold(self):
        return self._hold

    @feed_hold.setter
    def feed_hold(self, value):
        self._hold = bool(value)
        if value:
            self.held.set()

    def history(self, first_index, n):
        return np.zeros((n, 8), dtype=np.int16)

    def step(self, n):
        out = np.zeros((n, 8), dtype=np.int16)
        if self.armed:
            self.armed = False
            out[: min(n, 10)] = PULSE
        return out


class GatedEstimator(Estimator):
    """The real estimator, whose thread can be held inside `process` by the test."""

    gate = threading.Event()
    entered = threading.Event()
    sizes: list[int] = []

    def process(self, block):
        GatedEstimator.entered.set()
        GatedEstimator.gate.wait(30)
        GatedEstimator.sizes.append(len(block.counts))
        return super().process(block)


class Sink:
    def __init__(self):
        self.items = []
        self.lock = threading.Lock()

    def estimate(self, p):
        with self.lock:
            self.items.append(("estimate", p))

    def alarm(self, p):
        with self.lock:
            self.items.append(("alarm", p))

    def status(self, p):
        pass

    def close(self):
        pass

    def alarms(self, level=None):
        with self.lock:
            return [p for k, p in self.items if k == "alarm" and (level is None or p["level"] == level)]


@pytest.fixture
def live(tmp_path):
    source = PulseSource()
    device = DeviceModel(source)
    server = StreamServer(device, WireEmitter(device, per_frame=10), Pacer(1000, realtime=True, quantum=10))
    port = free_tcp_port()
    loop = asyncio.new_event_loop()
    ready = threading.Event()

    async def main():
        await server.open_tcp("127.0.0.1", port)
        ready.set()
        await server.run()

    thread = threading.Thread(target=loop.run_until_complete, args=(main(),), daemon=True)
    thread.start()
    assert ready.wait(10)
    cfg = write_config(tmp_path / "c.toml", machine="fc", daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {port}',
                       alarms="crash_power_w = 12000.0\ncrash_current_a = 55.0\nstall_current_a = 45.0",
                       interlock="enabled = true")
    settings = load_config(cfg)
    drv = TcpDriver("127.0.0.1", port)
    drv.start()
    assert drv.wait_connected(10)
    wait_for(lambda: drv.descriptor is not None, 10, "descriptor")
    GatedEstimator.gate.set()
    GatedEstimator.sizes.clear()
    runner = Runner(settings, drv, estimator_factory=GatedEstimator)
    sink = Sink()
    runner.start(sink)
    wait_for(lambda: runner.live.samples_received > 300, 10, "samples flowing")
    yield runner, source, sink, loop
    GatedEstimator.gate.set()
    runner.stop(1.0)
    drv.close()
    loop.call_soon_threadsafe(server.stop.set)
    thread.join(5)


def test_a_crash_in_one_frame_holds_the_feed_while_the_estimator_thread_is_stuck(live):
    runner, source, sink, loop = live
    GatedEstimator.entered.clear()
    GatedEstimator.gate.clear()  # the estimator thread stops inside its next batch
    wait_for(GatedEstimator.entered.is_set, 5, "the estimator thread held in its batch")
    revolutions, published = runner.live.revolutions, len(sink.items)
    loop.call_soon_threadsafe(lambda: setattr(source, "armed", True))

    assert source.held.wait(5), "the emulator never received feed hold while the estimator was stuck"
    assert runner.interlock.latched and runner.interlock.reason.startswith("crash p_gap_w")
    assert runner.live.revolutions == revolutions and len(sink.items) == published  # nothing waited for a batch
    wait_for(lambda: runner.live.last_trip_ms is not None, 5, "the reader's trip timed (it logs after the write)")

    GatedEstimator.gate.set()  # the estimator goes on: the crash is latched and published, once
    wait_for(lambda: sink.alarms("crash"), 5, "the crash alarm published")
    time.sleep(0.3)  # every frame of the pulse is through by now (it is over the limit for 10)
    crashes = sink.alarms("crash")
    assert len(crashes) == 1 and crashes[0]["interlock"] == "feed_hold" and crashes[0]["quantity"] == "p_gap_w"
    assert runner.interlock.trips == 1 and runner.core.alarms.crash_latched


def test_after_a_reset_the_next_crash_trips_again_and_frames_go_through_in_batches(live):
    runner, source, sink, loop = live
    for trip in (1, 2):
        source.held.clear()
        loop.call_soon_threadsafe(lambda: setattr(source, "armed", True))
        assert source.held.wait(5), f"trip {trip}: no feed hold at the emulator"
        wait_for(lambda: len(sink.alarms("crash")) == trip, 5, f"crash alarm {trip}")
        # the spindle stands still: the reset is granted once a block after the hold is judged
        wait_for(lambda: runner.controls.reset().get("ok"), 5, f"reset after trip {trip}")
        assert not runner.interlock.latched and not runner.core.alarms.crash_latched
    assert runner.interlock.trips == 2 and len(sink.alarms("crash")) == 2
    # nothing asks for the estimator at once while the spindle stands still: it takes frames in batches
    # (~50 ms of them; one at a time, blocks are the reader's: one frame, now and then two)
    mark = len(GatedEstimator.sizes)
    wait_for(lambda: len(GatedEstimator.sizes) >= mark + 20, 10, "20 more blocks processed")
    assert np.median(GatedEstimator.sizes[mark:]) >= 30


def test_a_frame_reaching_the_predicted_close_of_a_revolution_wakes_the_estimator():
    from types import SimpleNamespace

    from millsense.daemon.pipeline.run_core import Step

    daq = SimpleNamespace(descriptor=Descriptor(1000, RAMP_CHANNELS), link_up=True, last_status=None)
    runner = Runner(demo_config(), daq)  # not started: the reader's hook called by hand
    quiet = np.zeros((10, 8), dtype=np.int16)
    assert runner.frames.on_frame(0, quiet, 0, False) == (True, False)  # checked; nothing asks for the estimator
    runner.frames.predict_close(Step(items=[("estimate", {"seq_end": 1009, "samples": 100, "lost_samples": 0})]),
                                spindle_stopped=False)
    # the next revolution ends at sample 1109 and is closed by sample 1110, the first past its boundary: the
    # frame holding 1110 wakes the estimator, not those before (waking for 1109 found nothing to close)
    assert runner.frames.on_frame(1090, quiet, 0, False) == (True, False)
    assert runner.frames.on_frame(1100, quiet, 0, False) == (True, False)
    assert runner.frames.on_frame(1110, quiet, 0, False) == (True, True)
    runner.frames.predict_close(Step(), spindle_stopped=True)
    assert runner.frames.on_frame(1120, quiet, 0, False) == (True, False)  # stopped: no revolution to wait for
    loud = quiet.copy()
    loud[:, 3:6] = [12500, 12500, -25000]  # i_w 50 A: over stall_current_a (45), under crash_current_a (55)
    assert runner.frames.on_frame(1130, loud, 0, False) == (True, True)  # a stall is judged at once
    assert not runner.interlock.latched


@pytest.mark.serial
def test_the_trip_time_ends_when_the_hold_is_written(live):
    """`last_trip_ms` (status) is the daemon's share of the crash trip: frame decoded → feed hold written. What the
    tripping thread does after the write (the log line, the AFC override to 100 %, which waits for the AFC lock while
    another thread holds it) is not part of it: it measured up to the end of all of that before stop 28."""
    runner, source, sink, loop = live
    with runner.afc.lock:   # another thread in the middle of an override step as the crash lands
        loop.call_soon_threadsafe(lambda: setattr(source, "armed", True))
        assert source.held.wait(5), "the emulator never received feed hold"
        time.sleep(0.3)
    wait_for(lambda: runner.live.last_trip_ms is not None, 5, "the reader's trip timed")
    assert runner.interlock.latched and runner.interlock.trips == 1
    assert 0.0 <= runner.live.last_trip_ms < 300.0, runner.live.last_trip_ms
