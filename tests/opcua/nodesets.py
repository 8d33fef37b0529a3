"""The OPC Foundation's NodeSet2 files the OPC UA tests load, fetched from the npm registry, never kept in
this repository (issue 42, docs/opcua.md "The companion specifications").

`node-opcua-nodesets` at a pinned version, checked against the SHA-256 recorded here (its registry
integrity, sha512, is recorded beside it: `npm view node-opcua-nodesets@VERSION dist.integrity`). One
copy per test run, shared by every module and worker (tests/captures.py: a lock, built aside, renamed).
`.ci/run` fetches the tarball once into a cache folder (`MILLSENSE_NODESETS_CACHE`) with
`python -m tests.opcua.nodesets DIR`; without it, the first test that needs the files runs `npm pack`.
An unreachable registry, a missing `npm` or a tarball that is not the recorded one fails the tests: never a skip.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

from tests.captures import shared

PACKAGE = "node-opcua-nodesets"
VERSION = "2.185.0"
TARBALL_SHA256 = "c32b8b760a0cad4064a6c9d73d52547e3ce1933974df354998cabdfe826837d3"
# npm's own record of the same tarball (`dist.integrity`), for whoever checks it by hand
TARBALL_INTEGRITY = "sha512-7qDwdkYRKIGRBk0gKhY5C3olQ0wRHTCoZj4FbzD1GmXF5xGaZcv/OatvFa73H7yyq3LxWxTKVteELlbbyziyLg=="
# The six models, by their file names in this version of the package (the loader itself goes by the
# model URI each file declares, not by its name).
FILES = ("Opc.Ua.Di.NodeSet2.xml", "Opc.Ua.IA.NodeSet2.xml", "Opc.Ua.Machinery.NodeSet2.xml",
         "opc.ua.isa95-jobcontrol.nodeset2.xml", "Opc.Ua.Machinery.Jobs.Nodeset2.xml",
         "Opc.Ua.MachineTool.NodeSet2.xml")
CACHE_ENV = "MILLSENSE_NODESETS_CACHE"
TARBALL = f"{PACKAGE}-{VERSION}.tgz"
NPM_TIMEOUT_S = 300.0  # a failure detector for a hung registry, not a budget


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def tarball(cache: Path) -> Path:
    """The package's tarball in `cache`, fetched with `npm pack` when absent; always checked. Raises RuntimeError."""
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / TARBALL
    if not path.is_file():
        if shutil.which("npm") is None:
            raise RuntimeError(f"the OPC UA nodeset tests need npm (Debian: apt-get install npm) to fetch "
                               f"{PACKAGE}@{VERSION}")
        with tempfile.TemporaryDirectory(dir=cache) as work:
            # npm's own cache inside the work folder: nothing in the user's home
            done = subprocess.run(["npm", "pack", f"{PACKAGE}@{VERSION}", "--pack-destination", work,
                                   "--cache", str(Path(work) / "npm-cache"), "--silent"],
                                  capture_output=True, text=True, timeout=NPM_TIMEOUT_S)
            got = Path(work) / TARBALL
            if done.returncode != 0 or not got.is_file():
                raise RuntimeError(f"npm pack {PACKAGE}@{VERSION} failed (exit {done.returncode}): "
                                   f"{(done.stderr or done.stdout).strip()[-800:]}")
            os.replace(got, path)
    digest = _sha256(path)
    if digest != TARBALL_SHA256:
        raise RuntimeError(f"{path}: SHA-256 {digest}, not the recorded {TARBALL_SHA256} of {PACKAGE}@{VERSION}")
    return path


def extract(archive: Path, dest: Path) -> None:
    """The six NodeSet2 files of the package into `dest`."""
    with tarfile.open(archive) as tar:
        for name in FILES:
            member = tar.getmember(f"package/nodesets/{name}")
            source = tar.extractfile(member)
            assert source is not None, name
            (dest / name).write_bytes(source.read())


def folder() -> Path:
    """The run's shared, read-only folder of the six files."""

    def build(dest: Path) -> None:
        cache = os.environ.get(CACHE_ENV)
        if cache:
            extract(tarball(Path(cache)), dest)
            return
        with tempfile.TemporaryDirectory(prefix="millsense-npm-") as work:
            extract(tarball(Path(work)), dest)

    return shared(f"{PACKAGE}@{VERSION} {TARBALL_SHA256}", build)


if __name__ == "__main__":  # .ci/run: fetch and check the tarball once, into the cache folder given
    print(tarball(Path(sys.argv[1])))
