"""The captures shared by a test run (tests/captures.py): the bytes a build in place writes, built once
however many ask at once, and never handed over changed."""

from __future__ import annotations

import os
import threading
import uuid
from pathlib import Path

import pytest

from tests import captures
from tests.e2e.helpers import wait_for

pytestmark = pytest.mark.quick  # what many live modules read is checked in the inner loop too (a few seconds)


def test_a_shared_capture_is_the_bytes_the_simulator_writes_in_place(tmp_path):
    from millsense.sim import write_capture
    from tests.estimator import simcase

    cap, truth = simcase.capture(tmp_path, "crash", seed=4)
    write_capture("crash", str(tmp_path / "own.bin"), str(tmp_path / "own.jsonl"), seed=4, noise_scale=1.0,
                  extra_channels=None)
    assert cap.read_bytes() == (tmp_path / "own.bin").read_bytes()
    assert truth.read_bytes() == (tmp_path / "own.jsonl").read_bytes()
    again, _ = simcase.capture(tmp_path / "..", "crash", seed=4)     # another test's folder: the same files
    assert again.resolve() == cap.resolve()


def _flock_waiters(path: Path) -> int:
    """Processes or threads blocked on a lock of this file (Linux: the `->` lines of /proc/locks)."""
    inode = f":{os.stat(path).st_ino}"
    return sum(1 for line in Path("/proc/locks").read_text().splitlines()
               if "->" in line and line.split()[-3].endswith(inode))


def test_two_askers_at_once_build_once_and_get_the_same_files():
    key = f"test {uuid.uuid4()}"
    inside, release = threading.Event(), threading.Event()
    builds, got, errors = [], [], []

    def build(d: Path) -> None:
        builds.append(d)
        inside.set()
        assert release.wait(60)
        (d / "capture.bin").write_bytes(b"plant")

    def ask() -> None:
        try:
            got.append(captures.shared(key, build))
        except BaseException as exc:  # noqa: BLE001 - reported by the test's thread
            errors.append(exc)

    first = threading.Thread(target=ask)
    first.start()
    assert inside.wait(60)
    second = threading.Thread(target=ask)
    second.start()
    try:
        # the second asker waits on the first's lock; without it, it would be building a second copy
        wait_for(lambda: len(builds) > 1 or _flock_waiters(captures.lock_file(key)), 60, "the second asker waits")
    finally:
        release.set()
        first.join(60)
        second.join(60)
    assert not errors, errors
    assert len(builds) == 1
    assert got[0] == got[1] and (got[0] / "capture.bin").read_bytes() == b"plant"


def test_a_shared_capture_a_test_changed_is_refused():
    key = f"test {uuid.uuid4()}"
    d = captures.shared(key, lambda d: (d / "capture.bin").write_bytes(b"plant"))
    f = d / "capture.bin"
    f.chmod(0o644)            # what root may do to a read-only file anyway
    f.write_bytes(b"plane")
    with pytest.raises(AssertionError, match="a test changed the shared capture"):
        captures.shared(key, lambda d: None)


def test_a_failed_build_leaves_nothing_and_the_next_asker_builds_again():
    key = f"test {uuid.uuid4()}"

    def fails(d: Path) -> None:
        (d / "capture.bin").write_bytes(b"half")
        raise RuntimeError("the simulator failed")

    with pytest.raises(RuntimeError, match="the simulator failed"):
        captures.shared(key, fails)
    stem = captures.lock_file(key).stem
    assert [p.name for p in captures.root().glob(f"{stem}*") if p.suffix != ".lock"] == []
    d = captures.shared(key, lambda d: (d / "capture.bin").write_bytes(b"whole"))
    assert (d / "capture.bin").read_bytes() == b"whole"
