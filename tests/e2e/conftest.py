"""Fixtures of the end-to-end tests."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.e2e.helpers import CMD

STEP_CAPTURE_S = 16


@pytest.fixture(scope="session")
def step_capture(tmp_path_factory):
    """A capture of the first seconds of the step scenario, with its truth (fast, no pacing)."""
    d = tmp_path_factory.mktemp("step")
    cap, truth = d / "step.cap", d / "truth.jsonl"
    p = subprocess.run(
        CMD + ["sim", "--scenario", "step", "--capture", str(cap), "--duration-s", str(STEP_CAPTURE_S), "--truth", str(truth)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert p.returncode == 0, p.stderr
    return cap, [json.loads(x) for x in truth.read_text().splitlines() if x.strip()]
