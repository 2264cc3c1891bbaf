"""Reproduce thesis §4.5 (Figs. 4.7-4.9): the Blimpduino descends, turns in place, flies forward.

For each scenario of ``hilswarm.agents.sim.blimp_scenarios`` it runs the SIL simulation
(controller + nonlinear 6-DOF model) and, with ``--board``, also the pin-level chain
(Blimpduino on a ``sim://fio`` board with the BlimpPinPlant). It writes per scenario
``<name>_velocity.png`` (u, v, w, r), ``<name>_navigation.png`` (x, y, z, ψ),
``<name>_inputs.png`` (T_l, T_r, μ and the flight mode) and, for the forward flight,
``forward_trajectory.png`` (x-y path) into --out, and prints the end states, thrust
saturation counts, input reversal counts and mode switches.

    python scripts/reproduce_blimpduino.py --out out/blimpduino
    python scripts/reproduce_blimpduino.py --out out/blimpduino --board
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from hilswarm.agents.controllers.blimp_flight import Mode
from hilswarm.agents.sim.blimp_scenarios import (
    SCENARIOS,
    ScenarioResult,
    run_board_scenario,
    run_scenario,
)


def plot_velocity(results: dict[str, ScenarioResult], path: Path) -> None:
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(8, 8))
    labels = ("u [m/s]", "v [m/s]", "w [m/s] (down +)", "r [deg/s]")
    for label, result in results.items():
        s = result.states
        series = (s[:, 6], s[:, 7], s[:, 8], np.degrees(s[:, 11]))
        for axis, values, name in zip(axes, series, labels, strict=True):
            axis.plot(result.t, values, label=label)
            axis.set_ylabel(name)
    axes[0].legend()
    axes[-1].set_xlabel("t [s]")
    fig.suptitle(f"{next(iter(results.values())).scenario.title}: velocity states")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_navigation(results: dict[str, ScenarioResult], path: Path) -> None:
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(8, 8))
    labels = ("x [m]", "y [m]", "altitude -z [m]", "heading ψ [deg]")
    for label, result in results.items():
        s = result.states
        series = (s[:, 0], s[:, 1], -s[:, 2], np.degrees(np.unwrap(s[:, 5])))
        for axis, values, name in zip(axes, series, labels, strict=True):
            axis.plot(result.t, values, label=label)
            axis.set_ylabel(name)
    axes[0].legend()
    axes[-1].set_xlabel("t [s]")
    fig.suptitle(f"{next(iter(results.values())).scenario.title}: navigation states")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_inputs(results: dict[str, ScenarioResult], path: Path) -> None:
    fig, axes = plt.subplots(4, 1, sharex=True, figsize=(8, 8))
    for label, result in results.items():
        u = result.inputs
        axes[0].plot(result.t, u[:, 0], label=label)
        axes[1].plot(result.t, u[:, 1], label=label)
        axes[2].plot(result.t, np.degrees(u[:, 2]), label=label)
        axes[3].step(result.t, result.modes, where="post", label=label)
    for axis, name in zip(
        axes, ("T_left [N]", "T_right [N]", "thrust angle μ [deg]", "mode"), strict=True
    ):
        axis.set_ylabel(name)
    for axis in axes[:2]:
        axis.axhline(0.0637, color="grey", linestyle=":")
        axis.axhline(-0.0637, color="grey", linestyle=":")
    axes[3].set_yticks([m.value for m in Mode], [m.name for m in Mode])
    axes[0].legend()
    axes[-1].set_xlabel("t [s]")
    fig.suptitle(f"{next(iter(results.values())).scenario.title}: control inputs")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_trajectory(results: dict[str, ScenarioResult], path: Path) -> None:
    fig, axis = plt.subplots(figsize=(6, 6))
    for label, result in results.items():
        s = result.states
        axis.plot(s[:, 1], s[:, 0], label=label)
        step = max(1, len(s) // 15)
        axis.quiver(
            s[::step, 1],
            s[::step, 0],
            np.sin(s[::step, 5]),
            np.cos(s[::step, 5]),
            scale=25,
            width=0.004,
            alpha=0.6,
        )
    waypoint = next(iter(results.values())).scenario.params["waypoint"]
    axis.plot([waypoint[1]], [waypoint[0]], "k*", markersize=12, label="waypoint")
    axis.set_xlabel("y (east) [m]")
    axis.set_ylabel("x (north) [m]")
    axis.set_aspect("equal")
    axis.grid(True)
    axis.legend()
    axis.set_title("Forward flight: trajectory (NED, seen from above)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def report(label: str, result: ScenarioResult, seconds: float) -> None:
    x = result.final_state
    error = result.final_error()
    print(
        f"  {label:5s} end: x={x[0]:+.3f} y={x[1]:+.3f} z={x[2]:+.3f} m, "
        f"ψ={math.degrees(x[5]):+.2f}°, speed={error['speed_m_s']:.4f} m/s | "
        f"errors: distance {error['distance_m']:.3f} m, altitude {error['altitude_m']:+.3f} m, "
        f"heading {math.degrees(error['heading_rad']):+.2f}°"
    )
    forward = result.reversals(modes=[Mode.FORWARD])
    print(
        f"        saturations {result.saturations()} | reversals (whole run) "
        f"{result.reversals()} | reversals in FORWARD {forward} | mode switches "
        f"{result.mode_switches()} | {seconds:.2f} s wall"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the PNG figures")
    parser.add_argument("--board", action="store_true", help="also run the pin-level chain")
    parser.add_argument("--dt", type=float, default=0.05, help="control period [s]")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    for name, scenario in SCENARIOS.items():
        print(f"{name}: {scenario.title}")
        results: dict[str, ScenarioResult] = {}
        started = time.perf_counter()
        results["SIL"] = run_scenario(scenario, dt=args.dt)
        report("SIL", results["SIL"], time.perf_counter() - started)
        if args.board:
            started = time.perf_counter()
            results["board"] = run_board_scenario(scenario, dt=args.dt)
            report("board", results["board"], time.perf_counter() - started)
        plot_velocity(results, args.out / f"{name}_velocity.png")
        plot_navigation(results, args.out / f"{name}_navigation.png")
        plot_inputs(results, args.out / f"{name}_inputs.png")
        if name == "forward":
            plot_trajectory(results, args.out / "forward_trajectory.png")
    print(f"figures in {args.out}")


if __name__ == "__main__":
    main()
