"""Fixtures of the end-to-end tests."""

from __future__ import annotations

import json

import pytest

from tests import captures

STEP_CAPTURE_S = 16


@pytest.fixture(scope="session")
def step_capture(tmp_path_factory):
    """A capture of the first seconds of the step scenario, with its truth (fast, no pacing): made once per
    test run and shared by the workers (tests/captures.py), read-only."""

    def build(d):
        captures.sim("--scenario", "step", "--capture", d / "step.cap", "--duration-s", STEP_CAPTURE_S,
                     "--truth", d / "truth.jsonl")

    d = captures.shared(f"millsense sim --scenario step --duration-s {STEP_CAPTURE_S} --truth", build)
    cap, truth = d / "step.cap", d / "truth.jsonl"
    return cap, [json.loads(x) for x in truth.read_text().splitlines() if x.strip()]
