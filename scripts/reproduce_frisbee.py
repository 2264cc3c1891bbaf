"""Reproduce thesis Fig. 5.5: the Frisbee square with P and PI control, SIL vs HIL paths.

For each law (P, PI) the same WaypointController runs

1. SIL — controller + exact differential-drive kinematics (pure Python);
2. sim board — through FrisbeeBot on an in-process SimBoard (H-bridge pins, integer duty,
   inverse calibration, noisy simulated mocap);
3. runtime — ``hilswarm run graphs/frisbee_square_<law>.toml`` (agent process, bus, recorder);
4. simavr — the same experiment with ``--link frisbee=simavr://uno``: the real firmware in the
   AVR simulator between the agent and the plant.

It prints the time to finish the square for each and writes ``frisbee_square.png`` to --out.

    python scripts/reproduce_frisbee.py --out out/frisbee
    python scripts/reproduce_frisbee.py --out out/frisbee --skip-runtime --skip-simavr
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from hilswarm.agents.sim.frisbee_scenarios import (
    SQUARE_WAYPOINTS,
    SquareRun,
    result_from_recording,
    run_sil,
    run_sim_board,
)

REPO = Path(__file__).resolve().parents[1]
RUN_TIMEOUT_S = 600.0


def run_experiment(mode: str, out: Path, link: str | None) -> SquareRun:
    """``hilswarm run`` the square experiment of ``mode`` and read the recording back."""
    experiment = REPO / "graphs" / f"frisbee_square_{mode}.toml"
    suffix = "simavr" if link else "runtime"
    recording = out / f"frisbee_square_{mode}_{suffix}.mcap"
    command = [sys.executable, "-m", "hilswarm.orchestrator.cli", "run", str(experiment)]
    command += ["--out", str(recording)]
    if link:
        command += ["--link", f"frisbee={link}"]
    result = subprocess.run(
        command, capture_output=True, text=True, timeout=RUN_TIMEOUT_S, check=False
    )
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({result.returncode}): {result.stderr}")
    return result_from_recording(recording, "frisbee", label=f"{suffix} {mode.upper()}")


def plot(runs: dict[str, list[SquareRun]], path: Path) -> None:
    """One panel per law, every run's path and the waypoints."""
    fig, axes = plt.subplots(1, len(runs), figsize=(6.0 * len(runs), 5.6), dpi=110)
    for ax, (mode, mode_runs) in zip(axes, runs.items(), strict=True):
        for run in mode_runs:
            finish = "not finished" if run.finish_time_s is None else f"{run.finish_time_s:.1f} s"
            ax.plot(run.pose[:, 0], run.pose[:, 1], lw=1.2, label=f"{run.label} ({finish})")
        wx, wy = zip(*SQUARE_WAYPOINTS, strict=True)
        ax.plot(wx, wy, "k+", ms=12, mew=2, label="waypoints")
        ax.plot([0], [0], "ko", ms=4)
        ax.set_title(f"{mode.upper()} control")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_aspect("equal")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="center")
    fig.suptitle("Frisbee square (thesis Fig. 5.5): SIL vs simulated-board vs runtime paths")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("out/frisbee"), help="output folder")
    parser.add_argument("--skip-runtime", action="store_true", help="no `hilswarm run` runs")
    parser.add_argument("--skip-simavr", action="store_true", help="no real-firmware runs")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulated mocap noise")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    runs: dict[str, list[SquareRun]] = {}
    for mode in ("p", "pi"):
        mode_runs = [run_sil(mode), run_sim_board(mode, seed=args.seed)]
        for link, skip in ((None, args.skip_runtime), ("simavr://uno", args.skip_simavr)):
            if skip:
                continue
            try:
                mode_runs.append(run_experiment(mode, args.out, link))
            except (RuntimeError, OSError, subprocess.TimeoutExpired) as exc:
                print(f"skipped {link or 'runtime'} {mode.upper()}: {exc}", file=sys.stderr)
        runs[mode] = mode_runs

    print(f"{'run':<16} {'finish [s]':>10}   closest approach to each waypoint [mm]")
    for mode_runs in runs.values():
        for run in mode_runs:
            finish = "-" if run.finish_time_s is None else f"{run.finish_time_s:.2f}"
            gaps = " ".join(f"{1000 * run.closest_approach(p):4.1f}" for p in SQUARE_WAYPOINTS)
            print(f"{run.label:<16} {finish:>10}   {gaps}")
    path = args.out / "frisbee_square.png"
    plot(runs, path)
    print(f"plot: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
