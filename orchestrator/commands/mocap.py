"""``hilswarm mocap [EXPERIMENT | --system S --host H]``: list the bodies a mocap system sees.

Example::

    hilswarm mocap --system qualisys --host 192.168.1.10
    hilswarm mocap graphs/lead_follow_mocap.toml

Watches the stream for a moment (``--seconds``) and prints each rigid body with the rate at
which it is tracked and its pose in the project's world frame (z up, metres; heading in
degrees), so names and frames can be checked before a run. With an experiment file, its
``[mocap]`` section says where to look and every agent's body is listed (``MISSING`` when the
system does not see it); with ``system = "sim"`` the built-in simulator is started with the
experiment's bodies at their initial poses. Exit status: 0 every body needed is seen, 1 some
body is missing or the server cannot be reached, 2 bad input.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
from hilswarm.agents.errors import HilswarmError
from hilswarm.agents.mocap.clients import MocapConnectionError, MocapServerLost, QualisysClient
from hilswarm.agents.mocap.config import MocapSettings
from hilswarm.agents.mocap.frames import SYSTEMS, world_to_ned
from hilswarm.agents.mocap.probe import DEFAULT_PROBE_S, ProbeResult, probe
from hilswarm.agents.mocap.qtm_sim import QtmSimulator
from hilswarm.agents.mocap.sim_process import sim_settings
from hilswarm.agents.registry import resolve_vehicle
from hilswarm.orchestrator.cli_types import positive_number
from hilswarm.orchestrator.experiment import Experiment, load_experiment, mocap_settings

HELP = "list the bodies a mocap system sees, with rate and position"
#: Longest ``--seconds`` [s].
MAX_WATCH_S = 60.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``hilswarm mocap``."""
    parser.add_argument("file", nargs="?", type=Path, help="experiment file with [mocap]")
    parser.add_argument("--system", choices=SYSTEMS, help="mocap system (without a file)")
    parser.add_argument("--host", help="mocap server address (without a file)")
    parser.add_argument(
        "--port",
        type=int,
        default=None,
        help="server port (system default; OptiTrack: NatNet's command port)",
    )
    parser.add_argument("--up-axis", choices=("y", "z"), default=None, help="override up axis")
    parser.add_argument(
        "--seconds",
        type=positive_number(most=MAX_WATCH_S),
        default=DEFAULT_PROBE_S,
        help=f"how long to watch the stream [s] (default {DEFAULT_PROBE_S:g}, at most "
        f"{MAX_WATCH_S:g})",
    )


def _settings(args: argparse.Namespace) -> tuple[MocapSettings, Experiment | None]:
    if args.file is not None:
        experiment = load_experiment(args.file)
        if experiment.mocap is None:
            raise _BadInputError(f"{args.file} has no [mocap] section")
        return experiment.mocap, experiment
    if args.system is None or (args.host is None and args.system != "sim"):
        raise _BadInputError("give an experiment file, or --system and --host")
    table = {"system": args.system, "host": args.host or "127.0.0.1"}
    if args.port is not None:
        table["port"] = args.port
    if args.up_axis is not None:
        table["up_axis"] = args.up_axis
    settings, problems = mocap_settings(table, file="command line", where="")
    if settings is None:
        raise _BadInputError("; ".join(f"{p.key}: {p.message}" for p in problems))
    return settings, None


class _BadInputError(HilswarmError, ValueError):
    """Bad command-line input."""


def initial_pose(experiment: Experiment, name: str) -> np.ndarray:
    """The world pose agent ``name``'s simulated plant starts at (origin if it has none)."""
    spec = experiment.agent(name)
    try:
        vehicle = resolve_vehicle(spec.vehicle)(
            name=spec.name,
            params=spec.vehicle_params or None,
            initial_state=list(spec.initial_state) or None,
            dt=experiment.dt,
        )
        plant = vehicle.simulated_hardware(
            initial_state=list(spec.initial_state) or None, dt=experiment.dt
        )
        pose = np.asarray(plant.pose(), dtype=np.float64).reshape(6)
    except (HilswarmError, AttributeError, TypeError, ValueError, NotImplementedError):
        return np.zeros(6)
    return world_to_ned(pose) if getattr(plant, "pose_frame", "world") == "ned" else pose


def _probe_sim(
    settings: MocapSettings, experiment: Experiment | None, seconds: float
) -> ProbeResult:
    bodies = [spec.body for spec in experiment.agents] if experiment else ["body1"]
    with QtmSimulator(sim_settings(settings, bodies, experiment.seed if experiment else 0)) as sim:
        for spec in experiment.agents if experiment else ():
            sim.set_truth(spec.body, initial_pose(experiment, spec.name))
        return probe(settings, duration_s=seconds, client=QualisysClient("127.0.0.1", sim.port))


def run(args: argparse.Namespace) -> int:
    """Probe the system and print its bodies; see the module docstring for the exit status."""
    try:
        settings, experiment = _settings(args)
    except _BadInputError as exc:
        print(f"hilswarm mocap: {exc}", file=sys.stderr)
        return 2
    where = f"{settings.system} at {settings.host}" + (f":{settings.port}" if settings.port else "")
    print(f"watching {where} for {args.seconds:g} s ...", flush=True)
    try:
        if settings.system == "sim":
            result = _probe_sim(settings, experiment, args.seconds)
        else:
            result = probe(settings, duration_s=args.seconds)
    except (MocapConnectionError, MocapServerLost) as exc:
        print(f"hilswarm mocap: {exc}", file=sys.stderr)
        return 1
    print(f"{result.frames} frames, {result.rate_hz:.1f} Hz; world frame: z up, metres")
    users = {spec.body: spec.name for spec in experiment.agents} if experiment else {}
    names = list(result.bodies) + [b for b in users if b not in result.bodies]
    head = ("body", "agent", "rate Hz", "x m", "y m", "z m", "yaw deg")
    print("  {:<16} {:<12} {:>8} {:>8} {:>8} {:>8} {:>8}".format(*head))
    missing = []
    for name in names:
        seen = result.bodies.get(name)
        agent = users.get(name, "-")
        if seen is None or not seen.frames:
            state = "MISSING" if name in users else "not tracked"
            if name in users:
                missing.append(name)
            print(f"  {name:<16} {agent:<12} {state:>8}")
            continue
        x, y, z, _roll, _pitch, yaw = seen.pose.tolist()
        print(
            f"  {name:<16} {agent:<12} {result.body_rate_hz(name):8.1f} {x:8.3f} {y:8.3f} "
            f"{z:8.3f} {math.degrees(yaw):8.1f}"
        )
    if missing:
        print(f"hilswarm mocap: not visible: {', '.join(missing)}", file=sys.stderr)
        return 1
    return 0
