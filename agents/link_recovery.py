"""Riding out a board link fault: reconnect, bounded by the link's timeout, and what the
agent's tick ledger reads from the link.

A board link fault (a stall, an unplugged cable: :data:`LINK_FAULTS`) does not end an agent at
once. Its worker calls :func:`reconnect_within`, which retries ``board.reconnect()`` (the
handshake and the pin configuration again) every :data:`RECONNECT_PAUSE_S` until it succeeds
or the link's timeout (``Board.link_timeout_s``) has passed, and gives up at once when the
agent is told to quit. The agent's lifecycle (``degraded``, ``recover``, ``safe``) stays the
agent's business.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from hilswarm.agents.agent_counters import board_count
from hilswarm.agents.errors import (
    BoardConnectionError,
    BoardError,
    BoardTimeoutError,
    HilswarmError,
)

#: Board errors that mean the link failed (as opposed to a request the board refused).
LINK_FAULTS = (BoardTimeoutError, BoardConnectionError)
#: Pause between two reconnection attempts of a faulty board link [s].
RECONNECT_PAUSE_S = 0.1


class QuitRequestedError(HilswarmError, RuntimeError):
    """The agent was told to quit while its board link was down."""


def reconnect_within(
    board: Any,
    timeout_s: float,
    fault: BoardError,
    quitting: threading.Event,
    clock: Callable[[], float],
) -> int:
    """Reconnect ``board`` after ``fault``, for at most ``timeout_s`` [s]; returns the attempts.

    Args:
        board: the board link (``reconnect()`` raises one of :data:`LINK_FAULTS` while the
            link is down).
        timeout_s: how long to keep trying [s], from the first attempt.
        fault: the fault that took the link down (named when giving up).
        quitting: set when the agent must finish; also the pause between attempts.
        clock: the agent's monotonic clock [s].

    Raises:
        BoardConnectionError: the link is not back within ``timeout_s``.
        QuitRequestedError: ``quitting`` was set.
    """
    start = clock()
    last: BoardError = fault
    attempts = 0
    while True:
        if quitting.is_set():
            raise QuitRequestedError(f"stopped while the board link was down: {last}")
        attempts += 1
        try:
            board.reconnect()
            return attempts
        except LINK_FAULTS as exc:
            last = exc
        if clock() - start >= timeout_s:
            raise BoardConnectionError(
                f"board link not back within {timeout_s:g} s ({attempts} attempts): {last}"
            ) from last
        if quitting.wait(RECONNECT_PAUSE_S):
            raise QuitRequestedError(f"stopped while the board link was down: {last}")


def link_retries(board: Any) -> int:
    """Re-sends of board requests so far (0 for links that do not count them)."""
    return board_count(board, "retries")


def link_stages(board: Any, exchanged: bool) -> tuple[float, float] | tuple[()]:
    """``(gateway_s, radio_s)`` [s] of the tick's link round trip for a link through the XBee
    gateway (``take_link_stages``; 0 when the tick made no exchange: tick 0 senses what
    ``connect`` primed), ``()`` for other links (no gateway stage in the ledger)."""
    take = getattr(board, "take_link_stages", None)
    if take is None:
        return ()
    stages = take()
    return stages if exchanged else (0.0, 0.0)
