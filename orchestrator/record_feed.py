"""The instance manager's side of the record stream: when what it kept goes to the recorder.

The manager's bus callbacks keep each message in a
:class:`~hilswarm.orchestrator.record_stream.RecordWriter` under the manager's lock (a tuple
appended: cheap on the tick path). :class:`RecordFeed` hands what was kept to the
:class:`~hilswarm.orchestrator.record_stream.RecordSink` as one numbered batch at most one
flush period after it came: it cuts the kept messages under that lock, then logs them on the
MCAP stream outside it (foxglove-sdk's log call lets go of the GIL, so never while the
callbacks wait for the lock; docs/recording.md), one batch at a time, in the order of the cuts.

In realtime runs the manager hands a batch over when a tick completes from half a period
before the next batch is due (:attr:`RecordFeed.flush_from`): between the swarm's ticks, not
at a due time, where the recorder's work would compete with the agents'.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

from hilswarm.orchestrator.record_stream import RecordSink, RecordWriter, hand_over


class RecordFeed:
    """Batches of the record stream, from the manager's bus callbacks to ``sink``.

    Args:
        sink: where the batches go (the recorder process's pipe, or a recorder in this
            process).
        names: the experiment's agents, in order.
        lock: the manager's lock, under which its callbacks keep messages in :attr:`writer`.
        tick_base: the manager's oldest open tick (called under ``lock``): each batch says
            from which tick on it holds records.
        clock: the manager's monotonic clock [s].
        wall_clock_ns: wall clock [ns, Unix epoch] for the messages' log times.
        flush_period_s: a message goes to ``sink`` at most this long after it was kept [s].
    """

    def __init__(
        self,
        sink: RecordSink,
        names: Sequence[str],
        *,
        lock: threading.Lock,
        tick_base: Callable[[], int],
        clock: Callable[[], float],
        wall_clock_ns: Callable[[], int],
        flush_period_s: float,
    ) -> None:
        self.sink = sink
        #: Where the callbacks keep messages (under ``lock``).
        self.writer = RecordWriter(names)
        self._lock = lock
        self._tick_base = tick_base
        self._clock = clock
        self._wall_ns = wall_clock_ns
        self.flush_period_s = flush_period_s
        #: When the next batch is due [s, manager clock].
        self.next_flush = 0.0
        #: Realtime: a tick completing from this time on carries the next batch [s].
        self.flush_from = 0.0
        self._guard = threading.Lock()  # one batch at a time (taken before ``lock``)
        self._since = -1  # the tick at which the batch began gathering (-1: unknown)

    def event(self, agent: str, state: str, *, k: int, t: float, detail: str) -> None:
        """Keep an event the manager records itself (``/orchestrator/status``) at tick ``k``,
        experiment time ``t`` [s]."""
        with self._lock:
            self.writer.event(self._wall_ns(), agent, state, k=k, t=t, detail=detail)

    def flush(self, now: float | None = None, *, dt: float = 0.0) -> None:
        """Hand what was kept so far to the sink; the next batch is due one flush period from
        ``now`` [s, manager clock; default: the clock now], and a realtime tick (period
        ``dt`` [s]) completing from half a period before that carries it."""
        self.next_flush = (self._clock() if now is None else now) + self.flush_period_s
        self.flush_from = self.next_flush - 0.5 * dt
        self.hand_over(final=False)

    def hand_over(self, *, final: bool) -> None:
        """Hand what was kept so far to the sink as one batch (``final``: the last, which ends
        the stream; nothing after it)."""
        writer = self.writer
        with self._guard:  # batches in the order of their cuts
            with self._lock:
                if writer.closed:
                    return
                kept = writer.cut()
                first, tick = self._since, self._tick_base()
                if kept or final:
                    self._since = tick
            # logging the MCAP messages lets go of the GIL: never under the callbacks' lock
            now = self._wall_ns()
            batch = writer.write_end(kept, now) if final else writer.write(kept, now)
            if batch is None:
                return
            hand_over(self.sink, batch, tick=tick, first_tick=first)
