"""Bad option values are usage errors (exit 2, the option named, a range or an example in the
message), found by argparse before anything starts; ``--version``; the e-stop reason.

All through the real entry point, in-process (``main([...])``); nothing here opens a bus.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import zenoh
from hilswarm.agents import bus
from hilswarm.agents.agent import estop_reason
from hilswarm.agents.link.board import PROTOCOL_VERSION, SUPPORTED_PROTOCOL_VERSIONS
from hilswarm.agents.mocap.clients import (
    MocapConnectionError,
    MotionCaptureClient,
    QualisysClient,
    host_of,
)
from hilswarm.orchestrator.cli import main

REPO = Path(__file__).resolve().parents[2]
RING = str(REPO / "graphs" / "consensus_ring.toml")
LEAD = str(REPO / "graphs" / "lead_follow.toml")
XBEE = str(REPO / "graphs" / "xbee_swarm.toml")


def usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``hilswarm argv``; it must stop as a usage error (exit 2); its stderr."""
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


# -- endpoints ------------------------------------------------------------------------------------

ENDPOINT_COMMANDS = [
    pytest.param(["run", RING, "--connect", "foo"], "--connect", "foo", id="run-connect"),
    pytest.param(["run", RING, "--listen", "badendpoint"], "--listen", "badendpoint", id="listen"),
    pytest.param(
        ["set", "lead_follow", "leader", "kp=1", "--connect", "garbage"],
        "--connect",
        "garbage",
        id="set",
    ),
    pytest.param(
        ["stop", "lead_follow", "--connect", "garbage"], "--connect", "garbage", id="stop"
    ),
    pytest.param(
        ["agent", "--experiment", LEAD, "--name", "leader", "--connect", "tcp/"],
        "--connect",
        "tcp/",
        id="agent",
    ),
    pytest.param(["gateway", XBEE, "--connect", "x"], "--connect", "x", id="gateway"),
]


@pytest.mark.parametrize(("argv", "option", "value"), ENDPOINT_COMMANDS)
def test_a_malformed_endpoint_is_a_usage_error_naming_the_option(
    argv: list[str], option: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    err = usage_error(argv, capsys)
    expected = f"{option}: {value!r} is not a Zenoh endpoint (e.g. tcp/127.0.0.1:7447)"
    assert expected in err, err
    assert "ZError" not in err and "Json5Err" not in err


@pytest.mark.parametrize(
    ("value", "reason"),
    [
        ("tcp/127.0.0.1:99999", "port in 0..65535"),
        ("tcp/foo", "needs HOST:PORT"),
        ("xyz/1.2.3.4:5", "unknown protocol 'xyz'"),
        (" tcp/127.0.0.1:7447", "is not a Zenoh endpoint"),
    ],
)
def test_endpoints_zenoh_would_only_refuse_at_open_are_refused_up_front(
    value: str, reason: str, capsys: pytest.CaptureFixture[str]
) -> None:
    err = usage_error(["run", RING, "--listen", value], capsys)
    assert f"argument --listen: {value!r} is not a Zenoh endpoint" in err, err
    assert reason in err, err


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/127.0.0.1:7447",
        "tcp/127.0.0.1:0",
        "tls/0.0.0.0:7447",
        "tcp/[::1]:7447",
        "tcp/localhost:7447?iface=lo#rx_buffer_size=1024",
        "udp/10.0.0.1:7447",
        "unixsock-stream/hilswarm-bus.sock",
    ],
)
def test_endpoints_are_accepted_as_zenoh_takes_them(endpoint: str) -> None:
    assert bus.check_endpoint(endpoint) == endpoint
    bus.client_config([endpoint])  # and Zenoh's own parser agrees


def test_every_session_configuration_checks_its_endpoints() -> None:
    """The same rule where every configuration is built (credentials files, internal
    processes' ``--connect``): the project's error, not a ``zenoh.ZError``."""
    for build in (bus.client_config, bus.listen_config):
        with pytest.raises(bus.BusEndpointError, match="'foo' is not a Zenoh endpoint"):
            build(["foo"])
    with pytest.raises(bus.BusEndpointError):
        bus.session_config("client", connect=["tcp/127.0.0.1:7447", "nonsense"])


def test_a_session_that_cannot_open_is_told_in_words() -> None:
    """A well-formed endpoint this Zenoh cannot use: a BusConnectionError with Zenoh's reason,
    without its Rust source locations."""
    with pytest.raises(bus.BusConnectionError) as raised:
        bus.open_session(bus.listen_config(["vsock/1:2"]))
    message = str(raised.value)
    assert message.startswith("cannot open the bus session on vsock/1:2: "), message
    assert ".rs:" not in message and "vsock" in message
    assert not isinstance(raised.value, zenoh.ZError)


# -- durations, timeouts, counts ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "option", "value"),
    [
        (["run", RING, "--start-timeout", "-1"], "--start-timeout", "-1"),
        (["run", RING, "--answer-timeout", "0"], "--answer-timeout", "0"),
        (["run", RING, "--answer-timeout", "nan"], "--answer-timeout", "nan"),
        (["run", RING, "--start-timeout", "inf"], "--start-timeout", "inf"),
        (["stop", "lead_follow", "--timeout", "-1"], "--timeout", "-1"),
        (["set", "lead_follow", "leader", "kp=1", "--timeout", "0"], "--timeout", "0"),
        (["xbee", "scan", "--port", "X", "--timeout", "-1"], "--timeout", "-1"),
        (["mocap", "--system", "sim", "--seconds", "0"], "--seconds", "0"),
    ],
)
def test_a_duration_must_be_positive(
    argv: list[str], option: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    err = usage_error(argv, capsys)
    assert f"argument {option}: {value} is out of range; expected" in err, err


def test_a_duration_that_is_no_number_and_an_upper_bound(
    capsys: pytest.CaptureFixture[str],
) -> None:
    err = usage_error(["stop", "x", "--timeout", "soon"], capsys)
    assert "argument --timeout: 'soon' is not a number" in err, err
    err = usage_error(["mocap", "--system", "sim", "--seconds", "61"], capsys)
    assert "argument --seconds: 61 is out of range; expected 0 < value <= 60" in err, err


@pytest.mark.parametrize("command", ["check", "graph", "run"])
@pytest.mark.parametrize("value", ["0", "-3"])
def test_max_agents_must_be_at_least_one(
    command: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    err = usage_error([command, RING, "--max-agents", value], capsys)
    assert f"argument --max-agents: {value} is out of range; expected an integer >= 1" in err


def test_an_explicit_max_agents_is_named_as_such(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", RING, "--max-agents", "3"]) == 2
    err = capsys.readouterr().err
    assert "6 agents is more than 3, the limit set by --max-agents" in err, err
    assert "without an explicit limit" not in err


# -- xbee setup settings --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [
        ("--channel", "0x40", "channel 0x40 is out of range; expected 0x0B-0x1A"),
        ("--channel", "10", "channel 0xa is out of range; expected 0x0B-0x1A"),
        ("--pan-id", "0x10000", "PAN id 0x10000 is out of range; expected 0x0000-0xFFFF"),
        ("--pan-id", "-1", "PAN id -0x1 is out of range; expected 0x0000-0xFFFF"),
        ("--new-baud", "1234", "1234 baud is not a standard XBee rate"),
        ("--robot-baud", "250000", "250000 baud is not a standard XBee rate"),
        ("--baud", "9601", "9601 baud is not a standard XBee rate"),
        ("--channel", "twelve", "'twelve' is not an integer"),
    ],
)
def test_xbee_setup_checks_its_settings_before_any_radio(
    option: str, value: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    err = usage_error(["xbee", "setup", "--port", "sim", option, value], capsys)
    assert f"argument {option}: {message}" in err, err


def test_xbee_setup_settings_in_range_are_taken_as_written() -> None:
    from hilswarm.orchestrator.cli import build_parser

    args = build_parser("xbee").parse_args(
        ["xbee", "setup", "--port", "sim", "--channel", "0x1A", "--pan-id", "0xFFFF",
         "--new-baud", "9600"]
    )  # fmt: skip
    assert (args.channel, args.pan_id, args.new_baud, args.baud) == (0x1A, 0xFFFF, 9600, 115200)


def test_verbose_counts_before_and_after_the_command(capsys: pytest.CaptureFixture[str]) -> None:
    from hilswarm.orchestrator.cli import build_parser, parse_arguments

    assert parse_arguments(build_parser("check"), ["check", LEAD]).verbose == 0
    assert parse_arguments(build_parser("check"), ["-v", "check", LEAD, "-v"]).verbose == 2
    assert parse_arguments(build_parser("run"), ["run", LEAD, "-vv"]).verbose == 2
    args = parse_arguments(build_parser("xbee"), ["xbee", "scan", "--port", "sim", "-v"])
    assert args.verbose == 1 and not hasattr(args, "verbose_after_command")
    assert main(["check", LEAD, "-v"]) == 0  # was "unrecognized arguments: -v"
    assert "ok: lead_follow" in capsys.readouterr().out


# -- mocap host names that do not resolve ---------------------------------------------------------


@pytest.fixture
def no_dns(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Name resolution fails for every name (as for a host that does not exist); nothing is
    asked of a real resolver. The names asked for are listed."""
    asked: list[str] = []

    def fail(host: str, *_args: object, **_kwargs: object) -> None:
        asked.append(host)
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(socket, "getaddrinfo", fail)
    return asked


@pytest.mark.parametrize("system", ["qualisys", "vicon", "optitrack", "vrpn"])
def test_mocap_says_a_host_name_does_not_resolve(
    system: str, no_dns: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["mocap", "--system", system, "--host", "nonexistent.invalid"]) == 1
    err = capsys.readouterr().err
    assert "the host name 'nonexistent.invalid' does not resolve" in err, err
    assert "name resolution failed: Name or service not known" in err, err
    assert "refused" not in err and "no body" not in err and "answered" not in err, err
    assert no_dns == ["nonexistent.invalid"]


def test_each_client_looks_up_the_host_without_its_port(no_dns: list[str]) -> None:
    with pytest.raises(MocapConnectionError, match=r"QTM at mocap\.lab:22223: the host name"):
        QualisysClient("mocap.lab").run(lambda f: None, lambda: None)
    with pytest.raises(MocapConnectionError, match=r"vicon at vicon\.lab:801: the host name"):
        MotionCaptureClient("vicon", "vicon.lab:801").run(lambda f: None, lambda: None)
    assert no_dns == ["mocap.lab", "vicon.lab"]
    assert [host_of(a) for a in ("h", "h:1", "[::1]:3883", "fe80::1")] == [
        "h",
        "h",
        "::1",
        "fe80::1",
    ]


# -- --version ------------------------------------------------------------------------------------


def test_version_names_the_package_and_the_wire_protocols(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from importlib.metadata import version

    with pytest.raises(SystemExit) as stopped:
        main(["--version"])
    assert stopped.value.code == 0
    out = capsys.readouterr().out
    accepted = ", ".join(str(v) for v in sorted(SUPPORTED_PROTOCOL_VERSIONS))
    assert out == (
        f"hilswarm {version('hilswarm')} (board wire protocol {PROTOCOL_VERSION}; "
        f"boards speaking {accepted} accepted)\n"
    )


# -- the e-stop reason ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("given", "recorded"),
    [
        ("", "e-stop"),
        ("e-stop", "e-stop"),
        ("  ", "e-stop"),
        ("battery low", "e-stop: battery low"),
    ],
)
def test_the_estop_reason_is_said_once(given: str, recorded: str) -> None:
    assert estop_reason(given) == recorded


def _early_processes_of_this_process() -> list[int]:
    """Pids of agent fork servers and recorder processes whose parent is this process."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])
        started = b"hilswarm.agents.spawner" in cmdline or b"recorder_process" in cmdline
        if parent == os.getpid() and started:
            found.append(int(entry.name))
    return found


def test_run_starts_its_processes_first_and_never_leaves_them_behind(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``hilswarm run`` starts the agents' fork server and its recorder process before it
    imports its own modules; when the command ends without using them (``--help``, a usage
    error) they are ended at once, not left importing or waiting for a set-up."""
    with pytest.raises(SystemExit) as stopped:
        main(["run", "--help"])
    assert stopped.value.code == 0
    usage_error(["run", LEAD, "--start-timeout", "-1"], capsys)
    assert _early_processes_of_this_process() == []  # reaped: none left, not even a zombie
