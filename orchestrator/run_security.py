"""Per-run secrets: user/password credentials for every principal, and a per-run TLS CA.

:class:`RunSecurity` is made fresh by every ``hilswarm run``. It holds, in memory, a random
password per principal (each agent, the operator, the router itself) and, when the router has
``tls/`` endpoints, a CA made for this run only (``cryptography``: a well-kept library rather
than hand-made crypto) with the router's certificate signed by it. It writes into the run's
folder (0700, see :mod:`hilswarm.orchestrator.run_registry`):

* ``users.txt`` (0600): the ``user:password`` dictionary the router accepts;
* ``<user>.cred`` (0600): one :class:`~hilswarm.agents.credentials.Credentials` file per
  principal, which agents get by path and operators' commands read.

The router's private key never touches the disk.
"""

from __future__ import annotations

import contextlib
import datetime
import ipaddress
import secrets
import socket
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from hilswarm.agents import bus
from hilswarm.agents.credentials import Credentials, write_private
from hilswarm.agents.link.url import link_scheme
from hilswarm.orchestrator.bus_access import (
    GATEWAY,
    GATEWAY_GRANTS,
    MOCAP,
    MOCAP_GRANTS,
    VIEWER,
    VIEWER_GRANTS,
    Grants,
    access_control,
    agent_user,
    run_grants,
)
from hilswarm.orchestrator.experiment import Experiment

#: User name of the router itself (it makes no outgoing connection; Zenoh wants one).
ROUTER_USER = "router"
#: Validity of the run's certificates [days] (a run longer than this needs a new run).
CERTIFICATE_DAYS = 30


@dataclass(frozen=True)
class TlsMaterial:
    """The run's CA certificate and the router's certificate and key (all PEM)."""

    ca_pem: str
    certificate_pem: str
    private_key_pem: str


def make_tls(names: Iterable[str]) -> TlsMaterial:
    """A fresh CA and a router certificate for host ``names`` (DNS names or IP addresses).

    Elliptic-curve P-256 keys; the CA signs only this certificate (its key is dropped here),
    so a certificate that verifies against it is this run's router.
    """
    from cryptography import x509  # noqa: PLC0415 - only runs with TLS endpoints pay for it
    from cryptography.hazmat.primitives import hashes, serialization  # noqa: PLC0415
    from cryptography.hazmat.primitives.asymmetric import ec  # noqa: PLC0415
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID  # noqa: PLC0415

    now = datetime.datetime.now(datetime.UTC)
    start, end = now - datetime.timedelta(minutes=5), now + datetime.timedelta(CERTIFICATE_DAYS)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "hilswarm run CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                crl_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .sign(ca_key, hashes.SHA256())
    )
    alt_names: list[x509.GeneralName] = []
    for name in dict.fromkeys(names):
        try:
            alt_names.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alt_names.append(x509.DNSName(name))
    key = ec.generate_private_key(ec.SECP256R1())
    certificate = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "hilswarm router")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.SubjectAlternativeName(alt_names), critical=False)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    pem = serialization.Encoding.PEM
    return TlsMaterial(
        ca_pem=ca.public_bytes(pem).decode(),
        certificate_pem=certificate.public_bytes(pem).decode(),
        private_key_pem=key.private_bytes(
            pem, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        ).decode(),
    )


def host_names(listen: Sequence[str]) -> list[str]:
    """Names a router listening on ``listen`` is reached by: the endpoints' own hosts (when
    not a wildcard address), this host's name, its addresses, and loopback."""
    names: list[str] = []
    for endpoint in listen:
        host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
        if host and host not in ("0.0.0.0", "::"):
            names.append(host)
    hostname = socket.gethostname()
    names += [hostname, socket.getfqdn(), "localhost", "127.0.0.1", "::1"]
    with contextlib.suppress(OSError):
        names += [str(info[4][0]) for info in socket.getaddrinfo(hostname, None)]
    return list(dict.fromkeys(n for n in names if n))


class RunSecurity:
    """The secrets of one run (see the module docstring).

    Args:
        keys: the run's keys (experiment and run id).
        grants: user name -> what it may do (:func:`~hilswarm.orchestrator.bus_access.run_grants`).
        folder: the run's private folder (mode 0700), where the files go.
        listen: the router's endpoints; any ``tls/`` one makes the run's CA.
        tls_names: more names the router is reached by (put in its certificate).
    """

    def __init__(
        self,
        keys: bus.BusKeys,
        grants: Mapping[str, Grants],
        folder: Path,
        *,
        listen: Sequence[str],
        tls_names: Sequence[str] = (),
    ) -> None:
        self.keys = keys
        self.grants = dict(grants)
        self.folder = folder
        self.passwords = {user: secrets.token_urlsafe(24) for user in (ROUTER_USER, *grants)}
        self.tls: TlsMaterial | None = None
        if any(endpoint.startswith("tls/") for endpoint in listen):
            self.tls = make_tls([*host_names(listen), *tls_names])
        self._dictionary = write_private(
            folder / "users.txt",
            "".join(f"{u}:{p}\n" for u, p in self.passwords.items() if u != ROUTER_USER),
        )

    @classmethod
    def for_experiment(
        cls,
        experiment: Experiment,
        run_id: str,
        folder: Path,
        *,
        listen: Sequence[str],
        tls_names: Sequence[str] = (),
        extra: Mapping[str, Grants] | None = None,
    ) -> RunSecurity:
        """The security of a run of ``experiment``: a principal per agent (its row of the
        adjacency matrix), the operator, the viewer, the XBee gateway when an agent links
        through ``xbee://``, the mocap processes with ``[mocap]``, and ``extra`` ones."""
        others: dict[str, Grants] = {VIEWER: VIEWER_GRANTS}
        if any(spec.link and link_scheme(spec.link) == "xbee" for spec in experiment.agents):
            others[GATEWAY] = GATEWAY_GRANTS
        bodies = None
        if experiment.mocap is not None:
            others[MOCAP] = MOCAP_GRANTS
            bodies = {spec.name: spec.body for spec in experiment.agents}
        grants = run_grants(
            {name: experiment.neighbours(name) for name in experiment.agent_names},
            extra={**others, **(extra or {})},
            bodies=bodies,
        )
        keys = bus.BusKeys(experiment.name, run_id)
        return cls(keys, grants, folder, listen=listen, tls_names=tls_names)

    def router(self) -> bus.SessionSecurity:
        """The router's security: accepted users, its TLS certificate, access control."""
        return bus.SessionSecurity(
            user=ROUTER_USER,
            password=self.passwords[ROUTER_USER],
            user_dictionary=str(self._dictionary),
            certificate_pem=self.tls.certificate_pem if self.tls else None,
            private_key_pem=self.tls.private_key_pem if self.tls else None,
            access_control=access_control(self.keys, self.grants),
        )

    def credentials(self, user: str, endpoints: Sequence[str]) -> Credentials:
        """``user``'s credentials for the router at ``endpoints``."""
        return Credentials(
            experiment=self.keys.experiment,
            run_id=self.keys.run_id,
            user=user,
            password=self.passwords[user],
            endpoints=tuple(endpoints),
            ca_pem=self.tls.ca_pem if self.tls else None,
        )

    def write_credentials(
        self,
        endpoints: Sequence[str],
        *,
        remote: Sequence[str] = (),
        remote_users: Sequence[str] = (),
    ) -> dict[str, Path]:
        """Write every principal's credentials file; returns agent name -> its file.

        Args:
            endpoints: the router's bound endpoints. Processes on this host get the loopback
                ones; those on other machines the others (TLS).
            remote: names of agents that join from other machines.
            remote_users: other principals that join from other machines (``gateway``).
        """
        local = [e for e in endpoints if is_loopback(e)] or list(endpoints)
        other = [e for e in endpoints if not is_loopback(e)] or list(endpoints)
        remotes = {agent_user(name) for name in remote} | set(remote_users)
        files = {
            user: self.credentials(user, other if user in remotes else local).write(
                self.folder / f"{user}.cred"
            )
            for user in self.grants
        }
        return {
            user.removeprefix("agent."): path
            for user, path in files.items()
            if user.startswith("agent.")
        }


def is_loopback(endpoint: str) -> bool:
    """True for a ``tcp/`` endpoint on this host's loopback address."""
    return endpoint.startswith(("tcp/127.0.0.1:", "tcp/[::1]:"))
