"""The ``[mocap]`` section of an experiment file, as a small typed model.

::

    [mocap]
    system = "qualisys"     # vicon, optitrack, qualisys, vrpn or sim
    host = "192.168.1.10"   # the mocap server (sim: the built-in simulator on loopback)
    rate_hz = 100.0         # the system's frame rate [Hz]
    hold_frames = 10        # frames a lost body's pose is held before the agent goes safe
    # port = 22223          # optional: the server's port (system default otherwise;
    #                       # OptiTrack: NatNet's command port, 1510)
    # up_axis = "z"         # optional: override the system's default up axis ("y" or "z")
    # position_std_m = 0.002, yaw_std_rad = 0.02   # Kalman measurement noise
    # tick_lock = true      # realtime ticks in step with the frames (docs/mocap.md)
    # tick_lag_ms = 2.0     # a tick this long after its frame reaches the host [ms]
    # pose_wait_ms = 1.5    # a sense waits at most this long for an overdue pose [ms] (0)
    # tick_frames_only = false  # only the poses of the frames the ticks use (less CPU)
    # tick_spread_frames = 1    # agent i ticks (i mod N) frames after the swarm's due time

    [mocap.sim]             # system = "sim" only: what the simulated cameras do
    noise_std_m = 0.002
    noise_std_rad = 0.01
    latency_s = 0.002
    dropout_rate = 0.0      # probability per body and frame that an occlusion starts
    dropout_frames = 5
    occlusions = { f1 = [2.0, 3.0] }   # scripted: body -> [start, end] [s, experiment time]

Per agent, ``mocap_body = "frisbee1"`` names its rigid body (default: the agent's name).

The keys, their types and ranges are declared once, in the experiment schema
(:class:`hilswarm.orchestrator.schema.MocapSection`); the loader
(:func:`hilswarm.orchestrator.experiment.mocap_settings`) validates a table with it and builds
this model, which the agents, the mocap processes and the probe use.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

DEFAULT_RATE_HZ = 100.0
DEFAULT_HOLD_FRAMES = 10
DEFAULT_START_TIMEOUT_S = 5.0
#: Default lag of a tick after the frame it is locked to [ms] (capped at 0.3 of a frame
#: period: 1.25 ms at 240 Hz). Measured with 16 self-clocked agents (docs/mocap.md): shorter
#: lags miss frames whose poses are still on their way; each ms more is a ms more latency.
DEFAULT_TICK_LAG_MS = 3.0
#: The default lag is at most this fraction of a frame period.
DEFAULT_TICK_LAG_PERIODS = 0.3


@dataclass(frozen=True)
class SimCameras:
    """``[mocap.sim]``: the simulated camera system (see :class:`.qtm_sim.SimSettings`)."""

    noise_std_m: float = 0.0
    noise_std_rad: float = 0.0
    latency_s: float = 0.0
    dropout_rate: float = 0.0
    dropout_frames: int = 5
    occlusions: dict[str, tuple[float, float]] = field(default_factory=dict)
    seed: int | None = None


@dataclass(frozen=True)
class MocapSettings:
    """``[mocap]`` (see the module docstring for keys, units and defaults)."""

    system: str
    host: str = "127.0.0.1"
    port: int | None = None
    rate_hz: float = DEFAULT_RATE_HZ
    hold_frames: int = DEFAULT_HOLD_FRAMES
    up_axis: str | None = None
    position_std_m: float = 0.002
    yaw_std_rad: float = 0.02
    start_timeout_s: float = DEFAULT_START_TIMEOUT_S
    tick_lock: bool = True
    tick_lag_ms: float | None = None
    pose_wait_ms: float | None = None
    tick_frames_only: bool = False
    tick_spread_frames: int = 1
    sim: SimCameras = field(default_factory=SimCameras)

    @property
    def hold_s(self) -> float:
        """How long a body may go unseen before its agent goes safe [s]."""
        return self.hold_frames / self.rate_hz

    @property
    def tick_lag_s(self) -> float:
        """A locked tick is released this long after its frame reaches the host [s]
        (``tick_lag_ms``; default :data:`DEFAULT_TICK_LAG_MS`, at most
        :data:`DEFAULT_TICK_LAG_PERIODS` of a frame period)."""
        if self.tick_lag_ms is not None:
            return self.tick_lag_ms * 1e-3
        return min(DEFAULT_TICK_LAG_MS * 1e-3, DEFAULT_TICK_LAG_PERIODS / self.rate_hz)

    @property
    def pose_wait_s(self) -> float:
        """Bound on a sense's wait for the pose of its tick's frame [s] (``pose_wait_ms``,
        :mod:`.pose_source` "Waiting for the tick's frame"); 0 (the default: measured at
        240 Hz to help with up to four agents per core and to hurt with six or more,
        docs/mocap.md) or without ``tick_lock``: never waits."""
        if not self.tick_lock or self.pose_wait_ms is None:
            return 0.0
        return self.pose_wait_ms * 1e-3

    def tick_phase_s(self, index: int) -> float:
        """How long after the swarm's due time the agent of graph index ``index`` ticks [s]:
        ``index mod tick_spread_frames`` frame periods (``[mocap] tick_spread_frames``,
        docs/mocap.md "Ticks spread over the frames"); 0 without a spread or without
        ``tick_lock``."""
        if not self.tick_lock or self.tick_spread_frames <= 1:
            return 0.0
        return (index % self.tick_spread_frames) / self.rate_hz

    def spread_left_s(self, dt: float) -> float:
        """With ``tick_spread_frames``: how long the agents of the last phase have to answer
        before the swarm's next tick, in a control period of ``dt`` [s]: ``dt`` minus their
        phase minus one frame period (a locked tick sits up to a frame after its grid point);
        not above 0: the spread does not fit in one period."""
        return dt - self.tick_spread_frames / self.rate_hz

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able data (for command lines); inverse of :meth:`from_dict`."""
        data = asdict(self)
        data["sim"]["occlusions"] = {k: list(v) for k, v in self.sim.occlusions.items()}
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> MocapSettings:
        """Inverse of :meth:`to_dict`."""
        values = dict(data)
        sim = dict(values.pop("sim", {}) or {})
        sim["occlusions"] = {
            k: (float(v[0]), float(v[1])) for k, v in sim.get("occlusions", {}).items()
        }
        return cls(**values, sim=SimCameras(**sim))
