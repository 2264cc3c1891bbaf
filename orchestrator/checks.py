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
* the board watchdog is longer than a control period;
* with ``[mocap] system = "sim"`` every agent's board is simulated (the simulated cameras see
  only simulated plants); a real mocap system sees every agent's body now; ticks no faster
  than the camera frames, and ``tick_frames_only`` and ``tick_spread_frames`` only where the
  manager's schedule is known in advance (warnings);
* with ``xbee://`` links, the gateway's radio budget and, in realtime, a tick's latency
  through the radio (:mod:`~hilswarm.orchestrator.xbee_check`).

Errors are :class:`~hilswarm.orchestrator.problems.Problem` s (the file cannot run as written);
warnings are Problems too but do not fail the check (e.g. a graph that is not connected, a
consensus gain that the Euler step makes unstable).
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Container, Iterable, Mapping
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
    class_path,
    resolve_controller,
    resolve_vehicle,
)
from hilswarm.orchestrator.class_inspect import static_class_problem
from hilswarm.orchestrator.experiment import (
    DEFAULT_MAX_AGENTS,
    AgentSpec,
    Experiment,
    ExperimentParts,
    load_parts,
    self_clocked,
)
from hilswarm.orchestrator.graph_facts import GraphFacts, graph_facts
from hilswarm.orchestrator.problems import ExperimentError, Problem
from hilswarm.orchestrator.schema import ExperimentSection
from hilswarm.orchestrator.xbee_check import check_gateway

logger = logging.getLogger(__name__)

#: Link kinds that one process at a time can own (so two agents cannot share them); XBee
#: addresses are compared by xbee_check (parsed, so two spellings of one address clash).
EXCLUSIVE_LINK_KINDS = ("serial",)
#: Runs longer than this many ticks are reported as a warning (recording size, run time).
MANY_TICKS = 5_000_000
#: ``[mocap] tick_spread_frames``: warn when the last phase's agents have less than this share of
#: the control period to answer (docs/mocap.md: 16 agents at 240 Hz frames and 23 Hz control,
#: a spread of 8 frames, 23 % left, more than halved the pose latency's p99 in most runs; 10
#: frames, 4 % left, was no better than none).
SPREAD_ANSWER_FRACTION = 0.2
#: ``[mocap]`` locked ticks with no spread: suggest ``tick_spread_frames`` from this many agents
#: per core that all sense at one frame (docs/mocap.md: on 2 cores at 240 Hz, 4 agents met the
#: pose latency's target without a spread, 8 and 16 missed it without and met it with one).
SPREAD_ADVICE_AGENTS_PER_CORE = 4


@dataclass
class CheckReport:
    """Outcome of checking one experiment file.

    Attributes:
        path: the experiment file.
        experiment: the loaded experiment (``None`` when its structure is broken).
        problems: errors; the file cannot run while there are any.
        warnings: things that may be intended but are worth a look.
        facts: the graph facts (``None`` when the graph could not be read).
        unused_links: agents whose vehicle needs no board although a link is given (warned).
    """

    path: Path
    experiment: Experiment | None = None
    problems: list[Problem] = field(default_factory=list)
    warnings: list[Problem] = field(default_factory=list)
    facts: GraphFacts | None = None
    unused_links: set[str] = field(default_factory=set)

    @property
    def ok(self) -> bool:
        """True when there is no problem (warnings allowed)."""
        return not self.problems

    def raise_for_problems(self) -> Experiment:
        """Return the experiment, or raise :class:`ExperimentError` listing every problem."""
        if self.problems or self.experiment is None:
            raise ExperimentError(self.problems or [Problem(self.path, "", "cannot be loaded")])
        return self.experiment


def check_file(
    path: str | Path,
    *,
    overrides: Mapping[str, Any] | None = None,
    max_agents: int = DEFAULT_MAX_AGENTS,
    remote: Container[str] = (),
    remote_gateway: bool = False,
) -> CheckReport:
    """Load ``path`` (with ``overrides``, as :func:`load_experiment`) and run every check.

    The agents whose own tables are valid are checked even when another part of the file is
    broken, so every problem shows in one pass. ``remote`` agents' boards and a
    ``remote_gateway``'s coordinator are on other machines: their devices are not looked for.
    """
    parts = load_parts(path, overrides=overrides, max_agents=max_agents, remote=remote)
    report = CheckReport(Path(path), parts.experiment, list(parts.problems))
    check_parts(parts, report, remote_gateway=remote_gateway)
    return report


def check_parts(
    parts: ExperimentParts, report: CheckReport, *, remote_gateway: bool = False
) -> None:
    """The deep checks of everything in ``parts`` that loaded (see :func:`check_file`)."""
    add_search_path(parts.path.parent)  # user "module:Class" names beside the file
    if parts.graph is not None:
        names, adjacency, _ = parts.graph
        report.facts = graph_facts(names, adjacency)
        _check_graph(parts.path, report.facts, report)
    if parts.settings is not None:
        _check_settings(parts.path, parts.settings, report)
    _check_shared_links(parts, report)
    _check_mocap_bodies(parts, report)
    _check_mocap_timing(parts, report)
    shared: dict[tuple[str, str], _Outcome] = {}
    built = {name: _AgentCheck(parts, spec, report, shared) for name, spec in parts.agents.items()}
    for check in built.values():
        check.build()
    _check_sim_mocap_links(parts, built.values(), report)
    output_sizes = {name: check.n_outputs for name, check in built.items()}
    for check in built.values():
        check.check_controller(output_sizes, report.facts)
    vehicles = {name: check.vehicle for name, check in built.items()}
    check_gateway(parts, vehicles, report.problems, report.warnings, local=not remote_gateway)


# -- experiment-wide checks ---------------------------------------------------------------------


def _check_settings(path: Path, settings: ExperimentSection, report: CheckReport) -> None:
    dt = 1.0 / settings.rate_hz
    if settings.watchdog_s is not None and settings.watchdog_s <= dt:
        report.problems.append(
            Problem(
                path,
                "experiment.watchdog_s",
                f"{settings.watchdog_s:g} s is not longer than the control period "
                f"{dt:g} s ({settings.rate_hz:g} Hz): every board would go to safe "
                "mode between two ticks; make it a few periods long",
            )
        )
    n_ticks = max(1, round(settings.duration_s * settings.rate_hz))
    if n_ticks > MANY_TICKS:
        report.warnings.append(
            Problem(
                path,
                "experiment.duration_s",
                f"{n_ticks} ticks ({settings.duration_s:g} s at "
                f"{settings.rate_hz:g} Hz) make a very large recording",
            )
        )


def _check_mocap_bodies(parts: ExperimentParts, report: CheckReport) -> None:
    """A real mocap system must see every agent's body now (``sim``: the agents bring them)."""
    mocap = parts.mocap
    if mocap is None or mocap.system == "sim":
        return
    from hilswarm.agents.mocap.probe import probe  # noqa: PLC0415 - only with a real system

    try:
        seen = probe(mocap, duration_s=min(1.0, 20.0 / mocap.rate_hz + 0.2))
    except HilswarmError as exc:
        report.problems.append(Problem(parts.path, "mocap.host", str(exc)))
        return
    visible = seen.visible()
    for spec in parts.agents.values():
        if spec.body not in visible:
            key = f"agents.{spec.name}.mocap_body"
            report.problems.append(
                Problem(
                    parts.path,
                    key,
                    f"body {spec.body!r} is not visible to {mocap.system} at {mocap.host}; "
                    f"it sees: {', '.join(visible) or 'no bodies'}",
                )
            )


def _check_mocap_timing(parts: ExperimentParts, report: CheckReport) -> None:
    """Ticks faster than the camera frames repeat poses and cannot lock to the frames;
    ``tick_frames_only`` and ``tick_spread_frames`` need the manager's schedule, which tick
    messages replace."""
    mocap, settings = parts.mocap, parts.settings
    if mocap is None or settings is None:
        return
    realtime = settings.mode == "realtime"  # (lockstep with [mocap] is refused elsewhere)
    remote = [name for name in parts.agents if name in parts.remote]
    if realtime and not self_clocked(
        settings.mode, settings.realtime_clock, parts.gateway, remote=bool(remote)
    ):
        if parts.gateway is not None:
            driver = "an XBee [gateway]"
        elif settings.realtime_clock != "shared":
            driver = 'realtime_clock = "manager"'
        else:
            driver = f"the manager, for the agent on another machine (--remote {remote[0]}),"
        if mocap.tick_frames_only:
            report.warnings.append(
                Problem(
                    parts.path,
                    "mocap.tick_frames_only",
                    f"has no effect here: {driver} drives the ticks with tick messages, which "
                    "tell no tick in advance, so every frame's poses are published "
                    '(docs/mocap.md, "Only the frames the ticks use")',
                )
            )
        if mocap.tick_spread_frames > 1:
            report.warnings.append(
                Problem(
                    parts.path,
                    "mocap.tick_spread_frames",
                    f"has no effect here: {driver} drives the ticks with tick messages, and "
                    "every agent ticks when its message comes "
                    '(docs/mocap.md, "Ticks spread over the frames")',
                )
            )
    if realtime:
        _check_spread_margin(parts, report)
        if not remote and self_clocked(settings.mode, settings.realtime_clock, parts.gateway):
            _advise_spread(parts, report)
    if settings.rate_hz <= mocap.rate_hz:
        return
    report.warnings.append(
        Problem(
            parts.path,
            "experiment.rate_hz",
            f"{settings.rate_hz:g} Hz ticks are faster than the mocap frames "
            f"([mocap] rate_hz = {mocap.rate_hz:g} Hz): only about "
            f"{mocap.rate_hz / settings.rate_hz:.0%} of the ticks get a new pose (the others "
            "sense the last one again), and the ticks cannot lock to the frames "
            f"(docs/mocap.md); use rate_hz <= {mocap.rate_hz:g} Hz, or a faster frame rate if "
            "the system has one",
        )
    )


def fitting_spread(mocap_rate_hz: float, control_rate_hz: float) -> int:
    """The most frames ``tick_spread_frames`` may span and still leave the last phase's agents
    :data:`SPREAD_ANSWER_FRACTION` of the control period to answer (at least 1)."""
    return max(1, math.floor((1.0 - SPREAD_ANSWER_FRACTION) * mocap_rate_hz / control_rate_hz))


def available_cores() -> int:
    """CPU cores this process may run on (its agents are forked from it)."""
    return len(os.sched_getaffinity(0))


def _advise_spread(parts: ExperimentParts, report: CheckReport) -> None:
    """Many agents per core, ticks locked to the frames, no spread: every agent senses at the
    same frame and their ticks run one after another, so the last ones sense several ms after
    it. Warn, with the spread that fits (:data:`SPREAD_ADVICE_AGENTS_PER_CORE`)."""
    mocap, settings = parts.mocap, parts.settings
    agents, cores = len(parts.agents), available_cores()
    if mocap.tick_spread_frames > 1 or not mocap.tick_lock:
        return
    if agents < SPREAD_ADVICE_AGENTS_PER_CORE * cores:
        return
    fitting = min(agents, fitting_spread(mocap.rate_hz, settings.rate_hz))
    if fitting < 2:
        return  # the frames come too seldom for turns
    report.warnings.append(
        Problem(
            parts.path,
            "mocap.tick_spread_frames",
            f"{agents} agents on {cores} cores all sense at one frame: their ticks run one "
            "after another, and the last ones sense several ms after it (16 agents at 240 Hz "
            "on 2 cores: p99 ~10 ms from frame to sense, against a frame period of 4.2 ms); "
            f"tick_spread_frames = {fitting} lets them take turns over the frames (with "
            "tick_lag_ms = 0.25 and pose_wait_ms just under a frame period: p99 3.2-3.7 ms "
            'there; docs/mocap.md, "Ticks spread over the frames")',
        )
    )


def _check_spread_margin(parts: ExperimentParts, report: CheckReport) -> None:
    """``tick_spread_frames``: the agents of the last phase tick ``N - 1`` frames after the
    swarm's due time, up to one frame later again (a locked tick sits on the first frame at or
    after its grid point), and must answer before the swarm's next tick: warn when that leaves
    them under :data:`SPREAD_ANSWER_FRACTION` of the control period."""
    mocap, settings = parts.mocap, parts.settings
    spread = mocap.tick_spread_frames
    if spread <= 1 or not mocap.tick_lock:
        return
    period = 1.0 / settings.rate_hz
    answer = mocap.spread_left_s(period)
    if not 0.0 < answer < SPREAD_ANSWER_FRACTION * period:
        return  # fits comfortably, or refused already (it does not fit in one period)
    fitting = fitting_spread(mocap.rate_hz, settings.rate_hz)
    report.warnings.append(
        Problem(
            parts.path,
            "mocap.tick_spread_frames",
            f"{spread} frames at {mocap.rate_hz:g} Hz leave the last agents "
            f"{answer * 1e3:.3g} ms ({answer / period:.0%} of the {period * 1e3:.3g} ms control "
            "period) to answer before the swarm's next tick (which waits for no input): on a "
            f"busy machine their outputs come late; {fitting} frames leave "
            f"{SPREAD_ANSWER_FRACTION:.0%} or more "
            '(docs/mocap.md, "Ticks spread over the frames")',
        )
    )


def _check_sim_mocap_links(
    parts: ExperimentParts, checks: Iterable[_AgentCheck], report: CheckReport
) -> None:
    """``system = "sim"`` simulates cameras fed by the simulated plants' true poses: an agent on
    a real board has no such plant, so its body would never be seen and it could not start."""
    mocap = parts.mocap
    if mocap is None or mocap.system != "sim":
        return
    real = [(check.spec.name, check.real_link) for check in checks if check.real_link]
    if not real:
        return
    agents = ", ".join(f"{name!r} (link {link!r})" for name, link in real)
    one = len(real) == 1
    report.problems.append(
        Problem(
            parts.path,
            "mocap.system",
            f'"sim" simulates cameras that see only simulated robots (links sim://, simavr://, '
            f"xbee://...?sim=), but {'agent' if one else 'agents'} {agents} "
            f"{'has a real board: its body' if one else 'have real boards: their bodies'} "
            "would never be seen and the run could not start; set [mocap] system to your real "
            'motion capture system ("vicon", "optitrack", "qualisys" or "vrpn") and its host, '
            f"or give {'that agent a simulated link' if one else 'those agents simulated links'}",
        )
    )


def _check_graph(path: Path, facts: GraphFacts, report: CheckReport) -> None:
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


def _check_shared_links(parts: ExperimentParts, report: CheckReport) -> None:
    owners: dict[str, str] = {}
    for spec in parts.agents.values():
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
                    parts.path,
                    f"agents.{spec.name}.link",
                    f"{key!r} is already the link of agent {owners[key]!r}; a serial port or "
                    "XBee address belongs to one agent",
                )
            )
        else:
            owners[key] = spec.name


# -- per-agent checks --------------------------------------------------------------------------


@dataclass
class _Outcome:
    """What one shared check found: its value, and its problems/warnings by agent sub-key."""

    agent: str
    value: Any
    findings: list[tuple[bool, str, str]]  # (is a warning, sub-key, message)


class _AgentCheck:
    """Checks of one agent; :meth:`build` first, then :meth:`check_controller`.

    Agents whose settings are the same (a swarm of identical robots) share the expensive
    checks (building the vehicle, validating parameters, the dry controller step): each is done
    once per distinct setting and its findings are repeated under every such agent's key, so
    ``check`` stays fast for thousands of agents. The initial state shares by its length (its
    values are checked for every agent by the schema).
    """

    def __init__(
        self,
        parts: ExperimentParts,
        spec: AgentSpec,
        report: CheckReport,
        shared: dict[tuple[str, str], _Outcome],
    ) -> None:
        self.shared = shared
        self.parts = parts
        self.dt = parts.dt
        self.spec = spec
        self.report = report
        self.key = f"agents.{spec.name}"
        self.vehicle: Any = None
        self.n_inputs: int | None = None
        self.n_outputs: int | None = None
        #: The agent's link when it is a real board that needs a pose from ``[mocap]``
        #: (a valid URL, not simulated), else ``None``.
        self.real_link: str | None = None

    def problem(self, key: str, message: str) -> None:
        self.report.problems.append(Problem(self.parts.path, f"{self.key}.{key}", message))

    def warning(self, key: str, message: str) -> None:
        self.report.warnings.append(Problem(self.parts.path, f"{self.key}.{key}", message))

    def once(self, kind: str, setting: Any, check: Any) -> Any:
        """``check()`` once per distinct ``setting`` of ``kind``; later agents with the same
        setting get its value and its findings under their own key."""
        key = (kind, json.dumps(setting, sort_keys=True, default=str))
        outcome = self.shared.get(key)
        if outcome is None:
            problems, warnings = len(self.report.problems), len(self.report.warnings)
            value = check()
            start = len(self.key) + 1
            findings = [(False, p.key[start:], p.message) for p in self.report.problems[problems:]]
            findings += [(True, p.key[start:], p.message) for p in self.report.warnings[warnings:]]
            self.shared[key] = _Outcome(self.spec.name, value, findings)
            return value
        for is_warning, sub_key, found in outcome.findings:
            message = found.replace(repr(outcome.agent), repr(self.spec.name))
            (self.warning if is_warning else self.problem)(sub_key, message)
        return outcome.value

    # -- vehicle, link, calibration -----------------------------------------------------------

    def build(self) -> None:
        spec = self.spec
        vehicle_cls = self.once(
            "vehicle class",
            spec.vehicle,
            lambda: _resolve_class(self, "vehicle", spec.vehicle, resolve_vehicle),
        )
        link_kind = self._check_link(vehicle_cls)
        if vehicle_cls is None or self.dt is None:
            return
        setting = [
            spec.vehicle,
            spec.link,
            spec.pinout,
            spec.vehicle_params,
            len(spec.initial_state),
            spec.calibration,
        ]
        self.vehicle, self.n_inputs, self.n_outputs = self.once(
            "vehicle", setting, lambda: self._build_vehicle(vehicle_cls, link_kind)
        )

    def _build_vehicle(self, vehicle_cls: Any, link_kind: str | None) -> tuple[Any, Any, Any]:
        """Build the vehicle without a board; ``(vehicle, n_inputs, n_outputs)`` or Nones."""
        spec = self.spec
        calibration = self._load_calibration()
        if calibration is _FAILED:
            return None, None, None
        kwargs: dict[str, Any] = {"name": spec.name, "dt": self.dt}
        if spec.pinout:
            kwargs["pinout"] = spec.pinout
        if spec.vehicle_params:
            kwargs["params"] = spec.vehicle_params
        if spec.initial_state:
            kwargs["initial_state"] = spec.initial_state
        if calibration is not None:
            kwargs["calibration"] = calibration
        try:
            vehicle = vehicle_cls(**kwargs)
        except VehicleDefinitionError as exc:
            self.problem("vehicle", f"vehicle {spec.vehicle!r} is defined badly: {exc}")
            return None, None, None
        except (HilswarmError, ValueError, TypeError) as exc:
            self.problem(_vehicle_error_key(exc), str(exc))
            return None, None, None
        except NotImplementedError as exc:  # an unfinished `hilswarm new` skeleton
            self.problem("vehicle", f"vehicle {spec.vehicle!r} is not finished: {exc}")
            return None, None, None
        except Exception as exc:  # user code: report it with the agent's key, never a traceback
            self.problem(
                "vehicle",
                f"constructing vehicle {spec.vehicle!r} failed: {type(exc).__name__}: {exc}",
            )
            return None, None, None
        self._check_initial_state(vehicle, link_kind)
        # Sizes may be per instance (a simulated vehicle takes them from its plant).
        n_inputs = getattr(vehicle, "n_inputs", None)
        n_outputs = getattr(vehicle, "n_outputs", None)
        if isinstance(n_inputs, int) and isinstance(n_outputs, int):
            return vehicle, n_inputs, n_outputs
        return vehicle, None, None

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
            self.report.unused_links.add(spec.name)
            self.warning(
                "link",
                f"vehicle {spec.vehicle!r} needs no board; link {spec.link!r} is not used",
            )
        if not is_simulated(spec.link) and getattr(vehicle_cls, "needs_board", True):
            self.real_link = spec.link.strip()  # its pose can only come from a real system
        needs_pose = vehicle_cls is not None and getattr(vehicle_cls, "needs_pose", False)
        if needs_pose and not is_simulated(spec.link) and self.parts.mocap is None:
            self.problem(
                "link",
                f"agent {spec.name!r}: vehicle {spec.vehicle!r} needs a pose from motion "
                f"capture, but link {spec.link!r} gives none (only simulated boards, sim://, "
                "simavr://, xbee://...?sim=, simulate one) and the experiment has no [mocap] "
                'table; add [mocap] with system = "vicon", "optitrack", "qualisys", "vrpn" '
                'or "sim"',
            )
        return kind

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

    def _check_initial_state(self, vehicle: Any, link_kind: str | None) -> None:
        """Compare the initial state with the plant's state size when it can be known."""
        spec = self.spec
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
                vehicle.simulated_hardware(initial_state=spec.initial_state, dt=self.dt)
            except (HilswarmError, ValueError, TypeError) as exc:
                self.problem("initial_state", f"the simulated hardware rejects it: {exc}")

    # -- controller ---------------------------------------------------------------------------

    def check_controller(
        self, output_sizes: Mapping[str, int | None], facts: GraphFacts | None
    ) -> None:
        spec = self.spec
        built = self.once("controller", [spec.controller, spec.params], self._build_controller)
        if built is None:
            return
        controller, params = built
        neighbours = self.parts.neighbours(spec.name)
        if neighbours is None or self.dt is None:
            return  # the graph or [experiment] is broken (reported): nothing more to compare
        self._check_leader(params, neighbours)
        if facts is not None:
            self._check_consensus_gain(controller, params, facts, neighbours)
        if self.n_inputs is None:
            return
        mentioned = json.dumps(spec.params, default=str)
        setting = [
            spec.controller,
            spec.params,
            self.n_inputs,
            self.n_outputs,
            [(n if n in mentioned else "", output_sizes.get(n)) for n in neighbours],
        ]
        self.once(
            "dry step",
            setting,
            lambda: self._dry_step(controller, params, neighbours, output_sizes),
        )

    def _build_controller(self) -> tuple[Any, dict[str, Any]] | None:
        """The controller and its validated parameters, or ``None`` (problems reported)."""
        spec = self.spec
        controller_cls = _resolve_class(self, "controller", spec.controller, resolve_controller)
        if controller_cls is None:
            return None
        try:
            controller = controller_cls()
        except (HilswarmError, ValueError, TypeError) as exc:
            self.problem("controller", f"cannot build controller {spec.controller!r}: {exc}")
            return None
        try:
            params = controller.validate_params(dict(spec.params))
        except (ControllerError, ValueError, TypeError) as exc:
            self.problem("params", str(exc))
            return None
        return controller, params

    def _check_leader(self, params: Mapping[str, Any], neighbours: tuple[str, ...]) -> None:
        leader = params.get("leader")
        if not isinstance(leader, str):
            return
        names = self.parts.agent_names or ()
        if leader not in names:
            self.problem("params.leader", f"no agent named {leader!r}; agents: {', '.join(names)}")
        elif leader == self.spec.name:
            self.problem("params.leader", "an agent cannot follow itself")
        elif leader not in neighbours:
            i, j = names.index(self.spec.name), names.index(leader)  # only on this error
            self.problem(
                "params.leader",
                f"{self.spec.name!r} does not hear its leader {leader!r} through the graph: "
                f"adjacency[{i}][{j}] must be 1 (agent {self.spec.name} receives {leader}); "
                f"it hears: {', '.join(neighbours) or 'nobody'}",
            )

    def _check_consensus_gain(
        self,
        controller: Any,
        params: Mapping[str, Any],
        facts: GraphFacts,
        neighbours: tuple[str, ...],
    ) -> None:
        from hilswarm.agents.controllers.consensus import LinearConsensus  # noqa: PLC0415

        if not isinstance(controller, LinearConsensus):
            return
        weights = params["weights"]
        dt = self.dt or 0.0
        degree = sum(weights.get(name, 1.0) for name in neighbours)
        product = params["gain"] * dt * degree
        if product >= 1.0:
            self.warning(
                "params.gain",
                f"gain * dt * in-degree = {params['gain']:g} * {dt:g} * "
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
                dt=self.dt,
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


def _resolve_class(check: _AgentCheck, kind: str, name: str, resolve: Any) -> Any:
    """The class ``name`` names, or ``None`` with a problem at the agent's ``kind`` key.

    A module outside hilswarm is first inspected without running it (:mod:`.class_inspect`);
    the registry then imports it and checks that the class subclasses Vehicle / Controller.
    """
    try:
        problem = static_class_problem(kind, name, class_path(kind, name))
        if problem is None:
            return resolve(name)
    except RegistryError as exc:
        problem = str(exc)
    check.problem(kind, problem)
    return None


#: Marker: the calibration could not be loaded (a problem was reported).
_FAILED = object()
