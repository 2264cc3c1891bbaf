"""The gateway process: one per experiment, started by ``hilswarm run`` or ``hilswarm gateway``.

``python -m hilswarm.agents.xbee.gateway_process --connect EP --plan JSON`` opens its own bus
session (principal ``gateway``), starts the simulated coordinator when ``[gateway] port =
"sim"`` (one simulated radio per ``xbee://`` agent, its robot reached through
``agent/<name>/link/robot/{in,out}``), then runs the :class:`~.gateway.Gateway` until SIGTERM /
SIGINT. It prints ``READY <port>`` on stdout once the coordinator answered.

The simulated coordinator takes fault commands on ``gateway/sim`` (JSON, for tests and demos):
``{"out_of_range": "<agent>"}``, ``{"in_range": "<agent>"}``, ``{"unplug": true}``,
``{"replug": true}``.
"""

from __future__ import annotations

import argparse
import json
import logging
import queue
import signal
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from types import FrameType
from typing import Any

from hilswarm.agents import bus
from hilswarm.agents.credentials import add_credentials_arguments, bus_access_from_args
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.link.url import link_scheme
from hilswarm.agents.xbee.air import Air
from hilswarm.agents.xbee.api_frames import FrameFamily
from hilswarm.agents.xbee.config import GatewayConfig, parse_xbee_url
from hilswarm.agents.xbee.gateway import Gateway
from hilswarm.agents.xbee.sim_coordinator import SimCoordinator, SimRemote
from hilswarm.agents.xbee.sim_robot import BusUart

_log = logging.getLogger(__name__)

#: The bus principal (user name) of the gateway process.
PRINCIPAL = "gateway"


@dataclass(frozen=True)
class GatewayPlan:
    """What one gateway process serves.

    Attributes:
        experiment: experiment name (bus key prefix).
        config: ``[gateway]`` settings as a dict (:class:`GatewayConfig` fields).
        robots: agent name -> 64-bit address.
        simulated: agent names whose robot is simulated behind the simulated air.
        rate_hz: the experiment's tick rate [Hz] (broadcast mode gathers a tick's TICKs).
        reply_every: agent name -> m: its robot answers every m-th tick (broadcast mode).
    """

    experiment: str
    config: dict[str, Any]
    robots: dict[str, int]
    simulated: tuple[str, ...] = ()
    rate_hz: float = 20.0
    reply_every: dict[str, int] = field(default_factory=dict)

    def to_json(self) -> str:
        """Serialise (the command line of the process)."""
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> GatewayPlan:
        """Inverse of :meth:`to_json`."""
        data = json.loads(text)
        return cls(
            data["experiment"],
            data["config"],
            {k: int(v) for k, v in data["robots"].items()},
            tuple(data.get("simulated", ())),
            float(data.get("rate_hz", 20.0)),
            {k: int(v) for k, v in data.get("reply_every", {}).items()},
        )


def xbee_links(links: Mapping[str, str | None]) -> dict[str, str]:
    """The agents (name -> link URL) whose link is ``xbee://``."""
    out: dict[str, str] = {}
    for name, link in links.items():
        if link is not None and link_scheme(link) == "xbee":
            out[name] = link
    return out


def plan_for(experiment: Any) -> GatewayPlan | None:
    """The gateway plan of a loaded experiment (``None``: no ``xbee://`` agent)."""
    links = xbee_links({spec.name: spec.link for spec in experiment.agents})
    if not links:
        return None
    config = experiment.gateway or GatewayConfig()
    parsed = {name: parse_xbee_url(url) for name, url in links.items()}
    return GatewayPlan(
        experiment.name,
        asdict(config),
        {name: link.address for name, link in parsed.items()},
        tuple(name for name, link in parsed.items() if link.sim is not None),
        float(experiment.rate_hz),
        {
            spec.name: spec.reply_every
            for spec in experiment.agents
            if spec.name in links and spec.reply_every is not None
        },
    )


def serve(
    plan: GatewayPlan,
    endpoints: Sequence[str],
    stop: threading.Event,
    *,
    run_id: str = "",
    security: bus.SessionSecurity | None = None,
) -> int:
    """Run the gateway of ``plan`` until ``stop`` is set; return the exit status.

    ``run_id`` and ``security``: the run's id and the gateway principal's credentials.
    """
    config = GatewayConfig(**plan.config)
    keys = bus.BusKeys(plan.experiment, run_id)
    try:
        session = bus.open_session(bus.client_config(endpoints, security=security))
    except bus.BusConnectionError as exc:
        sys.stderr.write(f"hilswarm gateway: {exc}\n")
        return 1
    coordinator: SimCoordinator | None = None
    faults: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
    try:
        port_url = None
        if config.simulated:
            remotes = [
                SimRemote(plan.robots[name], BusUart(session, keys, name), node_id=name)
                for name in plan.simulated
            ]
            coordinator = SimCoordinator(
                remotes,
                api_mode=config.api_mode,
                family=FrameFamily(config.family),
                baud=config.baud,
                air=Air(seed=config.seed, default_loss=config.loss),
            ).start()
            port_url = coordinator.url
        if coordinator is not None:
            session.declare_subscriber(
                keys.gateway("sim"), lambda sample: faults.put(sample.payload.to_bytes())
            )
            threading.Thread(
                target=_apply_faults, args=(coordinator, plan, faults), daemon=True
            ).start()
        with Gateway(
            config,
            keys,
            plan.robots,
            session,
            port_url=port_url,
            reply_every=plan.reply_every,
            rate_hz=plan.rate_hz,
        ) as gateway:
            sys.stdout.write(f"READY {gateway.port_url} {gateway.family.value}\n")
            sys.stdout.flush()
            stop.wait()
        return 0
    except HilswarmError as exc:
        _log.debug("the gateway failed: %s", exc)
        sys.stderr.write(f"hilswarm gateway: {exc}\n")
        return 1
    finally:
        faults.put(None)
        if coordinator is not None:
            coordinator.stop()
        session.close()


def _apply_faults(
    coordinator: SimCoordinator, plan: GatewayPlan, commands: queue.SimpleQueue[bytes | None]
) -> None:
    """Apply the fault commands of ``gateway/sim`` (off the bus callback: unplugging blocks)."""
    while (data := commands.get()) is not None:
        try:
            command = json.loads(data)
            if "out_of_range" in command:
                coordinator.set_out_of_range(plan.robots[command["out_of_range"]])
            if "in_range" in command:
                coordinator.set_out_of_range(plan.robots[command["in_range"]], False)
            if command.get("unplug"):
                coordinator.unplug()
            if command.get("replug"):
                coordinator.replug()
        except (ValueError, KeyError, TypeError) as exc:
            _log.warning("gateway/sim: command %r not understood: %s", data[:200], exc)
        else:
            _log.info("gateway/sim: applied %s", data[:200].decode(errors="replace"))


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m hilswarm.agents.xbee.gateway_process``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT")
    add_credentials_arguments(parser)
    parser.add_argument("--plan", required=True, help="GatewayPlan as JSON")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(asctime)s %(levelname)s gateway %(name)s: %(message)s",
    )
    stop = threading.Event()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    endpoints, run_id, security = bus_access_from_args(args)
    return serve(
        GatewayPlan.from_json(args.plan), endpoints, stop, run_id=run_id, security=security
    )


if __name__ == "__main__":
    sys.exit(main())
