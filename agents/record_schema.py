"""JSON Schemas of the vector topics of a run recording: entry names and units.

A vector message is ``{"k", "t", "values", <field>: values[i], ...}`` (see
``docs/recording.md``). Its schema describes each named field as ``values[i]`` followed by
the entry's unit in brackets when it has one (``"values[0] [m]"``): Foxglove shows the
description, and :func:`entry_names_units` reads names and units back (``hilswarm plot``).
One place for the rule, used by the writer and the readers.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from typing import Any

#: Keys every vector message has.
BASE_KEYS = ("k", "t", "values")

_DESCRIPTION = re.compile(r"^values\[(\d+)\](?: \[(.*)\])?$")


def entry_description(index: int, unit: str | None = None) -> str:
    """``values[i]``, or ``values[i] [unit]`` when the entry has a unit."""
    return f"values[{index}] [{unit}]" if unit else f"values[{index}]"


def vector_schema(
    topic: str,
    fields: Sequence[str] | None = None,
    units: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The JSON Schema of a vector topic: ``k``, ``t``, ``values`` and the named ``fields``.

    Args:
        topic: the topic (schema title).
        fields: one name per vector entry, or ``None``.
        units: field name -> unit (``{"x": "m"}``); fields without one have no unit.
    """
    units = units or {}
    properties: dict[str, Any] = {
        "k": {"type": "integer", "description": "tick index"},
        "t": {"type": "number", "description": "experiment time [s]"},
        "values": {
            "type": "array",
            "items": {"type": ["number", "null"]},
            "description": "the vector; null marks a non-finite (NaN/inf) entry",
        },
    }
    for index, field in enumerate(fields or ()):
        properties[field] = {
            "type": ["number", "null"],
            "description": entry_description(index, units.get(field)),
        }
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": topic,
        "type": "object",
        "properties": properties,
        "required": list(BASE_KEYS),
    }


def entry_names_units(schema: Mapping[str, Any]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """``(names, units)`` of the entries of a vector topic's schema (``""``: no unit).

    Entries the schema does not name are called ``values[i]``.
    """
    named: dict[int, tuple[str, str]] = {}
    for name, spec in (schema.get("properties") or {}).items():
        description = spec.get("description", "") if isinstance(spec, Mapping) else ""
        match = _DESCRIPTION.match(str(description))
        if match:
            named[int(match.group(1))] = (name, match.group(2) or "")
    width = max(named, default=-1) + 1
    pairs = [named.get(i, (f"values[{i}]", "")) for i in range(width)]
    return tuple(p[0] for p in pairs), tuple(p[1] for p in pairs)


def experiment_log_time_ns(origin_ns: int, t: float) -> int:
    """MCAP log time [ns] of a message at experiment time ``t`` [s] of a run started at
    ``origin_ns`` [ns, wall clock, Unix epoch]: ``origin_ns + t``.

    So the timeline of a recording is the experiment's own: a 60 s lockstep run spans 60 s
    however fast it ran (the wall time of each message is kept in its ``wall_ns`` field).
    A non-finite or negative ``t`` maps to the origin.
    """
    if not t > 0.0 or t == float("inf"):
        return origin_ns
    return origin_ns + round(t * 1e9)
