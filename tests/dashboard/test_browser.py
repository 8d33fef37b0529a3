"""`millsense dashboard` in a real headless Chromium, on a real daemon, emulator and Zenoh over loopback.

One daemon on the simulated machine (the `step` scenario, a torque warning
armed low so that an alarm comes), the dashboard as a subprocess, the page
driven over WebDriver. Checked: the tile's torque changes as revolutions come;
the warning shows in the tile and in the recent alarms; a feed hold (a proof
test, asserted on the emulator's output) survives a wrong token typed into the
page and is released by the right one; a restarted daemon's tile comes back.

With MILLSENSE_SCREENSHOT=path the page is saved there (docs/dashboard.png).
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

from millsense.daemon.publish.command_auth import send_command
from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, Subscriber, read_jsonl, tcp, wait_for, write_config

TOKEN = "dashboard-token-of-at-least-32-characters-0123"
MACHINE = "dash-01"
SLOW_S = 90.0  # detects a failure on a loaded CI box; no budget


def _holds(log_path, on=True):
    return [e for e in read_jsonl(log_path) if e.get("event") == "outputs" and bool(e.get("feed_hold")) == on]


def _tile_text(browser, css):
    return browser.js("const t = document.querySelector(`article[data-machine='${arguments[0]}'] ${arguments[1]}`);"
                      "return t ? t.textContent : null;", MACHINE, css)


def _tile_class(browser):
    return browser.js("const t = document.querySelector(`article[data-machine='${arguments[0]}']`);"
                      "return t ? t.className : null;", MACHINE)


def _start_daemon(procs, cfg, name="daemon"):
    return procs.start(name, ["run", "--config", str(cfg), "--connect-timeout", "120"])


def test_page_shows_live_values_alarm_and_releases_a_held_feed(tmp_path, browser):
    daq_port, z_port, http_port = free_tcp_port(), free_tcp_port(), free_tcp_port()
    cfg = write_config(
        tmp_path / "d.toml", machine=MACHINE,
        daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
        zenoh_listen=[tcp(z_port)],
        alarms="torque_warn_nm = 0.5\nrevolutions = 2",
        interlock=f'enabled = true\nheartbeat_ms = 50\nwatchdog_ms = 1000\nreset = "token"\nreset_token = "{TOKEN}"',
    )
    log_path = tmp_path / "status.jsonl"
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--tcp", f"127.0.0.1:{daq_port}", "--realtime", "--loop",
                            "--status-log", str(log_path), "--watchdog-ms", "1000"])
        wait_for(lambda: "serving" in procs.text("sim"), 60.0, "emulator serving")
        daemon = _start_daemon(procs, cfg)
        dash = procs.start("dash", ["dashboard", "--listen", f"127.0.0.1:{http_port}", "--connect", tcp(z_port),
                                    "--no-scouting"])
        wait_for(lambda: "serving on" in procs.text("dash") or dash.poll() is not None, 60.0, "dashboard serving")
        assert dash.poll() is None, procs.text("dash")
        sub = Subscriber([tcp(z_port)], MACHINE, read=False)
        try:
            browser.get(f"http://127.0.0.1:{http_port}/")

            # Live values: the torque shown changes as revolutions arrive.
            first = wait_for(lambda: (_tile_text(browser, ".f-torque") or "").endswith("N·m")
                             and _tile_text(browser, ".f-torque"), SLOW_S, "a torque in the tile")
            wait_for(lambda: _tile_text(browser, ".f-torque") not in (first, None), SLOW_S, "the torque to change")
            assert daemon.poll() is None, procs.text("daemon")

            # The alarm: in the tile and in the recent alarms.
            wait_for(lambda: "warning" in (_tile_class(browser) or ""), SLOW_S, "the tile marked with the warning")
            alarms = browser.js("return document.getElementById('alarms').textContent")
            assert MACHINE in alarms and "warning" in alarms and "torque_nm" in alarms, alarms
            if os.environ.get("MILLSENSE_SCREENSHOT"):
                browser.js("return new Promise(r => setTimeout(r, 600))")  # let the plots draw
                browser.screenshot(Path(os.environ["MILLSENSE_SCREENSHOT"]))

            # A real hold on the DAQ's output, by a proof test.
            send_command(sub.session, MACHINE, "test-trip", TOKEN, timeout_s=20.0)
            wait_for(lambda: _holds(log_path), SLOW_S, "feed hold on the emulator")
            wait_for(lambda: _tile_text(browser, ".f-interlock") not in ("armed", "–", None), SLOW_S,
                     "the hold in the tile")

            form = f"article[data-machine='{MACHINE}'] form.reset"
            result = f"{form} .reset-result"
            # A wrong token: the page says so, the feed stays held, the field is emptied.
            browser.type(browser.find(f"{form} .reset-token"), "not-the-token-but-long-enough-0123456789ab")
            browser.click(browser.find(f"{form} .reset-go"))
            wait_for(lambda: "bad" in browser.js(f"return document.querySelector(\"{result}\").className"),
                     SLOW_S, "the wrong token refused on the page")
            assert browser.js(f"return document.querySelector(\"{form} .reset-token\").value") == ""
            assert not _holds(log_path, on=False), "a wrong token released the feed"

            # The right token: the daemon's MAC checks out in the page and the DAQ releases the feed.
            browser.type(browser.find(f"{form} .reset-token"), TOKEN)
            browser.click(browser.find(f"{form} .reset-go"))
            wait_for(lambda: "ok" in browser.js(f"return document.querySelector(\"{result}\").className")
                     and "verified" in browser.js(f"return document.querySelector(\"{result}\").textContent"),
                     SLOW_S, "the reset granted on the page")
            wait_for(lambda: _holds(log_path, on=False), SLOW_S, "feed released on the emulator")
            assert browser.js(f"return document.querySelector(\"{form} .reset-token\").value") == ""
            stored = browser.js("return JSON.stringify(localStorage) + JSON.stringify(sessionStorage)"
                                " + document.cookie")
            assert TOKEN not in stored

            # A restarted daemon: its tile goes grey, then comes back by itself with live values.
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(60)
            wait_for(lambda: "gone" in (_tile_class(browser) or ""), SLOW_S, "the tile marked gone")
            _start_daemon(procs, cfg, "daemon2")
            wait_for(lambda: "gone" not in (_tile_class(browser) or "gone"), SLOW_S, "the tile alive again")
            before = _tile_text(browser, ".f-torque")
            wait_for(lambda: _tile_text(browser, ".f-torque") != before, SLOW_S, "live values after the restart")
        finally:
            sub.close()
            dash.send_signal(signal.SIGTERM)
            assert dash.wait(30) == 0, procs.text("dash")
