"""``[gateway]`` of an experiment file and ``xbee://`` link URLs: small typed models.

::

    [gateway]
    port = "/dev/ttyUSB0"     # any pyserial URL; "sim" = a simulated coordinator and air
    baud = 115200             # host UART rate of the coordinator [baud]
    api_mode = 1              # 1 = API, 2 = API with escaping
    mode = "unicast"          # or "broadcast": one packed BCAST per tick (protocol 2 robots)
    answer = "wait"           # "wait" for a robot's own reply (broadcast: on its reply
                              # ticks), or "at_once" (samples one tick old or more, STALE)
    # only for port = "sim":
    family = "802.15.4"       # or "zigbee": the frame family the simulated radios speak
    seed = 0                  # seed of the simulated air (backoffs, losses)
    loss = 0.0                # loss probability of each frame on every link

A robot's link is ``xbee://<64-bit address>`` (16 hex digits, e.g. ``xbee://0013A20040A1B2C3``).
``?sim=sim://duemilanove`` or ``?sim=simavr://duemilanove`` adds, for ``port = "sim"``, the
simulated robot behind that address: the agent's process runs it (with the vehicle's simulated
hardware, as for ``sim://``) and the simulated air reaches its UART.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from hilswarm.agents.errors import HilswarmError, LinkUrlError
from hilswarm.agents.xbee.api_frames import FrameFamily
from hilswarm.agents.xbee.sim_coordinator import BAUD_CODES

#: ``port`` value that asks for the simulated coordinator.
SIM_PORT = "sim"
#: ``mode`` values: one request and one reply per robot and tick, or the packed broadcast.
MODES = ("unicast", "broadcast")
_ADDRESS_RE = re.compile(r"^(0x)?[0-9A-Fa-f]{1,16}$")


class GatewayConfigError(HilswarmError, ValueError):
    """A ``[gateway]`` table or an ``xbee://`` URL is malformed."""


@dataclass(frozen=True)
class GatewayConfig:
    """The gateway's settings (see the module docstring).

    Attributes:
        port: pyserial URL or device of the coordinator; ``"sim"`` for the simulated one.
        baud: host UART rate [baud].
        api_mode: 1 (API) or 2 (API with escaping).
        mode: ``"unicast"`` (a TICK and its reply per robot and tick) or ``"broadcast"`` (the
            agents' TICKs of a tick packed into one BCAST, replies decimated; docs/xbee.md).
        answer: ``"wait"`` (an agent gets its robot's own reply: every tick by unicast, on
            its reply ticks by broadcast) or ``"at_once"`` (every TICK answered at once from
            the robot's newest samples, marked STALE; the TICKs still go to the robots).
        family: frame family of the simulated radios (``port = "sim"`` only).
        seed: seed of the simulated air.
        loss: loss probability of each frame on every simulated link.
    """

    port: str = SIM_PORT
    baud: int = 115200
    api_mode: int = 1
    mode: str = "unicast"
    answer: str = "wait"
    family: str = FrameFamily.IEEE_802_15_4.value
    seed: int = 0
    loss: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.port, str) or not self.port.strip():
            raise GatewayConfigError(f"[gateway] port must be a serial port URL, got {self.port!r}")
        if self.baud not in BAUD_CODES.values():
            raise GatewayConfigError(
                f"[gateway] baud = {self.baud!r} is not an XBee rate; use one of "
                f"{sorted(BAUD_CODES.values())}"
            )
        if self.api_mode not in (1, 2):
            raise GatewayConfigError(
                f"[gateway] api_mode = {self.api_mode!r}: use 1 (API) or 2 (API, escaped)"
            )
        if self.mode not in MODES:
            raise GatewayConfigError(
                f"[gateway] mode = {self.mode!r}: use {' or '.join(repr(m) for m in MODES)}"
            )
        if self.answer not in ("wait", "at_once"):
            raise GatewayConfigError(f"[gateway] answer = {self.answer!r}: use 'wait' or 'at_once'")
        if self.family not in {f.value for f in FrameFamily}:
            raise GatewayConfigError(
                f"[gateway] family = {self.family!r}: use "
                f"{' or '.join(repr(f.value) for f in FrameFamily)}"
            )
        if not 0.0 <= self.loss <= 1.0:
            raise GatewayConfigError(f"[gateway] loss = {self.loss!r} is not a probability")

    @property
    def simulated(self) -> bool:
        """True for the simulated coordinator."""
        return self.port == SIM_PORT

    @classmethod
    def from_table(cls, table: Mapping[str, Any] | None) -> GatewayConfig:
        """Build from an experiment file's ``[gateway]`` table (``None``: the defaults)."""
        table = dict(table or {})
        known = {"port", "baud", "api_mode", "mode", "answer", "family", "seed", "loss"}
        unknown = sorted(set(table) - known)
        if unknown:
            raise GatewayConfigError(
                f"[gateway]: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
            )
        for key in ("baud", "api_mode", "seed"):
            if key in table and (not isinstance(table[key], int) or isinstance(table[key], bool)):
                raise GatewayConfigError(f"[gateway] {key} must be an integer, got {table[key]!r}")
        if "loss" in table and not isinstance(table["loss"], int | float):
            raise GatewayConfigError(f"[gateway] loss must be a number, got {table['loss']!r}")
        return cls(**table)


@dataclass(frozen=True)
class XBeeLink:
    """A parsed ``xbee://`` link URL.

    Attributes:
        address: the robot radio's 64-bit address.
        sim: the simulated robot's board URL (``sim://...`` or ``simavr://...``), or ``None``.
        options: SerialBoard options (``timeout_s``, ``retries``, ``open_timeout_s``,
            ``board_id``).
    """

    address: int
    sim: str | None = None
    options: tuple[tuple[str, Any], ...] = ()


_OPTIONS = {"timeout_s": float, "retries": int, "open_timeout_s": float, "board_id": int}


def parse_xbee_url(url: str) -> XBeeLink:
    """Parse ``xbee://<address>[?sim=...&timeout_s=...]``.

    Raises:
        LinkUrlError: not an xbee URL, a bad address or option.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "xbee":
        raise LinkUrlError(f"{url!r} is not an xbee:// URL")
    text = parts.netloc or parts.path.strip("/")
    if not _ADDRESS_RE.match(text):
        raise LinkUrlError(
            f"link URL {url!r}: expected xbee://<64-bit address> in hex, e.g. "
            "xbee://0013A20040A1B2C3"
        )
    address = int(text, 16)
    if address in (0, 0xFFFF):
        raise LinkUrlError(f"link URL {url!r}: {text} is a broadcast/coordinator address")
    sim: str | None = None
    options: list[tuple[str, Any]] = []
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key == "sim":
            if not value.startswith(("sim://", "simavr://")):
                raise LinkUrlError(
                    f"link URL {url!r}: sim= takes a sim:// or simavr:// board URL, got {value!r}"
                )
            sim = value
        elif key in _OPTIONS:
            try:
                options.append((key, _OPTIONS[key](value)))
            except ValueError:
                raise LinkUrlError(
                    f"link URL {url!r}: {key}={value!r} is not a {_OPTIONS[key].__name__}"
                ) from None
        else:
            raise LinkUrlError(
                f"link URL {url!r}: unknown option {key!r} (known: sim, {', '.join(_OPTIONS)})"
            )
    return XBeeLink(address, sim, tuple(options))


def validate_url(url: str, *, local: bool = True) -> None:
    """Check an ``xbee://`` URL as the transport would, and its ``sim=`` board URL.

    Raises:
        LinkUrlError: a bad address, option or simulated board URL.
    """
    from hilswarm.agents.link.url import validate_link_url  # noqa: PLC0415 - url imports us

    link = parse_xbee_url(url)
    if link.sim is not None:
        validate_link_url(link.sim, local=local)


def format_address(address: int) -> str:
    """``0x0013A20040A1B2C3`` -> ``"0013A20040A1B2C3"``."""
    return f"{address:016X}"
