"""`millsense run [--config FILE] [--seconds N]`: the daemon.

Start-up, in this order, each step with one clear failure:

1. configuration (`--config`, or the built-in demo: simulated DAQ playing the
   step-cut scenario in a loop, Zenoh peer on loopback) — a bad file exits 78;
2. Zenoh (a client retries its router for 30 s, then exits 69);
3. the DAQ: the driver reconnects with a doubling back-off; if it has not
   connected within the **start window** (`--connect-timeout`, default
   10 s) the daemon says where it tried and exits 69 (EX_UNAVAILABLE), so
   systemd's restart policy, not a silent loop, handles an absent DAQ. Once
   running, a lost link is reconnected forever (status `degraded`,
   `daq_lost` alarm). A DAQ whose channels do not fit the config exits 78;
4. the runner threads; sd_notify `READY=1` once samples flow. With a config
   file the daemon has a state directory (`latch_store.state_dir`): a latch
   persisted by an earlier run is asserted again at start, the audit log and
   the local control socket (`control.sock`, for root and the daemon's user)
   live there. The demo persists nothing and opens no socket.

On a terminal every run shows the **live line** (state, rpm, torque, force,
depths, alarm, interlock), refreshed in place each second below the log lines
(`logging_setup.NonBlockingWriter.show_live`); under systemd or into a pipe
there is none, and the logs are JSON. The demo off a terminal prints it as one
line per second on stdout instead.

SIGTERM / SIGINT stop it within about a second: threads joined, liveliness
token dropped, Zenoh closed, the DAQ link closed — and the feed hold output
left exactly as it was (a stop is not a reset).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from millsense.daemon.stop_signals import stop_on_signals

CONNECT_WINDOW_S = 10.0
DESCRIPTOR_WAIT_S = 3.0
ZENOH_RETRY_S = 30.0
PROG = "millsense run"
EXIT_UNAVAILABLE = 69
# glibc's mallopt() parameter number for the arena limit (<malloc.h>), and the limit the daemon sets.
M_ARENA_MAX = -8
MALLOC_ARENAS = 2


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", "-c", metavar="FILE", default=None, help="configuration file (default: the built-in demo)")
    parser.add_argument("--seconds", type=float, default=None, metavar="N", help="stop after N seconds (tests, demos)")
    parser.add_argument(
        "--connect-timeout",
        type=float,
        default=CONNECT_WINDOW_S,
        metavar="S",
        help=f"give up (exit 69) if the DAQ has not connected within S seconds of start (default {CONNECT_WINDOW_S:g})",
    )


def positive_option(value: float | None, option: str) -> str | None:
    """The error of a seconds option that is not a positive finite number (nan, inf, 0, negative), else None."""
    if value is not None and not 0 < value < float("inf"):   # nan fails both
        return f"{option} must be positive, got {value:g}"
    return None


STATE_WATCH_S = 2.0   # the state directory looked at under the running daemon (`_Daemon._watch_state`)
NAME_WATCH_S = 5.0    # another daemon answering as this machine looked for on Zenoh (`_Daemon._watch_name`)


def _fail(message: str, code: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def bound_native_memory() -> bool:
    """Bound what native libraries hold on to; called first in `run`, while the daemon has one thread
    and numpy is not imported yet (issue 13: the daemon's RSS budget). Returns whether the C library
    accepted the malloc arena limit (glibc does; elsewhere nothing is bounded and nothing breaks).

    - OpenBLAS starts a worker thread per extra core when numpy is imported; the daemon's arrays are
      far too small for BLAS to split, so the workers only sleep. OpenBLAS reads the variable once,
      at numpy's import. A value set by the operator wins.
    - glibc gives each new thread that allocates an arena of its own, up to 8 a core, and an arena
      keeps what was freed in it. The daemon runs ~20 threads (its own, Zenoh's runtimes). Two, not
      one, so that the reader and the estimator need not queue on one lock. Arenas are made when
      threads first allocate, so the limit must be set before any thread starts.
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    libc = _libc()
    try:
        return libc is not None and libc.mallopt(M_ARENA_MAX, MALLOC_ARENAS) == 1
    except AttributeError:  # a C library without mallopt
        return False


def release_free_heap() -> None:
    """Give the pages that start-up freed (parsed config, import-time temporaries) back to the system:
    glibc keeps them mapped otherwise. Called once, before the DAQ streams, so no thread on the sample
    path ever waits on the arena locks `malloc_trim` takes while it walks the heap."""
    libc = _libc()
    try:
        if libc is not None:
            libc.malloc_trim(0)
    except AttributeError:  # not glibc
        pass


def _libc() -> Any:
    import ctypes

    try:
        return ctypes.CDLL(None)  # the C library the interpreter is linked against
    except OSError:
        return None


def run(args: argparse.Namespace) -> int:
    bound_native_memory()
    from millsense.daemon.config.errors import ConfigError
    from millsense.daemon.config.load import check_against_descriptor, demo_config, load_config

    problem = positive_option(args.seconds, "--seconds") or positive_option(args.connect_timeout, "--connect-timeout")
    if problem:
        return _fail(problem, 2)
    demo = args.config is None
    settings = demo_config() if demo else load_config(args.config)

    from millsense.daemon.logging_setup import configure_logging

    configure_logging(settings.log.level, settings.log.format, stream=sys.stderr if demo else sys.stdout)
    if not demo:
        import structlog

        from millsense.daemon.config.warnings import config_warnings

        for warning in config_warnings(settings, args.config):
            structlog.get_logger("millsense.run").warning("config.warning", detail=warning)

    stop = threading.Event()
    stop_on_signals(stop, hangup=True)

    from millsense.drivers import DriverError, create_driver

    try:
        driver = create_driver(settings.daq.transport, **driver_options(settings.daq))
    except DriverError as exc:
        raise ConfigError([f"daq.transport: {exc}"]) from None
    lock = None   # held for the process's life: one daemon a state directory (the demo keeps none)
    if not demo:
        from millsense.daemon.state_dir import claim_state_dir, state_dir

        lock, busy = claim_state_dir(state_dir(settings.machine))
        if busy is not None:
            raise ConfigError([f"machine: {busy}"])
    # Everything slow (Zenoh, imports, declarations) happens before the driver
    # starts: from then on samples queue up, and a queued block's hand-over time
    # is no longer its arrival time (which live `t` is built from).
    session = _open_zenoh(settings, stop)
    if session is None:
        return EXIT_UNAVAILABLE if not stop.is_set() else 0
    try:
        from millsense.daemon.publish.sink import key_prefix, machine_alive

        if machine_alive(session, settings.machine):
            raise ConfigError([f"machine: a daemon is already alive as {settings.machine!r} on this Zenoh network "
                               f"({key_prefix(settings.machine)}/alive): each machine needs its own name (a copied "
                               f"configuration?), and one daemon a machine"])
        daemon = _Daemon(settings, driver, session, demo)
        try:
            release_free_heap()
            driver.start()
            if not _wait(lambda: driver.wait_connected(0.1), args.connect_timeout, stop):
                if stop.is_set():
                    return 0
                where = getattr(driver, "address", "?")
                return _fail(
                    f"DAQ unreachable: no connection to {settings.daq.transport} {where} within {args.connect_timeout:g} s"
                    f"{_last_error(driver)}",
                    EXIT_UNAVAILABLE,
                )
            if not _wait(lambda: driver.descriptor is not None or time.sleep(0.01), DESCRIPTOR_WAIT_S, stop):
                if stop.is_set():
                    return 0
                return _fail(f"the DAQ connected but sent no DESCRIPTOR within {DESCRIPTOR_WAIT_S:g} s", EXIT_UNAVAILABLE)
            check_against_descriptor(settings, driver.descriptor)  # ConfigError -> 78
            daemon.serve(args.seconds, stop)
            return 0
        finally:
            daemon.close()
            driver.close(why="the daemon is stopping")
    finally:
        try:
            session.close()
        except Exception:  # noqa: BLE001 - closing at exit; nothing left to save
            pass
        if lock is not None:
            lock.close()


def _open_zenoh(settings: Any, stop: threading.Event) -> Any:
    """The Zenoh session, or None (after saying why) if a client found no router in time."""
    import structlog

    from millsense.daemon.config.errors import ConfigError
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    log = structlog.get_logger("millsense.run")
    try:
        return open_session(
            settings,
            retry_for_s=ZENOH_RETRY_S,
            stop=stop,
            on_waiting=lambda event, fields: log.warning(event, **fields),
        )
    except ZenohConfigError as exc:
        raise ConfigError([str(exc)]) from None
    except ZenohUnavailable as exc:
        _fail(str(exc), EXIT_UNAVAILABLE)
        return None


def _last_error(driver: Any) -> str:
    """The driver's last reason a connect failed, for the message `run` and `record` end with ("" if none)."""
    why = getattr(driver, "last_connect_error", None)
    return f" ({why})" if why else ""


@dataclass
class _Watch:
    """A look `_Daemon.serve` takes every `every_s` seconds, the first one period after it starts."""

    look: Callable[[], None]
    every_s: float
    event: str   # logged when a look fails
    due: float = field(init=False)

    def __post_init__(self) -> None:
        self.due = time.monotonic() + self.every_s

    def run_if_due(self, now: float, log: Any) -> None:
        """Look if `due` has come, the next one `every_s` after `now`; a look that fails is logged, never raised."""
        if now < self.due:
            return
        self.due = now + self.every_s
        try:
            self.look()
        except Exception as exc:  # noqa: BLE001 - a watch must never stop the daemon
            log.error(self.event, error=f"{type(exc).__name__}: {exc}")


class _Daemon:
    """Runner + Zenoh sink, built before the DAQ starts streaming; `close()` is idempotent."""

    def __init__(self, settings: Any, driver: Any, session: Any, demo: bool):
        import structlog

        from millsense.daemon import __version__, sdnotify
        from millsense.daemon.config.load import effective_config_dict
        importlib.import_module("millsense.daemon.pipeline.estimator")  # numpy now, not on the first block
        from millsense.daemon.runtime.runner import Runner
        from millsense.daemon.publish.sink import ZenohSink

        from millsense.daemon.audit import AuditLog
        from millsense.daemon.runtime.latch_store import LatchStore
        from millsense.daemon.state_dir import state_dir

        self.log = structlog.get_logger("millsense.run")
        self.summary = _live_line(demo)
        self.demo = demo
        self.transport = settings.daq.transport
        # The demo persists nothing: no latch, no audit file, no control socket, no history.
        self.state_dir = None if demo else state_dir(settings.machine)
        history, limits, tools, first_process, history_error = _open_history(settings, self.state_dir)
        self.runner = Runner(
            settings,
            driver,
            version=__version__,
            notify=sdnotify.notify,
            on_second=self.summary,
            effective_config=lambda: effective_config_dict(settings),
            latch_store=LatchStore(self.state_dir) if self.state_dir is not None else None,
            audit=AuditLog(self.state_dir / "audit.log" if self.state_dir is not None else None, settings.machine),
            history=history,
            limits=limits,
            tools=tools,
            first_process=first_process,
        )
        if history_error is not None:  # monitoring goes on with the fixed limits and what it learns from now
            self.runner.board.fault("history", history_error)
        self.local = None
        self.sink = ZenohSink(session, self.runner.machine, self.runner.controls, log=self.log, close_timeout_s=0.5,
                              expects_router=settings.zenoh.mode == "client")
        self.session = session
        self._closed = False
        self._locks: list[Any] = []   # state-directory locks taken again after the directory was deleted
        self._watched: tuple[bool, bool, bool] | None = None   # directory, lock, socket there at the first look

    def serve(self, seconds: float | None, stop: threading.Event) -> None:
        if self.state_dir is not None:
            from millsense.daemon.state_dir import ensure_dir

            try:
                ensure_dir(self.state_dir)
            except OSError as exc:  # the daemon still protects the machine; it only cannot remember
                self.runner.board.fault("latch_store", f"cannot create the state directory {self.state_dir}: {exc}")
        self.runner.start(self.sink)
        if self.state_dir is not None:
            from millsense.daemon.runtime.local_control import LocalControl

            self.local = LocalControl(self.state_dir, self.runner.controls, on_error=self.runner.board.fault)
            self.local.start()
            self._watch_state()   # what there is to keep an eye on
        self.log.info("daemon.started", machine=self.runner.machine, transport=self.transport, demo=self.demo)
        deadline = None if seconds is None else time.monotonic() + seconds
        watches = (_Watch(self._watch_state, STATE_WATCH_S, "state.watch_failed"),
                   _Watch(self._watch_name, NAME_WATCH_S, "zenoh.name_watch_failed"))
        while not stop.is_set():
            left = 0.2 if deadline is None else min(0.2, deadline - time.monotonic())
            if left <= 0:
                break
            stop.wait(left)
            for watch in watches:
                watch.run_if_due(time.monotonic(), self.log)

    def _watch_state(self) -> None:
        """The state directory under the running daemon, every STATE_WATCH_S: deleted by hand (a clean-up), it is
        made again with what this daemon holds, the control socket, its lock and the latch; the history's database
        gone is the fault `history` (SQLite writes on into the deleted file: nothing would last). Only what was
        there is looked for: a directory that could not be written at start is its own fault already."""
        from millsense.daemon.state_dir import LOCK_FILE, claim_state_dir, ensure_dir

        d = self.state_dir
        if d is None:
            return
        if self._watched is None:   # the first look: what there is to keep
            self._watched = (d.is_dir(), (d / LOCK_FILE).exists(), self.local is not None and self.local.listening)
        had_dir, had_lock, had_socket = self._watched
        gone = ((had_dir and not d.is_dir()) or (had_lock and not (d / LOCK_FILE).exists())
                or (had_socket and not self.local.path.is_socket()))
        if gone:
            self.log.warning("state.directory_gone", path=str(d),
                             detail="the state directory, its lock or the control socket was deleted under the running "
                                    "daemon: made again (lock, control socket, latch)")
            ensure_dir(d)
            if had_lock and not (d / LOCK_FILE).exists():   # the old lock is on a deleted file: claim it again
                handle, busy = claim_state_dir(d)
                if handle is not None:
                    self._locks.append(handle)
                elif busy is not None:
                    self.log.error("state.claimed_by_another", path=str(d), detail=busy)
            if had_socket:
                self.local.close(timeout_s=0.5)
                self.local.start()
            if self.runner.latch_store is not None:
                self.runner.latch_store.save(self.runner.interlock.record())
        if self.runner.history is not None:
            self._watch_history()

    def _watch_name(self) -> None:
        """Another daemon answering as this machine, every NAME_WATCH_S: `run` refused to start beside one it could
        see, but two network segments joined later (a router, a laptop bridging them) bring two daemons of one name
        together. Both then publish on one key, and commands by name reach both (a network reset fails on the other's
        nonce): fault `machine` (status `degraded`, the AFC override back to 100 %; the feed is not held, each
        daemon still watches its own machine), cleared when the other is gone."""
        from millsense.daemon.publish.sink import key_prefix, other_daemons

        machine = self.runner.machine
        others = other_daemons(self.session, machine)
        if others and "machine" not in self.runner.faults:
            self.runner.board.fault("machine", f"another daemon is alive as {machine!r} on this Zenoh network (zenoh id "
                                         f"{', '.join(others)}): both publish on {key_prefix(machine)}/*, and commands "
                                         f"by name reach both; each machine needs its own name")
        elif not others and "machine" in self.runner.faults:
            self.runner.board.recover("machine")

    def _watch_history(self) -> None:
        history = self.runner.history
        if "history" in self.runner.faults or not history.stats().get("open") or history.path.exists():
            return
        self.runner.board.fault("history", f"the history database {history.path} was deleted under the running daemon: "
                                     f"what is written now is lost (restart the daemon to start a new one)")

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        t0 = time.monotonic()
        if self.local is not None:
            self.local.close(timeout_s=0.5)
        self.runner.stop(timeout_s=0.5)
        if self.runner.history is not None:
            try:
                self.runner.history.close(timeout_s=1.0)  # what is queued is committed, within a second
            except Exception as exc:  # noqa: BLE001
                self.log.error("history.close_failed", error=str(exc))
        try:
            self.sink.close()  # drops the liveliness token
        except Exception as exc:  # noqa: BLE001
            self.log.error("zenoh.close_failed", error=str(exc))
        for handle in self._locks:
            handle.close()
        if self.summary is not None:
            self.summary.end()
        self.log.info("daemon.stopped", stop_s=round(time.monotonic() - t0, 3), interlock=self.runner.interlock.state)


def _open_history(settings: Any, state: Any) -> tuple[Any, dict | None, dict | None, int, str | None]:
    """The history database and what earlier runs learned: (store, limits, tools, first process id, error).

    Off in the demo and with `[history] enabled = false`: then what is learned lives only as long as
    the process. A database that cannot be opened is the fault `history`; monitoring goes on.
    """
    from pathlib import Path

    conf = getattr(settings, "history", None)
    if state is None or conf is None or not conf.enabled:
        return None, None, None, 1, None
    from millsense.daemon.history.store import HistoryStore
    from millsense.daemon.state_dir import ensure_dir

    path = Path(conf.path) if conf.path else Path(state) / "history.sqlite3"
    try:
        ensure_dir(Path(state))
        path.parent.mkdir(parents=True, exist_ok=True)
        store = HistoryStore(path, machine=settings.machine, retention_days=conf.retention_days,
                             max_mb=conf.max_mb, keep_revolutions=conf.revolutions)
        store.start()  # never raises: a file it cannot open is the fault `history` once the runner listens
        return store, store.load_limits(), store.load_tools(), store.last_process_id() + 1, None
    except Exception as exc:  # noqa: BLE001 - the machine is still protected by the fixed limits
        return None, None, None, 1, f"cannot open the history database {path}: {type(exc).__name__}: {exc}"


def driver_options(daq: Any) -> dict[str, Any]:
    """The `[daq]` section as driver options (a driver ignores what it does not use). `record` uses it too."""
    raw = daq.model_dump() if hasattr(daq, "model_dump") else dict(vars(daq))
    return {k: v for k, v in raw.items() if k != "transport" and v is not None}


def _wait(done: Any, timeout_s: float, stop: threading.Event) -> bool:
    deadline = time.monotonic() + max(0.0, timeout_s)
    while not stop.is_set():
        if done():
            return True
        if time.monotonic() >= deadline:
            return False
    return False


def _live_line(demo: bool) -> Any:
    """Where the live line goes: the log writer when the logs go to a terminal (so the two never share
    a line); for the demo, whose logs go to stderr, stdout when that is a terminal, else one line per
    second on stdout; nowhere for a daemon off a terminal (systemd, a pipe)."""
    from millsense.daemon.logging_setup import NonBlockingWriter, live_writer, under_systemd

    writer = live_writer()
    if writer is not None:
        return _LiveLine(writer, owned=False)
    if not demo:
        return None
    if not under_systemd() and bool(getattr(sys.stdout, "isatty", lambda: False)()):
        return _LiveLine(NonBlockingWriter(sys.stdout, terminal=True), owned=True)
    return _SummaryLines(sys.stdout)


class _LiveLine:
    """The live line, refreshed in place by a terminal writer (which never blocks the status thread)."""

    def __init__(self, writer: Any, owned: bool):
        self.writer = writer
        self.owned = owned

    def __call__(self, status: dict, estimate: dict | None, alarm_state: str) -> None:
        from millsense.daemon.status_text import summary_line

        self.writer.show_live(summary_line(estimate, alarm_state, status))

    def end(self) -> None:
        self.writer.end_live()  # the last state stays on screen; what is logged next goes below it
        if self.owned:
            self.writer.close()


class _SummaryLines:
    """The demo off a terminal: the live line as one line per second on stdout."""

    def __init__(self, stream: Any):
        self.stream = stream

    def __call__(self, status: dict, estimate: dict | None, alarm_state: str) -> None:
        from millsense.daemon.status_text import summary_line

        self.stream.write(summary_line(estimate, alarm_state, status) + "\n")
        self.stream.flush()

    def end(self) -> None:
        pass
