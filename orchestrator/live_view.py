"""The live view of a run: foxglove-sdk's WebSocket server on localhost (``hilswarm run --live``).

The recorder process serves every message it records, as it records it: the same topics, JSON
schemas and messages as the MCAP file (``docs/recording.md``), so the Foxglove app plots
``/<agent>/y.x``, ``/<agent>/u.v_left``, ``/orchestrator/ticks.completion_s`` while the run goes.
For every agent whose outputs include a position and a heading (``x``, ``y``, optional ``z``,
and ``psi`` or ``yaw``) it also serves ``/<agent>/pose`` as a ``foxglove.PoseInFrame`` in frame
``world``, for the 3D panel (unless the run records a ``/<agent>/pose`` of its own, e.g. from
motion capture).

Cost. The server is foxglove-sdk's (Rust, its own threads). A message is handed to it only
while a client is subscribed to its topic (subscriptions are tracked with the server's
listener callbacks), so with no client connected the recorder pays one set lookup per message.
Each client has a bounded queue (:data:`DEFAULT_BACKLOG` messages); when a slow client lets
it fill, the server drops that client's oldest messages (its control messages, such as the
channels' advertisements, have a queue of the same size, and a client that lets that one fill
is disconnected). Nothing waits for a client: not the recorder, and certainly not the bus or
the ticks, which run in other processes.
"""

from __future__ import annotations

import json
import logging
import math
import socket
import threading
from collections.abc import Mapping
from typing import Any

import foxglove
from foxglove.channels import PoseInFrameChannel
from foxglove.messages import Pose, PoseInFrame, Quaternion, Timestamp, Vector3

logger = logging.getLogger(__name__)

#: Messages queued per client before its oldest are dropped (foxglove-sdk's backlog).
DEFAULT_BACKLOG = 4096
#: Interface the server listens on: the live view is for this machine only.
LOCALHOST = "127.0.0.1"
#: Frame of the poses served.
WORLD_FRAME = "world"
_HEADINGS = ("psi", "yaw")


def port_problem(port: int) -> str:
    """Why the live view cannot listen on localhost ``port`` ("" if it can; 0 always can)."""
    if port == 0:
        return ""
    if not 0 < port < 65536:
        return f"--live: {port} is not a TCP port (1..65535, or none for a free one)"
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((LOCALHOST, port))
        except OSError as exc:
            return f"--live: cannot listen on {LOCALHOST}:{port}: {exc.strerror or exc}"
    return ""


def pose_entries(schema: Mapping[str, Any]) -> tuple[str, str, str | None, str] | None:
    """The field names ``(x, y, z or None, heading)`` of a ``y`` schema that holds a pose."""
    fields = set((schema.get("properties") or {}).keys())
    heading = next((name for name in _HEADINGS if name in fields), None)
    if heading is None or not {"x", "y"} <= fields:
        return None
    return "x", "y", ("z" if "z" in fields else None), heading


class LiveView:
    """A foxglove-sdk WebSocket server that mirrors a recording (a ``mcap_io.Mirror``).

    Args:
        port: TCP port on localhost; 0 picks a free one (see :attr:`url`).
        name: server name shown by the Foxglove app.
        backlog: messages queued per client before its oldest are dropped.

    Raises:
        OSError: the port cannot be bound (foxglove-sdk's error, re-raised as ``OSError``).
    """

    def __init__(self, port: int = 0, *, name: str = "hilswarm", backlog: int = DEFAULT_BACKLOG):
        self._context = foxglove.Context()
        self._lock = threading.Lock()  # subscriptions change on the server's threads
        self._subscribers: dict[str, int] = {}  # topic -> subscriptions
        self._live: set[int] = set()  # recorder channel ids with a subscriber
        self._channels: dict[int, foxglove.Channel] = {}
        self._topics: dict[int, str] = {}
        self._ids: dict[str, int] = {}
        self._poses: dict[int, tuple[tuple[str, str, str | None, str], PoseInFrameChannel]] = {}
        self._pose_topics: dict[str, PoseInFrameChannel] = {}
        # Ids of the served channels with a subscriber (replaced, never mutated: read lock-free)
        self._subscribed_channel_ids: set[int] = set()
        self.messages_sent = 0
        try:
            self._server = foxglove.start_server(
                name=name,
                host=LOCALHOST,
                port=port,
                server_listener=self,
                context=self._context,
                message_backlog_size=backlog,
            )
        except RuntimeError as exc:  # foxglove-sdk reports bind errors as RuntimeError
            raise OSError(f"live view: cannot serve on {LOCALHOST}:{port}: {exc}") from exc
        self.port: int = self._server.port
        self.url = f"ws://{LOCALHOST}:{self.port}"

    # -- mcap_io.Mirror -------------------------------------------------------------------------

    def add_channel(self, channel_id: int, topic: str, schema: Mapping[str, Any]) -> None:
        """Advertise ``topic`` to clients (JSON messages with its JSON Schema)."""
        channel = foxglove.Channel(
            topic,
            schema=foxglove.Schema(
                name=str(schema.get("title") or topic),
                encoding="jsonschema",
                data=json.dumps(schema).encode(),
            ),
            message_encoding="json",
            context=self._context,
        )
        with self._lock:
            self._channels[channel_id] = channel
            self._topics[channel_id] = topic
            self._ids[topic] = channel_id
            if self._subscribers.get(topic):
                self._live.add(channel_id)
            agent, _, leaf = topic[1:].partition("/")
            if leaf == "pose":  # the run records its own poses (motion capture)
                self._drop_pose(agent)
            elif leaf == "y" and f"/{agent}/pose" not in self._ids:
                entries = pose_entries(schema)
                if entries is not None:
                    self._add_pose(channel_id, agent, entries)

    def log(self, channel_id: int, data: bytes, log_time_ns: int) -> None:
        """Serve one message (only while a client is subscribed to its topic)."""
        if channel_id not in self._live:
            return
        channel = self._channels.get(channel_id)
        if channel is not None and channel.id() in self._subscribed_channel_ids:
            channel.log(data, log_time=log_time_ns)
            self.messages_sent += 1
        pose = self._poses.get(channel_id)
        if pose is not None:
            self._log_pose(pose, data, log_time_ns)

    # -- poses --------------------------------------------------------------------------------

    def _add_pose(
        self, y_channel: int, agent: str, entries: tuple[str, str, str | None, str]
    ) -> None:
        topic = f"/{agent}/pose"
        channel = PoseInFrameChannel(topic, context=self._context)
        self._pose_topics[topic] = channel
        self._poses[y_channel] = (entries, channel)
        if self._subscribers.get(topic):
            self._live.add(y_channel)

    def _drop_pose(self, agent: str) -> None:
        channel = self._pose_topics.pop(f"/{agent}/pose", None)
        if channel is None:
            return
        self._poses = {k: v for k, v in self._poses.items() if v[1] is not channel}
        channel.close()

    def _log_pose(
        self,
        pose: tuple[tuple[str, str, str | None, str], PoseInFrameChannel],
        data: bytes,
        log_time_ns: int,
    ) -> None:
        (x_name, y_name, z_name, heading_name), channel = pose
        if channel.id() not in self._subscribed_channel_ids:
            return
        message = json.loads(data)
        numbers = [message.get(x_name), message.get(y_name), message.get(heading_name)]
        z = message.get(z_name) if z_name else 0.0
        if not all(isinstance(v, int | float) for v in (*numbers, z)):
            return  # a NaN (null) entry: no pose this tick
        x, y, heading = numbers
        channel.log(
            PoseInFrame(
                timestamp=Timestamp(log_time_ns // 1_000_000_000, log_time_ns % 1_000_000_000),
                frame_id=WORLD_FRAME,
                pose=Pose(
                    position=Vector3(x=x, y=y, z=z),
                    orientation=Quaternion(
                        x=0.0, y=0.0, z=math.sin(heading / 2), w=math.cos(heading / 2)
                    ),
                ),
            ),
            log_time=log_time_ns,
        )

    # -- foxglove.ServerListener ----------------------------------------------------------------

    def on_subscribe(self, client: Any, channel: Any) -> None:
        """A client subscribed to ``channel``: its messages are served from now on."""
        del client
        with self._lock:
            topic = str(channel.topic)
            self._subscribers[topic] = self._subscribers.get(topic, 0) + 1
            self._subscribed_channel_ids = {*self._subscribed_channel_ids, int(channel.id)}
            self._refresh()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """A client unsubscribed (or left): with no subscriber left, nothing more is served."""
        del client
        with self._lock:
            topic = str(channel.topic)
            left = self._subscribers.get(topic, 0) - 1
            if left > 0:
                self._subscribers[topic] = left
            else:
                self._subscribers.pop(topic, None)
                self._subscribed_channel_ids = self._subscribed_channel_ids - {int(channel.id)}
            self._refresh()

    def _refresh(self) -> None:
        """Recompute the recorder channels worth handing over (under the lock)."""
        live = {self._ids[t] for t in self._subscribers if t in self._ids}
        for y_channel, (_, pose_channel) in self._poses.items():
            if pose_channel.id() in self._subscribed_channel_ids:
                live.add(y_channel)
        self._live = live

    @property
    def subscribed_topics(self) -> tuple[str, ...]:
        """Topics at least one client is subscribed to."""
        with self._lock:
            return tuple(sorted(self._subscribers))

    def close(self) -> None:
        """Stop the server (clients are disconnected). Idempotent."""
        server, self._server = self._server, None
        if server is not None:
            server.stop()
