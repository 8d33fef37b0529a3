"""The core cross-compiles and links for two Cortex-M cores (Debian's gcc-arm-none-eabi), freestanding: the
only symbols it leaves undefined are the hardware interface a board implements, and string.h."""

from __future__ import annotations

import os
import re
import shutil
import subprocess

import pytest

from tests.firmware.conftest import FIRMWARE

HARDWARE_INTERFACE = {"ms_hw_read_sample", "ms_hw_write_outputs", "ms_hw_write_override", "ms_hw_read_cnc",
                      "ms_hw_tx", "ms_hw_rx", "ms_hw_millis", "ms_hw_event"}
STRING_H = {"memcpy", "memmove", "memset"}


def _missing(message: str) -> None:
    if os.environ.get("CI") == "true":
        pytest.fail(message)
    pytest.skip(message)


def test_the_core_links_for_cortex_m0plus_and_m4_needing_only_the_hardware_interface(tmp_path):
    if shutil.which("arm-none-eabi-gcc") is None:
        _missing("the cross build needs arm-none-eabi-gcc (Debian: gcc-arm-none-eabi)")
    header = subprocess.run(["arm-none-eabi-gcc", "-ffreestanding", "-E", "-x", "c", "-"], input="#include <string.h>\n",
                            capture_output=True, text=True, timeout=60)
    if header.returncode != 0:
        _missing("the cross build needs string.h for arm-none-eabi (Debian: libnewlib-arm-none-eabi)")
    p = subprocess.run(["make", "-C", str(FIRMWARE), f"BUILD={tmp_path}", "cross"], capture_output=True, text=True,
                       timeout=300)
    print(p.stdout)   # the sizes, for whoever reads the log
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    for cpu in ("cortex-m0plus", "cortex-m4"):
        undefined = set((tmp_path / "arm" / cpu / "undefined.txt").read_text().split())
        assert HARDWARE_INTERFACE <= undefined <= HARDWARE_INTERFACE | STRING_H, (cpu, undefined)
        assert (tmp_path / "arm" / cpu / "firmware.elf").stat().st_size > 0
        # arm-none-eabi-size's line for the linked image: text, data, bss; the device is one static object
        m = re.search(rf"^\s*(\d+)\s+(\d+)\s+(\d+)\s+\d+\s+\w+\s+\S*{cpu}/firmware\.elf$", p.stdout, re.M)
        assert m, p.stdout
        text, data, bss = (int(x) for x in m.groups())
        assert 0 < text < 16384 and bss > 0, (cpu, text, data, bss)
