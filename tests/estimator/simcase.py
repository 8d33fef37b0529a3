"""Simulator captures, matching configurations, and estimate <-> truth matching.

The configuration is what an operator would write for the scenario's cut
(tool, material, mode, feed, which depth is known): taken from the scenario's
published description, never from the plant's internals beyond the sensor
datasheet of docs/architecture.md.
"""

from __future__ import annotations

import json
from pathlib import Path

from . import configs

D_CHANNELS = """
[channels.ix_feed]
scale = 0.001
offset = {ix_offset}
[channels.fx_rate]
scale = 0.1
[channels.fx]
scale = 0.5
[channels.fy]
scale = 0.5
[channels.fz]
scale = 0.5
"""
FEED_FORCE = "ix_feed = { newton_per_amp = 950.0, friction_n = 120.0 }"


def capture(tmp: Path, scenario: str, *, seed: int = 1, filter_cutoff_hz: float | None = None,
            noise_scale: float = 1.0, extra_channels: bool | None = None, effects=None) -> tuple[Path, Path]:
    """A capture and its truth file for the scenario, as links in `tmp` to the one made for the whole
    test run (tests/captures.py): read-only, a test that damages a capture writes its own copy.
    `effects`: a `sim.cut_effects.CutEffects` the plant cuts with instead of [D]'s average model."""
    from millsense.sim import write_capture
    from tests import captures

    tag = f"{scenario}-s{seed}-f{filter_cutoff_hz}-n{noise_scale}-x{extra_channels}"
    if effects is not None:
        import hashlib
        from dataclasses import replace

        from millsense.sim.scenarios import SCENARIOS

        tag += "-e" + hashlib.sha1(repr(effects).encode()).hexdigest()[:12]
        scenario = replace(SCENARIOS[scenario], effects=effects)

    def build(d: Path) -> None:
        kwargs = {"seed": seed, "noise_scale": noise_scale, "extra_channels": extra_channels}
        if filter_cutoff_hz is not None:
            kwargs["filter_cutoff_hz"] = filter_cutoff_hz
        write_capture(scenario, str(d / "capture.bin"), str(d / "truth.jsonl"), **kwargs)

    d = captures.shared(f"write_capture {tag}", build)
    return (captures.link(d / "capture.bin", tmp / f"{tag}.bin"),
            captures.link(d / "truth.jsonl", tmp / f"{tag}.truth.jsonl"))


def read_truth(path: Path) -> list[dict]:
    """Revolution lines of a truth file (event lines skipped)."""
    out = []
    for line in Path(path).read_text().splitlines():
        if line.strip():
            rec = json.loads(line)
            if "event" not in rec:
                out.append(rec)
    return out


def settings_for(scenario: str, tmp: Path, *, method: str = "auto", filter_cutoff_hz: float | None = None,
                 encoder: bool = True, known: str | None = None, cf: float | str = 1.075,
                 ix_offset_counts: float = 0.0, **overrides):
    """A configuration for the scenario. `known`: "axial" or "radial" depth given to the daemon.

    `ix_offset_counts`: the feed-current sensor's zero (see `zero_feed_current`).
    """
    from millsense.sim.scenarios import SCENARIOS

    sc = SCENARIOS[scenario]
    m = sc.material
    d_extras = "ix_feed" in sc.extra_channels
    kwargs = dict(
        filter_cutoff_hz=sc.filter_cutoff_hz if filter_cutoff_hz is None else filter_cutoff_hz,
        encoder=encoder,
        tool=(sc.tool.diameter_mm, sc.tool.flutes),
        material=(m.ks, m.ks_exp, m.r1, m.r1_exp, m.r2, m.r2_exp),
        mode=sc.mode,
        method=method,
        cf=cf,
        extra_channels=D_CHANNELS.format(ix_offset=ix_offset_counts) if d_extras else "",
        feed_force=FEED_FORCE if d_extras else "",
        # with a feed-rate channel the feed is measured; otherwise the program's (first) feed
        feed_mm_min=None if d_extras else sc.feed_segments[0][1],
    )
    if known == "axial":
        kwargs["axial_depth_mm"] = max(d for _, d in sc.axial_profile)
    elif known == "radial":
        kwargs["radial_depth_mm"] = max(d for _, d in sc.radial_profile)
    kwargs.update(overrides)
    name = f"{scenario}-{method}-{filter_cutoff_hz}-{encoder}-{known}-{cf}-{ix_offset_counts:.3f}.toml"
    return configs.load(tmp, name=name, **kwargs)


def run(capture_path: Path, settings, **est_kwargs) -> tuple[list[dict], object]:
    """All estimates of a capture (and the estimator, for its counters)."""
    from millsense.daemon.commands.capture_reader import iter_capture_blocks
    from millsense.daemon.pipeline.estimator import Estimator

    est = None
    out: list[dict] = []
    for desc, block in iter_capture_blocks(capture_path):
        if est is None:
            est = Estimator(settings, desc, desc.sample_rate_hz, **est_kwargs)
        out += est.process(block).estimates
    return out, est


def match(estimates: list[dict], truth: list[dict], tolerance_samples: int = 0) -> list[tuple[dict, dict]]:
    """Pairs (estimate, truth revolution) whose last sample agrees (seq_end <-> index_end).

    `tolerance_samples` > 0 pairs each estimate with the nearest truth revolution end
    within that many samples (speed-integrated angle: its revolutions start elsewhere).
    """
    ends = {t["index_end"]: t for t in truth}
    pairs = []
    if tolerance_samples == 0:
        for e in estimates:
            t = ends.get(e["seq_end"])
            if t is not None:
                pairs.append((e, t))
        return pairs
    import bisect

    keys = sorted(ends)
    for e in estimates:
        i = bisect.bisect_left(keys, e["seq_end"])
        best = min((keys[j] for j in (i - 1, i) if 0 <= j < len(keys)), key=lambda k: abs(k - e["seq_end"]), default=None)
        if best is not None and abs(best - e["seq_end"]) <= tolerance_samples:
            pairs.append((e, ends[best]))
    return pairs


def settled(truth: list[dict], scenario: str, span: int = 3, step_rel: float = 0.02) -> set[int]:
    """Truth revolutions (by rev) inside a cut where the model of a steady cut applies.

    Always: cutting, and the part under the tool for one tool radius of travel
    either way (not entering or leaving: [D] §4 reports, and the model predicts,
    larger errors there). Steps: the truth's own `steady`, with no step in the
    part within a radius (the truth gives the depth under the tool's centre; a
    wall reaches the engagement a radius ahead). Ramps are never "steady": a ramp
    revolution counts when the depth does change along the window, the feed per
    tooth does not, and the torque changes by less than `step_rel` per revolution.
    """
    by_rev = {t["rev"]: t for t in truth}
    out = set()
    for t in truth:
        near = [by_rev.get(t["rev"] + k) for k in range(-span, span + 1)]
        if any(n is None or not n["cutting"] or n["feed_hold"] for n in near):
            continue
        reach = transit_revs(scenario, t["feed_per_tooth_mm"]) // 2 + 1     # one tool radius of travel
        around = [by_rev.get(t["rev"] + k) for k in range(-reach, reach + 1)]
        if any(b is None or b["radial_depth_mm"] <= 0 or b["axial_depth_mm"] <= 0 for b in around):
            continue                                    # the tool is entering or leaving the part
        depths = {(b["radial_depth_mm"], b["axial_depth_mm"]) for b in around}
        if t["steady"]:
            if len(depths) == 1:                        # a step in the part is a radius away at least
                out.add(t["rev"])
            continue
        if len(depths) < len(around) // 2:
            continue                                    # not a ramp: a step crossing the engagement
        feeds = [n["feed_per_tooth_mm"] for n in near]
        if max(feeds) > 1.001 * min(feeds):
            continue
        torques = [n["torque_nm"] for n in near]
        if all(abs(b - a) <= step_rel * abs(a) for a, b in zip(torques, torques[1:])):
            out.add(t["rev"])
    return out


def zero_feed_current(capture_path: Path, scenario: str, tmp: Path, settings=None) -> float:
    """The feed-current sensor's offset in counts, as a technician would zero it.

    The simulated sensors have a fixed offset per seed (a hall sensor's zero
    drifts); on `ix_feed` 0.005 A is 4.75 N of feed force, 3 % of [D]'s smaller
    forces, enough to move a radial depth by 5-10 %. It is measured the way it
    would be on the machine: the mean feed-force reading over air revolutions
    (spindle turning, feed moving, tool not yet in the part), where the true
    force is the feed drive's own friction, already in `friction_n`.
    `settings`: a configuration with the feed-force channel, for a cut that is not in SCENARIOS.
    """
    settings = settings or settings_for(scenario, tmp, method="off")
    est, _ = run(capture_path, settings)
    head = []
    for e in est:                                  # before the tool reaches the part
        if e["cutting"]:
            break
        if e["valid"] and e["force_feed_n"] is not None:
            head.append(e["force_feed_n"])
    head = head[:-1]                               # the last may already touch the part
    ff = settings.feed_force["ix_feed"]
    scale = settings.channels["ix_feed"].scale
    return (sum(head) / len(head)) / ff.newton_per_amp / scale


def transit_revs(scenario: str, feed_per_tooth_mm: float) -> int:
    """Revolutions for the tool to travel its own diameter: how long a step in the
    part takes to reach the whole engagement."""
    from millsense.sim.scenarios import SCENARIOS

    tool = SCENARIOS[scenario].tool
    return int(tool.diameter_mm / (feed_per_tooth_mm * tool.flutes)) + 1
