"""The run recorder: one MCAP file per run, written by the orchestrator process.

Topics (a user-facing contract, see ``docs/recording.md``):

* ``/experiment`` — first message of the file: the experiment file's text, the settings as run
  (after command-line overrides) and the graph (agent names and adjacency matrix).
* ``/<agent>/y``, ``/<agent>/u``, ``/<agent>/x_hat``, ``/<agent>/telemetry/<channel>`` —
  vectors, via :meth:`Recorder.write_vector`.
* ``/<agent>/status`` — lifecycle state changes, via :meth:`Recorder.write_status`.
* ``/orchestrator/ticks`` — the timing account of every tick, via :meth:`Recorder.write_ticks`.

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
from hilswarm.agents.mcap_io import McapJsonWriter
from hilswarm.orchestrator.experiment import Experiment
from numpy.typing import ArrayLike

logger = logging.getLogger(__name__)

EXPERIMENT_TOPIC = "/experiment"
TICKS_TOPIC = "/orchestrator/ticks"
#: Chunk size [bytes] of run recordings: small, so a crash loses little.
DEFAULT_CHUNK_SIZE = 32 * 1024


def status_topic(agent: str) -> str:
    """Topic of ``agent``'s lifecycle status messages."""
    return f"/{agent}/status"


class Recorder:
    """Records one run of ``experiment`` into the MCAP file ``path``.

    Args:
        path: the MCAP file to create (its folder is created if needed; an existing file is
            replaced).
        experiment: the experiment being run (recorded in ``/experiment``).
        chunk_size: MCAP chunk size [bytes].
        log_time_ns: log time [ns, wall clock, Unix epoch] of the ``/experiment`` message.
            When ``None`` the message is written just before the first other message, with
            that message's log time (the recorder reads no clock itself).

    Use as a context manager, or call :meth:`close` on every exit path: closing writes the
    MCAP summary and footer.
    """

    def __init__(
        self,
        path: str | Path,
        experiment: Experiment,
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        log_time_ns: int | None = None,
    ) -> None:
        self.path = Path(path)
        self.experiment = experiment
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._writer = McapJsonWriter(self.path, chunk_size=chunk_size)
        self._lock = threading.Lock()
        self._topics: dict[str, tuple[str, ...]] = {}
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

    def write_status(
        self,
        agent: str,
        *,
        state: str,
        k: int,
        t: float,
        log_time_ns: int,
        detail: str = "",
    ) -> None:
        """Record a lifecycle state of ``agent`` on ``/<agent>/status``.

        Args:
            agent: agent name.
            state: the state entered (e.g. ``"running"``, ``"safe"``, ``"lost"``).
            k: tick at which it happened.
            t: experiment time [s].
            log_time_ns: log time [ns, wall clock, Unix epoch].
            detail: free text, e.g. the reason of a safe-mode entry.
        """
        self._write(
            status_topic(agent),
            k=k,
            t=t,
            values=[],
            log_time_ns=log_time_ns,
            fields={"agent": agent, "state": str(state), "detail": str(detail)},
        )

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
        fields = {str(key): _jsonable(value) for key, value in timings.items()}
        self._write(TICKS_TOPIC, k=k, t=t, values=[], log_time_ns=log_time_ns, fields=fields)

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
        if not isinstance(topic, str) or not topic.startswith("/"):
            raise RecordingError(f"topic must be a string starting with '/', got {topic!r}")
        clean = {str(name): _jsonable(value) for name, value in fields.items()}
        with self._lock:
            if self._closed:
                raise RecordingError(f"recorder of {self.path} is closed; cannot write {topic}")
            if not self._experiment_written:
                self._write_experiment(log_time_ns)
            self._ensure_topic(topic, tuple(clean))
            self._writer.write(
                topic, k=int(k), t=float(t), values=values, log_time_ns=int(log_time_ns), **clean
            )
            self.message_count += 1

    def _ensure_topic(self, topic: str, names: Sequence[str]) -> None:
        known = self._topics.get(topic)
        if known is None:
            self._writer.add_topic(topic, fields=list(names) or None)
            self._topics[topic] = tuple(names)

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
                "params": _jsonable(spec.params),
                "vehicle_params": _jsonable(spec.vehicle_params),
                "pinout": _jsonable(spec.pinout),
                "initial_state": list(spec.initial_state),
                "calibration": str(spec.calibration) if spec.calibration else None,
            }
            for spec in experiment.agents
        }
        fields = {
            "name": experiment.name,
            "file": str(experiment.path),
            "text": experiment.source_text,
            "settings": settings,
            "graph": experiment.graph_dict(),
            "agents": agents,
        }
        self._writer.add_topic(EXPERIMENT_TOPIC, fields=list(fields))
        self._topics[EXPERIMENT_TOPIC] = tuple(fields)
        self._writer.write(
            EXPERIMENT_TOPIC, k=0, t=0.0, values=[], log_time_ns=int(log_time_ns), **fields
        )
        self._experiment_written = True
        self.message_count += 1


def _as_list(values: ArrayLike, topic: str) -> list[float]:
    try:
        array = np.asarray(values, dtype=float).ravel()
    except (TypeError, ValueError) as exc:
        raise RecordingError(f"{topic}: values must be numbers, got {values!r}") from exc
    return array.tolist()


def _jsonable(value: Any) -> Any:
    """Turn numpy scalars/arrays, tuples and Paths into JSON-able Python values."""
    if isinstance(value, Mapping):
        return {str(key): _jsonable(item) for key, item in value.items()}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list | tuple):
        return [_jsonable(item) for item in value]
    if isinstance(value, Path):
        return str(value)
    return value
