"""FrisbeeBot: the thesis' two-wheeled differential-drive ground vehicle (chapter 5).

Hardware (§5.1): an Arduino Duemilanove, two wheel motors (7 cm wheels at the rim of an 18 cm
round body) driven forwards and backwards through an H-bridge, a 12 V lithium-polymer battery,
and motion-capture beacons on top. The thesis gives no pinout; this one is ours:

=========  ======  ==================================================================
device     role    pin (Duemilanove)
=========  ======  ==================================================================
drive      left_fwd   D7   H-bridge IN1 (left forward)
drive      left_back  D8   H-bridge IN2 (left backward)
drive      left_pwm   D5   H-bridge ENA (left enable, Timer0 PWM)
drive      right_fwd  D4   H-bridge IN3 (right forward)
drive      right_back D12  H-bridge IN4 (right backward)
drive      right_pwm  D6   H-bridge ENB (right enable, Timer0 PWM)
battery    pin        A0   battery through a 1:3 divider (12.6 V full -> 4.2 V at the pin)
=========  ======  ==================================================================

D0/D1 stay free for the XBee/serial link, D9/D10 for servos (Timer1), D2/D3 for interrupts.

Inputs ``u = [v_left, v_right]``: wheel surface speeds [m/s], forward positive, limited to the
calibration's range (about ±0.22 m/s = ±1 rev/s, §5.1). The calibration (``calibration=``, by
default the shipped reference table ``data/frisbee_calibration.toml``) turns each speed into a
signed PWM duty by monotone spline, and the duty actually staged (an integer) back into the
speed that is reported as applied.

Outputs ``y = [x, y, psi]``: position [m, world frame] and heading [rad, from world x towards
world y, wrapped to [-π, π)] from the vehicle's ``pose_source`` (the motion-capture system, or a
:class:`~hilswarm.agents.sim.mocap.SimulatedMocap` of the simulated plant).

A battery below ``battery_low_v`` puts the vehicle in safe mode (motors off) — the vehicle base
class does that for every Battery device.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from hilswarm.agents.calibration import Calibration
from hilswarm.agents.devices.battery import Battery
from hilswarm.agents.devices.hbridge_motor import HBridgeMotor
from hilswarm.agents.errors import VehicleError
from hilswarm.agents.sim.differential_drive import (
    FRISBEE_GEOMETRY,
    BatteryModel,
    FrisbeePinPlant,
    HBridgePins,
)
from hilswarm.agents.vehicle import Vehicle

#: The shipped reference calibration (see :func:`reference_wheel_speed`).
DEFAULT_CALIBRATION = Path(__file__).resolve().parent / "data" / "frisbee_calibration.toml"

#: Shape constant of the reference curve [1/V] and the Arduino's full-duty voltage [V].
REFERENCE_CURVE_SHAPE_PER_V = 0.12
FULL_DUTY_V = 5.0
PWM_FULL = 255


def reference_wheel_speed(duty: float) -> float:
    """Wheel surface speed [m/s] of the reference curve for a signed PWM duty (wire units).

    Shaped like the thesis' Fig. 5.3 (nearly linear, flattening towards the top) and scaled so
    full duty (5 V) is the thesis' maximum of 1 rev/s of a 7 cm wheel::

        speed = sign(duty) · π · 0.07 · tanh(a V) / tanh(a · 5 V),  V = 5 V · |duty| / 255,
        a = 0.12 / V.
    """
    volts = FULL_DUTY_V * abs(duty) / PWM_FULL
    a = REFERENCE_CURVE_SHAPE_PER_V
    top = FRISBEE_GEOMETRY.max_wheel_speed_m_s
    magnitude = top * math.tanh(a * volts) / math.tanh(a * FULL_DUTY_V)
    return math.copysign(magnitude, duty) if duty else 0.0


class FrisbeeBot(Vehicle):
    """The thesis' Frisbee bot: ``u = [v_left, v_right]`` [m/s], ``y = [x, y, psi]`` [m, m, rad].

    Vehicle params (``vehicle_params`` in experiment files):
        battery_low_v: battery voltage [V] below which the vehicle enters safe mode (10.5 V =
            3.5 V per cell of the 3-cell LiPo).
        battery_multiplier: battery volts per volt at the A0 pin (the divider ratio).
        sim_battery_full_v: simulated battery voltage at t = 0 [V] (``sim://`` only).
        sim_battery_drain_v_per_s: simulated discharge rate [V/s] (``sim://`` only; 0 = none).
    """

    #: Outputs come from motion capture (``pose_source``): ``check`` wants a source of it.
    needs_pose: ClassVar[bool] = True
    n_inputs: ClassVar[int] = 2
    n_outputs: ClassVar[int] = 3
    input_names: ClassVar[tuple[str, ...]] = ("v_left", "v_right")
    output_names: ClassVar[tuple[str, ...]] = ("x", "y", "psi")
    input_units: ClassVar[Mapping[str, str]] = {"v_left": "m/s", "v_right": "m/s"}
    output_units: ClassVar[Mapping[str, str]] = {"x": "m", "y": "m", "psi": "rad"}
    profile: ClassVar[str] = "duemilanove"
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]] = {
        "drive": {
            "left_fwd": 7,
            "left_back": 8,
            "left_pwm": 5,
            "right_fwd": 4,
            "right_back": 12,
            "right_pwm": 6,
        },
        "battery": {"pin": "A0"},
    }
    default_params: ClassVar[Mapping[str, Any]] = {
        "battery_low_v": 10.5,
        "battery_multiplier": 3.0,
        "sim_battery_full_v": 12.6,
        "sim_battery_drain_v_per_s": 0.0,
    }

    def __init__(
        self,
        *,
        calibration: Calibration | str | Path | None = None,
        limits: Mapping[str, Sequence[float]] | None = None,
        **options: Any,
    ) -> None:
        if calibration is None:
            calibration = DEFAULT_CALIBRATION
        if isinstance(calibration, str | Path):
            calibration = Calibration.from_file(calibration)
        # Default limits: the calibrated speed range of each wheel (never extrapolate).
        merged: dict[str, Sequence[float]] = {}
        if isinstance(calibration, Calibration):
            merged = {n: calibration.curve(n).u_range for n in self.input_names if n in calibration}
        merged.update(limits or {})
        super().__init__(calibration=calibration, limits=merged, **options)
        missing = [
            n for n in self.input_names if self.calibration is None or n not in self.calibration
        ]
        if missing:
            raise VehicleError(
                f"vehicle {self.name!r} (FrisbeeBot): the calibration has no curve for {missing}; "
                "it needs v_left and v_right (wheel speed [m/s] <-> signed PWM)"
            )
        # Per tick: the two curves straight, no lookups (see actuate()).
        self._wheels = self._wheel_curves()
        self._duty_buffer = np.zeros(2)  # [left, right] signed duty of one tick [wire units]
        self._duty_channel = self.telemetry["wheel_duty"]

    def _wheel_curves(self) -> tuple[Calibration | None, tuple[tuple[str, str, Any], ...]]:
        calibration = self.calibration
        if calibration is None:
            return None, ()
        return calibration, tuple(
            (motor, name, calibration.curve(name))
            for motor, name in zip(("left", "right"), self.input_names, strict=True)
        )

    def setup_devices(self) -> None:
        """The two-motor H-bridge ``drive`` and the ``battery`` divider on A0."""
        self.drive = self.add_device(HBridgeMotor, "drive", motors=("left", "right"))
        self.battery = self.add_device(
            Battery,
            "battery",
            multiplier=float(self.params["battery_multiplier"]),
            low_v=float(self.params["battery_low_v"]),
            hysteresis_v=0.2,
        )

    def setup_telemetry(self) -> None:
        """Channel ``wheel_duty``: the signed duty staged on each motor [wire units]."""
        self.telemetry.add_channel("wheel_duty", ("left", "right"))

    def record_telemetry(self, k: int, t: float, y: np.ndarray) -> None:
        """Append the staged duties for tick ``k``."""
        duties = self._duty_buffer
        duties[0] = self.drive.duty("left")
        duties[1] = self.drive.duty("right")
        self._duty_channel.append(k, t, duties)

    def read_outputs(self) -> np.ndarray:
        """``[x, y, psi]`` from the pose source (mocap)."""
        if self.pose_source is None:
            raise VehicleError(
                f"vehicle {self.name!r} (FrisbeeBot) has no pose_source: attach the motion "
                "capture (or a SimulatedMocap) before sensing"
            )
        pose = self.pose_source.pose()
        if type(pose) is not np.ndarray or pose.shape != (6,):
            pose = np.asarray(pose, dtype=np.float64).reshape(-1)
        if pose.shape != (6,):
            raise VehicleError(
                f"vehicle {self.name!r}: pose_source.pose() must give [x, y, z, roll, pitch, "
                f"yaw], got shape {pose.shape}"
            )
        x, y, _z, _roll, _pitch, yaw = pose.tolist()
        return np.array([x, y, yaw])

    def actuate(self, u: np.ndarray) -> np.ndarray:
        """Wheel speeds [m/s] -> signed duties (calibration) on the H-bridge.

        Returns the speeds the staged integer duties stand for (quantised by the duty step).
        """
        calibration, wheels = self._wheels
        if calibration is not self.calibration:  # replaced since construction: look up again
            self._wheels = calibration, wheels = self._wheel_curves()
            if calibration is None:
                self.to_pwm(self.input_names[0], 0.0)  # raises: no calibration curve
        applied = []
        drive = self.drive
        speeds = np.asarray(u, dtype=np.float64).tolist()
        for (motor, name, curve), speed in zip(wheels, speeds, strict=True):
            lo, hi = curve.u_range
            # Inside the table (always, with the default limits): the curve directly;
            # outside it the calibration clips and reports (vehicle.to_pwm).
            pwm = curve.pwm_at_scalar(speed) if lo <= speed <= hi else self.to_pwm(name, speed)
            duty = drive.actuate(motor, pwm)
            if duty == 0:
                applied.append(0.0)
            else:
                low, high = curve.pwm_range
                inside = low <= duty <= high
                applied.append(curve.u_at_scalar(float(duty)) if inside else self.to_u(name, duty))
        return np.array(applied)

    def simulated_hardware(
        self, *, initial_state: Sequence[float] | None, dt: float
    ) -> FrisbeePinPlant:
        """The pin-level plant: H-bridge pins -> wheel speeds (inverse calibration) -> exact
        differential-drive kinematics; battery voltage on A0.

        Args:
            initial_state: ``[x, y, psi]`` [m, m, rad] (default: this vehicle's
                ``initial_state``, else the origin facing +x).
            dt: control period [s] (the plant itself integrates exactly over any step).
        """
        state = initial_state if initial_state is not None else self.initial_state
        state = (0.0, 0.0, 0.0) if state is None else tuple(float(v) for v in state)
        if len(state) != 3:
            raise VehicleError(
                f"vehicle {self.name!r}: initial_state must be [x, y, psi], got {list(state)}"
            )
        drive = self.drive
        battery = BatteryModel(
            pin=self.battery.pin("pin"),
            full_v=float(self.params["sim_battery_full_v"]),
            drain_v_per_s=float(self.params["sim_battery_drain_v_per_s"]),
            empty_v=min(9.0, float(self.params["sim_battery_full_v"])),
            multiplier=float(self.params["battery_multiplier"]),
        )
        return FrisbeePinPlant(
            self.calibration,
            left=HBridgePins(drive.pin("left_fwd"), drive.pin("left_back"), drive.pin("left_pwm")),
            right=HBridgePins(
                drive.pin("right_fwd"), drive.pin("right_back"), drive.pin("right_pwm")
            ),
            initial_state=state,
            geometry=FRISBEE_GEOMETRY,
            battery=battery,
        )
