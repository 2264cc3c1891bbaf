"""Telemetry: named series of samples kept in growable numpy storage.

A :class:`Channel` is one named series (e.g. ``"position"``) of samples with named fields
(e.g. ``("x", "y", "z")``). Every sample is a tick index ``k``, a time ``t`` [s, experiment
time] and one value per field (units are those of the field, documented by whoever defines the
channel). Appending is amortised O(1): the storage doubles its capacity when full, like the
thesis' ``DynamicArray``, instead of copying the whole history on every sample as a naive
``np.append`` loop does.

:class:`Telemetry` holds the channels of one vehicle or controller by name, and
:func:`write_to_mcap` writes every channel of it to ``/<agent>/telemetry/<channel>``.
:class:`TelemetryBatcher` hands out the rows appended since its previous batch, which an agent
process publishes (encoded by :func:`hilswarm.agents.bus.encode_telemetry_batch`) so that the
run's recording gets them.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from hilswarm.agents.errors import TelemetryError
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from hilswarm.agents.mcap_io import McapJsonWriter

#: Capacity (rows) a new channel starts with.
DEFAULT_INITIAL_CAPACITY = 64

_FLOAT64 = np.dtype(np.float64)


class ChannelArrays(NamedTuple):
    """The filled part of a channel.

    Attributes:
        k: tick indices, shape ``(n,)``, int64.
        t: sample times [s, experiment time], shape ``(n,)``, float64.
        values: one row per sample, one column per field, shape ``(n, n_fields)``, float64.
    """

    k: np.ndarray
    t: np.ndarray
    values: np.ndarray


class Channel:
    """One named series of samples with named fields, in growable numpy storage.

    Args:
        name: channel name, used as the last part of the MCAP topic.
        fields: field names, one per value of a sample (non-empty, unique, non-empty strings).
        initial_capacity: rows allocated up front; the storage doubles whenever it is full.

    Raises:
        TelemetryError: a bad name, field list or capacity.
    """

    def __init__(
        self,
        name: str,
        fields: Sequence[str],
        *,
        initial_capacity: int = DEFAULT_INITIAL_CAPACITY,
    ) -> None:
        if not isinstance(name, str) or not name or "/" in name:
            raise TelemetryError(
                f"channel name must be a non-empty string without '/', got {name!r}"
            )
        if isinstance(fields, str):
            raise TelemetryError(
                f"channel {name!r}: fields must be a sequence of names, got the string {fields!r}"
            )
        field_names = tuple(fields)
        if not field_names:
            raise TelemetryError(f"channel {name!r}: needs at least one field")
        for field in field_names:
            if not isinstance(field, str) or not field:
                raise TelemetryError(
                    f"channel {name!r}: field names must be non-empty strings, got {field!r}"
                )
        if len(set(field_names)) != len(field_names):
            raise TelemetryError(f"channel {name!r}: field names repeat: {field_names}")
        if not isinstance(initial_capacity, int) or initial_capacity < 1:
            raise TelemetryError(
                f"channel {name!r}: initial_capacity must be a positive int, "
                f"got {initial_capacity!r}"
            )
        self.name: str = name
        self.fields: tuple[str, ...] = field_names
        self._shape = (len(field_names),)
        self._size = 0
        self._clears = 0
        self._k = np.empty(initial_capacity, dtype=np.int64)
        self._t = np.empty(initial_capacity, dtype=np.float64)
        self._values = np.empty((initial_capacity, len(field_names)), dtype=np.float64)
        self._capacity = initial_capacity

    @property
    def n_fields(self) -> int:
        """Number of values per sample."""
        return len(self.fields)

    @property
    def capacity(self) -> int:
        """Rows currently allocated (grows by doubling)."""
        return self._capacity

    def __len__(self) -> int:
        return self._size

    def __repr__(self) -> str:
        return f"Channel({self.name!r}, fields={self.fields!r}, samples={self._size})"

    def append(self, k: int, t: float, values: ArrayLike) -> None:
        """Append one sample.

        Args:
            k: tick index.
            t: sample time [s, experiment time].
            values: one number per field (a scalar is accepted for a one-field channel).
                NaN marks a missing value.

        Raises:
            TelemetryError: ``values`` does not hold exactly ``n_fields`` numbers.
        """
        if (
            type(values) is not np.ndarray
            or values.shape != self._shape
            or values.dtype != _FLOAT64
        ):  # anything but a float vector of the right size: convert and check
            try:
                values = np.asarray(values, dtype=np.float64)
            except (TypeError, ValueError):
                raise TelemetryError(
                    f"channel {self.name!r}: expected {self.n_fields} values {self.fields}, "
                    f"got non-numeric {values!r}"
                ) from None
            if values.shape != self._shape and not (values.ndim == 0 and self.n_fields == 1):
                raise TelemetryError(
                    f"channel {self.name!r}: expected {self.n_fields} values {self.fields}, "
                    f"got shape {values.shape}"
                )
        i = self._size
        if i == self._capacity:
            self._grow()
        self._k[i] = k
        self._t[i] = t
        self._values[i] = values
        self._size = i + 1

    def _grow(self) -> None:
        new_capacity = 2 * self._k.shape[0]
        k = np.empty(new_capacity, dtype=np.int64)
        t = np.empty(new_capacity, dtype=np.float64)
        values = np.empty((new_capacity, self.n_fields), dtype=np.float64)
        k[: self._size] = self._k[: self._size]
        t[: self._size] = self._t[: self._size]
        values[: self._size] = self._values[: self._size]
        self._k, self._t, self._values = k, t, values
        self._capacity = new_capacity

    def arrays(self, *, copy: bool = True) -> ChannelArrays:
        """The filled part of the channel as ``(k, t, values)``.

        Args:
            copy: ``True`` (default) returns independent copies. ``False`` returns read-only
                views of the storage: cheap, but they do not see samples appended later.
        """
        if not copy:
            return self.rows_since(0)
        n = self._size
        return ChannelArrays(self._k[:n].copy(), self._t[:n].copy(), self._values[:n].copy())

    def rows_since(self, start: int) -> ChannelArrays:
        """Read-only views of the rows ``start, start + 1, ...`` appended so far.

        Cheap (no copy); the views do not see rows appended later.

        Raises:
            TelemetryError: ``start`` is negative or beyond the filled part.
        """
        n = self._size
        if not 0 <= start <= n:
            raise TelemetryError(
                f"channel {self.name!r}: rows from {start} asked for, but it holds {n}"
            )
        views = []
        for part in (self._k[start:n], self._t[start:n], self._values[start:n]):
            view = part.view()
            view.flags.writeable = False
            views.append(view)
        return ChannelArrays(*views)

    def field(self, name: str) -> np.ndarray:
        """A copy of one field's values over all samples, shape ``(n,)``.

        Raises:
            TelemetryError: ``name`` is not one of :attr:`fields`.
        """
        try:
            column = self.fields.index(name)
        except ValueError:
            raise TelemetryError(
                f"channel {self.name!r} has no field {name!r}; fields are {self.fields}"
            ) from None
        return self._values[: self._size, column].copy()

    def last(self) -> tuple[int, float, np.ndarray] | None:
        """The newest sample ``(k, t, values)`` or ``None`` when the channel is empty."""
        if self._size == 0:
            return None
        i = self._size - 1
        return int(self._k[i]), float(self._t[i]), self._values[i].copy()

    @property
    def clears(self) -> int:
        """How many times :meth:`clear` was called (readers of new rows restart on a change)."""
        return self._clears

    def clear(self) -> None:
        """Forget every sample (keeps the allocated capacity)."""
        self._size = 0
        self._clears += 1


class Telemetry:
    """The channels of one vehicle or controller, by name (in the order they were added)."""

    def __init__(self) -> None:
        self._channels: dict[str, Channel] = {}

    def add_channel(
        self,
        name: str,
        fields: Sequence[str],
        *,
        initial_capacity: int = DEFAULT_INITIAL_CAPACITY,
    ) -> Channel:
        """Create, store and return a new channel.

        Raises:
            TelemetryError: a channel of that name exists already, or bad name/fields.
        """
        if name in self._channels:
            raise TelemetryError(
                f"telemetry channel {name!r} exists already (fields {self._channels[name].fields})"
            )
        channel = Channel(name, fields, initial_capacity=initial_capacity)
        self._channels[name] = channel
        return channel

    def __getitem__(self, name: str) -> Channel:
        try:
            return self._channels[name]
        except KeyError:
            raise TelemetryError(
                f"no telemetry channel {name!r}; channels are {list(self._channels)}"
            ) from None

    def __contains__(self, name: object) -> bool:
        return name in self._channels

    def __iter__(self) -> Iterator[Channel]:
        return iter(list(self._channels.values()))

    def __len__(self) -> int:
        return len(self._channels)

    @property
    def names(self) -> tuple[str, ...]:
        """Channel names in the order they were added."""
        return tuple(self._channels)

    def clear(self) -> None:
        """Forget the samples of every channel (the channels stay)."""
        for channel in self._channels.values():
            channel.clear()

    def write_to_mcap(
        self, writer: McapJsonWriter, agent_name: str, *, start_time_ns: int = 0
    ) -> int:
        """Write every channel to ``/<agent_name>/telemetry/<channel>`` (:func:`write_to_mcap`)."""
        return write_to_mcap(self, writer, agent_name, start_time_ns=start_time_ns)


class TelemetryBatcher:
    """Hands out the rows of a :class:`Telemetry` appended since the previous batch.

    Args:
        telemetry: the channels to follow (channels added later are followed too).
        skip: channel names never handed out (e.g. ones that repeat what is recorded anyway).

    A channel that was :meth:`Channel.clear`-ed starts again from its first row.
    """

    def __init__(self, telemetry: Telemetry, *, skip: Sequence[str] = ()) -> None:
        self.telemetry = telemetry
        self.skip = frozenset(skip)
        self._sent: dict[str, tuple[int, int]] = {}  # channel -> (its clears, rows handed out)
        self.rows_handed_out = 0

    @property
    def pending(self) -> int:
        """Rows appended since the previous batch (skipped channels not counted)."""
        return sum(
            len(channel) - self._start(channel)
            for channel in self.telemetry
            if channel.name not in self.skip
        )

    def _start(self, channel: Channel) -> int:
        """First row of ``channel`` not handed out yet (0 after a :meth:`Channel.clear`)."""
        clears, sent = self._sent.get(channel.name, (channel.clears, 0))
        return sent if clears == channel.clears else 0

    def take(self) -> list[tuple[Channel, ChannelArrays]]:
        """The new rows of every followed channel (read-only views), and mark them handed out.

        Channels without new rows are left out; an empty list means nothing is new.
        """
        batch: list[tuple[Channel, ChannelArrays]] = []
        for channel in self.telemetry:
            if channel.name in self.skip:
                continue
            size, start = len(channel), self._start(channel)
            if size == start:
                continue
            batch.append((channel, channel.rows_since(start)))
            self._sent[channel.name] = (channel.clears, size)
            self.rows_handed_out += size - start
        return batch


def telemetry_topic(agent_name: str, channel_name: str) -> str:
    """The MCAP topic of a telemetry channel: ``/<agent>/telemetry/<channel>``."""
    return f"/{agent_name}/telemetry/{channel_name}"


def write_to_mcap(
    telemetry: Telemetry,
    writer: McapJsonWriter,
    agent_name: str,
    *,
    start_time_ns: int = 0,
) -> int:
    """Write every sample of every channel to ``/<agent_name>/telemetry/<channel>``.

    Each topic is registered with the channel's field names, so every message carries ``k``,
    ``t``, ``values`` and one named entry per field. The log time of a sample is
    ``start_time_ns + round(t * 1e9)``.

    Args:
        telemetry: the channels to write.
        writer: an open MCAP writer.
        agent_name: the agent the telemetry belongs to (first part of the topic).
        start_time_ns: log time [ns] of experiment time ``t = 0``.

    Returns:
        The number of messages written.

    Raises:
        TelemetryError: ``agent_name`` is empty or contains ``'/'``.
    """
    if not isinstance(agent_name, str) or not agent_name or "/" in agent_name:
        raise TelemetryError(f"agent name must be non-empty without '/', got {agent_name!r}")
    written = 0
    for channel in telemetry:
        topic = telemetry_topic(agent_name, channel.name)
        writer.add_topic(topic, fields=channel.fields)
        k, t, values = channel.arrays(copy=False)
        for i in range(k.shape[0]):
            writer.write(
                topic,
                k=int(k[i]),
                t=float(t[i]),
                values=values[i],
                log_time_ns=start_time_ns + round(float(t[i]) * 1e9),
            )
            written += 1
    return written
