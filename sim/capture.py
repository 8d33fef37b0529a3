"""Capture files: the byte stream the DAQ would have sent, generated as fast as possible.

A capture is DESCRIPTOR, then SAMPLES frames from index 0, with the DESCRIPTOR
repeated once a second as the device does (daq-protocol.md, stream transport),
so ``millsense replay`` reads it exactly like a live serial stream.

A part program (``program.py``) is written as a version-2 DAQ reporting context:
its CONTEXT goes with each DESCRIPTOR and, on every change, just before the
first sample it holds for (as ``millsense sim --capture`` writes it).
"""

from __future__ import annotations

from dataclasses import replace

from millsense.drivers.protocol import (
    CAP_CONTEXT,
    CAP_FEED_OVERRIDE,
    Context,
    encode_context,
    encode_descriptor,
    encode_sample_frames,
)
from millsense.sim.plant import Plant


def write_capture(scenario, capture_path, truth_path=None, *, seed: int = 0, per_frame: int = 10,
                  filter_cutoff_hz: float | None = None, noise_scale: float = 1.0,
                  descriptor_every_s: float = 1.0, extra_channels=None, duration_s: float | None = None,
                  parts: int | None = None, faults=None) -> int:
    """Write the whole scenario (or ``duration_s`` of it) and its truth; returns the sample count.

    ``parts`` and ``faults`` (a ``ProgramFaults``) are for a part program only."""
    if not 1 <= per_frame <= 64:
        raise ValueError("per_frame must be 1..64 samples (SAMPLES frame limit)")
    from millsense.sim.program import PROGRAMS, PartProgram

    if isinstance(scenario, PartProgram) or (isinstance(scenario, str) and scenario in PROGRAMS):
        from millsense.sim.program_plant import ProgramPlant

        plant = ProgramPlant(scenario, parts=parts, faults=faults, seed=seed, extra_channels=extra_channels,
                             filter_cutoff_hz=filter_cutoff_hz, noise_scale=noise_scale)
        descriptor = replace(plant.descriptor, protocol_version=2, capabilities=CAP_FEED_OVERRIDE | CAP_CONTEXT)
    elif parts is not None or faults is not None:
        raise ValueError(f"parts and faults are for a part program, not scenario {scenario!r}")
    else:
        plant = Plant(scenario, seed=seed, extra_channels=extra_channels, filter_cutoff_hz=filter_cutoff_hz,
                      noise_scale=noise_scale)
        descriptor = plant.descriptor
    drain = getattr(plant, "drain_context", None)
    context = Context(0, *plant.context()) if drain else None
    total = round((plant.duration_s if duration_s is None else duration_s) * plant.sample_rate_hz)
    every = max(1, round(descriptor_every_s * plant.sample_rate_hz))
    encoded_descriptor = encode_descriptor(descriptor)
    done = 0
    with open(capture_path, "wb") as fh:
        while done < total:
            n = min(every, total - done)
            fh.write(encoded_descriptor + (encode_context(context) if context else b""))
            counts = plant.step(n)
            start = 0
            for index, fields in drain() if drain else ():
                fh.write(encode_sample_frames(done + start, counts[start : index - done], per_frame=per_frame))
                context = Context(index, *fields)
                fh.write(encode_context(context))
                start = index - done
            fh.write(encode_sample_frames(done + start, counts[start:], per_frame=per_frame))
            done += n
    if truth_path is not None:
        plant.truth.write_jsonl(truth_path)
    return done
