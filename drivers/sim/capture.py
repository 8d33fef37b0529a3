"""Capture files: the byte stream the DAQ would have sent, generated as fast as possible.

A capture is DESCRIPTOR, then SAMPLES frames from index 0, with the DESCRIPTOR
repeated once a second as the device does (daq-protocol.md, stream transport),
so ``millsense replay`` reads it exactly like a live serial stream.
"""

from __future__ import annotations

from millsense.drivers.protocol import encode_descriptor, encode_sample_frames
from millsense.drivers.sim.plant import Plant


def write_capture(scenario, capture_path, truth_path=None, *, seed: int = 0, per_frame: int = 10,
                  filter_cutoff_hz: float | None = None, noise_scale: float = 1.0,
                  descriptor_every_s: float = 1.0, extra_channels=None, duration_s: float | None = None) -> int:
    """Write the whole scenario (or ``duration_s`` of it) and its truth; returns the sample count."""
    if not 1 <= per_frame <= 64:
        raise ValueError("per_frame must be 1..64 samples (SAMPLES frame limit)")
    plant = Plant(scenario, seed=seed, extra_channels=extra_channels, filter_cutoff_hz=filter_cutoff_hz,
                  noise_scale=noise_scale)
    total = round((plant.duration_s if duration_s is None else duration_s) * plant.sample_rate_hz)
    every = max(1, round(descriptor_every_s * plant.sample_rate_hz))
    descriptor = encode_descriptor(plant.descriptor)
    done = 0
    with open(capture_path, "wb") as fh:
        while done < total:
            n = min(every, total - done)
            fh.write(descriptor)
            fh.write(encode_sample_frames(done, plant.step(n), per_frame=per_frame))
            done += n
    if truth_path is not None:
        plant.truth.write_jsonl(truth_path)
    return done
