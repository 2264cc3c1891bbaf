"""The experiment's mocap process: one connection to the mocap server, poses on the bus.

``python -m hilswarm.agents.mocap.process --connect ENDPOINT --experiment EXP --bodies a,b
--settings JSON`` (the orchestrator starts it before the agents, :mod:`hilswarm.orchestrator.
mocap_runner`). It

1. opens a Zenoh client session (its own principal, ``mocap``) and declares one publisher per
   body of the experiment (explicit keys ``hilswarm/<exp>/mocap/<body>``), the status key
   and its liveliness token ``alive/_mocap``;
2. connects to the server through the system's client (:mod:`.clients`) — the only
   connection to it, as these systems expect;
3. per frame and body: maps the system's convention into the world frame (:mod:`.frames`),
   runs the body's filter (:mod:`.filter`), counts occluded frames, and publishes
   (:mod:`.message`); bodies the experiment does not use are not published;
   — with ``tick_frames_only`` in a self-clocked run only the frames its ticks can use, and a
   keep-alive (:mod:`.decimation`: it hears the manager's schedule on the tick key); with
   ``tick_spread_frames`` the bodies whose agents sense at this frame first (:mod:`.put_order`,
   from the same schedule);
4. after the poses of a frame, puts the frame clock (``mocap_clock``: frame number, frame time
   on this host's CLOCK_MONOTONIC, :mod:`.frame_clock`), which the instance manager locks the
   realtime ticks to;
5. publishes its status (JSON on ``mocap_status``): ``streaming`` with the bodies the system
   lists and those visible, every second and on change; ``lost`` when the server goes away
   (then it exits with status 1 — agents stop using poses at once); ``stopped`` on SIGTERM.

Exit status: 0 stopped, 1 server lost, 2 bad arguments or cannot connect.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any

import numpy as np
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.credentials import add_credentials_arguments, bus_access_from_args
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap import frame_clock, message
from hilswarm.agents.mocap.clients import (
    Frame,
    MocapClient,
    MocapConnectionError,
    MocapServerLost,
    make_client,
)
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.agents.mocap.decimation import PoseDecimator
from hilswarm.agents.mocap.filter import FilterBank, FilterTuning
from hilswarm.agents.mocap.frames import convention
from hilswarm.agents.mocap.put_order import PutOrder

logger = logging.getLogger(__name__)

#: Liveliness token name of the mocap process (``hilswarm/<exp>/alive/_mocap``).
MOCAP_NAME = "_mocap"
#: Zenoh principal (user name) of the mocap process where the bus has access control.
PRINCIPAL = "mocap"
#: Period of the status message while streaming [s].
STATUS_PERIOD_S = 1.0
#: QoS of pose messages: newest first, never blocking the frame loop on a slow subscriber.
POSE_QOS: dict[str, Any] = {
    "congestion_control": zenoh.CongestionControl.DROP,
    "priority": zenoh.Priority.REAL_TIME,
    "express": True,
}


class MocapProcess:
    """See the module docstring.

    Args:
        settings: the ``[mocap]`` section.
        experiment: experiment name (key prefix).
        bodies: the experiment's bodies (one per agent).
        endpoints: Zenoh endpoints (the orchestrator's router).
        run_id: the run's id (key prefix).
        security: the mocap principal's credentials (``None``: none).
        client: the system's client (default: :func:`~.clients.make_client`).
        clock: monotonic clock [s].
    """

    def __init__(
        self,
        settings: MocapSettings,
        experiment: str,
        bodies: Sequence[str],
        endpoints: Sequence[str],
        *,
        run_id: str = "",
        security: bus.SessionSecurity | None = None,
        client: MocapClient | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.settings = settings
        self.keys = bus.BusKeys(experiment, run_id)
        self._security = security
        self.bodies = tuple(bus.check_key_name(b, what="mocap body") for b in bodies)
        self.endpoints = list(endpoints)
        self.client = client or make_client(
            settings.system, settings.host, settings.port, settings.rate_hz
        )
        self._clock = clock
        self._convention = convention(settings.system, settings.up_axis)
        tuning = FilterTuning(
            position_std_m=settings.position_std_m, yaw_std_rad=settings.yaw_std_rad
        )
        n = len(self.bodies)
        self.filters = FilterBank(n, tuning)
        self.occluded = np.zeros(n, dtype=np.int64)  # consecutive frames unseen, per body
        self.seen = np.zeros(n, dtype=bool)  # seen at least once
        self._positions = np.full((n, 3), np.nan)  # this frame's measurements
        self._rotations = np.full((n, 3, 3), np.nan)
        # The simulator stamps frames with this host's CLOCK_MONOTONIC: latency is measurable.
        self._shared_clock = settings.system == "sim"
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._status_pub: zenoh.Publisher | None = None
        self._clock_pub: zenoh.Publisher | None = None
        self._tick_sub: zenoh.Subscriber | None = None
        self._status_due = 0.0
        self._last_state: tuple[Any, ...] = ()
        self._lock = threading.Lock()
        # a keep-alive at least twice per hold_s, so a waiting agent never counts its body lost
        self.decimator = PoseDecimator(
            1.0 / settings.rate_hz,
            keep_alive=max(1, settings.hold_frames // 2) if settings.tick_frames_only else 1,
        )
        # the bodies are the agents' own, in the graph's order: body i's agent has phase i
        self.put_order = PutOrder(
            [settings.tick_phase_s(i) for i in range(n)], 1.0 / settings.rate_hz
        )
        self.frames = 0
        self.skipped = 0

    # -- status ------------------------------------------------------------------------------

    def publish_status(self, state: str, detail: str = "") -> None:
        """Publish the status (JSON): state, bodies listed by the system, visible, missing."""
        visible = [n for i, n in enumerate(self.bodies) if self.seen[i] and not self.occluded[i]]
        status = {
            "state": state,
            "system": self.settings.system,
            "host": self.settings.host,
            "listed": list(self.client.bodies),
            "visible": visible,
            "missing": [n for n in self.bodies if n not in visible],
            "frames": self.frames,
            "frames_skipped": self.skipped,
            "frames_published": self.decimator.published,
            "detail": detail,
        }
        if self._status_pub is not None:
            self._status_pub.put(bus.encode_json(status))
        self._last_state = (state, tuple(visible))
        self._status_due = self._clock() + STATUS_PERIOD_S

    # -- frames ------------------------------------------------------------------------------

    def on_frame(self, frame: Frame) -> None:
        """Filter and publish every body of ``frame`` (runs on the client's thread).

        Every body at once, as arrays: the frame mapping, the filters, the occlusion counts;
        then one message and one put per body.
        """
        latency = frame.received_s - frame.time_s if self._shared_clock else 0.0
        positions, rotations = self._positions, self._rotations
        positions[:] = np.nan
        found = frame.bodies
        for i, name in enumerate(self.bodies):
            entry = found.get(name)
            if entry is not None:
                positions[i], rotations[i] = entry
        raw = self._convention.poses(positions, rotations)
        visible = np.isfinite(raw).all(axis=1)
        raw[~visible] = np.nan
        estimates = self.filters.update(frame.time_s, raw)
        self.occluded = np.where(visible, 0, self.occluded + 1)
        self.seen |= visible
        occluded = np.where(self.seen, self.occluded, np.maximum(self.occluded, 1)).tolist()
        rows = np.concatenate(
            [raw, estimates, self.filters.velocity, self.filters.innovation], axis=1
        ).tolist()
        number, time_s, received = frame.number, frame.time_s, frame.received_s
        host_time = received - latency  # the frame's time on this host's clock
        if self.decimator.wanted(host_time):
            bodies, publishers = self.bodies, self._publishers
            for i in self.put_order.order(host_time):
                publisher = publishers.get(bodies[i])
                if publisher is not None:
                    publisher.put(
                        message.encode_row(
                            number, time_s, received, latency, occluded=occluded[i], values=rows[i]
                        )
                    )
        if self._tick_sub is not None and self.decimator.ticked:
            if self.settings.tick_frames_only:  # said before the state below shows it
                logger.warning(
                    "tick_frames_only has no effect in this run: it is driven by tick messages "
                    '(agents on other hosts, an XBee gateway or realtime_clock = "manager"); '
                    "every frame's poses are published"
                )
            self._tick_sub.undeclare()  # tick messages may come at any rate: no more needed
            self._tick_sub = None
        clock_pub = self._clock_pub
        if clock_pub is not None:  # see frame_clock
            clock_pub.put(frame_clock.encode(number, host_time))
        self.frames += 1
        self.skipped += frame.skipped
        if self._clock() >= self._status_due:
            self.publish_status("streaming")

    def on_tick_key(self, sample: zenoh.Sample) -> None:
        """A message on the tick key (a Zenoh thread): the manager's schedule of a
        self-clocked run is handed to the decimator and the put order; a tick message means a
        run driven by tick messages, whose frames are all published, each in the bodies' own
        order (:mod:`.decimation`, :mod:`.put_order`)."""
        payload = sample.payload.to_bytes()
        if not bus.is_schedule(payload):
            self.decimator.every_frame()  # the frame loop then stops listening
            self.put_order.schedule = None
            return
        try:
            schedule = bus.decode_schedule(payload)
        except bus.BusMessageError:
            return  # not the manager's (it alone may put here): ignored
        self.decimator.schedule = schedule
        self.put_order.schedule = schedule

    # -- main --------------------------------------------------------------------------------

    def run(self) -> int:
        """Run until stopped (0) or the server is lost (1); cannot connect: 2."""
        session = bus.open_session(bus.client_config(self.endpoints, security=self._security))
        entities: list[Any] = []
        try:
            for name in self.bodies:
                self._publishers[name] = session.declare_publisher(
                    self.keys.mocap(name), **POSE_QOS
                )
            self._status_pub = session.declare_publisher(self.keys.mocap_status, **bus.DATA_QOS)
            self._clock_pub = session.declare_publisher(self.keys.mocap_clock, **POSE_QOS)
            entities.append(session.liveliness().declare_token(self.keys.alive(MOCAP_NAME)))
            if self.settings.tick_frames_only or self.put_order.spread:
                # the schedule says which frames to publish, and whose poses first
                self._tick_sub = session.declare_subscriber(self.keys.tick, self.on_tick_key)
            self.publish_status("connecting", f"{self.settings.system} at {self.settings.host}")
            try:
                self.client.run(self.on_frame, lambda: self.publish_status("streaming"))
            except MocapConnectionError as exc:
                logger.error("%s", exc)
                self.publish_status("failed", str(exc))
                return 2
            except MocapServerLost as exc:
                logger.error("%s", exc)
                self.publish_status("lost", str(exc))
                return 1
            self.publish_status("stopped")
            logger.info(
                "stopped after %d frames; poses published for %d of them",
                self.frames,
                self.decimator.published,
            )
            return 0
        finally:
            self._publishers.clear()
            self._status_pub = self._clock_pub = self._tick_sub = None
            entities.clear()
            session.close()

    def stop(self) -> None:
        """Stop streaming (thread- and signal-safe)."""
        self.client.stop()


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hilswarm.agents.mocap.process`` (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="python -m hilswarm.agents.mocap.process")
    parser.add_argument("--connect", action="append", default=[], help="Zenoh endpoint")
    parser.add_argument("--experiment", required=True, help="experiment name (key prefix)")
    parser.add_argument("--bodies", required=True, help="comma-separated rigid body names")
    parser.add_argument("--settings", required=True, help="[mocap] as JSON")
    parser.add_argument("--port", type=int, default=None, help="override the server's port")
    add_credentials_arguments(parser)
    parser.add_argument("-v", "--verbose", action="count", default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s mocap %(process)d %(name)s: %(message)s",
    )
    try:
        data = json.loads(args.settings)
        if args.port is not None:
            data["port"] = args.port
        settings = MocapSettings.from_dict(data)
        endpoints, run_id, security = bus_access_from_args(args)
        process = MocapProcess(
            settings,
            args.experiment,
            [b for b in args.bodies.split(",") if b],
            endpoints,
            run_id=run_id,
            security=security,
        )
    except (ValueError, TypeError, HilswarmError) as exc:
        logger.error("bad arguments: %s", exc)
        return 2

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        process.stop()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        return process.run()
    except bus.BusConnectionError as exc:
        logger.error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
