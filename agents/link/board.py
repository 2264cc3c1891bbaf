"""The board interface: the one way devices and the PinManager talk to an Arduino-class board.

Every transport (``sim://`` in-process board, a pyserial URL with the hilswarm firmware,
``simavr://`` real firmware in the AVR simulator, ``xbee://`` through the gateway) implements
:class:`Board`. The contract mirrors the wire protocol (``docs/protocol.md``):

1. :meth:`Board.open` performs the HELLO handshake and returns :class:`BoardInfo`.
2. :meth:`Board.configure` sets every pin mode once, each with a safe value, plus the watchdog
   timeout. Configuring again replaces the whole configuration and clears an e-stop.
3. :meth:`Board.exchange` is called once per control tick: it carries *all* writes of the tick
   and the pins to sample, and returns one :class:`TickReply`.
4. :meth:`Board.estop` drives every output to its safe value at once and latches until the
   next :meth:`Board.configure`.

Pin numbers follow Arduino numbering on ATmega328P boards: digital 0-13, analog A0-A5 = 14-19.
Values are integers in wire units: digital 0/1, PWM duty 0-255, servo pulse width in
microseconds, analog samples in ADC counts 0-1023 (of the board's reference voltage).
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Self

#: Protocol version spoken by this host code (separate from any firmware version).
PROTOCOL_VERSION = 2

#: Protocol versions this host talks to: version 2 only adds the packed broadcast (BCAST, the
#: CONFIG's broadcast id, the STALE flag), so a version-1 board works for everything else.
SUPPORTED_PROTOCOL_VERSIONS = frozenset({1, 2})

#: Number of pins addressed by the protocol on ATmega328P boards (0-13 digital, 14-19 = A0-A5).
PIN_COUNT = 20

#: First analog pin number (A0).
ANALOG_PIN_BASE = 14


class PinMode(enum.IntEnum):
    """How a pin is configured. The numeric values are the wire encoding."""

    UNUSED = 0
    DIGITAL_IN = 1
    DIGITAL_OUT = 2
    PWM = 3
    SERVO = 4
    ANALOG_IN = 5
    DIGITAL_IN_PULLUP = 6

    @property
    def is_output(self) -> bool:
        """True for modes the host writes (digital out, PWM, servo)."""
        return self in (PinMode.DIGITAL_OUT, PinMode.PWM, PinMode.SERVO)

    @property
    def is_input(self) -> bool:
        """True for modes the host samples (digital in, pull-up in, analog in)."""
        return self in (PinMode.DIGITAL_IN, PinMode.DIGITAL_IN_PULLUP, PinMode.ANALOG_IN)


class Capability(enum.IntFlag):
    """What a pin can do, as reported by HELLO (one byte per pin on the wire)."""

    NONE = 0
    DIGITAL_IN = 0x01
    DIGITAL_OUT = 0x02
    PWM = 0x04
    SERVO = 0x08
    ANALOG_IN = 0x10
    RESERVED = 0x80  # e.g. the serial pins 0/1: present but not usable


#: Which capability a mode needs.
MODE_CAPABILITY: dict[PinMode, Capability] = {
    PinMode.DIGITAL_IN: Capability.DIGITAL_IN,
    PinMode.DIGITAL_IN_PULLUP: Capability.DIGITAL_IN,
    PinMode.DIGITAL_OUT: Capability.DIGITAL_OUT,
    PinMode.PWM: Capability.PWM,
    PinMode.SERVO: Capability.SERVO,
    PinMode.ANALOG_IN: Capability.ANALOG_IN,
}


class BoardStatus(enum.IntFlag):
    """Status flags carried by every reply."""

    OK = 0
    WATCHDOG_TRIPPED = 0x01  # outputs went safe because of link silence since the last reply
    ESTOPPED = 0x02  # e-stop latched: outputs held safe until the next configure
    NOT_CONFIGURED = 0x04  # no configuration since boot/reset
    RX_ERRORS = 0x08  # frames were dropped (CRC/framing) since the last reply
    RESET = 0x10  # the board (re)booted since the last HELLO
    HW_WATCHDOG_RESET = 0x20  # the last reset was caused by the AVR hardware watchdog
    STALE = 0x40  # (protocol 2) never set by a board: a gateway repeated the last samples


class ErrorCode(enum.IntEnum):
    """Error codes of ERROR frames (and of :class:`~hilswarm.agents.errors.BoardRequestError`)."""

    UNKNOWN_TYPE = 1
    BAD_LENGTH = 2
    BAD_PIN = 3
    BAD_MODE = 4
    PIN_CONFLICT = 5
    NOT_CONFIGURED = 6
    BAD_VALUE = 7
    FRAME_TOO_LONG = 8
    BAD_STATE = 9


#: Servo pulse width accepted by the firmware [µs].
SERVO_MIN_US = 500
SERVO_MAX_US = 2500
#: Largest PWM duty value (8-bit timers).
PWM_MAX = 255
#: Largest ADC count (10-bit ADC).
ADC_MAX = 1023


@dataclass(frozen=True, slots=True)
class PinConfig:
    """One pin's configuration.

    Attributes:
        pin: pin number (0-19, A0 = 14).
        mode: the pin mode.
        safe_value: value the firmware drives on watchdog trip / e-stop, in wire units
            (0/1, PWM duty 0-255, servo pulse [µs]); ignored for inputs.
    """

    pin: int
    mode: PinMode
    safe_value: int = 0


@dataclass(frozen=True, slots=True)
class BoardInfo:
    """What the HELLO handshake reports.

    Attributes:
        protocol_version: wire protocol version (one of :data:`SUPPORTED_PROTOCOL_VERSIONS`).
        firmware_version: firmware version as ``(major, minor)``.
        board_id: board identity stored in EEPROM (0-65535).
        capabilities: per-pin capability flags, index = pin number.
    """

    protocol_version: int
    firmware_version: tuple[int, int]
    board_id: int
    capabilities: tuple[Capability, ...]


@dataclass(frozen=True, slots=True)
class TickReply:
    """The board's answer to one tick exchange.

    Attributes:
        seq: sequence number echoed from the request (0-255).
        status: status flags.
        board_time_s: board clock at the moment the reply was built [s, board monotonic clock].
        samples: sampled values by pin, in wire units (digital 0/1, ADC counts 0-1023).
    """

    seq: int
    status: BoardStatus
    board_time_s: float
    samples: Mapping[int, int] = field(default_factory=dict)


class Board(ABC):
    """A connection to one board. Use as a context manager; not thread-safe.

    Implementations raise :class:`~hilswarm.agents.errors.BoardRequestError` for requests the
    board refuses (with the protocol's :class:`ErrorCode`), :class:`BoardTimeoutError` when no
    answer arrives after retries and :class:`BoardConnectionError` when the link is gone.
    """

    #: URL this board was opened from (for messages and recordings).
    url: str

    @abstractmethod
    def open(self) -> BoardInfo:
        """Connect and perform the HELLO handshake; return what the board reported."""

    @property
    @abstractmethod
    def info(self) -> BoardInfo:
        """The last HELLO result (raises ``BoardConnectionError`` before :meth:`open`)."""

    @abstractmethod
    def configure(self, pins: Sequence[PinConfig], *, watchdog_s: float) -> None:
        """Replace the whole pin configuration and set the link watchdog.

        Args:
            pins: every pin to configure; pins not listed become unused.
            watchdog_s: link-silence timeout after which outputs go safe [s]; 0 disables it.
        """

    @abstractmethod
    def exchange(self, writes: Mapping[int, int], reads: Sequence[int]) -> TickReply:
        """One tick: apply ``writes`` (pin -> value) and sample ``reads``, in one round trip."""

    @abstractmethod
    def estop(self) -> TickReply:
        """Drive every output to its safe value now and latch until the next configure."""

    @abstractmethod
    def close(self) -> None:
        """Release the link. Idempotent."""

    # Fault handling. Boards behind a real link override these; in-process boards cannot fail.

    #: How long a faulty link may take to come back before the caller gives up on it [s]
    #: (0: the board has no link that can fail).
    link_timeout_s: float = 0.0

    def request_estop(self) -> bool:
        """Make every output safe now, from any thread, without waiting (the e-stop's own path).

        Returns ``False`` when the board has no such path: then the caller's next
        :meth:`estop`, on the board's own thread, does it.
        """
        return False

    def add_link_listener(self, listener: Callable[[str, str], None]) -> None:
        """Call ``listener(kind, detail)`` on link events (``disconnected``, ``reconnected``...),
        on the thread whose request met them. Default: a link that cannot fail has none."""
        return

    def abort(self) -> None:
        """Make a blocked request give up soon (any thread). Default: nothing can block."""
        return

    def reconnect(self) -> BoardInfo:
        """Re-establish a failed link and re-apply the configuration: one bounded attempt."""
        from hilswarm.agents.errors import BoardConnectionError  # noqa: PLC0415 - no cycle at import

        raise BoardConnectionError(f"{type(self).__name__} cannot reconnect")

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def pin_name(pin: int) -> str:
    """Human name of a pin number: ``13`` -> ``"D13"``, ``14`` -> ``"A0"``."""
    if pin >= ANALOG_PIN_BASE:
        return f"A{pin - ANALOG_PIN_BASE}"
    return f"D{pin}"
