"""A fork server for agent processes: the agent code is imported once, then each agent is forked.

Starting an agent with ``python -m hilswarm.agents.agent`` costs a Python start-up and the
import of numpy, scipy, zenoh and the vehicle code: about 0.5 s of CPU per agent, so 32 agents
on two cores need seconds before the first tick. The fork server (:class:`ForkServer`) is one
process started by the launcher that imports that code once (``preload``), before any Zenoh
session exists, and then forks one child per agent on request. Each child is still its own OS
process, in its own session and process group, with stdin and stdout on ``/dev/null``; it sets
its process title (``hilswarm.agents.agent --name NAME ...``) so ``ps`` shows which agent it is,
and runs the module's ``main(argv)`` exactly as ``python -m`` would.

A Zenoh session must never be open in a process that forks: its runtime threads do not survive
a fork. The server never opens one; it only imports.

Protocol between the launcher (:class:`ForkServer`) and the server (``python -m
hilswarm.agents.spawner``), one JSON object per line:

* launcher -> server: ``{"module": M, "argv": [...], "title": T, "path": [...]}``: fork a
  child running ``M.main(argv)``, with the folders ``path`` (optional) first on its
  ``sys.path`` and ``PYTHONPATH`` (the experiment's folder, for a user's classes: the server
  can then start before the experiment is known); the server answers ``{"pid": P}`` (or
  ``{"error": "..."}``);
* server -> launcher: ``{"ready": true}`` once, when its preload imports are done (before
  it reads any request); ``{"exit": P, "code": C}`` when child ``P`` ended (``C`` as
  :attr:`subprocess.Popen.returncode`: negative for a signal).

A request may be sent before ``ready``: the server reads it after its imports. The launcher
waits for ``ready`` up to :data:`READY_TIMEOUT_S` (the imports read and compile the agent
code: ~1 s of CPU on a 2-core development machine, seconds more when its disk cache went cold,
and a benchmark's first fork once waited over 10 s for them), then for each answer up to
:data:`SPAWN_TIMEOUT_S`; a server that exits during its imports (a module that fails to
import) is reported at once.

The launcher's ends are :class:`ForkedProcess` objects with the part of
:class:`subprocess.Popen`'s interface the launcher uses (``pid``, ``returncode``, ``poll``,
``wait``, ``send_signal``, ``terminate``, ``kill``).
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import queue
import select
import signal
import subprocess
import sys
import threading
import traceback
from collections.abc import Mapping, Sequence
from typing import IO, Any

import setproctitle
from hilswarm.agents import registry
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.timed_queue import get_within

logger = logging.getLogger(__name__)

__all__ = ["ForkServer", "ForkedProcess", "SpawnError", "main", "with_import_paths"]


def agent_preload() -> tuple[str, ...]:
    """Modules imported by the server before it forks: the agent and every library class."""
    tables = (registry.VEHICLES, registry.CONTROLLERS, registry.PLANTS)
    modules = {path.partition(":")[0] for table in tables for path in table.values()}
    # Imported lazily by agents on simulated links (no pose source of their own): every
    # simulated Frisbee and blimp would otherwise import it after its fork.
    lazy = ("hilswarm.agents.sim.mocap",)
    return ("hilswarm.agents.agent", *sorted(modules), *lazy)


def with_import_paths(pythonpath: str, folders: Sequence[str]) -> str:
    """A ``PYTHONPATH`` value with ``folders`` first, then the entries of ``pythonpath``."""
    inherited = [p for p in pythonpath.split(os.pathsep) if p]
    return os.pathsep.join([*folders, *inherited])


#: Bound on the server's answer to one request once it is ready [s].
SPAWN_TIMEOUT_S = 10.0
#: Bound on the server's preload imports, before its first answer [s].
READY_TIMEOUT_S = 120.0
#: Exit code reported for a child whose status was lost with the server.
UNKNOWN_EXIT = 255


class SpawnError(HilswarmError, OSError):
    """The fork server could not start a process (or is gone)."""


class ForkedProcess:
    """A process forked by the :class:`ForkServer` (a :class:`subprocess.Popen` look-alike).

    Args:
        pid: the child's process id.
        server: the server that reports its exit.
    """

    def __init__(self, pid: int, server: ForkServer) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self._server = server
        self._ended = threading.Event()

    def _set_exit(self, code: int) -> None:
        if self.returncode is None:
            self.returncode = code
        self._ended.set()

    def poll(self) -> int | None:
        """The exit code once the process has ended, else ``None``."""
        if self.returncode is None and self._server.gone:
            self._check_orphan()
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        """Wait until the process ends; raises :class:`subprocess.TimeoutExpired`."""
        if self._server.gone:
            self._check_orphan()
        if not self._ended.wait(timeout):
            raise subprocess.TimeoutExpired(f"agent process {self.pid}", timeout or 0.0)
        return self.returncode if self.returncode is not None else UNKNOWN_EXIT

    def _check_orphan(self) -> None:
        """The server is gone: the exit status is lost, but whether the process lives is not."""
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            self._set_exit(UNKNOWN_EXIT)
        except PermissionError:
            pass

    def send_signal(self, signum: int) -> None:
        """Send ``signum`` to the process (nothing once it has ended)."""
        if self.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, signum)

    def terminate(self) -> None:
        """SIGTERM."""
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        """SIGKILL."""
        self.send_signal(signal.SIGKILL)


class ForkServer:
    """The launcher's side of the fork server (see the module docstring).

    Args:
        python: the interpreter that runs the server.
        env: the server's environment, inherited by every child.
        preload: modules imported before the first fork.
    """

    def __init__(
        self,
        *,
        python: str = sys.executable,
        env: Mapping[str, str] | None = None,
        preload: Sequence[str] | None = None,
    ) -> None:
        self.gone = False
        self._lock = threading.Lock()
        self._replies: queue.SimpleQueue[ForkedProcess | str] = queue.SimpleQueue()
        self._children: dict[int, ForkedProcess] = {}
        self._early_exits: dict[int, int] = {}
        self._asked = False  # no fork asked for yet: close() may end the server at once
        self._ready = threading.Event()  # imports done (or the server gone: check ``gone``)
        try:
            self._process = subprocess.Popen(
                [python, "-m", "hilswarm.agents.spawner", *(preload or agent_preload())],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                env=dict(env) if env is not None else None,
                start_new_session=True,
            )
        except OSError as exc:
            raise SpawnError(f"cannot start the agent fork server: {exc}") from exc
        self._reader = threading.Thread(
            target=self._read, args=(self._process.stdout,), name="fork-server", daemon=True
        )
        self._reader.start()

    def spawn(
        self, module: str, argv: Sequence[str], *, title: str, path: Sequence[str] = ()
    ) -> ForkedProcess:
        """Fork a child that runs ``module.main(argv)`` with process title ``title`` and the
        folders ``path`` first on its import path."""
        request = json.dumps(
            {"module": module, "argv": list(argv), "title": title, "path": list(path)}
        )
        with self._lock:
            self._asked = True
            if self.gone or self._process.stdin is None:
                raise SpawnError("the agent fork server is gone")
            try:
                self._process.stdin.write(request.encode() + b"\n")
                self._process.stdin.flush()
            except OSError as exc:
                raise SpawnError(f"the agent fork server is gone: {exc}") from exc
            if not self._ready.wait(READY_TIMEOUT_S):
                raise SpawnError(
                    f"the agent fork server did not finish importing the agent code within "
                    f"{READY_TIMEOUT_S:g} s"
                )
            try:
                reply = get_within(self._replies, SPAWN_TIMEOUT_S)
            except queue.Empty:
                raise SpawnError(
                    f"the agent fork server did not answer within {SPAWN_TIMEOUT_S:g} s"
                ) from None
        if isinstance(reply, str):
            raise SpawnError(reply)
        return reply

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the server (its children are not touched: they are the launcher's to stop).

        A server never asked to fork is ended at once (SIGTERM), rather than after its
        imports (~1 s) when it would read the end of its input. Idempotent.
        """
        with self._lock:
            if not self._asked and self._process.poll() is None:
                self._process.terminate()
            if self._process.stdin is not None and not self._process.stdin.closed:
                with contextlib.suppress(OSError):
                    self._process.stdin.close()
        try:
            self._process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        self._reader.join(timeout_s)

    def _read(self, stream: IO[bytes]) -> None:
        """Reader thread: replies to the request queue, exits to their processes."""
        for line in stream:
            try:
                message = json.loads(line)
            except ValueError:
                logger.warning("fork server: unreadable line %r", line[:80])
                continue
            if "ready" in message:
                self._ready.set()
            elif "pid" in message:
                child = ForkedProcess(int(message["pid"]), self)
                self._children[child.pid] = child
                if child.pid in self._early_exits:
                    child._set_exit(self._early_exits.pop(child.pid))
                self._replies.put(child)
            elif "error" in message:
                self._replies.put(str(message["error"]))
            elif "exit" in message:
                pid, code = int(message["exit"]), int(message["code"])
                if pid in self._children:
                    self._children[pid]._set_exit(code)
                else:
                    self._early_exits[pid] = code
        self.gone = True
        self._replies.put("the agent fork server exited")
        self._ready.set()  # a spawn waiting for the imports finds the exit in its replies
        for child in list(self._children.values()):
            child._check_orphan()


# ---------------------------------------------------------------------------------------------
# The server process
# ---------------------------------------------------------------------------------------------


def _run_child(request: Mapping[str, Any], keep: Sequence[int]) -> int:
    """In the forked child: detach, then run ``module.main(argv)``; returns its exit code."""
    os.setsid()
    signal.set_wakeup_fd(-1)
    for signum in (signal.SIGCHLD, signal.SIGINT, signal.SIGTERM, signal.SIGPIPE):
        signal.signal(signum, signal.SIG_DFL)
    for fd in keep:
        with contextlib.suppress(OSError):
            os.close(fd)
    null = os.open(os.devnull, os.O_RDWR)
    os.dup2(null, 0)
    os.dup2(null, 1)
    os.close(null)
    sys.stdin = open(0, closefd=False)  # noqa: SIM115 - the process's own stdin, never closed
    sys.stdout = open(1, "w", closefd=False)  # noqa: SIM115
    setproctitle.setproctitle(str(request["title"]))
    folders = [str(folder) for folder in request.get("path", ())]
    if folders:  # as the PYTHONPATH of an agent started with ``python -m``
        sys.path[:0] = folders
        os.environ["PYTHONPATH"] = with_import_paths(os.environ.get("PYTHONPATH", ""), folders)
    argv = [str(a) for a in request["argv"]]
    sys.argv = [str(request["module"]), *argv]
    try:
        return int(importlib.import_module(str(request["module"])).main(argv) or 0)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 1
    except BaseException:  # the child's last word: its traceback on stderr, then exit 1
        traceback.print_exc()
        return 1


def _exit_code(status: int) -> int:
    """A wait status as :attr:`subprocess.Popen.returncode`."""
    return os.waitstatus_to_exitcode(status)


def serve(preload: Sequence[str]) -> int:
    """The server loop: fork on each request line, report each child's exit."""
    out = sys.stdout.buffer

    def send(message: Mapping[str, Any]) -> None:
        out.write(json.dumps(message).encode() + b"\n")
        out.flush()

    for module in preload:
        importlib.import_module(module)
    send({"ready": True})
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the launcher stops the server (stdin EOF)
    buffer = b""
    open_input = True
    while open_input:
        readable, _, _ = select.select([0, wake_r], [], [])
        if wake_r in readable:
            with contextlib.suppress(BlockingIOError):
                os.read(wake_r, 512)
        while True:  # reap every ended child
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            send({"exit": pid, "code": _exit_code(status)})
        if 0 not in readable:
            continue
        chunk = os.read(0, 65536)
        if not chunk:
            open_input = False
        buffer += chunk
        *lines, buffer = buffer.split(b"\n")
        for line in lines:
            try:
                request = json.loads(line)
                pid = os.fork()
            except (ValueError, OSError) as exc:
                send({"error": f"cannot fork an agent: {exc}"})
                continue
            if pid == 0:
                code = 1
                try:
                    code = _run_child(request, keep=(wake_r, wake_w))
                finally:
                    with contextlib.suppress(Exception):
                        sys.stdout.flush()
                        sys.stderr.flush()
                    os._exit(code)
            send({"pid": pid})
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m hilswarm.agents.spawner [PRELOAD_MODULE ...]``: the fork server."""
    return serve(list(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
