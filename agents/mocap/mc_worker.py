"""The ``motioncapture`` library (Vicon, OptiTrack, VRPN) in a process of its own.

libmotioncapture's Python bindings hold the GIL inside ``connect`` and ``waitForNextFrame``.
Measured: ``motioncapture.connect("optitrack", ...)`` with no NatNet server on the host blocks
for good, and no other thread of the calling process runs meanwhile (a timeout thread never
wakes). In the mocap process that would freeze its bus callbacks and its status messages, and
``hilswarm mocap`` would hang. So the library runs here, in a child process, and
:class:`~hilswarm.agents.mocap.clients.MotionCaptureClient` reads what it writes with deadlines
and kills it when it stops or gives up.

``python -m hilswarm.agents.mocap.mc_worker SYSTEM HOSTNAME`` writes records on its standard
output (the library's own prints go to its standard error instead), each a 4-byte
little-endian length and then a pickled tuple (:func:`encode`; only the process that started
this one reads them):

* ``("ready",)`` once connected;
* ``("frame", received_s, bodies)`` per frame: the arrival time [s, CLOCK_MONOTONIC, the
  machine's clock that the parent shares] and ``[(name, (x, y, z) [m], (w, x, y, z)), ...]``
  in the system's own convention;
* ``("error", message)`` when the library refuses (then the process exits with status 1).
"""

from __future__ import annotations

import os
import pickle
import select
import struct
import sys
import time
from typing import Any

_LENGTH = struct.Struct("<I")
#: Largest record accepted [bytes] (a frame of a few hundred bodies is ~50 kB).
MAX_RECORD_BYTES = 1 << 22


class RecordError(ValueError):
    """A record from the worker is malformed (too long, or not a tuple)."""


def encode(record: tuple[Any, ...]) -> bytes:
    """One record as written on the pipe."""
    payload = pickle.dumps(record, protocol=pickle.HIGHEST_PROTOCOL)
    return _LENGTH.pack(len(payload)) + payload


class RecordReader:
    """Reads the worker's records from file descriptor ``fd``, never blocking past a deadline.

    Args:
        fd: the read end of the worker's standard output.
        clock: monotonic clock [s] for the deadlines.
    """

    def __init__(self, fd: int, *, clock: Any = time.monotonic) -> None:
        self._fd = fd
        self._buffer = bytearray()
        self._clock = clock

    def _take(self) -> tuple[Any, ...] | None:
        if len(self._buffer) < _LENGTH.size:
            return None
        (length,) = _LENGTH.unpack_from(self._buffer)
        if length > MAX_RECORD_BYTES:
            raise RecordError(f"record of {length} bytes from the mocap worker (bound)")
        end = _LENGTH.size + length
        if len(self._buffer) < end:
            return None
        payload = bytes(self._buffer[_LENGTH.size : end])
        del self._buffer[:end]
        try:
            record = pickle.loads(payload)
        except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError) as exc:
            # (a truncated pickle raises EOFError: not to be read as the worker's end)
            raise RecordError(f"malformed record from the mocap worker: {exc}") from exc
        if not isinstance(record, tuple) or not record:
            raise RecordError(f"malformed record from the mocap worker: {record!r}")
        return record

    def read(self, timeout_s: float) -> tuple[Any, ...] | None:
        """The next record, or ``None`` when none is complete within ``timeout_s`` [s].

        Raises:
            EOFError: the worker closed its output (it exited).
            RecordError: a malformed record.
        """
        deadline = self._clock() + max(0.0, timeout_s)
        for _ in range(100_000):  # bounded: each pass reads or waits
            record = self._take()
            if record is not None:
                return record
            remaining = deadline - self._clock()
            if remaining <= 0.0:
                return None
            ready, _, _ = select.select([self._fd], [], [], remaining)
            if not ready:
                return None
            chunk = os.read(self._fd, 65536)
            if not chunk:
                raise EOFError("the mocap worker closed its output")
            self._buffer += chunk
        return None


def library_config(system: str, hostname: str) -> dict[str, str]:
    """``motioncapture.connect``'s configuration for ``hostname`` (``host`` or ``host:port``).

    OptiTrack's backend takes the NatNet command port apart (``port_command``; Motive's
    default 1510 otherwise) and an address alone as ``hostname``; Vicon's and VRPN's take
    ``host:port`` as it is.
    """
    if system == "optitrack":
        host, colon, port = hostname.rpartition(":")
        if colon and port.isdigit():
            return {"hostname": host, "port_command": port}
    return {"hostname": hostname}


def _write(out: Any, record: tuple[Any, ...]) -> None:
    out.write(encode(record))
    out.flush()


def main(argv: list[str] | None = None) -> int:
    """Connect ``SYSTEM`` at ``HOSTNAME`` and stream records until killed (module docstring)."""
    args = sys.argv[1:] if argv is None else argv
    # The records get the standard output to themselves: the library prints on it too (VRPN's
    # "tracker: cf1" and warnings, measured in the middle of a stream), so its file descriptor
    # 1 becomes a copy of the standard error (which the parent logs).
    sys.stdout.flush()
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    if len(args) != 2:
        _write(out, ("error", "usage: mc_worker SYSTEM HOSTNAME"))
        return 2
    system, hostname = args
    try:
        import motioncapture  # noqa: PLC0415 - only this process loads the library
    except ImportError as exc:
        _write(out, ("error", f"the motioncapture package is missing: {exc}"))
        return 1
    try:
        mc = motioncapture.connect(system, library_config(system, hostname))
    except RuntimeError as exc:
        _write(out, ("error", f"cannot connect to {system} at {hostname}: {exc}"))
        return 1
    _write(out, ("ready",))
    try:
        while True:  # until the parent kills this process (or the library fails)
            mc.waitForNextFrame()
            received = time.monotonic()
            bodies = []
            for name, body in mc.rigidBodies.items():
                p, q = body.position, body.rotation
                bodies.append((name, (float(p[0]), float(p[1]), float(p[2])), (q.w, q.x, q.y, q.z)))
            _write(out, ("frame", received, bodies))
    except RuntimeError as exc:
        _write(out, ("error", f"{system} at {hostname}: {exc}"))
        return 1
    except BrokenPipeError:
        return 0  # the parent is gone


if __name__ == "__main__":
    sys.exit(main())
