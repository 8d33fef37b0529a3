"""`millsense sim` imports scipy.signal (about 0.8 CPU s) only when it builds a filter: the emulator's ramp,
`--help` and a refused argument start without it (the suite starts hundreds of emulators; docs/testing.md)."""

from __future__ import annotations

import subprocess
import sys

import pytest

# run the CLI in-process, then say whether scipy.signal was imported; SystemExit is argparse's exit
PROBE = """
import sys
from millsense.daemon.cli import main
try:
    code = main(sys.argv[1:])
except SystemExit as exc:
    code = exc.code
print("scipy.signal" in sys.modules, code, file=sys.stderr)
"""


def _imports_scipy_signal(*args: str) -> bool:
    p = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, timeout=120)
    last = p.stderr.strip().splitlines()[-1]
    return last.split()[0] == "True"


@pytest.mark.parametrize("args", [["sim", "--help"], ["sim", "--scenario", "ramp", "--duration-s", "0.1", "--capture"],
                                  ["sim", "--scenario", "no-such-scenario", "--capture"]],
                         ids=["help", "ramp", "refused"])
def test_a_sim_that_never_filters_does_not_import_scipy_signal(tmp_path, args):
    if args[-1] == "--capture":
        args = [*args, str(tmp_path / "c.bin")]
    assert not _imports_scipy_signal(*args)


def test_a_plant_that_filters_does(tmp_path):
    # the probe itself can see the import (the test above cannot pass for want of a plant)
    assert _imports_scipy_signal("sim", "--scenario", "step", "--duration-s", "0.1",
                                 "--capture", str(tmp_path / "c.bin"))
