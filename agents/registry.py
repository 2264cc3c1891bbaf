"""Names that experiment files use for vehicles, controllers and plants.

A name is either a short registry name from the tables below or a ``"package.module:Class"``
path, so users can plug in their own classes without touching hilswarm. Modules next to the
experiment file are importable: the orchestrator calls :func:`add_search_path` with the
experiment's folder and gives agent processes the same folder on ``PYTHONPATH``. Classes are
imported lazily: loading an experiment that uses ``frisbee`` does not import the Blimpduino model.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path
from typing import Any

from hilswarm.agents.errors import HilswarmError


class RegistryError(HilswarmError, LookupError):
    """A vehicle/controller/plant name is unknown or its class cannot be imported."""


VEHICLES: dict[str, str] = {
    "simulated": "hilswarm.agents.sim.simulated_vehicle:SimulatedVehicle",
    "frisbee": "hilswarm.agents.vehicles.frisbee:FrisbeeBot",
    "blimpduino": "hilswarm.agents.vehicles.blimpduino:Blimpduino",
}

CONTROLLERS: dict[str, str] = {
    "static_gain": "hilswarm.agents.control:StaticGain",
    "state_feedback": "hilswarm.agents.control:StateFeedback",
    "discrete_state_space": "hilswarm.agents.control:DiscreteStateSpace",
    "waypoint": "hilswarm.agents.controllers.waypoint:WaypointController",
    "follower": "hilswarm.agents.controllers.follower:OffsetFollower",
    "consensus": "hilswarm.agents.controllers.consensus:LinearConsensus",
    "blimp_flight": "hilswarm.agents.controllers.blimp_flight:BlimpFlightController",
}

PLANTS: dict[str, str] = {
    "spring_mass_damper": "hilswarm.agents.sim.spring_mass_damper:SpringMassDamper",
    "integrator": "hilswarm.agents.sim.integrator:Integrator",
    "differential_drive": "hilswarm.agents.sim.differential_drive:DifferentialDrive",
    "blimp": "hilswarm.agents.sim.blimp:BlimpPlant",
}


def add_search_path(folder: str | Path) -> None:
    """Make modules in ``folder`` (an experiment file's folder) importable by name."""
    entry = str(Path(folder).resolve())
    if entry not in sys.path:
        sys.path.insert(0, entry)
        importlib.invalidate_caches()


#: kind -> "module:Class" every class of that kind must subclass.
BASES: dict[str, str] = {
    "vehicle": "hilswarm.agents.vehicle:Vehicle",
    "controller": "hilswarm.agents.control:Controller",
}


def class_path(kind: str, name: str) -> str:
    """The ``"package.module:Class"`` path a registry name or path stands for.

    Raises:
        RegistryError: not a string, or neither a registry name nor a ``module:Class`` path.
    """
    table = {"vehicle": VEHICLES, "controller": CONTROLLERS, "plant": PLANTS}[kind]
    if not isinstance(name, str) or not name:
        raise RegistryError(f"{kind} name must be a non-empty string, got {name!r}")
    target = table.get(name, name)
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        known = ", ".join(sorted(table))
        raise RegistryError(
            f"unknown {kind} {name!r}: expected one of {known} or a 'package.module:Class' path"
        )
    return target


def _resolve(kind: str, name: str) -> Any:
    module_name, _, attr = class_path(kind, name).partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise RegistryError(
            f"{kind} {name!r}: cannot import module {module_name!r}: {exc}"
        ) from exc
    except Exception as exc:  # a user's module failing as it runs: its error, never a traceback
        raise RegistryError(
            f"{kind} {name!r}: importing module {module_name!r} failed: {type(exc).__name__}: {exc}"
        ) from exc
    try:
        found = getattr(module, attr)
    except AttributeError:
        raise RegistryError(f"{kind} {name!r}: module {module_name!r} has no {attr!r}") from None
    if kind in BASES:
        base_module, _, base_name = BASES[kind].partition(":")
        base = getattr(importlib.import_module(base_module), base_name)
        if not (isinstance(found, type) and issubclass(found, base)):
            what = (
                f"class {found.__qualname__}" if isinstance(found, type) else type(found).__name__
            )
            raise RegistryError(
                f"{kind} {name!r} is {what}, not a {kind} class: name a class that subclasses "
                f"{base_module}.{base_name}"
            )
    return found


def resolve_vehicle(name: str) -> Any:
    """Return the Vehicle class for ``name`` (raises :class:`RegistryError`)."""
    return _resolve("vehicle", name)


def resolve_controller(name: str) -> Any:
    """Return the Controller class for ``name`` (raises :class:`RegistryError`)."""
    return _resolve("controller", name)


def resolve_plant(name: str) -> Any:
    """Return the plant class for ``name`` (raises :class:`RegistryError`)."""
    return _resolve("plant", name)
