"""Fixtures shared by the test folders: the firmware and the simulator harness, built once."""

from __future__ import annotations

import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hilswarm.agents.link.simavr import firmware_dir

#: Where Debian's libsimavr-dev (or a local build) puts the simulator headers.
SIMAVR_HEADERS = ("/usr/include/simavr/sim_avr.h", "/usr/local/include/simavr/sim_avr.h")


def toolchain_missing() -> str | None:
    """Why the firmware cannot be built here (``None`` when it can)."""
    if shutil.which("avr-gcc") is None:
        return "avr-gcc not installed (apt install gcc-avr avr-libc arduino-core-avr)"
    if not any(Path(p).exists() for p in SIMAVR_HEADERS):
        return "libsimavr headers not installed (apt install libsimavr-dev)"
    return None


@pytest.fixture(scope="session")
def firmware_built() -> Path:
    """The firmware folder with the Uno build and the simavr harness in it, up to date (make
    rebuilds what changed: a harness built before a new control command would fail its test).
    """
    reason = toolchain_missing()
    if reason is not None:
        pytest.skip(reason)
    root = firmware_dir()
    result = subprocess.run(  # incremental: a no-op when everything is up to date
        ["make", "-s", "-C", str(root), "all"],
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert result.returncode == 0, f"make -C firmware all failed:\n{result.stderr[-3000:]}"
    return root


@pytest.fixture(scope="module")
def benchmarks_on_path() -> Iterator[Path]:
    """The benchmarks folder on ``sys.path`` for one test module, so that its scripts import
    as modules (``import swarm_ticks``)."""
    folder = Path(__file__).resolve().parents[1] / "benchmarks"
    sys.path.insert(0, str(folder))
    try:
        yield folder
    finally:
        sys.path.remove(str(folder))
