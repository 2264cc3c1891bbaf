"""``hilswarm run``: run an experiment — one process per agent, ticks, recording to MCAP.

Example::

    hilswarm run graphs/lead_follow.toml
    hilswarm run graphs/lead_follow.toml --link leader=/dev/ttyUSB0 --mode realtime
    hilswarm run graphs/consensus_ring.toml --out out/ring.mcap --duration 5
    hilswarm run graphs/lead_follow.toml --mode realtime --live      # watch it in Foxglove

Ctrl-C (or ``hilswarm stop EXP`` from another terminal) brings every agent to safe mode, stops
it, and closes the recording properly. Exit status: 0 completed or stopped on request, 1 the
run failed (an agent lost with ``on_agent_loss = "stop"``, start-up failure), 2 bad input,
130 interrupted by Ctrl-C.
"""

from __future__ import annotations

import argparse
import datetime
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from hilswarm.agents import bus
from hilswarm.agents.errors import RecordingError
from hilswarm.orchestrator.checks import check_file
from hilswarm.orchestrator.commands.overrides import add_override_arguments, overrides_from_args
from hilswarm.orchestrator.experiment import Experiment, load_experiment
from hilswarm.orchestrator.gateway_launcher import GatewayLauncher, GatewayProcessError
from hilswarm.orchestrator.launcher import AgentLauncher, AgentProcessError, agent_config_for
from hilswarm.orchestrator.manager import (
    DEFAULT_ANSWER_TIMEOUT_S,
    DEFAULT_START_TIMEOUT_S,
    InstanceManager,
    ManagerError,
)
from hilswarm.orchestrator.mocap_runner import MocapError, MocapRunner
from hilswarm.orchestrator.recorder_process import RecorderProcess
from hilswarm.orchestrator.run_summary import RunSummary
from hilswarm.orchestrator.status_display import StatusDisplay

HELP = "run an experiment file (one process per agent, recorded to MCAP)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm run``."""
    parser.add_argument("file", type=Path, help="experiment file (TOML)")
    parser.add_argument(
        "--out", type=Path, default=None, help="MCAP file (default out/<exp>-<timestamp>.mcap)"
    )
    add_override_arguments(parser)
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="join an existing Zenoh router (e.g. tcp/127.0.0.1:7447) instead of opening one",
    )
    parser.add_argument(
        "--port",
        type=int,
        default=bus.DEFAULT_PORT,
        help=f"loopback port of the embedded bus (default {bus.DEFAULT_PORT})",
    )
    parser.add_argument(
        "--remote",
        action="append",
        default=[],
        metavar="AGENT",
        help="do not start AGENT here: it joins with `hilswarm agent` (repeatable)",
    )
    parser.add_argument(
        "--start-timeout",
        type=float,
        default=DEFAULT_START_TIMEOUT_S,
        metavar="SECONDS",
        help="bound on waiting for every agent to be ready [s]",
    )
    parser.add_argument(
        "--answer-timeout",
        type=float,
        default=DEFAULT_ANSWER_TIMEOUT_S,
        metavar="SECONDS",
        help="lockstep: an agent silent this long on one tick is lost [s]",
    )
    parser.add_argument(
        "--live",
        nargs="?",
        type=int,
        const=0,
        default=None,
        metavar="PORT",
        help="serve the run live to the Foxglove app (WebSocket on localhost; PORT default: "
        "a free one, printed as a ws:// URL)",
    )
    parser.add_argument(
        "--remote-gateway",
        action="store_true",
        help="do not start the XBee gateway here: it joins with `hilswarm gateway`",
    )
    parser.add_argument(
        "--no-check",
        action="store_true",
        help="skip the vehicle/controller checks (e.g. remote agents' classes not installed)",
    )


def _gateway_launcher(
    experiment: Experiment, endpoints: list[str], args: argparse.Namespace
) -> GatewayLauncher | None:
    """The gateway process of ``experiment`` when an agent links through XBee (and it runs
    here)."""
    if args.remote_gateway:
        return None
    from hilswarm.agents.xbee.gateway_process import plan_for  # noqa: PLC0415 - xbee runs only

    plan = plan_for(experiment)
    if plan is None:
        return None
    return GatewayLauncher(plan, endpoints, verbose=max(0, args.verbose - 1))


def default_output(experiment: Experiment, now: datetime.datetime) -> Path:
    """``out/<exp>-<YYYYmmdd-HHMMSS>.mcap``."""
    return Path("out") / f"{experiment.name}-{now:%Y%m%d-%H%M%S}.mcap"


def run(args: argparse.Namespace) -> int:
    """Run the experiment; see the module docstring for the exit status."""
    overrides = overrides_from_args(args)
    if args.no_check:
        experiment = load_experiment(
            args.file, overrides=overrides, max_agents=args.max_agents, remote=args.remote
        )
    else:
        report = check_file(
            args.file, overrides=overrides, max_agents=args.max_agents, remote=args.remote
        )
        experiment = report.raise_for_problems()
    unknown = [name for name in args.remote if name not in experiment.agent_names]
    if unknown:
        print(f"hilswarm run: --remote names unknown agents: {', '.join(unknown)}", file=sys.stderr)
        return 2
    if args.live:  # a given port: refuse a busy one before anything starts
        from hilswarm.orchestrator.live_view import port_problem  # noqa: PLC0415 - --live only

        problem = port_problem(args.live)
        if problem:
            print(f"hilswarm run: {problem}", file=sys.stderr)
            return 2
    out = args.out or default_output(experiment, datetime.datetime.now())
    endpoints = list(args.connect) or [bus.loopback_endpoint(args.port)]
    display = StatusDisplay(sys.stdout)
    recorder = RecorderProcess(out, experiment, log_time_ns=time.time_ns(), live_port=args.live)
    launcher = AgentLauncher(
        endpoints, verbose=max(0, args.verbose - 1), import_paths=[experiment.path.parent]
    )
    manager = InstanceManager(
        experiment,
        recorder=recorder,
        listen=[] if args.connect else endpoints,
        connect=args.connect,
        answer_timeout_s=args.answer_timeout,
        display=display,
        describe_process=launcher.describe,
    )
    interrupted = False
    gateway = _gateway_launcher(experiment, endpoints, args)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        nonlocal interrupted
        interrupted = interrupted or signum == signal.SIGINT
        manager.request_stop("interrupted" if signum == signal.SIGINT else "terminated")

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    summary: RunSummary | None = None
    error = ""
    mocap = MocapRunner(experiment, endpoints) if experiment.mocap is not None else None
    try:
        manager.open()
        if gateway is not None:
            display.log(f"XBee gateway: {gateway.start()}")
        if mocap is not None:
            mocap.start()
            mocap.wait_ready()
        launcher.start_all(
            [
                agent_config_for(experiment, n)
                for n in experiment.agent_names
                if n not in args.remote
            ]
        )
        display.log(
            f"{experiment.name}: {len(experiment.agents)} agents, {experiment.mode}, "
            f"{experiment.rate_hz:g} Hz, {experiment.duration_s:g} s; bus {', '.join(endpoints)}"
        )
        manager.wait_for_agents(args.start_timeout, check=launcher.check)
        recorder.wait_ready()
        if recorder.live_url:
            display.log("live view: open this in the Foxglove app (Open connection):")
            display.log(recorder.live_url)
        summary = manager.run()
    except (
        ManagerError,
        AgentProcessError,
        RecordingError,
        GatewayProcessError,
        MocapError,
    ) as exc:
        error = str(exc)
    finally:
        display.finish()
        launcher.stop()
        if gateway is not None:
            gateway.stop()
        if mocap is not None:
            mocap.stop()
        manager.close()
        if recorder.close() != 0 and not error:
            error = f"the recording {out} is incomplete (see the recorder's log above)"
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    print(f"recording: {out}")
    if summary is not None:
        print(summary.text())
    if error:
        print(f"hilswarm run: {error}", file=sys.stderr)
        return 130 if interrupted else 1
    if interrupted:
        return 130
    return 1 if summary is None or summary.failed else 0
