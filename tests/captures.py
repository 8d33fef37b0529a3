"""Captures of the simulated plant (and the firmware's host builds) made once per test run and shared by
every module and worker.

A capture is a pure function of what generates it (the scenario, the seed, the flags of
`millsense sim`): the plant is seeded and plays no clock. Several modules (and several tests
of one module) ask for the same one; each used to build its own copy, at 0.5 to 2 CPU s a
capture (docs/testing.md, "Captures made once a run"). `shared(key, build)` builds it the first
time any test of the run asks, with exactly the call the test made before, and hands every
later asker the same files:

- **one folder per run**: under xdist, the run's own folder that tests/parallel.py keeps
  for its locks (removed by the controller at the end of the run); in one process (`-n 0`,
  the planted-bug script), a folder of this process, removed when it exits. Nothing
  outlives the run, so a capture made by yesterday's simulator is never read today;
- **one builder**: a file lock per key (`flock`, dropped by the kernel if its holder
  dies), so that two workers asking at once build it once; the second waits, then reads;
- **never half a capture**: it is built in a folder of its own and renamed into place
  when complete; a build that fails leaves nothing, and the next asker builds again;
- **read-only**: the files are made read-only, so a test that would change a shared
  capture in place fails at once instead of changing it for the tests after it (a test
  that damages a capture writes its own copy). Root may write a read-only file, so each
  asker also checks the files' SHA-256 against the ones the build wrote, and refuses a
  capture some test has changed.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import hashlib
import io
import json
import os
import shutil
import stat
import tempfile
from collections.abc import Callable
from pathlib import Path

_own_root: Path | None = None


def root() -> Path:
    """The run's folder of shared captures."""
    global _own_root
    run = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    if os.environ.get("PYTEST_XDIST_WORKER") and run:
        from tests.parallel import _lock_path

        d = _lock_path("captures", run)
        d.mkdir(exist_ok=True)
        return d
    if _own_root is None:
        _own_root = Path(tempfile.mkdtemp(prefix="millsense-captures-"))
        atexit.register(shutil.rmtree, _own_root, True)
    return _own_root


def shared(key: str, build: Callable[[Path], None]) -> Path:
    """The folder of what `build(folder)` wrote for `key`, built once per run.

    `key` must name everything the build depends on (scenario, seed, duration, flags): two
    builds with one key must write the same bytes."""
    base = root()
    name = hashlib.sha256(key.encode()).hexdigest()[:20]
    done = base / name
    if done.is_dir():
        return _unchanged(done, key)
    fd = os.open(lock_file(key), os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        if not done.is_dir():
            work = Path(tempfile.mkdtemp(prefix=f"{name}.", dir=base))
            try:
                build(work)
                sums = {str(f.relative_to(work)): _sha256(f) for f in _files(work)}
                (work / SUMS).write_text(json.dumps({"key": key, "sha256": sums}, indent=1) + "\n")
                for f in _files(work):
                    # read-only; an executable stays one
                    f.chmod(f.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
                os.rename(work, done)
            except BaseException:
                shutil.rmtree(work, ignore_errors=True)
                raise
    finally:
        os.close(fd)   # closing drops the lock
    return _unchanged(done, key)


def lock_file(key: str) -> Path:
    """The file whose lock the builder of `key` holds."""
    return root() / f"{hashlib.sha256(key.encode()).hexdigest()[:20]}.lock"


SUMS = "sha256.json"


def _files(d: Path) -> list[Path]:
    return sorted(f for f in d.rglob("*") if f.is_file() and not f.is_symlink())


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _unchanged(done: Path, key: str) -> Path:
    """`done`, once every file the build wrote is as it wrote it (a shared capture is never changed)."""
    sums = json.loads((done / SUMS).read_text())
    assert sums["key"] == key, f"shared folder {done} holds {sums['key']!r}, not {key!r}"
    for name, digest in sums["sha256"].items():
        assert _sha256(done / name) == digest, f"a test changed the shared capture {done / name} ({key})"
    return done


def link(shared_file: Path, where: Path) -> Path:
    """`where`, a link to a shared (read-only) file: the path a test used before the captures were shared."""
    if not where.is_symlink():
        where.symlink_to(shared_file)
    return where


def sim(*args: object) -> None:
    """`millsense sim ARGS` (a `--capture`) run in this process: the CLI's own code, without a new interpreter's
    start-up and imports (about 0.3 CPU s a build, and a run builds over a hundred). Fails with what it said."""
    from millsense.daemon.cli import main

    words = [str(a) for a in args]
    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said), contextlib.redirect_stdout(said):
            code = main(["sim", *words])
    except SystemExit as exc:   # argparse refusing an argument
        code = exc.code
    assert code == 0, f"millsense sim {' '.join(words)}: exit {code}: {said.getvalue()[-2000:]}"
