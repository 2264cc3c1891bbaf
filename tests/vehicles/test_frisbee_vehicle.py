"""FrisbeeBot on a simulated board: pins, calibration, closed loop, battery safe mode."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.errors import PinError, VehicleError
from hilswarm.agents.link.sim_board import SimBoard
from hilswarm.agents.registry import resolve_vehicle
from hilswarm.agents.sim.mocap import SimulatedMocap
from hilswarm.agents.vehicles.frisbee import DEFAULT_CALIBRATION, FrisbeeBot, reference_wheel_speed

DT = 0.05


def connected(**options):
    vehicle = FrisbeeBot(name="fb", dt=DT, **options)
    plant = vehicle.simulated_hardware(initial_state=None, dt=DT)
    board = SimBoard(vehicle.profile, plant=plant, dt=DT)
    vehicle.pose_source = SimulatedMocap(plant)
    vehicle.connect(board)
    return vehicle, plant, board


def test_registry_name_and_declarations():
    assert resolve_vehicle("frisbee") is FrisbeeBot
    vehicle = FrisbeeBot(dt=DT)
    assert vehicle.profile == "duemilanove"
    assert vehicle.input_names == ("v_left", "v_right")
    assert vehicle.output_names == ("x", "y", "psi")
    assert sorted(vehicle.pins.used_pins()) == [4, 5, 6, 7, 8, 12, 14]


def test_shipped_calibration_is_the_documented_reference_curve():
    calibration = Calibration.from_file(DEFAULT_CALIBRATION)
    for name in ("v_left", "v_right"):
        curve = calibration.curve(name)
        expected = [reference_wheel_speed(d) for d in curve.pwm]
        assert curve.u == pytest.approx(expected, abs=1e-6)
        assert curve.unit == "m/s"
    # 255 duty is the thesis' maximum, 1 wheel revolution per second of a 7 cm wheel.
    assert reference_wheel_speed(255) == pytest.approx(math.pi * 0.07)


def test_limits_come_from_the_calibration_range():
    vehicle = FrisbeeBot(dt=DT)
    assert vehicle.limits["v_left"] == pytest.approx((-0.219911, 0.219911))
    narrow = FrisbeeBot(dt=DT, limits={"v_left": (-0.1, 0.1)})
    assert narrow.limits["v_left"] == (-0.1, 0.1)


def test_speeds_become_h_bridge_pins():
    vehicle, _, board = connected()
    vehicle.apply([0.1, -0.05])
    vehicle.exchange()
    out = board.outputs
    left_duty = round(vehicle.calibration.to_pwm("v_left", 0.1))
    right_duty = round(vehicle.calibration.to_pwm("v_right", 0.05))
    assert (out[7], out[8], out[5]) == (1, 0, left_duty)
    assert (out[4], out[12], out[6]) == (0, 1, right_duty)
    # The applied input is what the integer duty stands for (within one duty step).
    assert vehicle.u == pytest.approx([0.1, -0.05], abs=0.001)
    assert vehicle.u[0] == pytest.approx(vehicle.calibration.to_u("v_left", left_duty))


def test_closed_loop_straight_drive_matches_kinematics():
    vehicle, plant, _ = connected()
    for k in range(40):  # 2 s straight at about 0.1 m/s
        vehicle.sense(k, k * DT)
        vehicle.apply([0.1, 0.1])
        vehicle.exchange()
    y = vehicle.sense(40, 40 * DT)
    assert y[0] == pytest.approx(2.0 * vehicle.u[0], rel=1e-9)
    assert y[1] == pytest.approx(0.0, abs=1e-12)
    assert y[2] == pytest.approx(0.0, abs=1e-12)
    assert plant.pose()[0] == pytest.approx(y[0])


def test_pivot_turns_counter_clockwise_in_place():
    vehicle, _, _ = connected()
    for k in range(10):
        vehicle.sense(k, k * DT)
        vehicle.apply([-0.09, 0.09])
        vehicle.exchange()
    y = vehicle.sense(10, 10 * DT)
    assert y[:2] == pytest.approx([0.0, 0.0], abs=1e-12)
    assert y[2] == pytest.approx(10 * DT * 2 * vehicle.u[1] / 0.18, rel=1e-9)


def test_low_battery_enters_safe_mode_and_stops_the_motors():
    vehicle, plant, board = connected(params={"sim_battery_drain_v_per_s": 1.0})
    reasons = []
    vehicle.add_safe_mode_listener(reasons.append)
    for k in range(60):  # 12.6 V -> below 10.5 V after 2.1 s
        vehicle.sense(k, k * DT)
        vehicle.apply([0.1, 0.1])
        vehicle.exchange()
    assert vehicle.safe_mode
    assert reasons and "low battery" in reasons[0]
    assert all(board.outputs[p] == 0 for p in (4, 5, 6, 7, 8, 12))
    assert list(plant.wheel_speeds) == [0.0, 0.0]


def test_no_pose_source_is_a_clear_error():
    vehicle = FrisbeeBot(dt=DT)
    vehicle.connect(SimBoard("duemilanove", dt=DT))
    with pytest.raises(VehicleError, match="pose_source"):
        vehicle.sense(0, 0.0)


def test_bad_configuration_is_named():
    with pytest.raises(VehicleError, match="initial_state"):
        FrisbeeBot(dt=DT).simulated_hardware(initial_state=[0.0, 1.0], dt=DT)
    with pytest.raises(PinError):
        FrisbeeBot(dt=DT, pinout={"battery": {"pin": 5}})  # D5 already drives the left motor
    only_left = Calibration({"v_left": ([-0.2, 0.2], [-255, 255])})
    with pytest.raises(VehicleError, match="v_right"):
        FrisbeeBot(dt=DT, calibration=only_left)


def test_initial_state_places_the_plant():
    vehicle = FrisbeeBot(dt=DT, initial_state=[0.5, -0.2, math.pi / 2])
    plant = vehicle.simulated_hardware(initial_state=None, dt=DT)
    assert plant.pose() == pytest.approx([0.5, -0.2, 0, 0, 0, math.pi / 2])
    assert np.all(np.isfinite(plant.pose()))
