"""An agent's pose from the experiment's mocap process: its own body's key on the bus.

:class:`MocapPoseSource` is the vehicle's ``pose_source`` when the experiment has a
``[mocap]`` section. It subscribes to exactly one body key (``hilswarm/<exp>/mocap/<body>``)
and to the mocap process's status. The subscription callbacks only decode and store the newest
message (no blocking, no work); a pose message that cannot be decoded is dropped and counted
(:attr:`MocapPoseSource.malformed`, and ``on_malformed``: the agent's ``malformed["mocap"]``
status counter). :meth:`MocapPoseSource.pose`, called once per tick when the vehicle senses,
decides:

* the newest filtered pose (world frame, :mod:`hilswarm.agents.mocap.frames`) while the body
  is seen or occluded for at most ``hold_frames`` frames (the pose is then held);
* otherwise **no stale pose**: it calls ``on_lost("lost tracking: ...")`` (the vehicle enters
  safe mode; the agent goes safe with that reason and the experiment's ``on_agent_safe``
  policy applies) and returns NaN. The reasons: the body occluded for more than
  ``hold_frames`` frames; no message for longer than ``hold_s`` (the mocap process or its
  server is gone); the mocap process reporting its server lost.

A controller that ``uses_neighbour_poses`` also gets its graph neighbours' bodies
(:meth:`MocapPoseSource.neighbour_poses`; each an explicit key, nothing else is received).

With ``system = "sim"`` it also publishes its simulated plant's true world pose on
``mocap_truth/<body>`` after each sense, with the tick's experiment time (and at start, with
none) — what the simulated cameras see.

Per tick it appends to the vehicle's telemetry channel ``mocap`` (:data:`TELEMETRY_FIELDS`):
frame number, frame time [s], latency frame time -> this sense [s] (same host only), frames
occluded, the pose as position + quaternion (for ``/<agent>/pose``), the filter's innovation,
the delivery frame time -> the pose's arrival at this agent [s] (the rest of the latency is
the wait for the tick), and how long this sense waited for its frame's pose [s] (below).

**Waiting for the tick's frame.** With the realtime ticks locked to the frames (``[mocap]
tick_lock``, docs/mocap.md) each tick is due a short lag after a frame reached the host; its
pose may still be on its way to this agent (the bus delivery's tail is longer than the lag).
Then the newest pose here is the previous frame's, and using it would add a whole frame period
of latency. So, given ``pose_wait_s`` > 0, a sense whose newest pose arrived more than one frame
period ago (the next frame's pose is overdue: poses come one period apart) waits for it, at most
``pose_wait_s`` (``[mocap] pose_wait_ms``; 0 by default: docs/mocap.md has the measured
trade-off), and then uses the newest pose it has. A sense whose newest pose came less than a
period ago never waits, however late the sense itself is: that pose is its frame's (waiting
for the next frame instead, as a half-period rule did, made late senses later still and their
poses older). Only arrival times on this agent's own clock are compared,
so it holds for agents on other hosts too. The wait runs on the agent's worker thread (never
a bus thread); when frames stop, each sense waits at most ``pose_wait_s`` until tracking is
declared lost (``hold_frames``).

**Knowing the tick's frame** (self-clocked runs). A self-clocked agent knows when its tick was
due (:meth:`MocapPoseSource.tick_due`), so it knows its frame: the one that reached the host
``tick_lag_s`` before (its phase included, ``[mocap] tick_spread_frames``). Such agents run
on the host of the orchestrator, whose mocap process stamps each frame's arrival
(``received_s``) on the same CLOCK_MONOTONIC. So the sense waits (at most ``pose_wait_s``)
exactly when the newest pose reached the mocap process more than half a frame period before
the tick's frame did: the previous frame's, or older, whatever the lag. The rule above, on
arrival times only, is kept for ticks driven by tick messages.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap import message
from hilswarm.agents.mocap.frames import world_to_ned, yaw_quaternion

logger = logging.getLogger(__name__)

#: Fields of the ``mocap`` telemetry channel.
TELEMETRY_FIELDS: tuple[str, ...] = (
    "frame",
    "frame_time_s",
    "latency_s",
    "occluded",
    "x",
    "y",
    "z",
    "qx",
    "qy",
    "qz",
    "qw",
    "innovation_x",
    "innovation_y",
    "innovation_z",
    "innovation_yaw",
    "delivery_s",
    "pose_wait_s",
)
CHANNEL = "mocap"
#: Bound on the wake-ups of one such wait (poses of the same frame repeated, spurious wakes).
_POSE_WAIT_WAKES = 64
_NAN_POSE = np.full(6, np.nan)
_NAN_POSE.setflags(write=False)


class MocapBodyMissingError(HilswarmError, LookupError):
    """The agent's body was not seen by the mocap system at start."""


class MocapPoseSource:
    """One agent's pose from the bus (see the module docstring).

    Args:
        body: the rigid body's name.
        hold_frames: frames an occluded body's pose is held before tracking counts as lost.
        hold_s: longest time without a message before tracking counts as lost [s].
        start_timeout_s: bound on waiting for the first pose (:meth:`wait_first`) [s].
        truth: the simulated plant (``pose()`` in its ``pose_frame``) to feed the simulator,
            or ``None``.
        on_lost: called once with the reason when tracking is lost (``vehicle.enter_safe_mode``).
        clock: monotonic clock [s] (CLOCK_MONOTONIC: latencies are compared across processes).

    Attributes:
        on_malformed: called (on the bus thread, so it must not block) for each pose message,
            of the body or of a neighbour's, that cannot be decoded; the agent sets it to
            count ``malformed["mocap"]``. Set it before :meth:`attach_bus`.
    """

    #: Poses come in the world frame (z up).
    frame = "world"

    def __init__(
        self,
        body: str,
        *,
        hold_frames: int,
        hold_s: float,
        start_timeout_s: float = 5.0,
        truth: Any | None = None,
        on_lost: Callable[[str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        frame_period_s: float = 0.0,
        pose_wait_s: float = 0.0,
        tick_lag_s: float = 0.0,
    ) -> None:
        self.body = bus.check_key_name(body, what="mocap body")
        self.hold_frames = int(hold_frames)
        self.hold_s = float(hold_s)
        self.start_timeout_s = float(start_timeout_s)
        self._truth = truth
        self._on_lost = on_lost
        self._clock = clock
        if not (math.isfinite(frame_period_s) and frame_period_s >= 0.0):
            raise ValueError(f"frame_period_s must be >= 0 [s], got {frame_period_s!r}")
        if not (math.isfinite(pose_wait_s) and pose_wait_s >= 0.0):
            raise ValueError(f"pose_wait_s must be >= 0 [s], got {pose_wait_s!r}")
        #: Frame period of the mocap system [s] (0: unknown; no waiting for a frame's pose).
        self.frame_period_s = float(frame_period_s)
        #: Bound on a sense's wait for its tick's frame [s] (0: never waits; module docstring).
        self.pose_wait_s = float(pose_wait_s) if frame_period_s > 0.0 else 0.0
        #: Locked ticks are due this long after their frame reached the host [s].
        self.tick_lag_s = float(tick_lag_s)
        # When the next sense's frame reached the mocap process [s, CLOCK_MONOTONIC]; NaN:
        # not known (tick messages), the arrival rule applies (module docstring).
        self._frame_expected = math.nan
        #: Senses that waited for their frame's pose and got it / waited in vain.
        self.pose_waits = 0
        self.pose_wait_timeouts = 0
        self._fresh = threading.Event()  # set by every pose message of the agent's body
        self._latest: tuple[message.BodyPose, float] | None = None  # (message, arrival [s])
        #: Graph neighbours whose poses the controller asks for: agent name -> body.
        self.neighbours: dict[str, str] = {}
        self._neighbour_latest: dict[str, tuple[message.BodyPose, float]] = {}
        self._status: dict[str, Any] = {}
        self._first = threading.Event()
        self._truth_pub: zenoh.Publisher | None = None
        self._channel: Any = None
        self._row = np.full(len(TELEMETRY_FIELDS), np.nan)
        self.lost_reason: str | None = None
        self.on_malformed: Callable[[], None] | None = None
        self._malformed = 0
        self._malformed_lock = threading.Lock()  # two bus threads may count at once
        #: Latency [s] frame time -> sense of every pose used (benchmarks read it).
        self.latencies: list[float] = []
        self.keep_latencies = False

    # -- wiring ------------------------------------------------------------------------------

    def add_telemetry(self, telemetry: Any) -> None:
        """Add the ``mocap`` channel to the vehicle's telemetry (before the agent declares)."""
        self._channel = telemetry.add_channel(CHANNEL, TELEMETRY_FIELDS)

    def attach_bus(self, session: zenoh.Session, keys: bus.BusKeys) -> list[Any]:
        """Subscribe to this body and to the mocap status; returns the entities to keep."""
        entities: list[Any] = [
            session.declare_subscriber(keys.mocap(self.body), bus_callback.callback(self._on_pose)),
            session.declare_subscriber(keys.mocap_status, bus_callback.callback(self._on_status)),
        ]
        for agent, body in self.neighbours.items():
            entities.append(
                session.declare_subscriber(
                    keys.mocap(body),
                    bus_callback.callback(
                        lambda sample, agent=agent: self._on_neighbour(agent, sample)
                    ),
                )
            )
        if self._truth is not None:
            self._truth_pub = session.declare_publisher(keys.mocap_truth(self.body), **bus.DATA_QOS)
            entities.append(self._truth_pub)
            self._publish_truth()
        return entities

    @property
    def malformed(self) -> int:
        """Pose messages (own body and neighbours') dropped because they could not be decoded."""
        return self._malformed

    def _count_malformed(self, body: str, exc: BaseException) -> None:
        """Count a pose message that cannot be decoded (bus thread: no blocking work; only the
        first is logged, the rest are counted in the agent's status)."""
        with self._malformed_lock:
            self._malformed += 1
            first = self._malformed == 1
        if first:
            logger.warning("mocap body %s: %s (dropped; further ones are only counted)", body, exc)
        if self.on_malformed is not None:
            self.on_malformed()

    def _on_pose(self, sample: zenoh.Sample) -> None:
        try:
            decoded = message.decode(sample.payload.to_bytes())
        except bus.BusMessageError as exc:
            self._count_malformed(self.body, exc)
            return
        self._latest = (decoded, self._clock())
        self._fresh.set()
        if not decoded.occluded:
            self._first.set()

    def _on_neighbour(self, agent: str, sample: zenoh.Sample) -> None:
        try:
            decoded = message.decode(sample.payload.to_bytes())
        except bus.BusMessageError as exc:
            self._count_malformed(self.neighbours.get(agent, agent), exc)
            return
        self._neighbour_latest[agent] = (decoded, self._clock())

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if isinstance(status, dict):
            self._status = status

    def wait_first(self) -> None:
        """Wait (bounded by ``start_timeout_s``) until the body has been seen once.

        Raises:
            MocapBodyMissingError: not seen in time; names the bodies the system does see.
        """
        deadline = time.monotonic() + self.start_timeout_s
        while not self._first.wait(0.05):
            if self._truth is not None:
                self._publish_truth()
            if time.monotonic() > deadline:
                seen = self._status.get("visible")
                state = self._status.get("state")
                if state is None:
                    also = "no mocap process answered (is [mocap] running?)"
                else:
                    also = "the system sees: " + (", ".join(seen) if seen else "no bodies")
                raise MocapBodyMissingError(
                    f"mocap body {self.body!r} is not visible after {self.start_timeout_s:g} s; "
                    f"{also}"
                )

    # -- per tick ----------------------------------------------------------------------------

    def _publish_truth(self, t: float = math.nan) -> None:
        publisher, plant = self._truth_pub, self._truth
        if publisher is None or plant is None:
            return
        pose = np.asarray(plant.pose(), dtype=np.float64).reshape(6)
        if getattr(plant, "pose_frame", "world") == "ned":
            pose = world_to_ned(pose)  # its own inverse: NED -> world
        publisher.put(message.encode_truth(pose, t))

    def lost(self) -> str | None:
        """Why tracking is lost now, or ``None`` while the pose may be used."""
        return self._why_lost(self.body, self._latest)

    def _why_lost(self, body: str, latest: tuple[message.BodyPose, float] | None) -> str | None:
        if self._status.get("state") == "lost":
            return f"lost tracking: mocap server lost ({self._status.get('detail', '')})"
        if latest is None:
            return f"lost tracking: no pose of body {body!r} received"
        pose, arrived = latest
        if pose.occluded > self.hold_frames:
            return f"lost tracking: body {body!r} not seen for {pose.occluded} frames"
        age = self._clock() - arrived
        if age > self.hold_s:
            return f"lost tracking: no mocap frame for {age:.3f} s (mocap process silent)"
        return None

    def neighbour_poses(self) -> dict[str, np.ndarray | None]:
        """The neighbours' newest poses (world frame) by agent name; ``None``: lost or unseen
        (the same rules as the agent's own body, no stale pose)."""
        poses: dict[str, np.ndarray | None] = {}
        for agent, body in self.neighbours.items():
            latest = self._neighbour_latest.get(agent)
            lost = self._why_lost(body, latest)
            poses[agent] = None if lost is not None or latest is None else latest[0].pose.copy()
        return poses

    def tick_due(self, due_s: float) -> None:
        """The next sense is that of a tick due at ``due_s`` [s, this host's CLOCK_MONOTONIC]
        (a self-clocked agent tells it before each tick): its frame reached the host
        :attr:`tick_lag_s` before (module docstring, "Knowing the tick's frame")."""
        self._frame_expected = due_s - self.tick_lag_s

    def _await_frame(self) -> float:
        """Wait, bounded by :attr:`pose_wait_s`, for the pose of the tick's frame when the
        newest one is not it (module docstring). Returns the time waited [s]; runs on the
        agent's worker thread."""
        latest = self._latest
        expected, self._frame_expected = self._frame_expected, math.nan  # this sense's only
        if latest is None or self.pose_wait_s <= 0.0:
            return 0.0
        start = self._clock()
        if math.isfinite(expected):  # the tick's frame is known: wait for a pose of it
            since = expected - 0.5 * self.frame_period_s
            if latest[0].received_s >= since:
                return 0.0

            def arrived(newest: tuple[message.BodyPose, float]) -> bool:
                return newest[0].received_s >= since

        else:  # tick messages: the next frame's pose is overdue after one frame period
            if start - latest[1] <= self.frame_period_s:
                return 0.0
            frame = latest[0].frame

            def arrived(newest: tuple[message.BodyPose, float]) -> bool:
                return newest[0].frame != frame

        deadline = start + self.pose_wait_s
        for _ in range(_POSE_WAIT_WAKES):
            self._fresh.clear()
            newest = self._latest
            if newest is not None and arrived(newest):
                self.pose_waits += 1
                return self._clock() - start
            remaining = deadline - self._clock()
            if remaining <= 0.0:
                break
            self._fresh.wait(remaining)
        self.pose_wait_timeouts += 1
        return self._clock() - start

    def pose(self) -> np.ndarray:
        """The body's pose ``[x, y, z (m), roll, pitch, yaw (rad)]`` (world frame), or NaN.

        With :attr:`pose_wait_s` > 0 it may first wait, bounded, for the tick's frame (module
        docstring)."""
        waited = self._await_frame() if self.lost_reason is None else 0.0
        reason = self.lost_reason or self.lost()
        row = self._row
        if reason is not None:
            if self.lost_reason is None:
                self.lost_reason = reason
                logger.warning("mocap body %s: %s", self.body, reason)
                if self._on_lost is not None:
                    self._on_lost(reason)
            row[:] = np.nan
            return _NAN_POSE.copy()
        latest, arrived = self._latest  # type: ignore[misc]  # lost() checked it
        latency = latest.latency_s(self._clock())
        if self.keep_latencies:
            self.latencies.append(latency)
        p = latest.pose
        qx, qy, qz, qw = yaw_quaternion(float(p[3]), float(p[4]), float(p[5]))
        row[:] = (
            latest.frame,
            latest.frame_time_s,
            latency,
            latest.occluded,
            p[0],
            p[1],
            p[2],
            qx,
            qy,
            qz,
            qw,
            *latest.innovation.tolist(),
            latest.latency_s(arrived),
            waited,
        )
        return p.copy()

    def record(self, k: int, t: float) -> None:
        """After the sense of tick ``k`` at experiment time ``t`` [s] (the vehicle calls it):
        append the tick's row to the ``mocap`` telemetry channel and, with the simulator,
        publish the plant's true pose of time ``t`` (the next camera frames measure it)."""
        self._publish_truth(t)
        if self._channel is not None:
            self._channel.append(k, t, self._row)
