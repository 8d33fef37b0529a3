"""Runs of `bench/validate.py`: simulator captures, configurations, `millsense replay`, error statistics.

A *case* is one replay: a capture (scenario, seed, noise, hardware filter) and
a configuration (what the operator wrote, possibly with one input wrong). The
configuration starts from `tests/estimator/simcase.settings_for`, the same
operator's config the accuracy tests and `bench/accuracy.py` use, and one
wrong input is then applied as a text edit of the TOML file, so what the
daemon reads is exactly what a user would have typed. Replays are real
`millsense replay` subprocesses; estimates are paired with the truth by
`simcase.match` (the revolution's last sample) and classified by
`simcase.settled`. Alarms are the daemon's defaults (no [alarms] section):
what a user gets who sets no limits; tool breakage not armed (its default).
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tests.estimator import simcase  # noqa: E402

CMD = [sys.executable, "-m", "millsense.daemon"]
SAMPLE_RATE_HZ = 1000            # the simulated DAQ (docs/architecture.md); replay `t` = seq / rate
MATCH_TOLERANCE_SAMPLES = 1      # as bench/accuracy.py with an encoder
TIMEOUT_S = 300


@dataclass(frozen=True)
class Capture:
    scenario: str
    seed: int
    noise_scale: float = 1.0
    filter_cutoff_hz: float | None = None      # hardware filter; None = the scenario's (200 Hz)

    def paths(self, workdir: Path) -> tuple[Path, Path]:
        """Where `simcase.capture` puts (or finds) this capture and its truth."""
        d = workdir / "captures"
        d.mkdir(parents=True, exist_ok=True)
        return simcase.capture(d, self.scenario, seed=self.seed, filter_cutoff_hz=self.filter_cutoff_hz,
                               noise_scale=self.noise_scale)


@dataclass(frozen=True)
class Case:
    key: str                                   # unique, file-name safe
    capture: Capture
    label: str
    options: tuple[tuple[str, object], ...] = ()    # keyword arguments of simcase.settings_for
    edits: tuple[tuple[str, str], ...] = ()         # (old, new) text edits of the TOML: the wrong input
    calibrated: bool = False                        # use the friction fitted by `millsense calibrate`
    depths: tuple[str, ...] = ()                    # depth fields the daemon estimates (not configured)

    @property
    def scenario(self) -> str:
        return self.capture.scenario

    @property
    def method(self) -> str:
        return str(dict(self.options).get("method", "auto"))


@dataclass
class Result:
    case: Case
    estimates: list[dict] = field(default_factory=list)
    alarms: list[dict] = field(default_factory=list)
    config_text: str = ""
    summary: str = ""


def make_capture(cap: Capture, workdir: Path) -> tuple[Path, Path]:
    return cap.paths(workdir)


def calibrate(workdir: Path, seed: int) -> tuple[Path, str]:
    """`millsense calibrate` on the two air-cut captures; returns the calibration file and its printout."""
    caps = [Capture(name, seed).paths(workdir)[0] for name in ("aircut-low", "aircut-high")]
    d = workdir / "calibration"
    d.mkdir(parents=True, exist_ok=True)
    simcase.settings_for("aircut-low", d, feed_mm_min=None)   # air cuts: no feed
    cfg = next(d.glob("*.toml"))
    out = d / "friction.toml"
    p = subprocess.run([*CMD, "calibrate", *map(str, caps), "--config", str(cfg), "--out", str(out)],
                       capture_output=True, text=True, timeout=TIMEOUT_S)
    if p.returncode != 0:
        raise RuntimeError(f"millsense calibrate failed ({p.returncode}): {p.stderr.strip()}")
    return out, p.stdout


def write_config(case: Case, workdir: Path, calibration: Path | None) -> Path:
    """The operator's TOML for the case, with its one wrong input applied."""
    d = workdir / "cases" / case.key
    gen = d / "generated"
    gen.mkdir(parents=True, exist_ok=True)
    opts = dict(case.options)
    if opts.get("method") == "feed-drive":
        cap, _ = case.capture.paths(workdir)
        # the technician zeroes the feed-current sensor on air revolutions (see simcase.zero_feed_current)
        zero = d / "zero"
        zero.mkdir(exist_ok=True)
        opts["ix_offset_counts"] = simcase.zero_feed_current(cap, case.scenario, zero)
    simcase.settings_for(case.scenario, gen, **opts)
    (generated,) = gen.glob("*.toml")
    text = generated.read_text()
    for old, new in case.edits:
        if old not in text:
            raise ValueError(f"case {case.key}: {old!r} is not in the generated config")
        text = text.replace(old, new)
    if case.calibrated:
        head = 'machine = "test-mill"\n'
        text = text.replace(head, f'{head}calibration = "{calibration}"\n', 1)
    path = d / "config.toml"
    path.write_text(text)
    return path


def replay(case: Case, workdir: Path, calibration: Path | None = None) -> Result:
    """One `millsense replay` subprocess; estimates get `seq_end` back from `t` for the pairing."""
    cap, _ = case.capture.paths(workdir)
    cfg = write_config(case, workdir, calibration)
    p = subprocess.run([*CMD, "replay", str(cap), "--config", str(cfg)], capture_output=True, text=True,
                       timeout=TIMEOUT_S)
    if p.returncode != 0:
        raise RuntimeError(f"replay of {case.key} failed ({p.returncode}): {p.stderr.strip()}")
    res = Result(case, config_text=cfg.read_text(), summary=p.stderr.strip().splitlines()[-1])
    for line in p.stdout.splitlines():
        item = json.loads(line)
        if item["type"] == "estimate":
            item["seq_end"] = round(item["t"] * SAMPLE_RATE_HZ)
            res.estimates.append(item)
        else:
            res.alarms.append(item)
    return res


# --- statistics ------------------------------------------------------------------------------------

QUANTITIES = {          # name -> (estimate field, truth field, unit)
    "torque": ("torque_nm", "torque_nm", "N·m"),
    "force": ("force_n", "force_n", "N"),
    "radial": ("radial_depth_mm", "radial_depth_mm", "mm"),
    "axial": ("axial_depth_mm", "axial_depth_mm", "mm"),
}
# steady: settled cut (simcase.settled); broken: settled, but after a flute broke (the model assumes a
# sound tool) and after the speed swing the load step caused; transition: any other cutting revolution
# (entry, exit, steps, feed changes); air: no cut
SEGMENTS = ("steady", "broken", "transition", "air")
BREAK_SETTLE_S = 0.5    # after a flute breaks, the speed loop's swing (a transition) lasts this long


@dataclass(frozen=True)
class Stats:
    n: int
    mean: float        # signed: the bias
    p95: float         # of |error|
    max: float         # of |error|

    @staticmethod
    def of(err) -> Stats | None:
        e = np.asarray(err, dtype=float)
        if e.size == 0:
            return None
        a = np.abs(e)
        return Stats(int(e.size), float(e.mean()), float(np.percentile(a, 95)), float(a.max()))


def read_truth(case: Case, workdir: Path) -> list[dict]:
    return simcase.read_truth(case.capture.paths(workdir)[1])


def read_events(case: Case, workdir: Path) -> list[dict]:
    """Event lines of the truth file (tool_breakage, crash_power, ...)."""
    path = case.capture.paths(workdir)[1]
    return [rec for rec in map(json.loads, filter(str.strip, path.read_text().splitlines())) if "event" in rec]


def segment_of(truth: list[dict], scenario: str, events: list[dict] = ()) -> dict[int, str]:
    """Truth rev -> one of SEGMENTS."""
    settled = simcase.settled(truth, scenario)
    broke = min((e["t_s"] for e in events if e["event"] == "tool_breakage"), default=float("inf"))
    out = {}
    for t in truth:
        if t["rev"] in settled and broke < t["t_end_s"] <= broke + BREAK_SETTLE_S:
            out[t["rev"]] = "transition"        # the load step of the break: the spindle speed swings
        elif t["rev"] in settled:
            out[t["rev"]] = "broken" if t["t_end_s"] > broke else "steady"
        else:
            out[t["rev"]] = "transition" if t["cutting"] else "air"
    return out


@dataclass
class Paired:
    """Estimate and truth values per (segment, quantity), the scenario's full scale, missing estimates."""

    est: dict[tuple[str, str], np.ndarray]
    tru: dict[tuple[str, str], np.ndarray]
    full_scale: dict[str, float]                 # largest true value of each quantity in the run
    missing: dict[tuple[str, str], int]
    statuses: dict[str, int]                     # depth_status over steady revolutions
    missing_statuses: dict[str, int]             # depth_status of the revolutions with a null depth

    def stats(self, seg: str, q: str, kind: str = "abs", offset: float = 0.0) -> Stats | None:
        """kind: "abs" (unit), "rel" (% of the true value), "fs" (% of the run's largest true value).

        `offset` is added to the truth first: a reference that differs from the truth file's by a
        known amount (a taper's lead, see validate_report.ramp_lead_mm)."""
        e, t = self.est.get((seg, q)), self.tru.get((seg, q))
        if e is None or not e.size:
            return None
        t = t + offset
        err = e - t
        if kind == "rel":
            ok = t > 0
            return Stats.of(err[ok] / t[ok] * 100.0)
        if kind == "fs":
            return Stats.of(err / self.full_scale[q] * 100.0)
        return Stats.of(err)


def pair(res: Result, truth: list[dict], events: list[dict] = ()) -> Paired:
    seg = segment_of(truth, res.case.scenario, events)
    quantities = ["torque", "force", *res.case.depths]
    est: dict[tuple[str, str], list[float]] = {}
    tru: dict[tuple[str, str], list[float]] = {}
    missing: dict[tuple[str, str], int] = {}
    statuses: dict[str, int] = {}
    missing_statuses: dict[str, int] = {}
    for e, t in paired(res, truth):
        s = seg[t["rev"]]
        if s == "steady" and e.get("depth_status"):
            statuses[e["depth_status"]] = statuses.get(e["depth_status"], 0) + 1
        for q in quantities:
            if s == "air" and q != "torque":
                continue                 # no force or depth to speak of in the air
            e_key, t_key, _ = QUANTITIES[q]
            if e.get(e_key) is None:
                missing[(s, q)] = missing.get((s, q), 0) + 1
                if q in ("radial", "axial"):
                    status = str(e.get("depth_status"))
                    missing_statuses[status] = missing_statuses.get(status, 0) + 1
                continue
            est.setdefault((s, q), []).append(e[e_key])
            tru.setdefault((s, q), []).append(t[t_key])
    full_scale = {q: max([t[QUANTITIES[q][1]] for t in truth] + [1e-12]) for q in QUANTITIES}
    return Paired({k: np.asarray(v) for k, v in est.items()}, {k: np.asarray(v) for k, v in tru.items()},
                  full_scale, missing, statuses, missing_statuses)


def paired(res: Result, truth: list[dict]) -> list[tuple[dict, dict]]:
    return simcase.match(res.estimates, truth, MATCH_TOLERANCE_SAMPLES)
