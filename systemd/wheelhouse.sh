#!/bin/sh
# Build a wheelhouse on a connected machine, for an edge box that reaches no package
# index (docs/install.md, "Offline"). DIR gets millsense's own wheel, a wheel of every
# dependency, requirements.txt (each one pinned), README.txt (what it was built for and
# the two commands to install it), and this systemd/ folder and the config/ examples,
# so the box needs nothing but DIR:
#   systemd/wheelhouse.sh DIR [--extra NAME]... [--python-version X.Y] [--platform TAG]...
#   (on the box)  sudo sh DIR/systemd/install-offline.sh DIR
#
# Without --python-version/--platform the wheels fit this machine (its Python, its
# platform; a dependency with no wheel is built here). For another box give its Python
# and platform: --python-version 3.11 --platform manylinux_2_36_x86_64 (2_36: the box's
# glibc, `ldd --version`); a manylinux_2_N tag also takes wheels made for older glibc.
# Only ready-made wheels are taken then (pip's --only-binary=:all:).
# PYTHON=... the Python (3.11 or later) whose pip builds and downloads; python3 if unset.
set -eu

usage() {
    echo "usage: $0 DIR [--extra NAME]... [--python-version X.Y] [--platform TAG]..." >&2
    exit 2
}
fail() { echo "$0: $*" >&2; exit 1; }

python=${PYTHON:-python3}
out=
extras=
pyver=
platforms=
while [ $# -gt 0 ]; do
    case $1 in
        --extra|--python-version|--platform) [ $# -ge 2 ] || usage ;;
    esac
    case $1 in
        --extra) extras="${extras:+$extras,}$2"; shift 2 ;;
        --python-version) pyver=$2; shift 2 ;;
        --platform) platforms="$platforms $2"; shift 2 ;;
        -h|--help) usage ;;
        -*) echo "$0: unknown option $1" >&2; usage ;;
        *) [ -z "$out" ] || usage; out=$1; shift ;;
    esac
done
out=$(printf '%s' "$out" | sed 's:/*$::')
[ -n "$out" ] || usage

case $pyver in
    ''|3.[0-9]|3.[0-9][0-9]) ;;
    *) echo "$0: --python-version '$pyver': give it as 3.11, 3.12, ..." >&2; exit 2 ;;
esac
for p in $platforms; do
    case $p in *[!A-Za-z0-9_.]*) echo "$0: --platform '$p': a wheel platform tag such as manylinux_2_36_x86_64" >&2; exit 2 ;; esac
done
# A wheelhouse is made whole or not at all: never mixed into an older one.
if [ -e "$out" ] && { [ ! -d "$out" ] || [ -n "$(ls -A "$out")" ]; }; then
    echo "$0: $out exists and is not an empty directory: remove it or name a new one" >&2
    exit 2
fi

src=$(cd "$(dirname "$0")/.." && pwd)
command -v "$python" >/dev/null || fail "$python: not found (PYTHON=... names the Python to use)"
new_enough=$("$python" -c 'import sys; print(int(sys.version_info >= (3, 11)))' 2>/dev/null) ||
    fail "$python does not run (PYTHON=... names the Python to use)"
[ "$new_enough" = 1 ] || fail "$python is older than 3.11, which millsense needs: set PYTHON=python3.11 (or later)"

# An unknown extra is only a warning to pip, and the wheelhouse would silently lack it.
if [ -n "$extras" ]; then
    "$python" - "$src/pyproject.toml" "$extras" <<'EOF' || exit 2
import sys, tomllib
known = tomllib.load(open(sys.argv[1], "rb"))["project"].get("optional-dependencies", {})
unknown = [e for e in sys.argv[2].split(",") if e not in known]
if unknown:
    sys.exit(f"wheelhouse.sh: --extra {', '.join(unknown)}: millsense's extras are {', '.join(sorted(known))}")
EOF
fi

# manylinux_2_N_ARCH -> it and every older manylinux tag of ARCH: pip takes a --platform
# literally, and most wheels carry an older tag than the box's glibc.
expand_platform() {
    case $1 in
        manylinux_2_[0-9]*_*)
            rest=${1#manylinux_2_}
            minor=${rest%%_*}
            arch=${rest#*_}
            case $minor in *[!0-9]*) echo "$1"; return ;; esac
            while [ "$minor" -ge 5 ]; do
                echo "manylinux_2_${minor}_$arch"
                case $minor in
                    17) echo "manylinux2014_$arch" ;;
                    12) echo "manylinux2010_$arch" ;;
                    5) echo "manylinux1_$arch" ;;
                esac
                minor=$((minor - 1))
            done
            ;;
        *) echo "$1" ;;
    esac
}

tmp=$(mktemp -d)
mkdir -p "$(dirname "$out")"
work="$out.partial.$$"
trap 'rm -rf "$tmp" "$work"' EXIT
trap 'exit 130' INT TERM
mkdir "$work"

# Build from a clean copy: setuptools reuses build/ and *.egg-info in a source tree,
# so a module deleted since the last build could otherwise ride along in the wheel.
mkdir "$tmp/src"
tar -C "$src" -cf - --exclude=./.git --exclude=./.venv --exclude=./build --exclude=./dist \
    --exclude='*.egg-info' --exclude=__pycache__ --exclude=.pytest_cache --exclude=.hypothesis \
    --exclude=./bench/out --exclude='*.cap' . | tar -C "$tmp/src" -xf -

echo "building millsense's wheel"
"$python" -m pip wheel --disable-pip-version-check --no-deps -q -w "$work" "$tmp/src" >"$tmp/pip.log" 2>&1 ||
    { cat "$tmp/pip.log" >&2; fail "could not build millsense's wheel from $src (pip's output above)"; }
set -- "$work"/millsense-*.whl
[ $# -eq 1 ] && [ -f "$1" ] || fail "pip made no single millsense wheel in $work"
wheel=$1
requirement="$wheel${extras:+[$extras]}"

if [ -z "$pyver$platforms" ]; then
    target=$("$python" -c 'import platform, sys, sysconfig
libc, ver = platform.libc_ver()
print("Python %d.%d on %s%s" % (*sys.version_info[:2], sysconfig.get_platform(), f" (glibc {ver})" if libc == "glibc" else ""))')
    echo "fetching the dependencies for $target (this machine)"
    set -- wheel -w "$work"
else
    target="Python ${pyver:-$("$python" -c 'import sys; print("%d.%d" % sys.version_info[:2])')} on${platforms:- this machine's platform}"
    echo "fetching the dependencies for $target"
    set -- download -d "$work" --only-binary=:all:
    [ -z "$pyver" ] || set -- "$@" --python-version "$pyver"
    for p in $platforms; do
        for tag in $(expand_platform "$p"); do set -- "$@" --platform "$tag"; done
    done
fi
if ! "$python" -m pip "$@" --disable-pip-version-check -q "$requirement" >"$tmp/pip.log" 2>&1; then
    grep '^ERROR' "$tmp/pip.log" >&2 || tail -n 20 "$tmp/pip.log" >&2
    missing=$(sed -n 's/^ERROR: No matching distribution found for \(.*\)$/\1/p' "$tmp/pip.log" | head -n 1)
    if [ -n "$missing" ]; then
        fail "no wheel of $missing for $target: pick the box's Python and platform (docs/install.md), or build that wheel on a machine like the box; nothing written to $out"
    fi
    fail "pip could not fetch the dependencies for $target (its errors above); nothing written to $out"
fi

# requirements.txt pins exactly what is here; the box installs from it and nothing else.
version=$(basename "$wheel" | cut -d- -f2)
{
    echo "millsense${extras:+[$extras]}==$version"
    for w in "$work"/*.whl; do
        name=$(basename "$w" | cut -d- -f1)
        [ "$name" = millsense ] || echo "$name==$(basename "$w" | cut -d- -f2)"
    done
} >"$work/requirements.txt"

mkdir "$work/systemd" "$work/config"
cp "$src"/systemd/install*.sh "$src"/systemd/*.service "$src"/systemd/*.conf "$work/systemd/"
cp "$src"/config/* "$work/config/"
cp "$src"/README.md "$work/" && cp -R "$src"/docs "$work/docs"   # install.sh puts them where the unit's Documentation= points

cat >"$work/README.txt" <<EOF
millsense $version wheelhouse${extras:+ with the extras $extras}
built for: $target
built on:  $(date -u +%Y-%m-%dT%H:%MZ) by systemd/wheelhouse.sh

Install on the box (no network needed), as root; /opt/millsense is the venv and
/usr/local/bin/millsense the link the systemd unit runs:
    sh systemd/install-offline.sh .        # from inside this directory
or by hand:
    python3 -m venv /opt/millsense
    /opt/millsense/bin/pip install --no-index --find-links . -r requirements.txt

Then the service: systemd/install.sh MACHINE CONFIG.toml (docs/install.md, also in
this directory). config/ holds the example configurations.
EOF

[ ! -d "$out" ] || rmdir "$out"
mv "$work" "$out"
echo "wheelhouse ready: $out ($(ls "$out"/*.whl | wc -l) wheels, $(du -sh "$out" | cut -f1)); on the box: sh $out/systemd/install-offline.sh $out"
