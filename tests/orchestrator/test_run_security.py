"""Run registry, credentials files, access-control rules and session configurations."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.agents import bus
from hilswarm.agents.credentials import Credentials, CredentialsError
from hilswarm.orchestrator.bus_access import (
    OPERATOR,
    VIEWER,
    VIEWER_GRANTS,
    access_control,
    agent_user,
    run_grants,
)
from hilswarm.orchestrator.run_registry import (
    RegistryError,
    RunEntry,
    RunLookupError,
    RunRecord,
    find_run,
    list_runs,
    registry_root,
)
from hilswarm.orchestrator.run_security import RunSecurity, is_loopback, make_tls


def test_keys_carry_the_run_id() -> None:
    keys = bus.BusKeys("lead_follow", "3f9c1a2b")
    assert keys.tick == "hilswarm/lead_follow/3f9c1a2b/tick"
    assert keys.y("f1") == "hilswarm/lead_follow/3f9c1a2b/agent/f1/y"
    assert keys.manager_request == "hilswarm/lead_follow/3f9c1a2b/manager/request"
    assert bus.BusKeys("lead_follow").tick == "hilswarm/lead_follow/tick"
    with pytest.raises(bus.BusKeyError):
        bus.BusKeys("lead_follow", "a/b")


def test_every_session_config_turns_scouting_off_and_carries_its_security() -> None:
    security = bus.SessionSecurity(user="agent.a", password="pw", ca_pem="-----CA-----")
    config = bus.client_config(["tls/10.0.0.1:7447"], security=security)
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("scouting/gossip/enabled")) is False
    usrpwd = json.loads(config.get_json("transport/auth/usrpwd"))
    assert (usrpwd["user"], usrpwd["password"]) == ("agent.a", "pw")
    # (the CA goes in as root_ca_certificate_base64, which get_json does not show; the TLS
    # tests in tests/integration/test_bus_multihost.py use it for real)
    router = bus.listen_config([bus.loopback_endpoint()])
    assert json.loads(router.get_json("listen/endpoints")) == ["tcp/127.0.0.1:0"]
    assert json.loads(router.get_json("scouting/multicast/enabled")) is False


def test_router_binds_a_free_port_and_reports_it() -> None:
    with bus.open_session(bus.listen_config([bus.loopback_endpoint(0)])) as router:
        (endpoint,) = bus.bound_endpoints(router)
    assert endpoint.startswith("tcp/127.0.0.1:") and not endpoint.endswith(":0")


def test_refused_session_is_explained_without_zenoh_text() -> None:
    with bus.open_session(bus.listen_config([bus.loopback_endpoint(0)])) as router:
        (endpoint,) = bus.bound_endpoints(router)
        security = bus.SessionSecurity(user="nobody", password="x")
        # The router has no user dictionary: plain sessions are fine; a closed port is not.
    with pytest.raises(bus.BusConnectionError) as raised:
        bus.open_session(bus.client_config([endpoint], security=security))
    message = str(raised.value)
    assert "nothing answers there" in message and "orchestrator.rs" not in message


def test_agent_may_hear_exactly_its_neighbours() -> None:
    keys = bus.BusKeys("toy", "r1")
    grants = run_grants({"a": ("b",), "b": ("c",), "c": ("a",)}, extra={VIEWER: VIEWER_GRANTS})
    assert set(grants) == {"agent.a", "agent.b", "agent.c", OPERATOR, VIEWER}
    acl = access_control(keys, grants)
    assert acl["default_permission"] == "deny" and acl["enabled"] is True
    rules = {rule["id"]: rule for rule in acl["rules"]}
    subscribe = rules["agent.a/subscribe/0"]
    assert subscribe["messages"] == ["declare_subscriber"] and subscribe["flows"] == ["ingress"]
    assert subscribe["key_exprs"] == [
        "hilswarm/toy/r1/tick",
        "hilswarm/toy/r1/control",
        "hilswarm/toy/r1/agent/b/y",
        "hilswarm/toy/r1/agent/a/link/rx",  # its own board behind the XBee gateway
        "hilswarm/toy/r1/agent/a/link/robot/in",
    ]
    assert rules["agent.a/put/0"]["key_exprs"] == ["hilswarm/toy/r1/agent/a/**"]
    assert rules["agent.a/tokens/0"]["key_exprs"] == ["hilswarm/toy/r1/alive/a"]
    every_put = [r for r in acl["rules"] if "put" in r["messages"] and "ingress" in r["flows"]]
    assert not any(k.endswith(("/tick", "/control")) for r in every_put for k in r["key_exprs"])
    policies = {p["id"]: p for p in acl["policies"]}
    assert {s["id"]: s["usernames"] for s in acl["subjects"]}["agent.a"] == ["agent.a"]
    assert all(r.startswith("agent.a/") for r in policies["agent.a"]["rules"])


def test_credentials_files_are_private_and_refused_when_not(tmp_path: Path) -> None:
    credentials = Credentials("toy", "r1", "agent.a", "secret", ("tcp/127.0.0.1:4000",))
    path = credentials.write(tmp_path / "a.cred")
    assert path.stat().st_mode & 0o777 == 0o600
    assert Credentials.read(path) == credentials
    path.chmod(0o644)
    with pytest.raises(CredentialsError, match="readable by other users"):
        Credentials.read(path)
    path.chmod(0o600)
    path.write_text("{not json")
    with pytest.raises(CredentialsError, match="malformed"):
        Credentials.read(path)


def test_run_security_writes_private_files_and_a_tls_ca(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    folder.mkdir(mode=0o700)
    grants = run_grants({"a": ("b",), "b": ()})
    security = RunSecurity(
        bus.BusKeys("toy", "r1"), grants, folder, listen=["tcp/127.0.0.1:0", "tls/0.0.0.0:0"]
    )
    endpoints = ["tcp/127.0.0.1:4100", "tls/10.0.0.5:4101"]
    files = security.write_credentials(endpoints, remote=["b"])
    assert set(files) == {"a", "b"}
    a, b = Credentials.read(files["a"]), Credentials.read(files["b"])
    assert a.endpoints == ("tcp/127.0.0.1:4100",) and b.endpoints == ("tls/10.0.0.5:4101",)
    assert a.password != b.password and a.ca_pem and a.ca_pem == b.ca_pem
    for path in folder.iterdir():
        assert path.stat().st_mode & 0o077 == 0, path
    dictionary = (folder / "users.txt").read_text().splitlines()
    assert f"{agent_user('a')}:{a.password}" in dictionary
    router = security.router()
    assert router.access_control and router.certificate_pem and router.private_key_pem
    assert is_loopback("tcp/127.0.0.1:1") and not is_loopback("tls/127.0.0.1:1")


def test_tls_certificate_names_the_host() -> None:
    from cryptography import x509

    material = make_tls(["10.0.0.5", "hostA.lab"])
    certificate = x509.load_pem_x509_certificate(material.certificate_pem.encode())
    names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "hostA.lab" in names.get_values_for_type(x509.DNSName)
    assert [str(a) for a in names.get_values_for_type(x509.IPAddress)] == ["10.0.0.5"]


def _entry(name: str, run_id: str) -> RunEntry:
    return RunEntry(name=name, run_id=run_id, endpoints=["tcp/127.0.0.1:1"], pid=0, mode="x")


def test_registry_finds_runs_by_name_and_cleans_stale_ones(tmp_path: Path) -> None:
    root = tmp_path / "registry"
    root.mkdir(mode=0o700)
    one = RunRecord(_entry("toy", "aaaa1111"), root)
    one.write()
    two = RunRecord(_entry("toy", "bbbb2222"), root)
    two.write()
    assert (root / "aaaa1111").stat().st_mode & 0o777 == 0o700
    assert {e.run_id for e in list_runs(root)} == {"aaaa1111", "bbbb2222"}
    with pytest.raises(RunLookupError, match=r"2 experiments called 'toy'.*--run"):
        find_run("toy", root=root)
    assert find_run("toy", "bbbb", root=root).run_id == "bbbb2222"
    with pytest.raises(RunLookupError, match=r"no running experiment 'other'.*aaaa1111"):
        find_run("other", root=root)
    # A run whose orchestrator is gone (another pid) disappears from the registry.
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    two.entry.pid = dead.pid
    two.write()
    assert [e.run_id for e in list_runs(root)] == ["aaaa1111"]
    assert not (root / "bbbb2222").exists()
    one.remove()
    assert list_runs(root) == []


def test_registry_root_must_be_private(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    runtime = tmp_path / "xdg"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(runtime))
    root = registry_root()
    assert root == runtime / "hilswarm" and root.stat().st_mode & 0o777 == 0o700
    os.chmod(root, 0o755)
    with pytest.raises(RegistryError, match="open to other users"):
        registry_root()
