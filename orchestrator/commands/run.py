"""``hilswarm run``: run an experiment — one process per agent, ticks, recording to MCAP.

Example::

    hilswarm run graphs/lead_follow.toml
    hilswarm run graphs/lead_follow.toml --link leader=/dev/ttyUSB0 --mode realtime
    hilswarm run graphs/consensus_ring.toml --out out/ring.mcap --duration 5
    hilswarm run graphs/lead_follow.toml --mode realtime --live      # watch it in Foxglove

Every run has a bus of its own: the embedded router binds a free loopback port (printed, and
listed by ``hilswarm ps``), every key carries a fresh run id, and every process authenticates
with credentials made for this run; the router's access control lets each one do only its job
(docs/security.md). ``--listen tls/0.0.0.0:PORT`` adds a TLS endpoint for agents on other
machines (``--remote NAME``, joined with ``hilswarm agent --credentials FILE``).

Ctrl-C (or ``hilswarm stop EXP`` from another terminal) brings every agent to safe mode, stops
it, and closes the recording properly. The exit status tells the truth about the run (see
:mod:`hilswarm.orchestrator.outcome` and :data:`EXIT_STATUS_HELP`); the end-of-run summary lists
every degradation with counts and ticks.

``--out`` never replaces an existing recording unless ``--force`` is given, and a run that
fails before its first tick leaves no file: the recording is written under a hidden name and
takes its name when the first tick is sent. An ``--out`` that cannot be written (a folder, a
file in the way of its folder, a read-only folder) is refused before anything starts (exit 2).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import secrets
import signal
import sys
import time
from pathlib import Path
from types import FrameType

from hilswarm.agents import bus
from hilswarm.agents.errors import RecordingError
from hilswarm.orchestrator import outcome
from hilswarm.orchestrator.bus_access import GATEWAY, MOCAP, VIEWER
from hilswarm.orchestrator.checks import check_file
from hilswarm.orchestrator.cli_types import endpoint, positive_float
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
from hilswarm.orchestrator.mocap_runner import MocapError, MocapRunner, describe_frames
from hilswarm.orchestrator.output_paths import check_output_file
from hilswarm.orchestrator.recorder_process import RecorderProcess
from hilswarm.orchestrator.run_registry import RunEntry, RunRecord
from hilswarm.orchestrator.run_security import RunSecurity, is_loopback
from hilswarm.orchestrator.run_summary import RunSummary
from hilswarm.orchestrator.segments import existing_segments
from hilswarm.orchestrator.status_display import StatusDisplay, StatusSnapshot

HELP = "run an experiment file (one process per agent, recorded to MCAP)"

EXIT_STATUS_HELP = """\
exit status:
  0    clean: every tick ran (or the run was stopped on request), nothing degraded
  3    completed but degraded: an agent went safe, was lost or had link faults, ticks
       were missed, late ticks above max_late_fraction (default 1 %), an e-stop, or the
       recording is incomplete or split after a recorder failure (see the summary)
  1    failed: an agent lost with on_agent_loss = "stop", safe with on_agent_safe =
       "stop", safe from its first tick, no tick completed, or a start-up failure
  2    bad input (experiment file, options, --out exists without --force or cannot be
       written)
  130  interrupted (Ctrl-C)

If the recorder process dies it is restarted and the recording continues in the next
segment (run.1.mcap, run.2.mcap, ...). A full disk: on_recording_failure = "stop"
(default: robots safe, the run stops, exit 3) or "continue" (the run goes on unrecorded).
"""
#: ``on_recording_failure`` when the experiment does not set it.
DEFAULT_ON_RECORDING_FAILURE = "stop"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm run``."""
    parser.epilog = EXIT_STATUS_HELP
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("file", type=Path, help="experiment file (TOML)")
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="MCAP file (default out/<exp>-<timestamp>.mcap); never replaced without --force",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out recording (and its segments run.N.mcap)",
    )
    add_override_arguments(parser)
    parser.add_argument(
        "--connect",
        action="append",
        type=endpoint,
        default=[],
        metavar="ENDPOINT",
        help="join an existing Zenoh router (e.g. tcp/127.0.0.1:7447) instead of opening one "
        "(no authentication: secure that router yourself)",
    )
    parser.add_argument(
        "--port",
        type=int,
        default=0,
        help="loopback port of the embedded bus (default 0: a free port, printed)",
    )
    parser.add_argument(
        "--listen",
        action="append",
        type=endpoint,
        default=[],
        metavar="ENDPOINT",
        help="also listen here for agents on other machines, e.g. tls/0.0.0.0:7447 "
        "(port 0: a free one; tls/ endpoints use a CA made for this run)",
    )
    parser.add_argument(
        "--tls-name",
        action="append",
        default=[],
        metavar="HOST",
        help="another name or address other machines reach this one by (TLS certificate)",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="no authentication and no access control on the bus (debugging, benchmarks)",
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
        type=positive_float,
        default=DEFAULT_START_TIMEOUT_S,
        metavar="SECONDS",
        help="bound on waiting for every agent to be ready [s]",
    )
    parser.add_argument(
        "--answer-timeout",
        type=positive_float,
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
    experiment: Experiment, run_id: str, args: argparse.Namespace
) -> GatewayLauncher | None:
    """The gateway process of ``experiment`` when an agent links through XBee (and it runs
    here)."""
    if args.remote_gateway:
        return None
    from hilswarm.agents.xbee.gateway_process import plan_for  # noqa: PLC0415 - xbee runs only

    plan = plan_for(experiment)
    if plan is None:
        return None
    return GatewayLauncher(plan, [], run_id=run_id, verbose=max(0, args.verbose - 1))


def default_output(experiment: Experiment, now: datetime.datetime) -> Path:
    """``out/<exp>-<YYYYmmdd-HHMMSS>.mcap`` (``-2``, ``-3``, ... when that name is taken)."""
    base = Path("out") / f"{experiment.name}-{now:%Y%m%d-%H%M%S}.mcap"
    candidate, n = base, 1
    while existing_segments(candidate):
        n += 1
        candidate = base.with_name(f"{base.stem}-{n}{base.suffix}")
    return candidate


def on_recording_failure(experiment: Experiment) -> str:
    """The experiment's ``on_recording_failure`` policy (``"stop"`` or ``"continue"``)."""
    # read defensively: the key comes with the experiment schema
    return str(getattr(experiment, "on_recording_failure", DEFAULT_ON_RECORDING_FAILURE))


def run(args: argparse.Namespace) -> int:
    """Run the experiment; see the module docstring for the exit status."""
    overrides = overrides_from_args(args)
    if args.no_check:
        experiment = load_experiment(
            args.file, overrides=overrides, max_agents=args.max_agents, remote=args.remote
        )
    else:
        report = check_file(
            args.file,
            overrides=overrides,
            max_agents=args.max_agents,
            remote=args.remote,
            remote_gateway=args.remote_gateway,
        )
        experiment = report.raise_for_problems()
        for warning in report.warnings:  # as `hilswarm check` shows them: nothing silent
            print(f"warning: {warning}", file=sys.stderr)
    unknown = [name for name in args.remote if name not in experiment.agent_names]
    if unknown:
        print(f"hilswarm run: --remote names unknown agents: {', '.join(unknown)}", file=sys.stderr)
        return outcome.BAD_INPUT
    if args.live:  # a given port: refuse a busy one before anything starts
        from hilswarm.orchestrator.live_view import port_problem  # noqa: PLC0415 - --live only

        problem = port_problem(args.live)
        if problem:
            print(f"hilswarm run: {problem}", file=sys.stderr)
            return outcome.BAD_INPUT
    out = args.out or default_output(experiment, datetime.datetime.now())
    check_output_file(out, what="the recording")  # before anything starts: exit 2
    taken = existing_segments(out)
    if taken and not args.force:
        names = ", ".join(str(path) for path in taken)
        print(
            f"hilswarm run: {names} exists; it is not replaced: choose another --out or pass "
            "--force",
            file=sys.stderr,
        )
        return outcome.BAD_INPUT
    run_id = secrets.token_hex(4)
    secure = not (args.insecure or args.connect)
    listen = [] if args.connect else [bus.loopback_endpoint(args.port), *args.listen]
    record = RunRecord(
        RunEntry(
            name=experiment.name,
            run_id=run_id,
            endpoints=list(args.connect or listen),
            pid=0,
            mode=experiment.mode,
            n_ticks=experiment.n_ticks,
            agents=dict.fromkeys(experiment.agent_names, "starting"),
            file=str(args.file),
            out=str(out),
            started=datetime.datetime.now(datetime.UTC).isoformat(timespec="milliseconds"),
            secure=secure,
        )
    )
    try:
        return _run(args, experiment, record, listen=listen, secure=secure)
    finally:
        record.remove()


def _run(
    args: argparse.Namespace,
    experiment: Experiment,
    record: RunRecord,
    *,
    listen: list[str],
    secure: bool,
) -> int:
    run_id = record.entry.run_id
    out = Path(record.entry.out)
    security = None
    if secure:
        security = RunSecurity.for_experiment(
            experiment, run_id, record.folder, listen=listen, tls_names=args.tls_name
        )
    display = StatusDisplay(sys.stdout)
    policy = on_recording_failure(experiment)
    manager: InstanceManager | None = None

    def recording_failed(reason: str) -> None:
        display.log(f"recording failed: {reason}")
        if policy == "stop" and manager is not None:
            manager.request_stop(f"recording failed ({reason}); on_recording_failure = stop")
        else:
            display.log("on_recording_failure = continue: the run goes on, not recorded")

    out.parent.mkdir(parents=True, exist_ok=True)
    recorder = RecorderProcess(
        out,
        experiment,
        log_time_ns=time.time_ns(),
        staged=True,
        on_failure=recording_failed,
        live_port=args.live,
        process=getattr(args, "recorder_process", None),  # started by the CLI (cli.py)
    )
    launcher = AgentLauncher(
        [],
        verbose=max(0, args.verbose - 1),
        import_paths=[experiment.path.parent],
        fork_server=getattr(args, "fork_server", None),  # started by the CLI (cli.py)
    )
    manager = InstanceManager(
        experiment,
        recorder=recorder,
        listen=listen,
        connect=args.connect,
        run_id=run_id,
        security=security.router() if security else None,
        answer_timeout_s=args.answer_timeout,
        display=_RegistryDisplay(display, record),
        describe_process=launcher.describe,
        remote=args.remote,
    )
    interrupted = False
    gateway = _gateway_launcher(experiment, run_id, args)

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        nonlocal interrupted
        interrupted = interrupted or signum == signal.SIGINT
        manager.request_stop("interrupted" if signum == signal.SIGINT else "terminated")

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    summary: RunSummary | None = None
    error = ""
    mocap = (
        MocapRunner(experiment, [], run_id=run_id, verbose=max(0, args.verbose - 1))
        if experiment.mocap is not None
        else None
    )
    try:
        if len(args.remote) < len(experiment.agents):  # agents of ours: their code imports now
            launcher.prepare()
        manager.open()
        endpoints = manager.endpoints
        launcher.endpoints = [e for e in endpoints if is_loopback(e)] or endpoints
        if security is not None:
            launcher.credentials = security.write_credentials(
                endpoints,
                remote=args.remote,
                remote_users=[GATEWAY] if args.remote_gateway else [],
            )
        record.entry.endpoints = endpoints
        record.entry.state = "waiting"
        record.write()
        if gateway is not None:
            gateway.endpoints = launcher.endpoints
            if security is not None:
                gateway.credentials = security.folder / f"{GATEWAY}.cred"
            display.log(f"XBee gateway: {gateway.start()}")
        if mocap is not None:
            mocap.endpoints = launcher.endpoints
            if security is not None:
                mocap.credentials = security.folder / f"{MOCAP}.cred"
                mocap.security = security.credentials(VIEWER, launcher.endpoints).security()
            mocap.start()
            mocap.wait_ready()
        launcher.start_all(
            [
                agent_config_for(experiment, n, run_id=run_id)
                for n in experiment.agent_names
                if n not in args.remote
            ]
        )
        display.log(
            f"{experiment.name}: {len(experiment.agents)} agents, {experiment.mode}, "
            f"{experiment.rate_hz:g} Hz, {experiment.duration_s:g} s; run {run_id}; "
            f"bus {', '.join(endpoints)}" + ("" if secure else " (no authentication)")
        )
        for name in args.remote:
            where = launcher.credentials.get(name)
            display.log(
                f"waiting for remote agent {name}"
                + (f": hilswarm agent --credentials {where} ..." if where else "")
            )

        def check() -> None:  # while waiting: agents that fail, and their states for `ps`
            launcher.check()
            states = manager.states_now()
            if any(record.entry.agents.get(name) != state for name, state in states.items()):
                record.entry.agents.update(states)
                record.write()

        manager.wait_for_agents(args.start_timeout, check=check)
        recorder.wait_ready()
        recorder.publish(replace=args.force)  # the run begins: the recording takes its name
        record.entry.state = "running"
        if recorder.live_url:
            display.log("live view: open this in the Foxglove app (Open connection):")
            display.log(recorder.live_url)
        summary = manager.run()
    except (
        ManagerError,
        AgentProcessError,
        RecordingError,
        GatewayProcessError,
        bus.BusConnectionError,
        MocapError,
    ) as exc:
        error = str(exc)
    finally:
        record.entry.state = "stopping"
        with contextlib.suppress(OSError):  # `hilswarm stop`/`set` then say it is ending
            record.write()
        display.finish()
        launcher.stop(told=summary is not None)  # a summary: the manager stopped the agents
        if gateway is not None:
            gateway.stop()
        if mocap is not None:
            mocap.stop()
        manager.close()
        try:
            recorder.close()
        except (RecordingError, OSError) as exc:
            error = error or f"closing the recording failed: {exc}"
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if summary is not None:
        summary.recording = recorder.report()
        print("recording: " + ", ".join(summary.recording.segments))
        print(summary.text())
        frames = describe_frames(mocap.status) if mocap is not None else None
        if frames is not None:
            print(frames)
    else:
        print(f"recording: none ({out} not written: the run did not begin)")
    result = outcome.decide(summary, error=error, interrupted=interrupted)
    print(result.text())
    if error:
        print(f"hilswarm run: {error}", file=sys.stderr)
    return result.code


class _RegistryDisplay:
    """The live status display, also kept in the run's registry entry (``hilswarm ps``)."""

    def __init__(self, display: StatusDisplay, record: RunRecord) -> None:
        self._display = display
        self._record = record

    def update(self, snapshot: StatusSnapshot) -> None:
        self._display.update(snapshot)
        entry = self._record.entry
        entry.tick = snapshot.k
        entry.agents.update(snapshot.states)
        entry.agents.update(dict.fromkeys(snapshot.lost, "lost"))
        if entry.state in ("running", "paused"):
            entry.state = "paused" if snapshot.paused else "running"
        self._record.write()

    def log(self, text: str) -> None:
        self._display.log(text)

    def finish(self) -> None:
        self._display.finish()
