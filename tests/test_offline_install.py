"""The offline install (docs/install.md): a wheelhouse built by systemd/wheelhouse.sh
installs into a fresh venv with systemd/install-offline.sh when pip can reach no index.

One wheelhouse and one installed venv serve the whole module (numpy, scipy and zenoh
are tens of MB). Building it needs the package index; pip's cache makes that quick
after CI's own install. Under CI a failed build is a failure; elsewhere a build that
fails for want of a network skips, saying so.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from millsense.daemon import __version__
from tests.conftest import REPO

pytestmark = pytest.mark.slow  # over about 10 s each: handed out first (tests/parallel.py)

WHEELHOUSE_SH = REPO / "systemd" / "wheelhouse.sh"
INSTALL_OFFLINE = REPO / "systemd" / "install-offline.sh"
PROJECT = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
VERSION = __version__  # pyproject.toml's version is `dynamic`: millsense.daemon.__version__ (this checkout's)
# Port 9 (discard): nothing answers there, so any attempt to reach an index fails.
UNREACHABLE = "http://127.0.0.1:9"
NETWORK_TROUBLE = re.compile(
    r"NewConnectionError|Temporary failure in name resolution|Network is unreachable|"
    r"Max retries exceeded|Could not fetch URL|from versions: none")


def _name(requirement: str) -> str:
    """`eclipse-zenoh>=1.0` -> `eclipse_zenoh`, the way wheel file names spell it (PEP 503)."""
    return re.sub(r"[-_.]+", "_", re.match(r"[A-Za-z0-9_.-]+", requirement).group(0)).lower()


def offline_env(**more: str) -> dict[str, str]:
    """The caller's environment with every way pip could find a package outside the wheelhouse
    taken away: no pip config file (this one's names find-links and indexes), no PIP_* settings,
    no PYTHONPATH, an index URL and proxies where nothing listens, and no index at all."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith("PIP_") and k != "PYTHONPATH" and not k.lower().endswith("_proxy")}
    env.update(PIP_CONFIG_FILE=os.devnull, PIP_NO_INDEX="1", PIP_INDEX_URL=UNREACHABLE + "/simple",
               http_proxy=UNREACHABLE, https_proxy=UNREACHABLE, PYTHON=sys.executable)
    env.update(more)
    return env


def run(args: list, env: dict, timeout: float = 900) -> subprocess.CompletedProcess:
    return subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout, env=env)


def build(out: Path, *options: str) -> subprocess.CompletedProcess:
    """systemd/wheelhouse.sh on this (connected) machine, with this venv's pip and its cache."""
    return run(["sh", WHEELHOUSE_SH, out, *options], env={**os.environ, "PYTHON": sys.executable})


def skip_without_network(done: subprocess.CompletedProcess) -> None:
    if done.returncode != 0 and not os.environ.get("CI") and NETWORK_TROUBLE.search(done.stderr):
        pytest.skip(f"no package index reachable to build a wheelhouse (CI unset): {done.stderr[-300:]}")


@pytest.fixture(scope="module")
def wheelhouse(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("offline") / "wheelhouse"
    done = build(out)
    skip_without_network(done)
    assert done.returncode == 0, done.stdout + done.stderr
    return out


@pytest.fixture(scope="module")
def installed(wheelhouse, tmp_path_factory) -> dict[str, Path]:
    """install-offline.sh into a fresh venv, with the link where the unit would find it."""
    root = tmp_path_factory.mktemp("box")
    venv, bindir = root / "opt-millsense", root / "bin"
    done = run(["sh", wheelhouse / "systemd" / "install-offline.sh", wheelhouse, venv],
               env=offline_env(BINDIR=str(bindir)))
    assert done.returncode == 0, done.stdout + done.stderr
    return {"venv": venv, "millsense": bindir / "millsense", "root": root}


def test_wheelhouse_holds_every_dependency_pinned_and_the_scripts(wheelhouse):
    wheels = {p.name.split("-")[0]: p.name.split("-")[1] for p in wheelhouse.glob("*.whl")}
    assert wheels["millsense"] == VERSION
    for requirement in PROJECT["dependencies"]:
        assert _name(requirement) in wheels, f"{requirement}: no wheel in the wheelhouse"
    pins = (wheelhouse / "requirements.txt").read_text().split()
    assert pins[0] == f"millsense=={VERSION}"
    assert sorted(pins) == sorted(f"{name}=={version}" for name, version in wheels.items())
    assert not list(wheelhouse.glob("*.tar.gz")) and not list(wheelhouse.glob("*.zip")), "only wheels: the box builds nothing"
    readme = (wheelhouse / "README.txt").read_text()
    assert f"built for: Python {sys.version_info[0]}.{sys.version_info[1]} on " in readme
    for script in ("install-offline.sh", "install.sh", "millsense@.service", "millsense.sysusers.conf"):
        assert (wheelhouse / "systemd" / script).read_bytes() == (REPO / "systemd" / script).read_bytes()
    assert sorted(p.name for p in (wheelhouse / "config").iterdir()) == sorted(p.name for p in (REPO / "config").iterdir())
    # the documentation install.sh puts where the unit's Documentation= points
    assert (wheelhouse / "README.md").read_bytes() == (REPO / "README.md").read_bytes()
    assert sorted(p.name for p in (wheelhouse / "docs").glob("*.md")) == sorted(p.name for p in (REPO / "docs").glob("*.md"))


def test_installed_cli_runs_from_its_own_venv(installed):
    version = run([installed["millsense"], "--version"], env=offline_env())
    assert version.returncode == 0, version.stderr
    assert version.stdout.strip() == f"millsense {VERSION}"
    # The code comes from the venv, not from this checkout's editable install.
    where = run([installed["venv"] / "bin" / "python", "-c", "import millsense.daemon.cli as c; print(c.__file__)"],
                env=offline_env())
    assert Path(where.stdout.strip()).is_relative_to(installed["venv"]), where.stdout + where.stderr
    # with its package data: the demo configuration `millsense run` starts without --config
    demo = run([installed["venv"] / "bin" / "python", "-c",
                "from millsense.daemon.config.load import demo_config; print(demo_config().machine)"], env=offline_env())
    assert demo.returncode == 0 and demo.stdout.strip() == "mch10-demo", demo.stdout + demo.stderr
    # with the -OO bytecode the unit's PYTHONOPTIMIZE=2 reads (the service cannot write it), for
    # millsense's modules and for its libraries
    compiled = run([installed["venv"] / "bin" / "python", "-c",
                    "import importlib.util as u, os, millsense.daemon.runtime.runner as r, numpy, pydantic\n"
                    "print([m.__name__ for m in (r, numpy, pydantic)"
                    " if not os.path.exists(u.cache_from_source(m.__file__, optimization=2))])"], env=offline_env())
    assert compiled.returncode == 0 and compiled.stdout.strip() == "[]", compiled.stdout + compiled.stderr


def test_installed_cli_checks_a_shipped_config(installed, wheelhouse):
    """As install.sh would: the example copied into /etc/millsense, its token made by `token new`."""
    millsense, etc = installed["millsense"], installed["root"] / "etc"
    etc.mkdir()
    config = etc / "mch10-01.toml"
    shutil.copyfile(wheelhouse / "config" / "mch10-spindle-power.toml", config)
    token_file = tomllib.loads(config.read_text())["interlock"]["reset_token_file"]
    made = run([millsense, "token", "new", "--out", etc / token_file], env=offline_env())
    assert made.returncode == 0, made.stderr
    checked = run([millsense, "check-config", config], env=offline_env())
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert checked.stdout.startswith(f"{config}: OK (machine mch10-01"), checked.stdout
    # and it refuses what it should: a wrong value, named by section.key, exit 78
    bad = etc / "bad.toml"
    bad.write_text(config.read_text().replace("flutes = 2", "flutes = 0"))
    refused = run([millsense, "check-config", bad], env=offline_env())
    assert refused.returncode == 78 and "tool.flutes" in refused.stdout + refused.stderr, refused


def test_running_again_upgrades_in_place_and_replaces_the_code(installed, wheelhouse):
    """The upgrade path: the same command over an existing venv. A wheel rebuilt with the
    same version number must still replace the installed code."""
    init = next((installed["venv"] / "lib").glob("python3*/site-packages/millsense/daemon/__init__.py"))
    original = init.read_text()
    init.write_text(original + "\nSTALE_FROM_AN_OLDER_BUILD = True\n")
    done = run(["sh", INSTALL_OFFLINE, wheelhouse, installed["venv"]], env=offline_env(BINDIR=""))
    assert done.returncode == 0, done.stdout + done.stderr
    assert init.read_text() == original


def test_a_missing_wheel_is_named_and_installs_nothing(wheelhouse, tmp_path):
    """A wheelhouse without scipy (as one built for another platform would be for this box).
    The index here *has* scipy: had the script not passed --no-index, pip would take it from
    there and succeed, so PIP_NO_INDEX is left unset for this one."""
    partial = tmp_path / "partial"
    partial.mkdir()
    for item in wheelhouse.iterdir():
        if not item.name.startswith("scipy-"):
            (partial / item.name).symlink_to(item)
    index = tmp_path / "index" / "scipy"
    index.mkdir(parents=True)
    (scipy_wheel,) = wheelhouse.glob("scipy-*.whl")
    (index / scipy_wheel.name).symlink_to(scipy_wheel)
    # pip reads a file: index's project page from its index.html (PEP 503)
    (index / "index.html").write_text(f'<a href="{scipy_wheel.name}">{scipy_wheel.name}</a>\n')
    env = offline_env(BINDIR="", PIP_INDEX_URL=index.parent.as_uri())
    del env["PIP_NO_INDEX"]
    venv = tmp_path / "venv"
    done = run(["sh", INSTALL_OFFLINE, partial, venv], env=env)
    assert done.returncode == 1, done.stdout + done.stderr
    assert f"{partial} has no wheel of scipy==" in done.stderr, done.stderr
    assert "it was built for Python" in done.stderr and "--python-version" in done.stderr, done.stderr
    assert not list(venv.glob("lib/python3*/site-packages/numpy")), "nothing installed when one wheel is missing"


@pytest.mark.parametrize("case", ["missing", "not-a-wheelhouse"])
def test_install_refuses_a_directory_that_is_no_wheelhouse(case, tmp_path):
    target = tmp_path / "nothing-here"
    if case == "not-a-wheelhouse":
        target.mkdir()
        (target / "requirements.txt").write_text("numpy==2.0\n")
    venv = tmp_path / "venv"
    done = run(["sh", INSTALL_OFFLINE, target, venv], env=offline_env(BINDIR=""))
    assert done.returncode == 2, done
    expected = "no such directory" if case == "missing" else "holds no millsense wheel"
    assert f"{target}" in done.stderr and expected in done.stderr, done.stderr
    assert not venv.exists(), "a refused install makes no venv"


def test_wheelhouse_refuses_an_unknown_extra_before_building(tmp_path):
    done = build(tmp_path / "w", "--extra", "plto")
    assert done.returncode == 2, done
    assert "--extra plto" in done.stderr and "plot" in done.stderr, done.stderr
    assert not (tmp_path / "w").exists()


def test_wheelhouse_names_the_dependency_with_no_wheel_for_the_target(wheelhouse, tmp_path):
    """A platform nothing is built for: the first dependency pip cannot find is named, and no
    half-made wheelhouse is left to be copied to a box."""
    out = tmp_path / "w"
    done = build(out, "--python-version", "3.11", "--platform", "nonesuch_riscv")
    if done.returncode != 0 and not os.environ.get("CI") and not re.search(r"no wheel of \S+", done.stderr):
        skip_without_network(done)
    assert done.returncode == 1, done.stdout + done.stderr
    named = re.search(r"no wheel of (\S+) for Python 3\.11 on nonesuch_riscv", done.stderr)
    assert named, done.stderr
    assert _name(named.group(1)) in {p.name.split("-")[0].lower() for p in wheelhouse.glob("*.whl")}, "one of millsense's dependencies"
    assert not out.exists() and not list(tmp_path.glob("w.partial*"))
