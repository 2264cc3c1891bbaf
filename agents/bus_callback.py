"""Bus callbacks run on Zenoh's own threads, each of which keeps its Python thread state.

zenoh-python runs a callback declared with ``indirect=False`` on the Zenoh thread that received
the message, through PyO3, which takes the GIL with ``PyGILState_Ensure`` and gives it back
with ``PyGILState_Release``. On a thread that Python did not start, the first *creates* a
Python thread state and the second *deletes* it again as its count drops to zero (PyO3 issue
#2495). So every message paid for a new thread state: a ``gettid`` system call, a 16 KiB frame
stack mapped and unmapped again (``munmap`` interrupts the other cores the process runs on, to
flush their TLBs) and the interpreter's bookkeeping of a thread that comes and goes. Seen with
``strace`` in a lockstep run of 8 agents: one ``mmap``/``munmap`` pair per message, in every
agent and in the orchestrator (docs/running.md, Levers).

:func:`callback` wraps a function so that, the first time it runs on a thread, it takes one
more reference with ``PyGILState_Ensure`` and never gives it back: the thread state then lives
as long as the thread, and PyO3's own Ensure and Release only take and give back the GIL
(what Pants and Sail do for their Rust worker threads). A thread Python started keeps its
state anyway; the extra reference changes nothing there.

What it costs: one thread state and one frame stack per Zenoh thread that ever ran a callback
(the lean runtime, :data:`hilswarm.agents.bus.LEAN_RUNTIME`, receives on one thread), and a
check of a thread-local flag per message. A session's callbacks must not outlive the
interpreter, with or without this: every hilswarm process closes its sessions before it exits.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable
from typing import TypeVar

import zenoh

__all__ = ["callback"]

_T = TypeVar("_T")

_ensure = ctypes.pythonapi.PyGILState_Ensure  # a PyDLL function: called with the GIL held
_ensure.restype = ctypes.c_int
_ensure.argtypes = []
_kept = threading.local()  # per thread state: empty again whenever the state was new


def _keep_thread_state() -> None:
    _ensure()  # one reference more, never released: the state outlives this callback
    _kept.kept = True


def callback(function: Callable[[_T], object]) -> zenoh.handlers.Callback:
    """``function`` as a Zenoh callback handler run on Zenoh's receiving thread
    (``indirect=False``) that keeps that thread's Python thread state (module docstring).

    The function must be short and never block, as every hilswarm bus callback: decode, hand
    off to a thread, or store a value.
    """

    def run(argument: _T) -> None:
        if not getattr(_kept, "kept", False):
            _keep_thread_state()
        function(argument)

    return zenoh.handlers.Callback(run, indirect=False)
