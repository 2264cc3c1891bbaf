"""Starts one OS process per agent and guarantees they are gone when the run ends.

Each agent runs ``hilswarm.agents.agent --connect ENDPOINT --credentials FILE --config JSON``
(the credentials file, mode 0600, holds its password; the command line only its path) in its
own process and process group (a new session), so a Ctrl-C at the terminal reaches only the
orchestrator, which then stops the agents in order (safe mode first). By default the agents
are forked by a fork server that imported the agent code once (:mod:`hilswarm.agents.spawner`:
start-up in milliseconds instead of ~0.5 s of CPU per agent); ``start_method="exec"`` starts
each with ``python -m hilswarm.agents.agent`` instead. :meth:`AgentLauncher.stop` — called on
every exit path, also from ``__exit__`` — waits for agents that were told to stop, then sends
SIGTERM to every remaining process group and finally SIGKILL, each step with a timeout.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType

from hilswarm.agents.agent import AgentConfig
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.spawner import ForkedProcess, ForkServer, SpawnError, with_import_paths
from hilswarm.orchestrator.experiment import Experiment

logger = logging.getLogger(__name__)


class AgentProcessError(HilswarmError, RuntimeError):
    """An agent process exited while the run needed it (start-up failure, crash)."""


def agent_config_for(
    experiment: Experiment,
    name: str,
    *,
    mocap_noise_std_m: float = 0.0,
    mocap_noise_std_rad: float = 0.0,
    run_id: str = "",
) -> AgentConfig:
    """The :class:`AgentConfig` of agent ``name`` of ``experiment`` (links as overridden)."""
    spec = experiment.agent(name)
    return AgentConfig(
        experiment=experiment.name,
        name=spec.name,
        agent_names=experiment.agent_names,
        neighbours=experiment.neighbours(name),
        vehicle=spec.vehicle,
        link=spec.link,
        controller=spec.controller,
        dt=experiment.dt,
        params=dict(spec.params),
        vehicle_params=dict(spec.vehicle_params),
        pinout={device: dict(roles) for device, roles in spec.pinout.items()},
        initial_state=tuple(float(v) for v in spec.initial_state),
        calibration=str(spec.calibration) if spec.calibration else None,
        watchdog_s=experiment.watchdog_s,
        lockstep_window=experiment.lockstep_window,
        seed=experiment.seed,
        mocap_noise_std_m=mocap_noise_std_m,
        mocap_noise_std_rad=mocap_noise_std_rad,
        run_id=run_id,
        mocap=experiment.mocap.to_dict() if experiment.mocap is not None else None,
        mocap_body=spec.body if experiment.mocap is not None else None,
        mocap_neighbours=(
            {n: experiment.agent(n).body for n in experiment.neighbours(name)}
            if experiment.mocap is not None
            else {}
        ),
    )


class AgentLauncher:
    """Starts and supervises agent processes.

    Args:
        endpoints: Zenoh endpoints the agents connect to.
        python: interpreter to run agents with.
        env: extra environment variables for the agents.
        import_paths: folders put first on the agents' ``PYTHONPATH`` (the experiment file's
            folder, so user vehicles/controllers named ``"module:Class"`` beside it import).
        verbose: agent log verbosity (0 warnings, 1 info, 2 debug).
        credentials: agent name -> its credentials file (``None``: the bus needs none).
        start_method: ``"fork"`` (the fork server, default) or ``"exec"`` (a new interpreter
            per agent).
        fork_server: a fork server already started (``hilswarm run`` starts one before it
            imports its own modules, so both import at once); it must have been started with
            this launcher's ``env``. The launcher owns it from here: :meth:`stop` closes it.
    """

    def __init__(
        self,
        endpoints: Sequence[str],
        *,
        python: str = sys.executable,
        env: Mapping[str, str] | None = None,
        import_paths: Sequence[str | Path] = (),
        verbose: int = 0,
        credentials: Mapping[str, Path] | None = None,
        start_method: str = "fork",
        fork_server: ForkServer | None = None,
    ) -> None:
        if start_method not in ("fork", "exec"):
            raise ValueError(f"start_method must be 'fork' or 'exec', got {start_method!r}")
        self.start_method = start_method
        self._fork_server = fork_server if start_method == "fork" else None
        self.endpoints = list(endpoints)
        self.credentials = dict(credentials or {})
        self.python = python
        self.env = {**os.environ, **(env or {})}
        #: Folders first on every agent's import path: with ``python -m`` in its PYTHONPATH,
        #: with the fork server in each fork request (the server's own environment is
        #: ``env``, so it can start before the experiment is known).
        self.import_paths = [str(Path(p).resolve()) for p in import_paths]
        if fork_server is not None and start_method != "fork":
            fork_server.close()
        self.verbose = verbose
        self.processes: dict[str, subprocess.Popen[bytes] | ForkedProcess] = {}

    def arguments(self, config: AgentConfig) -> list[str]:
        """The arguments of ``hilswarm.agents.agent`` that start ``config``'s agent."""
        arguments = []
        for endpoint in self.endpoints:
            arguments += ["--connect", endpoint]
        if config.name in self.credentials:
            arguments += ["--credentials", str(self.credentials[config.name])]
        arguments += ["--config", config.to_json()]
        arguments += ["-v"] * self.verbose
        return arguments

    def command(self, config: AgentConfig) -> list[str]:
        """The command line that starts ``config``'s agent in a new interpreter."""
        return [self.python, "-m", "hilswarm.agents.agent", *self.arguments(config)]

    def _exec_env(self) -> dict[str, str]:
        """The environment of an agent started with ``python -m``: ``env`` and the import
        paths first on its PYTHONPATH."""
        env = dict(self.env)
        if self.import_paths:
            env["PYTHONPATH"] = with_import_paths(env.get("PYTHONPATH", ""), self.import_paths)
        return env

    def prepare(self) -> None:
        """Start the fork server now (``start_method="fork"``; nothing otherwise).

        The server imports the agent code (~1 s of CPU) while the caller goes on: ``hilswarm
        run`` calls this before it opens the bus and writes the credentials, so that work and
        the import overlap. :meth:`start` calls it too; a fork request waits for the import.

        Raises:
            AgentProcessError: the server process cannot be started.
        """
        if self.start_method == "fork":
            self._server()

    def _server(self) -> ForkServer:
        if self._fork_server is None:
            try:
                self._fork_server = ForkServer(python=self.python, env=self.env)
            except SpawnError as exc:
                raise AgentProcessError(f"cannot start agents: {exc}") from exc
        return self._fork_server

    def start(self, config: AgentConfig) -> subprocess.Popen[bytes] | ForkedProcess:
        """Start ``config``'s agent in its own process group."""
        if config.name in self.processes:
            raise AgentProcessError(f"agent {config.name!r} was already started")
        if self.start_method == "fork":
            server = self._server()
            title = f"hilswarm.agents.agent --name {config.name} --experiment {config.experiment}"
            try:
                process: subprocess.Popen[bytes] | ForkedProcess = server.spawn(
                    "hilswarm.agents.agent",
                    self.arguments(config),
                    title=title,
                    path=self.import_paths,
                )
            except SpawnError as exc:
                raise AgentProcessError(f"cannot start agent {config.name!r}: {exc}") from exc
        else:
            process = subprocess.Popen(
                self.command(config),
                env=self._exec_env(),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                start_new_session=True,
            )
        self.processes[config.name] = process
        logger.info("started agent %s (pid %d)", config.name, process.pid)
        return process

    def start_all(self, configs: Sequence[AgentConfig]) -> None:
        """Start every agent of ``configs``."""
        for config in configs:
            self.start(config)

    def exited(self) -> dict[str, int]:
        """Agents whose process has exited, with their exit status."""
        return {
            name: code
            for name, process in self.processes.items()
            if (code := process.poll()) is not None
        }

    def describe(self, name: str) -> str:
        """What agent ``name``'s process is doing, for a loss report ("" when not started here).

        A process that is still running while its bus session dropped is hung (stopped,
        deadlocked) or starved: on an overloaded machine its link lease ran out.
        """
        process = self.processes.get(name)
        if process is None:
            return ""
        code = process.poll()
        if code is None:
            return "its process is still running (hung, or starved on an overloaded machine)"
        if code < 0:
            return f"its process was killed by {_signal_name(-code)}"
        return f"its process exited with status {code}"

    def check(self) -> None:
        """Raise :class:`AgentProcessError` if any agent process has exited."""
        exited = self.exited()
        if exited:
            described = ", ".join(f"{name} (exit status {code})" for name, code in exited.items())
            raise AgentProcessError(f"agent process exited: {described}; see its log above")

    def stop(
        self, *, grace_s: float = 5.0, term_s: float = 3.0, told: bool = True
    ) -> dict[str, int | None]:
        """Make sure every agent process is gone; returns exit statuses (None: unkillable).

        Waits up to ``grace_s`` for processes to exit by themselves (they were told to stop
        on the bus), then SIGTERMs the process groups of the rest and waits ``term_s``, then
        SIGKILLs what is left. A stopped (SIGSTOP) process is continued so it can die.
        ``told=False``: nobody told them on the bus (the run never began, or ended before its
        stop command): SIGTERM, an agent's own stop request, goes to every one at once,
        without a grace period and without a warning.
        """
        if not told:
            grace_s = 0.0
        codes: dict[str, int | None] = {}
        for name, process in self.processes.items():
            codes[name] = _wait(process, grace_s)
            grace_s = 0.2 if codes[name] is None else grace_s  # do not wait n * grace_s
        for name, process in self.processes.items():
            if codes[name] is None:
                if told:
                    logger.warning("agent %s did not exit; sending SIGTERM", name)
                else:
                    logger.info("agent %s: not told to stop on the bus; sending SIGTERM", name)
                _signal_group(process, signal.SIGTERM)
                _signal_group(process, signal.SIGCONT)
        for name, process in self.processes.items():
            if codes[name] is None:
                codes[name] = _wait(process, term_s)
                term_s = 0.2 if codes[name] is None else term_s
        for name, process in self.processes.items():
            if codes[name] is None:
                logger.warning("agent %s ignored SIGTERM; sending SIGKILL", name)
                _signal_group(process, signal.SIGKILL)
                codes[name] = _wait(process, 5.0)
        # Children of an agent (e.g. the simavr harness) share its group: kill leftovers.
        for process in self.processes.values():
            _signal_group(process, signal.SIGKILL)
        if self._fork_server is not None:
            self._fork_server.close()
            self._fork_server = None
        return codes

    def __enter__(self) -> AgentLauncher:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop(grace_s=0.5 if exc_type is not None else 5.0)


def _wait(process: subprocess.Popen[bytes] | ForkedProcess, timeout_s: float) -> int | None:
    try:
        return process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None


def _signal_group(process: subprocess.Popen[bytes] | ForkedProcess, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(process.pid, signum)


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"
