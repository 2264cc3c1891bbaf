"""One real agent (in this process, on its own threads) on a real Zenoh router, driven by a
small stand-in for the instance manager: it sends ticks and control commands and records the
agent's y messages, status messages and liveliness. For fault tests that need to reach the
agent's board (mute or stop the simulator, stop a socket board server) while the agent runs.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import zenoh
from hilswarm.agents import bus
from hilswarm.agents.agent import MANAGER_NAME, Agent, AgentConfig, AgentHardware
from hilswarm.agents.control import ControlModel
from swarm_harness import wait_for
from swarm_toys import ToyCart, ToyDrive

DT = 0.02


def cart_config(*, link: str = "socket://test", name: str = "cart") -> AgentConfig:
    """A one-agent experiment: the toy cart driven forward."""
    return AgentConfig(
        experiment="rig",
        name=name,
        agent_names=(name,),
        neighbours=(),
        vehicle="swarm_toys:ToyCart",
        link=link,
        controller="swarm_toys:ToyDrive",
        dt=DT,
        lockstep_window=1,
    )


def cart_hardware(board: Any, *, watchdog_s: float = 0.0) -> Callable[..., AgentHardware]:
    """A hardware factory: the toy cart on ``board`` (opened and configured by the cart)."""

    def build(config: AgentConfig, **_bus: Any) -> AgentHardware:
        vehicle = ToyCart(name=config.name, dt=config.dt)
        vehicle.connect(board, watchdog_s=watchdog_s)
        model = ControlModel(ToyDrive(), dt=config.dt, n_inputs=2, n_outputs=1)
        return AgentHardware(vehicle=vehicle, board=board, model=model)

    return build


class Rig:
    """The router, the stand-in manager and the agent (see the module docstring)."""

    def __init__(self, config: AgentConfig, hardware: Callable[..., AgentHardware]) -> None:
        self.config = config
        self.keys = bus.BusKeys(config.experiment)
        self.router = bus.open_session(bus.listen_config([bus.loopback_endpoint(0)]))
        (endpoint,) = bus.bound_endpoints(self.router)  # the free port the router bound
        self.lock = threading.Lock()
        self.ys: list[int] = []
        self.statuses: list[dict[str, Any]] = []
        self.liveliness: list[str] = []
        name = config.name
        self._entities = [
            self.router.declare_subscriber(
                self.keys.y(name), zenoh.handlers.Callback(self._on_y, indirect=False)
            ),
            self.router.declare_subscriber(
                self.keys.status(name), zenoh.handlers.Callback(self._on_status, indirect=False)
            ),
            self.router.liveliness().declare_subscriber(
                self.keys.alive(name), zenoh.handlers.Callback(self._on_alive, indirect=False)
            ),
            self.router.liveliness().declare_token(self.keys.alive(MANAGER_NAME)),
        ]
        self.tick_pub = self.router.declare_publisher(self.keys.tick, **bus.TICK_PATH_QOS)
        self.agent = Agent(config, [endpoint], hardware_factory=hardware, startup_timeout_s=30)
        self.exit_status: list[int] = []
        self.thread = threading.Thread(
            target=lambda: self.exit_status.append(self.agent.run()), daemon=True
        )
        self.thread.start()
        wait_for(lambda: self.state() == "armed", 30, "the agent to arm")

    def _on_y(self, sample: zenoh.Sample) -> None:
        k, _t, _values = bus.decode_vector(sample.payload.to_bytes())
        with self.lock:
            self.ys.append(k)

    def _on_status(self, sample: zenoh.Sample) -> None:
        message = bus.decode_json(sample.payload.to_bytes())
        with self.lock:
            self.statuses.append(message)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.liveliness.append("PUT" if sample.kind == zenoh.SampleKind.PUT else "DELETE")

    def state(self) -> str:
        """The state of the agent's last status message."""
        with self.lock:
            return str(self.statuses[-1]["state"]) if self.statuses else ""

    def states(self) -> list[str]:
        """Every state the agent reported, in order, repeats removed."""
        with self.lock:
            seen = [str(m["state"]) for m in self.statuses]
        return [s for i, s in enumerate(seen) if i == 0 or seen[i - 1] != s]

    def answered(self) -> list[int]:
        with self.lock:
            return list(self.ys)

    def tick(self, k: int, *, realtime: bool = False) -> None:
        """Release tick ``k``."""
        self.tick_pub.put(bus.encode_tick(bus.TickMessage(k, k * DT, realtime=realtime)))

    def run_ticks(self, first: int, last: int, timeout_s: float = 30.0) -> None:
        """Lockstep: release each tick once the previous one is answered."""
        for k in range(first, last + 1):
            self.tick(k)
            wait_for(lambda k=k: k in self.answered(), timeout_s, f"the answer to tick {k}")

    def control(self, command: bus.ControlCommand, reason: str = "test") -> None:
        self.router.put(
            self.keys.control,
            bus.encode_control(command, reason=reason),
            priority=zenoh.Priority.REAL_TIME,
        )

    def close(self) -> int | None:
        """Stop the agent (bounded) and the router; the agent's exit status if it ended."""
        if self.thread.is_alive():
            self.control(bus.ControlCommand.STOP, "rig closed")
            self.thread.join(15)
        self._entities.clear()
        self.router.close()
        return self.exit_status[0] if self.exit_status else None
