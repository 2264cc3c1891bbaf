"""The three simulations of thesis §4.5, with the hardware limits kept and no input thrashing.

Tolerances (end of each run, all derived from the controller's thresholds):

* descend — altitude within 0.06 m: VERTICAL ends once |Δz| < z_exit = 0.02 m and |ż| <
  settle_speed = 0.005 m/s; after that the blimp coasts at most settle_speed · m_z / D_w
  ≈ 0.005 · 0.37 / 0.05 ≈ 0.04 m (no vertical authority with the thrust forward).
* turn — heading within 0.01 rad of -135° ("zero steady-state error": the LQR holds the heading
  with no disturbance to fight; 0.01 rad allows for the PWM quantisation on the board path),
  still at (1, 1) within 0.02 m.
* forward — within 0.05 m of (0, 0) and nearly at rest (< 0.01 m/s): the leg ends within
  distance_exit = 0.03 m and HOLD then pulls the along-heading error to zero.

Input switching: a reversal is a change of direction of an input by steps > 1 % of its range.
The thesis' forward flight thrashed (~one reversal per sample, cut at 5 s); here every input
reverses at most a handful of times over the whole flight, and μ never moves in FORWARD.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.controllers.blimp_flight import Mode
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS
from hilswarm.agents.sim.blimp_scenarios import (
    SCENARIOS,
    reversal_count,
    run_board_scenario,
    run_scenario,
)

P = DEFAULT_BLIMP_PARAMS
MAX_REVERSALS = 6


@pytest.fixture(scope="module")
def results():
    return {name: run_scenario(name) for name in SCENARIOS}


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_inputs_stay_within_the_hardware_limits(results, name: str) -> None:
    inputs = results[name].inputs
    assert np.all(np.abs(inputs[:, :2]) <= P.thrust_limit_n + 1e-12)
    assert np.all(inputs[:, 2] >= P.thrust_angle_min_rad - 1e-12)
    assert np.all(inputs[:, 2] <= P.thrust_angle_max_rad + 1e-12)


def test_descend_one_metre(results) -> None:
    result = results["descend"]
    error = result.final_error()
    assert abs(error["altitude_m"]) < 0.06
    assert error["distance_m"] < 0.02
    assert error["speed_m_s"] < 0.01
    vertical = result.modes == Mode.VERTICAL
    assert vertical[0]
    # Thesis Fig. 4.7c: thrusters pointed straight "down" (μ = -90°) with negative thrust. The
    # servo slews there at servo_rate_rad_s = 3 rad/s: π/2 takes 0.52 s (11 ticks).
    mu = result.inputs[:, 2]
    arrived = int(np.argmax(np.isclose(mu, -math.pi / 2)))
    assert result.t[arrived] <= 0.55
    assert np.all(np.isclose(mu[arrived:][vertical[arrived:]], -math.pi / 2))
    first_seconds = slice(arrived, arrived + 40)
    assert np.all(result.inputs[first_seconds, :2] < 0)
    assert result.saturations()["thrust_left"] > 0  # it does use full thrust
    assert result.mode_switches() <= 2


def test_turn_in_place_to_face_the_origin(results) -> None:
    result = results["turn"]
    error = result.final_error()
    assert abs(error["heading_rad"]) < 0.01
    assert error["distance_m"] < 0.02
    assert abs(error["yaw_rate_rad_s"]) < 1e-3
    heading = np.unwrap(result.states[:, 5])
    assert heading[-1] == pytest.approx(-3 * math.pi / 4, abs=0.01)
    # Fig. 4.8c: the thrusters saturate in opposite directions while turning.
    turning = result.modes == Mode.TURN
    opposite = turning & (result.inputs[:, 0] * result.inputs[:, 1] < 0)
    saturated = opposite & (np.abs(result.inputs[:, 0]) >= P.thrust_limit_n - 1e-12)
    assert np.count_nonzero(saturated) > 20
    assert result.mode_switches() <= 2


def test_forward_flight_reaches_the_waypoint_without_thrashing(results) -> None:
    result = results["forward"]
    error = result.final_error()
    assert error["distance_m"] < 0.05
    assert error["speed_m_s"] < 0.01
    assert abs(error["altitude_m"]) < 0.01
    forward = result.modes == Mode.FORWARD
    assert forward[0]  # 10° off: no turn in place first, corrected on the fly
    assert forward.sum() * result.dt > 5.0  # longer than the thesis' 5 s
    reversals = result.reversals(modes=[Mode.FORWARD])
    assert max(reversals.values()) <= MAX_REVERSALS, reversals
    assert reversals["thrust_angle"] == 0
    assert result.mode_switches() <= 2
    # The flight is towards the origin: the distance shrinks (almost) monotonically.
    distance = np.hypot(result.states[:, 0], result.states[:, 1])
    assert np.all(np.diff(distance[forward]) < 1e-3)


def test_reversal_count_tells_thrashing_from_smooth_motion() -> None:
    t = np.linspace(0.0, 5.0, 101)
    smooth = 0.05 * np.sin(t)
    thrashing = 0.05 * (-1.0) ** np.arange(t.size)
    assert reversal_count(smooth, threshold=0.001) <= 2
    assert reversal_count(thrashing, threshold=0.001) == t.size - 2
    assert reversal_count(thrashing, threshold=0.2) == 0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_the_pin_level_chain_flies_the_same_scenarios(results, name: str) -> None:
    # Blimpduino on a sim://fio board with the BlimpPinPlant: duties, pulses, quantisation.
    board = run_board_scenario(name)
    software = results[name]
    assert not board.extras["safe_mode"]
    np.testing.assert_allclose(board.final_state[:3], software.final_state[:3], atol=0.02)
    heading_gap = math.remainder(board.final_state[5] - software.final_state[5], 2 * math.pi)
    assert abs(heading_gap) < 0.01
    assert max(board.reversals().values()) <= MAX_REVERSALS
