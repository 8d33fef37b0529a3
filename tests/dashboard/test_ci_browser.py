"""Without a browser the browser tests skip and say what to install; under CI=true they fail."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _browser_tests_without_a_browser(tmp_path, ci: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=str(tmp_path), CI=ci)  # an empty folder: no chromium, no chromedriver
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-rs", "-p", "no:cacheprovider", "-n", "0",
                           "tests/dashboard/test_browser.py"], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=120)


def test_a_missing_browser_skips_with_the_packages_to_install(tmp_path):
    p = _browser_tests_without_a_browser(tmp_path, "")
    assert p.returncode == 0 and re.search(r"\b\d+ skipped in", p.stdout), p.stdout + p.stderr
    assert "passed" not in p.stdout and "failed" not in p.stdout, p.stdout
    assert "chromium chromium-driver" in p.stdout


def test_a_missing_browser_fails_under_ci(tmp_path):
    p = _browser_tests_without_a_browser(tmp_path, "true")
    assert p.returncode == 1 and "CI=true and no headless browser" in p.stdout, p.stdout + p.stderr
