"""What an agent process is made of: its configuration and its hardware.

:class:`AgentConfig` is everything one agent process needs (the orchestrator builds it from the
experiment file and passes it as JSON on the agent's command line); :func:`build_hardware`
turns it into the vehicle, its board link (opened and configured) and the controller's
:class:`~hilswarm.agents.control.ControlModel`. The agent process itself (the bus, the tick
engine, the lifecycle) is :mod:`hilswarm.agents.agent`.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from hilswarm.agents import bus
from hilswarm.agents.control import ControlModel
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.link.url import board_for_url, is_simulated, link_scheme
from hilswarm.agents.registry import resolve_controller, resolve_vehicle

#: Lockstep window when the orchestrator gives none [ticks] (the experiment file's default).
DEFAULT_LOCKSTEP_WINDOW = 8
#: Board watchdog when the experiment gives none [s].
DEFAULT_WATCHDOG_S = 0.5


class AgentConfigError(HilswarmError, ValueError):
    """An agent configuration (JSON or fields) is malformed."""


@dataclass(frozen=True)
class AgentConfig:
    """Everything one agent process needs (built by the orchestrator from the experiment).

    Attributes:
        experiment: experiment name (bus key prefix).
        name: this agent's name.
        agent_names: every agent of the experiment, in graph order (tick messages name lost
            agents by index in this tuple).
        neighbours: agents whose output this agent receives (row of the adjacency matrix).
        vehicle: vehicle registry name or ``"package.module:Class"``.
        link: board link URL, or ``None`` for vehicles that need no board.
        controller: controller registry name or ``"package.module:Class"``.
        params: controller parameters.
        vehicle_params: vehicle keyword parameters.
        pinout: pin overrides (device -> role -> pin).
        initial_state: initial state of the simulated plant (plant units).
        calibration: calibration file path or ``None``.
        dt: control period [s].
        watchdog_s: board watchdog timeout [s] (``None``: :data:`DEFAULT_WATCHDOG_S`).
        seed: seed for simulated sensors (mocap noise), or ``None``.
        mocap_noise_std_m: standard deviation of simulated mocap position noise [m].
        mocap_noise_std_rad: standard deviation of simulated mocap attitude noise [rad].
        lockstep_window: the experiment's lockstep window [ticks]: a lockstep agent never
            runs more than this many ticks past its own last tick, whatever arrives.
        run_id: the run's id (bus key prefix ``hilswarm/<exp>/<run_id>``; empty: none).
        mocap: the experiment's ``[mocap]`` section as plain data
            (:meth:`~hilswarm.agents.mocap.config.MocapSettings.to_dict`), or ``None``: the
            pose then comes from the link (a ``SimulatedMocap`` of a ``sim://`` plant).
        mocap_body: this agent's rigid body (``None``: its name).
        mocap_neighbours: the graph neighbours' rigid bodies (agent name -> body), received
            only when the controller ``uses_neighbour_poses``.
    """

    experiment: str
    name: str
    agent_names: tuple[str, ...]
    neighbours: tuple[str, ...]
    vehicle: str
    link: str | None
    controller: str
    dt: float
    params: dict[str, Any] = field(default_factory=dict)
    vehicle_params: dict[str, Any] = field(default_factory=dict)
    pinout: dict[str, dict[str, int | str]] = field(default_factory=dict)
    initial_state: tuple[float, ...] = ()
    calibration: str | None = None
    watchdog_s: float | None = None
    seed: int | None = None
    mocap_noise_std_m: float = 0.0
    mocap_noise_std_rad: float = 0.0
    lockstep_window: int = DEFAULT_LOCKSTEP_WINDOW
    run_id: str = ""
    mocap: dict[str, Any] | None = None
    mocap_body: str | None = None
    mocap_neighbours: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bus.check_key_name(self.experiment, what="experiment name")
        if self.run_id:
            bus.check_key_name(self.run_id, what="run id")
        bus.check_key_name(self.name, what="agent name")
        if self.name not in self.agent_names:
            raise AgentConfigError(
                f"agent {self.name!r} is not in the experiment's agents {self.agent_names}"
            )
        unknown = [n for n in self.neighbours if n not in self.agent_names]
        if unknown:
            raise AgentConfigError(f"agent {self.name!r}: unknown neighbours {unknown}")
        if self.name in self.neighbours:
            raise AgentConfigError(f"agent {self.name!r} lists itself as its own neighbour")
        if not (isinstance(self.dt, int | float) and math.isfinite(self.dt) and self.dt > 0):
            raise AgentConfigError(f"agent {self.name!r}: dt must be > 0 [s], got {self.dt!r}")
        window = self.lockstep_window
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise AgentConfigError(
                f"agent {self.name!r}: lockstep_window must be an integer >= 1, got {window!r}"
            )

    @property
    def index(self) -> int:
        """Index of this agent in :attr:`agent_names`."""
        return self.agent_names.index(self.name)

    def to_json(self) -> str:
        """Serialise (the launcher passes this on the agent's command line)."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> AgentConfig:
        """Inverse of :meth:`to_json` (raises :class:`AgentConfigError`)."""
        try:
            data = json.loads(text)
            data["agent_names"] = tuple(data["agent_names"])
            data["neighbours"] = tuple(data["neighbours"])
            data["initial_state"] = tuple(data.get("initial_state", ()))
            return cls(**data)
        except (ValueError, KeyError, TypeError) as exc:
            raise AgentConfigError(f"bad agent configuration JSON: {exc}") from exc


# ---------------------------------------------------------------------------------------------
# Building the vehicle, board and controller
# ---------------------------------------------------------------------------------------------


@dataclass
class AgentHardware:
    """The vehicle, its board (or ``None``) and its control model."""

    vehicle: Any
    board: Any | None
    model: Any


def build_hardware(
    config: AgentConfig,
    *,
    endpoints: Sequence[str] = (),
    security: bus.SessionSecurity | None = None,
    prepare_calibration: bool = True,
) -> AgentHardware:
    """Build the vehicle, open/configure its board and build the controller's ControlModel.

    For ``sim://`` and ``simavr://`` links (and ``xbee://...?sim=...``, a simulated robot behind
    the simulated radio) the board drives the vehicle's own simulated hardware
    (``vehicle.simulated_hardware``) and a simulated mocap follows that plant. ``endpoints``
    are the agent's bus endpoints, through which an ``xbee://`` board reaches the gateway
    (authenticated with ``security``, the agent's credentials). ``prepare_calibration``:
    compute the calibration's inverse now (~25 ms for a Frisbee), so that no tick pays for it
    (off: each duty's inverse is computed on its first use; for throwaway copies).
    """
    vehicle_cls = resolve_vehicle(config.vehicle)
    vehicle = vehicle_cls(
        name=config.name,
        pinout=config.pinout or None,
        params=config.vehicle_params,
        calibration=config.calibration,
        initial_state=list(config.initial_state) or None,
        dt=config.dt,
    )
    calibration = getattr(vehicle, "calibration", None)
    if calibration is not None and prepare_calibration:  # now, so that no tick pays for it
        calibration.prepare_inverse()
    board = None
    if getattr(vehicle, "needs_board", True):
        board = _open_board(config, vehicle, endpoints, security)
    controller = resolve_controller(config.controller)()
    source = getattr(vehicle, "pose_source", None)
    asks = getattr(controller, "uses_neighbour_poses", False) and config.mocap_neighbours
    if asks and hasattr(source, "neighbour_poses"):
        source.neighbours = dict(config.mocap_neighbours)
    model = ControlModel(
        controller,
        dt=config.dt,
        n_inputs=int(vehicle.n_inputs),
        n_outputs=int(vehicle.n_outputs),
        params=config.params,
    )
    if asks and hasattr(source, "neighbour_poses"):
        model.neighbour_poses = source.neighbour_poses
    return AgentHardware(vehicle=vehicle, board=board, model=model)


def tick_phase_s(config: AgentConfig) -> float:
    """How long after the swarm's due times this agent's self-clocked ticks are due [s]
    (``[mocap] tick_spread_frames``; 0 without it)."""
    if config.mocap is None:
        return 0.0
    from hilswarm.agents.mocap.config import MocapSettings  # noqa: PLC0415 - mocap runs only

    return MocapSettings.from_dict(config.mocap).tick_phase_s(config.index)


def mocap_pose_source(config: AgentConfig, vehicle: Any, plant: Any | None) -> Any:
    """The bus pose source of ``config``'s body; with ``system = "sim"`` and a simulated plant
    it also feeds the plant's true pose to the simulator."""
    from hilswarm.agents.mocap.config import MocapSettings  # noqa: PLC0415 - mocap runs only
    from hilswarm.agents.mocap.pose_source import MocapPoseSource  # noqa: PLC0415

    settings = MocapSettings.from_dict(config.mocap or {})
    feed = plant if settings.system == "sim" and plant is not None else None
    source = MocapPoseSource(
        config.mocap_body or config.name,
        hold_frames=settings.hold_frames,
        hold_s=settings.hold_s,
        start_timeout_s=settings.start_timeout_s,
        truth=feed,
        on_lost=vehicle.enter_safe_mode,
        # Ticks locked to the frames: a sense may wait, bounded, for its frame's pose.
        frame_period_s=1.0 / settings.rate_hz,
        pose_wait_s=settings.pose_wait_s,
        tick_lag_s=settings.tick_lag_s,
    )
    source.add_telemetry(vehicle.telemetry)
    return source


def _open_board(
    config: AgentConfig,
    vehicle: Any,
    endpoints: Sequence[str] = (),
    security: bus.SessionSecurity | None = None,
) -> Any:
    if not config.link:
        raise AgentConfigError(
            f"agent {config.name!r}: vehicle {config.vehicle!r} needs a board but the "
            'experiment gives no link URL (e.g. link = "sim://")'
        )
    options: dict[str, Any] = {}
    scheme = link_scheme(config.link)
    if scheme == "xbee":
        options = {
            "endpoints": list(endpoints),
            "experiment": config.experiment,
            "run_id": config.run_id,
            "security": security,
            "agent": config.name,
        }
    if is_simulated(config.link):
        plant = vehicle.simulated_hardware(
            initial_state=list(config.initial_state) or None, dt=config.dt
        )
        options.update(plant=plant, dt=config.dt)
        if config.mocap is not None:
            vehicle.pose_source = mocap_pose_source(config, vehicle, plant)
        elif plant is not None:
            from hilswarm.agents.sim.mocap import SimulatedMocap  # noqa: PLC0415 - sim only

            vehicle.pose_source = SimulatedMocap(
                plant,
                noise_std_m=config.mocap_noise_std_m,
                noise_std_rad=config.mocap_noise_std_rad,
                seed=(config.seed or 0) + config.index,  # distinct, reproducible per agent
            )
    elif config.mocap is not None:
        vehicle.pose_source = mocap_pose_source(config, vehicle, None)
    board = board_for_url(config.link, **options)
    vehicle.connect(board, watchdog_s=config.watchdog_s or DEFAULT_WATCHDOG_S)
    return board
