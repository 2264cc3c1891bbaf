"""Lowering a helper process's CPU priority so that it really yields to the ticks.

``os.nice`` alone is not enough on Linux with *autogroup* scheduling
(``/proc/sys/kernel/sched_autogroup_enabled`` = 1, the default of Debian's and most
distributions' kernels). The scheduler then first shares the CPU between *sessions* (one
autogroup each), equally, and a process's niceness only weighs it against the processes of its
own session. hilswarm starts the recorder (like every agent) in a session of its own, so a
niced recorder still got a whole session's share against each agent: measured on one core, a
niced busy process in its own session beside a plain one got 50 % of the CPU; with its
autogroup niced as well, 10 %.

:func:`lower_own_priority` therefore raises both: the process's niceness and its autogroup's
(``/proc/self/autogroup``, which only this process's session shares — call it only in a
process that leads a session of its own). On kernels without autogroup the second step is
skipped, and so it is for a process in the *root* autogroup (the one of processes whose
session began before autogroup existed, e.g. a container's first process that never called
``setsid``): the kernel shows it as an empty file, refuses a niceness for it, and schedules its
processes against each other by niceness alone. On any other failure the first step still
holds and the caller is told.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

#: The autogroup (session scheduling group) of the calling process.
AUTOGROUP = Path("/proc/self/autogroup")


class PriorityError(OSError):
    """The CPU priority could not be lowered (fully); the message says which step failed."""


def lower_own_priority(increment: int, *, autogroup: Path = AUTOGROUP) -> int:
    """Add ``increment`` to this process's niceness, and set its autogroup's niceness to the
    result when the kernel schedules by autogroup. Returns the process's new niceness.

    Raises:
        PriorityError: a step failed (the niceness, or the autogroup's: a process whose
            niceness did rise but whose autogroup did not still competes as a whole session).
    """
    try:
        niceness = os.nice(increment)
    except OSError as exc:
        raise PriorityError(f"os.nice({increment}): {exc}") from exc
    try:
        if parse_autogroup(autogroup.read_text()) is None:
            return niceness  # the root autogroup: the niceness is all there is
        autogroup.write_text(f"{niceness}\n")
    except FileNotFoundError:
        return niceness  # a kernel built without autogroup: the niceness is all there is
    except (OSError, ValueError) as exc:
        raise PriorityError(f"autogroup niceness ({autogroup}): {exc}") from exc
    return niceness


#: What the kernel shows of an autogroup: "/autogroup-1234 nice 10".
AUTOGROUP_LINE = re.compile(r"/autogroup-\d+ nice (-?\d+)")


def parse_autogroup(text: str) -> int | None:
    """The niceness in the text of a ``/proc/PID/autogroup`` file; ``None`` for an empty one
    (the root autogroup, which the kernel does not show and in which niceness alone counts).

    Raises:
        ValueError: the text is neither empty nor the kernel's one line.
    """
    if not text.strip():
        return None
    match = AUTOGROUP_LINE.fullmatch(text.strip())
    if match is None:
        raise ValueError(f"not an autogroup line: {text.strip()!r}")
    return int(match.group(1))


def autogroup_niceness(pid: int) -> int | None:
    """The niceness of process ``pid``'s autogroup (``None``: no autogroup on this kernel, or
    the process is in the root autogroup).

    Raises:
        ProcessLookupError: no process ``pid``.
    """
    if not Path(f"/proc/{pid}").is_dir():
        raise ProcessLookupError(f"no process {pid}")
    try:
        text = Path(f"/proc/{pid}/autogroup").read_text()
    except FileNotFoundError:
        return None
    return parse_autogroup(text)
