"""``hilswarm xbee scan|setup``: find and configure XBee radios (no X-CTU needed).

Examples::

    hilswarm xbee scan --port /dev/ttyUSB0
    hilswarm xbee setup --port /dev/ttyUSB0 --api-mode 1 --pan-id 0x3332 --channel 0x0C \\
        --remote 0013A20040A1B2C3 --remote 0013A20040A1B2C4

``scan`` lists every radio the coordinator hears (64-bit address, node id, RSSI). ``setup``
configures the robots' radios over the air (transparent mode, PAN id, channel, destination =
the coordinator) and then the coordinator (API mode, PAN id, channel, baud); ``--all`` takes
every radio a scan finds. Exit status: 0 done, 1 a radio did not answer, 2 bad input (e.g. a
serial device that does not exist: the message lists the ports present).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from hilswarm.orchestrator.cli_types import positive_float

HELP = "XBee radios: node discovery (scan) and configuration (setup)"


def _setting(check_name: str) -> Callable[[str], int]:
    """A ``type=`` for a radio setting (decimal or ``0x..``), checked up front by
    :mod:`hilswarm.agents.xbee.radio_setup`'s own ``check_*`` rule (the range in the message)."""

    def parse(text: str) -> int:
        from hilswarm.agents.xbee import radio_setup  # noqa: PLC0415 - xbee only

        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        try:
            return getattr(radio_setup, check_name)(value)
        except radio_setup.RadioSettingError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = "integer"
    return parse


def _address(text: str) -> int:
    from hilswarm.agents.xbee.config import parse_xbee_url  # noqa: PLC0415

    try:
        return parse_xbee_url(f"xbee://{text.removeprefix('xbee://')}").address
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


_baud = _setting("check_baud")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm xbee``."""
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    scan = sub.add_parser("scan", help="node discovery: address, node id, RSSI of every radio")
    setup = sub.add_parser("setup", help="configure the robots' radios and the coordinator")
    for p in (scan, setup):
        p.add_argument("--port", required=True, help="the coordinator's serial port")
        p.add_argument("--baud", type=_baud, default=115200, help="its current baud rate")
    scan.add_argument("--timeout", type=positive_float, default=10.0, help="discovery bound [s]")
    setup.add_argument("--api-mode", type=int, choices=(1, 2), default=1)
    setup.add_argument(
        "--pan-id", type=_setting("check_pan_id"), default=0x3332, help="PAN id 0x0000-0xFFFF"
    )
    setup.add_argument(
        "--channel", type=_setting("check_channel"), default=0x0C, help="channel 0x0B-0x1A"
    )
    setup.add_argument("--new-baud", type=_baud, default=None, help="coordinator's new baud")
    setup.add_argument("--robot-baud", type=_baud, default=115200, help="robots' UART baud")
    setup.add_argument(
        "--remote", type=_address, action="append", default=[], help="a robot radio's address"
    )
    setup.add_argument("--all", action="store_true", help="configure every radio a scan finds")


def run(args: argparse.Namespace) -> int:
    """Scan or set up."""
    from hilswarm.agents.link.serial_board import validate_url  # noqa: PLC0415
    from hilswarm.agents.xbee import radio_setup  # noqa: PLC0415 - digi-xbee only here

    def progress(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    try:
        validate_url(args.port)  # a device path that does not exist: bad input, said so
        if args.action == "scan":
            nodes = radio_setup.scan(
                args.port, args.baud, timeout_s=args.timeout, progress=progress
            )
            print(f"{'address':<18} {'node id':<20} RSSI [dBm]")
            for node in nodes:
                rssi = "?" if node.rssi_dbm is None else str(node.rssi_dbm)
                print(f"{node.address:016X}   {node.node_id:<20} {rssi}")
            print(f"{len(nodes)} radio(s) found", file=sys.stderr)
            return 0
        remotes = list(args.remote)
        if args.all:
            found = radio_setup.scan(args.port, args.baud, progress=progress)
            remotes += [n.address for n in found if n.address not in remotes]
        radio_setup.setup(
            args.port,
            args.baud,
            api_mode=args.api_mode,
            pan_id=args.pan_id,
            channel=args.channel,
            new_baud=args.new_baud,
            robot_baud=args.robot_baud,
            remotes=remotes,
            progress=progress,
        )
        print(f"configured {len(remotes)} robot radio(s) and the coordinator")
        return 0
    except ValueError as exc:
        print(f"hilswarm xbee: {exc}", file=sys.stderr)
        return 2
    except radio_setup.RadioSetupError as exc:
        print(f"hilswarm xbee: {exc}", file=sys.stderr)
        return 1
