"""Domain exceptions of hilswarm.

Every exception subclasses :class:`HilswarmError` *and* the builtin it is closest to, so callers
can catch either ``hilswarm`` errors as a family or the builtin (``ValueError``, ``TypeError``,
``TimeoutError``, ``ConnectionError``) they already handle.
"""

from __future__ import annotations


class HilswarmError(Exception):
    """Base class of every error hilswarm raises on purpose."""


class PinError(HilswarmError, ValueError):
    """A pin request breaks a PinManager rule (unknown pin, conflict, wrong direction, ...)."""


class DeviceError(HilswarmError, ValueError):
    """A device was given a bad pinout, option or command."""


class VehicleDefinitionError(HilswarmError, TypeError):
    """A Vehicle subclass is incomplete or inconsistent (missing devices, sizes, methods)."""


class CalibrationError(HilswarmError, ValueError):
    """A calibration table or file is malformed or a value falls outside it."""


class ControllerError(HilswarmError, ValueError):
    """A controller returned something of the wrong shape or was configured badly."""


class BoardError(HilswarmError):
    """Base class of errors raised by a board link."""


class BoardRequestError(BoardError, ValueError):
    """The board refused a request (an ERROR frame, or the same check done by a simulated board).

    Attributes:
        code: the protocol error code (:class:`hilswarm.agents.link.board.ErrorCode`).
        pin: the offending pin number, or ``None`` when the error is not about a pin.
    """

    def __init__(self, message: str, *, code: int, pin: int | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.pin = pin


class BoardTimeoutError(BoardError, TimeoutError):
    """The board did not answer within the allowed time (after the allowed retries)."""


class BoardConnectionError(BoardError, ConnectionError):
    """The link to the board could not be opened, or was lost and not re-established."""


class ProtocolError(BoardError, ValueError):
    """A frame was well formed but its content breaks the protocol (version mismatch, wrong id)."""


class LinkUrlError(HilswarmError, ValueError):
    """A link URL is malformed or names an unknown scheme."""


class TelemetryError(HilswarmError, ValueError):
    """A telemetry channel was defined badly or given a sample of the wrong size."""


class RecordingError(HilswarmError, ValueError):
    """An MCAP recording was used wrongly (unknown topic, bad message, closed writer)."""


class PlantError(HilswarmError, ValueError):
    """A plant model was configured badly or given a state/input of the wrong shape."""


class CobsDecodeError(BoardError, ValueError):
    """Bytes between two 0x00 delimiters are not a valid COBS encoding (a damaged frame)."""


class WireFormatError(ProtocolError):
    """A frame's body does not follow the wire protocol (bad length, unknown type, bad pin...).

    Attributes:
        code: the protocol error code a board answers with (``ErrorCode``).
        detail: the offending pin for pin errors, else the offending message type.
    """

    def __init__(self, message: str, *, code: int, detail: int) -> None:
        super().__init__(message)
        self.code = code
        self.detail = detail


class SimulatorError(BoardConnectionError):
    """The AVR simulator harness or the firmware it runs is missing or failed to start."""


class VehicleError(HilswarmError, ValueError):
    """A vehicle was configured or driven with bad values (pinout override, limits, u/y shape)."""
