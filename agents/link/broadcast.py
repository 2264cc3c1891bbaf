"""The packed broadcast of protocol 2 (``docs/protocol.md``, BCAST): one robot's section. Pure.

A BCAST frame carries every robot's outputs of one tick; each board takes the section with its
broadcast id (set by CONFIG). A section's data is compact, because the board knows its
configuration:

* ``levels``: ceil(n / 8) bytes for the n DIGITAL_OUT pins, bit j = the j-th DIGITAL_OUT pin in
  ascending pin order;
* then one value per PWM (u8 duty) and SERVO (u16 pulse width [µs]) pin, ascending.

A Frisbee (4 DIGITAL_OUT, 2 PWM) has 3 B of data: 5 B with its id and header, against 16 B for
its TICK frame. Replies (BCAST_REPLY) carry a sample of every input pin, ascending.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from hilswarm.agents.errors import WireFormatError
from hilswarm.agents.link.board import SERVO_MAX_US, SERVO_MIN_US, ErrorCode, PinMode
from hilswarm.agents.link.codec import MsgType


@dataclass(frozen=True, slots=True)
class SectionLayout:
    """What a section holds for one configuration (pin -> mode).

    Attributes:
        dout_pins: DIGITAL_OUT pins, ascending (bit j of the levels = ``dout_pins[j]``).
        wide_pins: PWM and SERVO pins, ascending (the order of the values).
        servo_pins: the SERVO pins among them (u16 values).
        input_pins: DIGITAL_IN, DIGITAL_IN_PULLUP and ANALOG_IN pins, ascending (the samples
            of a BCAST_REPLY).
    """

    dout_pins: tuple[int, ...]
    wide_pins: tuple[int, ...]
    servo_pins: frozenset[int]
    input_pins: tuple[int, ...]

    @classmethod
    def of(cls, modes: Mapping[int, int]) -> SectionLayout:
        """The layout of the configuration ``modes`` (pin -> PinMode)."""
        pins = sorted(modes)
        return cls(
            tuple(p for p in pins if modes[p] == PinMode.DIGITAL_OUT),
            tuple(p for p in pins if modes[p] in (PinMode.PWM, PinMode.SERVO)),
            frozenset(p for p in pins if modes[p] == PinMode.SERVO),
            tuple(p for p in pins if PinMode(modes[p]).is_input),
        )

    @property
    def length(self) -> int:
        """Section data length [B]."""
        return (len(self.dout_pins) + 7) // 8 + sum(
            2 if p in self.servo_pins else 1 for p in self.wide_pins
        )

    def encode(self, dout: int, values: Mapping[int, int]) -> bytes:
        """Section data: levels from ``dout`` (bit i = pin i, as a TICK's), then every PWM and
        servo pin's value from ``values``.

        Raises:
            WireFormatError: a PWM or servo pin has no value or one out of range.
        """
        levels = bytearray((len(self.dout_pins) + 7) // 8)
        for j, pin in enumerate(self.dout_pins):
            if dout >> pin & 1:
                levels[j // 8] |= 1 << (j % 8)
        out = bytearray(levels)
        for pin in self.wide_pins:
            value = values.get(pin)
            servo = pin in self.servo_pins
            ok = value is not None and (
                SERVO_MIN_US <= value <= SERVO_MAX_US if servo else 0 <= value <= 0xFF
            )
            if not ok:
                raise WireFormatError(
                    f"BCAST section: pin {pin} needs a {'servo' if servo else 'PWM'} value in "
                    f"range, got {value!r}",
                    code=ErrorCode.BAD_VALUE,
                    detail=pin,
                )
            out += value.to_bytes(2 if servo else 1, "little")  # type: ignore[union-attr]
        return bytes(out)

    def decode(self, data: bytes) -> dict[int, int]:
        """Writes (pin -> value) of every output from section ``data``.

        Raises:
            WireFormatError: BAD_LENGTH (not :attr:`length` bytes), BAD_VALUE (servo range).
        """
        if len(data) != self.length:
            raise WireFormatError(
                f"BCAST section of {len(data)} B; this configuration needs {self.length}",
                code=ErrorCode.BAD_LENGTH,
                detail=MsgType.BCAST,
            )
        writes = {pin: data[j // 8] >> (j % 8) & 1 for j, pin in enumerate(self.dout_pins)}
        index = (len(self.dout_pins) + 7) // 8
        for pin in self.wide_pins:
            if pin in self.servo_pins:
                value = int.from_bytes(data[index : index + 2], "little")
                if not SERVO_MIN_US <= value <= SERVO_MAX_US:
                    raise WireFormatError(
                        f"BCAST section: servo pin {pin} at {value} µs",
                        code=ErrorCode.BAD_VALUE,
                        detail=pin,
                    )
                index += 2
            else:
                value = data[index]
                index += 1
            writes[pin] = value
        return writes
