"""Node discovery and radio configuration with Digi's own library (``digi-xbee``).

Why digi-xbee here: device and remote configuration is where the library's knowledge of the
radios (operating-mode detection, protocol from ``HV``/``VR``, remote AT commands, node
discovery across the families) is worth more than a few microseconds per frame; the per-tick
hot path uses the small codec of :mod:`.api_frames` (``benchmarks/xbee_gateway.py`` measures
both).

* :func:`scan` — node discovery (``ND``) through the coordinator: each robot radio's 64-bit
  address, node id and RSSI [dBm] (its ``DB``: the strength of the last packet it heard).
* :func:`setup` — the robots' radios first (over the air, remote AT commands: PAN id, channel,
  destination = the coordinator, transparent mode, their UART rate; written and applied), then
  the coordinator (API mode, PAN id, channel, host UART rate). The thesis used Digi's X-CTU for
  this; no extra tool is needed here.

The coordinator must already answer in API mode 1 or 2 (a radio fresh from the factory is in
transparent mode: put it in API mode once with X-CTU or any terminal ``+++``, ``ATAP1``,
``ATWR``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.xbee.config import format_address
from hilswarm.agents.xbee.sim_coordinator import baud_code


class RadioSetupError(HilswarmError, ConnectionError):
    """The coordinator or a remote radio could not be reached or configured."""


class RadioSettingError(HilswarmError, ValueError):
    """A radio setting (channel, PAN id, baud rate, API mode) outside what the radios take."""


#: 802.15.4 channels of the XBee radios (``CH``), first and last.
CHANNELS = (0x0B, 0x1A)
#: PAN ids (``ID``), first and last.
PAN_IDS = (0x0000, 0xFFFF)
#: API modes of the coordinator (``AP``).
API_MODES = (1, 2)


def check_channel(channel: int) -> int:
    """``channel`` if the radios have it, else :class:`RadioSettingError` with the range."""
    low, high = CHANNELS
    if not low <= channel <= high:
        raise RadioSettingError(
            f"channel {channel:#x} is out of range; expected 0x{low:02X}-0x{high:02X} "
            f"(802.15.4 channels {low}-{high})"
        )
    return channel


def check_pan_id(pan_id: int) -> int:
    """``pan_id`` if it is a PAN id, else :class:`RadioSettingError` with the range."""
    low, high = PAN_IDS
    if not low <= pan_id <= high:
        raise RadioSettingError(
            f"PAN id {pan_id:#x} is out of range; expected 0x{low:04X}-0x{high:04X}"
        )
    return pan_id


def check_baud(baud: int) -> int:
    """``baud`` if it is a standard XBee UART rate, else :class:`RadioSettingError`."""
    try:
        baud_code(baud)
    except ValueError as exc:
        raise RadioSettingError(str(exc)) from None
    return baud


def check_api_mode(api_mode: int) -> int:
    """``api_mode`` if it is 1 or 2, else :class:`RadioSettingError`."""
    if api_mode not in API_MODES:
        raise RadioSettingError(f"API mode must be 1 or 2, got {api_mode}")
    return api_mode


@dataclass(frozen=True)
class Node:
    """One radio found by node discovery.

    Attributes:
        address: 64-bit address.
        node_id: its ``NI`` string.
        rssi_dbm: strength of the last packet it received [dBm], or ``None`` if unknown.
    """

    address: int
    node_id: str
    rssi_dbm: int | None


#: Bound on each local AT command while the coordinator is opened [s].
OPEN_TIMEOUT_S = 1.5
#: digi-xbee's default bound on a synchronous operation (remote AT commands) [s].
SYNC_OPS_TIMEOUT_S = 4


def _open(port: str, baud: int):
    from digi.xbee.devices import XBeeDevice  # noqa: PLC0415 - heavy import, CLI only
    from digi.xbee.exception import XBeeException  # noqa: PLC0415

    device = XBeeDevice(port, baud)
    try:
        # A local radio answers its AT commands within milliseconds: 1.5 s instead of
        # digi-xbee's 4 s for the AP query. A silent port then fails after ~6 s instead of
        # ~8 s: the rest is digi-xbee's probe for a radio in transparent mode (guard times
        # around +++), kept, as it names that case.
        device.set_sync_ops_timeout(OPEN_TIMEOUT_S)
        device.open()
        device.set_sync_ops_timeout(SYNC_OPS_TIMEOUT_S)  # remote commands cross the air
    except (XBeeException, OSError) as exc:
        raise RadioSetupError(
            f"no XBee in API mode answers at {port} ({baud} baud): {exc}; check the port and "
            "the baud rate; a radio in transparent mode must be put in API mode once (ATAP1)"
        ) from exc
    return device


def scan(
    port: str, baud: int = 115200, *, timeout_s: float = 10.0, progress: Callable[[str], None]
) -> list[Node]:
    """Discover the radios the coordinator at ``port`` hears.

    Raises:
        RadioSetupError: the coordinator does not answer.
    """
    from digi.xbee.exception import XBeeException  # noqa: PLC0415

    progress(f"asking the radio at {port} ({baud} baud)...")  # a silent port: ~6 s (AP, then +++)
    device = _open(port, baud)
    try:
        progress(
            f"coordinator {device.get_64bit_addr()} ({device.get_protocol().description}); "
            "discovering..."
        )
        network = device.get_network()
        network.start_discovery_process()
        deadline = time.monotonic() + timeout_s
        while network.is_discovery_running() and time.monotonic() < deadline:
            time.sleep(0.1)  # digi-xbee's discovery runs on its own thread; poll its state
        network.stop_discovery_process()
        nodes = []
        for remote in network.get_devices():
            try:
                rssi: int | None = -int(remote.get_parameter("DB")[0])
            except (XBeeException, IndexError):
                rssi = None
            address = int(str(remote.get_64bit_addr()), 16)
            nodes.append(Node(address, remote.get_node_id() or "", rssi))
        return sorted(nodes, key=lambda n: n.address)
    finally:
        device.close()


def setup(
    port: str,
    baud: int = 115200,
    *,
    api_mode: int = 1,
    pan_id: int = 0x3332,
    channel: int = 0x0C,
    new_baud: int | None = None,
    robot_baud: int = 115200,
    remotes: Sequence[int] = (),
    progress: Callable[[str], None],
) -> None:
    """Configure the robots' radios ``remotes`` and then the coordinator at ``port``.

    Every setting is checked before any radio is touched (a bad coordinator rate found after
    the robots were switched would leave them on another channel than the coordinator).

    Raises:
        RadioSettingError: a setting out of range (nothing was changed).
        RadioSetupError: a radio does not answer or refuses a setting.
    """
    from digi.xbee.devices import RemoteXBeeDevice  # noqa: PLC0415
    from digi.xbee.exception import XBeeException  # noqa: PLC0415
    from digi.xbee.models.address import XBee64BitAddress  # noqa: PLC0415

    check_api_mode(api_mode)
    check_channel(channel)
    check_pan_id(pan_id)
    for rate in (baud, robot_baud, new_baud or baud):
        check_baud(rate)
    progress(f"asking the radio at {port} ({baud} baud)...")  # a silent port: ~6 s (AP, then +++)
    device = _open(port, baud)
    try:
        own = int(str(device.get_64bit_addr()), 16)
        for address in remotes:
            name = format_address(address)
            progress(f"robot radio {name}: PAN {pan_id:#06x}, channel {channel:#04x}, ...")
            remote = RemoteXBeeDevice(device, XBee64BitAddress.from_hex_string(name))
            settings = [
                ("ID", pan_id.to_bytes(2, "big")),
                ("DH", (own >> 32).to_bytes(4, "big")),
                ("DL", (own & 0xFFFFFFFF).to_bytes(4, "big")),
                ("AP", b"\x00"),  # transparent: the firmware needs no new wiring
                ("BD", bytes((baud_code(robot_baud),))),
                ("CH", bytes((channel,))),  # last: after AC the radio is on the new channel
            ]
            try:
                for command, value in settings:
                    remote.set_parameter(command, bytearray(value), apply=False)
                remote.write_changes()
                remote.apply_changes()
            except XBeeException as exc:
                raise RadioSetupError(f"robot radio {name}: {exc}") from exc
        progress(
            f"coordinator: API mode {api_mode}, PAN {pan_id:#06x}, channel {channel:#04x}, "
            f"{new_baud or baud} baud"
        )
        try:
            for command, value in (
                ("ID", pan_id.to_bytes(2, "big")),
                ("CH", bytes((channel,))),
                ("BD", bytes((baud_code(new_baud or baud),))),
                ("AP", bytes((api_mode,))),
            ):
                device.set_parameter(command, bytearray(value), apply=False)
            device.write_changes()
            device.apply_changes()
        except XBeeException as exc:
            raise RadioSetupError(f"coordinator at {port}: {exc}") from exc
    finally:
        device.close()
