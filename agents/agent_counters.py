"""An agent's input and fault counters: what its status messages report, and when.

:class:`AgentCounters` keeps the agent's own counts — ``malformed`` messages by key (see
:data:`INPUT_KEYS`), ticks ``skipped``, board ``link_faults`` ridden out — and reads the
others where they live: the tick engine's ``dropped`` messages, stale realtime ticks and
``inputs_missing``, and the board link's ``stale_samples`` (an XBee gateway in broadcast mode
answering with a robot's last samples). :meth:`AgentCounters.fields` gives the non-zero ones
for a status message; :meth:`AgentCounters.changed` says when a status of kind ``inputs`` is
due (the counters changed, or ticks with missing inputs are pending), at most once per
:data:`COUNTERS_PERIOD_S`. The field names are those of the agent's module docstring.
"""

from __future__ import annotations

import math
import threading
from typing import Any

from hilswarm.agents.tick_engine import TickEngine

#: The keys whose malformed messages are counted (keys of :attr:`AgentCounters.malformed`).
INPUT_KEYS = ("tick", "y", "control", "set", "mocap")
#: Shortest time between two status messages that only report changed counters [s].
COUNTERS_PERIOD_S = 1.0


def board_count(board: Any, name: str) -> int:
    """The board link's counter ``name`` so far (``stats.<name>``; 0 for links without it)."""
    return int(getattr(getattr(board, "stats", None), name, 0) or 0)


class AgentCounters:
    """The counters of one agent (see the module docstring).

    Args:
        engine: the agent's tick engine.
        engine_lock: the lock that guards it (held here only for the engine's short reads;
            malformed counts are taken under it too: several bus threads count at once).

    Attributes:
        malformed: messages that could not be decoded, by key (:data:`INPUT_KEYS`).
        skipped: ticks the agent missed in total.
        link_faults: board link faults ridden out (or not).
        board: the board link whose ``stale_samples`` are reported (``None``: none yet).
    """

    def __init__(self, engine: TickEngine, engine_lock: threading.Lock) -> None:
        self._engine = engine
        self._lock = engine_lock
        self.malformed: dict[str, int] = dict.fromkeys(INPUT_KEYS, 0)
        self.skipped = 0
        self.link_faults = 0
        self.board: Any = None
        self._published: tuple[int, ...] = ()
        self._due = -math.inf  # the agent's clock [s] of the next check

    def count_malformed(self, key: str) -> None:
        """One more message on ``key`` that could not be decoded (any thread)."""
        with self._lock:
            self.malformed[key] += 1

    def stale_samples(self) -> int:
        """Board answers marked STALE so far (0 for links that do not count them)."""
        return board_count(self.board, "stale_samples")

    def fields(self) -> dict[str, Any]:
        """The non-zero counters, as a status message carries them; takes the engine's
        ``inputs_missing`` noted since the previous call."""
        engine = self._engine
        with self._lock:
            dropped = dict(engine.counters())
            malformed = {key: n for key, n in self.malformed.items() if n}
            inputs_missing = engine.take_inputs_missing()
        fields: dict[str, Any] = {}
        if inputs_missing:
            fields["inputs_missing"] = inputs_missing
        if malformed:
            fields["malformed"] = malformed
        if dropped:
            fields["dropped"] = dropped
        if self.skipped:
            fields["skipped"] = self.skipped
        if self.link_faults:
            fields["link_faults"] = self.link_faults
        stale = self.stale_samples()
        if stale:
            fields["stale_samples"] = stale
        return fields

    def changed(self, now: float) -> bool:
        """Whether a status of kind ``inputs`` is due at ``now`` [s, the agent's clock]: some
        counter changed since the last such status, or ticks with missing inputs are pending;
        checked at most once per :data:`COUNTERS_PERIOD_S`."""
        if now < self._due:
            return False
        self._due = now + COUNTERS_PERIOD_S
        engine = self._engine
        with self._lock:
            snapshot = (
                *engine.dropped.values(),
                engine.stale,
                *self.malformed.values(),
                self.skipped,
                self.link_faults,
                self.stale_samples(),
            )
            pending = bool(engine.inputs_missing)
        if pending or (snapshot != self._published and any(snapshot)):
            self._published = snapshot
            return True
        return False
