"""The mocap simulator as its own process, fed by the agents' simulated plants over the bus.

``python -m hilswarm.agents.mocap.sim_process --connect ENDPOINT --experiment EXP --bodies a,b
--settings JSON`` starts a :class:`~.qtm_sim.QtmSimulator` on a free loopback port, prints
``port <N>`` on its standard output (the orchestrator reads it and points the mocap process
there), subscribes to each body's true pose (``mocap_truth/<body>``: explicit keys; the
callback only stores it) and serves frames until SIGTERM. Killing it is what a mocap server
that disappears looks like to the client.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType
from typing import Any

import zenoh
from hilswarm.agents import bus, bus_callback
from hilswarm.agents.credentials import add_credentials_arguments, bus_access_from_args
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap import message
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.agents.mocap.qtm_sim import QtmSimulator, SimSettings

logger = logging.getLogger(__name__)


def sim_settings(settings: MocapSettings, bodies: Sequence[str], seed: int | None) -> SimSettings:
    """The simulator's settings from ``[mocap]`` / ``[mocap.sim]`` (seed: the experiment's)."""
    cams = settings.sim
    return SimSettings(
        bodies=tuple(bodies),
        rate_hz=settings.rate_hz,
        noise_std_m=cams.noise_std_m,
        noise_std_rad=cams.noise_std_rad,
        latency_s=cams.latency_s,
        dropout_rate=cams.dropout_rate,
        dropout_frames=cams.dropout_frames,
        occlusions=dict(cams.occlusions),
        seed=cams.seed if cams.seed is not None else (seed or 0),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring). Exit status 0 stopped, 2 cannot start."""
    parser = argparse.ArgumentParser(prog="python -m hilswarm.agents.mocap.sim_process")
    parser.add_argument("--connect", action="append", required=True, help="Zenoh endpoint")
    parser.add_argument("--experiment", required=True)
    parser.add_argument("--bodies", required=True, help="comma-separated rigid body names")
    parser.add_argument("--settings", required=True, help="[mocap] as JSON")
    add_credentials_arguments(parser)
    parser.add_argument("--seed", type=int, default=None, help="the experiment's seed")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s mocap-sim: %(message)s")
    stop = threading.Event()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        settings = MocapSettings.from_dict(json.loads(args.settings))
        bodies = [b for b in args.bodies.split(",") if b]
        simulator = QtmSimulator(sim_settings(settings, bodies, args.seed))
        endpoints, run_id, security = bus_access_from_args(args)
        keys = bus.BusKeys(args.experiment, run_id)
        session = bus.open_session(bus.client_config(endpoints, security=security))
    except (ValueError, TypeError, HilswarmError) as exc:
        logger.error("cannot start: %s", exc)
        return 2
    entities: list[Any] = []
    try:
        for body in bodies:

            def on_truth(sample: zenoh.Sample, body: str = body) -> None:
                try:
                    pose, t = message.decode_truth(sample.payload.to_bytes())
                    simulator.set_truth(body, pose, t=t)
                except bus.BusMessageError as exc:
                    logger.warning("body %s: %s", body, exc)

            entities.append(
                session.declare_subscriber(keys.mocap_truth(body), bus_callback.callback(on_truth))
            )
        port = simulator.start()
        sys.stdout.write(f"port {port}\n")
        sys.stdout.flush()
        while not stop.wait(0.2):
            pass
        return 0
    except HilswarmError as exc:
        logger.error("%s", exc)
        return 2
    finally:
        simulator.close()
        entities.clear()
        session.close()


if __name__ == "__main__":
    sys.exit(main())
