"""Experiment files: load and validate the TOML file that describes one swarm run.

The format is documented in ``docs/experiments.md`` and declared, key by key, in
:mod:`hilswarm.orchestrator.schema` (pydantic models, published as a JSON Schema). In short::

    [experiment]
    name = "lead_follow"        # [A-Za-z0-9_-]+, used in bus keys hilswarm/<name>/...
    rate_hz = 20.0              # control rate [Hz]
    duration_s = 30.0           # experiment length [s, experiment time]
    mode = "lockstep"           # or "realtime"
    on_agent_loss = "stop"      # or "continue"

    [graph]
    agents = ["leader", "f1"]
    adjacency = [[0, 0],        # A[i][j] = 1: agent i receives agent j's output
                 [1, 0]]
    # or: file = "ring6.csv" (a CSV matrix or a networkx-readable file beside this one)

    [agents.leader]
    vehicle = "frisbee"
    link = "sim://"
    controller = "waypoint"
    params = { ... }

:func:`load_experiment` validates every table against the schema, then the rules that span
tables (graph names vs agent tables, the tick count, the agent count, graph files inside the
experiment's folder, link URLs), and reports every problem at once in one
:class:`ExperimentError`; a broken table never hides the problems of the others
(:func:`load_parts` returns whatever could be loaded, for the deeper checks). The checks that
need the vehicle and controller classes live in :mod:`hilswarm.orchestrator.checks`.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Container, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np
from hilswarm.agents.errors import LinkUrlError
from hilswarm.agents.link.url import validate_link_url
from hilswarm.orchestrator.graph_io import read_graph_file, validate_matrix
from hilswarm.orchestrator.problems import ExperimentError, Problem, key_path, schema_problems
from hilswarm.orchestrator.schema import (
    DEFAULT_LOCKSTEP_WINDOW,
    DEFAULT_MAX_LATE_FRACTION,
    NAME_REGEX,
    AgentTable,
    ExperimentFile,
    ExperimentSection,
    GatewaySection,
    GraphSection,
    MocapSection,
)
from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError

__all__ = [
    "DEFAULT_MAX_AGENTS",
    "MAX_TICKS",
    "NAME_PATTERN",
    "OVERRIDE_KEYS",
    "AgentSpec",
    "Experiment",
    "ExperimentError",
    "ExperimentParts",
    "Problem",
    "load_experiment",
    "load_parts",
    "mocap_settings",
    "parse_experiment",
    "parse_link_overrides",
]

#: Experiment and agent names: they become parts of bus keys and MCAP topics.
NAME_PATTERN = re.compile(NAME_REGEX)
#: Keys :func:`load_experiment` accepts in ``overrides``: every [experiment] key but the name,
#: and ``links`` (agent name -> link URL).
OVERRIDE_KEYS: tuple[str, ...] = (
    *(key for key in ExperimentSection.model_fields if key != "name"),
    "links",
)
#: More agents than this need an explicit ``max_agents`` (``--max-agents N``): one OS process
#: per agent, so a typo in a generated graph must not start thousands of processes.
DEFAULT_MAX_AGENTS = 256
#: Most ticks a run may have (duration_s * rate_hz).
MAX_TICKS = 20_000_000
#: Memory the orchestrator keeps per planned tick [bytes]: the instance manager's completion
#: time of every tick (float64) and the summary's copy of it.
BYTES_PER_TICK = 16


@dataclass(frozen=True)
class AgentSpec:
    """One agent of an experiment, as written in ``[agents.<name>]``.

    Attributes:
        name: agent name (``[A-Za-z0-9_-]+``), unique in the experiment.
        vehicle: vehicle registry name or ``"package.module:Class"`` path.
        link: board link URL (``sim://``, ``/dev/ttyUSB0``, ``xbee://...``), or ``None`` for
            vehicles that need no board (``needs_board = False``).
        controller: controller registry name or ``"package.module:Class"`` path.
        params: controller parameters (validated by the controller's ``validate_params``).
        vehicle_params: keyword parameters of the vehicle (e.g. ``plant`` and its constants
            for a simulated vehicle).
        pinout: pin overrides, device -> role -> pin (``13``, ``"D13"``, ``"A0"``).
        initial_state: initial state of a simulated plant (units of that plant's state).
        calibration: calibration file (resolved against the experiment file's folder) or
            ``None``.
        mocap_body: the agent's rigid body in the motion-capture system (``None``: its name,
            see :attr:`body`).
        reply_every: ``xbee://`` robots in broadcast mode: answer every m-th tick (``None``:
            every tick).
    """

    name: str
    vehicle: str
    link: str | None
    controller: str
    params: dict[str, Any] = field(default_factory=dict)
    vehicle_params: dict[str, Any] = field(default_factory=dict)
    pinout: dict[str, dict[str, int | str]] = field(default_factory=dict)
    initial_state: tuple[float, ...] = ()
    calibration: Path | None = None
    mocap_body: str | None = None
    reply_every: int | None = None

    @property
    def body(self) -> str:
        """The agent's rigid body name in the motion-capture system."""
        return self.mocap_body or self.name


@dataclass(frozen=True, eq=False)
class Experiment:
    """A loaded and structurally valid experiment.

    Attributes:
        name: experiment name, the prefix of its bus keys (``hilswarm/<name>/...``).
        path: the experiment file.
        rate_hz: control rate [Hz]; one tick every ``dt = 1 / rate_hz`` seconds.
        duration_s: experiment length [s, experiment time].
        mode: ``"lockstep"`` (ticks as fast as agents answer, simulated time) or
            ``"realtime"`` (ticks on a monotonic wall-clock schedule).
        on_agent_loss: ``"stop"`` the whole run, or ``"continue"`` without the lost agent.
        on_agent_safe: when an agent's vehicle enters safe mode (low battery, e-stop, fault):
            ``"continue"`` the others go on (the safe agent keeps publishing its held outputs),
            or ``"stop"`` every agent goes to safe mode and the run ends.
        agents: the agents, in graph order (row ``i`` of ``adjacency`` is ``agents[i]``).
        adjacency: ``A`` (read-only ``int8``, ``n x n``): ``A[i][j] = 1`` means agent ``i``
            receives agent ``j``'s output.
        source_text: the experiment file's text as loaded (recorded in ``/experiment``).
        watchdog_s: board watchdog timeout [s], or ``None`` for the agent's default.
        seed: seed of every random generator of the run (noise, simulated mocap), or ``None``.
        graph_file: the graph file the adjacency came from, or ``None`` when inline.
        lockstep_window: lockstep only: an agent computes tick ``k`` as soon as its own
            neighbours' ``y_{k-1}`` are in, at most this many ticks ahead of the slowest
            agent [ticks]. Results do not depend on it (an agent's input depends on its
            neighbours' outputs only); ``1`` makes every tick a swarm-wide barrier.
        on_recording_failure: when the recording cannot be written (disk full): ``"stop"``
            (robots safe, the run ends) or ``"continue"`` unrecorded.
        max_late_fraction: realtime: late ticks above this fraction of all ticks make the run
            degraded (0..1).
        realtime_clock: realtime: ``"shared"`` (agents on the orchestrator's host keep the
            manager's schedule on the shared monotonic clock; the default) or ``"manager"``
            (one tick message per period; docs/running.md, Ticks and modes).
        mocap: the ``[mocap]`` table (motion capture) as a
            :class:`~hilswarm.agents.mocap.config.MocapSettings`, or ``None``.
        gateway: the ``[gateway]`` table (XBee gateway) as a
            :class:`~hilswarm.agents.xbee.config.GatewayConfig`, or ``None``.
    """

    name: str
    path: Path
    rate_hz: float
    duration_s: float
    mode: Literal["lockstep", "realtime"]
    on_agent_loss: Literal["stop", "continue"]
    agents: tuple[AgentSpec, ...]
    adjacency: np.ndarray
    source_text: str = field(repr=False)
    watchdog_s: float | None = None
    seed: int | None = None
    graph_file: Path | None = None
    on_agent_safe: Literal["continue", "stop"] = "continue"
    lockstep_window: int = DEFAULT_LOCKSTEP_WINDOW
    on_recording_failure: Literal["stop", "continue"] = "stop"
    max_late_fraction: float = DEFAULT_MAX_LATE_FRACTION
    realtime_clock: Literal["shared", "manager"] = "shared"
    mocap: Any = None
    gateway: Any = None

    @property
    def dt(self) -> float:
        """Control period [s]."""
        return 1.0 / self.rate_hz

    @property
    def n_ticks(self) -> int:
        """Number of ticks of a full run (``k = 0 .. n_ticks - 1``)."""
        return max(1, round(self.duration_s * self.rate_hz))

    @property
    def agent_names(self) -> tuple[str, ...]:
        """Agent names in graph order."""
        return tuple(spec.name for spec in self.agents)

    @cached_property
    def _positions(self) -> dict[str, int]:
        return {spec.name: i for i, spec in enumerate(self.agents)}

    def index(self, name: str) -> int:
        """Row/column of agent ``name`` in :attr:`adjacency` (raises ``KeyError``)."""
        position = self._positions.get(name)
        if position is not None:
            return position
        raise KeyError(
            f"experiment {self.name!r} has no agent {name!r}; agents: "
            + ", ".join(self.agent_names)
        )

    def agent(self, name: str) -> AgentSpec:
        """The :class:`AgentSpec` of agent ``name`` (raises ``KeyError``)."""
        return self.agents[self.index(name)]

    def neighbours(self, name: str) -> tuple[str, ...]:
        """Agents whose output ``name`` receives (``A[i][j] = 1``), in graph order."""
        row = self.adjacency[self.index(name)]
        return tuple(self.agents[j].name for j in np.flatnonzero(row))

    def receivers(self, name: str) -> tuple[str, ...]:
        """Agents that receive ``name``'s output (``A[j][i] = 1``), in graph order."""
        column = self.adjacency[:, self.index(name)]
        return tuple(self.agents[j].name for j in np.flatnonzero(column))

    def graph_dict(self) -> dict[str, Any]:
        """The graph as plain JSON-able data: ``{"agents": [...], "adjacency": [[...]]}``."""
        return {"agents": list(self.agent_names), "adjacency": self.adjacency.tolist()}


@dataclass
class ExperimentParts:
    """Whatever could be loaded from an experiment file, also from a broken one.

    The deeper checks (:mod:`~hilswarm.orchestrator.checks`) check every agent in
    :attr:`agents` even when another table is broken, so one pass reports everything.

    Attributes:
        path: the experiment file.
        problems: every problem found while loading.
        settings: the valid ``[experiment]`` table (overrides applied), or ``None``.
        agents: agent name -> spec, for every agent whose table (with ``[defaults]``) is valid.
        graph: ``(names, adjacency, graph file or None)`` when the graph is valid.
        mocap: the valid ``[mocap]`` table as a
            :class:`~hilswarm.agents.mocap.config.MocapSettings`, or ``None``.
        gateway: the valid ``[gateway]`` table as a
            :class:`~hilswarm.agents.xbee.config.GatewayConfig`, or ``None``.
        remote: the agents that run on other machines (``hilswarm run --remote``; every one
            but its own for ``hilswarm agent``).
        experiment: the experiment, when there is no problem at all.
    """

    path: Path
    problems: list[Problem] = field(default_factory=list)
    settings: ExperimentSection | None = None
    agents: dict[str, AgentSpec] = field(default_factory=dict)
    graph: tuple[list[str], np.ndarray, Path | None] | None = None
    mocap: Any = None
    gateway: Any = None
    remote: Container[str] = ()
    experiment: Experiment | None = None
    _positions: dict[str, int] | None = field(default=None, repr=False)

    @property
    def dt(self) -> float | None:
        """Control period [s] when ``[experiment]`` is valid."""
        return 1.0 / self.settings.rate_hz if self.settings is not None else None

    @property
    def agent_names(self) -> tuple[str, ...] | None:
        """Agent names in graph order when the graph is valid."""
        return tuple(self.graph[0]) if self.graph is not None else None

    def neighbours(self, name: str) -> tuple[str, ...] | None:
        """Agents whose output ``name`` receives, when the graph is valid (see
        :meth:`Experiment.neighbours`)."""
        if self.graph is None:
            return None
        names, adjacency, _ = self.graph
        if self._positions is None:
            self._positions = {n: i for i, n in enumerate(names)}
        position = self._positions.get(name)
        if position is None:
            return None
        return tuple(names[j] for j in np.flatnonzero(adjacency[position]))


def self_clocked(
    mode: str, realtime_clock: str, gateway: object | None, *, remote: bool = False
) -> bool:
    """Whether a run's agents keep the manager's schedule on the shared monotonic clock (one
    schedule message) instead of one tick message per period (docs/running.md, "Ticks and
    modes"): realtime, ``realtime_clock = "shared"``, every agent on the orchestrator's host
    (``remote``: some join from others) and no XBee ``gateway`` (it is driven by ticks)."""
    return mode == "realtime" and realtime_clock == "shared" and not remote and gateway is None


def parse_link_overrides(items: Sequence[str]) -> dict[str, str]:
    """Turn command-line ``NAME=URL`` items (``--link leader=/dev/ttyUSB0``) into a mapping.

    Raises:
        ExperimentError: an item without ``=`` or with an empty name or URL, or a second link
            for the same agent (which one was meant?).
    """
    links: dict[str, str] = {}
    problems: list[Problem] = []
    for item in items:
        name, sep, url = item.partition("=")
        if not sep or not name.strip() or not url.strip():
            problems.append(Problem("--link", item, "expected NAME=URL, e.g. leader=/dev/ttyUSB0"))
            continue
        name = name.strip()
        if name in links:
            problems.append(
                Problem("--link", item, f"agent {name!r} has a --link already ({links[name]})")
            )
            continue
        links[name] = url.strip()
    if problems:
        raise ExperimentError(problems)
    return links


def load_experiment(
    path: str | Path,
    *,
    overrides: Mapping[str, Any] | None = None,
    max_agents: int = DEFAULT_MAX_AGENTS,
    remote: Container[str] = (),
) -> Experiment:
    """Load, check and return the experiment in ``path``.

    Args:
        path: the TOML experiment file.
        overrides: values that replace the file's: any ``[experiment]`` key but ``name``
            (``mode``, ``duration_s``, ``rate_hz``, ``on_agent_loss``, ``watchdog_s``, ``seed``,
            ...) and ``links`` (agent name -> link URL, e.g. ``{"leader": "/dev/ttyUSB0"}``).
        max_agents: most agents accepted (default :data:`DEFAULT_MAX_AGENTS`).
        remote: agents whose board is on another machine (``hilswarm run --remote``): their
            links are checked without what only that machine can know (device, firmware).

    Raises:
        ExperimentError: listing every problem found (file, key, reason).
    """
    experiment, problems = parse_experiment(
        path, overrides=overrides, max_agents=max_agents, remote=remote
    )
    if problems or experiment is None:
        raise ExperimentError(problems or [Problem(path, "", "cannot be loaded")])
    return experiment


def parse_experiment(
    path: str | Path,
    *,
    overrides: Mapping[str, Any] | None = None,
    max_agents: int = DEFAULT_MAX_AGENTS,
    remote: Container[str] = (),
) -> tuple[Experiment | None, list[Problem]]:
    """Like :func:`load_experiment` but return ``(experiment or None, problems)``."""
    parts = load_parts(path, overrides=overrides, max_agents=max_agents, remote=remote)
    return parts.experiment, parts.problems


def load_parts(
    path: str | Path,
    *,
    overrides: Mapping[str, Any] | None = None,
    max_agents: int = DEFAULT_MAX_AGENTS,
    remote: Container[str] = (),
) -> ExperimentParts:
    """Load ``path`` as far as it goes: see :class:`ExperimentParts`."""
    path = Path(path)
    parts = ExperimentParts(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        parts.problems.append(Problem(path, "", "experiment file does not exist"))
        return parts
    except (OSError, UnicodeDecodeError) as exc:
        parts.problems.append(Problem(path, "", f"cannot read experiment file: {exc}"))
        return parts
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        parts.problems.append(Problem(path, "", f"not valid TOML: {exc}"))
        return parts
    _Loader(parts, data, max_agents, remote).load(overrides or {}, text)
    return parts


class _Loader:
    """Validates each table with its schema model, then the rules that span tables."""

    def __init__(
        self,
        parts: ExperimentParts,
        data: dict[str, Any],
        max_agents: int,
        remote: Container[str],
    ) -> None:
        self.parts = parts
        self.remote = remote
        parts.remote = remote
        self.path = parts.path
        self.data = data
        self.max_agents = max_agents

    def problem(self, key: str, message: str) -> None:
        self.parts.problems.append(Problem(self.path, key, message))

    def validate(self, model: type[BaseModel], value: Any, key: str) -> Any:
        """``value`` validated with ``model`` (problems at ``key``), or ``None``."""
        try:
            return model.model_validate(value)
        except ValidationError as exc:
            self.parts.problems.extend(schema_problems(exc, self.path, key, model))
            return None

    def load(self, overrides: Mapping[str, Any], text: str) -> None:
        for key in self.data:
            if key not in ExperimentFile.model_fields:
                known = ", ".join(ExperimentFile.model_fields)
                self.problem(key, f"unknown key; expected one of {known}")
        settings = self._settings(overrides)
        gateway = self.parts.gateway = self._gateway()
        agent_tables = self._table("agents", required=True)
        too_many = len(agent_tables) > self.max_agents
        if too_many:
            self._too_many("agents", len(agent_tables))
        else:
            self._agents(agent_tables)
        self._links(overrides.get("links") or {}, agent_tables)
        mocap = self.parts.mocap = self._mocap(settings)
        graph = self._graph(self._table("graph", required=True), skip=too_many)
        if too_many or self.parts.problems or settings is None or graph is None:
            return
        names, adjacency, graph_file = graph
        adjacency.setflags(write=False)
        self.parts.experiment = Experiment(
            name=settings.name,
            path=self.path,
            rate_hz=settings.rate_hz,
            duration_s=settings.duration_s,
            mode=settings.mode,
            on_agent_loss=settings.on_agent_loss,
            agents=tuple(self.parts.agents[name] for name in names),
            adjacency=adjacency,
            source_text=text,
            watchdog_s=settings.watchdog_s,
            seed=settings.seed,
            graph_file=graph_file,
            on_agent_safe=settings.on_agent_safe,
            lockstep_window=settings.lockstep_window,
            on_recording_failure=settings.on_recording_failure,
            max_late_fraction=settings.max_late_fraction,
            realtime_clock=settings.realtime_clock,
            mocap=mocap,
            gateway=gateway,
        )

    def _mocap(self, settings: ExperimentSection | None) -> Any:
        """``[mocap]`` as a MocapSettings (``None`` when absent), and the rules between it, the
        run's mode and the agents' bodies."""
        if "mocap" not in self.data:
            for name, spec in self.parts.agents.items():
                if spec.mocap_body is not None:
                    self.problem(f"agents.{name}.mocap_body", "given but there is no [mocap]")
            return None
        mocap, problems = mocap_settings(self.data["mocap"], file=self.path)
        self.parts.problems.extend(problems)
        if settings is not None and settings.mode == "lockstep":
            self.problem(
                "experiment.mode", 'a [mocap] system runs on the wall clock; use mode = "realtime"'
            )
        if mocap is not None and settings is not None:
            self._mocap_spread(mocap, settings)
        bodies: dict[str, str] = {}
        for name, spec in self.parts.agents.items():
            other = bodies.setdefault(spec.body, name)
            if other != name:
                self.problem(
                    f"agents.{name}.mocap_body", f"body {spec.body!r} is already agent {other!r}'s"
                )
        return mocap

    def _mocap_spread(self, mocap: Any, settings: ExperimentSection) -> None:
        """``tick_spread_frames``: counted in frames of locked ticks, every tick of one control
        period within that period, and not with ``tick_frames_only`` (docs/mocap.md)."""
        spread = mocap.tick_spread_frames
        if spread <= 1:
            return
        key = "mocap.tick_spread_frames"
        if not mocap.tick_lock:
            self.problem(key, "needs tick_lock = true (the spread is counted in locked frames)")
        if mocap.tick_frames_only:
            self.problem(
                key,
                "does not go with tick_frames_only = true: the mocap process publishes the "
                "frames of the swarm's due times, not of each agent's phase",
            )
        if mocap.spread_left_s(1.0 / settings.rate_hz) <= 0.0:
            self.problem(
                key,
                f"{spread} frames ({1000.0 * spread / mocap.rate_hz:.3g} ms at [mocap] rate_hz = "
                f"{mocap.rate_hz:g}) do not fit in one control period "
                f"({1000.0 / settings.rate_hz:.3g} ms at rate_hz = {settings.rate_hz:g}); at most "
                f"{math.ceil(mocap.rate_hz / settings.rate_hz) - 1}",
            )

    def _gateway(self) -> Any:
        """``[gateway]`` as a GatewayConfig (``None`` when absent)."""
        section = self._section("gateway", GatewaySection)
        if section is None:
            return None
        from hilswarm.agents.xbee.config import (  # noqa: PLC0415 - only files with [gateway]
            GatewayConfig,
            GatewayConfigError,
        )

        try:
            return GatewayConfig.from_table(section.model_dump())
        except GatewayConfigError as exc:
            self.problem("gateway", str(exc))
            return None

    def _too_many(self, key: str, count: int) -> None:
        limit = (
            "the most accepted without an explicit limit"
            if self.max_agents == DEFAULT_MAX_AGENTS
            else "the limit set by --max-agents"
        )
        self.problem(
            key,
            f"{count} agents is more than {self.max_agents}, {limit} (one process per agent); "
            f"pass --max-agents {count} to allow it",
        )

    # -- tables --------------------------------------------------------------------------------

    def _table(self, name: str, *, required: bool) -> dict[str, Any]:
        value = self.data.get(name)
        if value is None:
            if required:
                self.problem(name, f"missing [{name}] table")
            return {}
        if not isinstance(value, dict):
            self.problem(name, f"must be a table ([{name}]), got {type(value).__name__}")
            return {}
        return value

    def _section(self, name: str, model: type[BaseModel]) -> Any:
        if name not in self.data:
            return None
        table = self._table(name, required=False)
        return self.validate(model, table, name) if isinstance(self.data[name], dict) else None

    # -- [experiment] and overrides ------------------------------------------------------------

    def _settings(self, overrides: Mapping[str, Any]) -> ExperimentSection | None:
        table = self._table("experiment", required=True)
        settings = self.validate(ExperimentSection, table, "experiment") if table else None
        changes: dict[str, Any] = {}
        for key, value in overrides.items():
            where = f"override {key}"
            if key not in OVERRIDE_KEYS:
                self.problem(where, f"unknown override; expected one of {', '.join(OVERRIDE_KEYS)}")
            elif value is not None and key != "links":
                try:
                    changes[key] = _FIELD_ADAPTERS[key].validate_python(value)
                except ValidationError as exc:
                    self.parts.problems.extend(
                        schema_problems(exc, self.path, where, ExperimentSection)
                    )
        if settings is None:
            return None
        settings = settings.model_copy(update=changes)
        self.parts.settings = settings if self._ticks_ok(settings) else None
        return self.parts.settings

    def _ticks_ok(self, settings: ExperimentSection) -> bool:
        rate, duration = settings.rate_hz, settings.duration_s
        ticks = duration * rate
        if ticks < 0.5:  # round() would give 0 ticks
            self.problem(
                "experiment.duration_s",
                f"{duration:g} s at {rate:g} Hz is less than one tick; make it at least "
                f"{1.0 / rate:g} s",
            )
            return False
        if ticks > MAX_TICKS:
            self.problem(
                "experiment.duration_s",
                f"{duration:g} s at {rate:g} Hz is {ticks:.3g} ticks, more than {MAX_TICKS:,}; "
                f"the orchestrator alone would need {_bytes(ticks * BYTES_PER_TICK)} of memory "
                f"for it ({BYTES_PER_TICK} bytes per tick, at most "
                f"{_bytes(MAX_TICKS * BYTES_PER_TICK)}): shorten duration_s or lower rate_hz, "
                "and run long experiments in parts",
            )
            return False
        return True

    # -- [agents.*] and [defaults] -------------------------------------------------------------

    def _agents(self, agent_tables: Mapping[str, Any]) -> None:
        defaults_table = self._table("defaults", required=False)
        defaults = self.validate(AgentTable, defaults_table, "defaults")
        base = defaults.model_dump(exclude_unset=True) if defaults is not None else {}
        for name, table in agent_tables.items():
            key = f"agents.{name}"
            if not NAME_PATTERN.match(name):
                self.problem(
                    key,
                    f"{name!r} is not a valid agent name; use letters, digits, '_' and '-' only "
                    "(it is part of bus keys)",
                )
                continue
            if not isinstance(table, dict):
                self.problem(key, f"must be a table ([{key}])")
                continue
            own = self.validate(AgentTable, table, key)
            merged = _merge(base, own.model_dump(exclude_unset=True) if own else table)
            missing = [k for k in ("vehicle", "controller") if merged.get(k) is None]
            for item in missing:
                self.problem(f"{key}.{item}", f"missing (in [{key}] or [defaults])")
            if missing or own is None:
                continue
            spec = self._spec(name, merged)
            if spec is not None:
                self.parts.agents[name] = spec

    def _spec(self, name: str, merged: dict[str, Any]) -> AgentSpec | None:
        link = merged.get("link")
        if link is not None and not self._link_ok(name, link):
            return None
        calibration = merged.get("calibration")
        return AgentSpec(
            name=name,
            vehicle=merged["vehicle"],
            link=link,
            controller=merged["controller"],
            params=dict(merged.get("params", {})),
            vehicle_params=dict(merged.get("vehicle_params", {})),
            pinout={d: dict(roles) for d, roles in merged.get("pinout", {}).items()},
            initial_state=tuple(merged.get("initial_state", ())),
            calibration=(self.path.parent / calibration).resolve() if calibration else None,
            mocap_body=merged.get("mocap_body"),
            reply_every=merged.get("reply_every"),
        )

    def _link_ok(self, name: str, url: str) -> bool:
        """Agent ``name``'s link URL is complete and its device exists (as a run opens it)."""
        try:
            validate_link_url(url, local=name not in self.remote)
        except LinkUrlError as exc:
            self.problem(f"agents.{name}.link", str(exc))
            return False
        return True

    def _links(self, links: Any, agent_tables: Mapping[str, Any]) -> None:
        if not isinstance(links, Mapping):
            self.problem("--link", "link overrides must map agent name -> URL")
            return
        for name, url in links.items():
            if name not in agent_tables:
                self.problem(f"--link {name}", f"no agent named {name!r} in the experiment")
            elif not isinstance(url, str) or not url.strip():
                self.problem(f"--link {name}", f"link URL must be a non-empty string: {url!r}")
            elif name in self.parts.agents:
                spec = self.parts.agents[name]
                if self._link_ok(name, url):
                    self.parts.agents[name] = replace(spec, link=url.strip())
                else:
                    del self.parts.agents[name]

    # -- [graph] -------------------------------------------------------------------------------

    def _graph(
        self, table: dict[str, Any], *, skip: bool
    ) -> tuple[list[str], np.ndarray, Path | None] | None:
        section: GraphSection | None = self.validate(GraphSection, table, "graph")
        if section is None or skip:
            return None
        names = self._graph_names(section.agents) if section.agents is not None else None
        if section.agents is not None and names is None:
            return None
        if (section.adjacency is None) == (section.file is None):
            self.problem(
                "graph",
                "give exactly one of adjacency = [[...]] (with agents = [...]) or "
                'file = "<graph file>"',
            )
            if names is not None:
                self._match_names(names)
            return None
        if section.adjacency is not None:
            if names is None:
                self.problem("graph.agents", "missing; an inline adjacency needs agents = [...]")
                return None
            self._match_names(names)
            matrix = validate_matrix(
                section.adjacency,
                names,
                file=self.path,
                key="graph.adjacency",
                problems=self.parts.problems,
            )
            graph = (names, matrix, None) if matrix is not None else None
        else:
            graph = self._graph_file(section, names)
        if graph is not None:
            self.parts.graph = graph
        return graph

    def _graph_file(
        self, section: GraphSection, names: list[str] | None
    ) -> tuple[list[str], np.ndarray, Path | None] | None:
        file_name = section.file or ""
        folder = self.path.parent.resolve()
        graph_path = (folder / file_name).resolve()
        if not graph_path.is_relative_to(folder):
            self.problem(
                "graph.file",
                f"{file_name!r} is outside the experiment's folder {str(folder)!r}; keep graph "
                "files beside the experiment file (or in a folder below it)",
            )
            if names is not None:
                self._match_names(names)
            return None
        result = read_graph_file(
            graph_path,
            names,
            undirected=section.undirected,
            file=self.path,
            key="graph.file",
            problems=self.parts.problems,
        )
        if result is None:
            if names is not None:
                self._match_names(names)
            return None
        file_names, matrix = result
        bad = [n for n in file_names if not NAME_PATTERN.match(n)]
        for name in bad:
            self.problem(
                "graph.file",
                f"agent name {name!r} in {file_name} is not valid; use "
                "letters, digits, '_' and '-' only",
            )
        if len(file_names) > self.max_agents:
            self._too_many("graph.file", len(file_names))
            return None
        self._match_names(file_names)
        return (file_names, matrix, graph_path) if not bad else None

    def _graph_names(self, names: list[str]) -> list[str] | None:
        if len(names) > self.max_agents:
            self._too_many("graph.agents", len(names))
            return None
        seen: set[str] = set()
        ok = True
        for i, name in enumerate(names):
            if name in seen:
                self.problem(f"graph.agents[{i}]", f"agent {name!r} is listed twice")
                ok = False
            seen.add(name)
        return names if ok else None

    def _match_names(self, names: Sequence[str]) -> None:
        agent_tables = self.data.get("agents")
        if not isinstance(agent_tables, dict):
            return
        for i, name in enumerate(names):
            if name not in agent_tables:
                self.problem(
                    f"graph.agents[{i}]",
                    f"agent {name!r} is in the graph but has no [agents.{name}] table",
                )
        listed = set(names)
        for name in agent_tables:
            if name not in listed:
                self.problem(
                    f"agents.{name}",
                    f"agent {name!r} has a table but is not in the graph "
                    f"(graph agents: {', '.join(names)})",
                )


_OVERRIDE_CONFIG = ConfigDict(strict=True, allow_inf_nan=False)
#: One validator per overridable [experiment] key, built from the schema's own field.
_FIELD_ADAPTERS: dict[str, TypeAdapter[Any]] = {
    key: TypeAdapter(info.rebuild_annotation(), config=_OVERRIDE_CONFIG)
    for key, info in ExperimentSection.model_fields.items()
}


def mocap_settings(
    table: Any, *, file: Path | str, where: str = "mocap"
) -> tuple[Any, list[Problem]]:
    """A ``[mocap]`` table checked against the schema and read into a
    :class:`~hilswarm.agents.mocap.config.MocapSettings`: ``(settings or None, problems)``.

    Used for experiment files and for ``hilswarm mocap --system S --host H``.
    """
    try:
        section = MocapSection.model_validate(table)
    except ValidationError as exc:
        return None, schema_problems(exc, file, where, MocapSection)
    problems = []
    if section.host is None and section.system != "sim":
        problems.append(
            Problem(
                file,
                key_path(where, ("host",)),
                'missing; give the mocap server address, e.g. host = "..."',
            )
        )
    if section.sim is not None and section.system != "sim":
        problems.append(Problem(file, key_path(where, ("sim",)), 'only for system = "sim"'))
    period_ms = 1000.0 / section.rate_hz
    for key in ("tick_lag_ms", "pose_wait_ms"):  # both must be under one frame period
        value = getattr(section, key)
        if value is not None and value >= period_ms:
            problems.append(
                Problem(
                    file,
                    key_path(where, (key,)),
                    f"{value:g} ms is not under one frame period "
                    f"({period_ms:.3g} ms at rate_hz = {section.rate_hz:g})",
                )
            )
    if problems:
        return None, problems
    from hilswarm.agents.mocap.config import MocapSettings  # noqa: PLC0415 - mocap files only

    data = section.model_dump(exclude_none=True)
    data.setdefault("host", "127.0.0.1")
    return MocapSettings.from_dict(data), []


def _bytes(count: float) -> str:
    """``count`` bytes in a readable unit (``1.6 GB``)."""
    for unit in ("bytes", "kB", "MB", "GB", "TB"):
        if count < 1000.0 or unit == "TB":
            return f"{count:.3g} {unit}"
        count /= 1000.0
    return f"{count:.3g} TB"


def _merge(defaults: Mapping[str, Any], table: Mapping[str, Any]) -> dict[str, Any]:
    """``table`` over ``defaults``, merging sub-tables recursively (params, pinout, ...)."""
    merged = dict(defaults)
    for key, value in table.items():
        base = merged.get(key)
        if isinstance(base, dict) and isinstance(value, dict):
            merged[key] = _merge(base, value)
        else:
            merged[key] = value
    return merged
