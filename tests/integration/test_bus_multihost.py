"""Two machines on a lab network, made on this one: two network namespaces joined by a veth pair.

The orchestrator runs in namespace A and listens on a TLS endpoint of A's address (a CA made
for the run); agent ``d`` runs in namespace B with ``hilswarm agent --credentials FILE`` (the
credentials file copied from A's run folder). The addresses exist only inside the two
namespaces. Needs root (``ip netns``); skipped with the reason otherwise.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hilswarm.agents.credentials import Credentials
from hilswarm.orchestrator.bus_access import agent_user
from swarm_harness import HERE, RunProcess, read_recording, run_env, wait_for, write_toy_experiment

pytestmark = pytest.mark.integration

ADDRESS_A, ADDRESS_B = "10.231.0.1", "10.231.0.2"


def _ip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=False)


@pytest.fixture
def namespaces() -> Iterator[tuple[str, str]]:
    """Namespaces A and B, joined by a veth pair (A: 10.231.0.1/24, B: 10.231.0.2/24)."""
    if shutil.which("ip") is None:
        pytest.skip("network namespaces: the `ip` command is not installed")
    tag = f"hs{os.getpid() % 100000}"
    ns_a, ns_b = f"{tag}a", f"{tag}b"
    probe = _ip("netns", "add", ns_a)
    if probe.returncode != 0:
        pytest.skip(f"network namespaces cannot be made here: {probe.stderr.strip()}")
    try:
        steps = [
            ("netns", "add", ns_b),
            ("link", "add", f"{tag}va", "type", "veth", "peer", "name", f"{tag}vb"),
            ("link", "set", f"{tag}va", "netns", ns_a),
            ("link", "set", f"{tag}vb", "netns", ns_b),
            ("-n", ns_a, "addr", "add", f"{ADDRESS_A}/24", "dev", f"{tag}va"),
            ("-n", ns_b, "addr", "add", f"{ADDRESS_B}/24", "dev", f"{tag}vb"),
            ("-n", ns_a, "link", "set", f"{tag}va", "up"),
            ("-n", ns_b, "link", "set", f"{tag}vb", "up"),
            ("-n", ns_a, "link", "set", "lo", "up"),
            ("-n", ns_b, "link", "set", "lo", "up"),
        ]
        for step in steps:
            done = _ip(*step)
            if done.returncode != 0:
                pytest.skip(f"network namespaces: `ip {' '.join(step)}` failed: {done.stderr}")
        yield ns_a, ns_b
    finally:
        _ip("netns", "del", ns_a)
        _ip("netns", "del", ns_b)


def test_agent_on_another_host_joins_over_tls(tmp_path: Path, namespaces: tuple[str, str]) -> None:
    ns_a, ns_b = namespaces
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=4.0)
    host_a = tmp_path / "host_a"
    host_b = tmp_path / "host_b"
    host_a.mkdir()
    host_b.mkdir()
    run = RunProcess(
        host_a,
        experiment,
        "--no-check",
        "--listen",
        f"tls/{ADDRESS_A}:0",
        "--remote",
        "d",
        netns=ns_a,
    )
    agent: subprocess.Popen[bytes] | None = None
    try:
        entry = run.entry()
        tls = [e for e in entry.endpoints if e.startswith(f"tls/{ADDRESS_A}:")]
        assert tls, entry.endpoints
        # The operator copies d's credentials file to host B (scp keeps it 0600).
        issued = run.registry / entry.run_id / f"{agent_user('d')}.cred"
        copy = host_b / "d.cred"
        copy.write_bytes(issued.read_bytes())
        copy.chmod(0o600)
        credentials = Credentials.read(copy)
        assert credentials.endpoints == tuple(tls) and credentials.ca_pem
        env = run_env(host_b)
        command = [
            *("ip", "netns", "exec", ns_b, sys.executable, "-m", "hilswarm.orchestrator.cli"),
            *("agent", "--credentials", str(copy), "--experiment", str(experiment), "--name", "d"),
        ]
        with (host_b / "agent.log").open("wb") as log:
            agent = subprocess.Popen(
                command,
                env=env,
                cwd=HERE,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        assert run.wait(240) == 0, run.output() + (host_b / "agent.log").read_text()
        wait_for(lambda: agent.poll() is not None, 30, "the remote agent to stop")
        assert agent.returncode == 0, (host_b / "agent.log").read_text()
    finally:
        if agent is not None and agent.poll() is None:
            os.killpg(agent.pid, 9)
            agent.wait(10)
        run.cleanup()
    recording = read_recording(run.out)
    for name in ("a", "b", "c", "d"):
        assert [m["k"] for m in recording[f"/{name}/y"]] == list(range(200)), name


def test_tls_endpoint_refuses_clients_without_the_runs_ca_or_password(
    tmp_path: Path, namespaces: tuple[str, str]
) -> None:
    ns_a, ns_b = namespaces
    experiment = write_toy_experiment(tmp_path / "toy.toml", duration_s=600.0)
    run = RunProcess(
        tmp_path, experiment, "--no-check", "--listen", f"tls/{ADDRESS_A}:0", "--remote", "d",
        netns=ns_a,
    )  # fmt: skip
    try:
        entry = run.entry()
        issued = Credentials.read(run.registry / entry.run_id / f"{agent_user('d')}.cred")
        probe = HERE / "bus_probe.py"
        cases = {
            "no CA": (issued.user, issued.password, ""),
            "wrong password": (issued.user, "wrong", issued.ca_pem or ""),
            "right": (issued.user, issued.password, issued.ca_pem or ""),
        }
        results = {}
        for case, (user, password, ca) in cases.items():
            done = subprocess.run(
                ["ip", "netns", "exec", ns_b, sys.executable, str(probe), issued.endpoints[0]],
                input=f"{user}\n{password}\n{ca}",
                capture_output=True,
                text=True,
                timeout=60,
                env=run_env(tmp_path),
                check=False,
            )
            results[case] = done.stdout.strip() or done.stderr
        assert results == {"no CA": "refused", "wrong password": "refused", "right": "open"}
    finally:
        run.cleanup()
