"""Lowering a helper process's CPU priority: its niceness and its session's autogroup's.

Each case runs in a child process of its own session (a lowered priority cannot be raised
again by an unprivileged process, and the autogroup is the session's)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.orchestrator.cpu_priority import AUTOGROUP, autogroup_niceness

HAS_AUTOGROUP = AUTOGROUP.exists()


def run_child(code: str) -> str:
    """``code`` in a new session; returns its standard output (fails on a non-zero exit)."""
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
        start_new_session=True, stdin=subprocess.DEVNULL, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


@pytest.mark.skipif(not HAS_AUTOGROUP, reason="this kernel has no autogroup scheduling")
def test_the_niceness_and_the_autogroup_are_lowered_together() -> None:
    out = run_child(
        "import os\n"
        "from hilswarm.orchestrator.cpu_priority import lower_own_priority, autogroup_niceness\n"
        "before = os.getpriority(os.PRIO_PROCESS, 0)\n"
        "new = lower_own_priority(5)\n"
        "print(before, new, os.getpriority(os.PRIO_PROCESS, 0), autogroup_niceness(os.getpid()))\n"
    )
    before, new, now, group = (int(word) for word in out.split())
    assert new == now == min(19, before + 5)
    assert group == new


def test_a_kernel_without_autogroup_keeps_the_niceness_alone(tmp_path: Path) -> None:
    missing = tmp_path / "no-such-dir" / "autogroup"
    out = run_child(
        "import os\n"
        "from pathlib import Path\n"
        "from hilswarm.orchestrator.cpu_priority import lower_own_priority\n"
        "before = os.getpriority(os.PRIO_PROCESS, 0)\n"
        f"new = lower_own_priority(3, autogroup=Path({str(missing)!r}))\n"
        "print(before, new)\n"
    )
    before, new = (int(word) for word in out.split())
    assert new == min(19, before + 3)


def test_an_autogroup_that_cannot_be_written_is_reported(tmp_path: Path) -> None:
    directory = tmp_path / "autogroup"
    directory.mkdir()  # writing a directory as a file fails (IsADirectoryError, an OSError)
    out = run_child(
        "from pathlib import Path\n"
        "from hilswarm.orchestrator.cpu_priority import PriorityError, lower_own_priority\n"
        "try:\n"
        f"    lower_own_priority(1, autogroup=Path({str(directory)!r}))\n"
        "except PriorityError as exc:\n"
        "    print('PriorityError', exc)\n"
    )
    assert out.startswith("PriorityError autogroup niceness")


def test_autogroup_niceness_of_a_missing_process_raises() -> None:
    with pytest.raises(ProcessLookupError):
        autogroup_niceness(2**22 + 12345)  # above pid_max's default ceiling


def test_this_process_reads_its_own_autogroup() -> None:
    group = autogroup_niceness(os.getpid())
    assert group is None if not HAS_AUTOGROUP else isinstance(group, int)
