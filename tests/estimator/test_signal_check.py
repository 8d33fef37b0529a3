"""Issue 10, findings 2 and 3: stuck, clipped and lying signals are never published as measurements.

Every capture here is made by the real plant through `millsense sim --capture`
with its sensor-fault flags (sim/sensors.py, which knows nothing of the
daemon), then read through `PipelineCore` exactly as `run` and `replay` read a
stream: a descriptor the configuration refuses drops the estimator (the
runner's fault `descriptor`), every block goes through estimator, signal and
safety checks. Time is counted in samples, never by the clock.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from millsense.daemon.config.errors import ConfigError
from millsense.daemon.config.load import load_config
from millsense.daemon.commands.capture_reader import iter_capture_blocks
from millsense.daemon.pipeline.run_core import PipelineCore
from tests import captures
from tests.estimator import configs

RATE = 1000
CURRENTS = ("i_u", "i_v", "i_w")


def capture(tmp: Path, scenario: str, seconds: float, *flags: str, seed: int = 1) -> Path:
    """`millsense sim --capture` with these flags, made once per test run (tests/captures.py), linked into `tmp`."""
    args = ["--scenario", scenario, "--duration-s", str(seconds), "--seed", str(seed), *flags]

    def build(d: Path) -> None:
        captures.sim(*args[:2], "--capture", d / "capture.bin", *args[2:])

    shared = captures.shared("millsense sim " + " ".join(args), build)
    name = f"{scenario}-{seed}-{'_'.join(flags).replace('=', '-') or 'clean'}.bin"
    return captures.link(shared / "capture.bin", tmp / name)


def settings(tmp: Path, *, alarms: str = "", encoder: bool = True, channels_extra: dict[str, str] | None = None,
             feed_mm_min: float | None = 200.0, pole_pairs: int | None = 2):
    text = configs.toml_text(encoder=encoder, feed_mm_min=feed_mm_min, pole_pairs=pole_pairs)
    for name, extra in (channels_extra or {}).items():
        head = f"[channels.{name}]\n"
        assert head in text
        text = text.replace(head, head + extra + "\n", 1)
    if alarms:
        text += f"\n[alarms]\n{alarms}\n"
    path = tmp / f"cfg-{abs(hash(text))}.toml"
    path.write_text(text)
    return load_config(path)


class Run:
    """Everything a capture produced, block by block, as the runner would see it."""

    def __init__(self, cfg, path: Path):
        self.core = PipelineCore(cfg)
        self.estimates: list[dict] = []
        self.trips = []
        self.faults: list[tuple[int, str, str]] = []     # (last seq of the block, kind, reason)
        self.cleared: list[tuple[int, str]] = []
        self.descriptor_faults: list[str] = []
        self.steps = 0
        self.first_seq: int | None = None
        refused = None
        for desc, block in iter_capture_blocks(path):
            if self.first_seq is None:
                self.first_seq = int(block.seq)
            if desc != self.core.descriptor and desc != refused:
                try:
                    self.core.on_descriptor(desc)
                except ConfigError as exc:  # the runner: fault "descriptor", no estimator until it fits
                    refused = desc
                    self.core.drop_estimator()
                    self.descriptor_faults.append("; ".join(exc.problems))
            if self.core.estimator is None:
                self.core.skip(block)
                continue
            step = self.core.process(block)
            self.steps += 1
            assert step.last_seq == block.seq + len(block.counts) - 1
            assert set(step.peaks) == {"p_gap_w", "current_a"}
            self.estimates += [item for kind, item in step.items if kind == "estimate"]
            self.trips += step.trips
            self.faults += [(step.last_seq, k, r) for k, r in step.faults.items()]
            self.cleared += [(step.last_seq, k) for k in step.clear_faults]

    @property
    def valid(self) -> list[dict]:
        return [e for e in self.estimates if e["valid"]]

    def signal_fault(self) -> tuple[int, str]:
        hits = [(seq, reason) for seq, kind, reason in self.faults if kind == "signals"]
        assert hits, f"no fault signals (faults {self.faults})"
        return hits[0]


def assert_all_invalid(run: Run, why: str = "signals") -> None:
    assert run.estimates, "no revolution closed at all"
    assert not run.valid, [(e["rev"], e["torque_nm"]) for e in run.valid][:5]
    for e in run.estimates:
        assert e["invalid"] == why
        assert e["torque_nm"] is None and e["p_gap_w"] is None and e["spindle_rpm"] is None and e["force_n"] is None


# ---------------------------------------------------------------------------- finding 2
def test_currents_pinned_at_the_rail_give_no_valid_revolution_and_name_the_channel(tmp_path):
    cap = capture(tmp_path, "step", 3, *(f"--pin={c}=32767" for c in CURRENTS))
    run = Run(settings(tmp_path, alarms="crash_current_a = 100"), cap)
    assert_all_invalid(run)
    assert not any(e["saturated"] for e in run.estimates)  # stuck, not a crash: no current swung to the rail
    assert not run.trips
    seq, reason = run.signal_fault()
    assert seq - run.first_seq < RATE, "later than 1 s of samples"
    assert "i_u: at raw_max 32767 in 100 % of samples" in reason, reason


def test_currents_clipped_at_the_int16_limits_are_invalid_saturated_and_trip(tmp_path):
    # hall sensors 20x too sensitive: the true ~5-10 A swing far past the int16 rails
    cap = capture(tmp_path, "step", 3, "--current-gain", "20")
    # 100 A is beyond what these sensors can read (65.5 A): only "clipped while high" can reach it
    run = Run(settings(tmp_path, alarms="crash_current_a = 100"), cap)
    assert_all_invalid(run)
    assert all(e["saturated"] for e in run.estimates)
    assert [(t.level, t.quantity, t.limit) for t in run.trips] == [("crash", "current_a", 100.0)]
    assert run.trips[0].seq - run.first_seq < 50
    seq, reason = run.signal_fault()
    assert seq - run.first_seq < RATE and "i_u: at raw_min -32768 and raw_max 32767" in reason, reason


def test_a_sensor_clipping_at_its_own_configured_limits(tmp_path):
    # sensors saturating at ±20000 counts, and the config says so: raw_min / raw_max per channel
    cap = capture(tmp_path, "step", 3, "--current-gain", "20", "--clip-currents", "20000")
    limits = {c: "raw_min = -20000\nraw_max = 20000" for c in CURRENTS}
    run = Run(settings(tmp_path, alarms="crash_current_a = 100", channels_extra=limits), cap)
    assert_all_invalid(run)
    assert all(e["saturated"] for e in run.estimates)
    assert [t.quantity for t in run.trips] == ["current_a"]
    assert "i_u: at raw_min -20000 and raw_max 20000" in run.signal_fault()[1]
    # with the int16 defaults the same samples look like a measurement: the limits are what tells them apart
    blind = Run(settings(tmp_path, alarms="crash_current_a = 100"), cap)
    assert blind.valid and not blind.trips


def test_all_channels_pinned_fault_within_a_second_of_samples(tmp_path):
    flags = [f"--pin={c}=32767" for c in ("v_uv", "v_vw", "v_wu", *CURRENTS, "sp_rpm", "sp_enc")]
    cap = capture(tmp_path, "step", 3, *flags)
    run = Run(settings(tmp_path), cap)
    assert not run.valid
    seq, reason = run.signal_fault()
    assert seq - run.first_seq < RATE
    for name in ("v_uv", "i_u", "sp_rpm"):
        assert f"{name}: at raw_max 32767" in reason, reason


@pytest.mark.parametrize("channel,count", [("v_vw", 120), ("i_v", -40)])
def test_a_flat_channel_while_the_drive_runs(tmp_path, channel, count):
    cap = capture(tmp_path, "step", 3, f"--pin={channel}={count}")
    run = Run(settings(tmp_path), cap)
    assert_all_invalid(run)
    seq, reason = run.signal_fault()
    assert seq - run.first_seq < RATE and reason.startswith(f"{channel}: flat (peak-to-peak 0 counts"), reason


# ---------------------------------------------------------------------------- finding 3
@pytest.mark.parametrize("claimed_hz", [500, 1200, 2000, 65535])
def test_a_descriptor_claiming_another_rate_is_refused(tmp_path, claimed_hz):
    cap = capture(tmp_path, "step", 2, "--descriptor-rate", str(claimed_hz))
    run = Run(settings(tmp_path), cap)
    assert run.descriptor_faults and not run.estimates and run.steps == 0
    assert f"daq.sample_rate_hz: the DAQ's descriptor says {claimed_hz} Hz, the configuration 1000 Hz" in \
        run.descriptor_faults[0]
    assert run.core.lost_samples_total == 0  # received, unusable, nothing lost


def test_the_configured_rate_is_the_one_believed(tmp_path):
    cap = capture(tmp_path, "step", 2, "--descriptor-rate", "500")
    text_cfg = settings(tmp_path)
    cfg = text_cfg.model_copy(update={"daq": text_cfg.daq.model_copy(update={"sample_rate_hz": 500})})
    run = Run(cfg, cap)  # the integrator said 500: descriptor and config agree, so it is accepted ...
    assert not run.descriptor_faults and run.estimates
    # ... and the speed channel (in rpm, rate-free) then disagrees with the encoder and f_e: still never valid
    assert_all_invalid(run)
    assert "sp_rpm: reads 600 rpm" in run.signal_fault()[1]


@pytest.mark.parametrize("encoder", [True, False], ids=["encoder", "speed-channel"])
def test_a_speed_channel_disagreeing_with_the_electrical_frequency(tmp_path, encoder):
    cap = capture(tmp_path, "step", 3, "--pin=sp_rpm=3000")  # reads 300 rpm, the spindle turns 600
    run = Run(settings(tmp_path, encoder=encoder), cap)
    assert_all_invalid(run)
    seq, reason = run.signal_fault()
    assert seq - run.first_seq < RATE and reason.startswith("sp_rpm: reads 300 rpm"), reason


def test_without_pole_pairs_the_encoder_and_the_speed_channel_must_still_agree(tmp_path):
    cap = capture(tmp_path, "step", 3, "--pin=sp_rpm=3000")
    run = Run(settings(tmp_path, pole_pairs=None), cap)  # no f_e check possible: the encoder is the witness
    assert_all_invalid(run)
    reason = run.signal_fault()[1]
    assert reason.startswith("sp_rpm: reads 300 rpm, the encoder sp_enc ") and "10 % and 20 rpm apart" in reason, reason


def test_the_fault_clears_after_a_second_of_good_samples(tmp_path):
    # a stuck sensor for 1.5 s, then the same machine again (another capture joined on: a device restart)
    bad = capture(tmp_path, "step", 1.5, "--pin=i_w=0")
    good = capture(tmp_path, "step", 3)
    joined = tmp_path / "joined.bin"
    joined.write_bytes(bad.read_bytes() + good.read_bytes())
    run = Run(settings(tmp_path), joined)
    seq, reason = run.signal_fault()
    assert reason.startswith("i_w: flat")
    clears = [s for s, k in run.cleared if k == "signals"]
    assert len(clears) == 1 and clears[0] > seq
    late = [e for e in run.estimates if e["seq_end"] > clears[0]]
    assert late and all(e["valid"] for e in late)


# ---------------------------------------------------------------------------- no false alarms
NORMAL = ("step", "fig5", "fig6", "crash", "aircut-low", "aircut-high", "breakage", "taper")


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize("scenario", NORMAL)
def test_normal_scenarios_raise_no_signal_fault(tmp_path, scenario, seed):
    from millsense.sim.scenarios import SCENARIOS

    cap = capture(tmp_path, scenario, SCENARIOS[scenario].duration_s, seed=seed)
    # the air cuts have no feed; fig5/fig6's extra channels are left unconfigured (the DAQ may send more)
    cfg = settings(tmp_path, feed_mm_min=None if scenario.startswith("aircut") else 200.0)
    run = Run(cfg, cap)
    assert not run.faults, run.faults[:3]
    assert not run.descriptor_faults
    invalid = [e for e in run.estimates if not e["valid"]]
    if scenario == "crash":
        # the crash drives the currents past the hall sensors' range: those revolutions are no measurement,
        # and they are saturated (the alarms count them over every limit)
        assert all(e["saturated"] and e["invalid"] == "signals" for e in invalid)
        assert 0 < len(invalid) <= 5
    else:
        assert not invalid, [(e["rev"], e["invalid"]) for e in invalid][:5]
    assert len(run.valid) > 50


def test_a_sensor_that_fails_mid_run_spoils_only_the_samples_from_then_on():
    """`millsense sim --faults-from-s`: the pin begins at its sample, wherever the blocks fall."""
    import numpy as np

    from millsense.sim.plant import Plant
    from millsense.sim.sensors import SensorFaults

    sound = Plant("step", seed=3).step(1000)
    faulty = SensorFaults(Plant("step", seed=3), pin={"i_u": 7}, from_s=0.45)
    got = np.concatenate([faulty.step(n) for n in (300, 100, 17, 583)])
    col = [ch.name for ch in faulty.descriptor.channels].index("i_u")
    assert (got[:450] == sound[:450]).all()
    assert (got[450:, col] == 7).all() and (got[450:, :col] == sound[450:, :col]).all()


# ---------------------------------------------------------------------------- a sensor that just stopped
def _newest_pinned_per_frame(cfg, cap: Path, frame: int = 10) -> list[tuple[int, str | None]]:
    """(last seq, `newest_pinned()`) after every frame of `frame` samples, as the live estimator sees them."""
    from millsense.drivers.base import SampleBlock

    core = PipelineCore(cfg)
    out = []
    for desc, block in iter_capture_blocks(cap):
        core.on_descriptor(desc)
        for a in range(0, len(block.counts), frame):
            part = block.counts[a : a + frame]
            core.process(SampleBlock(block.seq + a, block.index + a, part, block.lost_before if a == 0 else 0,
                                     block.discontinuity and a == 0))
            out.append((block.seq + a + len(part) - 1, core.estimator.signals.newest_pinned()))
    return out


@pytest.mark.parametrize("scenario", ["step", "aircut-low", "aircut-high", "fig6"])
def test_no_healthy_channel_reads_as_stopped_in_the_newest_samples(tmp_path, scenario):
    """The feed controller raises no feed while a channel has not moved over the newest 5 samples: on sound
    signals (speed changes down to the slowest air cut, a cut, the spindle starting) that never holds."""
    from millsense.sim.scenarios import SCENARIOS

    cap = capture(tmp_path, scenario, SCENARIOS[scenario].duration_s)
    cfg = settings(tmp_path, feed_mm_min=None if scenario.startswith("aircut") else 200.0)
    flagged = [(seq, name) for seq, name in _newest_pinned_per_frame(cfg, cap) if name is not None]
    assert not flagged, flagged[:5]


def test_a_current_pinned_mid_cut_reads_as_stopped_within_a_frame(tmp_path):
    cap = capture(tmp_path, "step", 6.0, "--pin", "i_u=0", "--faults-from-s", "5.0")
    seen = _newest_pinned_per_frame(settings(tmp_path), cap)
    first = seen[0][0]
    onset = first + 5 * RATE
    before = [name for seq, name in seen if seq < onset]
    after = [name for seq, name in seen if seq >= onset + 4]   # 5 pinned samples by then
    assert set(before) == {None} and after and set(after) == {"i_u"}


@pytest.mark.parametrize("f_e_hz", [5.0, 20.0, 80.0])
def test_a_clean_phase_at_its_peak_is_not_read_as_stopped(f_e_hz, tmp_path):
    """Noise-free balanced waveforms (written from first principles, tests/estimator/synthetic.py) through
    every phase angle: at its peak a phase moves least, yet more than PIN_COUNTS over PIN_SAMPLES whenever
    another of its kind swings LIVE_COUNTS (signal_check.py says down to f_e = 5 Hz)."""
    from millsense.daemon.pipeline.estimator import Estimator
    from millsense.drivers.base import SampleBlock
    from tests.estimator import synthetic

    m = synthetic.Machine()
    m = synthetic.Machine(spindle_rpm=f_e_hz * 60.0 * (1.0 - m.slip) / (m.pole_pairs * m.gear_ratio))
    assert abs(m.f_e_hz - f_e_hz) < 1e-9
    est = Estimator(configs.load(tmp_path, name="pin.toml", encoder=True, pole_pairs=2), synthetic.descriptor(), 1000.0)
    counts = synthetic.counts(m, int(2 * 1000 / f_e_hz) + 10)   # two electrical periods: every peak
    flagged = []
    for a in range(0, len(counts), 5):
        est.process(SampleBlock(a, a, counts[a : a + 5], 0, False))
        flagged.append(est.signals.newest_pinned())
    assert set(flagged) == {None}, [(5 * k, f) for k, f in enumerate(flagged) if f][:5]


# ---------------------------------------------------------------------------- stops and starts
# Found live (stop 20): the part program's looping emulator, at a tool change, raised fault `signals` and held
# the feed, "sp_enc: reads 32 rpm, but the electrical frequency 14.5 Hz means 90 rpm in gear low-speed". The
# drive had been off for 135 samples of the 200-sample window (f_e read from noise: ±250 Hz a sample) and
# on for 65 (the spindle starting); the window before it named i_w "flat" while the drive magnetised the motor
# before the start (a standing current vector: i_u = −i_v, i_w ≈ 0). Two bad windows in a row: the fault.

def _estimator(tmp_path, drop: tuple[str, ...] = ()):
    from millsense.daemon.pipeline.estimator import Estimator
    from tests.estimator import synthetic

    cfg = configs.load(tmp_path, name=f"transitions-{'-'.join(drop)}.toml", encoder=True, pole_pairs=2, drop=drop)
    return Estimator(cfg, synthetic.descriptor(), 1000.0)


def _feed(est, counts, size: int = 10) -> None:
    from millsense.drivers.base import SampleBlock

    for a in range(0, len(counts), size):
        est.process(SampleBlock(a, a, counts[a : a + size], 0, False))


def _bad_windows(check, window: int = 200, step: int = 10) -> list[tuple[int, dict]]:
    """Every window of `window` samples the ring holds, one every `step`: (its last seq, problems) where the
    exact check names something."""
    out = []
    for b in range(window, check.w + 1, step):
        problems = check._problems(b - window, b)[0]
        if problems:
            out.append((int(check.seq[b - 1]), problems))
    return out


def _drive_off(rng, n: int, *, residual_hz: float = 40.0) -> np.ndarray:
    """The drive off, the spindle at rest: every channel its noise, and the voltages a residual of a few
    counts rotating at `residual_hz` (below MIN_VOLTAGE_V: the f_e read from it means nothing)."""
    from tests.estimator import synthetic

    c = np.zeros((n, len(synthetic.CHANNELS)))
    t = np.arange(n) / 1000.0
    for k in range(3):
        c[:, k] = 6.0 * np.cos(2 * np.pi * residual_hz * t - k * 2 * np.pi / 3) + rng.normal(0, 1.0, n)
    c[:, 3:7] = rng.normal(0, 3.0, (n, 4))
    c[:, 7] = 1234                                          # the encoder stands
    return np.round(c).astype(np.int16)


def test_f_e_read_while_the_drive_is_off_is_no_evidence_against_the_speed(tmp_path):
    """A window that holds both the drive off (f_e from a residual of a few counts) and the spindle starting
    (f_e and the encoder agreeing) names no speed source: only samples with a voltage carry f_e."""
    from tests.estimator import synthetic

    rng = np.random.default_rng(5)
    m = synthetic.Machine(spindle_rpm=30.0)                 # low gear: f_e 4.9 Hz, the spindle at 30 rpm
    counts = np.concatenate([_drive_off(rng, 1135), synthetic.counts(m, 465, start_angle_rev=0.3)])
    est = _estimator(tmp_path)
    _feed(est, counts)
    assert _bad_windows(est.signals) == []
    assert not est.signals.faulted


def test_a_standing_current_vector_leaves_no_phase_flat(tmp_path):
    """The drive magnetising the motor before a start (or DC braking after a stop): the current vector stands
    still, so the three phases do not swing alike: here i_u = −i_v and i_w ≈ 0. The three currents sum to
    zero, as Kirchhoff says they must: every sensor reads its share, none is dead."""
    rng = np.random.default_rng(6)
    counts = _drive_off(rng, 600)
    ramp = np.minimum(np.arange(400) * 40.0, 10600.0)      # the magnetising current builds up: 21 A
    counts[200:, 3] = np.round(-ramp + rng.normal(0, 3.0, 400)).astype(np.int16)
    counts[200:, 4] = np.round(ramp + rng.normal(0, 3.0, 400)).astype(np.int16)
    counts[200:, 5] = np.round(-0.006 * ramp + rng.normal(0, 3.0, 400)).astype(np.int16)
    est = _estimator(tmp_path)
    _feed(est, counts)
    assert _bad_windows(est.signals) == []


def test_a_dead_sensor_under_a_standing_current_vector_is_still_named(tmp_path):
    """The counterpart: i_w's sensor reads nothing while its phase carries half the current (the three do not
    sum to zero): that is a dead sensor, standing vector or not."""
    rng = np.random.default_rng(7)
    counts = _drive_off(rng, 600)
    ramp = np.minimum(np.arange(400) * 40.0, 10600.0)
    counts[200:, 3] = np.round(-ramp + rng.normal(0, 3.0, 400)).astype(np.int16)
    counts[200:, 4] = np.round(0.5 * ramp + rng.normal(0, 3.0, 400)).astype(np.int16)   # i_w's half is missing
    est = _estimator(tmp_path)
    _feed(est, counts)
    named = {name for _, problems in _bad_windows(est.signals) for name in problems}
    assert named == {"i_w"}


def test_with_two_current_sensors_a_standing_vector_leaves_no_phase_flat(tmp_path):
    """i_w not measured (the DAQ derives nothing, the daemon takes −(i_u + i_v)): no Kirchhoff sum to read, so
    only a field that turned through an electrical period says the two phases should swing alike. Standing,
    i_v ≈ 0 is its share; turning, a dead i_v is named."""
    from tests.estimator import synthetic

    rng = np.random.default_rng(8)
    counts = _drive_off(rng, 600)
    ramp = np.minimum(np.arange(400) * 40.0, 10600.0)
    counts[200:, 3] = np.round(ramp + rng.normal(0, 3.0, 400)).astype(np.int16)
    counts[200:, 4] = np.round(0.006 * ramp + rng.normal(0, 3.0, 400)).astype(np.int16)
    est = _estimator(tmp_path, drop=("i_w",))
    _feed(est, counts)
    assert _bad_windows(est.signals) == []

    running = synthetic.counts(synthetic.Machine(spindle_rpm=300.0), 600)
    running[:, 4] = np.round(rng.normal(0, 3.0, 600)).astype(np.int16)      # i_v's sensor dead
    est = _estimator(tmp_path, drop=("i_w",))
    _feed(est, running)
    named = {name for _, problems in _bad_windows(est.signals) for name in problems}
    assert named == {"i_v"}
