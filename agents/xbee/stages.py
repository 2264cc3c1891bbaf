"""The gateway's stage times, sent back with every answer to an agent (the latency ledger).

An ``xbee://`` agent's link round trip (``link_s`` of the tick's ledger) runs agent -> bus ->
gateway -> radio -> robot and back. Only the gateway sees its own share and the radio's, so it
attaches both, measured on its monotonic clock, to each sample it puts on an agent's
``link/rx`` key (a Zenoh *attachment*: the wire-protocol bytes of the sample stay exactly what
the robot sent, and an agent that ignores it reads the same stream):

* ``gateway_s`` — the gateway's own time for the answer [s]: from the request's arrival on
  ``link/tx`` (bus callback) to its first byte written to the coordinator's UART (queueing
  behind the writer, in broadcast mode the round's gathering and packing), plus, on the way
  back, from the robot's RX frame decoded to its publication. For an answer the gateway gives
  itself (a STALE answer in broadcast mode): from the request's arrival to the answer's
  publication.
* ``radio_s`` — the radio's time [s]: from the request's first byte written to the host UART
  to the robot's answer decoded from it (host UART out, air, the robot's UART and turnaround,
  its answer's air and UART back; in broadcast mode from the BCAST carrying the robot's
  section). 0 for an answer the gateway gives itself.

The gateway keeps one arrival time per robot, the newest: when an agent's next request comes in
before the previous one went to the UART (the gateway is behind), the older answer's
``gateway_s`` counts from the newer request's arrival and is too low by the time between them.

Layout: two little-endian float32, 8 bytes. A sample without an attachment (or with one of
another size) carries no stage times. The agent's side (:class:`~.transport.BusPort`) keeps the
stage times of the last sample received since its last write; the agent puts them in its tick
report, the recorder derives the bus hops (``gateway_bus_s = link_s - gateway_s - radio_s``).
"""

from __future__ import annotations

import struct

_STAGES = struct.Struct("<ff")
#: Size of the attachment [bytes].
STAGES_SIZE = _STAGES.size


def encode_stages(gateway_s: float, radio_s: float) -> bytes:
    """The attachment of an answer: the gateway's and the radio's time [s]."""
    return _STAGES.pack(gateway_s, radio_s)


def decode_stages(attachment: bytes | None) -> tuple[float, float] | None:
    """``(gateway_s, radio_s)`` [s] of an attachment, or ``None`` when it carries none."""
    if attachment is None or len(attachment) != STAGES_SIZE:
        return None
    gateway_s, radio_s = _STAGES.unpack(attachment)
    return gateway_s, radio_s
