"""The per-user registry of running experiments (what ``hilswarm ps`` lists).

Every ``hilswarm run`` gets a private folder ``<root>/<run_id>/`` (mode 0700) holding
``run.json`` (its :class:`RunEntry`, rewritten atomically about twice a second with the tick
and each agent's state), the router's user dictionary and the credentials files of the run's
principals. ``<root>`` is ``$XDG_RUNTIME_DIR/hilswarm`` (a per-user, memory-backed folder that
the system empties at logout), else ``<tmp>/hilswarm-<uid>``; it must belong to the user and
have mode 0700, or nothing is written there. The run removes its folder when it ends; a folder
whose orchestrator is gone (killed) is removed by the next listing.

``set``, ``stop`` and ``agent`` find an experiment by name here (:func:`find_run`), so they
need no port and cannot reach another user's or another run's experiment.
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hilswarm.agents.errors import HilswarmError

#: Layout version of ``run.json`` and of ``hilswarm ps --json``.
REGISTRY_VERSION = 1
#: File of a run's entry inside its folder.
ENTRY_FILE = "run.json"


class RegistryError(HilswarmError, RuntimeError):
    """The run registry's folder is unusable (not ours, open to other users)."""


class RunLookupError(HilswarmError, LookupError):
    """No running experiment of that name, or several (the message lists the candidates)."""


@dataclass
class RunEntry:
    """One running experiment, as ``hilswarm ps --json`` reports it.

    Attributes:
        name: experiment name.
        run_id: the run's id (part of every bus key of the run).
        endpoints: the run router's endpoints.
        pid: process id of the orchestrator.
        mode: ``lockstep`` or ``realtime``.
        state: the manager's state (``starting``, ``waiting``, ``running``, ``paused``,
            ``stopping``).
        tick: last tick completed (-1 before the first).
        n_ticks: ticks the run will send.
        agents: agent name -> lifecycle state (``lost`` for a lost agent).
        file: the experiment file.
        out: the recording.
        started: start time (ISO 8601, UTC).
        secure: the bus authenticates and authorizes (``False`` with ``--insecure`` or a
            joined zenohd).
        pid_start: the orchestrator's start time (clock ticks after boot, /proc), so a reused
            pid is not taken for the run.
    """

    name: str
    run_id: str
    endpoints: list[str]
    pid: int
    mode: str
    state: str = "starting"
    tick: int = -1
    n_ticks: int = 0
    agents: dict[str, str] = field(default_factory=dict)
    file: str = ""
    out: str = ""
    started: str = ""
    secure: bool = True
    pid_start: int = 0

    def to_json(self) -> dict[str, Any]:
        """The entry as plain JSON data."""
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> RunEntry:
        """Inverse of :meth:`to_json` (unknown keys are ignored; raises ValueError)."""
        known = {f for f in cls.__dataclass_fields__}
        try:
            return cls(**{k: v for k, v in data.items() if k in known})
        except TypeError as exc:
            raise ValueError(f"bad run entry: {exc}") from None


def registry_root() -> Path:
    """The user's registry folder (created 0700; see the module docstring).

    Raises:
        RegistryError: the folder belongs to someone else or other users can enter it.
    """
    runtime = os.environ.get("XDG_RUNTIME_DIR", "")
    if runtime and os.path.isdir(runtime) and os.stat(runtime).st_uid == os.getuid():
        root = Path(runtime) / "hilswarm"
    else:
        root = Path(tempfile.gettempdir()) / f"hilswarm-{os.getuid()}"
    try:
        root.mkdir(mode=0o700, exist_ok=True)
        info = os.lstat(root)
    except OSError as exc:
        raise RegistryError(f"cannot use the run registry {root}: {exc.strerror}") from None
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid():
        raise RegistryError(f"the run registry {root} is not a folder of yours; remove it")
    if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise RegistryError(
            f"the run registry {root} is open to other users (mode "
            f"{stat.S_IMODE(info.st_mode):o}); run: chmod 700 {root}"
        )
    return root


def process_start(pid: int) -> int:
    """Start time of process ``pid`` [clock ticks after boot] (0: no such process)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return 0
    return int(fields[19]) if fields[0] != "Z" else 0


class RunRecord:
    """The registry folder of the run in this process (created, updated, removed).

    Args:
        entry: the run's entry (``pid`` and ``pid_start`` are filled in here).
        root: the registry folder (default :func:`registry_root`).
    """

    def __init__(self, entry: RunEntry, root: Path | None = None) -> None:
        self.entry = entry
        entry.pid = os.getpid()
        entry.pid_start = process_start(entry.pid)
        self.folder = (root or registry_root()) / entry.run_id
        self.folder.mkdir(mode=0o700)

    def write(self) -> None:
        """Write the entry (atomically: readers never see half a file)."""
        data = json.dumps({"version": REGISTRY_VERSION, **self.entry.to_json()})
        fd, tmp = tempfile.mkstemp(dir=self.folder, prefix=".run.", suffix=".tmp")
        with os.fdopen(fd, "w", encoding="utf-8") as file:
            file.write(data)
        os.replace(tmp, self.folder / ENTRY_FILE)

    def remove(self) -> None:
        """Remove the run's folder (entry and credentials). Idempotent."""
        shutil.rmtree(self.folder, ignore_errors=True)


def list_runs(root: Path | None = None) -> list[RunEntry]:
    """Running experiments of this user, oldest first; entries of dead runs are removed."""
    root = root or registry_root()
    entries: list[RunEntry] = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir()):
        try:
            data = json.loads((folder / ENTRY_FILE).read_text(encoding="utf-8"))
            entry = RunEntry.from_json(data)
        except (OSError, ValueError):
            if _older_than(folder, 60.0):  # a run that died before writing its entry
                shutil.rmtree(folder, ignore_errors=True)
            continue
        if process_start(entry.pid) != entry.pid_start:
            shutil.rmtree(folder, ignore_errors=True)  # stale: its orchestrator is gone
            continue
        entries.append(entry)
    entries.sort(key=lambda e: e.started)
    return entries


def _older_than(path: Path, seconds: float) -> bool:
    try:
        return time.time() - path.stat().st_mtime > seconds
    except OSError:
        return False


def run_folder(entry: RunEntry, root: Path | None = None) -> Path:
    """The private folder of ``entry``'s run (its credentials files are there)."""
    return (root or registry_root()) / entry.run_id


def describe(entries: Sequence[RunEntry]) -> str:
    """``"lead_follow (run 3f9c1a2b, pid 123)"`` for each entry, comma-separated."""
    return ", ".join(f"{e.name} (run {e.run_id}, pid {e.pid})" for e in entries) or "none"


def find_run(name: str, run_id: str | None = None, root: Path | None = None) -> RunEntry:
    """The one running experiment called ``name`` (and whose run id starts with ``run_id``).

    Raises:
        RunLookupError: none or several match; the message lists what is running.
    """
    entries = list_runs(root)
    matches = [e for e in entries if e.name == name]
    if run_id:
        matches = [e for e in matches if e.run_id.startswith(run_id)]
    if len(matches) == 1:
        return matches[0]
    if not matches:
        which = f"{name!r}" + (f" with run id {run_id!r}" if run_id else "")
        raise RunLookupError(
            f"no running experiment {which}; running: {describe(entries)}"
            " (`hilswarm ps` lists them)"
        )
    raise RunLookupError(
        f"{len(matches)} experiments called {name!r} are running: {describe(matches)}; "
        "choose one with --run RUN_ID"
    )
