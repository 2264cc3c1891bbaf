"""Which running experiment a command (``set``, ``stop``, ``agent``) talks to, and as whom.

By default the experiment is found by name in the user's run registry
(:mod:`hilswarm.orchestrator.run_registry`); its entry gives the run id and the router's
endpoints, and the run's folder the principal's credentials. ``--credentials FILE`` (a copied
credentials file, e.g. on another machine) names the run by itself. ``--connect`` overrides
the endpoints (a run that joined a ``zenohd`` without authentication).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from hilswarm.agents import bus
from hilswarm.agents.credentials import Credentials
from hilswarm.orchestrator.cli_types import endpoint
from hilswarm.orchestrator.run_registry import (
    RunEntry,
    RunLookupError,
    find_run,
    list_runs,
    run_folder,
)


@dataclass(frozen=True)
class RunTarget:
    """A running experiment, as one principal reaches it.

    Attributes:
        keys: the run's keys (experiment and run id).
        endpoints: where its router listens.
        security: the principal's credentials (``None``: the bus needs none).
        entry: its registry entry (``None`` when named by a credentials file).
    """

    keys: bus.BusKeys
    endpoints: tuple[str, ...]
    security: bus.SessionSecurity | None
    entry: RunEntry | None = None

    def describe(self) -> str:
        """``"lead_follow (run 3f9c1a2b)"``."""
        return f"{self.keys.experiment} (run {self.keys.run_id})"

    def ended(self) -> str:
        """Why the run is no longer there to talk to, read afresh from the run registry:
        ``"has stopped"`` (its entry is gone) or ``"is stopping"``; ``""`` while it runs, or
        when the registry cannot tell (a target named by a credentials file)."""
        if self.entry is None:
            return ""
        try:
            now = {e.run_id: e for e in list_runs()}.get(self.entry.run_id)
        except OSError:
            return ""
        if now is None:
            return "has stopped"
        return "is stopping" if now.state == "stopping" else ""


def add_target_arguments(parser: argparse.ArgumentParser) -> None:
    """``--run``, ``--credentials`` and ``--connect`` (shared by set, stop and agent)."""
    parser.add_argument(
        "--run",
        metavar="RUN_ID",
        help="which run, when several experiments of that name run (`hilswarm ps`)",
    )
    parser.add_argument(
        "--credentials",
        type=Path,
        metavar="FILE",
        help="a credentials file of the run (e.g. copied to another machine)",
    )
    parser.add_argument(
        "--connect",
        action="append",
        type=endpoint,
        default=[],
        metavar="ENDPOINT",
        help="bus endpoint (default: the run's own, from the run registry)",
    )


def find_target(
    name: str,
    user: str,
    *,
    run_id: str | None = None,
    credentials: Path | None = None,
    connect: list[str] | None = None,
) -> RunTarget:
    """The running experiment ``name`` as principal ``user`` reaches it.

    Raises:
        RunLookupError: no such experiment running, or several (the message lists them).
        CredentialsError: the credentials file is unreadable or open to other users.
    """
    if credentials is not None:
        creds = Credentials.read(credentials)
        if creds.experiment != name:
            raise RunLookupError(
                f"credentials {credentials} are for experiment {creds.experiment!r}, not {name!r}"
            )
        endpoints = tuple(connect or creds.endpoints)
        return RunTarget(bus.BusKeys(name, creds.run_id), endpoints, creds.security())
    entry = find_run(name, run_id)
    keys = bus.BusKeys(entry.name, entry.run_id)
    security = None
    endpoints = tuple(connect or entry.endpoints)
    if entry.secure:
        creds = Credentials.read(run_folder(entry) / f"{user}.cred")
        security = creds.security()
        endpoints = tuple(connect or creds.endpoints)
    return RunTarget(keys, endpoints, security, entry)


def target_from_args(args: argparse.Namespace, name: str, user: str) -> RunTarget:
    """:func:`find_target` with the arguments of :func:`add_target_arguments`."""
    return find_target(
        name, user, run_id=args.run, credentials=args.credentials, connect=args.connect
    )
