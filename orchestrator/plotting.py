"""PNG plots of a run recording (``hilswarm plot``), drawn with matplotlib's Agg backend.

From one MCAP file written by the recorder:

* ``outputs.png`` — every agent's output ``y`` against experiment time, one panel per output
  entry (named and in the units the vehicle declares, angles in [rad] unwrapped), one line per
  agent, the agents' references (controller parameter ``reference``) dashed;
* ``inputs.png`` — the same for the inputs ``u``;
* ``paths.png`` — the x–y paths of all agents in the world frame (entries ``xy`` of ``y``),
  start marked ``o``, end ``s``, the waypoints of the agents (parameters ``waypoints`` or
  ``waypoint``) as ``x`` joined by dotted lines;
* ``ticks.png`` — the tick latency from ``/orchestrator/ticks`` against experiment time, with
  the deadline (one period, ``1 / rate_hz``) drawn, and its histogram; late ticks (an answer
  not in when the next tick was due) marked ``x`` at the time their last answer came (from
  ``/orchestrator/late``), or ``^`` at the top when some answer never came;
* ``latency.png`` (``latency=True``) — where each tick's time went, per agent: controller,
  apply, board link, sense and bus (the rest of the answer time), stacked, against time, and
  the median split per agent; answers that came after their tick closed
  (``/orchestrator/late``) included.

Safe-mode entries, lost agents and e-stops (from ``/<agent>/status`` and
``/orchestrator/status``) are marked by vertical lines on every time axis; the agents' safe
entries after the run's stop began (``stopping`` on ``/orchestrator/status``: the run's orderly
end) are not. A plot whose data
is absent from the recording is skipped. Truncated recordings are read up to their last
complete chunk.
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
from hilswarm.agents.mcap_io import iter_messages
from hilswarm.agents.record_schema import entry_names_units
from hilswarm.orchestrator.output_paths import check_output_folder
from hilswarm.orchestrator.recover import check_mcap_magic
from hilswarm.orchestrator.segments import existing_segments
from matplotlib.axes import Axes
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
#: The ledger of one agent's tick in ``/orchestrator/ticks`` (``agents.<name>``), in the order
#: the time is spent, with the label of each part [s].
LEDGER_PARTS: tuple[tuple[str, str], ...] = (
    ("compute_s", "controller"),
    ("actuate_s", "apply u"),
    ("link_s", "board link"),
    ("sense_s", "sense y"),
    ("bus_s", "bus and waits"),
)
#: The link round trip through the XBee gateway, split (present in the ledger of an agent on
#: ``xbee://``): replaces ``link_s`` in the latency figure when a recording has it.
GATEWAY_PARTS: tuple[tuple[str, str], ...] = (
    ("gateway_bus_s", "link: bus hops"),
    ("gateway_s", "link: gateway"),
    ("radio_s", "link: radio"),
)
#: Lifecycle states marked on every time axis, and their line colours.
EVENT_COLOURS: dict[str, str] = {"safe": "tab:orange", "lost": "tab:red", "estop": "black"}
#: More agents than this and the legends are left out (they would cover the data).
MAX_LEGEND_ENTRIES = 12
#: Agents drawn in the latency figure's time panels (the slowest by median answer time).
MAX_LATENCY_PANELS = 6
_ANGLE_UNITS = ("rad",)
_DPI = 120


class PlotError(RecordingError):
    """A plot request names something the recording does not have (exit status 2)."""


@dataclass
class Series:
    """One vector topic read from a recording.

    Attributes:
        k: tick indices, shape ``(n,)``.
        t: experiment times [s], shape ``(n,)``.
        values: one row per message, shape ``(n, width)``; NaN where a message had fewer
            entries or a ``null``.
        names: names of the entries (from the topic's schema), or ``values[i]``.
        units: unit of each entry (``""``: none declared).
    """

    k: np.ndarray
    t: np.ndarray
    values: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...] = ()

    def label(self, entry: int) -> str:
        """Axis label of an entry: ``psi [rad]``."""
        unit = self.units[entry] if entry < len(self.units) else ""
        return f"{self.names[entry]} [{unit}]" if unit else self.names[entry]


@dataclass(frozen=True)
class Event:
    """A lifecycle event worth marking: an agent went safe or was lost, an e-stop."""

    t: float
    agent: str
    state: str
    detail: str = ""


@dataclass
class RecordingData:
    """The plottable content of one recording.

    Attributes:
        outputs: agent -> its ``/<agent>/y`` series.
        inputs: agent -> its ``/<agent>/u`` series.
        ticks: the ``/orchestrator/ticks`` messages (dicts), in order.
        late: the ``/orchestrator/late`` messages (answers after their tick closed), in order.
        experiment: the ``/experiment`` message, or ``None``.
        events: safe / lost / e-stop events, in time order.
    """

    outputs: dict[str, Series] = field(default_factory=dict)
    inputs: dict[str, Series] = field(default_factory=dict)
    ticks: list[dict[str, Any]] = field(default_factory=list)
    late: list[dict[str, Any]] = field(default_factory=list)
    experiment: dict[str, Any] | None = None
    events: list[Event] = field(default_factory=list)

    @property
    def agent_names(self) -> tuple[str, ...]:
        """Agents of the run (graph order), or those with data."""
        graph = ((self.experiment or {}).get("graph") or {}).get("agents")
        return tuple(graph) if graph else tuple(dict.fromkeys([*self.outputs, *self.inputs]))

    @property
    def period_s(self) -> float | None:
        """The tick period [s] (``1 / rate_hz``), when the recording says."""
        rate = ((self.experiment or {}).get("settings") or {}).get("rate_hz")
        return 1.0 / float(rate) if isinstance(rate, int | float) and rate > 0 else None

    def params(self, agent: str) -> dict[str, Any]:
        """The controller parameters ``agent`` ran with (from ``/experiment``)."""
        spec = ((self.experiment or {}).get("agents") or {}).get(agent) or {}
        return dict(spec.get("params") or {})


def load_recording(path: str | os.PathLike[str]) -> RecordingData:
    """Read ``/<agent>/y``, ``/<agent>/u``, statuses, ``/orchestrator/ticks``,
    ``/orchestrator/late`` and ``/experiment``.

    A recording split into segments (``run.mcap``, ``run.1.mcap``, ...) is read whole.

    Raises:
        RecordingError: the file does not exist, is a directory or is not an MCAP file.
    """
    path = Path(path)
    check_mcap_magic(path)
    rows: dict[str, list[tuple[int, float, list[float | None]]]] = {}
    data = RecordingData()
    seen: set[tuple[str, int]] = set()
    schemas: dict[str, dict[str, Any]] = {}
    stopping = False  # the run's stop began: agents going safe from here on is its orderly end
    for segment in existing_segments(path):  # run.mcap, run.1.mcap, ... of a split recording
        found: dict[str, dict[str, Any]] = {}
        for topic, _, message in iter_messages(segment, schemas=found):
            if topic == "/experiment":
                data.experiment = data.experiment or message
            elif topic.endswith("/status"):
                if topic == "/orchestrator/status" and message.get("state") == "stopping":
                    stopping = True
                elif not (stopping and message.get("state") == "safe"):
                    _add_event(data.events, topic, message)
            elif topic == "/orchestrator/late":
                data.late.append(message)
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
        schemas = {**found, **schemas}
    data.events.sort(key=lambda event: event.t)
    graph_order = ((data.experiment or {}).get("graph") or {}).get("agents") or []
    rank = {name: i for i, name in enumerate(graph_order)}
    ordered = sorted(rows.items(), key=lambda item: rank.get(item[0][1:].split("/")[0], len(rank)))
    for topic, samples in ordered:
        agent, kind = topic[1:].split("/")
        names, units = entry_names_units(schemas.get(topic, {}))
        series = _series(samples, names, units)
        (data.outputs if kind == "y" else data.inputs)[agent] = series
    return data


def _add_event(events: list[Event], topic: str, message: dict[str, Any]) -> None:
    state = str(message.get("state", ""))
    if state not in EVENT_COLOURS:
        return
    agent = str(message.get("agent") or topic[1:].split("/", maxsplit=1)[0])
    events.append(Event(_float(message.get("t")), agent, state, str(message.get("detail", ""))))


def plot_recording(
    path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    xy: Sequence[int | str] | None = None,
    agents: Iterable[str] | None = None,
    fields: Iterable[str] | None = None,
    latency: bool = False,
) -> list[Path]:
    """Write the PNG plots of recording ``path`` into ``out_dir``; return the files written.

    Args:
        path: the MCAP recording.
        out_dir: folder for the PNG files (created when the first one is written: nothing
            plottable leaves no folder; checked writable before anything is drawn).
        xy: the x and y position entries of ``y`` for the path plot, by index or name
            (checked: a bad one raises ``PlotError``); ``None``: entries 0 and 1, and no path
            plot when ``y`` has fewer.
        agents: only these agents (default: all).
        fields: only these entries of ``y`` and ``u``, by name (default: all).
        latency: also write ``latency.png``, where each tick's time went.

    Raises:
        RecordingError: a missing file, a directory, a file that is not MCAP.
        OutputPathError: ``out_dir`` cannot be written (a file, a read-only folder).
        PlotError: an unknown agent or field, or bad ``xy`` (the message lists the valid
            names).
    """
    data = load_recording(path)
    if agents is not None:
        _select_agents(data, list(agents))
    ix, iy = (0, 1) if xy is None else _xy_indices(data, xy)
    positions = dict(data.outputs)  # the path plot needs x and y whatever the fields shown
    if fields is not None:
        _select_fields(data, list(fields))
    out = Path(out_dir)
    check_output_folder(out, what="the plots")
    title = (data.experiment or {}).get("name") or Path(path).stem
    written: list[Path] = []
    jobs = [
        ("outputs.png", lambda: _signals_figure(data, data.outputs, f"{title}: outputs y", True)),
        ("inputs.png", lambda: _signals_figure(data, data.inputs, f"{title}: inputs u", False)),
        ("paths.png", lambda: _paths_figure(data, (ix, iy), f"{title}: x-y paths", positions)),
        ("ticks.png", lambda: _ticks_figure(data, f"{title}: tick latency")),
    ]
    if latency:
        jobs.append(("latency.png", lambda: _latency_figure(data, f"{title}: tick ledger")))
    for name, build in jobs:
        figure = build()
        if figure is None:
            logger.info("no data for %s; skipped", name)
            continue
        target = out / name
        out.mkdir(parents=True, exist_ok=True)
        figure.savefig(target, dpi=_DPI)
        plt.close(figure)
        written.append(target)
    return written


# -- selections --------------------------------------------------------------------------------


def _select_agents(data: RecordingData, wanted: list[str]) -> None:
    known = data.agent_names
    unknown = [name for name in wanted if name not in known]
    if unknown:
        raise PlotError(
            f"--agent: unknown agent(s) {', '.join(unknown)}; agents: {', '.join(known)}"
        )
    data.outputs = {a: s for a, s in data.outputs.items() if a in wanted}
    data.inputs = {a: s for a, s in data.inputs.items() if a in wanted}
    data.events = [e for e in data.events if e.agent in wanted or e.agent == "orchestrator"]


def _select_fields(data: RecordingData, wanted: list[str]) -> None:
    known = list(
        dict.fromkeys(n for s in [*data.outputs.values(), *data.inputs.values()] for n in s.names)
    )
    unknown = [name for name in wanted if name not in known]
    if unknown:
        raise PlotError(
            f"--field: unknown field(s) {', '.join(unknown)}; fields of y and u: {', '.join(known)}"
        )
    for signals in (data.outputs, data.inputs):
        for agent, series in list(signals.items()):
            keep = [i for i, name in enumerate(series.names) if name in wanted]
            if not keep:
                del signals[agent]
                continue
            signals[agent] = Series(
                series.k,
                series.t,
                series.values[:, keep],
                tuple(series.names[i] for i in keep),
                tuple(series.units[i] for i in keep if i < len(series.units)),
            )


def _xy_indices(data: RecordingData, xy: Sequence[int | str]) -> tuple[int, int]:
    """``xy`` as two entry indices of ``y`` (names resolved); PlotError lists valid ones."""
    names = list(dict.fromkeys(n for s in data.outputs.values() for n in s.names))
    width = max((s.values.shape[1] for s in data.outputs.values()), default=0)
    valid = f"indices 0..{width - 1}" + (f" or names {', '.join(names)}" if names else "")
    if len(xy) != 2:
        raise PlotError(f"--xy must be two entries of y like 0,1 or x,y ({valid}); got {xy!r}")
    indices = []
    for item in xy:
        if isinstance(item, str) and not item.isdigit():
            found = [s.names.index(item) for s in data.outputs.values() if item in s.names]
            if not found:
                raise PlotError(f"--xy: y has no entry {item!r}; valid: {valid}")
            indices.append(found[0])
            continue
        index = int(item)
        if isinstance(item, bool) or index < 0 or (data.outputs and index >= width):
            raise PlotError(f"--xy: y has no entry {item!r}; valid: {valid}")
        indices.append(index)
    return indices[0], indices[1]


# -- figures -----------------------------------------------------------------------------------


def _signals_figure(
    data: RecordingData, signals: dict[str, Series], title: str, references: bool
) -> Figure | None:
    if not signals:
        return None
    width = max(series.values.shape[1] for series in signals.values())
    if width == 0:
        return None
    figure, axes = plt.subplots(
        width, 1, sharex=True, figsize=(8, 2.0 + 1.6 * width), squeeze=False
    )
    colours: dict[str, str] = {}
    for entry, axis in enumerate(axes[:, 0]):
        labels = set()
        for agent, series in signals.items():
            if entry >= series.values.shape[1]:
                continue
            values = series.values[:, entry]
            unit = series.units[entry] if entry < len(series.units) else ""
            if unit in _ANGLE_UNITS:
                values = _unwrap(values)
            (line,) = axis.plot(series.t, values, label=agent, linewidth=1.2)
            colours[agent] = line.get_color()
            labels.add(series.label(entry))
            reference = _reference(data, agent, series) if references else None
            if reference is not None and entry < len(reference):
                axis.axhline(reference[entry], color=line.get_color(), linestyle="--",
                             linewidth=0.9, alpha=0.8)  # fmt: skip
        axis.set_ylabel(labels.pop() if len(labels) == 1 else f"values[{entry}]")
        axis.grid(True, alpha=0.3)
        _mark_events(axis, data.events)
    axes[-1, 0].set_xlabel("experiment time t [s]")
    if len(signals) <= MAX_LEGEND_ENTRIES:
        axes[0, 0].legend(loc="best", fontsize="small", ncols=min(len(signals), 4))
    notes = "dashed: reference; " if references and _any_reference(data, signals) else ""
    figure.suptitle(title + _events_note(data.events, notes))
    figure.tight_layout()
    return figure


def _reference(data: RecordingData, agent: str, series: Series) -> list[float] | None:
    """The agent's ``reference`` parameter when it is one number per entry of ``y``."""
    value = data.params(agent).get("reference")
    if (
        isinstance(value, list)
        and len(value) == series.values.shape[1]
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        return [float(v) for v in value]
    return None


def _any_reference(data: RecordingData, signals: dict[str, Series]) -> bool:
    return any(_reference(data, agent, series) is not None for agent, series in signals.items())


def _waypoints(data: RecordingData, agent: str) -> np.ndarray | None:
    """The agent's waypoints ``[[x, y], ...]`` (parameter ``waypoints`` or ``waypoint``)."""
    params = data.params(agent)
    raw = params.get("waypoints")
    if raw is None and isinstance(params.get("waypoint"), list):
        raw = [params["waypoint"]]
    try:
        points = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        return None
    if points.ndim != 2 or points.shape[1] < 2 or not len(points):
        return None
    return points[:, :2]


def _paths_figure(
    data: RecordingData,
    xy: tuple[int, int],
    title: str,
    outputs: dict[str, Series] | None = None,
) -> Figure | None:
    ix, iy = xy
    outputs = data.outputs if outputs is None else outputs
    usable = {a: s for a, s in outputs.items() if s.values.shape[1] > max(ix, iy)}
    if not usable:
        return None
    figure, axis = plt.subplots(figsize=(7, 7))
    drew_waypoints = False
    for agent, series in usable.items():
        x, y = series.values[:, ix], series.values[:, iy]
        (line,) = axis.plot(x, y, label=agent, linewidth=1.2)
        finite = np.isfinite(x) & np.isfinite(y)
        if finite.any():
            first, last = np.flatnonzero(finite)[[0, -1]]
            axis.plot(x[first], y[first], "o", color=line.get_color())
            axis.plot(x[last], y[last], "s", color=line.get_color())
        points = _waypoints(data, agent)
        if points is not None:
            axis.plot(points[:, 0], points[:, 1], "x:", color=line.get_color(), markersize=9)
            drew_waypoints = True
    any_series = next(iter(usable.values()))
    axis.set_xlabel(_position_label(any_series, ix))
    axis.set_ylabel(_position_label(any_series, iy))
    axis.set_aspect("equal", adjustable="datalim")
    axis.grid(True, alpha=0.3)
    if len(usable) <= MAX_LEGEND_ENTRIES:
        axis.legend(loc="best", fontsize="small")
    legend = "o start, s end" + (", x waypoints" if drew_waypoints else "")
    axis.set_title(f"{title}  ({legend})")
    figure.tight_layout()
    return figure


def _ticks_figure(data: RecordingData, title: str) -> Figure | None:
    latency = tick_latencies(data.ticks)
    if latency is None:
        return None
    _, seconds, key = latency
    t = np.array([_float(m.get("t")) for m in data.ticks])
    milliseconds = seconds * 1e3
    deadline = data.period_s
    figure, (series_axis, histogram_axis) = plt.subplots(2, 1, figsize=(8, 6))
    series_axis.plot(t, milliseconds, linewidth=0.8, label=key)
    n_late = sum(1 for message in data.ticks if message.get("late"))
    closed = late_tick_completions(data.ticks, data.late) if key == "completion_s" else {}
    if closed:  # late ticks closed before every answer came: when their last answer came
        by_k = {int(m.get("k", -1)): _float(m.get("t")) for m in data.ticks}
        late_t = np.array([by_k[k] for k in closed])
        late_ms = np.array(list(closed.values())) * 1e3
        known = np.isfinite(late_ms)
        series_axis.scatter(
            late_t[known], late_ms[known], marker="x", color="tab:red",
            label=f"late tick closed without an answer: its last answer ({int(known.sum())})",
        )  # fmt: skip
        if not known.all():
            top = max([*milliseconds[np.isfinite(milliseconds)], *late_ms[known], 0.0])
            top = max(top, (deadline or 0.0) * 1e3) * 1.05
            series_axis.scatter(
                late_t[~known], np.full(int((~known).sum()), top), marker="^", color="tab:red",
                label=f"late tick, an answer never came ({int((~known).sum())})",
            )  # fmt: skip
        milliseconds = np.concatenate([milliseconds, late_ms[known]])
    series_axis.set_xlabel("experiment time t [s]")
    series_axis.set_ylabel(f"{key} [ms]")
    series_axis.grid(True, alpha=0.3)
    _mark_events(series_axis, data.events)
    finite = milliseconds[np.isfinite(milliseconds)]
    histogram_axis.hist(finite, bins=min(60, max(5, finite.size // 10)))
    histogram_axis.set_xlabel(f"{key} [ms]")
    histogram_axis.set_ylabel("ticks")
    if deadline is not None:
        label = f"deadline (one period) {deadline * 1e3:g} ms"
        series_axis.axhline(deadline * 1e3, color="tab:red", linestyle="--", label=label)
        histogram_axis.axvline(deadline * 1e3, color="tab:red", linestyle="--", label=label)
    if deadline is not None or n_late:
        series_axis.legend(loc="best", fontsize="small")
    if finite.size:
        p50, p99 = np.percentile(finite, [50, 99])
        over = "" if deadline is None else f", {int((finite > deadline * 1e3).sum())} over"
        over += f", {n_late} late" if n_late else ""
        histogram_axis.set_title(
            f"median {p50:.3f} ms, p99 {p99:.3f} ms, max {finite.max():.3f} ms "
            f"({finite.size} ticks{over})"
        )
    figure.suptitle(title + _events_note(data.events, ""))
    figure.tight_layout()
    return figure


def ledger_parts(ticks: list[dict[str, Any]]) -> tuple[tuple[str, str], ...]:
    """The parts of the ledger in ``/orchestrator/ticks``: :data:`LEDGER_PARTS`, with the
    :data:`GATEWAY_PARTS` after ``link_s`` when any agent's ledger has them."""
    for message in ticks:
        agents = message.get("agents")
        if isinstance(agents, dict) and any(
            isinstance(entry, dict) and "gateway_s" in entry for entry in agents.values()
        ):
            at = [key for key, _ in LEDGER_PARTS].index("link_s") + 1
            return (*LEDGER_PARTS[:at], *GATEWAY_PARTS, *LEDGER_PARTS[at:])
    return LEDGER_PARTS


def tick_ledger(
    ticks: list[dict[str, Any]], late: Sequence[dict[str, Any]] = ()
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per agent ``(t [s], parts [s])`` from ``/orchestrator/ticks`` and the answers that came
    after their tick closed (``late``, ``/orchestrator/late``): one row per tick the agent
    answered, in time order, one column per :func:`ledger_parts` entry (NaN where not
    recorded).

    With the gateway parts, an agent's ``link_s`` column holds what its gateway parts do not
    explain: 0 when they are recorded (they sum to ``link_s``), all of ``link_s`` (and 0 in
    the gateway parts) for an agent without a gateway or a tick whose link had no answer from
    it.
    """
    keys = [key for key, _ in ledger_parts(ticks)]
    split = len(keys) > len(LEDGER_PARTS)
    link = keys.index("link_s")
    rows: dict[str, list[tuple[float, list[float]]]] = {}

    def add(agent: str, t: float, entry: dict[str, Any]) -> None:
        parts = [_float(entry.get(key)) for key in keys]
        if split:
            stages = parts[link + 1 : link + 1 + len(GATEWAY_PARTS)]
            if all(np.isfinite(stages)):
                parts[link] -= sum(stages)
            else:
                parts[link + 1 : link + 1 + len(GATEWAY_PARTS)] = [0.0] * len(stages)
        rows.setdefault(agent, []).append((t, parts))

    for message in ticks:
        t = _float(message.get("t"))
        for agent, entry in (message.get("agents") or {}).items():
            if isinstance(entry, dict):
                add(agent, t, entry)
    for entry in late:
        add(str(entry.get("agent")), _float(entry.get("t")), entry)
    for items in rows.values():
        items.sort(key=lambda row: row[0])
    return {
        agent: (np.array([r[0] for r in items]), np.array([r[1] for r in items], dtype=float))
        for agent, items in rows.items()
    }


def _latency_figure(data: RecordingData, title: str) -> Figure | None:
    ledger = tick_ledger(data.ticks, data.late)
    if data.outputs or data.inputs:
        shown = set(data.outputs) | set(data.inputs)
        ledger = {a: v for a, v in ledger.items() if a in shown}
    ledger = {a: v for a, v in ledger.items() if np.isfinite(v[1]).any()}
    if not ledger:
        return None
    medians = {a: np.nan_to_num(np.nanmedian(parts, axis=0)) for a, (_, parts) in ledger.items()}
    slowest = sorted(ledger, key=lambda a: -float(medians[a].sum()))[:MAX_LATENCY_PANELS]
    n = len(slowest)
    figure, axes = plt.subplots(n + 1, 1, figsize=(9, 2.4 * (n + 1) + 1), squeeze=False)
    labels = [label for _, label in ledger_parts(data.ticks)]
    deadline = data.period_s
    for axis, agent in zip(axes[:n, 0], slowest, strict=True):
        t, parts = ledger[agent]
        stacks = np.nan_to_num(np.clip(parts, 0.0, None)).T * 1e3
        axis.stackplot(t, stacks, labels=labels, alpha=0.85)
        if deadline is not None:
            axis.axhline(deadline * 1e3, color="tab:red", linestyle="--", linewidth=1)
        axis.set_ylabel(f"{agent} [ms]")
        axis.set_xlabel("experiment time t [s]")
        axis.grid(True, alpha=0.3)
        _mark_events(axis, data.events)
    axes[0, 0].legend(loc="upper right", fontsize="small", ncols=min(len(labels), 5))
    bars = axes[n, 0]
    names = list(ledger)
    left = np.zeros(len(names))
    for j, label in enumerate(labels):
        widths = np.array([medians[a][j] for a in names]) * 1e3
        bars.barh(names, widths, left=left, label=label)
        left += widths
    if deadline is not None:
        bars.axvline(deadline * 1e3, color="tab:red", linestyle="--", label="deadline")
    bars.set_xlabel("median time per tick [ms]")
    bars.invert_yaxis()
    bars.grid(True, axis="x", alpha=0.3)
    figure.suptitle(f"{title}: where each tick's time went (red dashed: deadline)")
    figure.tight_layout()
    return figure


def late_tick_completions(
    ticks: list[dict[str, Any]], late: Sequence[dict[str, Any]]
) -> dict[int, float]:
    """Late ticks closed before every answer came (``late`` listed, ``completion_s`` not
    recorded), by ``k``: their completion [s] with the answers that came after the close
    (``/orchestrator/late``): ``send_delay_s`` plus the last answer time; ``inf`` when some
    late agent's answer never came."""
    answers: dict[tuple[int, str], float] = {
        (int(m.get("k", -1)), str(m.get("agent"))): _float(m.get("answer_s")) for m in late
    }
    completions: dict[int, float] = {}
    for message in ticks:
        if not message.get("late") or np.isfinite(_float(message.get("completion_s"))):
            continue
        k = int(message.get("k", -1))
        times = [_float(entry.get("answer_s")) for entry in (message.get("agents") or {}).values()]
        times += [answers.get((k, str(agent)), np.inf) for agent in message["late"]]
        completions[k] = _float(message.get("send_delay_s")) + max(times)
    return completions


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


def _mark_events(axis: Axes, events: Sequence[Event]) -> None:
    """A vertical line per safe / lost / e-stop event (its colour says which)."""
    for event in events:
        if np.isfinite(event.t):
            axis.axvline(event.t, color=EVENT_COLOURS[event.state], linestyle=":", linewidth=1.2)


def _events_note(events: Sequence[Event], prefix: str) -> str:
    if not events:
        return f"\n({prefix.rstrip('; ')})" if prefix else ""
    seen = dict.fromkeys(f"{e.state} {e.agent} t={e.t:.2f} s" for e in events[:4])
    more = f" +{len(events) - 4}" if len(events) > 4 else ""
    return f"\n({prefix}dotted: {'; '.join(seen)}{more})"


def _unwrap(values: np.ndarray) -> np.ndarray:
    """An angle series [rad] without its ±π jumps (NaN gaps kept)."""
    result = values.copy()
    finite = np.isfinite(values)
    result[finite] = np.unwrap(values[finite])
    return result


def _position_label(series: Series, index: int) -> str:
    return f"{series.label(index)} (y[{index}])"


def _vector_kind(topic: str) -> str | None:
    parts = topic[1:].split("/") if topic.startswith("/") else []
    if len(parts) == 2 and parts[0] != "orchestrator" and parts[1] in ("y", "u"):
        return parts[1]
    return None


def _series(
    samples: list[tuple[int, float, list[float | None]]],
    names: tuple[str, ...],
    units: tuple[str, ...],
) -> Series:
    width = max((len(values) for _, _, values in samples), default=0)
    values = np.full((len(samples), width), np.nan)
    for row, (_, _, entries) in enumerate(samples):
        values[row, : len(entries)] = [_float(v) for v in entries]
    order = np.argsort([k for k, _, _ in samples], kind="stable")
    full_names = tuple(names[i] if i < len(names) else f"values[{i}]" for i in range(width))
    full_units = tuple(units[i] if i < len(units) else "" for i in range(width))
    return Series(
        k=np.array([k for k, _, _ in samples])[order],
        t=np.array([t for _, t, _ in samples])[order],
        values=values[order],
        names=full_names,
        units=full_units,
    )


def _float(value: Any) -> float:
    return (
        float(value) if isinstance(value, int | float) and not isinstance(value, bool) else np.nan
    )
