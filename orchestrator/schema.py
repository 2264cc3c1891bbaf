"""The experiment file's schema: one declarative pydantic model per TOML table.

This module is the single statement of which keys an experiment file may have, their types,
defaults and ranges. :mod:`~hilswarm.orchestrator.experiment` validates every table of a file
with these models (and turns their errors into ``file:key: reason`` problems), ``hilswarm check
--schema`` publishes them as a JSON Schema (``schema/experiment.schema.json``) so editors
complete and check experiment files, and the docs table in ``docs/experiments.md`` follows
them. Rules that need more than one table (graph names vs agent tables, a tick count, files
beside the experiment) live in the loader; rules that need the code an agent names live in
:mod:`~hilswarm.orchestrator.checks`.

Why pydantic: it validates and reports *every* error of a table in one pass, with the key path
of each, rejects ``true`` where a number belongs in strict mode, and derives the JSON Schema from
the same declarations, so the published schema cannot drift from what the loader accepts.
"""

from __future__ import annotations

import json
from typing import Annotated, Any, Literal

from hilswarm.agents.mocap.config import (
    DEFAULT_HOLD_FRAMES,
    DEFAULT_RATE_HZ,
    DEFAULT_START_TIMEOUT_S,
)
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    PlainValidator,
    StringConstraints,
    WithJsonSchema,
)
from pydantic_core import PydanticCustomError

__all__ = [
    "DEFAULT_LOCKSTEP_WINDOW",
    "DEFAULT_MAX_LATE_FRACTION",
    "MAX_LOCKSTEP_WINDOW",
    "MAX_RATE_HZ",
    "NAME_REGEX",
    "AgentTable",
    "ExperimentFile",
    "ExperimentSection",
    "GatewaySection",
    "GraphSection",
    "MocapSection",
    "MocapSimSection",
    "json_schema",
    "json_schema_text",
]

#: Experiment and agent names: they become parts of bus keys and MCAP topics.
NAME_REGEX = r"^[A-Za-z0-9_-]+$"
#: Highest control rate accepted [Hz]; above it no board link or bus keeps up.
MAX_RATE_HZ = 1000.0
#: Lockstep: how many ticks an agent may run ahead of the slowest one (1: a strict barrier).
DEFAULT_LOCKSTEP_WINDOW = 8
#: Largest accepted lockstep window [ticks].
MAX_LOCKSTEP_WINDOW = 1024
#: Late ticks (realtime) above this fraction of all ticks make a run "degraded".
DEFAULT_MAX_LATE_FRACTION = 0.01

Name = Annotated[str, StringConstraints(pattern=NAME_REGEX)]
NonEmpty = Annotated[str, StringConstraints(min_length=1, strip_whitespace=True)]

_PIN_SCHEMA = {
    "anyOf": [
        {"type": "integer", "minimum": 0},
        {"type": "string", "pattern": "^[AaDd]?[0-9]+$"},
    ],
    "description": 'pin number (13) or name ("D13", "A0")',
}


def _pin(value: Any) -> int | str:
    """A pin as written: a number (``13``) or a name (``"D13"``, ``"A0"``); checked per board
    profile when the vehicle is built."""
    if isinstance(value, bool) or not isinstance(value, int | str):
        raise PydanticCustomError(
            "pin",
            '{value!r} is not a pin; expected a number (13) or a name ("D13", "A0")',
            {"value": value},
        )
    return value


Pin = Annotated[int | str, PlainValidator(_pin), WithJsonSchema(_PIN_SCHEMA)]

_ADJACENCY_SCHEMA = {
    "type": "array",
    "items": {
        "type": "array",
        "items": {"anyOf": [{"enum": [0, 1]}, {"type": "boolean"}]},
    },
    "description": "A[i][j] = 1: agent i receives agent j's output; square, zero diagonal",
}

# The matrix's shape and entries are checked by graph_io.validate_matrix, which reports each
# row and entry by index (a model would stop at the first bad row's type).
Adjacency = Annotated[Any, WithJsonSchema(_ADJACENCY_SCHEMA)]


class _Table(BaseModel):
    """One TOML table: unknown keys are errors, numbers are numbers (``true`` is not one)."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        frozen=True,
        allow_inf_nan=False,
        use_attribute_docstrings=True,
    )


class ExperimentSection(_Table):
    """``[experiment]``: what the run is and how it behaves."""

    name: Name = Field(examples=["lead_follow"])
    """Experiment name, [A-Za-z0-9_-]+; bus keys are hilswarm/<name>/..."""
    rate_hz: float = Field(gt=0.0, le=MAX_RATE_HZ, examples=[20.0])
    """Control rate [Hz]; one tick every dt = 1 / rate_hz s."""
    duration_s: float = Field(gt=0.0, examples=[30.0])
    """Run length [s of experiment time]; round(duration_s * rate_hz) ticks, at least one."""
    mode: Literal["lockstep", "realtime"] = "lockstep"
    """lockstep: ticks as fast as every agent answers (simulated time, reproducible); realtime:
    ticks on a monotonic wall-clock schedule, late answers counted."""
    on_agent_loss: Literal["stop", "continue"] = "stop"
    """When an agent process dies or stops answering: stop the run, or continue without it."""
    on_agent_safe: Literal["continue", "stop"] = "continue"
    """When an agent's vehicle enters safe mode (low battery, e-stop, fault): the others
    continue, or every agent goes safe and the run stops."""
    on_recording_failure: Literal["stop", "continue"] = "stop"
    """When the recording cannot be written (disk full): stop (robots safe, the run ends) or
    continue unrecorded."""
    max_late_fraction: float = Field(DEFAULT_MAX_LATE_FRACTION, ge=0.0, le=1.0)
    """Realtime: late ticks above this fraction of all ticks make the run degraded."""
    watchdog_s: float | None = Field(None, gt=0.0, le=60.0)
    """Board watchdog timeout [s]; must exceed one control period. Default: the agent's."""
    seed: int | None = Field(None, ge=0)
    """Seed of every random generator of the run (noise, simulated motion capture)."""
    lockstep_window: int = Field(DEFAULT_LOCKSTEP_WINDOW, ge=1, le=MAX_LOCKSTEP_WINDOW)
    """Lockstep only: ticks an agent may run ahead of the slowest one (1: a barrier)."""
    realtime_clock: Literal["shared", "manager"] = "shared"
    """Realtime only: "shared" (default): agents on the orchestrator's host keep the manager's
    schedule on the shared monotonic clock themselves (tick messages stay when agents join from
    other hosts or an XBee gateway runs); "manager": one tick message per period."""


class GraphSection(_Table):
    """``[graph]``: who hears whom. Exactly one of ``adjacency`` (with ``agents``) or ``file``."""

    agents: list[Name] | None = Field(None, min_length=1)
    """Agent names in row order; required with adjacency, optional with file."""
    adjacency: Adjacency = None
    """A[i][j] = 1: agent i receives agent j's output."""
    file: NonEmpty | None = None
    """Graph file (.csv, .graphml, .gml, .edgelist, .edges, .adjlist) inside the experiment's
    folder, relative to the experiment file."""
    undirected: bool = False
    """For edge and adjacency lists: make every edge two-way."""


class AgentTable(_Table):
    """``[agents.<name>]`` and ``[defaults]`` (an agent's keys win; sub-tables merge)."""

    vehicle: NonEmpty | None = None
    """Registry name (simulated, frisbee, blimpduino) or "package.module:Class"."""
    link: NonEmpty | None = None
    """Board link URL: sim://[profile], simavr://[profile], a serial device (/dev/ttyUSB0),
    a pyserial URL (socket://host:port, rfc2217://host:port, loop://)."""
    controller: NonEmpty | None = None
    """Registry name (waypoint, follower, consensus, ...) or "package.module:Class"."""
    params: dict[str, Any] = Field(default_factory=dict)
    """Controller parameters (checked by the controller's validate_params)."""
    vehicle_params: dict[str, Any] = Field(default_factory=dict)
    """Vehicle parameters (e.g. plant and plant_params of a simulated vehicle)."""
    pinout: dict[str, dict[str, Pin]] = Field(default_factory=dict)
    """Pin overrides: device -> role -> pin."""
    initial_state: list[float] = Field(default_factory=list)
    """Initial state of a simulated plant, in that plant's state units."""
    calibration: NonEmpty | None = None
    """Calibration file, relative to the experiment file."""
    mocap_body: Name | None = None
    """Name of this agent's rigid body in the motion-capture system (default: the agent's
    name)."""
    reply_every: int | None = Field(None, ge=1, le=255)
    """xbee:// links with [gateway] mode = "broadcast": the robot answers (samples) every
    reply_every-th tick, round-robin; on the others the gateway repeats its last samples,
    marked stale (default 1: every tick)."""


def _occlusion(window: list[float]) -> list[float]:
    if not 0.0 <= window[0] < window[1]:
        raise PydanticCustomError(
            "occlusion",
            "{window!r} is not [start_s, end_s] with 0 <= start < end",
            {"window": window},
        )
    return window


Occlusion = Annotated[list[float], Field(min_length=2, max_length=2), AfterValidator(_occlusion)]


class MocapSimSection(_Table):
    """``[mocap.sim]`` (system = "sim" only): what the simulated cameras do."""

    noise_std_m: float = Field(0.0, ge=0.0, le=10.0)
    """Standard deviation of the position noise [m]."""
    noise_std_rad: float = Field(0.0, ge=0.0, le=10.0)
    """Standard deviation of the attitude noise [rad]."""
    latency_s: float = Field(0.0, ge=0.0, le=10.0)
    """Delay between a pose and its frame's arrival [s]."""
    dropout_rate: float = Field(0.0, ge=0.0, le=1.0)
    """Probability per body and frame that an occlusion starts (0..1)."""
    dropout_frames: int = Field(5, ge=1)
    """Frames an occlusion lasts."""
    occlusions: dict[str, Occlusion] = Field(default_factory=dict)
    """Scripted occlusions: body -> [start_s, end_s] [s from its first pose]."""
    seed: int | None = Field(None, ge=0)
    """Seed of the simulated noise and dropouts."""


class MocapSection(_Table):
    """``[mocap]``: the motion-capture system that gives vehicles their pose (read into a
    :class:`hilswarm.agents.mocap.config.MocapSettings`)."""

    system: Literal["vicon", "optitrack", "qualisys", "vrpn", "sim"]
    """vicon, optitrack, qualisys, vrpn, or sim (the protocol-level simulator on loopback)."""
    host: NonEmpty | None = None
    """The mocap server's address; required except for sim (then 127.0.0.1)."""
    port: int | None = Field(None, gt=0, lt=65536)
    """The server's port (default: the system's; Qualisys 22223, OptiTrack NatNet's command
    port 1510, VRPN 3883)."""
    rate_hz: float = Field(DEFAULT_RATE_HZ, gt=0.0, le=10000.0)
    """The system's frame rate [Hz]."""
    hold_frames: int = Field(DEFAULT_HOLD_FRAMES, ge=1, le=100000)
    """Frames a lost body's pose is held before its agent goes safe."""
    up_axis: Literal["y", "z"] | None = None
    """Override the system's default up axis."""
    position_std_m: float = Field(0.002, ge=0.0)
    """Kalman measurement noise of the position [m]."""
    yaw_std_rad: float = Field(0.02, ge=0.0)
    """Kalman measurement noise of the yaw [rad]."""
    start_timeout_s: float = Field(DEFAULT_START_TIMEOUT_S, ge=0.0, le=600.0)
    """How long an agent waits for its body to be seen at start [s]."""
    tick_lock: bool = True
    """Release the realtime ticks in step with the frames (a lag after a frame comes)."""
    tick_lag_ms: float | None = Field(None, ge=0.0, le=1000.0)
    """A locked tick is released this long after its frame reaches the host [ms], under one
    frame period (default: 3 ms, at most 0.3 of a frame period)."""
    pose_wait_ms: float | None = Field(None, ge=0.0, le=1000.0)
    """With tick_lock: a sense whose frame's pose is not in yet waits for it at most this long
    [ms], under one frame period (default 0: never waits)."""
    tick_frames_only: bool = False
    """In a self-clocked run, publish only the poses of the frames the ticks use and a
    keep-alive (less CPU; default: every frame's)."""
    tick_spread_frames: int = Field(1, ge=1, le=1000)
    """With tick_lock, in a self-clocked run: the agents' ticks spread over this many
    consecutive frames, agent i (graph order) ticking (i mod N) frame periods after the
    swarm's due time, so that fewer agents sense at each frame (default 1: all at once)."""
    sim: MocapSimSection | None = None
    """system = "sim" only: the simulated cameras."""


class GatewaySection(_Table):
    """``[gateway]``: the XBee API-mode gateway that carries ``xbee://`` links (read into a
    :class:`hilswarm.agents.xbee.config.GatewayConfig`, which adds the XBee baud-rate rule)."""

    port: NonEmpty = "sim"
    """The coordinator XBee's serial port: a device or any pyserial URL; "sim" for the
    simulated coordinator and air."""
    baud: int = Field(115200, gt=0)
    """Host UART rate of the coordinator [baud]: an XBee rate (9600 ... 230400)."""
    api_mode: Literal[1, 2] = 1
    """XBee API mode: 1 (API) or 2 (API with escaping, AP = 2)."""
    mode: Literal["unicast", "broadcast"] = "unicast"
    """unicast: a TICK and its reply per robot and tick; broadcast: every robot's outputs of a
    tick in one packed BCAST frame (firmware protocol 2), replies every reply_every-th tick."""
    answer: Literal["wait", "at_once"] = "wait"
    """wait: an agent waits for its robot's own reply (broadcast: on its reply ticks); at_once:
    every TICK is answered at once with the robot's newest samples, marked stale (the TICKs
    still go to the robots)."""
    family: Literal["802.15.4", "zigbee"] = "802.15.4"
    """port = "sim": the frame family the simulated radios speak."""
    seed: int = Field(0, ge=0)
    """port = "sim": seed of the simulated air (backoffs, losses)."""
    loss: float = Field(0.0, ge=0.0, le=1.0)
    """port = "sim": loss probability of each frame on every link (0..1)."""


class ExperimentFile(_Table):
    """One experiment file (hilswarm): the run, its graph and its agents."""

    experiment: ExperimentSection
    graph: GraphSection
    defaults: AgentTable | None = None
    """Keys every agent starts from."""
    agents: dict[Name, AgentTable]
    """One table per agent of the graph: [agents.<name>]."""
    mocap: MocapSection | None = None
    gateway: GatewaySection | None = None


def json_schema() -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of an experiment file, generated from the models."""
    schema = _without_null(ExperimentFile.model_json_schema())
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


def json_schema_text() -> str:
    """:func:`json_schema` as the text of ``schema/experiment.schema.json``."""
    return json.dumps(json_schema(), indent=2, sort_keys=False) + "\n"


def _without_null(node: Any) -> Any:
    """Drop ``null`` alternatives and ``null`` defaults: TOML has no null, a key is left out."""
    if isinstance(node, list):
        return [_without_null(item) for item in node]
    if not isinstance(node, dict):
        return node
    out = {k: _without_null(v) for k, v in node.items() if not (k == "default" and v is None)}
    options = out.get("anyOf")
    if isinstance(options, list):
        options = [o for o in options if o != {"type": "null"}]
        if len(options) == 1:
            del out["anyOf"]
            out = {**options[0], **out}
        else:
            out["anyOf"] = options
    return out
