"""The pose message of one rigid body on ``hilswarm/<exp>/mocap/<body>``.

Fixed little-endian layout (no JSON on the hot path), 200 bytes:

=======  =========  ============================================================
offset   type       field
=======  =========  ============================================================
0        uint64     ``frame``: the system's frame number
8        float64    ``frame_time_s``: the system's timestamp of the frame [s]
16       float64    ``received_s``: when the mocap process got it [s, CLOCK_MONOTONIC]
24       float64    ``source_latency_s``: frame time -> received [s] when the system's
                    clock is this host's CLOCK_MONOTONIC (the simulator), else 0
32       uint32     ``occluded``: consecutive frames the body was not seen (0: seen)
36       uint32     ``flags``: reserved (0)
40       6 x f64    ``raw``: the measured pose (world frame; NaN when occluded)
88       6 x f64    ``pose``: the filtered pose (world frame; the held one when occluded)
136      4 x f64    ``velocity``: backward difference of the raw pose [m/s, rad/s]
168      4 x f64    ``innovation``: the Kalman filter's innovation [m, m, m, rad]
=======  =========  ============================================================

Poses are ``[x, y, z (m), roll, pitch, yaw (rad)]`` in the world frame
(:mod:`hilswarm.agents.mocap.frames`).
"""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass

import numpy as np
from hilswarm.agents.bus import BusMessageError

_HEAD = struct.Struct("<QdddII")
_VALUES = 20
_LAYOUT = struct.Struct(f"<QdddII{_VALUES}d")
SIZE = _LAYOUT.size


@dataclass(frozen=True)
class BodyPose:
    """One body in one frame (see the module docstring for units and frames)."""

    frame: int
    frame_time_s: float
    received_s: float
    source_latency_s: float
    occluded: int
    raw: np.ndarray
    pose: np.ndarray
    velocity: np.ndarray
    innovation: np.ndarray

    def latency_s(self, now_s: float | None = None) -> float:
        """Frame time -> ``now_s`` [s, CLOCK_MONOTONIC; default now] (same host only)."""
        now = time.monotonic() if now_s is None else now_s
        return now - self.received_s + self.source_latency_s


def encode(body: BodyPose) -> bytes:
    """The message bytes of ``body``."""
    values = np.concatenate([body.raw, body.pose, body.velocity, body.innovation])
    return _LAYOUT.pack(
        int(body.frame),
        float(body.frame_time_s),
        float(body.received_s),
        float(body.source_latency_s),
        int(body.occluded),
        0,
        *values.tolist(),
    )


def encode_row(
    frame: int,
    frame_time_s: float,
    received_s: float,
    source_latency_s: float,
    *,
    occluded: int,
    values: list[float],
) -> bytes:
    """The message bytes from plain numbers: ``values`` = raw (6), pose (6), velocity (4),
    innovation (4) (the mocap process's per-frame path: no arrays per body)."""
    return _LAYOUT.pack(frame, frame_time_s, received_s, source_latency_s, occluded, 0, *values)


def decode(payload: bytes | bytearray | memoryview) -> BodyPose:
    """Inverse of :func:`encode`.

    Raises:
        BusMessageError: the payload is not :data:`SIZE` bytes.
    """
    if len(payload) != SIZE:
        raise BusMessageError(f"mocap pose message must be {SIZE} bytes, got {len(payload)}")
    frame, frame_time, received, latency, occluded, _flags = _HEAD.unpack_from(payload)
    values = np.frombuffer(payload, dtype="<f8", count=_VALUES, offset=_HEAD.size)
    return BodyPose(
        frame=frame,
        frame_time_s=frame_time,
        received_s=received,
        source_latency_s=latency,
        occluded=occluded,
        raw=values[0:6],
        pose=values[6:12],
        velocity=values[12:16],
        innovation=values[16:20],
    )


def encode_truth(pose: np.ndarray, t: float = math.nan) -> bytes:
    """A simulated body's true world pose (6 float64) and the experiment time ``t`` [s] it
    holds for (NaN: before the run), for the simulator; 56 bytes."""
    values = np.asarray(pose, dtype=np.float64).reshape(6).tolist()
    return struct.pack("<7d", *values, float(t))


def decode_truth(payload: bytes | bytearray | memoryview) -> tuple[np.ndarray, float]:
    """Inverse of :func:`encode_truth`: ``(pose, t)`` (raises :class:`BusMessageError`)."""
    if len(payload) != 56:
        raise BusMessageError(f"mocap truth message must be 56 bytes, got {len(payload)}")
    values = np.frombuffer(bytes(payload), dtype="<f8").copy()
    return values[:6], float(values[6])
