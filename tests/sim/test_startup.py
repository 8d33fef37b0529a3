"""`millsense sim` never imports scipy.signal (about 0.8 CPU s) nor scipy.optimize (0.4): its filters are numpy
alone (sim/lti.py), the cutting effects' fit its own bisection (sim/cut_effects.py). The suite starts hundreds of
emulators and capture builds (docs/testing.md); and an import in the middle of a stream is a pause a real DAQ
never makes: scipy.optimize came at a first-part plant's first tool change, 0.27 s of one block on a quiet box,
past the daemon's 1-s stall check on a loaded one (its DAQ watchdog then held the feed for the rest of the part)."""

from __future__ import annotations

import subprocess
import sys

import pytest

# run the CLI in-process, then say which of the named modules were imported; SystemExit is argparse's exit
PROBE = """
import sys
from millsense.daemon.cli import main
try:
    code = main(sys.argv[2:])
except SystemExit as exc:
    code = exc.code
print(*(name in sys.modules for name in sys.argv[1].split(",")), code, file=sys.stderr)
"""


def _imported(modules: tuple[str, ...], *args: str) -> tuple[bool, ...]:
    p = subprocess.run([sys.executable, "-c", PROBE, ",".join(modules), *args], capture_output=True, text=True,
                       timeout=120)
    last = p.stderr.strip().splitlines()[-1].split()
    return tuple(word == "True" for word in last[:len(modules)])


@pytest.mark.parametrize("args", [["sim", "--help"], ["sim", "--scenario", "ramp", "--duration-s", "0.1", "--capture"],
                                  ["sim", "--scenario", "no-such-scenario", "--capture"],
                                  ["sim", "--scenario", "step", "--duration-s", "0.1", "--capture"],
                                  ["sim", "--scenario", "first-part-slot", "--duration-s", "1", "--capture"]],
                         ids=["help", "ramp", "refused", "filtering-plant", "cutting-effects-at-a-tool-change"])
def test_no_sim_imports_scipy_signal_or_optimize(tmp_path, args):
    if args[-1] == "--capture":
        args = [*args, str(tmp_path / "c.bin")]
    # the probe sees an import where there is one: numpy, which `sim` always imports (the positive control)
    assert _imported(("scipy.signal", "scipy.optimize", "numpy"), *args) == (False, False, True)
