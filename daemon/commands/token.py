"""`millsense token new [--out FILE]`: a fresh reset token, 256 random bits.

The token is what `[interlock] reset_token_file` names and what `millsense
reset` proves it knows (docs/zenoh.md): 32 bytes from the system's CSPRNG as
base64url without padding, 43 characters. 256 bits make an offline guess from a
sniffed exchange hopeless, far past the 128-bit floor (`check-config` refuses a
token under 32 characters).

The same command makes a CNC adapter's key (`[context] adapter_key_file`, docs/zenoh.md "Signed context"):
a secret of its own, never the reset token's file (a config naming the same secret for both is refused).

Without `--out` the token goes to stdout (for a secret store). With `--out` it
is written to a new file of mode 0600, never over an existing one (replacing a
token is a decision: delete the old file first).
"""

from __future__ import annotations

import argparse
import os
import secrets
import sys

PROG = "millsense token"
TOKEN_BYTES = 32


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="token_command", metavar="ACTION", required=True)
    new = sub.add_parser("new", help="make a new reset token (256 bits, base64url, 43 characters)",
                         description="make a new reset token (256 bits, base64url, 43 characters)")
    new.add_argument("--out", "-o", metavar="FILE", default=None,
                     help="write it to FILE (created with mode 0600; an existing file is never overwritten)")


def new_token() -> str:
    return secrets.token_urlsafe(TOKEN_BYTES)


def run(args: argparse.Namespace) -> int:
    token = new_token()
    if args.out is None:
        print(token)
        return 0
    try:
        fd = os.open(args.out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        print(f"{PROG}: error: {args.out} exists; not overwritten (delete it first to replace the token)", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"{PROG}: error: cannot create {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    try:
        os.fchmod(fd, 0o600)  # a umask cannot loosen it; a group cannot read it
        os.write(fd, (token + "\n").encode("ascii"))
    finally:
        os.close(fd)
    print(f"{PROG}: wrote a new token to {args.out} (mode 0600); point [interlock] reset_token_file at it "
          "(or [context] adapter_key_file, for a CNC adapter's key) and give it to the daemon's user only",
          file=sys.stderr)
    return 0
