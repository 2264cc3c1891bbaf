"""Calibration as a recorded artefact: the calibration a run used, as JSON for the MCAP.

A run's recording should say which calibration turned controller inputs into PWM, so that a
plot of ``/<agent>/u`` can be traced back to duty cycles later. :func:`calibration_as_json`
gives a JSON-ready dict; the recorder writes it once per agent (topic ``/<agent>/calibration``,
at ``k = 0``) beside ``/experiment``.
"""

from __future__ import annotations

from typing import Any

from hilswarm.agents.calibration import Calibration

#: MCAP topic suffix under which a run records an agent's calibration.
TOPIC_SUFFIX = "calibration"

#: JSON Schema of the message (for ``McapJsonWriter.add_topic``-style schema registration).
SCHEMA: dict[str, Any] = {
    "type": "object",
    "properties": {
        "vehicle_id": {"type": "string"},
        "date": {"type": "string"},
        "source": {"type": "string"},
        "inputs": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "name": {"type": "string"},
                    "unit": {"type": "string"},
                    "u": {"type": "array", "items": {"type": "number"}},
                    "pwm": {"type": "array", "items": {"type": "number"}},
                },
            },
        },
    },
}


def calibration_topic(agent_name: str) -> str:
    """``/<agent>/calibration``."""
    return f"/{agent_name}/{TOPIC_SUFFIX}"


def calibration_as_json(calibration: Calibration | None) -> dict[str, Any]:
    """The calibration's identity and tables as plain JSON types.

    Returns ``{"vehicle_id", "date", "source", "inputs": [{"name", "unit", "u", "pwm"}, ...]}``
    (``u`` in each input's unit, ``pwm`` signed duty in wire units), or
    ``{"inputs": []}`` with empty strings when the vehicle runs without a calibration.
    """
    if calibration is None:
        return {"vehicle_id": "", "date": "", "source": "", "inputs": []}
    inputs = []
    for name in calibration.names:
        curve = calibration.curve(name)
        inputs.append(
            {
                "name": curve.name,
                "unit": curve.unit,
                "u": [float(v) for v in curve.u],
                "pwm": [float(v) for v in curve.pwm],
            }
        )
    return {
        "vehicle_id": calibration.vehicle_id,
        "date": calibration.date,
        "source": calibration.source,
        "inputs": inputs,
    }
