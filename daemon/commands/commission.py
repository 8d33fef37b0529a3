"""`millsense commission --config FILE`: a guided check of a machine's DAQ, wiring and feed hold.

Steps (docs/commissioning.md): the DAQ's descriptor against the configuration; each current and voltage
channel's RMS against a meter's reading (proposing the scale that agrees); the phase order and current-voltage
alignment (the daemon's phase check); the encoder's direction and counts per revolution against a commanded
spindle speed; the feed hold through the DAQ and the CNC's confirmation, timed; the DAQ's watchdog holding the
feed when the heartbeats stop. Then a report the shop keeps (`--report`, default in the state directory).

Readings come from `--readings`, `--answers FILE` (`key=value` lines) or, on a terminal, typed at the prompts
(`s` skips). The command holds the machine's state directory: it refuses to run beside a daemon of this
machine (two masters on one DAQ). Exit 0: commissioned; 1: not commissioned (a step failed or was not
checked: each fix is printed); 2: bad usage; 69: no DAQ; 78: configuration; 130: interrupted (a hold this
command set is left asserted and persisted: `millsense reset` clears it once the daemon runs).
"""

from __future__ import annotations

import argparse
import datetime
import math
import platform
import re
import sys
import time
from pathlib import Path
from typing import Any

PROG = "millsense commission"
SCALE_TOL_PCT = 3.0    # a clamp meter's own error (1-2 %) and a hall sensor's: more is a wrong scale
SPEED_TOL_PCT = 3.0    # a commanded speed the drive holds within about 1 %
SAMPLE_S = 2.0
DESCRIPTOR_WAIT_S = 3.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", required=True, metavar="FILE", help="the machine's configuration")
    parser.add_argument("--readings", metavar="NAME=VALUE,...", default=None,
                        help="meter readings (true RMS): a channel (i_u=12.3, v_uv=398), or current_a / voltage_v "
                             "for every current / voltage channel; 's' skips one")
    parser.add_argument("--answers", metavar="FILE", default=None,
                        help="the same as key=value lines, with spindle_rpm and release_found_hold (yes/no)")
    parser.add_argument("--spindle-rpm", type=float, default=None, metavar="RPM",
                        help="the speed the spindle runs at, forward (M03), for the encoder check")
    parser.add_argument("--release-found-hold", action="store_true",
                        help="a feed hold the DAQ has when commission connects may be released for the tests "
                             "(it is asserted again before commission ends)")
    parser.add_argument("--report", metavar="FILE", default=None,
                        help="the report (.json, and .txt beside it; default: the state directory's "
                             "commissioning-<machine>-<UTC date>.json, -2 … for a later run that day)")
    parser.add_argument("--seconds", type=float, default=SAMPLE_S, metavar="S",
                        help=f"samples taken for each measurement (default {SAMPLE_S:g})")
    parser.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                        help="give up (exit 69) if the DAQ has not connected within S seconds")


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def _answers(args: argparse.Namespace) -> dict[str, str] | str:
    """key -> value of --answers and --readings (the command line wins), or the one-line error."""
    pairs: list[tuple[str, str]] = []
    if args.answers:
        try:
            text = Path(args.answers).read_text(encoding="utf-8")
        except OSError as exc:
            return f"--answers {args.answers}: {exc.strerror or exc}"
        pairs += [(f"--answers line {k}", line) for k, line in enumerate(text.splitlines(), 1)
                  if line.strip() and not line.lstrip().startswith("#")]
    if args.readings:
        pairs += [("--readings", item) for item in args.readings.split(",") if item.strip()]
    out: dict[str, str] = {}
    for where, item in pairs:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            return f"{where}: expected NAME=VALUE, got {item.strip()!r}"
        out[key.strip()] = value.strip()
    if args.spindle_rpm is not None:
        out["spindle_rpm"] = str(args.spindle_rpm)
    for key, value in out.items():   # before the DAQ is touched: a typo costs nothing
        if key != "release_found_hold" and value.lower() not in ("s", "skip") and not _positive(value):
            return f"{key}={value}: expected a positive number (or s to skip)"
    return out


def _positive(text: str) -> bool:
    try:
        value = float(text)
    except ValueError:
        return False
    return math.isfinite(value) and value > 0   # nan and inf: not a reading


class _Asker:
    """A value from the answers, else typed at the terminal (prompts only there), else None (skipped)."""

    def __init__(self, answers: dict[str, str]):
        self.answers = answers
        self.interactive = sys.stdin.isatty()

    def number(self, keys: tuple[str, ...], prompt: str) -> float | None:
        for key in keys:
            if key in self.answers:
                return _number(self.answers[key], key)
        while self.interactive:
            text = _typed(prompt)
            if text.lower() in ("s", "skip", ""):
                return None
            if _positive(text):
                return float(text)
            print(f"  a positive number, or s to skip (got {text!r})")
        return None

    def yes(self, key: str, prompt: str, given: bool) -> bool:
        if given or self.answers.get(key, "").lower() in ("y", "yes", "true", "1"):
            return True
        return self.interactive and _typed(prompt).lower() in ("y", "yes")

    def enter(self, prompt: str) -> None:
        if self.interactive:
            _typed(prompt)


def _typed(prompt: str) -> str:
    """A line typed at the terminal after `prompt` (on stdout, with the steps: `input()` without readline puts
    it on stderr); the end of input is an empty answer."""
    print(prompt, end="", flush=True)
    return sys.stdin.readline().strip()


def _number(text: str, key: str) -> float | None:
    """An answer `_answers` has checked: a positive number, or s."""
    return None if text.lower() in ("s", "skip") else float(text)


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.commands.run import driver_options, positive_option
    from millsense.daemon.config.errors import ConfigError
    from millsense.daemon.config.load import load_config

    problem = positive_option(args.seconds, "--seconds") or positive_option(args.connect_timeout, "--connect-timeout")
    if problem:
        return _fail(problem, 2)
    answers = _answers(args)
    if isinstance(answers, str):
        return _fail(answers, 2)
    settings = load_config(args.config)   # ConfigError -> 78, each problem naming section.key
    known = {*settings.channels, "current_a", "voltage_v", "spindle_rpm", "release_found_hold"}
    unknown = sorted(set(answers) - known)
    if unknown:
        return _fail(f"{unknown[0]}: no such reading (a configured channel, current_a, voltage_v, spindle_rpm or "
                     "release_found_hold)", 2)
    from millsense.daemon.logging_setup import configure_logging

    configure_logging("error", "console", stream=sys.stderr)   # the steps speak for themselves
    from millsense.daemon.state_dir import claim_state_dir, daemon_state_dir
    from millsense.drivers import DriverError, create_driver

    try:
        driver = create_driver(settings.daq.transport, **driver_options(settings.daq))
    except DriverError as exc:
        raise ConfigError([f"daq.transport: {exc}"]) from None
    # the daemon's own directory (a unit's, where its control socket is): the latch and the report go where it looks
    directory = daemon_state_dir(settings.machine)
    lock, busy = claim_state_dir(directory)
    if busy is not None:
        return _fail(f"{busy}; commission drives the DAQ itself, and two masters on one DAQ would fight", 1)
    if lock is None:   # a daemon may hold it, and a latch could not be kept: not safe to go on
        return _fail(f"cannot take the state directory {directory} (run as root or the daemon's user, or set "
                     "STATE_DIRECTORY)", 1)
    try:
        driver.start()
        if not driver.wait_connected(args.connect_timeout):
            why = getattr(driver, "last_connect_error", None)
            return _fail(f"DAQ unreachable: no connection to {settings.daq.transport} "
                         f"{getattr(driver, 'address', '?')} within {args.connect_timeout:g} s"
                         + (f" ({why})" if why else ""), 69)
        deadline = time.monotonic() + DESCRIPTOR_WAIT_S
        while driver.descriptor is None and time.monotonic() < deadline:
            time.sleep(0.01)
        if driver.descriptor is None:
            return _fail(f"the DAQ connected but sent no DESCRIPTOR within {DESCRIPTOR_WAIT_S:g} s", 69)
        return _commission(args, settings, driver, _Asker(answers), directory)
    finally:
        driver.close()
        if lock is not None:
            lock.close()


def _commission(args, settings, driver, ask: _Asker, directory: Path) -> int:
    from millsense.daemon import __version__
    from millsense.daemon.commission import proof, report, signals
    from millsense.daemon.commission.bench import Bench, BenchError
    from millsense.daemon.config.checks import descriptor_problems

    lines: list[str] = []

    def say(text: str) -> None:
        lines.append(text)
        print(text, flush=True)

    started = datetime.datetime.now(datetime.timezone.utc)
    desc = driver.descriptor
    say(f"commissioning {settings.machine}: {settings.daq.transport} {getattr(driver, 'address', '')}, "
        f"{started.isoformat(timespec='seconds')}")
    steps = []
    first = report.Step("descriptor", "the DAQ's channels and sample rate fit the configuration")
    first.figures = {"sample_rate_hz": desc.sample_rate_hz, "protocol_version": desc.protocol_version,
                     "capabilities": desc.capabilities,
                     "channels": [{"name": ch.name, "kind": _kind(ch.kind)} for ch in desc.channels]}
    for p in descriptor_problems(settings, desc):
        first.fail(p, _remedy(p))
    steps.append(first)
    say("\n".join(first.lines()))
    bench = Bench(settings, driver)
    released_found = False
    try:
        bench.start()
        if bench.found_held:
            say("the DAQ holds the feed: it did when commission connected (its watchdog, or a hold not reset)")
        if first.problems:
            for name in ("scales", "phases", "speed"):
                steps.append(report.Step(name, "the DAQ's samples"))
                steps[-1].not_checked("the descriptor does not fit the configuration (step descriptor)")
        else:
            raw = bench.samples(args.seconds)
            rows = []
            for name, unit in signals.metered_channels(settings, desc):
                daq = signals.rms(settings, desc, raw, name)
                key = "current_a" if unit == "A" else "voltage_v"
                meter = ask.number((name, key), f"  {name}: the DAQ reads {daq:.2f} {unit} RMS; your meter on that "
                                                f"{'phase' if unit == 'A' else 'pair of lines'}, {unit} (s to skip): ")
                rows.append({"channel": name, "unit": unit, "daq_rms": round(daq, 4), "skipped": True} if meter is None
                            else signals.judge_scale(name, unit, daq, meter, float(settings.channels[name].scale),
                                                     SCALE_TOL_PCT))
            steps.append(signals.scale_step(rows, SCALE_TOL_PCT))
            say("\n".join(steps[-1].lines()))
            steps.append(signals.phase_step(settings, desc, raw))
            say("\n".join(steps[-1].lines()))
            rpm = ask.number(("spindle_rpm",), "  the spindle speed you will command, forward (M03), rpm (s to skip): ")
            if rpm is not None and "spindle_rpm" not in ask.answers:
                ask.enter(f"  run the spindle at {rpm:g} rpm forward, then press Enter: ")
                raw = bench.samples(args.seconds)
            steps.append(signals.speed_step(settings, desc, raw, rpm, SPEED_TOL_PCT))
            say("\n".join(steps[-1].lines()))
        may_test = not bench.found_held or ask.yes(
            "release_found_hold", "  release it for the feed-hold and watchdog tests (held again at the end)? [y/N] ",
            args.release_found_hold)
        why_not = ("the DAQ held the feed when commission came, and commission releases a hold it did not set only "
                   "when told (--release-found-hold, or y at the prompt)")
        for name, fn in (("test-trip", proof.trip_step), ("watchdog", proof.watchdog_step)):
            if not may_test:
                steps.append(report.Step(name, "the feed hold"))
                steps[-1].not_checked(why_not)
            else:
                if bench.found_held and not released_found:
                    released_found = bool(bench.interlock.reset().get("ok"))
                    say("  the hold found on the DAQ is released for the tests" if released_found else
                        "  the hold found on the DAQ was not released (the DAQ refused)")
                say(f"{name}:")
                steps.append(fn(bench, say))
            say("\n".join(steps[-1].lines()))
            if steps[-1].problems and bench.asserted:
                may_test = False   # a hold the test could not prove stays: nothing more is released
                why_not = f"the hold the {name} step asserted stays asserted (it failed): fix it first"
    except BenchError as exc:
        _leave_safe(bench, released_found, directory, say, "")
        return _fail(str(exc), 69)
    except KeyboardInterrupt:
        _leave_safe(bench, released_found, directory, say, "\ninterrupted: ")
        raise
    else:
        _leave_safe(bench, released_found, directory, say, "")
    finally:
        bench.close()
    failed = [s for s in steps if s.result != "pass"]
    verdict = "commissioned" if not failed else f"not commissioned: {len(failed)} step{'s' if len(failed) != 1 else ''} " \
                                                "failed or not checked"
    say(verdict)
    for s in failed:
        for fix in s.fixes:
            say(f"  {s.name}: {fix}")
        for why in s.unchecked:
            say(f"  {s.name}: not checked: {why}")
    if bench.interlock.enabled and bench.interlock.watchdog_ms:
        # Say the watchdog holds the feed only when this run saw it do so: after a failed or unchecked watchdog
        # step that sentence would promise a stop nobody proved.
        if any(s.name == "watchdog" and s.result == "pass" for s in steps):
            say("the heartbeats end with this command: the DAQ's watchdog holds the feed until the daemon runs and "
                "`millsense reset` clears it")
        else:
            say("the heartbeats end with this command, and the DAQ's watchdog was not proved to hold the feed (the "
                "watchdog step did not pass): do not rely on it until commission passes")
    record = {"machine": settings.machine, "date_utc": started.isoformat(timespec="seconds"),
              "commissioned": not failed, "config": str(Path(args.config).resolve()),
              "versions": {"millsense": __version__, "python": platform.python_version(),
                           "daq_protocol": desc.protocol_version},
              "daq": {"transport": settings.daq.transport, "address": str(getattr(driver, "address", ""))},
              "steps": [s.as_dict() for s in steps]}
    path = Path(args.report) if args.report else report.default_path(directory, settings.machine,
                                                                     started.strftime("%Y-%m-%d"))
    try:
        json_path, text_path = report.write(path, record, "\n".join(lines) + "\n")
    except OSError as exc:
        return _fail(f"cannot write the report {path}: {exc.strerror or exc}", 1)
    print(f"report: {json_path} and {text_path}")
    return 0 if not failed else 1


def _remedy(problem: str) -> str:
    """The daemon's descriptor problems end with what to do, in parentheses: that, under the key they name."""
    key, _, rest = problem.partition(": ")
    m = re.search(r"\(([^()]*)\)$", rest)
    return f"{key}: {m.group(1)}" if m else f"{key}: make the DAQ and the configuration agree"


def _kind(kind: Any) -> str:
    from millsense.drivers.protocol import ChannelKind

    try:
        return ChannelKind(kind).name.lower()
    except ValueError:
        return str(kind)


def _leave_safe(bench: Any, released_found: bool, directory: Path, say, lead: str) -> None:
    """The DAQ as safe as found, or safer: a hold found and released for the tests is asserted again; a hold this
    command set and could not prove (a failed step, Ctrl-C mid-step) stays asserted and is persisted as the
    daemon's latch, so that a daemon started next asserts it again until `millsense reset`. Each is said."""
    if released_found and not bench.asserted:
        bench.interlock.trip("held when commissioning began")
        say(f"{lead}the feed hold found at the start is asserted again, as it was found")
    elif bench.asserted and bench.interlock.reason != "held when commissioning began":
        from millsense.daemon.runtime.latch_store import LatchStore

        store = LatchStore(directory)
        store.start()
        store.save({**bench.interlock.record(), "reason": f"commission: {bench.interlock.reason}"})
        store.close(2.0)
        say(f"{lead}the feed hold this command asserted stays asserted (latched in {directory}); "
            "`millsense reset` clears it once the daemon runs")
    elif lead:
        say(f"{lead}no feed hold of this command is asserted")
