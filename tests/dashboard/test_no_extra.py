"""`millsense dashboard` needs no extra (README, docs/dashboard.md): it serves its page with none installed.

docs/dashboard.md asked for `pip install 'millsense[hmi]'` while the README said the dashboard needs
nothing beyond the core. The truth is the code's: here the dashboard runs in a Python where every
extra's package (asyncua of `opcua`/`hmi`, matplotlib of `plot`, cryptography of `test`) cannot be
imported, and still serves its page; and the page that says how to run it asks for no extra.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tomllib
import urllib.request

from tests.conftest import REPO, free_tcp_port
from tests.e2e.helpers import Procs, wait_for

ZENOH = ["--connect", "tcp/127.0.0.1:1", "--no-scouting", "--mode", "peer"]


def _extras_packages() -> set[str]:
    """The top-level import names of every optional dependency but the test tools."""
    with open(REPO / "pyproject.toml", "rb") as fh:
        extras = tomllib.load(fh)["project"]["optional-dependencies"]
    names = {re.split(r"[<>=\[ ;]", req, maxsplit=1)[0].lower() for reqs in extras.values() for req in reqs}
    return names - {"pytest", "hypothesis"}


def test_the_dashboard_serves_its_page_with_no_extra_importable(tmp_path):
    blocked = sorted(_extras_packages())
    assert {"asyncua", "matplotlib", "cryptography"} <= set(blocked)
    code = ("import sys\n"
            f"for name in {blocked!r}: sys.modules[name] = None   # import fails, as when not installed\n"
            "from millsense.daemon.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    port = free_tcp_port()
    with Procs(tmp_path) as procs, open(tmp_path / "dash.err", "wb") as err:
        dash = subprocess.Popen([sys.executable, "-c", code, "dashboard", "--listen", f"127.0.0.1:{port}", *ZENOH],
                                stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, "PYTHONUNBUFFERED": "1"})
        procs.procs.append(dash)   # killed on the way out if the test fails
        wait_for(lambda: "serving on" in procs.text("dash") or dash.poll() is not None, 60, "dashboard serving")
        assert dash.poll() is None, procs.text("dash")
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as r:
            assert r.status == 200 and "/static/app.js" in r.read().decode()
        dash.send_signal(signal.SIGTERM)
        assert dash.wait(30) == 0, procs.text("dash")


def test_the_dashboard_page_asks_for_no_extra():
    text = (REPO / "docs" / "dashboard.md").read_text(encoding="utf-8")
    running = text[text.index("## Running it"):text.index("## What the page shows")]
    assert "millsense[" not in running, "docs/dashboard.md asks for an extra the dashboard does not need"
