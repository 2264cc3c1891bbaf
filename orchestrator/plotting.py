"""PNG plots of a run recording (``hilswarm plot``), drawn with matplotlib's Agg backend.

From one MCAP file written by the recorder:

* ``outputs.png`` — every agent's output ``y`` against experiment time, one panel per output
  entry, one line per agent;
* ``inputs.png`` — the same for the inputs ``u``;
* ``paths.png`` — the x–y paths of all agents in the world frame (when ``y`` has at least two
  entries; which entries are x and y is configurable), start marked ``o``, end ``s``;
* ``ticks.png`` — the tick latency from ``/orchestrator/ticks``: time series and histogram.

A plot whose data is absent from the recording is skipped. Truncated recordings are read up to
their last complete chunk.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib as mpl

mpl.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from hilswarm.agents.errors import RecordingError
from hilswarm.agents.mcap_io import iter_messages, read_schemas
from hilswarm.orchestrator.segments import existing_segments
from matplotlib.figure import Figure

logger = logging.getLogger(__name__)

#: Keys of /orchestrator/ticks tried in order as "the tick latency" [s].
TICK_LATENCY_KEYS: tuple[str, ...] = (
    "completion_s",
    "duration_s",
    "latency_s",
    "round_trip_s",
    "elapsed_s",
)
#: More agents than this and the legends are left out (they would cover the data).
MAX_LEGEND_ENTRIES = 12
_DPI = 120


@dataclass
class Series:
    """One vector topic read from a recording.

    Attributes:
        k: tick indices, shape ``(n,)``.
        t: experiment times [s], shape ``(n,)``.
        values: one row per message, shape ``(n, width)``; NaN where a message had fewer
            entries or a ``null``.
        names: names of the entries (from the topic's schema), or ``values[i]``.
    """

    k: np.ndarray
    t: np.ndarray
    values: np.ndarray
    names: tuple[str, ...]


@dataclass
class RecordingData:
    """The plottable content of one recording.

    Attributes:
        outputs: agent -> its ``/<agent>/y`` series.
        inputs: agent -> its ``/<agent>/u`` series.
        ticks: the ``/orchestrator/ticks`` messages (dicts), in order.
        experiment: the ``/experiment`` message, or ``None``.
    """

    outputs: dict[str, Series] = field(default_factory=dict)
    inputs: dict[str, Series] = field(default_factory=dict)
    ticks: list[dict[str, Any]] = field(default_factory=list)
    experiment: dict[str, Any] | None = None


def load_recording(path: str | os.PathLike[str]) -> RecordingData:
    """Read ``/<agent>/y``, ``/<agent>/u``, ``/orchestrator/ticks`` and ``/experiment``.

    A recording split into segments (``run.mcap``, ``run.1.mcap``, ...) is read whole.

    Raises:
        RecordingError: the file does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"recording {path} does not exist")
    rows: dict[str, list[tuple[int, float, list[float | None]]]] = {}
    data = RecordingData()
    seen: set[tuple[str, int]] = set()
    schemas: dict[str, dict[str, Any]] = {}
    for segment in existing_segments(path):  # run.mcap, run.1.mcap, ... of a split recording
        for topic, _, message in iter_messages(segment):
            if topic == "/experiment":
                data.experiment = data.experiment or message
            elif topic == "/orchestrator/ticks" or _vector_kind(topic) is not None:
                k = int(message["k"])
                if (topic, k) in seen:
                    continue
                seen.add((topic, k))
                if topic == "/orchestrator/ticks":
                    data.ticks.append(message)
                    continue
                rows.setdefault(topic, []).append(
                    (k, _float(message.get("t")), list(message.get("values") or []))
                )
        schemas = {**read_schemas(segment), **schemas}
    graph_order = ((data.experiment or {}).get("graph") or {}).get("agents") or []
    rank = {name: i for i, name in enumerate(graph_order)}
    ordered = sorted(rows.items(), key=lambda item: rank.get(item[0][1:].split("/")[0], len(rank)))
    for topic, samples in ordered:
        agent, kind = topic[1:].split("/")
        series = _series(samples, _entry_names(schemas.get(topic, {})))
        (data.outputs if kind == "y" else data.inputs)[agent] = series
    return data


def plot_recording(
    path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    xy: Sequence[int] = (0, 1),
    agents: Iterable[str] | None = None,
) -> list[Path]:
    """Write the PNG plots of recording ``path`` into ``out_dir``; return the files written.

    Args:
        path: the MCAP recording.
        out_dir: folder for the PNG files (created if needed).
        xy: indices of the x and y position entries of ``y`` for the path plot.
        agents: only these agents (default: all).

    Raises:
        RecordingError: a missing file or bad ``xy`` indices.
    """
    if len(xy) != 2 or any(isinstance(i, bool) or not isinstance(i, int) or i < 0 for i in xy):
        raise RecordingError(f"xy must be two entry indices >= 0, got {xy!r}")
    data = load_recording(path)
    if agents is not None:
        wanted = set(agents)
        data.outputs = {a: s for a, s in data.outputs.items() if a in wanted}
        data.inputs = {a: s for a, s in data.inputs.items() if a in wanted}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    title = (data.experiment or {}).get("name") or Path(path).stem
    written: list[Path] = []
    jobs = (
        ("outputs.png", lambda: _signals_figure(data.outputs, f"{title}: outputs y")),
        ("inputs.png", lambda: _signals_figure(data.inputs, f"{title}: inputs u")),
        ("paths.png", lambda: _paths_figure(data.outputs, xy, f"{title}: x-y paths")),
        ("ticks.png", lambda: _ticks_figure(data.ticks, f"{title}: tick latency")),
    )
    for name, build in jobs:
        figure = build()
        if figure is None:
            logger.info("no data for %s; skipped", name)
            continue
        target = out / name
        figure.savefig(target, dpi=_DPI)
        plt.close(figure)
        written.append(target)
    return written


# -- figures -----------------------------------------------------------------------------------


def _signals_figure(signals: dict[str, Series], title: str) -> Figure | None:
    if not signals:
        return None
    width = max(series.values.shape[1] for series in signals.values())
    if width == 0:
        return None
    names = _common_names(signals, width)
    figure, axes = plt.subplots(
        width, 1, sharex=True, figsize=(8, 2.0 + 1.6 * width), squeeze=False
    )
    for entry, axis in enumerate(axes[:, 0]):
        for agent, series in signals.items():
            if entry < series.values.shape[1]:
                axis.plot(series.t, series.values[:, entry], label=agent, linewidth=1.2)
        axis.set_ylabel(names[entry])
        axis.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("experiment time t [s]")
    if len(signals) <= MAX_LEGEND_ENTRIES:
        axes[0, 0].legend(loc="best", fontsize="small", ncols=min(len(signals), 4))
    figure.suptitle(title)
    figure.tight_layout()
    return figure


def _paths_figure(outputs: dict[str, Series], xy: Sequence[int], title: str) -> Figure | None:
    ix, iy = xy
    usable = {a: s for a, s in outputs.items() if s.values.shape[1] > max(ix, iy)}
    if not usable:
        return None
    figure, axis = plt.subplots(figsize=(7, 7))
    for agent, series in usable.items():
        x, y = series.values[:, ix], series.values[:, iy]
        (line,) = axis.plot(x, y, label=agent, linewidth=1.2)
        finite = np.isfinite(x) & np.isfinite(y)
        if finite.any():
            first, last = np.flatnonzero(finite)[[0, -1]]
            axis.plot(x[first], y[first], "o", color=line.get_color())
            axis.plot(x[last], y[last], "s", color=line.get_color())
    any_series = next(iter(usable.values()))
    axis.set_xlabel(_axis_label(any_series.names[ix], ix))
    axis.set_ylabel(_axis_label(any_series.names[iy], iy))
    axis.set_aspect("equal", adjustable="datalim")
    axis.grid(True, alpha=0.3)
    if len(usable) <= MAX_LEGEND_ENTRIES:
        axis.legend(loc="best", fontsize="small")
    axis.set_title(f"{title}  (o start, s end)")
    figure.tight_layout()
    return figure


def _ticks_figure(ticks: list[dict[str, Any]], title: str) -> Figure | None:
    latency = tick_latencies(ticks)
    if latency is None:
        return None
    k, seconds, key = latency
    milliseconds = seconds * 1e3
    figure, (series_axis, histogram_axis) = plt.subplots(2, 1, figsize=(8, 6))
    series_axis.plot(k, milliseconds, linewidth=0.8)
    series_axis.set_xlabel("tick k")
    series_axis.set_ylabel(f"{key} [ms]")
    series_axis.grid(True, alpha=0.3)
    finite = milliseconds[np.isfinite(milliseconds)]
    histogram_axis.hist(finite, bins=min(60, max(5, finite.size // 10)))
    histogram_axis.set_xlabel(f"{key} [ms]")
    histogram_axis.set_ylabel("ticks")
    if finite.size:
        p50, p99 = np.percentile(finite, [50, 99])
        histogram_axis.set_title(
            f"median {p50:.3f} ms, p99 {p99:.3f} ms, max {finite.max():.3f} ms "
            f"({finite.size} ticks)"
        )
    figure.suptitle(title)
    figure.tight_layout()
    return figure


def tick_latencies(ticks: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray, str] | None:
    """``(k, latency [s], key)`` from ``/orchestrator/ticks`` messages, or ``None``.

    The latency is the first of :data:`TICK_LATENCY_KEYS` present in the messages, else
    ``done_s - sent_s`` when both are present.
    """
    if not ticks:
        return None
    k = np.array([int(message.get("k", i)) for i, message in enumerate(ticks)])
    for key in TICK_LATENCY_KEYS:
        if any(key in message for message in ticks):
            return k, np.array([_float(message.get(key)) for message in ticks]), key
    if all("done_s" in m and "sent_s" in m for m in ticks):
        done = np.array([_float(m["done_s"]) for m in ticks])
        sent = np.array([_float(m["sent_s"]) for m in ticks])
        return k, done - sent, "done_s - sent_s"
    return None


# -- helpers -----------------------------------------------------------------------------------


def _vector_kind(topic: str) -> str | None:
    parts = topic[1:].split("/") if topic.startswith("/") else []
    if len(parts) == 2 and parts[0] != "orchestrator" and parts[1] in ("y", "u"):
        return parts[1]
    return None


def _series(samples: list[tuple[int, float, list[float | None]]], names: tuple[str, ...]) -> Series:
    width = max((len(values) for _, _, values in samples), default=0)
    values = np.full((len(samples), width), np.nan)
    for row, (_, _, entries) in enumerate(samples):
        values[row, : len(entries)] = [_float(v) for v in entries]
    order = np.argsort([k for k, _, _ in samples], kind="stable")
    full_names = tuple(names[i] if i < len(names) else f"values[{i}]" for i in range(width))
    return Series(
        k=np.array([k for k, _, _ in samples])[order],
        t=np.array([t for _, t, _ in samples])[order],
        values=values[order],
        names=full_names,
    )


def _entry_names(schema: dict[str, Any]) -> tuple[str, ...]:
    """Entry names of a vector topic: schema properties described as ``values[i]``."""
    named: dict[int, str] = {}
    for name, spec in (schema.get("properties") or {}).items():
        description = spec.get("description", "") if isinstance(spec, dict) else ""
        if description.startswith("values[") and description.endswith("]"):
            index = description[len("values[") : -1]
            if index.isdigit():
                named[int(index)] = name
    return tuple(named.get(i, f"values[{i}]") for i in range(len(named)))


def _common_names(signals: dict[str, Series], width: int) -> tuple[str, ...]:
    names = []
    for entry in range(width):
        labels = {s.names[entry] for s in signals.values() if entry < len(s.names)}
        names.append(labels.pop() if len(labels) == 1 else f"values[{entry}]")
    return tuple(names)


def _axis_label(name: str, index: int) -> str:
    return f"y[{index}]" if name == f"values[{index}]" else f"{name} (y[{index}])"


def _float(value: Any) -> float:
    return (
        float(value) if isinstance(value, int | float) and not isinstance(value, bool) else np.nan
    )
