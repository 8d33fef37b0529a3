"""A foreign OPC UA client for the tests: node-opcua from the npm registry, driven through a subprocess (issue 42).

The client is our small script `tests/opcua/node_client/client.js`; its packages are pinned to exact versions in
`tests/opcua/node_client/package.json` and `package-lock.json` (the registry's integrity of every package),
installed by `npm ci` once per test run into a folder shared by every module and worker (tests/captures.py: a
lock, built aside, renamed), never into the repository. npm's download cache is `MILLSENSE_NPM_CACHE` when set
(`.ci/run` keeps one between runs and fills it with `python -m tests.opcua.foreign`), else a throw-away folder:
nothing in the user's home. A missing `npm`/`node` or an unreachable registry fails the tests: never a skip.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path
from typing import Any

from tests.captures import shared

HERE = Path(__file__).parent / "node_client"
SCRIPT = HERE / "client.js"
CACHE_ENV = "MILLSENSE_NPM_CACHE"
NPM_TIMEOUT_S = 300.0  # a failure detector for a hung registry, not a budget


def _need(tool: str) -> str:
    path = shutil.which(tool)
    if path is None:
        raise RuntimeError(f"the foreign-client OPC UA test needs {tool} (Debian: apt-get install nodejs npm)")
    return path


def _npm_ci(dest: Path, cache: Path) -> None:
    for name in ("package.json", "package-lock.json"):
        shutil.copyfile(HERE / name, dest / name)
    done = subprocess.run([_need("npm"), "ci", "--cache", str(cache), "--prefer-offline", "--no-audit", "--no-fund",
                           "--loglevel", "error"], cwd=dest, capture_output=True, text=True, timeout=NPM_TIMEOUT_S)
    if done.returncode != 0:
        raise RuntimeError(f"npm ci in {dest} failed (exit {done.returncode}): "
                           f"{(done.stderr or done.stdout).strip()[-800:]}")


def modules() -> Path:
    """The run's shared, read-only node_modules folder of the pinned packages."""
    lock = (HERE / "package-lock.json").read_bytes()

    def build(dest: Path) -> None:
        cache = os.environ.get(CACHE_ENV)
        if cache:
            _npm_ci(dest, Path(cache))
            return
        with tempfile.TemporaryDirectory(prefix="millsense-npm-") as work:
            _npm_ci(dest, Path(work))

    return shared(f"node-opcua client {hashlib.sha256(lock).hexdigest()}", build) / "node_modules"


class NodeClient:
    """client.js running with `options`; `lines` are its JSON lines so far (a line that is not JSON, e.g. one
    of node-opcua's own warnings, as `{"step": "log", "text": ...}`)."""

    def __init__(self, options: dict[str, Any]) -> None:
        env = {**os.environ, "NODE_PATH": str(modules())}
        self.lines: list[dict[str, Any]] = []
        self.proc = subprocess.Popen([_need("node"), str(SCRIPT), json.dumps(options)], stdout=subprocess.PIPE,
                                     stderr=subprocess.STDOUT, text=True, env=env)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            try:
                line = json.loads(raw)
            except ValueError:
                line = {"step": "log", "text": raw.rstrip()}
            self.lines.append(line if isinstance(line, dict) else {"step": "log", "text": raw.rstrip()})

    def steps(self, step: str) -> list[dict[str, Any]]:
        return [line for line in list(self.lines) if line.get("step") == step]

    def ended(self) -> bool:
        return self.proc.poll() is not None

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self._reader.join(timeout=5)

    def transcript(self) -> str:
        return "\n".join(json.dumps(line) for line in list(self.lines))


if __name__ == "__main__":  # .ci/run: fill npm's cache once (MILLSENSE_NPM_CACHE), so that the tests' npm ci is local
    with tempfile.TemporaryDirectory() as folder:
        _npm_ci(Path(folder), Path(os.environ[CACHE_ENV]))
