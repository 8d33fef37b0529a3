#!/bin/sh
# Install millsense on a box with no package index, from a wheelhouse that
# systemd/wheelhouse.sh built on a connected machine (docs/install.md, "Offline"):
#   install-offline.sh WHEELHOUSE [VENV]      VENV: /opt/millsense unless given
# makes VENV if it does not exist (an existing one is upgraded in place), installs
# exactly the wheelhouse's requirements.txt with `pip install --no-index --find-links
# WHEELHOUSE`, reinstalls millsense's own wheel (a rebuilt wheel of the same version
# replaces the old code), and links BINDIR/millsense to it, where the unit runs it.
# PYTHON=... the Python that makes the venv (python3 if unset); BINDIR=... where the
# link goes (/usr/local/bin if unset; BINDIR= for no link).
# Then the service: systemd/install.sh MACHINE CONFIG.toml.
set -eu

fail() { echo "$0: $*" >&2; exit 1; }
if [ $# -lt 1 ] || [ $# -gt 2 ]; then
    echo "usage: $0 WHEELHOUSE [VENV]" >&2
    exit 2
fi
wheelhouse=$1
venv=${2:-/opt/millsense}
python=${PYTHON:-python3}
bindir=${BINDIR-/usr/local/bin}

[ -d "$wheelhouse" ] || { echo "$0: $wheelhouse: no such directory (build one with systemd/wheelhouse.sh)" >&2; exit 2; }
wheelhouse=$(cd "$wheelhouse" && pwd)
set -- "$wheelhouse"/millsense-*.whl
[ -f "$1" ] || { echo "$0: $wheelhouse holds no millsense wheel: not a wheelhouse from systemd/wheelhouse.sh" >&2; exit 2; }
[ $# -eq 1 ] || { echo "$0: $wheelhouse holds $# millsense wheels: keep the one to install" >&2; exit 2; }
wheel=$1
[ -f "$wheelhouse/requirements.txt" ] || { echo "$0: $wheelhouse/requirements.txt: missing (systemd/wheelhouse.sh writes it)" >&2; exit 2; }
case $venv in /*) ;; *) venv=$(pwd)/$venv ;; esac

if [ ! -x "$venv/bin/python" ]; then
    command -v "$python" >/dev/null || fail "$python: not found (PYTHON=... names the Python for the venv)"
    echo "making the venv $venv with $python"
    "$python" -m venv "$venv"
fi

log=$(mktemp)
trap 'rm -f "$log"' EXIT
echo "installing from $wheelhouse into $venv (no index)"
if ! "$venv/bin/python" -m pip install --disable-pip-version-check --no-index --find-links "$wheelhouse" \
        -q -r "$wheelhouse/requirements.txt" >"$log" 2>&1; then
    grep '^ERROR' "$log" >&2 || tail -n 20 "$log" >&2
    missing=$(sed -n 's/^ERROR: No matching distribution found for \(.*\)$/\1/p' "$log" | head -n 1)
    [ -n "$missing" ] || fail "pip could not install from $wheelhouse (its errors above); $venv may be half-installed: run again with a good wheelhouse"
    # Which Python and platform the box is, and what the wheelhouse was made for.
    here=$("$venv/bin/python" -c 'import platform, sys, sysconfig
libc, ver = platform.libc_ver()
tag = f"manylinux_{ver.replace(chr(46), chr(95))}_{platform.machine()}" if libc == "glibc" else sysconfig.get_platform()
print("%d.%d %s" % (*sys.version_info[:2], tag))')
    built=$(sed -n 's/^built for: //p' "$wheelhouse/README.txt" 2>/dev/null)
    fail "$wheelhouse has no wheel of $missing for this box (Python ${here% *}, ${here#* })${built:+; it was built for $built}. On a connected machine: systemd/wheelhouse.sh DIR --python-version ${here% *} --platform ${here#* }"
fi
"$venv/bin/python" -m pip install --disable-pip-version-check --no-index --no-deps --force-reinstall -q "$wheel"
# The unit runs Python with -OO (PYTHONOPTIMIZE=2) and cannot write to the venv: its -OO bytecode is
# compiled here, once, or every start of the daemon compiles it again in memory (docs/install.md).
"$venv/bin/python" -OO -m compileall -q -j 0 "$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" >/dev/null ||
    echo "$0: warning: compiling the -OO bytecode failed; the daemon compiles it at each start instead" >&2
"$venv/bin/millsense" --version

if [ -n "$bindir" ]; then
    link=$bindir/millsense
    if [ -e "$link" ] && [ ! -L "$link" ]; then
        fail "$link exists and is not a link (another install?): remove it, then run this again"
    fi
    mkdir -p "$bindir"
    ln -sfn "$venv/bin/millsense" "$link"
    echo "linked $link -> $venv/bin/millsense"
fi
echo "next: systemd/install.sh MACHINE CONFIG.toml (docs/install.md)"
