"""The deep checks behind ``hilswarm check``: everything that can be known before a run starts.

:func:`check_file` first loads the file (:func:`~hilswarm.orchestrator.experiment.parse_experiment`
checks its structure: keys, types, ranges, the adjacency matrix, agent names in the graph and
in ``[agents.*]``), then, when that succeeds, checks every agent against the code it names:

* the vehicle and controller names resolve (registry or ``package.module:Class``);
* the link URL has a known scheme; a vehicle that needs a board has a link; no two agents
  share one serial port or XBee address;
* the vehicle can be built *without a board* with the agent's pinout overrides, vehicle
  parameters, initial state and calibration (pin conflicts are ``PinError`` s, named by the
  agent's key);
* the calibration file exists and loads;
* the controller accepts the parameters (``validate_params``), a follower's ``leader`` is a
  direct neighbour (``A[i][leader] = 1``), and one dry controller step with zero data fits the
  vehicle's input and output sizes and the neighbours' output sizes;
* the board watchdog is longer than a control period.

Errors are :class:`~hilswarm.orchestrator.problems.Problem` s (the file cannot run as written);
warnings are Problems too but do not fail the check (e.g. a graph that is not connected, a
consensus gain that the Euler step makes unstable).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from hilswarm.agents.errors import (
    CalibrationError,
    ControllerError,
    DeviceError,
    HilswarmError,
    LinkUrlError,
    PinError,
    VehicleDefinitionError,
)
from hilswarm.agents.link.url import is_simulated, link_scheme
from hilswarm.agents.registry import (
    RegistryError,
    add_search_path,
    resolve_controller,
    resolve_vehicle,
)
from hilswarm.orchestrator.experiment import AgentSpec, Experiment, parse_experiment
from hilswarm.orchestrator.graph_facts import GraphFacts, graph_facts
from hilswarm.orchestrator.problems import ExperimentError, Problem
from hilswarm.orchestrator.xbee_check import check_gateway

logger = logging.getLogger(__name__)

#: Link kinds that one process at a time can own (so two agents cannot share them).
EXCLUSIVE_LINK_KINDS = ("serial", "xbee")
#: Runs longer than this many ticks are reported as a warning (recording size, run time).
MANY_TICKS = 5_000_000


@dataclass
class CheckReport:
    """Outcome of checking one experiment file.

    Attributes:
        path: the experiment file.
        experiment: the loaded experiment (``None`` when its structure is broken).
        problems: errors; the file cannot run while there are any.
        warnings: things that may be intended but are worth a look.
        facts: the graph facts (``None`` when the graph could not be read).
    """

    path: Path
    experiment: Experiment | None = None
    problems: list[Problem] = field(default_factory=list)
    warnings: list[Problem] = field(default_factory=list)
    facts: GraphFacts | None = None

    @property
    def ok(self) -> bool:
        """True when there is no problem (warnings allowed)."""
        return not self.problems

    def raise_for_problems(self) -> Experiment:
        """Return the experiment, or raise :class:`ExperimentError` listing every problem."""
        if self.problems or self.experiment is None:
            raise ExperimentError(self.problems or [Problem(self.path, "", "cannot be loaded")])
        return self.experiment


def check_file(path: str | Path, *, overrides: Mapping[str, Any] | None = None) -> CheckReport:
    """Load ``path`` (with ``overrides``, as :func:`load_experiment`) and run every check."""
    experiment, problems = parse_experiment(path, overrides=overrides)
    report = CheckReport(Path(path), experiment, list(problems))
    if experiment is not None:
        check_experiment(experiment, report)
    return report


def check_experiment(experiment: Experiment, report: CheckReport | None = None) -> CheckReport:
    """Run the deep checks on a loaded experiment, adding to ``report`` (or a new one)."""
    report = report or CheckReport(experiment.path, experiment)
    report.experiment = experiment
    add_search_path(experiment.path.parent)  # user "module:Class" names beside the file
    report.facts = graph_facts(experiment.agent_names, experiment.adjacency)
    _check_settings(experiment, report)
    _check_graph(experiment, report.facts, report)
    _check_shared_links(experiment, report)
    _check_mocap_bodies(experiment, report)
    built = {spec.name: _AgentCheck(experiment, spec, report) for spec in experiment.agents}
    for check in built.values():
        check.build()
    output_sizes = {name: check.n_outputs for name, check in built.items()}
    for check in built.values():
        check.check_controller(output_sizes, report.facts)
    vehicles = {name: check.vehicle for name, check in built.items()}
    check_gateway(experiment, vehicles, report.problems, report.warnings)
    return report


# -- experiment-wide checks ---------------------------------------------------------------------


def _check_settings(experiment: Experiment, report: CheckReport) -> None:
    path = experiment.path
    if experiment.watchdog_s is not None and experiment.watchdog_s <= experiment.dt:
        report.problems.append(
            Problem(
                path,
                "experiment.watchdog_s",
                f"{experiment.watchdog_s:g} s is not longer than the control period "
                f"{experiment.dt:g} s ({experiment.rate_hz:g} Hz): every board would go to safe "
                "mode between two ticks; make it a few periods long",
            )
        )
    if experiment.n_ticks > MANY_TICKS:
        report.warnings.append(
            Problem(
                path,
                "experiment.duration_s",
                f"{experiment.n_ticks} ticks ({experiment.duration_s:g} s at "
                f"{experiment.rate_hz:g} Hz) make a very large recording",
            )
        )


def _check_mocap_bodies(experiment: Experiment, report: CheckReport) -> None:
    """A real mocap system must see every agent's body now (``sim``: the agents bring them)."""
    mocap = experiment.mocap
    if mocap is None or mocap.system == "sim":
        return
    from hilswarm.agents.mocap.probe import probe  # noqa: PLC0415 - only with a real system

    try:
        seen = probe(mocap, duration_s=min(1.0, 20.0 / mocap.rate_hz + 0.2))
    except HilswarmError as exc:
        report.problems.append(Problem(experiment.path, "mocap.host", str(exc)))
        return
    visible = seen.visible()
    for spec in experiment.agents:
        if spec.body not in visible:
            key = f"agents.{spec.name}.mocap_body"
            report.problems.append(
                Problem(
                    experiment.path,
                    key,
                    f"body {spec.body!r} is not visible to {mocap.system} at {mocap.host}; "
                    f"it sees: {', '.join(visible) or 'no bodies'}",
                )
            )


def _check_graph(experiment: Experiment, facts: GraphFacts, report: CheckReport) -> None:
    path = experiment.path
    if len(facts.names) > 1 and not facts.weakly_connected:
        groups = "; ".join(", ".join(component) for component in facts.components)
        report.warnings.append(
            Problem(path, "graph", f"the graph is not connected: groups {groups}")
        )
    for name in facts.isolated:
        if len(facts.names) > 1:
            report.warnings.append(
                Problem(path, f"agents.{name}", f"agent {name!r} hears nobody and nobody hears it")
            )


def _check_shared_links(experiment: Experiment, report: CheckReport) -> None:
    owners: dict[str, str] = {}
    for spec in experiment.agents:
        if spec.link is None:
            continue
        try:
            kind = link_scheme(spec.link)
        except LinkUrlError:
            continue  # reported per agent
        if kind not in EXCLUSIVE_LINK_KINDS:
            continue
        key = spec.link.strip()
        if key in owners:
            report.problems.append(
                Problem(
                    experiment.path,
                    f"agents.{spec.name}.link",
                    f"{key!r} is already the link of agent {owners[key]!r}; a serial port or "
                    "XBee address belongs to one agent",
                )
            )
        else:
            owners[key] = spec.name


# -- per-agent checks --------------------------------------------------------------------------


class _AgentCheck:
    """Checks of one agent; :meth:`build` first, then :meth:`check_controller`."""

    def __init__(self, experiment: Experiment, spec: AgentSpec, report: CheckReport) -> None:
        self.experiment = experiment
        self.spec = spec
        self.report = report
        self.key = f"agents.{spec.name}"
        self.vehicle: Any = None
        self.n_inputs: int | None = None
        self.n_outputs: int | None = None

    def problem(self, key: str, message: str) -> None:
        self.report.problems.append(Problem(self.experiment.path, f"{self.key}.{key}", message))

    def warning(self, key: str, message: str) -> None:
        self.report.warnings.append(Problem(self.experiment.path, f"{self.key}.{key}", message))

    # -- vehicle, link, calibration -----------------------------------------------------------

    def build(self) -> None:
        spec = self.spec
        try:
            vehicle_cls = resolve_vehicle(spec.vehicle)
        except RegistryError as exc:
            self.problem("vehicle", str(exc))
            vehicle_cls = None
        link_kind = self._check_link(vehicle_cls)
        self._check_pose(vehicle_cls, link_kind)
        calibration = self._load_calibration()
        if vehicle_cls is None or calibration is _FAILED:
            return
        kwargs: dict[str, Any] = {"name": spec.name, "dt": self.experiment.dt}
        if spec.pinout:
            kwargs["pinout"] = spec.pinout
        if spec.vehicle_params:
            kwargs["params"] = spec.vehicle_params
        if spec.initial_state:
            kwargs["initial_state"] = spec.initial_state
        if calibration is not None:
            kwargs["calibration"] = calibration
        try:
            self.vehicle = vehicle_cls(**kwargs)
        except VehicleDefinitionError as exc:
            self.problem("vehicle", f"vehicle {spec.vehicle!r} is defined badly: {exc}")
            return
        except (HilswarmError, ValueError, TypeError) as exc:
            self.problem(_vehicle_error_key(exc), str(exc))
            return
        except NotImplementedError as exc:  # an unfinished `hilswarm new` skeleton
            self.problem("vehicle", f"vehicle {spec.vehicle!r} is not finished: {exc}")
            return
        except Exception as exc:  # user code: report it with the agent's key, never a traceback
            self.problem(
                "vehicle",
                f"constructing vehicle {spec.vehicle!r} failed: {type(exc).__name__}: {exc}",
            )
            return
        # Sizes may be per instance (a simulated vehicle takes them from its plant).
        n_inputs = getattr(self.vehicle, "n_inputs", None)
        n_outputs = getattr(self.vehicle, "n_outputs", None)
        if isinstance(n_inputs, int) and isinstance(n_outputs, int):
            self.n_inputs, self.n_outputs = n_inputs, n_outputs
        self._check_initial_state(link_kind)

    def _check_link(self, vehicle_cls: Any) -> str | None:
        spec = self.spec
        if spec.link is None:
            if vehicle_cls is not None and getattr(vehicle_cls, "needs_board", True):
                self.problem(
                    "link",
                    f'missing; vehicle {spec.vehicle!r} needs a board: give link = "sim://" '
                    "for a simulated board, or a serial port such as /dev/ttyUSB0",
                )
            return None
        try:
            kind = link_scheme(spec.link)
        except LinkUrlError as exc:
            self.problem("link", str(exc))
            return None
        if vehicle_cls is not None and not getattr(vehicle_cls, "needs_board", True):
            self.warning(
                "link",
                f"vehicle {spec.vehicle!r} needs no board; link {spec.link!r} is not used",
            )
        return kind

    def _check_pose(self, vehicle_cls: Any, link_kind: str | None) -> None:
        """A vehicle whose outputs come from motion capture needs a pose from somewhere."""
        if vehicle_cls is None or not getattr(vehicle_cls, "needs_pose", False):
            return
        simulated = link_kind in ("sim", "simavr") or (
            link_kind == "xbee" and self.spec.link is not None and is_simulated(self.spec.link)
        )
        if self.experiment.mocap is None and not simulated:
            self.problem(
                "link",
                f"agent {self.spec.name!r}: vehicle {self.spec.vehicle!r} needs its pose from "
                f"motion capture, link {self.spec.link!r} gives none and the experiment has no "
                '[mocap] section; add one (e.g. [mocap] system = "vicon", host = "...")',
            )

    def _load_calibration(self) -> Any:
        path = self.spec.calibration
        if path is None:
            return None
        if not path.is_file():
            self.problem("calibration", f"calibration file {str(path)!r} does not exist")
            return _FAILED
        try:
            from hilswarm.agents.calibration import Calibration  # noqa: PLC0415 - optional part
        except ImportError as exc:
            self.problem("calibration", f"calibration support is not available: {exc}")
            return _FAILED
        try:
            return Calibration.from_file(path)
        except (CalibrationError, OSError, ValueError) as exc:
            self.problem("calibration", f"cannot load {path.name}: {exc}")
            return _FAILED

    def _check_initial_state(self, link_kind: str | None) -> None:
        """Compare the initial state with the plant's state size when it can be known."""
        spec = self.spec
        vehicle = self.vehicle
        plant = getattr(vehicle, "plant", None)
        n_states = getattr(plant, "n_states", None)
        if isinstance(n_states, int) and spec.initial_state and len(spec.initial_state) != n_states:
            self.problem(
                "initial_state",
                f"has {len(spec.initial_state)} entries but the plant of vehicle "
                f"{spec.vehicle!r} has {n_states} states",
            )
            return
        if link_kind == "sim" and spec.initial_state:
            try:
                vehicle.simulated_hardware(initial_state=spec.initial_state, dt=self.experiment.dt)
            except (HilswarmError, ValueError, TypeError) as exc:
                self.problem("initial_state", f"the simulated hardware rejects it: {exc}")

    # -- controller ---------------------------------------------------------------------------

    def check_controller(self, output_sizes: Mapping[str, int | None], facts: GraphFacts) -> None:
        spec = self.spec
        try:
            controller_cls = resolve_controller(spec.controller)
        except RegistryError as exc:
            self.problem("controller", str(exc))
            return
        try:
            controller = controller_cls()
        except (HilswarmError, ValueError, TypeError) as exc:
            self.problem("controller", f"cannot build controller {spec.controller!r}: {exc}")
            return
        try:
            params = controller.validate_params(dict(spec.params))
        except (ControllerError, ValueError, TypeError) as exc:
            self.problem("params", str(exc))
            return
        neighbours = self.experiment.neighbours(spec.name)
        self._check_leader(params, neighbours)
        self._check_consensus_gain(controller, params, facts)
        if self.n_inputs is None:
            return
        self._dry_step(controller, params, neighbours, output_sizes)

    def _check_leader(self, params: Mapping[str, Any], neighbours: tuple[str, ...]) -> None:
        leader = params.get("leader")
        if not isinstance(leader, str):
            return
        names = self.experiment.agent_names
        if leader not in names:
            self.problem("params.leader", f"no agent named {leader!r}; agents: {', '.join(names)}")
        elif leader == self.spec.name:
            self.problem("params.leader", "an agent cannot follow itself")
        elif leader not in neighbours:
            i, j = self.experiment.index(self.spec.name), self.experiment.index(leader)
            self.problem(
                "params.leader",
                f"{self.spec.name!r} does not hear its leader {leader!r} through the graph: "
                f"adjacency[{i}][{j}] must be 1 (agent {self.spec.name} receives {leader}); "
                f"it hears: {', '.join(neighbours) or 'nobody'}",
            )

    def _check_consensus_gain(
        self, controller: Any, params: Mapping[str, Any], facts: GraphFacts
    ) -> None:
        from hilswarm.agents.controllers.consensus import LinearConsensus  # noqa: PLC0415

        if not isinstance(controller, LinearConsensus):
            return
        weights = params["weights"]
        degree = sum(weights.get(name, 1.0) for name in self.experiment.neighbours(self.spec.name))
        product = params["gain"] * self.experiment.dt * degree
        if product >= 1.0:
            self.warning(
                "params.gain",
                f"gain * dt * in-degree = {params['gain']:g} * {self.experiment.dt:g} * "
                f"{degree:g} = {product:g} >= 1: the Euler-stepped consensus may oscillate or "
                "diverge; lower the gain or raise rate_hz",
            )
        if not facts.has_spanning_tree:
            self.warning(
                "controller",
                "consensus needs a graph with a spanning tree (some agent heard, directly or "
                "not, by all); this graph has none, so the agents cannot agree",
            )

    def _dry_step(
        self,
        controller: Any,
        params: Mapping[str, Any],
        neighbours: tuple[str, ...],
        output_sizes: Mapping[str, int | None],
    ) -> None:
        from hilswarm.agents.control import ControlModel  # noqa: PLC0415 - numpy-heavy

        data = {
            name: (np.zeros(size) if size is not None else None)
            for name, size in ((name, output_sizes.get(name)) for name in neighbours)
        }
        try:
            model = ControlModel(
                controller,
                dt=self.experiment.dt,
                n_inputs=self.n_inputs or 0,
                n_outputs=self.n_outputs,
                params=params,
            )
            model.step(np.zeros(self.n_inputs or 0), np.zeros(self.n_outputs or 0), neighbours=data)
        except (ControllerError, ValueError, TypeError, IndexError, KeyError) as exc:
            self.problem(
                "controller",
                f"controller {self.spec.controller!r} does not fit vehicle {self.spec.vehicle!r} "
                f"({self.n_inputs} inputs, {self.n_outputs} outputs): a dry step with zero data "
                f"failed: {exc}",
            )


def _vehicle_error_key(exc: BaseException) -> str:
    """The agent key a vehicle construction error is about."""
    if isinstance(exc, PinError | DeviceError):
        return "pinout"
    if isinstance(exc, CalibrationError):
        return "calibration"
    text = str(exc)
    for key in ("pinout", "initial_state", "calibration", "limits"):
        if key in text:
            return "vehicle" if key == "limits" else key
    return "vehicle_params"


#: Marker: the calibration could not be loaded (a problem was reported).
_FAILED = object()
