"""Planted bugs, one at a time: which tests kill each (issue 37).

Each mutant is one plausible bug a developer could write (a flipped comparison, an
off-by-one, a forgotten call, a wrong default): a search string in one file, which
must match exactly once, and its replacement. For each, the script runs

    pytest -x -q -p no:cacheprovider -n 0 <the mutant's target tests>

with the mutant applied and records `killed` (a test failed; the first failing
test's node id), `survived` (every target test passed: a gap in the suite),
`error` (pytest could not collect or run: the mutant broke an import, which
is not a test catching it), `timeout`, or `refused` (the search string does
not match exactly once in today's code: the table must be brought up to date).
A kill is confirmed by running the killing test alone on the unmutated copy: if
it fails there too, the result is `inconclusive` (the test fails without the bug:
load, or a broken test), never `killed`.

Why a copy and not a patch in place: the mutant is applied in a temporary copy
of the repository (its tracked and untracked, not ignored, files as they are in
the working tree now), imported through a private virtual environment of that
copy. The working tree is never written, so no Ctrl-C, crash or `kill -9` of
this script can leave a bug planted in it; a patch in place with a restore in
`finally` cannot promise that for SIGKILL or a power cut. The private
environment (`python -m venv --without-pip`, a `.pth` that puts a shim whose
`millsense/daemon`, `millsense/drivers` and `millsense/sim` (pyproject's
`package-dir`) point into the copy first, and the running interpreter's
site-packages after it for the dependencies) needs no
PYTHONPATH, which tests may replace for their subprocesses
(tests/faults/test_clock.py does): every `sys.executable` the tests start
imports the copy. The script checks that before the first mutant.

Target sets: the mutant's own package's tests, the live tests of its area and
the tests/e2e files (or single e2e tests) that drive its path, the quickest and
most specific first so that `-x` stops early on a kill. They are chosen so that
the whole table runs in about an hour on the 2-core CI box (docs/testing.md
gives the measured times); not part of `.ci/run`.

Run (from the repository, with its `.venv`):
    .venv/bin/python bench/mutants.py --list
    .venv/bin/python bench/mutants.py [--only ID ...] [--timeout-per-mutant S] [--out FILE] [--no-confirm]

tests/test_mutants_table.py checks, in the normal suite, that every search
string still matches exactly once, so the table cannot rot silently.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SANDBOX_PREFIX = "millsense-mutants-"
DEFAULT_TIMEOUT_S = 900.0
# One process (`-n 0` overrides pyproject's xdist workers): the targets run in the table's order and `-x` stops at
# the first failure with exit code 1. In workers `-x` ends the session "Interrupted", exit code 2: read as `error`.
PYTEST_ARGS = ("-x", "-q", "-p", "no:cacheprovider", "-n", "0")


@dataclasses.dataclass(frozen=True)
class Mutant:
    id: str
    package: str
    description: str
    file: str
    search: str
    replace: str
    targets: tuple[str, ...]
    trust: bool = False   # one of the five planted bugs of the trust issue (issue 36, finding 9)


# Target sets shared by several mutants (paths from the repository root; a node id selects one test).
RUNTIME = "tests/runtime"   # the interlock's, the runner's and the frame check's own package tests
STANDSTILL = "tests/faults/test_reset_at_standstill.py"
E2E_INTERLOCK = "tests/e2e/test_interlock.py"
E2E_FAILURES = "tests/e2e/test_failures.py"
E2E_CRASH = "tests/e2e/test_crash_trips.py"
E2E_FLUTE_WHILE_FEED_MOVES = ("tests/e2e/test_afc_closed_loop.py::"
                              "test_a_flute_that_breaks_while_the_feed_moves_is_still_caught")
AUTH = ("tests/publish/test_command_auth.py", "tests/publish/test_command_authority.py")
E2E_AUTH = "tests/e2e/test_command_authority_live.py"
EXPECTED = "tests/learning/test_expected.py"   # the expected band of issue 41
FRAME = ("tests/runtime/test_frame_check.py", "tests/runtime/test_safety_check.py", "tests/runtime/test_reader_path.py")
DRIVER_CODEC = ("tests/drivers/test_crc.py", "tests/drivers/test_protocol.py", "tests/drivers/test_protocol2.py")

MUTANTS: tuple[Mutant, ...] = (
    # -- interlock ---------------------------------------------------------------------------------------------
    Mutant("il-reset-crash-current", "interlock",
           "reset check: `>` for `>=` at crash_current_a (a current exactly at the limit lets the reset through)",
           "daemon/runtime/interlock.py",
           "i_a is not None and i_a >= self.crash_current_a:",
           "i_a is not None and i_a > self.crash_current_a:",
           ("tests/runtime/test_interlock.py", "tests/runtime/test_runner.py", RUNTIME, STANDSTILL, E2E_INTERLOCK),
           trust=True),
    Mutant("il-reset-judged-on-hold-sample", "interlock",
           "reset check: data from the last sample before the hold counts as newer (`>=` for `>`)",
           "daemon/runtime/interlock.py",
           "return self.hold_seq is None or (seq is not None and seq > self.hold_seq)",
           "return self.hold_seq is None or (seq is not None and seq >= self.hold_seq)",
           ("tests/runtime/test_interlock.py", STANDSTILL, RUNTIME, E2E_INTERLOCK, E2E_CRASH)),
    Mutant("il-reset-not-atomic", "interlock",
           "a reset judged and applied in two steps: a trip that latches between them is released unjudged",
           "daemon/runtime/controls.py",
           "        with self._trip_lock:\n            with self._check_lock:\n                held = il.latched",
           "        if True:\n            with self._check_lock:\n                held = il.latched",
           ("tests/runtime/test_runner.py", RUNTIME, E2E_INTERLOCK)),
    Mutant("il-test-trip-masks-real-trip", "interlock",
           "a real trip during a proof test leaves the latch's reason `test-trip` (reset then judges no condition)",
           "daemon/runtime/interlock.py",
           "                if self.reason == TEST_TRIP and reason != TEST_TRIP:\n"
           "                    # a real condition during a proof test: the latch now stands for it\n"
           "                    self.reason = reason\n"
           "                    self._changed()\n",
           "",
           ("tests/runtime/test_interlock.py", "tests/runtime/test_runner.py", RUNTIME, "tests/e2e/test_test_trip.py")),
    Mutant("il-latch-damaged-unlatched", "interlock",
           "latch store: a damaged latch file is read as `nothing latched` instead of held",
           "daemon/runtime/latch_store.py",
           'return {"latched": True, "reason": f"latch file damaged ({exc}): {self.path}", "since": None, "trips": 0}',
           "return None",
           ("tests/runtime/test_latch.py", "tests/faults/test_state_dir.py", RUNTIME, E2E_INTERLOCK)),
    Mutant("il-watchdog-not-rearmed", "interlock",
           "watchdog: after the link comes back the DAQ's watchdog is not armed again (a restarted DAQ forgot it)",
           "daemon/runtime/runner.py",
           "            safe(self.interlock.start)\n",
           "",
           ("tests/faults/test_watchdog_rearm.py", "tests/runtime/test_interlock.py", "tests/runtime/test_runner.py",
            "tests/faults/test_watchdog_hold.py", RUNTIME, E2E_FAILURES, "tests/faults/test_link.py")),
    Mutant("il-watchdog-never-armed", "interlock",
           "watchdog: the interlock's start no longer sets the DAQ's watchdog (a hung daemon leaves the feed running)",
           "daemon/runtime/interlock.py",
           "        if self.watchdog_ms > 0:\n            self._out.set_watchdog_ms(self.watchdog_ms)\n",
           "",
           ("tests/runtime/test_interlock.py", "tests/runtime/test_runner.py", "tests/faults/test_watchdog_hold.py",
            RUNTIME, E2E_FAILURES, "tests/faults/test_link.py")),
    Mutant("il-frame-check-not-rearmed", "interlock",
           "a reset does not re-arm the reader thread's frame check: the next crash is not caught there",
           "daemon/runtime/frame_guard.py",
           "            if self.frame_check is not None:\n                self.frame_check.rearm()\n",
           "            pass\n",
           (STANDSTILL, "tests/runtime/test_frame_check.py", "tests/runtime/test_interlock.py",
            "tests/runtime/test_runner.py", RUNTIME, E2E_CRASH, E2E_INTERLOCK)),
    # -- signal checks -----------------------------------------------------------------------------------------
    Mutant("sc-frame-check-clip-gate", "signal checks",
           "frame check: a frame is looked at only when a current passes crash_current_a (a clipped sensor, "
           "reading below it, is never checked)",
           "daemon/pipeline/safety_check.py",
           "not (bound_w > self._p_limit or bound_a >= self._i_gate)",
           "not (bound_w > self._p_limit or bound_a > self._i_limit)",
           (*FRAME, RUNTIME, E2E_CRASH)),
    Mutant("sc-frame-check-clip-edge", "signal checks",
           "frame check: a count at exactly the sensor's limit is not taken as clipped (`<`/`>` for `<=`/`>=`)",
           "daemon/pipeline/safety_check.py",
           "bool(((counts <= self._lo) | (counts >= self._hi)).any())",
           "bool(((counts < self._lo) | (counts > self._hi)).any())",
           (*FRAME, RUNTIME, E2E_CRASH)),
    Mutant("sc-stuck-sensor-weak-forgotten", "signal checks",
           "signal check: only a flat channel is named; one that swings a tenth of its phases' (unplugged, noisy) "
           "passes",
           "daemon/pipeline/signal_check.py",
           "if (dead or weak) and name not in out",
           "if dead and name not in out",
           ("tests/estimator/test_signal_check.py", "tests/estimator/test_program_signals.py",
            "tests/faults/test_signals.py", "tests/faults/test_sensors.py")),
    Mutant("sc-loss-threshold", "signal checks",
           "loss check: blind only past half the stream lost (a wrong default for RAISE_SHARE)",
           "daemon/pipeline/loss_check.py",
           "RAISE_SHARE = 0.20",
           "RAISE_SHARE = 0.50",
           ("tests/faults/test_data_loss.py", "tests/faults/test_blind.py")),
    Mutant("sc-phase-kirchhoff-factor", "signal checks",
           "phase check: the line currents' sum compared with a whole phase, not a quarter of it (factor forgotten)",
           "daemon/pipeline/phase_check.py",
           "if sum_ptp > KIRCHHOFF_SHARE * phase_ptp:",
           "if sum_ptp > phase_ptp:",
           ("tests/faults/test_current_scale.py", "tests/faults/test_phase_order.py", "tests/faults/test_sensors.py",
            "tests/faults/test_signals.py")),
    Mutant("sc-rate-one-sided", "signal checks",
           "rate check: only a stream slower than stated is caught (`abs` forgotten on the drift)",
           "daemon/pipeline/rate_check.py",
           "wrong = abs(drift) > RAISE_SHARE",
           "wrong = drift > RAISE_SHARE",
           ("tests/faults/test_sample_rate.py",)),
    Mutant("sc-rate-check-off-ignored", "signal checks",
           "rate check: `[daq] check_sample_rate = false` read and ignored (a bench's stream at speed is judged blind)",
           "daemon/runtime/runner.py",
           'self._check_rate = bool(getattr(getattr(settings, "daq", None), "check_sample_rate", True))',
           "self._check_rate = True",
           ("tests/faults/test_sample_rate.py",)),
    Mutant("sc-rate-check-off-by-default", "signal checks",
           "config: `[daq] check_sample_rate` defaults to false (a test bench's setting for parts at speed leaks "
           "into every machine: a stream at the wrong rate, or played faster, passes)",
           "daemon/config/models.py",
           "check_sample_rate: bool = True",
           "check_sample_rate: bool = False",
           ("tests/faults/test_sample_rate.py",)),
    # -- command authorisation ---------------------------------------------------------------------------------
    Mutant("ca-mac-compare-eq", "command authorisation",
           "proof check: `==` for `hmac.compare_digest` (a timing side channel on the MAC)",
           "daemon/publish/command_auth.py",
           "MAC_RE.match(given) and hmac.compare_digest(given, expected)",
           "MAC_RE.match(given) and given == expected",
           (*AUTH, E2E_AUTH), trust=True),
    Mutant("ca-nonce-reusable", "command authorisation",
           "nonce store: a server nonce is looked up, not spent (a captured proof replays)",
           "daemon/publish/command_auth.py",
           "expires = self._live.pop(nonce, None)",
           "expires = self._live.get(nonce)",
           (*AUTH, E2E_AUTH)),
    Mutant("ca-open-allows-afc-off", "command authorisation",
           "reset = \"open\": `afc off` added to the allow-list (it may raise a reduced override back to 100 %)",
           "daemon/publish/command_auth.py",
           '"afc": ("status",),',
           '"afc": ("status", "off"),',
           (*AUTH, "tests/publish/test_afc_command.py", E2E_AUTH)),
    Mutant("ca-limiter-off-by-one", "command authorisation",
           "failure limiter: pauses after max_failures + 1 failed proofs (`>` for `>=`)",
           "daemon/publish/command_auth.py",
           "if len(self._failures) >= self.max_failures:",
           "if len(self._failures) > self.max_failures:",
           (*AUTH, E2E_AUTH)),
    # -- learning ----------------------------------------------------------------------------------------------
    Mutant("le-overload-teaches", "learning",
           "\"overload\" missing from the levels that keep a process from teaching its envelope",
           "daemon/learning/monitor.py",
           '_FIXED_LEVELS = frozenset({"warning", "overload", "crash", "tool_breakage", "daq_lost"})',
           '_FIXED_LEVELS = frozenset({"warning", "crash", "tool_breakage", "daq_lost"})',
           ("tests/learning", "tests/e2e/test_learning_acceptance.py"), trust=True),
    Mutant("le-band-union-off-by-one", "learning",
           "envelope band: the high side at k is the union over k-1..k, not k-1..k+1 (slice end off by one)",
           "daemon/learning/envelope.py",
           "high[k] = float(np.nanmax(up[max(k - 1, 0): k + 2]))",
           "high[k] = float(np.nanmax(up[max(k - 1, 0): k + 1]))",
           ("tests/learning", "tests/e2e/test_learning_acceptance.py")),
    Mutant("le-widen-cap-per-command", "learning",
           "widen cap: each widen checked alone, not with the widening since the last relearn",
           "daemon/learning/envelope.py",
           "or now * factor > MAX_WIDENING * (1.0 + 1e-9):",
           "or factor > MAX_WIDENING * (1.0 + 1e-9):",
           ("tests/learning", "tests/e2e/test_limits_cli.py")),
    Mutant("le-set-aside-negative-width", "learning",
           "restore: a stored band with a negative half-width is restored, not set aside (only the finite check kept)",
           "daemon/learning/envelope.py",
           "if not np.all(np.isfinite(values[known]) & (values[known] >= 0.0)):",
           "if not np.all(np.isfinite(values[known])):",
           ("tests/learning", "tests/history/test_stored_limits.py", "tests/e2e/test_learning_live.py")),
    Mutant("le-context-seq-replay", "learning",
           "context authority: a signed context with the same sequence number as the last is taken again (replay)",
           "daemon/learning/context_auth.py",
           "if seq <= self.last_seq:",
           "if seq < self.last_seq:",
           ("tests/learning/test_context_auth.py", "tests/runtime/test_context_authority.py",
            "tests/pipeline/test_feed_control_authority.py", "tests/e2e/test_context_authority.py")),
    Mutant("ex-high-not-held", "learning",
           "expected_high (a cut deeper than its operation declares) warns but does not hold the feed",
           "daemon/learning/expected.py",
           "                       value > high, True)",
           "                       value > high, False)",
           (EXPECTED, "tests/e2e/test_expected_live.py"), trust=False),
    Mutant("ex-varying-low-holds", "learning",
           "expected_low holds the feed in a varying-engagement operation (a pocket's corners stop the machine)",
           "daemon/learning/expected.py",
           "value < low and low_on and self._low_counts(run, quantity, value, expected, low),\n"
           "                       op.engagement == \"constant\")",
           "value < low and low_on and self._low_counts(run, quantity, value, expected, low),\n"
           "                       True)",
           (EXPECTED, "tests/e2e/test_expected_live.py")),
    Mutant("ex-unknown-override-armed", "learning",
           "an unknown feed override is taken as 100 %: the expected band is armed on a guess",
           "daemon/physics/expected.py",
           "    if override_pct is None or not math.isfinite(override_pct) or override_pct <= 0.0:\n        return None",
           "    override_pct = 100.0 if override_pct is None else override_pct\n"
           "    if not math.isfinite(override_pct) or override_pct <= 0.0:\n        return None",
           ("tests/physics/test_expected.py", EXPECTED, "tests/e2e/test_expected_live.py")),
    Mutant("ex-light-cut-unseen", "learning",
           "the expected band takes a revolution in cut only over `[depth] min_torque_nm`: a light operation's "
           "half-depth first part is never judged",
           "daemon/learning/expected.py",
           "        return rise >= IN_CUT_OF_EXPECTED * exp.torque_nm and rise > ENTRY_NOISE_SIGMAS * (sigma or 0.0)",
           "        return False",
           ("tests/learning/test_expected_entry.py", EXPECTED)),
    Mutant("ex-air-settling-is-a-cut", "learning",
           "a light cut's air level taken below 0: the air settling after a spindle run-up is judged as a cut "
           "missing its stock (a correct part held)",
           "daemon/learning/expected.py",
           "        rise = torque - max(min(run.air_torques), 0.0)",
           "        rise = torque - min(run.air_torques)",
           ("tests/learning/test_expected_entry.py", EXPECTED)),
    # -- AFC ---------------------------------------------------------------------------------------------------
    Mutant("afc-trip-not-safe", "AFC",
           "a trip no longer puts the override to <= 100 % at once (the next revolution would)",
           "daemon/runtime/runner.py",
           '        self.afc.safe(f"feed hold: {reason}")  # after the hold is written: it never waits for this\n',
           "",
           ("tests/runtime/test_afc_runner.py", "tests/pipeline", E2E_FLUTE_WHILE_FEED_MOVES), trust=True),
    Mutant("afc-fault-not-safe", "AFC",
           "a fault no longer puts the override to <= 100 % (the call on the fault path forgotten)",
           "daemon/runtime/faults.py",
           '        safe(self._afc_safe, f"fault: {kind}: {reason}")  # first: the feed never runs above',
           '        pass  # first: the feed never runs above',
           ("tests/runtime/test_afc_runner.py", "tests/pipeline", E2E_FLUTE_WHILE_FEED_MOVES)),
    Mutant("afc-clamp-upper-forgotten", "AFC",
           "controller: the PI's output is clamped below only (max_override_pct forgotten)",
           "daemon/afc/controller.py",
           "clamped = min(max(wanted, s.min_override_pct), s.max_override_pct)",
           "clamped = max(wanted, s.min_override_pct)",
           ("tests/pipeline", "tests/runtime/test_afc_runner.py", E2E_FLUTE_WHILE_FEED_MOVES)),
    Mutant("afc-not-followed-timer-restarts", "AFC",
           "not-followed detection: the `above since` time restarts at every STATUS, so it never trips",
           "daemon/afc/supervisor.py",
           "        if self._override_above_since is None:\n            self._override_above_since = now\n",
           "        self._override_above_since = now\n",
           ("tests/runtime/test_afc_runner.py", "tests/pipeline")),
    Mutant("afc-safe-keeps-recent-raise", "AFC",
           "safe: min(commanded, 100 %) only; what a failing sensor made the controller raise just before stays",
           "daemon/afc/controller.py",
           "new = min(self._commanded, NEUTRAL_PCT, self._lowest_recent())",
           "new = min(self._commanded, NEUTRAL_PCT)",
           ("tests/pipeline", "tests/runtime/test_afc_runner.py")),
    # -- history -----------------------------------------------------------------------------------------------
    Mutant("hi-retention-hours", "history",
           "retention_days taken as hours (3600 for 86400): a day's history goes within the day",
           "daemon/history/store.py",
           "self.retention_s = float(retention_days) * 86400.0",
           "self.retention_s = float(retention_days) * 3600.0",
           ("tests/history", "tests/e2e/test_history_daemon.py")),
    Mutant("hi-export-from-exclusive", "history",
           "export: --from excludes its own instant (`>` for `>=`)",
           "daemon/history/export.py",
           '(("t", ">=", t_from), ("t", "<", t_to)',
           '(("t", ">", t_from), ("t", "<", t_to)',
           ("tests/history", "tests/e2e/test_history_daemon.py")),
    # -- dashboard ---------------------------------------------------------------------------------------------
    Mutant("db-post-host-unchecked", "dashboard",
           "do_POST skips the Host check (DNS rebinding reaches the reset relay)",
           "daemon/dashboard/server.py",
           "    def do_POST(self) -> None:  # noqa: N802\n        if self._host_refused():\n            return\n",
           "    def do_POST(self) -> None:  # noqa: N802\n",
           ("tests/dashboard/test_server.py", "tests/dashboard/test_connections.py", "tests/dashboard"), trust=True),
    Mutant("db-refusal-body-not-drained", "dashboard",
           "a refused request's body is not drained: the connection's next request starts inside it",
           "daemon/dashboard/server.py",
           "        if not self.body_done:\n            self._drain_body()\n        self.send_response(status)",
           "        self.send_response(status)",
           ("tests/dashboard/test_connections.py", "tests/dashboard/test_server.py", "tests/dashboard")),
    # -- physics -----------------------------------------------------------------------------------------------
    Mutant("ph-force-radius-as-diameter", "physics",
           "eq. 16: F_T = T_c/R with the tool's diameter taken for R (a factor 2)",
           "daemon/physics/force.py",
           "return values(torque_nm) / (values(tool_radius_mm) * 1e-3)",
           "return values(torque_nm) / (values(tool_radius_mm) * 2e-3)",
           ("tests/physics", "tests/estimator/test_force_truth.py")),
    Mutant("ph-feed-per-tooth-bound-max", "physics",
           "validity: the largest feed per tooth is max(...) of its two bounds, not min(...)",
           "daemon/physics/validity.py",
           "return min(FEED_PER_TOOTH_MAX_MM, FEED_PER_TOOTH_MAX_PER_RADIUS * radius_mm)",
           "return max(FEED_PER_TOOTH_MAX_MM, FEED_PER_TOOTH_MAX_PER_RADIUS * radius_mm)",
           ("tests/physics", "tests/estimator/test_preconditions.py", "tests/e2e/test_part_program_depths.py")),
    Mutant("ph-edge-split-ignored", "physics",
           "the material's edge coefficients ignored: C_f takes the whole law as chip (thin-chip 3-flute slots 2 % high)",
           "daemon/physics/force.py",
           "    if has_edge(material):   # the material's edge forces taken out of its law (edge.py, E3)\n",
           "    if False:\n",
           ("tests/physics/test_edge.py", "tests/estimator/test_force_first_part.py")),
    # -- drivers -----------------------------------------------------------------------------------------------
    Mutant("dr-fast-path-crc-unchecked", "drivers",
           "decoder: the one-frame shortcut trusts a frame shaped like the last without checking its CRC",
           "drivers/decoder.py",
           "        if crc16_modbus(data[2 : flen - 2]) != data[flen - 2] | (data[flen - 1] << 8):\n"
           "            return None\n",
           "",
           (*DRIVER_CODEC, "tests/faults/test_corpus.py")),
    Mutant("dr-gap-not-counted", "drivers",
           "index tracker: a forward jump moves seq but its samples are not counted lost",
           "drivers/base.py",
           "seq, lost = self.next_seq + gap, gap",
           "seq, lost = self.next_seq + gap, 0",
           ("tests/drivers/test_protocol.py", "tests/drivers/test_faults.py", "tests/runtime/test_reader_path.py",
            "tests/faults/test_data_loss.py")),
    Mutant("dr-resync-drops-half-sync", "drivers",
           "decoder: the 0xA5 at the end of a read (half a sync) is dropped: a frame split there is lost",
           "drivers/decoder.py",
           "keep = 1 if n > p and buf[n - 1] == 0xA5 else 0",
           "keep = 0",
           (*DRIVER_CODEC, "tests/faults/test_corpus.py")),
    # -- OPC UA ------------------------------------------------------------------------------------------------
    Mutant("op-feedheld-severity-floor", "OPC UA",
           "FeedHeld: the severity is the cause's level alone, not at least a held feed's 900",
           "daemon/opcua/feed_held.py",
           "return max(MIN_SEVERITY, levels.get(cause_level(reason), 0))",
           "return levels.get(cause_level(reason), MIN_SEVERITY)",
           ("tests/opcua/test_feed_held.py", "tests/opcua/test_opcua_unit.py", "tests/opcua")),
    Mutant("op-feedheld-stale-status-clears", "OPC UA",
           "FeedHeld: a status built before the trip clears the condition the alarm just raised",
           "daemon/opcua/feed_held.py",
           "t < self._from_alarm_t + NOT_BEFORE_S:",
           "t < self._from_alarm_t:",
           ("tests/opcua/test_feed_held.py", "tests/opcua/test_opcua_unit.py", "tests/opcua")),
    Mutant("hi-failed-write-not-spooled", "history",
           "historian: a batch PostgreSQL did not take is dropped, not spooled (a restart of the server loses it)",
           "daemon/historian/writer.py",
           "            if by_table and not self._write_tables(by_table):\n                self._to_spool(_pairs(by_table))",
           "            if by_table and not self._write_tables(by_table):\n                pass",
           ("tests/historian/test_live.py", "tests/historian/test_schema.py")),
    Mutant("hi-replay-duplicates", "history",
           "historian: the staged rows inserted without ON CONFLICT (a replayed batch written twice)",
           "daemon/historian/writer.py",
           " ON CONFLICT DO NOTHING\")",
           "\")",
           ("tests/historian/test_schema.py", "tests/historian/test_live.py")),
    Mutant("hi-newer-schema-taken", "history",
           "historian: a database of a newer schema version written into as if it were its own",
           "daemon/historian/schema.py",
           "if stored > version:",
           "if False:",
           ("tests/historian/test_schema.py",)),
    Mutant("op-ack-anyone", "OPC UA",
           "Acknowledge/Confirm: any trusted client may, not only an operator's certificate",
           "daemon/opcua/acknowledge.py",
           'if not getattr(user, "operator", False):',
           "if False:",
           ("tests/opcua/test_acknowledge.py", "tests/opcua")),
    Mutant("hi-limit-change-untold", "history",
           "limits/change: an operator's applied widen never published (the plant's history without who changed it)",
           "daemon/runtime/controls.py",
           "        if key in changed:\n            self._publish_limits_change(",
           "        if False:\n            self._publish_limits_change(",
           ("tests/historian/test_limit_changes_live.py",)),
    Mutant("zq-status-cache-ignores-state", "command authorisation",
           "status query: a kept answer served for its 0.2 s whatever changed (a cached `armed` after a trip)",
           "daemon/publish/queryables.py",
           "if hit is not None and now < hit[0] and hit[2] == current:",
           "if hit is not None and now < hit[0]:",
           ("tests/publish/test_queryables.py", "tests/faults/test_data_loss.py")),
    Mutant("sc-phase-numbers-valid", "signal checks",
           "wiring check: the revolutions of a miswired stream published valid while the fault holds",
           "daemon/runtime/runner.py",
           '"phase" if phase is not None and phase.faulted else',
           "None if phase is not None and phase.faulted else",
           ("tests/faults/test_phase_invalid.py", "tests/faults/test_phase_order.py")),
    Mutant("sc-wiring-numbers-valid", "signal checks",
           "power check: the revolutions of current sensors turned round published valid while the fault holds",
           "daemon/runtime/runner.py",
           '"wiring" if self.power_check.faulted else None)',
           "None)",
           ("tests/faults/test_phase_invalid.py", "tests/runtime/test_power_check.py")),
    Mutant("sc-overrun-gap-is-outage", "signal checks",
           "loss check: every half-second gap taken for an outage of the link (a reader a ring behind unseen)",
           "daemon/pipeline/loss_check.py",
           "if discontinuity or (after_link_up and lost >= self.link_gap):",
           "if discontinuity or lost >= self.link_gap:",
           ("tests/faults/test_data_loss.py", "tests/faults/test_modbus_overrun.py")),
)


# ---------------------------------------------------------------------------------------------------------- table
def by_id() -> dict[str, Mutant]:
    return {m.id: m for m in MUTANTS}


def table_problems(root: Path, mutants: tuple[Mutant, ...] = MUTANTS) -> dict[str, str]:
    """Mutant id -> why it cannot be planted in the tree at `root` (its search string does not match exactly
    once, its file or a target is missing, the replacement is the search string). Empty: the table holds."""
    problems: dict[str, str] = {}
    seen: set[str] = set()
    for m in mutants:
        if m.id in seen:
            problems[m.id] = "duplicate id"
            continue
        seen.add(m.id)
        path = root / m.file
        if not path.is_file():
            problems[m.id] = f"{m.file}: no such file"
            continue
        n = path.read_text(encoding="utf-8").count(m.search)
        if n != 1:
            problems[m.id] = f"{m.file}: the search string matches {n} times, not once"
            continue
        if m.search == m.replace:
            problems[m.id] = "the replacement is the search string"
            continue
        missing = [t for t in m.targets if not _target_exists(root, t)]
        if missing or not m.targets:
            problems[m.id] = f"target tests missing: {', '.join(missing) or '(none given)'}"
    return problems


def _target_exists(root: Path, target: str) -> bool:
    path, _, test = target.partition("::")
    if not (root / path).exists():
        return False
    return not test or f"def {test.split('[', 1)[0]}(" in (root / path).read_text(encoding="utf-8")


# ---------------------------------------------------------------------------------------------------------- sandbox
class Sandbox:
    """A temporary copy of the repository with its own environment. Removed on exit (the working tree is
    never written)."""

    def __init__(self, repo: Path):
        self.repo = repo
        self.dir = Path(tempfile.mkdtemp(prefix=SANDBOX_PREFIX))
        (self.dir / "pid").write_text(str(os.getpid()))
        self.src = self.dir / "src"
        self.venv = self.dir / "venv"
        self.python = self.venv / "bin" / "python"
        self.env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
        self.env["PYTHONUNBUFFERED"] = "1"

    def build(self) -> None:
        self._copy()
        self._environment()
        self._check_imports()

    def _copy(self) -> None:
        out = subprocess.run(["git", "-C", str(self.repo), "ls-files", "-z", "--cached", "--others",
                              "--exclude-standard"], check=True, capture_output=True).stdout
        for rel in sorted(set(out.decode("utf-8").split("\0")) - {""}):
            src = self.repo / rel
            if not src.exists() and not src.is_symlink():
                continue   # deleted in the working tree, not yet committed
            dst = self.src / rel
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst, follow_symlinks=False)

    def _environment(self) -> None:
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(self.venv)], check=True)
        shim = self.dir / "shim" / "millsense"
        shim.mkdir(parents=True)
        for name, folder in self.packages().items():   # millsense.daemon -> daemon/, millsense.sim -> sim/, ...
            (shim / name.removeprefix("millsense.")).symlink_to(self.src / folder, target_is_directory=True)
        site = Path(subprocess.run([str(self.python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                   check=True, capture_output=True, text=True).stdout.strip())
        deps = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
        # the copy first, then this interpreter's packages (numpy, zenoh, pytest ...); none of their .pth run,
        # so the repository's own editable install (a .pth there) never puts the working tree on the path
        (site / "_millsense_mutants.pth").write_text("\n".join([str(self.dir / "shim"), *deps]) + "\n")
        bindir = self.venv / "bin"
        (bindir / "millsense").write_text(f"#!{self.python}\nimport sys\nfrom millsense.daemon.cli import main\n"
                                          "sys.exit(main())\n")
        (bindir / "millsense").chmod(0o755)
        self.env["PATH"] = f"{bindir}{os.pathsep}{self.env.get('PATH', '')}"
        self.env["VIRTUAL_ENV"] = str(self.venv)

    def packages(self) -> dict[str, str]:
        """pyproject's top-level packages and their folders (`package-dir`): every one must come from the copy
        (the simulator moved to millsense.sim, sim/: a shim without it imported the working tree's)."""
        import tomllib

        dirs = tomllib.loads((self.src / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
        return {name: folder for name, folder in dirs.items() if name.count(".") == 1}

    def _check_imports(self) -> None:
        names = sorted(self.packages())
        code = f"import {', '.join(names)}, pytest; " + "; ".join(f"print({n}.__file__)" for n in names)
        out = subprocess.run([str(self.python), "-c", code], cwd=self.src, env=self.env, check=True,
                             capture_output=True, text=True).stdout.split()
        for f in out:
            if not Path(f).resolve().is_relative_to(self.src.resolve()):
                raise RuntimeError(f"the sandbox imports {f}, not its copy in {self.src}: refusing to run")

    def remove(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


def remove_stale_sandboxes() -> None:
    """Sandboxes left by a run that was killed (its pid gone)."""
    for d in Path(tempfile.gettempdir()).glob(SANDBOX_PREFIX + "*"):
        try:
            pid = int((d / "pid").read_text())
            os.kill(pid, 0)
        except ProcessLookupError:
            shutil.rmtree(d, ignore_errors=True)
        except (OSError, ValueError):
            continue


class Planted:
    """The mutant applied in the sandbox's copy for the `with` block, the original written back after."""

    def __init__(self, root: Path, m: Mutant):
        self.path = root / m.file
        self.m = m
        self.original = self.path.read_text(encoding="utf-8")

    def __enter__(self) -> "Planted":
        if self.original.count(self.m.search) != 1:
            raise ValueError(f"{self.m.id}: the search string does not match exactly once")
        self._write(self.original.replace(self.m.search, self.m.replace, 1))
        return self

    def __exit__(self, *exc: object) -> None:
        self._write(self.original)

    def _write(self, text: str) -> None:
        self.path.write_text(text, encoding="utf-8")
        # a byte-code cache of the other version could be taken for this one (same size, same second)
        for pyc in (self.path.parent / "__pycache__").glob(f"{self.path.stem}.*.pyc"):
            pyc.unlink(missing_ok=True)


# ---------------------------------------------------------------------------------------------------------- running
# the short summary's "FAILED <node id> - <message>"; a parametrised id may hold spaces inside its brackets
_FIRST_FAILURE = re.compile(r"^(?:FAILED|ERROR) ([^\s\[]+(?:\[[^\n]*?\])?)(?= - |$)", re.M)


def run_pytest(sb: Sandbox, targets: list[str], timeout_s: float) -> tuple[int | None, str, float]:
    """(pytest's exit code or None on timeout, its output, wall seconds). The whole process group goes on
    timeout or interrupt (the daemons and emulators the tests started too)."""
    shutil.rmtree(sb.src / ".hypothesis", ignore_errors=True)   # no example found for one mutant replays for the next
    t0 = time.monotonic()
    proc = subprocess.Popen([str(sb.python), "-m", "pytest", *PYTEST_ARGS, *targets], cwd=sb.src, env=sb.env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=timeout_s)
        return proc.returncode, out, time.monotonic() - t0
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        out, _ = proc.communicate()
        return None, out, time.monotonic() - t0
    except BaseException:
        _kill_group(proc)
        raise


def _kill_group(proc: subprocess.Popen) -> None:
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def classify(rc: int | None, out: str) -> tuple[str, str | None]:
    if rc is None:
        return "timeout", None
    if rc == 0:
        return "survived", None
    first = _FIRST_FAILURE.search(out)
    if rc == 1 and first:
        return "killed", first.group(1)
    return "error", first.group(1) if first else None   # 2: collection error (an import broken), 3, 4, 5


def expand_targets(root: Path, targets: tuple[str, ...]) -> list[str]:
    """The targets in the order given, a folder as its test files (sorted), each file once: pytest would
    otherwise collect a file named before its folder in the folder's order, and `-x` would stop elsewhere."""
    out: list[str] = []
    for t in targets:
        path = root / t
        if "::" not in t and path.is_dir():
            out += [p.relative_to(root).as_posix() for p in sorted(path.rglob("test_*.py"))]
        else:
            out.append(t)
    return list(dict.fromkeys(out))


def run_mutant(sb: Sandbox, m: Mutant, timeout_s: float, confirm: bool) -> dict:
    result: dict = {"id": m.id, "package": m.package, "file": m.file, "description": m.description,
                    "targets": list(m.targets), "trust": m.trust}
    problems = table_problems(sb.src, (m,))
    if problems:
        return {**result, "status": "refused", "detail": problems[m.id], "seconds": 0.0}
    with Planted(sb.src, m):
        rc, out, seconds = run_pytest(sb, expand_targets(sb.src, m.targets), timeout_s)
    status, first = classify(rc, out)
    result.update(status=status, killed_by=first, seconds=round(seconds, 1), pytest_rc=rc,
                  tail=out.strip().splitlines()[-3:] if out.strip() else [])
    if status == "killed" and confirm:
        rc0, out0, s0 = run_pytest(sb, [first], timeout_s)
        result["confirm_seconds"] = round(s0, 1)
        if rc0 != 0:
            result["status"] = "inconclusive"
            result["detail"] = f"{first} fails without the mutant too (rc {rc0}): {_last_line(out0)}"
    return result


def _last_line(out: str) -> str:
    lines = out.strip().splitlines()
    return lines[-1] if lines else ""


def _line(i: int, n: int, r: dict) -> str:
    what = r.get("killed_by") or r.get("detail") or ""
    return f"[{i:2d}/{n}] {r['id']:<36} {r['status']:<12} {r.get('seconds', 0.0):7.1f} s  {what}"


def write_results(path: Path, results: list[dict], started: float, selected: list[Mutant]) -> None:
    counts: dict[str, int] = {}
    for r in results:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    doc = {
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(started)),
        "commit": _git(["rev-parse", "HEAD"]),
        "working_tree_changes": bool(_git(["status", "--porcelain"])),
        "pytest_args": list(PYTEST_ARGS),
        "selected": [m.id for m in selected],
        "summary": counts,
        "total_seconds": round(sum(r.get("seconds", 0.0) + r.get("confirm_seconds", 0.0) for r in results), 1),
        "results": results,
    }
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, path)


def _git(args: list[str]) -> str:
    try:
        return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return ""


def markdown_rows(results_files: list[Path]) -> str:
    """The per-mutant table of docs/testing.md, its "before" column from result files (a later file's result
    for a mutant replaces an earlier one's); a mutant in none of them is "not yet run"."""
    found: dict[str, dict] = {}
    for path in results_files:
        for r in json.loads(path.read_text(encoding="utf-8"))["results"]:
            found[r["id"]] = r
    rows = ["| id | area | planted bug | before | after |", "| --- | --- | --- | --- | --- |"]
    for m in MUTANTS:
        r = found.get(m.id)
        if r is None:
            before = "not yet run"
        elif r["status"] == "killed":
            before = f"killed by `{r['killed_by']}` ({r['seconds']:.0f} s)"
        else:
            before = f"**{r['status']}** ({r['seconds']:.0f} s)" + (f": {r['detail']}" if r.get("detail") else "")
        mark = " (trust issue)" if m.trust else ""
        rows.append(f"| `{m.id}` | {m.package} | {m.description.replace('|', '/')}{mark} | {before} | |")
    return "\n".join(rows)


def _on_sigterm(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Plant each bug of the table in a copy of the repository and "
                                             "record which test kills it (issue 37).")
    ap.add_argument("--only", nargs="+", metavar="ID", help="run these mutants only")
    ap.add_argument("--list", action="store_true", help="print the table and exit")
    ap.add_argument("--timeout-per-mutant", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                    help=f"a mutant's pytest run is stopped after S seconds: `timeout` (default {DEFAULT_TIMEOUT_S:g})")
    ap.add_argument("--out", type=Path, default=Path("mutants-result.json"), metavar="FILE",
                    help="JSON results, rewritten after each mutant (default ./mutants-result.json)")
    ap.add_argument("--no-confirm", action="store_true",
                    help="do not re-run a killing test alone without its mutant")
    ap.add_argument("--markdown", nargs="+", type=Path, metavar="RESULT",
                    help="print docs/testing.md's per-mutant table from these result files and exit")
    args = ap.parse_args(argv)
    if args.markdown:
        print(markdown_rows(args.markdown))
        return 0

    table = by_id()
    if args.only:
        unknown = [i for i in args.only if i not in table]
        if unknown:
            print(f"mutants: unknown id(s): {', '.join(unknown)} (--list shows them)", file=sys.stderr)
            return 2
        selected = [table[i] for i in dict.fromkeys(args.only)]
    else:
        selected = list(MUTANTS)

    if args.list:
        problems = table_problems(REPO)
        for m in selected:
            mark = " (trust issue)" if m.trust else ""
            print(f"{m.id:<36} {m.package:<22} {m.file}{mark}\n    {m.description}\n    targets: {' '.join(m.targets)}")
            if m.id in problems:
                print(f"    REFUSED: {problems[m.id]}")
        return 0

    signal.signal(signal.SIGTERM, _on_sigterm)
    remove_stale_sandboxes()
    started = time.time()
    results: list[dict] = []
    sb = Sandbox(REPO)
    try:
        print(f"mutants: copying the repository into {sb.dir}", flush=True)
        sb.build()
        for i, m in enumerate(selected, 1):
            r = run_mutant(sb, m, args.timeout_per_mutant, confirm=not args.no_confirm)
            results.append(r)
            print(_line(i, len(selected), r), flush=True)
            write_results(args.out, results, started, selected)
    except KeyboardInterrupt:
        print("mutants: interrupted; the working tree was never touched", file=sys.stderr)
        return 130
    finally:
        sb.remove()
        if results:
            write_results(args.out, results, started, selected)
    counts: dict[str, int] = {}
    for r in results:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    total = sum(r.get("seconds", 0.0) + r.get("confirm_seconds", 0.0) for r in results)
    print("mutants: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items())) + f" of {len(results)}"
          f" in {total / 60:.1f} min; results in {args.out}")
    for r in results:
        if r["status"] == "survived":
            print(f"  survived: {r['id']}: {r['description']}")
    return 0 if all(r["status"] == "killed" for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
