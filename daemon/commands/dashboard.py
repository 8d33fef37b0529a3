"""`millsense dashboard`: a web page of every machine seen on Zenoh (docs/dashboard.md).

Listens on 127.0.0.1:8470 unless `--listen HOST:PORT` says otherwise. With
`--cert` and `--key` it serves HTTPS; the page's reset (WebCrypto, which
browsers give only to a secure context) is offered over HTTPS or on a loopback
address, nowhere else. Zenoh is reached the way `watch` reaches it
(`--connect`, `--zenoh-config`, `--config`).

Prints one line `dashboard: serving on http(s)://HOST:PORT/` on stderr when the
page can be loaded; SIGTERM or Ctrl-C stops it (exit 0).
"""

from __future__ import annotations

import argparse
import sys
import threading
from typing import Any

from millsense.daemon.publish.cli_args import (
    EXIT_USAGE,
    CliUsageError,
    add_config_argument,
    add_zenoh_arguments,
    client_settings,
    hint,
    strip_rust,
)
from millsense.daemon.stop_signals import stop_on_signals

PROG = "millsense dashboard"
DEFAULT_LISTEN = "127.0.0.1:8470"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # Its own dest: `listen` is what cli_args reads as Zenoh's listen endpoints.
    parser.add_argument("--listen", dest="http_listen", metavar="HOST:PORT", default=DEFAULT_LISTEN,
                        help=f"where the web page is served (default {DEFAULT_LISTEN}: this host only)")
    parser.add_argument("--cert", metavar="FILE", default=None, help="TLS certificate (PEM): serve HTTPS")
    parser.add_argument("--key", metavar="FILE", default=None, help="the certificate's private key (PEM)")
    add_config_argument(parser, "where to connect")
    add_zenoh_arguments(parser, listen=False)


def parse_listen(text: str) -> tuple[str, int]:
    """`HOST:PORT` (`[::1]:8470` for IPv6) → (host, port); raises CliUsageError."""
    host, sep, port_text = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port_text.isdigit() or not 0 <= int(port_text) <= 65535:
        raise CliUsageError(f"--listen: {text!r} is not HOST:PORT (e.g. 127.0.0.1:8470)")
    return host, int(port_text)


def _tls_context(cert: str | None, key: str | None) -> Any:
    if not cert and not key:
        return None
    if not (cert and key):
        raise CliUsageError("--cert and --key go together")
    import ssl

    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise CliUsageError(f"--cert/--key: cannot load {cert} with {key}: {exc}") from None
    return ctx


def run(args: argparse.Namespace) -> int:
    from millsense.daemon.publish.session import ZenohConfigError, ZenohUnavailable, open_session

    try:
        host, port = parse_listen(args.http_listen)
        tls = _tls_context(args.cert, args.key)
    except CliUsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    connection = client_settings(args, PROG)
    if isinstance(connection, int):
        return connection
    daemon, settings = connection

    stop = threading.Event()
    stop_on_signals(stop)
    try:
        session = open_session(settings, retry_for_s=None, stop=stop, on_waiting=lambda event, f: print(
            f"{PROG}: waiting for a Zenoh router at {', '.join(f['connect']) or '(scouting)'} ({f['error']})",
            file=sys.stderr))
    except ZenohConfigError as exc:
        print(f"{PROG}: error: {strip_rust(str(exc))}", file=sys.stderr)
        return 1
    except ZenohUnavailable as exc:
        print(f"{PROG}: error: {strip_rust(str(exc))}\n{hint(settings, daemon)}", file=sys.stderr)
        return 1
    try:
        return _serve(session, host, port, tls, stop)
    finally:
        session.close()


def _serve(session: Any, host: str, port: int, tls: Any, stop: threading.Event) -> int:
    from millsense.daemon import sdnotify
    from millsense.daemon.dashboard.book import Book
    from millsense.daemon.dashboard.server import DashboardServer
    from millsense.daemon.dashboard.zenoh_side import ZenohSide

    book = Book()
    side = ZenohSide(session, book)
    try:
        try:
            server = DashboardServer((host, port), book, side, https=tls is not None)
        except OSError as exc:
            print(f"{PROG}: error: cannot listen on {host}:{port}: {exc.strerror or exc}", file=sys.stderr)
            return 1
        if tls is not None:
            # The handshake then happens in the connection's own thread, not in the accepting one.
            server.socket = tls.wrap_socket(server.socket, server_side=True, do_handshake_on_connect=False)
        thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, daemon=True)
        thread.start()
        scheme = "https" if tls is not None else "http"
        shown = f"[{host}]" if ":" in host else host
        print(f"dashboard: serving on {scheme}://{shown}:{server.server_address[1]}/"
              + ("" if server.reset_offered else " (reset not offered: plain HTTP off localhost; give --cert/--key)"),
              file=sys.stderr, flush=True)
        sdnotify.notify(ready=True, status=f"serving on {scheme}://{shown}:{server.server_address[1]}/")
        while not stop.wait(0.5):
            pass
        sdnotify.notify(stopping=True)
        server.stopping.set()
        server.shutdown()
        server.server_close()
        return 0
    finally:
        side.close()
