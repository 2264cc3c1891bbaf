"""Value types of ``hilswarm`` options (argparse ``type=``): a bad value is a usage error.

Argparse reports what these raise as ``hilswarm CMD: error: argument --OPTION: <message>`` and
exits with status 2 (bad input), before anything starts. Each rule lives in one place: a range
here, an endpoint's syntax in :func:`hilswarm.agents.bus.check_endpoint`.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def positive_number(*, most: float | None = None) -> Callable[[str], float]:
    """A ``type=`` for a finite number > 0 (and <= ``most`` when given): durations, timeouts,
    rates."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not math.isfinite(value) or value <= 0 or (most is not None and value > most):
            bound = f"0 < value <= {most:g}" if most is not None else "a number > 0"
            raise argparse.ArgumentTypeError(f"{text} is out of range; expected {bound}")
        return value

    parse.__name__ = "positive number"
    return parse


#: A finite number > 0.
positive_float = positive_number()


def positive_int(text: str) -> int:
    """A ``type=`` for an integer >= 1 (counts)."""
    try:
        value = int(text, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{value} is out of range; expected an integer >= 1")
    return value


def endpoint(text: str) -> str:
    """A ``type=`` for a Zenoh endpoint (``--connect``, ``--listen``)."""
    from hilswarm.agents import bus  # noqa: PLC0415 - Zenoh only for commands that use the bus

    try:
        return bus.check_endpoint(text)
    except bus.BusEndpointError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
