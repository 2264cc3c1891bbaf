"""The 802.15.4 air and the UARTs around it: packet times, CSMA-CA, ACKs, retries, loss. Pure.

Figures (IEEE Std 802.15.4-2006, 2.4 GHz O-QPSK PHY, §6.5 and the MAC constants of §7.4; the
XBee figures from Digi's *XBee/XBee-PRO 802.15.4 RF Modules* product manual, "Networking" and
the ``RR``/``NP``/``RO`` command tables):

* bit rate 250 kbit/s: 32 µs per byte (62.5 ksymbol/s, 2 symbols per byte);
* PHY overhead 6 B: preamble 4, start-of-frame delimiter 1, PHY header (length) 1;
* MAC overhead with 64-bit source and destination addresses and PAN id compression 23 B: frame
  control 2, sequence number 1, PAN id 2, destination 8, source 8, FCS 2 (11 B with 16-bit
  addresses);
* unslotted CSMA-CA: a random backoff of 0..2^BE-1 unit periods (20 symbols = 320 µs) with
  macMinBE = 3 (mean 3.5 periods = 1.12 ms at the first try), a clear channel assessment of
  8 symbols (128 µs) and the RX-to-TX turnaround (aTurnaroundTime, 12 symbols = 192 µs);
* the acknowledgement: 5 B of MAC frame + 6 B PHY = 352 µs, sent a turnaround after the frame;
  a sender that hears none waits macAckWaitDuration (54 symbols = 864 µs) and retries, up to
  macMaxFrameRetries = 3 times; the XBee adds ``RR`` (default 0) retries of that whole
  sequence on top (802.15.4 manual, ``RR``);
* the largest RF payload of the XBee 802.15.4 firmware is 100 B (``NP``);
* a transparent-mode XBee sends what its UART received when the line stays quiet for ``RO``
  character times (default 3) or when a full payload is buffered.

So an acknowledged unicast with a 20 B payload takes 1.12 + 0.128 + 0.192 + (6 + 23 + 20) ×
0.032 + 0.192 + 0.352 ≈ 3.55 ms: about 280 packets/s per channel at best, ~250/s with longer
payloads — the figures ``tests/xbee/test_xbee_air.py`` checks.

:class:`Air` is the seeded model the simulated coordinator runs: one shared channel, each
transmission drawn its backoff and its fate (per-link loss probability, for the frame and for
its ACK), and returned as a :class:`Transmission` with its times [s, the caller's clock].
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

from hilswarm.agents.errors import HilswarmError


class AirModelError(HilswarmError, ValueError):
    """An air model parameter or a transmission request is invalid (payload too long, ...)."""


@dataclass(frozen=True, slots=True)
class AirParams:
    """802.15.4 PHY/MAC constants and the XBee settings that shape air time.

    Attributes:
        bit_rate: air bit rate [bit/s].
        phy_overhead_bytes: preamble + SFD + PHY header [B].
        mac_overhead_bytes: MAC header + FCS with 64-bit addresses [B].
        ack_bytes: acknowledgement frame including its PHY overhead [B].
        backoff_period_s: CSMA-CA unit backoff period [s].
        cca_s: clear channel assessment [s].
        turnaround_s: RX-to-TX turnaround [s].
        ack_wait_s: how long a sender waits for an ACK before retrying [s].
        min_be: macMinBE, the first backoff exponent.
        max_be: macMaxBE.
        mac_retries: macMaxFrameRetries (802.15.4: 3).
        xbee_retries: the XBee's ``RR`` retries of the whole MAC sequence (default 0).
        max_payload: largest RF payload [B] (XBee 802.15.4 ``NP``: 100).
        packetization_chars: transparent-mode ``RO``: quiet characters that end a packet.
    """

    bit_rate: float = 250_000.0
    phy_overhead_bytes: int = 6
    mac_overhead_bytes: int = 23
    ack_bytes: int = 11
    backoff_period_s: float = 320e-6
    cca_s: float = 128e-6
    turnaround_s: float = 192e-6
    ack_wait_s: float = 864e-6
    min_be: int = 3
    max_be: int = 5
    mac_retries: int = 3
    xbee_retries: int = 0
    max_payload: int = 100
    packetization_chars: int = 3

    @property
    def byte_s(self) -> float:
        """Air time of one byte [s] (32 µs at 250 kbit/s)."""
        return 8.0 / self.bit_rate

    def frame_s(self, payload: int) -> float:
        """Air time of one data frame carrying ``payload`` bytes [s], PHY and MAC included."""
        return (self.phy_overhead_bytes + self.mac_overhead_bytes + payload) * self.byte_s

    @property
    def ack_s(self) -> float:
        """Turnaround plus the ACK frame [s] (~0.54 ms)."""
        return self.turnaround_s + self.ack_bytes * self.byte_s

    def mean_backoff_s(self, attempt: int = 0) -> float:
        """Mean CSMA-CA random backoff before the ``attempt``-th try (0 = first) [s]."""
        be = min(self.min_be + attempt, self.max_be)
        return (2**be - 1) / 2 * self.backoff_period_s

    def mean_unicast_s(self, payload: int) -> float:
        """Mean channel time of one acknowledged unicast at its first try [s] (~3.5-4 ms)."""
        return (
            self.mean_backoff_s()
            + self.cca_s
            + self.turnaround_s
            + self.frame_s(payload)
            + self.ack_s
        )

    def mean_broadcast_s(self, payload: int) -> float:
        """Mean channel time of one broadcast (no ACK, no retries) [s]."""
        return self.mean_backoff_s() + self.cca_s + self.turnaround_s + self.frame_s(payload)

    @property
    def attempts(self) -> int:
        """Most transmissions of one unicast: (1 + MAC retries) × (1 + ``RR``)."""
        return (1 + self.mac_retries) * (1 + self.xbee_retries)


def uart_s(nbytes: int, baud: int) -> float:
    """Time ``nbytes`` take on an 8N1 UART at ``baud`` [s] (10 bits per byte)."""
    return nbytes * 10.0 / baud


@dataclass(frozen=True, slots=True)
class Transmission:
    """The fate of one packet on the air.

    Attributes:
        start_s: when the sender started (backoff included) [s].
        end_s: when the channel was released (last ACK or ACK wait) [s].
        delivered_s: when the receiver had the payload [s] (``None``: never delivered).
        attempts: transmissions made (1 = first try).
        acked: True when the sender saw an ACK (always False for a broadcast).
    """

    start_s: float
    end_s: float
    delivered_s: float | None
    attempts: int
    acked: bool

    @property
    def retries(self) -> int:
        """Retransmissions made."""
        return self.attempts - 1

    @property
    def air_s(self) -> float:
        """Channel time used [s]."""
        return self.end_s - self.start_s


@dataclass
class AirStats:
    """Totals of an :class:`Air` since it was made."""

    packets: int = 0
    attempts: int = 0
    failures: int = 0
    busy_s: float = 0.0


@dataclass
class Air:
    """One 802.15.4 channel shared by every radio (seeded, see the module docstring).

    Args:
        params: PHY/MAC constants.
        seed: random seed of backoffs and losses.
        loss: per-link loss probability of one frame (and, separately, of its ACK), by
            unordered pair of 64-bit addresses; absent pairs use ``default_loss``.
        default_loss: loss probability of links not in ``loss``.
    """

    params: AirParams = field(default_factory=AirParams)
    seed: int = 0
    loss: dict[frozenset[int], float] = field(default_factory=dict)
    default_loss: float = 0.0
    stats: AirStats = field(default_factory=AirStats)

    def __post_init__(self) -> None:
        self._rng = random.Random(self.seed)
        self._free_at = 0.0  # when the channel is next clear [s]

    def set_loss(self, a: int, b: int, probability: float) -> None:
        """Loss probability of the link between ``a`` and ``b`` (1.0: out of range)."""
        if not 0.0 <= probability <= 1.0:
            raise AirModelError(f"loss probability must be in [0, 1], got {probability}")
        self.loss[frozenset((a, b))] = probability

    def lost(self, a: int, b: int) -> bool:
        """Draw whether one frame between ``a`` and ``b`` is lost (per-link probability)."""
        p = self.loss.get(frozenset((a, b)), self.default_loss)
        return p > 0.0 and self._rng.random() < p

    def _backoff(self, attempt: int) -> float:
        be = min(self.params.min_be + attempt, self.params.max_be)
        return self._rng.randrange(2**be) * self.params.backoff_period_s

    def transmit(self, now_s: float, src: int, dst: int | None, payload: int) -> Transmission:
        """Send ``payload`` bytes from ``src`` to ``dst`` (``None``: broadcast) at ``now_s`` [s].

        The channel is one queue: a packet starts when it is clear, after its backoff.

        Raises:
            AirModelError: ``payload`` exceeds :attr:`AirParams.max_payload`.
        """
        p = self.params
        if not 0 <= payload <= p.max_payload:
            raise AirModelError(f"RF payload of {payload} B; the radio takes 0..{p.max_payload}")
        start = max(now_s, self._free_at)
        t = start
        attempts = 0
        delivered: float | None = None
        acked = False
        limit = 1 if dst is None else p.attempts
        while attempts < limit:
            t += self._backoff(attempts % (1 + p.mac_retries)) + p.cca_s + p.turnaround_s
            t += p.frame_s(payload)
            attempts += 1
            if dst is None:
                delivered = t
                break
            if self.lost(src, dst):
                t += p.ack_wait_s
                continue
            if delivered is None:
                delivered = t  # a lost ACK makes the sender retry: the receiver gets a copy
            if self.lost(src, dst):
                t += p.ack_wait_s
                continue
            t += p.ack_s
            acked = True
            break
        self._free_at = t
        self.stats.packets += 1
        self.stats.attempts += attempts
        self.stats.busy_s += t - start
        if dst is not None and not acked:
            self.stats.failures += 1
        return Transmission(start, t, delivered, attempts, acked)
