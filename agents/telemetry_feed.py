"""An agent's telemetry on the bus: the vehicle's channels in batches, every period.

:class:`TelemetryFeed` takes the rows appended to the vehicle's telemetry channels since its
previous batch (:class:`~hilswarm.agents.telemetry.TelemetryBatcher`) and puts them as one
message on ``agent/<name>/telemetry`` (:func:`~hilswarm.agents.bus.encode_telemetry_batch`),
every :data:`~hilswarm.agents.bus.TELEMETRY_PERIOD_S` of the agent's clock, and once more
when the agent goes safe or shuts down (the agent calls :meth:`TelemetryFeed.publish`). A
killed agent loses at most one period of telemetry. It never reads a wall clock itself: the
agent passes its clock's time.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from hilswarm.agents import bus
from hilswarm.agents.telemetry import Telemetry, TelemetryBatcher

#: Vehicle telemetry channels not published: they would repeat ``/<agent>/{y,u,x_hat}``,
#: which the tick path records already.
DUPLICATE_CHANNELS = ("y", "u", "x_hat")


class TelemetryFeed:
    """The vehicle's telemetry batches on one publisher (see the module docstring).

    Args:
        telemetry: the vehicle's channels.
        publisher: the agent's ``telemetry`` publisher (anything with ``put(bytes)``).
        now: the agent's clock [s] when it is made; the first batch is due one period later.
        skip: channel names never published.
    """

    def __init__(
        self,
        telemetry: Telemetry,
        publisher: Any,
        *,
        now: float,
        skip: Sequence[str] = DUPLICATE_CHANNELS,
    ) -> None:
        self._batcher = TelemetryBatcher(telemetry, skip=skip)
        self._publisher: Any = publisher
        self._heads: dict[str, bytes] = {}
        #: When the next batch is due [s, the agent's clock]; ``inf`` once closed.
        self.due = now + bus.TELEMETRY_PERIOD_S
        #: Batches published so far.
        self.batches = 0

    def publish(self, now: float) -> int:
        """Publish the rows appended since the previous batch; returns the row count.

        Args:
            now: the agent's clock [s]; the next batch is due one period after it.

        Does nothing after :meth:`close` or when nothing is new. Called by the thread that
        owns the hardware (the agent's worker while it runs, else its main thread).
        """
        publisher = self._publisher
        if publisher is None:
            return 0
        self.due = now + bus.TELEMETRY_PERIOD_S
        rows = self._batcher.take()
        if not rows:
            return 0
        heads = self._heads
        parts = []
        count = 0
        for channel, arrays in rows:
            head = heads.get(channel.name)
            if head is None:
                head = heads[channel.name] = bus.telemetry_channel_head(
                    channel.name, channel.fields
                )
            parts.append((head, arrays.k, arrays.t, arrays.values))
            count += arrays.k.shape[0]
        publisher.put(bus.encode_telemetry_batch(parts))
        self.batches += 1
        return count

    def close(self) -> None:
        """Publish nothing more (the agent is shutting down its session)."""
        self._publisher = None
        self.due = math.inf
