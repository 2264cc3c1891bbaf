"""Starts the experiment's mocap process (and, for ``system = "sim"``, the simulator) for a run.

:class:`MocapRunner` is used by ``hilswarm run`` between opening the bus and starting the
agents: :meth:`~MocapRunner.start` launches ``python -m hilswarm.agents.mocap.sim_process``
(sim only; it prints the simulator's port) and ``python -m hilswarm.agents.mocap.process``, and
:meth:`~MocapRunner.wait_ready` waits (bounded) for the mocap process to stream. With a real
system it also waits for every agent's body to be visible and otherwise fails naming the
missing bodies and listing the visible ones (with ``sim`` the bodies appear when the agents'
plants start, and each agent checks its own body). :meth:`~MocapRunner.stop` ends both
processes on every exit path (SIGTERM, then SIGKILL).
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zenoh
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.errors import HilswarmError
from hilswarm.orchestrator.experiment import Experiment

#: Bound on the simulator announcing its port [s].
SIM_START_TIMEOUT_S = 20.0


class MocapError(HilswarmError, RuntimeError):
    """The mocap process could not start, or a body is not visible."""


def describe_status(status: dict[str, Any]) -> str:
    """One line: what the system lists and sees."""
    listed = ", ".join(status.get("listed") or []) or "none"
    visible = ", ".join(status.get("visible") or []) or "none"
    return f"the system lists: {listed}; visible: {visible}"


def describe_frames(status: dict[str, Any]) -> str | None:
    """One line for the run's end: frames the mocap process handled, skipped (it fell behind)
    and, with ``tick_frames_only``, whose poses it published; ``None`` without counts."""
    frames = status.get("frames")
    if not isinstance(frames, int):
        return None
    text = f"mocap: {frames} frames"
    skipped = status.get("frames_skipped")
    if isinstance(skipped, int) and skipped:
        text += f", {skipped} skipped (the mocap process fell behind)"
    published = status.get("frames_published")
    if isinstance(published, int) and published < frames:
        text += f"; poses published for {published} of them (tick_frames_only)"
    return text


class MocapRunner:
    """See the module docstring.

    Args:
        experiment: the experiment (with a ``[mocap]`` section).
        endpoints: Zenoh endpoints of the run's bus.
        run_id: the run's id.
        credentials: the mocap principal's credentials file, handed to both processes by path
            (``None``: the bus needs none).
        security: this runner's own session's credentials (the run's viewer).
        verbose: log verbosity of the mocap process.
    """

    def __init__(
        self,
        experiment: Experiment,
        endpoints: Sequence[str],
        *,
        run_id: str = "",
        credentials: Path | None = None,
        security: bus.SessionSecurity | None = None,
        verbose: int = 0,
    ):
        if experiment.mocap is None:
            raise MocapError(f"experiment {experiment.name!r} has no [mocap] section")
        self.experiment = experiment
        self.settings = experiment.mocap
        self.endpoints = list(endpoints)
        self.run_id = run_id
        self.credentials = credentials
        self.security = security
        self.verbose = verbose
        self.bodies = [spec.body for spec in experiment.agents]
        self.processes: dict[str, subprocess.Popen[bytes]] = {}
        self.status: dict[str, Any] = {}
        self._changed = threading.Condition()
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []

    def _common(self) -> list[str]:
        args = ["--experiment", self.experiment.name, "--bodies", ",".join(self.bodies)]
        for endpoint in self.endpoints:
            args += ["--connect", endpoint]
        if self.credentials is not None:
            args += ["--credentials", str(self.credentials)]
        else:
            args += ["--run-id", self.run_id]
        return [*args, "--settings", json.dumps(self.settings.to_dict())]

    def start(self) -> None:
        """Start the simulator (sim only) and the mocap process; watch the mocap status."""
        self._session = bus.open_session(bus.client_config(self.endpoints, security=self.security))
        self._entities.append(
            self._session.declare_subscriber(
                bus.BusKeys(self.experiment.name, self.run_id).mocap_status,
                bus_callback.callback(self._on_status),
            )
        )
        python = sys.executable
        extra: list[str] = []
        if self.settings.system == "sim":
            seed = [] if self.experiment.seed is None else ["--seed", str(self.experiment.seed)]
            sim = subprocess.Popen(
                [python, "-m", "hilswarm.agents.mocap.sim_process", *self._common(), *seed],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                start_new_session=True,
            )
            self.processes["mocap simulator"] = sim
            extra = ["--port", str(self._read_port(sim))]
        self.processes["mocap"] = subprocess.Popen(
            [python, "-m", "hilswarm.agents.mocap.process", *self._common(), *extra]
            + ["-v"] * self.verbose,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            start_new_session=True,
        )

    @staticmethod
    def _read_port(process: subprocess.Popen[bytes]) -> int:
        stdout = process.stdout
        if stdout is None:  # pragma: no cover - started with a pipe
            raise MocapError("the mocap simulator has no output pipe")
        deadline = time.monotonic() + SIM_START_TIMEOUT_S
        line = b""
        while not line.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or process.poll() is not None:
                raise MocapError("the mocap simulator did not start (see its log above)")
            ready, _, _ = select.select([stdout], [], [], min(left, 0.2))
            if ready:
                chunk = os.read(stdout.fileno(), 64)
                if not chunk:
                    raise MocapError("the mocap simulator exited during start-up")
                line += chunk
        word, _, port = line.decode().strip().partition(" ")
        if word != "port" or not port.isdigit():
            raise MocapError(f"the mocap simulator said {line!r}, expected 'port N'")
        return int(port)

    def _on_status(self, sample: zenoh.Sample) -> None:
        try:
            status = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        with self._changed:
            self.status = status if isinstance(status, dict) else {}
            self._changed.notify_all()

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Wait until the mocap process streams (and, with a real system, sees every body).

        Raises:
            MocapError: it failed, exited, or timed out; a body missing is named, with the
                bodies the system lists and sees.
        """
        timeout = self.settings.start_timeout_s + 5.0 if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        where = f"{self.settings.system} at {self.settings.host}"
        need_bodies = self.settings.system != "sim"
        with self._changed:
            while True:
                status = self.status
                state = status.get("state")
                if state in ("failed", "lost"):
                    raise MocapError(f"mocap {where}: {status.get('detail', state)}")
                if state == "streaming" and (not need_bodies or not status.get("missing")):
                    return
                for name, process in self.processes.items():
                    if process.poll() is not None:
                        raise MocapError(f"the {name} process exited with status {process.poll()}")
                left = deadline - time.monotonic()
                if left <= 0:
                    if state == "streaming":
                        missing = ", ".join(status.get("missing") or [])
                        raise MocapError(
                            f"mocap body not visible: {missing}; {describe_status(status)}"
                        )
                    raise MocapError(f"mocap {where}: no stream after {timeout:g} s")
                self._changed.wait(min(left, 0.2))

    def stop(self, *, term_s: float = 3.0) -> dict[str, int | None]:
        """End both processes (SIGTERM, then SIGKILL); returns their exit statuses."""
        codes: dict[str, int | None] = {}
        for name in ("mocap", "mocap simulator"):
            process = self.processes.get(name)
            if process is None:
                continue
            if process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGTERM)
            try:
                codes[name] = process.wait(timeout=term_s)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, signal.SIGKILL)
                codes[name] = process.wait(timeout=5.0)
            if process.stdout is not None:
                process.stdout.close()
        self._entities.clear()
        if self._session is not None:
            self._session.close()
            self._session = None
        return codes
