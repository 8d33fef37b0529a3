"""What the live daemon loads (issue 13: RSS ≤ 70 MB): every module imported stays resident for the
process's life, so the run path imports only what it uses, and bounds native memory before numpy."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from tests.conftest import free_tcp_port
from tests.e2e.helpers import Procs, tcp, write_config

# Subcommands and extras that run as processes of their own, never inside `millsense run`.
NOT_ON_THE_RUN_PATH = (
    "scipy",                               # calibration only; scipy.optimize alone cost 45 MB
    "matplotlib",                          # replay --plot
    "asyncua",                             # `millsense opcua`
    "millsense.daemon.opcua",
    "millsense.daemon.dashboard",          # `millsense dashboard`
    "http.server",
    "millsense.sim.emulator",          # `millsense sim`
    "millsense.sim",
    "millsense.daemon.commands.replay",
    "millsense.daemon.commands.calibrate",
    "millsense.daemon.commands.capture_reader",   # a capture file: the offline commands' input
    "millsense.daemon.history.export",     # `millsense history`
    "serial",                              # pyserial and pymodbus: other transports than the one configured
    "pymodbus",
    # what the standard library and numpy load for a convenience the daemon does without (1.3 MB, 1.5 MB
    # and 0.4 MB): np.percentile's first call, parsing the package's own metadata for its version, and
    # the idna codec that `getaddrinfo` runs a str host through
    "numpy.ma",
    "email.parser",
    "encodings.idna",
)

# `millsense run`, writing at exit the modules it loaded and the OpenBLAS setting numpy saw.
_RUN_AND_LIST = r"""
import atexit, json, os, sys
out = sys.argv.pop(1)
def dump():
    with open(out, "w") as f:
        json.dump({"modules": sorted(sys.modules), "openblas": os.environ.get("OPENBLAS_NUM_THREADS")}, f)
atexit.register(dump)
sys.argv[0] = "millsense"
from millsense.daemon.cli import main
sys.exit(main())
"""


def _loaded(modules: list[str], prefix: str) -> list[str]:
    return [m for m in modules if m == prefix or m.startswith(prefix + ".")]


def test_the_live_daemon_loads_nothing_it_does_not_use(tmp_path):
    """A daemon on TCP with learning and history on (the defaults), run for a few seconds."""
    daq_port, z_port = free_tcp_port(), free_tcp_port()
    cfg = write_config(tmp_path / "d.toml", machine="imports-01",
                       daq=f'transport = "tcp"\nhost = "127.0.0.1"\ntcp_port = {daq_port}',
                       zenoh_listen=[tcp(z_port)])
    listing = tmp_path / "modules.json"
    env_without_blas = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    with Procs(tmp_path) as procs:
        procs.start("sim", ["sim", "--scenario", "step", "--tcp", f"127.0.0.1:{daq_port}", "--realtime",
                            "--watchdog-ms", "1000"])
        p = subprocess.run([sys.executable, "-c", _RUN_AND_LIST, str(listing), "run", "--config", str(cfg),
                            "--seconds", "3", "--connect-timeout", "30"],
                           capture_output=True, text=True, timeout=120, env=env_without_blas)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    seen = json.loads(listing.read_text())
    modules = seen["modules"]
    # the path under test is the whole one: history, learning and the local control socket were built
    for used in ("millsense.daemon.history.store", "millsense.daemon.learning.monitor",
                 "millsense.daemon.runtime.local_control", "millsense.drivers.tcp_driver", "zenoh"):
        assert used in modules, used
    loaded = {name: _loaded(modules, name) for name in NOT_ON_THE_RUN_PATH}
    assert not any(loaded.values()), {k: v for k, v in loaded.items() if v}
    # set by `run` before numpy was imported (OpenBLAS reads it once): no idle BLAS worker threads
    assert seen["openblas"] == "1"


def _python(code: str) -> str:
    """What a fresh interpreter prints running `code`."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_numpy_is_not_imported_before_run_starts():
    """`bound_native_memory` sets OPENBLAS_NUM_THREADS first thing in `run`; it only works if nothing
    on the way there (the CLI, the parser, the run module) has imported numpy already."""
    code = (
        "import sys\n"
        "from millsense.daemon.cli import build_parser\n"
        "build_parser(only='run')\n"
        "print(sorted(m for m in sys.modules if m == 'numpy' or m.startswith('numpy.')))\n"
    )
    assert _python(code) == "[]"


# Eight threads allocate at once; glibc's malloc_info then lists the arenas (one `<heap nr=..>` each).
_ARENAS_AFTER_EIGHT_THREADS = r"""
import ctypes, sys, threading
from millsense.daemon.commands import run
if sys.argv[2] == "bounded":
    run.bound_native_memory()
libc = ctypes.CDLL(None)
libc.malloc.restype = libc.fopen.restype = ctypes.c_void_p
libc.free.argtypes = libc.fclose.argtypes = [ctypes.c_void_p]
libc.malloc_info.argtypes = [ctypes.c_int, ctypes.c_void_p]
barrier = threading.Barrier(8)
def work():
    barrier.wait()
    for _ in range(2000):
        libc.free(libc.malloc(4096))
threads = [threading.Thread(target=work) for _ in range(8)]
for t in threads: t.start()
for t in threads: t.join()
fp = libc.fopen(sys.argv[1].encode(), b"w")
libc.malloc_info(0, fp)
libc.fclose(fp)
print(open(sys.argv[1]).read().count("<heap nr="))
"""


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's malloc arenas")
def test_the_daemon_keeps_to_two_malloc_arenas(tmp_path):
    """Without the bound each of the eight threads gets an arena of its own (glibc allows 8 a core);
    with it they share `MALLOC_ARENAS`."""
    def arenas(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", _ARENAS_AFTER_EIGHT_THREADS, str(tmp_path / mode), mode],
                             capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        return int(out.stdout)

    assert arenas("unbounded") > 2  # the check can see more than two
    assert arenas("bounded") <= 2


def test_the_run_command_is_the_one_imported():
    """`millsense run --help` builds only `run`'s arguments: the other subcommands' modules stay unloaded."""
    code = (
        "import sys\n"
        "from millsense.daemon.cli import COMMANDS, build_parser\n"
        "build_parser(only='run')\n"
        "print(sorted(m for name, (m, _) in COMMANDS.items() if name != 'run' and m in sys.modules))\n"
    )
    assert _python(code) == "[]"
