"""The frame-clock message on ``hilswarm/<exp>/<run_id>/mocap_clock``.

The mocap process puts one per frame it handles, after the frame's poses, so the instance
manager can release realtime ticks in step with the camera frames
(:mod:`hilswarm.orchestrator.frame_lock`). Only the mocap principal may put it; the manager and
viewers read it.

Fixed little-endian layout, 16 bytes:

=======  =========  ===============================================================
offset   type       field
=======  =========  ===============================================================
0        int64      ``frame``: the system's frame number
8        float64    ``frame_time_s``: the frame's time on this host's CLOCK_MONOTONIC [s]:
                    the camera time stamp with the simulator (its clock is this host's),
                    the frame's arrival at the mocap process with a real system
=======  =========  ===============================================================
"""

from __future__ import annotations

import math
import struct

from hilswarm.agents.bus import BusMessageError

_LAYOUT = struct.Struct("<qd")
#: Size of a frame-clock message [bytes].
SIZE = _LAYOUT.size


def encode(frame: int, frame_time_s: float) -> bytes:
    """The message of frame number ``frame`` at ``frame_time_s`` [s, CLOCK_MONOTONIC]."""
    return _LAYOUT.pack(frame, frame_time_s)


def decode(payload: bytes | bytearray | memoryview) -> tuple[int, float]:
    """``(frame, frame_time_s)`` of a message.

    Raises:
        BusMessageError: wrong size, or a frame time that is not finite.
    """
    if len(payload) != SIZE:
        raise BusMessageError(f"frame clock of {len(payload)} bytes, expected {SIZE}")
    frame, frame_time_s = _LAYOUT.unpack(payload)
    if not math.isfinite(frame_time_s):
        raise BusMessageError("frame clock with a frame time that is not finite")
    return frame, frame_time_s
