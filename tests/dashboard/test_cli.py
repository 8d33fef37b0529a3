"""`millsense dashboard` as a user runs it: bad options, a taken port, HTTPS, and a clean stop."""

from __future__ import annotations

import json
import signal
import socket
import ssl
import subprocess
import urllib.request

from tests.conftest import free_tcp_port
from tests.e2e.helpers import CMD, Procs, wait_for
from tests.publish.pki import Pki

ZENOH = ["--connect", "tcp/127.0.0.1:1", "--no-scouting", "--mode", "peer"]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(CMD + ["dashboard", *args], capture_output=True, text=True, timeout=60)


def test_bad_options_say_one_line_and_exit_2(tmp_path):
    for args, words in ((["--listen", "nonsense"], "--listen"), (["--cert", str(tmp_path / "c.pem")], "go together"),
                        (["--cert", str(tmp_path / "c.pem"), "--key", str(tmp_path / "k.pem")], "cannot load")):
        p = _run(*args, *ZENOH)
        assert p.returncode == 2, p.stderr
        assert words in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_an_unreadable_daemon_config_exits_78(tmp_path):
    p = _run("--config", str(tmp_path / "missing.toml"))
    assert p.returncode == 78 and "missing.toml" in p.stderr and "Traceback" not in p.stderr


def test_a_taken_port_is_a_clear_error(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        p = _run("--listen", f"127.0.0.1:{taken.getsockname()[1]}", *ZENOH)
    assert p.returncode == 1 and "cannot listen on" in p.stderr and "Traceback" not in p.stderr


def test_https_with_a_certificate_offers_the_reset_off_localhost_and_stops_on_sigterm(tmp_path):
    pki = Pki(tmp_path)
    cert, key = pki.issue("dash", "localhost")
    port = free_tcp_port()
    with Procs(tmp_path) as procs:
        dash = procs.start("dash", ["dashboard", "--listen", f"0.0.0.0:{port}", "--cert", str(cert), "--key", str(key),
                                    *ZENOH])
        wait_for(lambda: "serving on" in procs.text("dash") or dash.poll() is not None, 60, "dashboard serving")
        assert f"https://0.0.0.0:{port}/" in procs.text("dash"), procs.text("dash")
        ctx = ssl.create_default_context(cafile=str(pki.ca))
        with urllib.request.urlopen(f"https://localhost:{port}/api/info", context=ctx, timeout=10) as r:
            info = json.loads(r.read())
        assert info == {"reset_offered": True, "https": True}
        with urllib.request.urlopen(f"https://localhost:{port}/", context=ctx, timeout=10) as r:
            page = r.read().decode()
            csp = r.headers["Content-Security-Policy"]
        assert "/static/app.js" in page and "http" not in page.split("<body>")[0].replace('http-equiv', '')
        assert "default-src 'self'" in csp
        dash.send_signal(signal.SIGTERM)
        assert dash.wait(30) == 0, procs.text("dash")


def test_plain_http_off_localhost_says_the_reset_is_not_offered(tmp_path):
    port = free_tcp_port()
    with Procs(tmp_path) as procs:
        dash = procs.start("dash", ["dashboard", "--listen", f"0.0.0.0:{port}", *ZENOH])
        wait_for(lambda: "serving on" in procs.text("dash") or dash.poll() is not None, 60, "dashboard serving")
        assert "reset not offered" in procs.text("dash"), procs.text("dash")
        dash.send_signal(signal.SIGTERM)
        assert dash.wait(30) == 0, procs.text("dash")
