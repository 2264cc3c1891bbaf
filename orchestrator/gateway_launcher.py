"""Starts the experiment's XBee gateway process and makes sure it is gone when the run ends.

``hilswarm run`` starts one when any agent's link is ``xbee://...``, before the agents, and
waits for its ``READY`` line (the coordinator answered), so that the agents' first HELLO finds
the radio. The process runs in its own process group, like the agents.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.xbee.gateway_process import GatewayPlan

#: How long the gateway may take to open the coordinator and answer [s].
START_TIMEOUT_S = 20.0


class GatewayProcessError(HilswarmError, RuntimeError):
    """The gateway process did not start (coordinator missing, bus unreachable) or died."""


class GatewayLauncher:
    """One gateway process for ``plan``, connected to ``endpoints``.

    ``run_id``: the run's id; ``credentials``: the gateway principal's credentials file (its
    path goes on the command line, never the secret).
    """

    def __init__(
        self,
        plan: GatewayPlan,
        endpoints: Sequence[str],
        *,
        run_id: str = "",
        credentials: Path | None = None,
        verbose: int = 0,
    ) -> None:
        self.plan = plan
        self.endpoints = list(endpoints)
        self.run_id = run_id
        self.credentials = credentials
        self.verbose = verbose
        self.process: subprocess.Popen[bytes] | None = None
        self.ready_line = ""

    def command(self) -> list[str]:
        """The command line of the gateway process."""
        command = [sys.executable, "-m", "hilswarm.agents.xbee.gateway_process"]
        for endpoint in self.endpoints:
            command += ["--connect", endpoint]
        if self.credentials is not None:
            command += ["--credentials", str(self.credentials)]
        elif self.run_id:
            command += ["--run-id", self.run_id]
        return [*command, "--plan", self.plan.to_json(), *["-v"] * self.verbose]

    def start(self, timeout_s: float = START_TIMEOUT_S) -> str:
        """Start it and wait for ``READY``; return that line. Raises GatewayProcessError."""
        self.process = subprocess.Popen(
            self.command(),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        stdout = self.process.stdout
        if stdout is None:
            raise GatewayProcessError("the gateway process has no stdout")
        deadline = time.monotonic() + timeout_s
        buffer = b""
        while b"\n" not in buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.stop()
                raise GatewayProcessError(f"the XBee gateway did not start within {timeout_s} s")
            ready, _, _ = select.select([stdout], [], [], min(remaining, 0.2))
            if ready:
                chunk = os.read(stdout.fileno(), 4096)
                if not chunk:
                    code = self.process.wait(timeout=5)
                    self.process = None
                    raise GatewayProcessError(
                        f"the XBee gateway exited with status {code} before it was ready "
                        "(see its message above)"
                    )
                buffer += chunk
        self.ready_line = buffer.split(b"\n", 1)[0].decode(errors="replace").strip()
        return self.ready_line

    def check(self) -> None:
        """Raise GatewayProcessError if the process has exited."""
        if self.process is not None and (code := self.process.poll()) is not None:
            raise GatewayProcessError(f"the XBee gateway process exited with status {code}")

    def stop(self, *, term_s: float = 5.0) -> int | None:
        """SIGTERM its process group, then SIGKILL after ``term_s``; return its status."""
        process, self.process = self.process, None
        if process is None:
            return None
        for sig, wait_s in ((signal.SIGTERM, term_s), (signal.SIGKILL, 3.0)):
            if process.poll() is not None:
                break
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(process.pid, sig)
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(timeout=wait_s)
        if process.stdout is not None:
            process.stdout.close()
        return process.poll()
