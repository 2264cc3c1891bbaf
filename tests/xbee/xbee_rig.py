"""What the XBee end-to-end tests share: a swarm behind the real gateway on the simulated
coordinator (real Zenoh sessions on loopback, the protocol-checking Python firmware,
``WireServer`` around ``SimBoard``, behind each radio), the agents' ticks, bounded waits."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import ExitStack
from typing import NamedTuple

import zenoh
from hilswarm.agents import bus
from hilswarm.agents.link.board import PinConfig, TickReply
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.xbee.config import GatewayConfig
from hilswarm.agents.xbee.gateway import Gateway
from hilswarm.agents.xbee.sim_coordinator import SimCoordinator, SimRemote
from hilswarm.agents.xbee.sim_robot import WireServerUart
from hilswarm.agents.xbee.transport import XBeeBoard, board_from_url


class Swarm(NamedTuple):
    """The simulated coordinator, the gateway on it, the agents' boards and the robots."""

    coordinator: SimCoordinator
    gateway: Gateway
    boards: dict[str, XBeeBoard]
    sims: dict[str, SimBoard]


def wait_for(condition: Callable[[], bool], timeout_s: float, what: str) -> None:
    """Poll ``condition`` until it holds; fail after ``timeout_s`` [s] naming ``what``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.01)


def open_swarm(
    stack: ExitStack,
    client_session: Callable[[], zenoh.Session],
    experiment: str,
    addresses: Mapping[str, int],
    config: GatewayConfig,
    *,
    seed: int,
    pins: Sequence[PinConfig],
    sims: Mapping[str, SimBoard] | None = None,
    reply_every: Mapping[str, int] | None = None,
    link_options: str = "timeout_s=0.3&retries=2",
) -> Swarm:
    """Robots (``sims``, default a SimBoard each) behind their radios, the gateway with
    ``config`` on the simulated coordinator, and each agent's ``xbee://`` board opened and
    configured with ``pins``; everything closed by ``stack``."""
    sims = dict(sims or {name: SimBoard(dt=0.05) for name in addresses})
    remotes = [SimRemote(addresses[n], WireServerUart(sims[n]), node_id=n) for n in sims]
    coordinator = stack.enter_context(SimCoordinator(remotes, api_mode=config.api_mode, seed=seed))
    gateway = Gateway(
        config,
        bus.BusKeys(experiment),
        {n: addresses[n] for n in sims},
        client_session(),
        port_url=coordinator.url,
        stats_period_s=0.1,
        reply_every=reply_every,
        rate_hz=20.0,
    )
    stack.enter_context(gateway)
    agent_session = client_session()
    boards = {}
    for name in sims:
        board = board_from_url(
            f"xbee://{addresses[name]:016X}?{link_options}",
            session=agent_session,
            experiment=experiment,
            agent=name,
        )
        stack.callback(board.close)
        board.open()
        board.configure(pins, watchdog_s=2.0)
        boards[name] = board
    return Swarm(coordinator, gateway, boards, sims)


def tick_all(
    boards: Mapping[str, XBeeBoard], writes: Mapping[str, dict[int, int]], reads: Sequence[int]
) -> dict[str, TickReply | BaseException]:
    """Every agent's exchange of one tick at once, as the agents' processes do: its reply, or
    what it raised."""
    out: dict[str, TickReply | BaseException] = {}

    def run(name: str) -> None:
        try:
            out[name] = boards[name].exchange(writes[name], reads)
        except Exception as exc:  # reported to the test
            out[name] = exc

    threads = [threading.Thread(target=run, args=(n,)) for n in writes]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=10.0)
    if len(out) != len(writes):
        raise AssertionError("an exchange did not finish")
    return out
