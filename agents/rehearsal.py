"""The rehearsal: an agent's tick path run on throwaway copies before the agent is armed.

An agent process is forked from the launcher's fork server, so the first ticks of a run pay for
what the process has not done yet: pages shared with the server copied on first write, caches
and Python's specialised bytecode of every function on the tick path warmed. Measured in one
forked agent (Frisbee on ``sim://``, waypoint controller; the tick's own work without the
bus): tick 0 0.55 ms and tick 1 1.1 ms against 0.06 ms from tick 10 on; after a rehearsal in
the same process 0.05 and 0.2 ms. With every agent of a swarm due at once on a few cores, that
start-up cost is what made the first ticks of large realtime swarms late (docs/running.md,
"The rehearsal").

:func:`rehearse` builds a second agent from the same configuration, never on the bus, and runs
its tick work for a few ticks with made-up neighbour outputs: the same functions, other
objects. The experiment's own vehicle, board, controller, random generators and telemetry are
never touched, so a run computes exactly what it computes without the rehearsal.

Only what the project ships runs in a rehearsal (:func:`can_rehearse`): a registry vehicle on a
``sim://`` board (or one that needs no board) with a registry controller. A user's own classes
may have effects outside their objects (files, global state, hardware), and a real board link
must never see made-up ticks, so those agents go without it.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
from hilswarm.agents import bus
from hilswarm.agents.agent_config import AgentConfig, build_hardware
from hilswarm.agents.lifecycle import AgentLifecycle
from hilswarm.agents.link.url import link_scheme
from hilswarm.agents.registry import CONTROLLERS, VEHICLES

logger = logging.getLogger(__name__)

#: Ticks a rehearsal runs: Python specialises a function's bytecode after a few calls, and
#: from about tick 8 a rehearsed path costs what it costs in the steady state.
REHEARSAL_TICKS = 10
#: Lifecycle events that take an offline agent from ``starting`` to ``running``.
_TO_RUNNING = ("connect", "configure", "arm", "start")


class OfflineAgent(Protocol):
    """What a rehearsal uses of an agent (:class:`~hilswarm.agents.agent.Agent`)."""

    hardware: Any
    lifecycle: AgentLifecycle

    def use_hardware(self, hardware: Any) -> None: ...

    def receive_neighbour(self, name: str, payload: bytes) -> None: ...

    def tick_work(self, k: int, t: float) -> Any: ...


def can_rehearse(config: AgentConfig) -> bool:
    """Whether :func:`rehearse` may run for ``config``: a registry vehicle on ``sim://`` (or
    with no board) and a registry controller; never a user's class or a real link."""
    if config.vehicle not in VEHICLES or config.controller not in CONTROLLERS:
        return False
    if not config.link:
        return True
    return link_scheme(config.link) == "sim"


def rehearse(
    make_agent: Callable[[AgentConfig, Sequence[str]], OfflineAgent],
    config: AgentConfig,
    ticks: int = REHEARSAL_TICKS,
) -> float | None:
    """Run ``ticks`` ticks of a throwaway agent built from ``config``; return the wall time
    it took [s], or ``None`` when ``config`` may not be rehearsed (:func:`can_rehearse`).

    Args:
        make_agent: builds an agent from ``(config, endpoints)`` without connecting it (the
            agent class).
        config: the agent's configuration. The copy gets no mocap section (its poses come from
            its own simulated plant), is never connected to the bus, and its lifecycle tells
            nobody (no log lines, no status).
        ticks: how many ticks (tick 0 senses only, as in a run).

    A failure inside the rehearsal (a controller refusing the made-up inputs) ends it early
    and is logged at debug level: it is never the run's failure.
    """
    if not can_rehearse(config):
        return None
    started = time.perf_counter()
    copy = dataclasses.replace(config, mocap=None)
    hardware = None
    try:
        agent = make_agent(copy, ())
        agent.lifecycle = AgentLifecycle()  # quiet: the run's log shows the run's agent only
        hardware = build_hardware(copy, prepare_calibration=False)
        agent.use_hardware(hardware)
        for event in _TO_RUNNING:
            agent.lifecycle.send(event)
        values = np.zeros(int(hardware.vehicle.n_outputs))
        dt = copy.dt
        for k in range(ticks):
            if k > 0:
                for name in copy.neighbours:
                    agent.receive_neighbour(name, bus.encode_vector(k - 1, (k - 1) * dt, values))
            agent.tick_work(k, k * dt)
            if agent.lifecycle.state_id != "running":
                break  # gone safe: the rest of the path is not the run's
    except Exception as exc:  # a warm-up's failure is never the run's
        logger.debug("%s: rehearsal ended early: %s: %s", config.name, type(exc).__name__, exc)
    finally:
        if hardware is not None and hardware.board is not None:
            hardware.board.close()
    return time.perf_counter() - started
