"""Lowering a helper process's CPU priority: its niceness and its session's autogroup's.

Each case runs in a child process of its own session (a lowered priority cannot be raised
again by an unprivileged process, and the autogroup is the session's)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.orchestrator.cpu_priority import AUTOGROUP, autogroup_niceness, parse_autogroup

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
    # An int, or None: no autogroup, or the root autogroup (a test run whose session began
    # with the container, which the kernel shows as an empty file).
    group = autogroup_niceness(os.getpid())
    assert group is None or isinstance(group, int)


@pytest.mark.skipif(not HAS_AUTOGROUP, reason="this kernel has no autogroup scheduling")
def test_a_new_session_reads_an_autogroup_of_its_own() -> None:
    out = run_child(
        "import os\n"
        "from hilswarm.orchestrator.cpu_priority import autogroup_niceness\n"
        "print(autogroup_niceness(os.getpid()))\n"
    )
    assert out.lstrip("-").isdigit()


@pytest.mark.parametrize(
    ("text", "niceness"),
    [("/autogroup-28616 nice 0\n", 0), ("/autogroup-7 nice 10\n", 10),
     ("/autogroup-7 nice -5\n", -5), ("", None), ("\n", None)],
)  # fmt: skip
def test_the_kernel_autogroup_line_is_parsed(text: str, niceness: int | None) -> None:
    assert parse_autogroup(text) == niceness


@pytest.mark.parametrize("text", ["nice 10", "/autogroup-7 nice ten", "/autogroup-7\n"])
def test_anything_else_in_an_autogroup_file_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="not an autogroup line"):
        parse_autogroup(text)


def test_the_root_autogroup_keeps_the_niceness_alone(tmp_path: Path) -> None:
    # The root autogroup reads as an empty file, and the kernel refuses a niceness for it
    # (EINVAL): the niceness alone counts there, so nothing is written and nothing fails.
    root = tmp_path / "autogroup"
    root.write_text("")
    out = run_child(
        "import os\n"
        "from pathlib import Path\n"
        "from hilswarm.orchestrator.cpu_priority import lower_own_priority\n"
        "before = os.getpriority(os.PRIO_PROCESS, 0)\n"
        f"new = lower_own_priority(2, autogroup=Path({str(root)!r}))\n"
        "print(before, new)\n"
    )
    before, new = (int(word) for word in out.split())
    assert new == min(19, before + 2)
    assert root.read_text() == ""


def test_an_autogroup_file_in_an_unknown_form_is_reported(tmp_path: Path) -> None:
    odd = tmp_path / "autogroup"
    odd.write_text("something else\n")
    out = run_child(
        "from pathlib import Path\n"
        "from hilswarm.orchestrator.cpu_priority import PriorityError, lower_own_priority\n"
        "try:\n"
        f"    lower_own_priority(1, autogroup=Path({str(odd)!r}))\n"
        "except PriorityError as exc:\n"
        "    print('PriorityError', exc)\n"
    )
    assert out.startswith("PriorityError autogroup niceness")
    assert "not an autogroup line" in out
