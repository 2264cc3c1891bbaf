"""The run recorder: one MCAP file per run, written by the orchestrator process.

Topics (a user-facing contract, see ``docs/recording.md``):

* ``/experiment`` — first message of the file: the experiment file's text, the settings as run
  (after command-line overrides) and the graph (agent names and adjacency matrix).
* ``/<agent>/y``, ``/<agent>/u``, ``/<agent>/x_hat``, ``/<agent>/telemetry/<channel>`` —
  vectors, via :meth:`Recorder.write_vector` / :meth:`Recorder.write_floats` (telemetry topics
  are registered with the channel's field names by
  :class:`~hilswarm.orchestrator.stream_recorder.StreamRecorder` when the first batch comes).
* ``/<agent>/status`` — lifecycle state changes, via :meth:`Recorder.write_status`.
* ``/orchestrator/ticks`` — the timing account of every tick, via :meth:`Recorder.write_ticks`.
* ``/<agent>/calibration`` — the calibration each vehicle runs with (once, at ``k = 0``), via
  :func:`record_vehicles`, which also names the entries of ``/<agent>/y`` after the vehicle's
  ``output_names``.

Every message carries ``k`` (tick), ``t`` (experiment time [s]) and ``values`` (a list of
numbers, empty for topics that are not vectors); named fields sit beside them. The file is
written in small chunks, so a crash of the orchestrator loses at most the last chunk, and
``hilswarm recover`` rewrites a file whose writer was killed. Calls are thread-safe (bus
callbacks may record from several threads).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import DEFAULT_COMPRESSION, McapJsonWriter, Mirror
from hilswarm.orchestrator import calibration_report, record_content
from hilswarm.orchestrator.experiment import Experiment
from numpy.typing import ArrayLike

logger = logging.getLogger(__name__)

EXPERIMENT_TOPIC = "/experiment"
TICKS_TOPIC = "/orchestrator/ticks"
#: Answers that came after their tick was closed without them (the ledger's late arrivals).
LATE_TOPIC = "/orchestrator/late"
#: Chunk size [bytes] of run recordings: small, so a crash loses little.
DEFAULT_CHUNK_SIZE = 32 * 1024

_BASE_PROPERTIES: dict[str, Any] = {
    "k": {"type": "integer", "description": "tick index"},
    "t": {"type": "number", "description": "experiment time [s]"},
    "values": {"type": "array", "items": {"type": ["number", "null"]}},
}


def _object_schema(title: str, properties: Mapping[str, Any]) -> dict[str, Any]:
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": {**_BASE_PROPERTIES, **properties},
        "required": ["k", "t", "values"],
    }


STATUS_SCHEMA = _object_schema(
    "agent status",
    {
        "agent": {"type": "string"},
        "state": {"type": "string", "description": "lifecycle state entered"},
        "detail": {"type": "string", "description": "reason or remark"},
        "malformed": {
            "type": "object",
            "description": (
                "messages the agent could not decode, by key (tick, y, control, set, mocap)"
            ),
        },
        "dropped": {
            "type": "object",
            "description": "well-formed messages the agent's tick engine rejected, by reason",
        },
        "skipped": {"type": "integer", "description": "ticks the agent missed in total"},
        "link_faults": {"type": "integer", "description": "board link faults of the agent"},
        "stale_samples": {
            "type": "integer",
            "description": "board answers marked STALE (XBee gateway, broadcast mode)",
        },
    },
)
TICKS_SCHEMA = _object_schema(
    TICKS_TOPIC,
    {"agents": {"type": "object", "description": "per-agent timings of the tick"}},
)
LATE_SCHEMA = _object_schema(
    LATE_TOPIC,
    {
        "agent": {"type": "string", "description": "the agent whose y_k came late"},
        "answer_s": {
            "type": ["number", "null"],
            "description": "its answer time after tick k was sent [s], past the tick's close",
        },
    },
)
EXPERIMENT_SCHEMA = _object_schema(
    EXPERIMENT_TOPIC,
    {
        "name": {"type": "string"},
        "file": {"type": "string", "description": "experiment file path"},
        "text": {"type": "string", "description": "experiment file text as loaded"},
        "settings": {"type": "object"},
        "graph": {
            "type": "object",
            "description": "agents and adjacency; A[i][j] = 1: agent i receives agent j",
        },
        "agents": {"type": "object"},
    },
)


CALIBRATION_SCHEMA = _object_schema(
    "vehicle calibration", calibration_report.SCHEMA.get("properties", {})
)


def status_topic(agent: str) -> str:
    """Topic of ``agent``'s lifecycle status messages."""
    return f"/{agent}/status"


class Recorder:
    """Records one run of ``experiment`` into the MCAP file ``path``.

    Args:
        path: the MCAP file to create (its folder is created if needed; an existing file is
            replaced).
        experiment: the experiment being run (recorded in ``/experiment``).
        chunk_size: MCAP chunk size [bytes] (``None``: chunks end only at :meth:`flush`).
        compression: chunk compression, ``"zstd"``, ``"lz4"`` or ``"none"`` (default:
            :data:`~hilswarm.agents.mcap_io.DEFAULT_COMPRESSION`).
        log_time_ns: start of the run [ns, wall clock, Unix epoch]: the log time of the
            ``/experiment`` message and of experiment time 0. Every message's log time is then
            this plus its experiment time ``t``, and the wall time a write method is given
            goes into the message as ``wall_ns``. When ``None``, log times are the wall times
            given, and ``/experiment`` is written just before the first other message, with
            that message's log time (the recorder reads no clock itself).
        mirror: also sees every channel and message written (the live view,
            :class:`~hilswarm.orchestrator.live_view.LiveView`).

    Use as a context manager, or call :meth:`close` on every exit path: closing writes the
    MCAP summary and footer.
    """

    def __init__(
        self,
        path: str | Path,
        experiment: Experiment,
        *,
        chunk_size: int | None = DEFAULT_CHUNK_SIZE,
        compression: str = DEFAULT_COMPRESSION,
        log_time_ns: int | None = None,
        mirror: Mirror | None = None,
    ) -> None:
        self.path = Path(path)
        self.experiment = experiment
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._origin = log_time_ns
        self._writer = McapJsonWriter(
            self.path,
            chunk_size=chunk_size,
            compression=compression,
            time_origin_ns=log_time_ns,
            mirror=mirror,
        )
        self._lock = threading.Lock()
        self._experiment_written = False
        self._closed = False
        self.message_count = 0
        if log_time_ns is not None:
            with self._lock:
                self._write_experiment(log_time_ns)

    # -- context manager ---------------------------------------------------------------------

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    @property
    def experiment_clock(self) -> bool:
        """True if log times are experiment times (the run's start was given)."""
        return self._origin is not None

    # -- writing -----------------------------------------------------------------------------

    def write_vector(
        self,
        topic: str,
        *,
        k: int,
        t: float,
        values: ArrayLike,
        log_time_ns: int,
        **named_fields: Any,
    ) -> None:
        """Record one vector sample on ``topic`` (e.g. ``/a1/y``).

        Args:
            topic: MCAP topic, ``/<agent>/y``, ``/<agent>/u``, ``/<agent>/x_hat`` or
                ``/<agent>/telemetry/<channel>``.
            k: tick index.
            t: experiment time [s].
            values: the vector (any shape; flattened), in the units of its signal.
            log_time_ns: log time [ns, wall clock, Unix epoch].
            named_fields: extra JSON-able fields beside ``values`` (e.g. ``x=..., y=...``).
        """
        vector = _as_list(values, topic)
        self._write(topic, k=k, t=t, values=vector, log_time_ns=log_time_ns, fields=named_fields)

    def add_topic(
        self,
        topic: str,
        fields: Sequence[str] | None = None,
        units: Mapping[str, str] | None = None,
    ) -> None:
        """Name the entries of a vector topic before its first message (optional).

        With ``fields`` (one name per vector entry, e.g. a vehicle's ``output_names``) every
        message also carries ``{field: values[i]}``, so Foxglove plots ``/a1/y.x``; ``units``
        (field -> unit) go into the schema. Topics written without this call are registered
        on first use without entry names.
        """
        with self._lock:
            self._check_open(topic)
            self._writer.add_topic(topic, fields=fields, units=units)

    def write_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        """Write an MCAP metadata record (string keys and values), e.g. the run's record."""
        with self._lock:
            self._check_open(name)
            self._writer.add_metadata(name, metadata)

    def topic_fields(self, topic: str) -> tuple[str, ...] | None:
        """The entry names ``topic`` was registered with (``None``: none, or not registered)."""
        with self._lock:
            return self._writer.topic_fields(topic)

    def write_floats(
        self, topic: str, *, k: int, t: float, values: Sequence[float], log_time_ns: int
    ) -> None:
        """:meth:`write_vector` for a vector that is a sequence of Python floats (fast path).

        Raises:
            RecordingError: the topic was named with other fields than values given.
        """
        with self._lock:
            self._check_open(topic)
            if not self._experiment_written:
                self._write_experiment(log_time_ns)
            writer = self._writer
            if not writer.has_topic(topic):
                writer.add_topic(topic)
            writer.write_floats(topic, k=k, t=t, values=values, log_time_ns=int(log_time_ns))
            self.message_count += 1

    def write_floats_many(
        self, rows: Sequence[tuple[str, int, float, Sequence[float], int]]
    ) -> None:
        """:meth:`write_floats` for several messages, in order, under one lock (hot path).

        Args:
            rows: per message ``(topic, k, t, values, log_time_ns)``: the topic, tick index,
                experiment time [s], the vector as Python floats and the log time [ns, wall
                clock, Unix epoch]. Topics not named with :meth:`add_topic` are registered
                without entry names, like :meth:`write_floats` does.

        Raises:
            RecordingError: a topic named with other fields than the values given; the rows
                before it are recorded, none after it.
        """
        if not rows:
            return
        with self._lock:
            self._check_open(rows[0][0])
            if not self._experiment_written:
                self._write_experiment(rows[0][4])
            writer = self._writer
            before = writer.messages_written
            try:
                writer.write_floats_many(rows, register=True)
            finally:
                self.message_count += writer.messages_written - before

    def write_encoded(
        self,
        topic: str,
        data: bytes,
        *,
        log_time_ns: int,
        schema: Mapping[str, Any] | None = None,
        t: float | None = None,
    ) -> None:
        """Record a JSON message already encoded by the caller (see ``write_encoded``).

        ``data`` must hold ``k``, ``t`` and ``values`` like every message of a run recording
        (and ``wall_ns``, the wall time, when the recorder runs on the experiment clock);
        ``t`` is its experiment time [s].
        """
        with self._lock:
            self._check_open(topic)
            if not self._experiment_written:
                self._write_experiment(log_time_ns)
            self._writer.write_encoded(topic, data, int(log_time_ns), schema, t=t)
            self.message_count += 1

    def write_message(self, topic: str, message: Mapping[str, Any], *, log_time_ns: int) -> None:
        """Record a free-form message (must have ``k``, ``t``, ``values``) on a topic."""
        self._write_json(topic, message, log_time_ns, None)

    def write_calibration(
        self, agent: str, calibration: Mapping[str, Any], *, log_time_ns: int
    ) -> None:
        """Record the calibration ``agent``'s vehicle runs with on ``/<agent>/calibration``.

        Args:
            agent: agent name.
            calibration: :func:`~hilswarm.orchestrator.calibration_report.calibration_as_json`
                of the vehicle's calibration.
            log_time_ns: log time [ns, wall clock, Unix epoch].
        """
        message = {"k": 0, "t": 0.0, "values": [], **calibration}
        self._write_json(
            calibration_report.calibration_topic(agent), message, log_time_ns, CALIBRATION_SCHEMA
        )

    def write_status(
        self,
        agent: str,
        *,
        state: str,
        k: int,
        t: float,
        log_time_ns: int,
        detail: str = "",
        counters: Mapping[str, Any] | None = None,
    ) -> None:
        """Record a lifecycle state of ``agent`` on ``/<agent>/status``.

        Args:
            agent: agent name.
            state: the state entered (e.g. ``"running"``, ``"safe"``, ``"lost"``).
            k: tick at which it happened.
            t: experiment time [s].
            log_time_ns: log time [ns, wall clock, Unix epoch].
            detail: free text, e.g. the reason of a safe-mode entry.
            counters: the agent's input and fault counters (``malformed``, ``dropped``,
                ``skipped``, ``link_faults``, ``stale_samples``), as it sent them.
        """
        message = {
            "k": int(k),
            "t": float(t),
            "values": [],
            "agent": agent,
            "state": str(state),
            "detail": str(detail),
            **(counters or {}),
        }
        self._write_json(status_topic(agent), message, log_time_ns, STATUS_SCHEMA)

    def write_ticks(
        self, *, k: int, t: float, log_time_ns: int, timings: Mapping[str, Any]
    ) -> None:
        """Record the timing account of tick ``k`` on ``/orchestrator/ticks``.

        Args:
            k: tick index.
            t: experiment time [s] of the tick.
            log_time_ns: log time [ns, wall clock, Unix epoch].
            timings: the tick's numbers, e.g. ``{"scheduled_s": ..., "sent_s": ...,
                "done_s": ..., "duration_s": ..., "late": 0, "agents": {"a1": {"sense_s":
                ..., "compute_s": ...}}}``. Numbers (numpy scalars too), strings, lists and
                nested mappings of those are accepted; units belong in the key names.
        """
        message: dict[str, Any] = {"k": int(k), "t": float(t), "values": []}
        for key, value in timings.items():
            if key in message:
                raise RecordingError(f"{TICKS_TOPIC}: timing key {key!r} clashes with k/t/values")
            message[str(key)] = value
        self._write_json(TICKS_TOPIC, message, log_time_ns, TICKS_SCHEMA)

    def flush(self) -> None:
        """Finish the chunk in progress and hand the file everything written so far."""
        with self._lock:
            if not self._closed:
                self._writer.flush()

    def close(self) -> None:
        """Write the summary and footer and close the file (idempotent)."""
        with self._lock:
            if self._closed:
                return
            try:
                if not self._experiment_written:
                    self._write_experiment(0)
            finally:
                self._closed = True
                self._writer.close()
        logger.info("recorded %d messages to %s", self.message_count, self.path)

    # -- internals ---------------------------------------------------------------------------

    def _check_open(self, topic: str) -> None:
        if self._closed:
            raise RecordingError(f"recorder of {self.path} is closed; cannot write {topic}")

    def _write(
        self,
        topic: str,
        *,
        k: int,
        t: float,
        values: list[float],
        log_time_ns: int,
        fields: Mapping[str, Any],
    ) -> None:
        with self._lock:
            self._check_open(topic)
            if not self._experiment_written:
                self._write_experiment(log_time_ns)
            if not self._writer.has_topic(topic):
                self._writer.add_topic(topic)
            self._writer.write(
                topic, k=int(k), t=float(t), values=values, log_time_ns=int(log_time_ns), **fields
            )
            self.message_count += 1

    def _write_json(
        self, topic: str, message: Mapping[str, Any], log_time_ns: int, schema: Mapping[str, Any]
    ) -> None:
        with self._lock:
            self._check_open(topic)
            if not self._experiment_written:
                self._write_experiment(log_time_ns)
            self._writer.write_json(topic, message, int(log_time_ns), schema)
            self.message_count += 1

    def _write_experiment(self, log_time_ns: int) -> None:
        experiment = self.experiment
        settings = {
            "rate_hz": experiment.rate_hz,
            "duration_s": experiment.duration_s,
            "mode": experiment.mode,
            "on_agent_loss": experiment.on_agent_loss,
            "watchdog_s": experiment.watchdog_s,
            "seed": experiment.seed,
        }
        agents = {
            spec.name: {
                "vehicle": spec.vehicle,
                "link": spec.link,
                "controller": spec.controller,
                "params": spec.params,
                "vehicle_params": spec.vehicle_params,
                "pinout": spec.pinout,
                "initial_state": list(spec.initial_state),
                "calibration": str(spec.calibration) if spec.calibration else None,
            }
            for spec in experiment.agents
        }
        message = {
            "k": 0,
            "t": 0.0,
            "values": [],
            "name": experiment.name,
            "file": str(experiment.path),
            "text": experiment.source_text,
            "settings": settings,
            "graph": experiment.graph_dict(),
            "agents": agents,
        }
        self._writer.write_json(EXPERIMENT_TOPIC, message, int(log_time_ns), EXPERIMENT_SCHEMA)
        self._experiment_written = True
        self.message_count += 1


def _as_list(values: ArrayLike, topic: str) -> list[float]:
    try:
        array = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{topic}: values must be numbers, got {values!r}") from exc
    return array.tolist()


def record_vehicles(recorder: Recorder, experiment: Experiment, *, log_time_ns: int) -> None:
    """Record what the agents of ``experiment`` are, before the first tick.

    For every agent (as far as its classes can be built here, see
    :func:`~hilswarm.orchestrator.record_content.describe_agent`): its calibration on
    ``/<agent>/calibration``, and the entry names and units of ``/<agent>/y``, ``/<agent>/u``
    (from the vehicle) and ``/<agent>/x_hat`` (from the controller's ``state_names``). Then
    the run's metadata record (:func:`~hilswarm.orchestrator.record_content.run_metadata`).
    """
    calibrations: dict[str, Any] = {}
    for spec in experiment.agents:
        description = record_content.describe_agent(experiment, spec)
        calibration = description.calibration
        calibrations[spec.name] = calibration
        if calibration is not None:
            recorder.write_calibration(
                spec.name,
                calibration_report.calibration_as_json(calibration),
                log_time_ns=log_time_ns,
            )
        signals = (("y", description.y), ("u", description.u), ("x_hat", description.x_hat))
        for leaf, signal in signals:
            if signal is None:
                continue
            topic = f"/{spec.name}/{leaf}"
            try:
                recorder.add_topic(topic, fields=signal.names, units=signal.units)
            except RecordingError as exc:  # e.g. an entry called "k": plain values then
                logger.warning("%s without field names: %s", topic, exc)
    recorder.write_metadata(
        record_content.RUN_METADATA, record_content.run_metadata(experiment, calibrations)
    )
