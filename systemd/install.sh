#!/bin/sh
# Install one machine's configuration for millsense@MACHINE, with the owners and modes
# docs/security.md asks for:
#   /etc/millsense/              root:millsense 0750  (the daemon reads, cannot write)
#   /etc/millsense/MACHINE.toml  root:millsense 0640  (not readable by other users)
#   the reset token file it names (reset_token_file, relative to /etc/millsense)
#                                millsense:millsense 0600, made by `millsense token new`
#                                if it does not exist yet (an existing token is kept)
#   /etc/millsense/tls/          root:millsense 0750 (certificates and keys: put them there 0640)
# then runs `millsense check-config` and, unless --no-start, enables and starts the unit.
#
# Usage (as root, after millsense itself, the unit and the sysusers file are installed;
# docs/install.md, also for a box with no package index: systemd/install-offline.sh):
#   systemd/install.sh MACHINE path/to/config.toml [--no-start]
# ETC=/some/dir overrides /etc/millsense (for a trial run); MILLSENSE=... the CLI to use.
set -eu

if [ $# -lt 2 ]; then
    echo "usage: $0 MACHINE CONFIG.toml [--no-start]" >&2
    exit 2
fi
machine=$1
config=$2
start=yes
[ "${3:-}" = "--no-start" ] && start=no
etc=${ETC:-/etc/millsense}
millsense=${MILLSENSE:-millsense}

case $machine in
    *[!A-Za-z0-9._-]*|'') echo "$0: machine name '$machine': letters, digits, . _ - only" >&2; exit 2 ;;
esac
[ -f "$config" ] || { echo "$0: $config: no such file" >&2; exit 2; }
command -v "$millsense" >/dev/null || {
    echo "$0: $millsense: not found: install millsense first (docs/install.md; offline: systemd/install-offline.sh WHEELHOUSE)" >&2
    exit 2
}
getent group millsense >/dev/null || systemd-sysusers /usr/lib/sysusers.d/millsense.conf

# The unit's Documentation= (file:///usr/share/doc/millsense/README.md): the README and docs/
# of the source tree or wheelhouse this script came from. DOC=/some/dir overrides the place.
doc=${DOC:-/usr/share/doc/millsense}
tree=$(dirname "$0")/..
if [ -f "$tree/README.md" ]; then
    (umask 022; install -d "$doc" && cp "$tree/README.md" "$doc/" && { [ ! -d "$tree/docs" ] || cp -R "$tree/docs" "$doc/"; })
fi

umask 077
install -d -o root -g millsense -m 0750 "$etc" "$etc/tls"
install -o root -g millsense -m 0640 "$config" "$etc/$machine.toml"

# The token file the config names, if any (a relative path is taken from the config's folder).
token=$(python3 -c 'import sys, tomllib; print(tomllib.load(open(sys.argv[1], "rb")).get("interlock", {}).get("reset_token_file") or "")' "$etc/$machine.toml")
if [ -n "$token" ]; then
    case $token in /*) ;; *) token="$etc/$token" ;; esac
    if [ ! -e "$token" ]; then
        "$millsense" token new --out "$token"
        echo "made a new reset token in $token: copy it to the operator consoles over a trusted channel"
    fi
    chown millsense:millsense "$token"
    chmod 0600 "$token"
fi

"$millsense" check-config "$etc/$machine.toml"
if [ $start = yes ]; then
    systemctl enable --now "millsense@$machine"
fi
