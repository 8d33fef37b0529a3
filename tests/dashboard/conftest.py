"""The browser for tests/dashboard: Debian's chromium and chromedriver, driven over WebDriver.

Without them the tests skip and say what to install; under CI=true they fail
instead, since CI is where the browser must be (.ci/run installs it).
"""

from __future__ import annotations

import os

import pytest

from tests.dashboard.webdriver import Browser, find_browser


@pytest.fixture
def browser(tmp_path):
    found = find_browser()
    if isinstance(found, str):
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true and {found}")
        pytest.skip(found)
    b = Browser(*found, log_dir=tmp_path)
    try:
        yield b
    finally:
        b.close()
