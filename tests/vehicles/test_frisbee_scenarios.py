"""The Frisbee square of thesis §5.6: P and PI, SIL and through the vehicle on a SimBoard."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest
from hilswarm.agents.sim.frisbee_scenarios import (
    SQUARE_WAYPOINTS,
    run_sil,
    run_sim_board,
    square_params,
)

REPO = Path(__file__).resolve().parents[2]
TOLERANCE = square_params("p")["waypoint_tolerance_m"]


@pytest.fixture(scope="module")
def runs():
    return {
        (kind, mode): run(mode)
        for kind, run in (("sil", run_sil), ("board", run_sim_board))
        for mode in ("p", "pi")
    }


@pytest.mark.parametrize("kind", ["sil", "board"])
@pytest.mark.parametrize("mode", ["p", "pi"])
def test_every_corner_is_reached_in_order(runs, kind, mode):
    run = runs[kind, mode]
    assert run.finish_time_s is not None
    for corner in SQUARE_WAYPOINTS:
        assert run.closest_approach(corner) <= TOLERANCE
    assert list(dict.fromkeys(run.waypoint_index.tolist())) == list(range(len(SQUARE_WAYPOINTS)))


def test_pi_finishes_no_later_than_p(runs):
    # The thesis' hardware PI was slightly slower than P (overshoot). Here the distance error
    # never changes sign while driving, the integral restarts at every pivot and does not grow
    # at the speed limit, so the integral only speeds up P's exponential approach to each corner:
    # PI finishes earlier. Both with perfect (SIL) and with noisy, quantised (board) feedback.
    for kind in ("sil", "board"):
        assert runs[kind, "pi"].finish_time_s < runs[kind, "p"].finish_time_s


def test_board_and_sil_take_about_the_same_time(runs):
    for mode in ("p", "pi"):
        sil, board = runs["sil", mode].finish_time_s, runs["board", mode].finish_time_s
        assert board == pytest.approx(sil, rel=0.05)


@pytest.mark.parametrize("mode", ["p", "pi"])
def test_experiment_files_use_the_scenario_params(mode):
    data = tomllib.loads((REPO / "graphs" / f"frisbee_square_{mode}.toml").read_text())
    params = data["agents"]["frisbee"]["params"]
    assert params == square_params(mode)
