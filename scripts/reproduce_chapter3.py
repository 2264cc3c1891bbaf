"""Reproduce thesis chapter 3 (§3.2): SIL versus simulated HIL of the spring-mass-damper.

Places the poles {-2 ± 0.1i, -2 ± 0.1i} (eq. 3.4), runs the closed loop from
z0 = [4, 0, -4, 0] as SIL with adaptive RK45 (ode45), SIL with Euler (ode1), and SHIL
(ControlModel + SimulatedVehicle exchanging u and y every tick), writes figures like
Figs. 3.3/3.4 and prints how far SHIL is from each SIL run.

    python scripts/reproduce_chapter3.py --out out/chapter3 [--dt 0.1] [--duration 6]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from hilswarm.agents.sim.chapter3 import (
    DEFAULT_DT,
    DEFAULT_DURATION_S,
    THESIS_GAIN,
    Trajectory,
    max_abs_difference,
    place_gains,
    shil,
    sil_adaptive,
    sil_fixed_step,
    tick_count,
)

STATE_LABELS = ("x [m]", "ẋ [m/s]", "y [m]", "ẏ [m/s]")


def plot_states(trajectory: Trajectory, title: str, path: Path) -> None:
    """One figure: the four states against time (like thesis Figs. 3.3/3.4)."""
    figure, axes = plt.subplots(figsize=(7, 4.2))
    for index, label in enumerate(STATE_LABELS):
        axes.plot(trajectory.t, trajectory.z[:, index], marker=".", markersize=3, label=label)
    axes.set_xlabel("time [s]")
    axes.set_ylabel("state")
    axes.set_title(title)
    axes.grid(True, alpha=0.3)
    axes.legend(loc="upper right")
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def plot_comparison(runs: list[Trajectory], reference: Trajectory, path: Path) -> None:
    """x and y of every run on top of each other, and |run - SHIL| per tick."""
    figure, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for run in runs:
        style = "--" if run.label == "SHIL" else "-"
        top.plot(run.t, run.z[:, 0], style, label=f"x, {run.label}")
        top.plot(run.t, run.z[:, 2], style, label=f"y, {run.label}")
    top.set_ylabel("position [m]")
    top.grid(True, alpha=0.3)
    top.legend(fontsize=8, ncol=2)
    for run in runs:
        if run is reference:
            continue
        difference = np.max(np.abs(run.z - reference.z), axis=1)
        label = f"|{run.label} - SHIL|"
        if not np.any(difference):
            label += " = 0 at every tick (drawn at 1e-17)"
        bottom.semilogy(run.t, np.maximum(difference, 1e-17), label=label)
    bottom.set_xlabel("time [s]")
    bottom.set_ylabel("max |Δz| over states")
    bottom.grid(True, alpha=0.3)
    bottom.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/chapter3"), help="figure folder")
    parser.add_argument("--dt", type=float, default=DEFAULT_DT, help="control period [s]")
    parser.add_argument(
        "--duration", type=float, default=DEFAULT_DURATION_S, help="simulated time [s]"
    )
    args = parser.parse_args(argv)
    if not args.dt > 0 or not args.duration > 0:
        parser.error("--dt and --duration must be > 0")
    args.out.mkdir(parents=True, exist_ok=True)

    gain = place_gains()
    print("K (eq. 3.4) =")
    print(np.array2string(gain, precision=4, suppress_small=True))
    print(f"max |K - thesis K| = {np.max(np.abs(gain - THESIS_GAIN)):.2e}")

    n_ticks = tick_count(args.duration, args.dt)
    sil_rk45 = sil_adaptive(gain, dt=args.dt, n_ticks=n_ticks)
    sil_euler = sil_fixed_step(gain, dt=args.dt, n_ticks=n_ticks, method="euler")
    simulated_hil = shil(gain, dt=args.dt, n_ticks=n_ticks)

    plot_states(sil_rk45, "SIL, Dormand-Prince (RK45 ≈ ode45)", args.out / "fig3_3a_sil_rk45.png")
    plot_states(
        sil_euler, f"SIL, Euler (ode1), h = {args.dt} s", args.out / "fig3_3b_sil_euler.png"
    )
    plot_states(
        simulated_hil,
        f"SHIL: ControlModel + SimulatedVehicle, dt = {args.dt} s",
        args.out / "fig3_4_shil.png",
    )
    plot_comparison(
        [sil_rk45, sil_euler, simulated_hil], simulated_hil, args.out / "comparison.png"
    )

    print(f"ticks: {n_ticks} of dt = {args.dt} s")
    print(f"max |SHIL - SIL-Euler| = {max_abs_difference(simulated_hil, sil_euler):.3e}")
    print(f"max |SHIL - SIL-RK45|  = {max_abs_difference(simulated_hil, sil_rk45):.3e}")
    print(f"figures in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
