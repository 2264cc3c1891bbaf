"""``hilswarm check`` for experiments with ``xbee://`` links: link URLs and the radio budget.

The budget (:mod:`hilswarm.agents.xbee.budget`) uses each vehicle's pin configuration (every
output written, every input sampled: the largest TICK it can send), the ``[gateway]`` baud and
mode and each agent's ``reply_every``; over 100 % of the tick period is a problem (``check`` and
``run`` refuse the file), over 70 % a warning. In a realtime experiment a tick's latency
through the radio over 80 % of the period is a warning too (late ticks to expect,
:func:`~hilswarm.agents.xbee.budget.latency_messages`). ``reply_every`` belongs to
``xbee://`` agents of a gateway in broadcast mode (unicast answers every TICK: there is nothing
to decimate).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from hilswarm.agents.errors import LinkUrlError
from hilswarm.agents.link.url import link_scheme
from hilswarm.orchestrator.experiment import ExperimentParts
from hilswarm.orchestrator.problems import Problem


def _is_xbee(link: str) -> bool:
    try:
        return link_scheme(link) == "xbee"
    except LinkUrlError:
        return False


def check_gateway(
    experiment: ExperimentParts,
    vehicles: Mapping[str, Any],
    problems: list[Problem],
    warnings: list[Problem],
    *,
    local: bool = True,
) -> None:
    """Add the problems and warnings of ``experiment``'s XBee links and gateway budget (of the
    agents that loaded; the budget when ``[experiment]`` is valid), and, when an agent is on
    an XBee link and the gateway runs here (``local``), its coordinator's port: a device path
    must exist, as an agent's serial link must."""
    from hilswarm.agents.link.serial_board import (  # noqa: PLC0415
        validate_url as validate_serial_url,
    )
    from hilswarm.agents.xbee.api_frames import FrameFamily  # noqa: PLC0415 - xbee files only
    from hilswarm.agents.xbee.budget import (  # noqa: PLC0415
        RobotTraffic,
        budget_for,
        budget_messages,
        latency_messages,
        section_size,
        tick_frame_sizes,
    )
    from hilswarm.agents.xbee.config import GatewayConfig, parse_xbee_url  # noqa: PLC0415

    robots: list[RobotTraffic] = []
    addresses: dict[int, str] = {}
    config = experiment.gateway or GatewayConfig()
    for spec in experiment.agents.values():
        every = getattr(spec, "reply_every", None)
        xbee = spec.link is not None and _is_xbee(spec.link)
        if every is not None and not xbee:
            problems.append(
                Problem(
                    experiment.path,
                    f"agents.{spec.name}.reply_every",
                    "only for xbee:// links (a gateway in broadcast mode decimates replies)",
                )
            )
        elif every is not None and every > 1 and config.mode != "broadcast":
            problems.append(
                Problem(
                    experiment.path,
                    f"agents.{spec.name}.reply_every",
                    f'reply_every = {every} needs [gateway] mode = "broadcast" (by unicast '
                    "every TICK is answered by its robot)",
                )
            )
        if spec.link is None:
            continue
        try:
            if link_scheme(spec.link) != "xbee":
                continue
            link = parse_xbee_url(spec.link)
        except LinkUrlError as exc:
            problems.append(Problem(experiment.path, f"agents.{spec.name}.link", str(exc)))
            continue
        if link.address in addresses:
            problems.append(
                Problem(
                    experiment.path,
                    f"agents.{spec.name}.link",
                    f"XBee address {link.address:016X} is also agent "
                    f"{addresses[link.address]!r}'s; each robot has its own radio",
                )
            )
        addresses[link.address] = spec.name
        vehicle = vehicles.get(spec.name)
        pins = getattr(getattr(vehicle, "pins", None), "pin_configs", None)
        if pins is None:
            continue  # its vehicle did not build: reported elsewhere
        request, reply = tick_frame_sizes(pins())
        robots.append(RobotTraffic(spec.name, request, reply, section_size(pins()), every or 1))
    if addresses and not config.simulated:
        try:
            validate_serial_url(config.port, local=local)
        except LinkUrlError as exc:
            problems.append(Problem(experiment.path, "gateway.port", f"the coordinator: {exc}"))
    if not robots or experiment.settings is None:
        return
    budget = budget_for(
        [robots[i] for i in sorted(range(len(robots)), key=lambda i: robots[i].name)],
        mode=config.mode,
        rate_hz=experiment.settings.rate_hz,
        baud=config.baud,
        family=FrameFamily(config.family),
    )
    errors, notes = budget_messages(budget)
    if experiment.settings.mode == "realtime":  # a lockstep tick has no deadline
        notes += latency_messages(budget, answer=config.answer)
    problems += [Problem(experiment.path, "gateway", message) for message in errors]
    warnings += [Problem(experiment.path, "gateway", message) for message in notes]
