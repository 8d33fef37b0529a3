"""Bad input: the fuzz corpus replayed, and a short fuzz run of the same targets on every test run.

tests/faults/corpus/decoder/ and corpus/modbus/ hold hand-made edge cases (a
run of equal frames with a bad CRC inside, a sync pattern inside a damaged
frame, the largest frame, a length over 4096, samples before or wider than the
descriptor, a descriptor with rate 0, the index wrap, a trailing 0xA5, ...),
inputs from the generators of tests/faults/fuzz_targets.py, Modbus answers
with the wrong register count (found by bench/fuzz.py before the driver
checked them), and libFuzzer's final corpus from
`bench/fuzz.py --engine atheris --corpus-out tests/faults/corpus` (inputs that
each reached code the others did not). Each must pass the targets' checks;
the long runs (10^6 inputs) are `bench/fuzz.py`.
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.faults.fuzz_targets import (
    decoder_target,
    modbus_input,
    modbus_target,
    mutate,
    reference_decode,
    stream_input,
)

CORPUS = Path(__file__).resolve().parent / "corpus"
DECODER = sorted((CORPUS / "decoder").glob("*"))
MODBUS = sorted((CORPUS / "modbus").glob("*"))


def test_the_corpus_is_there():
    assert len(DECODER) >= 30 and len(MODBUS) >= 20, (len(DECODER), len(MODBUS))


@pytest.mark.parametrize("path", DECODER, ids=lambda p: p.name)
def test_decoder_corpus(path):
    decoder_target(path.read_bytes())


@pytest.mark.parametrize("path", MODBUS, ids=lambda p: p.name)
def test_modbus_corpus(path):
    modbus_target(path.read_bytes())


def test_the_reference_decoder_is_not_the_decoder_under_test():
    """The differential check means something only if the reference can tell frames from junk itself."""
    data = (CORPUS / "decoder" / "bad-crc-mid-run-1.bin").read_bytes()[1:]
    frames, left = reference_decode(data)
    samples = sum(len(f.counts) for f in frames if hasattr(f, "counts"))
    assert samples == 190 and left == 0  # 20 frames of 10 samples, one damaged


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), raw=st.binary(max_size=600))
def test_decoder_fuzz(seed, raw):
    rng = random.Random(seed)
    decoder_target(stream_input(rng))
    decoder_target(raw)
    decoder_target(bytes([seed & 0xFF]) + mutate(raw, rng))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), raw=st.binary(max_size=600))
def test_modbus_fuzz(seed, raw):
    rng = random.Random(seed)
    modbus_target(modbus_input(rng))
    modbus_target(raw)
