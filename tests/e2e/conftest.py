"""Fixtures of the end-to-end tests."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests import captures
from tests.e2e.helpers import CMD

STEP_CAPTURE_S = 16


@pytest.fixture(scope="session")
def step_capture(tmp_path_factory):
    """A capture of the first seconds of the step scenario, with its truth (fast, no pacing): made once per
    test run and shared by the workers (tests/captures.py), read-only."""

    def build(d):
        p = subprocess.run(
            CMD + ["sim", "--scenario", "step", "--capture", str(d / "step.cap"), "--duration-s", str(STEP_CAPTURE_S),
                   "--truth", str(d / "truth.jsonl")],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert p.returncode == 0, p.stderr

    d = captures.shared(f"millsense sim --scenario step --duration-s {STEP_CAPTURE_S} --truth", build)
    cap, truth = d / "step.cap", d / "truth.jsonl"
    return cap, [json.loads(x) for x in truth.read_text().splitlines() if x.strip()]
