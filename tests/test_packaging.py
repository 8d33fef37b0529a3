"""The wheel carries every package, under the millsense namespace only."""

from __future__ import annotations

import importlib
import subprocess
import sys
import tomllib
import zipfile

from tests.conftest import REPO


def _declared_packages() -> set[str]:
    with open(REPO / "pyproject.toml", "rb") as fh:
        return set(tomllib.load(fh)["tool"]["setuptools"]["packages"])


def _package_folders() -> set[str]:
    found = set()
    for top, prefix in (("daemon", "millsense.daemon"), ("drivers", "millsense.drivers")):
        for init in (REPO / top).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / top).parts
            found.add(".".join((prefix, *rel)))
    return found


def test_every_package_folder_is_declared():
    missing = _package_folders() - _declared_packages()
    assert not missing, f"add to [tool.setuptools] packages in pyproject.toml: {sorted(missing)}"


def test_declared_packages_import():
    for name in sorted(_declared_packages()):
        importlib.import_module(name)


def test_wheel_installs_only_under_millsense(tmp_path):
    """A built wheel holds millsense/daemon and millsense/drivers, never bare daemon/ or drivers/."""
    # pip's own isolated build environment: a fresh venv's setuptools may predate bdist_wheel
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(REPO)],
        capture_output=True, text=True, timeout=300,
    )
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = tmp_path.glob("millsense-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops <= {"millsense", next(t for t in tops if t.endswith(".dist-info"))}, tops
    assert "millsense/daemon/cli.py" in names
    assert "millsense/drivers/protocol.py" in names
    assert "millsense/daemon/demo.toml" in names
    # the licence the metadata names travels with the code (Apache-2.0, pyproject's `license`)
    assert any(n.endswith(".dist-info/licenses/LICENSE") for n in names), names
    dist_info = next(t for t in tops if t.endswith(".dist-info"))
    meta = zipfile.ZipFile(wheel).read(f"{dist_info}/METADATA").decode()
    assert "License-Expression: Apache-2.0" in meta and "License-File: LICENSE" in meta, meta[:800]
