"""A principal's credentials for one run's bus, in a file only its owner can read.

``hilswarm run`` makes fresh credentials per run and principal (each agent, the operator) and
writes one file per principal (JSON, mode 0600, in the run's 0700 folder of the run registry):
the run it belongs to, the endpoints of the run's router, the user name and password the
router accepts (Zenoh ``transport/auth/usrpwd``), and the run's CA certificate when the router
has TLS endpoints. Agents get the *path* on their command line, never the secret itself; for
another machine the file is copied there (``hilswarm agent --credentials FILE``).

File layout (``version`` 1)::

    {"version": 1, "experiment": "lead_follow", "run_id": "3f9c1a2b", "user": "agent.f1",
     "password": "...", "endpoints": ["tcp/127.0.0.1:40321"], "ca_pem": null}
"""

from __future__ import annotations

import argparse
import json
import os
import stat
from dataclasses import asdict, dataclass
from pathlib import Path

from hilswarm.agents import bus
from hilswarm.agents.errors import HilswarmError

#: Layout version of a credentials file.
CREDENTIALS_VERSION = 1


def write_private(path: Path, text: str) -> Path:
    """Write ``text`` to ``path`` with mode 0600: created so (never readable by others, not
    even for a moment), then renamed into place (readers never see half a file)."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as file:
        file.write(text)
    os.replace(tmp, path)
    return path


class CredentialsError(HilswarmError, ValueError):
    """A credentials file is missing, malformed, or readable by other users."""


@dataclass(frozen=True)
class Credentials:
    """One principal's credentials for one run.

    Attributes:
        experiment: experiment name.
        run_id: the run's id (part of every key of the run).
        user: Zenoh user name (``agent.<name>``, ``operator``, ...).
        password: its password (random, per run).
        endpoints: the run router's endpoints (``tcp/...`` on this host, ``tls/...``).
        ca_pem: the run's CA certificate (PEM), for ``tls/`` endpoints; ``None``: no TLS.
    """

    experiment: str
    run_id: str
    user: str
    password: str
    endpoints: tuple[str, ...]
    ca_pem: str | None = None

    def security(self) -> bus.SessionSecurity:
        """The :class:`~hilswarm.agents.bus.SessionSecurity` of a client session."""
        return bus.SessionSecurity(user=self.user, password=self.password, ca_pem=self.ca_pem)

    def write(self, path: Path) -> Path:
        """Write to ``path`` with mode 0600 (see :func:`write_private`)."""
        data = {"version": CREDENTIALS_VERSION, **asdict(self), "endpoints": list(self.endpoints)}
        return write_private(path, json.dumps(data))

    @classmethod
    def read(cls, path: Path) -> Credentials:
        """Read a credentials file; refuse one that other users could read.

        Raises:
            CredentialsError: missing, readable by group/others, or malformed.
        """
        try:
            mode = path.stat().st_mode
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise CredentialsError(f"cannot read credentials {path}: {exc.strerror}") from None
        if mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise CredentialsError(
                f"credentials {path} are readable by other users (mode {stat.S_IMODE(mode):o}); "
                f"run: chmod 600 {path}"
            )
        try:
            data = json.loads(text)
            if data.get("version") != CREDENTIALS_VERSION:
                raise ValueError(f"version {data.get('version')!r}, expected 1")
            return cls(
                experiment=str(data["experiment"]),
                run_id=str(data["run_id"]),
                user=str(data["user"]),
                password=str(data["password"]),
                endpoints=tuple(str(e) for e in data["endpoints"]),
                ca_pem=data.get("ca_pem"),
            )
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise CredentialsError(f"credentials {path} are malformed: {exc}") from None


def add_credentials_arguments(parser: argparse.ArgumentParser) -> None:
    """``--credentials FILE`` and ``--run-id`` of a process the orchestrator starts (its
    ``--connect`` endpoints default to the file's)."""
    parser.add_argument("--credentials", type=Path, help="this process's credentials (0600)")
    parser.add_argument("--run-id", default="", help="the run's id (without --credentials)")


def bus_access_from_args(
    args: argparse.Namespace,
) -> tuple[list[str], str, bus.SessionSecurity | None]:
    """``(endpoints, run_id, security)`` from ``--connect`` and :func:`add_credentials_arguments`.

    Raises:
        CredentialsError: the credentials file is unreadable, open to others, or malformed.
    """
    credentials = Credentials.read(args.credentials) if args.credentials else None
    if credentials is None:
        return list(args.connect), args.run_id, None
    endpoints = list(args.connect) or list(credentials.endpoints)
    return endpoints, credentials.run_id, credentials.security()
