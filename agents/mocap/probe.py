"""Look at what a mocap system streams for a moment: bodies, their rate and world pose.

Used by ``hilswarm mocap`` (list what the system sees before a run) and by ``hilswarm check``
(a body the experiment needs that the system does not see is named, with the ones it sees).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from hilswarm.agents.mocap.clients import Frame, MocapClient, MocapConnectionError, make_client
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.agents.mocap.frames import convention, pose_from

#: How long a probe watches the stream by default [s].
DEFAULT_PROBE_S = 1.0


@dataclass
class BodySeen:
    """One body over the probe.

    Attributes:
        name: the system's name of the body.
        frames: frames in which it was tracked.
        pose: its last world pose ``[x, y, z (m), roll, pitch, yaw (rad)]`` (NaN: never seen).
    """

    name: str
    frames: int = 0
    pose: np.ndarray = field(default_factory=lambda: np.full(6, np.nan))


@dataclass
class ProbeResult:
    """What the probe saw.

    Attributes:
        frames: frames received.
        duration_s: how long it watched (first to last frame) [s].
        bodies: every body the system listed or sent, by name.
    """

    frames: int = 0
    duration_s: float = 0.0
    bodies: dict[str, BodySeen] = field(default_factory=dict)

    @property
    def rate_hz(self) -> float:
        """Frames per second received (0 with fewer than two frames)."""
        return (self.frames - 1) / self.duration_s if self.frames > 1 and self.duration_s else 0.0

    def visible(self) -> list[str]:
        """Bodies tracked in at least one frame."""
        return [name for name, body in self.bodies.items() if body.frames]

    def body_rate_hz(self, name: str) -> float:
        """Frames per second in which ``name`` was tracked."""
        body = self.bodies.get(name)
        if body is None or not self.frames:
            return 0.0
        return self.rate_hz * body.frames / self.frames


def probe(
    settings: MocapSettings,
    *,
    duration_s: float = DEFAULT_PROBE_S,
    client: MocapClient | None = None,
) -> ProbeResult:
    """Connect, watch ``duration_s`` of frames, disconnect.

    Raises:
        MocapConnectionError: the server cannot be reached (or refuses the session).
        MocapServerLost: it went away during the probe.
    """
    client = client or make_client(settings.system, settings.host, settings.port, settings.rate_hz)
    to_world = convention(settings.system, settings.up_axis).to_world
    result = ProbeResult()
    first: list[float] = []
    timer: list[threading.Timer] = []

    def on_frame(frame: Frame) -> None:
        if not first:
            first.append(frame.received_s)
        result.frames += 1
        result.duration_s = frame.received_s - first[0]
        for name in client.bodies:
            result.bodies.setdefault(name, BodySeen(name))
        for name, entry in frame.bodies.items():
            body = result.bodies.setdefault(name, BodySeen(name))
            if entry is not None:
                position, rotation = to_world(*entry)
                body.pose = pose_from(position, rotation)
                body.frames += 1

    def on_ready() -> None:
        stop = threading.Timer(duration_s, client.stop)
        stop.daemon = True
        timer.append(stop)
        stop.start()

    try:
        client.run(on_frame, on_ready)
    finally:
        for stop in timer:
            stop.cancel()
    for name in client.bodies:
        result.bodies.setdefault(name, BodySeen(name))
    return result


__all__ = ["BodySeen", "MocapConnectionError", "ProbeResult", "probe"]
