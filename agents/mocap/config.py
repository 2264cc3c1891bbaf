"""The ``[mocap]`` section of an experiment file, as a small typed model.

::

    [mocap]
    system = "qualisys"     # vicon, optitrack, qualisys, vrpn or sim
    host = "192.168.1.10"   # the mocap server (sim: the built-in simulator on loopback)
    rate_hz = 100.0         # the system's frame rate [Hz]
    hold_frames = 10        # frames a lost body's pose is held before the agent goes safe
    # port = 22223          # optional: the server's port (system default otherwise)
    # up_axis = "z"         # optional: override the system's default up axis ("y" or "z")
    # position_std_m = 0.002, yaw_std_rad = 0.02   # Kalman measurement noise

    [mocap.sim]             # system = "sim" only: what the simulated cameras do
    noise_std_m = 0.002
    noise_std_rad = 0.01
    latency_s = 0.002
    dropout_rate = 0.0      # probability per body and frame that an occlusion starts
    dropout_frames = 5
    occlusions = { f1 = [2.0, 3.0] }   # scripted: body -> [start, end] [s, experiment time]

Per agent, ``mocap_body = "frisbee1"`` names its rigid body (default: the agent's name).

:func:`parse_mocap` returns the model and a list of ``(key, message)`` problems, so the
experiment loader reports them with every other problem of the file.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from hilswarm.agents.mocap.frames import SYSTEMS

MOCAP_KEYS: tuple[str, ...] = (
    "system",
    "host",
    "port",
    "rate_hz",
    "hold_frames",
    "up_axis",
    "position_std_m",
    "yaw_std_rad",
    "start_timeout_s",
    "sim",
)
SIM_KEYS: tuple[str, ...] = (
    "noise_std_m",
    "noise_std_rad",
    "latency_s",
    "dropout_rate",
    "dropout_frames",
    "occlusions",
    "seed",
)
DEFAULT_RATE_HZ = 100.0
DEFAULT_HOLD_FRAMES = 10
DEFAULT_START_TIMEOUT_S = 5.0


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
    sim: SimCameras = field(default_factory=SimCameras)

    @property
    def hold_s(self) -> float:
        """How long a body may go unseen before its agent goes safe [s]."""
        return self.hold_frames / self.rate_hz

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


def parse_mocap(
    table: Any, *, where: str = "mocap"
) -> tuple[MocapSettings | None, list[tuple[str, str]]]:
    """Check a ``[mocap]`` table; returns ``(settings or None, [(key, message), ...])``."""
    problems: list[tuple[str, str]] = []
    if not isinstance(table, dict):
        return None, [(where, "must be a table ([mocap])")]
    for key in table:
        if key not in MOCAP_KEYS:
            problems.append(
                (f"{where}.{key}", f"unknown key; expected one of {', '.join(MOCAP_KEYS)}")
            )
    system = table.get("system")
    if system not in SYSTEMS:
        problems.append(
            (f"{where}.system", f"{system!r} is not one of " + ", ".join(repr(s) for s in SYSTEMS))
        )
    host = table.get("host", "127.0.0.1" if system == "sim" else None)
    if not isinstance(host, str) or not host.strip():
        problems.append(
            (f"{where}.host", 'missing; give the mocap server address, e.g. host = "192.168.1.10"')
        )
    port = table.get("port")
    if port is not None and (
        isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536
    ):
        problems.append((f"{where}.port", f"{port!r} is not a port (1..65535)"))
    rate = _number(
        table.get("rate_hz", DEFAULT_RATE_HZ), f"{where}.rate_hz", problems, low=0.0, high=10000.0
    )
    hold = table.get("hold_frames", DEFAULT_HOLD_FRAMES)
    if isinstance(hold, bool) or not isinstance(hold, int) or not 1 <= hold <= 100000:
        problems.append((f"{where}.hold_frames", f"{hold!r} is not a number of frames >= 1"))
    up = table.get("up_axis")
    if up is not None and up not in ("y", "z"):
        problems.append((f"{where}.up_axis", f"{up!r} is not 'y' or 'z'"))
    pos_std = _number(
        table.get("position_std_m", 0.002), f"{where}.position_std_m", problems, low=0.0
    )
    yaw_std = _number(table.get("yaw_std_rad", 0.02), f"{where}.yaw_std_rad", problems, low=0.0)
    start = _number(
        table.get("start_timeout_s", DEFAULT_START_TIMEOUT_S),
        f"{where}.start_timeout_s",
        problems,
        low=0.0,
        high=600.0,
    )
    sim = _sim(table.get("sim", {}), f"{where}.sim", problems)
    if "sim" in table and system != "sim":
        problems.append((f"{where}.sim", 'only for system = "sim"'))
    if problems:
        return None, problems
    return (
        MocapSettings(
            system=system,
            host=host,
            port=port,
            rate_hz=rate,
            hold_frames=hold,
            up_axis=up,
            position_std_m=pos_std,
            yaw_std_rad=yaw_std,
            start_timeout_s=start,
            sim=sim,
        ),
        problems,
    )


def _sim(table: Any, where: str, problems: list[tuple[str, str]]) -> SimCameras:
    if not isinstance(table, dict):
        problems.append((where, "must be a table ([mocap.sim])"))
        return SimCameras()
    for key in table:
        if key not in SIM_KEYS:
            problems.append(
                (f"{where}.{key}", f"unknown key; expected one of {', '.join(SIM_KEYS)}")
            )
    values: dict[str, Any] = {}
    for key in ("noise_std_m", "noise_std_rad", "latency_s"):
        values[key] = _number(table.get(key, 0.0), f"{where}.{key}", problems, low=0.0, high=10.0)
    values["dropout_rate"] = _number(
        table.get("dropout_rate", 0.0), f"{where}.dropout_rate", problems, low=0.0, high=1.0
    )
    frames = table.get("dropout_frames", 5)
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        problems.append((f"{where}.dropout_frames", f"{frames!r} is not a number of frames >= 1"))
        frames = 5
    values["dropout_frames"] = frames
    occlusions: dict[str, tuple[float, float]] = {}
    raw = table.get("occlusions", {})
    if not isinstance(raw, dict):
        problems.append((f"{where}.occlusions", "must be a table: body = [start_s, end_s]"))
        raw = {}
    for body, window in raw.items():
        ok = isinstance(window, list) and len(window) == 2
        ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in window)
        if not ok or not 0 <= window[0] < window[1]:
            problems.append(
                (
                    f"{where}.occlusions.{body}",
                    f"{window!r} is not [start_s, end_s] with 0 <= start < end",
                )
            )
            continue
        occlusions[body] = (float(window[0]), float(window[1]))
    values["occlusions"] = occlusions
    seed = table.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
        problems.append((f"{where}.seed", f"{seed!r} is not an integer >= 0"))
        seed = None
    values["seed"] = seed
    return SimCameras(**values)


def _number(
    value: Any, key: str, problems: list[tuple[str, str]], *, low: float, high: float = math.inf
) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        problems.append((key, f"{value!r} is not a finite number"))
        return 0.0
    if not low <= value <= high or (low == 0.0 and key.endswith("rate_hz") and value == 0):
        problems.append((key, f"{value!r} is out of range ({low:g} .. {high:g})"))
        return 0.0
    return float(value)
