"""Experiment files: load and validate the TOML file that describes one swarm run.

The format is documented in ``docs/experiments.md``. In short::

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

:func:`load_experiment` reads and checks the *structure* of the file (types, names, ranges,
the adjacency matrix) and reports every problem at once in one :class:`ExperimentError`; the
deeper checks that import vehicle and controller classes live in
:mod:`hilswarm.orchestrator.checks`.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from hilswarm.agents.mocap.config import MocapSettings, parse_mocap
from hilswarm.orchestrator.graph_io import read_graph_file, validate_matrix
from hilswarm.orchestrator.problems import ExperimentError, Problem

__all__ = [
    "AGENT_KEYS",
    "NAME_PATTERN",
    "OVERRIDE_KEYS",
    "AgentSpec",
    "Experiment",
    "ExperimentError",
    "Problem",
    "load_experiment",
    "parse_experiment",
    "parse_link_overrides",
]

#: Experiment and agent names: they become parts of bus keys and MCAP topics.
NAME_PATTERN = re.compile(r"^[A-Za-z0-9_-]+$")
MODES: tuple[str, ...] = ("lockstep", "realtime")
AGENT_LOSS_POLICIES: tuple[str, ...] = ("stop", "continue")
#: What the run does when an agent's vehicle enters safe mode (low battery, fault).
AGENT_SAFE_POLICIES: tuple[str, ...] = ("continue", "stop")
#: Highest control rate accepted [Hz]; above it no board link or bus keeps up.
MAX_RATE_HZ = 1000.0
#: Lockstep: how many ticks an agent may run ahead of the slowest one (1: a strict barrier).
DEFAULT_LOCKSTEP_WINDOW = 8
#: Largest accepted lockstep window [ticks].
MAX_LOCKSTEP_WINDOW = 1024

EXPERIMENT_KEYS: tuple[str, ...] = (
    "name",
    "rate_hz",
    "duration_s",
    "mode",
    "on_agent_loss",
    "on_agent_safe",
    "watchdog_s",
    "seed",
    "lockstep_window",
)
GRAPH_KEYS: tuple[str, ...] = ("agents", "adjacency", "file", "undirected")
AGENT_KEYS: tuple[str, ...] = (
    "vehicle",
    "link",
    "controller",
    "params",
    "vehicle_params",
    "pinout",
    "initial_state",
    "calibration",
    "mocap_body",
)
TOP_LEVEL_KEYS: tuple[str, ...] = (
    "experiment",
    "graph",
    "defaults",
    "agents",
    "gateway",
    "mocap",
)
#: Keys :func:`load_experiment` accepts in ``overrides``.
OVERRIDE_KEYS: tuple[str, ...] = (
    "mode",
    "duration_s",
    "rate_hz",
    "on_agent_loss",
    "on_agent_safe",
    "watchdog_s",
    "seed",
    "links",
)


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
        mocap_body: the agent's rigid body in the mocap system (``None``: the agent's name).
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

    @property
    def body(self) -> str:
        """The agent's rigid body name in the mocap system."""
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
    gateway: Any = None
    mocap: MocapSettings | None = None

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

    def index(self, name: str) -> int:
        """Row/column of agent ``name`` in :attr:`adjacency` (raises ``KeyError``)."""
        for i, spec in enumerate(self.agents):
            if spec.name == name:
                return i
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
        return tuple(spec.name for spec, a in zip(self.agents, row, strict=True) if a)

    def receivers(self, name: str) -> tuple[str, ...]:
        """Agents that receive ``name``'s output (``A[j][i] = 1``), in graph order."""
        column = self.adjacency[:, self.index(name)]
        return tuple(spec.name for spec, a in zip(self.agents, column, strict=True) if a)

    def graph_dict(self) -> dict[str, Any]:
        """The graph as plain JSON-able data: ``{"agents": [...], "adjacency": [[...]]}``."""
        return {"agents": list(self.agent_names), "adjacency": self.adjacency.tolist()}


def parse_link_overrides(items: Sequence[str]) -> dict[str, str]:
    """Turn command-line ``NAME=URL`` items (``--link leader=/dev/ttyUSB0``) into a mapping.

    Raises:
        ExperimentError: an item without ``=`` or with an empty name or URL.
    """
    links: dict[str, str] = {}
    problems: list[Problem] = []
    for item in items:
        name, sep, url = item.partition("=")
        if not sep or not name.strip() or not url.strip():
            problems.append(Problem("--link", item, "expected NAME=URL, e.g. leader=/dev/ttyUSB0"))
            continue
        links[name.strip()] = url.strip()
    if problems:
        raise ExperimentError(problems)
    return links


def load_experiment(path: str | Path, *, overrides: Mapping[str, Any] | None = None) -> Experiment:
    """Load, check and return the experiment in ``path``.

    Args:
        path: the TOML experiment file.
        overrides: values that replace the file's: ``mode``, ``duration_s``, ``rate_hz``,
            ``on_agent_loss``, ``watchdog_s``, ``seed`` and ``links`` (agent name -> link URL,
            e.g. ``{"leader": "/dev/ttyUSB0"}``).

    Raises:
        ExperimentError: listing every problem found (file, key, reason).
    """
    experiment, problems = parse_experiment(path, overrides=overrides)
    if problems or experiment is None:
        raise ExperimentError(problems or [Problem(path, "", "cannot be loaded")])
    return experiment


def parse_experiment(
    path: str | Path, *, overrides: Mapping[str, Any] | None = None
) -> tuple[Experiment | None, list[Problem]]:
    """Like :func:`load_experiment` but return ``(experiment or None, problems)``."""
    path = Path(path)
    problems: list[Problem] = []
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None, [Problem(path, "", "experiment file does not exist")]
    except (OSError, UnicodeDecodeError) as exc:
        return None, [Problem(path, "", f"cannot read experiment file: {exc}")]
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return None, [Problem(path, "", f"not valid TOML: {exc}")]
    experiment = _Parser(path, text, data, problems).parse(overrides or {})
    return (experiment if not problems else None), problems


class _Parser:
    """Walks the TOML data once, appending a Problem for everything wrong."""

    def __init__(self, path: Path, text: str, data: dict[str, Any], problems: list[Problem]):
        self.path = path
        self.text = text
        self.data = data
        self.problems = problems
        self.graph_names: list[str] | None = None

    def problem(self, key: str, message: str) -> None:
        self.problems.append(Problem(self.path, key, message))

    # -- whole file --------------------------------------------------------------------------

    def parse(self, overrides: Mapping[str, Any]) -> Experiment | None:
        self._unknown_keys(self.data, TOP_LEVEL_KEYS, "")
        header = self._table(self.data, "experiment", required=True)
        if "experiment" in self.data:
            settings = self._settings(header)
        else:  # reported once above, not once per missing key
            settings = dict.fromkeys(EXPERIMENT_KEYS)
        self._apply_overrides(settings, overrides)
        defaults = self._table(self.data, "defaults", required=False)
        self._unknown_keys(defaults, AGENT_KEYS, "defaults")
        agent_tables = self._table(self.data, "agents", required=True)
        specs = {
            name: self._agent(name, table, defaults)
            for name, table in agent_tables.items()
            if self._agent_table_ok(name, table)
        }
        graph = self._graph(self._table(self.data, "graph", required=True))
        mocap = self._mocap(settings, specs)
        links = overrides.get("links") or {}
        if isinstance(links, Mapping):
            for name, url in links.items():
                if name not in agent_tables:
                    self.problem(f"--link {name}", f"no agent named {name!r} in the experiment")
                elif not isinstance(url, str) or not url:
                    self.problem(f"--link {name}", f"link URL must be a non-empty string: {url!r}")
                elif specs.get(name) is not None:
                    specs[name] = replace(specs[name], link=url)
        else:
            self.problem("--link", "link overrides must map agent name -> URL")
        if graph is None:
            if self.graph_names is not None:
                self._match_names(self.graph_names, agent_tables)
            return None
        names, adjacency, graph_file = graph
        self._match_names(names, agent_tables)
        gateway = self._gateway(self.data.get("gateway"))
        if self.problems:
            return None
        adjacency.setflags(write=False)
        return Experiment(
            name=settings["name"],
            path=self.path,
            rate_hz=settings["rate_hz"],
            duration_s=settings["duration_s"],
            mode=settings["mode"],
            on_agent_loss=settings["on_agent_loss"],
            agents=tuple(specs[name] for name in names),
            adjacency=adjacency,
            source_text=self.text,
            watchdog_s=settings["watchdog_s"],
            seed=settings["seed"],
            graph_file=graph_file,
            on_agent_safe=settings["on_agent_safe"],
            lockstep_window=settings["lockstep_window"],
            gateway=gateway,
            mocap=mocap,
        )

    def _gateway(self, table: Any) -> Any:
        """``[gateway]`` as a GatewayConfig (``None`` when absent)."""
        if table is None:
            return None
        from hilswarm.agents.xbee.config import (  # noqa: PLC0415 - only files with [gateway]
            GatewayConfig,
            GatewayConfigError,
        )

        if not isinstance(table, dict):
            self.problem("gateway", "must be a table: [gateway]")
            return None
        try:
            return GatewayConfig.from_table(table)
        except GatewayConfigError as exc:
            self.problem("gateway", str(exc))
            return None

    # -- [mocap] ---------------------------------------------------------------------------

    def _mocap(
        self, settings: Mapping[str, Any], specs: Mapping[str, AgentSpec]
    ) -> MocapSettings | None:
        if "mocap" not in self.data:
            for name, spec in specs.items():
                if spec.mocap_body is not None:
                    self.problem(f"agents.{name}.mocap_body", "given but there is no [mocap]")
            return None
        mocap, problems = parse_mocap(self.data["mocap"])
        for key, message in problems:
            self.problem(key, message)
        if mocap is not None and settings.get("mode") == "lockstep":
            self.problem(
                "experiment.mode",
                'a [mocap] system runs on the wall clock; use mode = "realtime"',
            )
        bodies: dict[str, str] = {}
        for name, spec in specs.items():
            other = bodies.setdefault(spec.body, name)
            if other != name:
                self.problem(
                    f"agents.{name}.mocap_body",
                    f"body {spec.body!r} is already agent {other!r}'s",
                )
        return mocap

    # -- [experiment] ------------------------------------------------------------------------

    def _settings(self, table: dict[str, Any]) -> dict[str, Any]:
        self._unknown_keys(table, EXPERIMENT_KEYS, "experiment")
        settings: dict[str, Any] = {}
        name = table.get("name")
        if name is None:
            self.problem("experiment.name", "missing; give the experiment a name")
        elif not isinstance(name, str) or not NAME_PATTERN.match(name):
            self.problem(
                "experiment.name",
                f"{name!r} is not a valid name; use letters, digits, '_' and '-' only "
                "(it is part of bus keys)",
            )
        settings["name"] = name
        settings["rate_hz"] = self._rate(table.get("rate_hz"), "experiment.rate_hz")
        settings["duration_s"] = self._duration(table.get("duration_s"), "experiment.duration_s")
        settings["mode"] = self._choice(table.get("mode", "lockstep"), MODES, "experiment.mode")
        settings["on_agent_loss"] = self._choice(
            table.get("on_agent_loss", "stop"), AGENT_LOSS_POLICIES, "experiment.on_agent_loss"
        )
        settings["on_agent_safe"] = self._choice(
            table.get("on_agent_safe", "continue"), AGENT_SAFE_POLICIES, "experiment.on_agent_safe"
        )
        settings["watchdog_s"] = self._watchdog(table.get("watchdog_s"), "experiment.watchdog_s")
        settings["seed"] = self._seed(table.get("seed"), "experiment.seed")
        settings["lockstep_window"] = self._window(
            table.get("lockstep_window", DEFAULT_LOCKSTEP_WINDOW), "experiment.lockstep_window"
        )
        return settings

    def _apply_overrides(self, settings: dict[str, Any], overrides: Mapping[str, Any]) -> None:
        for key, value in overrides.items():
            where = f"override {key}"
            if key not in OVERRIDE_KEYS:
                self.problem(where, f"unknown override; expected one of {', '.join(OVERRIDE_KEYS)}")
            elif value is None or key == "links":
                continue
            elif key == "mode":
                settings["mode"] = self._choice(value, MODES, where)
            elif key == "on_agent_loss":
                settings["on_agent_loss"] = self._choice(value, AGENT_LOSS_POLICIES, where)
            elif key == "on_agent_safe":
                settings["on_agent_safe"] = self._choice(value, AGENT_SAFE_POLICIES, where)
            elif key == "rate_hz":
                settings["rate_hz"] = self._rate(value, where)
            elif key == "duration_s":
                settings["duration_s"] = self._duration(value, where)
            elif key == "watchdog_s":
                settings["watchdog_s"] = self._watchdog(value, where)
            else:
                settings["seed"] = self._seed(value, where)
        rate, duration = settings["rate_hz"], settings["duration_s"]
        if rate is not None and duration is not None and duration * rate < 1.0:
            self.problem(
                "experiment.duration_s",
                f"{duration} s at {rate} Hz is less than one tick; make it at least "
                f"{1.0 / rate:g} s",
            )

    def _rate(self, value: Any, key: str) -> float | None:
        if value is None:
            self.problem(key, "missing; give the control rate in Hz, e.g. rate_hz = 20")
            return None
        number = self._number(value, key)
        if number is not None and not 0.0 < number <= MAX_RATE_HZ:
            self.problem(
                key, f"{value!r} Hz is out of range; expected 0 < rate_hz <= {MAX_RATE_HZ:g}"
            )
            return None
        return number

    def _duration(self, value: Any, key: str) -> float | None:
        if value is None:
            self.problem(
                key, "missing; give the experiment length in seconds, e.g. duration_s = 30"
            )
            return None
        number = self._number(value, key)
        if number is not None and number <= 0.0:
            self.problem(key, f"{value!r} s is out of range; expected a duration > 0 s")
            return None
        return number

    def _watchdog(self, value: Any, key: str) -> float | None:
        if value is None:
            return None
        number = self._number(value, key)
        if number is not None and not 0.0 < number <= 60.0:
            self.problem(key, f"{value!r} s is out of range; expected 0 < watchdog_s <= 60")
            return None
        return number

    def _seed(self, value: Any, key: str) -> int | None:
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            self.problem(key, f"{value!r} is not a valid seed; expected an integer >= 0")
            return None
        return value

    def _window(self, value: Any, key: str) -> int:
        if (
            isinstance(value, bool)
            or not isinstance(value, int)
            or not 1 <= value <= MAX_LOCKSTEP_WINDOW
        ):
            self.problem(
                key,
                f"{value!r} is not a valid window; expected an integer number of ticks, "
                f"1 <= lockstep_window <= {MAX_LOCKSTEP_WINDOW}",
            )
            return DEFAULT_LOCKSTEP_WINDOW
        return value

    def _number(self, value: Any, key: str) -> float | None:
        if isinstance(value, bool) or not isinstance(value, int | float):
            self.problem(key, f"{value!r} is not a number")
            return None
        if not math.isfinite(value):
            self.problem(key, f"{value!r} is not a finite number")
            return None
        return float(value)

    def _choice(self, value: Any, choices: tuple[str, ...], key: str) -> Any:
        if value not in choices:
            self.problem(key, f"{value!r} is not one of " + ", ".join(repr(c) for c in choices))
            return None
        return value

    # -- [graph] -----------------------------------------------------------------------------

    def _graph(self, table: dict[str, Any]) -> tuple[list[str], np.ndarray, Path | None] | None:
        self._unknown_keys(table, GRAPH_KEYS, "graph")
        names = table.get("agents")
        if names is not None:
            names = self._graph_names(names)
            if names is None:
                return None
            self.graph_names = names
        undirected = table.get("undirected", False)
        if not isinstance(undirected, bool):
            self.problem("graph.undirected", f"{undirected!r} is not true or false")
            undirected = False
        has_matrix, has_file = "adjacency" in table, "file" in table
        if has_matrix == has_file:
            self.problem(
                "graph",
                "give exactly one of adjacency = [[...]] (with agents = [...]) or "
                'file = "<graph file>"',
            )
            return None
        if has_matrix:
            if names is None:
                self.problem("graph.agents", "missing; an inline adjacency needs agents = [...]")
                return None
            matrix = validate_matrix(
                table["adjacency"],
                names,
                file=self.path,
                key="graph.adjacency",
                problems=self.problems,
            )
            return (names, matrix, None) if matrix is not None else None
        file_name = table["file"]
        if not isinstance(file_name, str) or not file_name:
            self.problem("graph.file", f"{file_name!r} is not a file name")
            return None
        graph_path = (self.path.parent / file_name).resolve()
        result = read_graph_file(
            graph_path,
            names,
            undirected=undirected,
            file=self.path,
            key="graph.file",
            problems=self.problems,
        )
        if result is None:
            return None
        file_names, matrix = result
        bad = [n for n in file_names if not NAME_PATTERN.match(n)]
        for name in bad:
            self.problem(
                "graph.file",
                f"agent name {name!r} in {file_name} is not valid; use "
                "letters, digits, '_' and '-' only",
            )
        return (file_names, matrix, graph_path) if not bad else None

    def _graph_names(self, names: Any) -> list[str] | None:
        if not isinstance(names, list) or not names:
            self.problem("graph.agents", "must be a non-empty list of agent names")
            return None
        ok = True
        seen: set[str] = set()
        for i, name in enumerate(names):
            if not isinstance(name, str) or not NAME_PATTERN.match(name):
                self.problem(
                    f"graph.agents[{i}]",
                    f"{name!r} is not a valid agent name; use letters, digits, '_' and '-' only",
                )
                ok = False
            elif name in seen:
                self.problem(f"graph.agents[{i}]", f"agent {name!r} is listed twice")
                ok = False
            seen.add(name)
        return list(names) if ok else None

    def _match_names(self, names: Sequence[str], agent_tables: Mapping[str, Any]) -> None:
        for i, name in enumerate(names):
            if name not in agent_tables:
                self.problem(
                    f"graph.agents[{i}]",
                    f"agent {name!r} is in the graph but has no [agents.{name}] table",
                )
        for name in agent_tables:
            if name not in names:
                self.problem(
                    f"agents.{name}",
                    f"agent {name!r} has a table but is not in the graph "
                    f"(graph agents: {', '.join(names)})",
                )

    # -- [agents.*] --------------------------------------------------------------------------

    def _agent_table_ok(self, name: str, table: Any) -> bool:
        if not NAME_PATTERN.match(name):
            self.problem(
                f"agents.{name}",
                f"{name!r} is not a valid agent name; use letters, "
                "digits, '_' and '-' only (it is part of bus keys)",
            )
            return False
        if not isinstance(table, dict):
            self.problem(f"agents.{name}", "must be a table ([agents.<name>])")
            return False
        return True

    def _agent(self, name: str, table: dict[str, Any], defaults: dict[str, Any]) -> AgentSpec:
        key = f"agents.{name}"
        self._unknown_keys(table, AGENT_KEYS, key)
        merged = _merge(defaults, table)
        vehicle = self._string(merged.get("vehicle"), f"{key}.vehicle", required=True)
        controller = self._string(merged.get("controller"), f"{key}.controller", required=True)
        link = self._string(merged.get("link"), f"{key}.link", required=False)
        params = self._mapping(merged.get("params", {}), f"{key}.params")
        vehicle_params = self._mapping(merged.get("vehicle_params", {}), f"{key}.vehicle_params")
        pinout = self._pinout(merged.get("pinout", {}), f"{key}.pinout")
        initial_state = self._vector(merged.get("initial_state", []), f"{key}.initial_state")
        body = None
        if merged.get("mocap_body") is not None:
            body = self._string(merged["mocap_body"], f"{key}.mocap_body", required=True)
            if body is not None and not NAME_PATTERN.match(body):
                self.problem(f"{key}.mocap_body", f"{body!r}: use letters, digits, '_', '-'")
                body = None
        calibration = None
        if merged.get("calibration") is not None:
            text = self._string(merged["calibration"], f"{key}.calibration", required=True)
            calibration = (self.path.parent / text).resolve() if text else None
        return AgentSpec(
            name=name,
            vehicle=vehicle or "",
            link=link,
            controller=controller or "",
            params=params,
            vehicle_params=vehicle_params,
            pinout=pinout,
            initial_state=initial_state,
            calibration=calibration,
            mocap_body=body,
        )

    def _string(self, value: Any, key: str, *, required: bool) -> str | None:
        if value is None:
            if required:
                self.problem(key, "missing")
            return None
        if not isinstance(value, str) or not value.strip():
            self.problem(key, f"{value!r} is not a non-empty string")
            return None
        return value

    def _mapping(self, value: Any, key: str) -> dict[str, Any]:
        if not isinstance(value, dict):
            self.problem(key, f"must be a table, got {type(value).__name__}")
            return {}
        return dict(value)

    def _pinout(self, value: Any, key: str) -> dict[str, dict[str, int | str]]:
        pinout: dict[str, dict[str, int | str]] = {}
        if not isinstance(value, dict):
            self.problem(key, "must be a table: device -> { role = pin }")
            return pinout
        for device, roles in value.items():
            if not isinstance(roles, dict):
                self.problem(
                    f"{key}.{device}", 'must be a table of role = pin, e.g. { pwm = 5, fwd = "D4" }'
                )
                continue
            for role, pin in roles.items():
                if isinstance(pin, bool) or not isinstance(pin, int | str):
                    self.problem(
                        f"{key}.{device}.{role}",
                        f'{pin!r} is not a pin; expected a number (13) or a name ("D13", "A0")',
                    )
            pinout[device] = dict(roles)
        return pinout

    def _vector(self, value: Any, key: str) -> tuple[float, ...]:
        if not isinstance(value, list):
            self.problem(key, f"must be a list of numbers, got {value!r}")
            return ()
        numbers = []
        for i, item in enumerate(value):
            number = self._number(item, f"{key}[{i}]")
            numbers.append(number if number is not None else math.nan)
        return tuple(numbers)

    # -- helpers -----------------------------------------------------------------------------

    def _table(self, data: dict[str, Any], name: str, *, required: bool) -> dict[str, Any]:
        value = data.get(name)
        if value is None:
            if required:
                self.problem(name, f"missing [{name}] table")
            return {}
        if not isinstance(value, dict):
            self.problem(name, f"must be a table ([{name}]), got {type(value).__name__}")
            return {}
        return value

    def _unknown_keys(self, table: Mapping[str, Any], known: tuple[str, ...], where: str) -> None:
        for key in table:
            if key not in known:
                full = f"{where}.{key}" if where else key
                self.problem(full, f"unknown key; expected one of {', '.join(known)}")


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
