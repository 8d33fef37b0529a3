"""Fixtures of the firmware tests: the host build (plain, and under ASan + UBSan), made with the system's
`cc` once per test run (tests/captures.py), and the captures it plays."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from tests import captures
from tests.conftest import REPO
from tests.e2e.conftest import step_capture  # noqa: F401 - the e2e tests' capture of the step scenario, reused
from tests.e2e.helpers import CMD

FIRMWARE = REPO / "firmware"
BUILDS = {"plain": "host", "san": "host-san"}


def _missing(what: str) -> None:
    """No compiler: a skip with its reason on a developer's box, a failure in CI (which must build it)."""
    message = f"the firmware tests need {what} (Debian: build-essential)"
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)


def _build(kind: str) -> Path:
    """The build, made once per test run and shared by the workers (tests/captures.py): the serial phase's
    firmware tests find it made by the parallel ones, not compiled while nothing else may run."""
    for tool in ("cc", "make"):
        if shutil.which(tool) is None:
            _missing(tool)

    def make(out: Path) -> None:
        p = subprocess.run(["make", "-C", str(FIRMWARE), f"BUILD={out}", BUILDS[kind]], capture_output=True,
                           text=True, timeout=300)
        assert p.returncode == 0, f"make {BUILDS[kind]} failed:\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}"

    out = captures.shared(f"make -C firmware {BUILDS[kind]}", make)
    return out / "san" if kind == "san" else out


@pytest.fixture(scope="session")
def plain_build() -> Path:
    """The directory of the plain host build: msfw-host, msfw-selftest."""
    return _build("plain")


@pytest.fixture(scope="session", params=["plain", "san"])
def any_build(request) -> Path:
    """Each host build in turn: the plain one and the one under AddressSanitizer and UBSan."""
    return _build(request.param)


def _sim_capture(*args: str) -> Path:
    """`millsense sim ... --capture`, made once per test run and shared by the workers (tests/captures.py)."""

    def build(d: Path) -> None:
        p = subprocess.run(CMD + ["sim", *args, "--capture", str(d / "capture.cap")], capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 0, p.stderr

    return captures.shared("millsense sim " + " ".join(args), build) / "capture.cap"


@pytest.fixture(scope="session")
def ramp_capture() -> Path:
    """Three seconds of the emulator's ramp: channel c of sample k is (k + 1000 c) mod 2^16."""
    return _sim_capture("--scenario", "ramp", "--duration-s", "3")


@pytest.fixture(scope="session")
def ramp_capture_v2() -> Path:
    """The ramp from a protocol-2 emulator whose CNC runs program 1234, tool 12, operation 3 (its CONTEXT)."""
    return _sim_capture("--scenario", "ramp", "--protocol", "2", "--program", "1234", "--tool", "12",
                        "--operation", "3", "--duration-s", "3")


def ramp_counts(index: int, channels: int = 8) -> tuple[int, ...]:
    return tuple(((index + 1000 * c) % 65536 ^ 0x8000) - 0x8000 for c in range(channels))
