"""Every hilswarm process runs Zenoh on its own lean runtime (bus.LEAN_RUNTIME), unless the
user set ``ZENOH_RUNTIME`` themselves."""

from __future__ import annotations

import os
import subprocess
import sys

from hilswarm.agents import bus

#: Opens a router and a client of it through bus.open_session; prints the process's threads.
_PROBE = """
import os
from hilswarm.agents import bus
router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
client = bus.open_session(bus.client_config(bus.bound_endpoints(router)))
client.put("probe", b"x")  # some traffic: every pool in use
tasks = os.listdir("/proc/self/task")
names = sorted(open(f"/proc/self/task/{t}/comm").read().strip() for t in tasks)
print(os.environ.get("ZENOH_RUNTIME", ""))
print(" ".join(names))
client.close()
router.close()
"""


def _probe(runtime: str | None) -> tuple[str, list[str]]:
    env = {key: value for key, value in os.environ.items() if key != "ZENOH_RUNTIME"}
    if runtime is not None:
        env["ZENOH_RUNTIME"] = runtime
    result = subprocess.run(
        [sys.executable, "-c", _PROBE],
        check=False,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stderr
    setting, threads = result.stdout.strip().splitlines()[-2:]
    return setting, threads.split()


def test_sessions_run_on_the_lean_runtime_by_default() -> None:
    setting, threads = _probe(None)
    assert setting == bus.LEAN_RUNTIME
    pools = {name.split("-")[0] for name in threads if "-" in name}
    assert "app" in pools, threads
    assert pools <= {"app", "tx"}, threads  # rx, acc and net handed over to the app worker


def test_a_users_zenoh_runtime_wins() -> None:
    setting, threads = _probe("()")
    assert setting == "()"
    assert any(name.split("-")[0] in {"acc", "rx", "tx", "net"} for name in threads), threads
