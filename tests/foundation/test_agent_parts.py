"""The agent's parts of their own: its counters, its telemetry feed, its link recovery.

Closed-form tests, no bus and no processes (the agent's integration tests run them in a real
agent): a fake clock, a board whose ``reconnect`` fails a given number of times, and a
publisher that keeps what it is given, decoded with the bus's own decoder.
"""

from __future__ import annotations

import math
import threading
from types import SimpleNamespace

import numpy as np
import pytest
from hilswarm.agents import bus
from hilswarm.agents.agent_counters import COUNTERS_PERIOD_S, INPUT_KEYS, AgentCounters
from hilswarm.agents.errors import BoardConnectionError, BoardTimeoutError
from hilswarm.agents.link_recovery import (
    RECONNECT_PAUSE_S,
    QuitRequestedError,
    link_retries,
    link_stages,
    reconnect_within,
)
from hilswarm.agents.telemetry import Telemetry
from hilswarm.agents.telemetry_feed import DUPLICATE_CHANNELS, TelemetryFeed
from hilswarm.agents.tick_engine import TickEngine

DT = 0.01


def _counters() -> tuple[AgentCounters, TickEngine]:
    engine = TickEngine(("b",), ("a", "b"), DT, 1)
    return AgentCounters(engine, threading.Lock()), engine


# -- counters ---------------------------------------------------------------------------------


def test_counters_report_only_what_is_not_zero() -> None:
    counters, engine = _counters()
    assert counters.fields() == {}
    assert set(counters.malformed) == set(INPUT_KEYS)
    counters.count_malformed("y")
    counters.count_malformed("y")
    counters.skipped += 3
    counters.link_faults += 1
    engine.dropped["tick_ahead"] += 2
    engine.inputs_missing["b"] = [4, 5]
    counters.board = SimpleNamespace(stats=SimpleNamespace(stale_samples=7))
    assert counters.fields() == {
        "inputs_missing": {"b": [4, 5]},
        "malformed": {"y": 2},
        "dropped": {"tick_ahead": 2},
        "skipped": 3,
        "link_faults": 1,
        "stale_samples": 7,
    }
    # inputs_missing is taken by the status that reports it; the counts stay
    assert "inputs_missing" not in counters.fields()
    assert counters.fields()["skipped"] == 3


def test_a_counters_status_is_due_on_a_change_at_most_once_per_period() -> None:
    counters, engine = _counters()
    assert not counters.changed(0.0)  # nothing counted: no status
    counters.count_malformed("tick")
    assert not counters.changed(0.5 * COUNTERS_PERIOD_S)  # checked at 0.0: not yet
    assert counters.changed(COUNTERS_PERIOD_S)  # the change, reported once
    assert not counters.changed(2 * COUNTERS_PERIOD_S)  # no further change
    engine.stale += 1
    assert counters.changed(3 * COUNTERS_PERIOD_S)
    engine.inputs_missing["b"] = [30]  # pending ticks without inputs: due even unchanged
    assert counters.changed(4 * COUNTERS_PERIOD_S)


def test_counters_without_a_board_counter_read_zero() -> None:
    counters, _ = _counters()
    counters.board = object()  # a link that does not count stale samples
    assert counters.stale_samples() == 0 and counters.fields() == {}


# -- telemetry feed ---------------------------------------------------------------------------


class _Publisher:
    def __init__(self) -> None:
        self.messages: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.messages.append(payload)


def test_the_feed_publishes_new_rows_once_and_skips_duplicates() -> None:
    telemetry = Telemetry()
    pose = telemetry.add_channel("pose", ("x", "y"))
    y = telemetry.add_channel("y", ("v",))
    publisher = _Publisher()
    feed = TelemetryFeed(telemetry, publisher, now=10.0)
    assert "y" in DUPLICATE_CHANNELS
    assert feed.due == pytest.approx(10.0 + bus.TELEMETRY_PERIOD_S)
    pose.append(0, 0.0, [1.0, 2.0])
    pose.append(1, DT, [3.0, 4.0])
    y.append(0, 0.0, [9.0])
    assert feed.publish(10.3) == 2
    assert feed.due == pytest.approx(10.3 + bus.TELEMETRY_PERIOD_S) and feed.batches == 1
    (rows,) = bus.decode_telemetry_batch(publisher.messages[0])
    assert (rows.channel, rows.fields) == ("pose", ("x", "y"))
    np.testing.assert_array_equal(rows.k, [0, 1])
    np.testing.assert_array_equal(rows.values, [[1.0, 2.0], [3.0, 4.0]])
    assert feed.publish(10.6) == 0 and len(publisher.messages) == 1  # nothing new: no message
    pose.append(2, 2 * DT, [5.0, 6.0])
    assert feed.publish(10.9) == 1
    (rows,) = bus.decode_telemetry_batch(publisher.messages[1])
    np.testing.assert_array_equal(rows.k, [2])


def test_a_closed_feed_publishes_nothing_and_is_never_due() -> None:
    telemetry = Telemetry()
    channel = telemetry.add_channel("pose", ("x",))
    publisher = _Publisher()
    feed = TelemetryFeed(telemetry, publisher, now=0.0)
    feed.close()
    channel.append(0, 0.0, [1.0])
    assert feed.publish(1.0) == 0 and publisher.messages == [] and feed.due == math.inf


# -- link recovery ----------------------------------------------------------------------------


class _Board:
    """``reconnect`` fails ``failures`` times, then succeeds; each attempt takes 0.05 s."""

    def __init__(self, failures: int, clock: list[float]) -> None:
        self.failures = failures
        self.attempts = 0
        self._clock = clock

    def reconnect(self) -> None:
        self.attempts += 1
        self._clock[0] += 0.05
        if self.attempts <= self.failures:
            raise BoardTimeoutError(f"no answer ({self.attempts})")


class _Pause(threading.Event):
    """An event whose wait advances the fake clock instead of sleeping."""

    def __init__(self, clock: list[float]) -> None:
        super().__init__()
        self._clock = clock

    def wait(self, timeout: float | None = None) -> bool:
        self._clock[0] += timeout or 0.0
        return self.is_set()


def test_reconnect_retries_until_the_board_is_back() -> None:
    now = [0.0]
    board = _Board(3, now)
    attempts = reconnect_within(
        board, 2.0, BoardTimeoutError("stalled"), _Pause(now), lambda: now[0]
    )
    assert attempts == board.attempts == 4
    assert now[0] == pytest.approx(4 * 0.05 + 3 * RECONNECT_PAUSE_S)


def test_reconnect_gives_up_past_the_timeout_naming_the_attempts() -> None:
    now = [0.0]
    board = _Board(1000, now)
    with pytest.raises(BoardConnectionError, match=r"not back within 0\.5 s \(4 attempts\)"):
        reconnect_within(board, 0.5, BoardTimeoutError("stalled"), _Pause(now), lambda: now[0])
    assert board.attempts == 4  # 0.15 s per failed attempt and its pause: 0.5 s reached at the 4th


def test_reconnect_stops_at_once_when_the_agent_quits() -> None:
    now = [0.0]
    quitting = _Pause(now)
    quitting.set()
    board = _Board(0, now)
    with pytest.raises(QuitRequestedError, match="stalled"):
        reconnect_within(board, 5.0, BoardTimeoutError("stalled"), quitting, lambda: now[0])
    assert board.attempts == 0


def test_the_ledger_reads_retries_and_gateway_stages_where_the_link_has_them() -> None:
    assert link_retries(object()) == 0 and link_stages(object(), True) == ()
    board = SimpleNamespace(
        stats=SimpleNamespace(retries=2), take_link_stages=lambda: (0.001, 0.004)
    )
    assert link_retries(board) == 2
    assert link_stages(board, True) == (0.001, 0.004)
    assert link_stages(board, False) == (0.0, 0.0)  # tick 0: no exchange
