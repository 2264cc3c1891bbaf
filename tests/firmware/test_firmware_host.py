"""The firmware's protocol code built for the host, and the firmware's size budget.

* ``make -C firmware host-test``: the C++ parser, frame builder, request validation and engine,
  compiled with AddressSanitizer + UndefinedBehaviorSanitizer, checked against the golden vectors
  shared with the Python codec (``firmware/protocol/golden_vectors.json``) and fed a bounded,
  seeded random fuzz loop (200 000 frames).
* ``make -C firmware size``: flash and static RAM of the Uno and Fio builds must stay well inside
  the ATmega328P (32 KiB flash, 2 KiB RAM).

Skipped, with the missing tool named, only when the toolchain is absent on a developer machine;
under CI (``CI`` set in the environment) a missing toolchain is a failure, never a skip.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.firmware

FIRMWARE_DIR = Path(__file__).resolve().parents[2] / "firmware"

#: Budgets "well inside" the ATmega328P: half the flash, half the RAM (the rest is stack).
FLASH_BUDGET_BYTES = 16 * 1024
RAM_BUDGET_BYTES = 1024
#: Boards whose size is checked (Duemilanove flashes the Uno build).
BOARDS = ("uno", "fio")

SIZE_LINE = re.compile(
    r"^(?P<board>\w+): flash (?P<flash>\d+) / (?P<flash_max>\d+) bytes .*?"
    r"static RAM (?P<ram>\d+) / (?P<ram_max>\d+) bytes",
    re.MULTILINE,
)

HOST_TOOLS = ("make", "g++")
AVR_TOOLS = ("make", "avr-gcc", "avr-g++", "avr-size", "avr-objcopy")


def require_tools(tools: tuple[str, ...]) -> None:
    """Skip (developer machine) or fail (CI) when a tool in ``tools`` is not on PATH."""
    missing = [tool for tool in tools if shutil.which(tool) is None]
    if not missing:
        return
    reason = (
        f"firmware toolchain missing: {', '.join(missing)} "
        "(install with `bash scripts/setup.sh`: gcc-avr avr-libc arduino-core-avr)"
    )
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI must install it")
    pytest.skip(reason)


def run_make(*targets: str, timeout_s: float) -> subprocess.CompletedProcess[str]:
    """Run ``make -C firmware <targets>`` and return the finished process (output captured)."""
    return subprocess.run(
        ["make", "--no-print-directory", "-C", str(FIRMWARE_DIR), *targets],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
    )


def tail(text: str, lines: int = 40) -> str:
    """The last ``lines`` lines of ``text`` (for assertion messages)."""
    return "\n".join(text.splitlines()[-lines:])


@pytest.mark.timeout(900)
def test_host_build_of_protocol_code_passes_vectors_and_fuzz() -> None:
    require_tools(HOST_TOOLS)
    result = run_make("host-test", timeout_s=840)
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"make host-test failed:\n{tail(output)}"
    assert re.search(r"host-test: \d+ checks, 0 failures", output), tail(output)
    assert re.search(r"golden vectors: \d+ ", output), "golden vectors were not checked"
    assert re.search(r"fuzz: 200000 frames", output), "the fuzz loop did not run in full"


@pytest.mark.timeout(600)
def test_firmware_fits_well_inside_the_atmega328p() -> None:
    require_tools(AVR_TOOLS)
    result = run_make("size", timeout_s=540)
    output = result.stdout + result.stderr
    assert result.returncode == 0, f"make size failed:\n{tail(output)}"
    sizes = {m["board"]: m for m in SIZE_LINE.finditer(result.stdout)}
    assert set(BOARDS) <= set(sizes), f"size lines for {BOARDS} expected in:\n{tail(output)}"
    for board in BOARDS:
        flash, flash_max = int(sizes[board]["flash"]), int(sizes[board]["flash_max"])
        ram, ram_max = int(sizes[board]["ram"]), int(sizes[board]["ram_max"])
        assert flash <= min(FLASH_BUDGET_BYTES, flash_max), (
            f"{board}: flash {flash} bytes exceeds the budget {FLASH_BUDGET_BYTES}"
        )
        assert ram <= min(RAM_BUDGET_BYTES, ram_max), (
            f"{board}: static RAM {ram} bytes exceeds the budget {RAM_BUDGET_BYTES}"
        )
