"""The Blimpduino: a twin-engine vectored-thrust indoor blimp on an Arduino Fio (thesis ch. 4).

Devices and pinout exactly as thesis Code Sample A.2:

==========  ==================================  =========================================
device      roles -> pins                       notes
==========  ==================================  =========================================
motor       left_fwd 5, left_back 4, left_pwm 3  HBridgeMotor, motors ("left", "right")
            right_fwd 7, right_back 8,
            right_pwm 11
servo       pin 10                              thrust-angle servo (disables PWM on 9)
standby     pin 6                               H-bridge enable, driven HIGH on start-up
battery     pin A0                              vref 3.3 V, multiplier 3, low 6.5 V
==========  ==================================  =========================================

Board profile ``"fio"`` (3.3 V ADC reference). A low battery (below 6.5 V) puts the vehicle in
safe mode: motors off (direction pins low, duty 0, H-bridge disabled) and the servo at its
neutral angle (μ = -90°, 1500 µs).

Input ``u = [thrust_left, thrust_right, thrust_angle]``: propeller thrusts [N] (limited to
±0.0637 N, thesis §4.5) and thrust angle μ [rad] (limited to the servo's -π..0, thesis §4.5.1;
μ = 0 thrusts forward, μ = -π/2 up). Thrusts go to signed PWM duties through the vehicle's
calibration (default: :func:`reference_calibration`); μ goes to the servo as an angle in
degrees (the servo maps -180°..0° onto ``servo_min_us``..``servo_max_us``).

Output ``y = [x, y, z, yaw]`` from the pose source (motion capture): position [m, world NED,
z down] and heading [rad]; see :mod:`hilswarm.agents.sim.blimp` for the frames.

``simulated_hardware()`` returns a :class:`~hilswarm.agents.sim.blimp.BlimpPinPlant` for
``sim://fio`` boards: it reads these very pins, converts the duties back to thrusts with the
same calibration, integrates the 6-DOF model and feeds the battery divider voltage to A0.
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
from hilswarm.agents.devices.output_pin import OutputPin
from hilswarm.agents.devices.servo import Servo
from hilswarm.agents.errors import VehicleError
from hilswarm.agents.link.board import PWM_MAX
from hilswarm.agents.mocap.frames import world_to_ned
from hilswarm.agents.sim.blimp import BlimpPinout, BlimpPinPlant
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS, BatteryParams, BlimpParams
from hilswarm.agents.vehicle import Vehicle
from numpy.typing import ArrayLike

__all__ = ["REFERENCE_THRUST_EXPONENT", "Blimpduino", "reference_calibration", "reference_thrust"]

#: Shape of the reference thrust curve: thrust ∝ |duty|^1.5 (propeller thrust grows faster
#: than linearly with motor voltage, as in thesis Fig. 4.4).
REFERENCE_THRUST_EXPONENT = 1.5

_PARAMS = DEFAULT_BLIMP_PARAMS


def reference_thrust(duty: ArrayLike, thrust_limit_n: float = _PARAMS.thrust_limit_n) -> np.ndarray:
    """Reference thrust [N] of one propeller at signed duty ``duty`` (wire units, -255..255).

    Not a measurement (the thesis' Fig. 4.4 data are not published): a curve shaped like it,
    ``sign(d) T_max (|d| / 255)^1.5``, reaching the thesis' limit T_max = 0.0637 N at full duty.
    """
    d = np.asarray(duty, dtype=float)
    return np.sign(d) * thrust_limit_n * (np.abs(d) / PWM_MAX) ** REFERENCE_THRUST_EXPONENT


def reference_calibration() -> Calibration:
    """Calibration thrust [N] <-> signed duty for ``thrust_left`` and ``thrust_right``."""
    magnitudes = np.array([0, 16, 32, 64, 96, 128, 160, 192, 224, 255], dtype=float)
    pwm = np.concatenate([-magnitudes[:0:-1], magnitudes])
    thrust = reference_thrust(pwm)
    return Calibration(
        {"thrust_left": (thrust, pwm), "thrust_right": (thrust, pwm)},
        units={"thrust_left": "N", "thrust_right": "N"},
        vehicle_id="blimpduino-reference",
        source="hilswarm.agents.vehicles.blimpduino.reference_calibration()",
    )


class Blimpduino(Vehicle):
    """The thesis' Blimpduino (see the module docstring for pins, units and frames).

    Vehicle parameters (``params=``):
        battery_charge: state of charge 0..1 the *simulated* battery starts with.
        substeps: RK4 steps per tick of the simulated hardware.
    """

    #: Outputs come from motion capture (``pose_source``): ``check`` wants a source of it.
    needs_pose: ClassVar[bool] = True
    n_inputs: ClassVar[int] = 3
    n_outputs: ClassVar[int] = 4
    input_names: ClassVar[tuple[str, ...]] = ("thrust_left", "thrust_right", "thrust_angle")
    output_names: ClassVar[tuple[str, ...]] = ("x", "y", "z", "yaw")
    input_units: ClassVar[Mapping[str, str]] = {
        "thrust_left": "N",
        "thrust_right": "N",
        "thrust_angle": "rad",
    }
    output_units: ClassVar[Mapping[str, str]] = {"x": "m", "y": "m", "z": "m", "yaw": "rad"}
    profile: ClassVar[str] = "fio"
    default_pinout: ClassVar[Mapping[str, Mapping[str, int | str]]] = {
        "motor": {
            "left_fwd": 5,
            "left_back": 4,
            "left_pwm": 3,
            "right_fwd": 7,
            "right_back": 8,
            "right_pwm": 11,
        },
        "servo": {"pin": 10},
        "standby": {"pin": 6},
        "battery": {"pin": "A0"},
    }
    default_limits: ClassVar[Mapping[str, tuple[float, float]]] = {
        "thrust_left": (-_PARAMS.thrust_limit_n, _PARAMS.thrust_limit_n),
        "thrust_right": (-_PARAMS.thrust_limit_n, _PARAMS.thrust_limit_n),
        "thrust_angle": (_PARAMS.thrust_angle_min_rad, _PARAMS.thrust_angle_max_rad),
    }
    default_params: ClassVar[Mapping[str, Any]] = {"battery_charge": 1.0, "substeps": 2}

    #: Battery options of Code Sample A.2.
    BATTERY_VREF_V = 3.3
    BATTERY_MULTIPLIER = 3.0
    BATTERY_LOW_V = 6.5

    def __init__(
        self,
        *,
        name: str | None = None,
        pinout: Mapping[str, Mapping[str, int | str]] | None = None,
        limits: Mapping[str, Sequence[float]] | None = None,
        calibration: Calibration | str | Path | None = None,
        params: Mapping[str, Any] | None = None,
        initial_state: Sequence[float] | None = None,
        dt: float | None = None,
    ) -> None:
        super().__init__(
            name=name,
            pinout=pinout,
            limits=limits,
            calibration=reference_calibration() if calibration is None else calibration,
            params=params,
            initial_state=initial_state,
            dt=dt,
        )
        charge = self.params["battery_charge"]
        if isinstance(charge, bool) or not isinstance(charge, int | float) or not 0 <= charge <= 1:
            raise VehicleError(
                f"vehicle {self.name!r}: params.battery_charge must be in [0, 1], got {charge!r}"
            )
        substeps = self.params["substeps"]
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise VehicleError(
                f"vehicle {self.name!r}: params.substeps must be an int >= 1, got {substeps!r}"
            )

    # -- devices -----------------------------------------------------------------------------

    def setup_devices(self) -> None:
        p = _PARAMS
        self.motor: HBridgeMotor = self.add_device(HBridgeMotor, "motor", motors=("left", "right"))
        self.servo: Servo = self.add_device(
            Servo,
            "servo",
            min_pulse_us=p.servo_min_us,
            max_pulse_us=p.servo_max_us,
            min_angle_deg=math.degrees(p.thrust_angle_min_rad),
            max_angle_deg=math.degrees(p.thrust_angle_max_rad),
            neutral_deg=math.degrees((p.thrust_angle_min_rad + p.thrust_angle_max_rad) / 2),
        )
        self.standby: OutputPin = self.add_device(OutputPin, "standby", safe_value=0)
        self.battery: Battery = self.add_device(
            Battery,
            "battery",
            vref_v=self.BATTERY_VREF_V,
            multiplier=self.BATTERY_MULTIPLIER,
            low_v=self.BATTERY_LOW_V,
        )
        # Pull the H-bridge standby HIGH, i.e. enable the motors (Code Sample A.2, line 44).
        self.standby.actuate(True)

    def setup_telemetry(self) -> None:
        self.telemetry.add_channel("duty", ("left", "right"))
        self.telemetry.add_channel("servo_angle_deg", ("angle",))

    def record_telemetry(self, k: int, t: float, y: np.ndarray) -> None:
        self.telemetry["duty"].append(k, t, [self.motor.duty("left"), self.motor.duty("right")])
        self.telemetry["servo_angle_deg"].append(k, t, [self.servo.angle_deg])

    # -- the tick ----------------------------------------------------------------------------

    def read_outputs(self) -> np.ndarray:
        """``[x, y, z, yaw]`` from the pose source [m, world NED; rad].

        A pose source in the project's world frame (``frame = "world"``: the mocap system) is
        mapped into NED by :func:`~hilswarm.agents.mocap.frames.world_to_ned`; a
        :class:`~hilswarm.agents.sim.mocap.SimulatedMocap` of the blimp plant is NED already.
        """
        if self.pose_source is None:
            raise VehicleError(
                f"vehicle {self.name!r} (Blimpduino) has no pose source: its outputs come from "
                "motion capture; set vehicle.pose_source (e.g. a SimulatedMocap)"
            )
        pose = np.asarray(self.pose_source.pose(), dtype=float).reshape(-1)
        if pose.shape != (6,):
            raise VehicleError(
                f"vehicle {self.name!r}: pose source returned shape {pose.shape}, expected "
                "[x, y, z, roll, pitch, yaw]"
            )
        if getattr(self.pose_source, "frame", "ned") == "world":  # mocap: world -> NED
            pose = world_to_ned(pose)
        return pose[[0, 1, 2, 5]]

    def actuate(self, u: np.ndarray) -> np.ndarray:
        """Thrusts [N] -> signed duties (calibration), μ [rad] -> servo angle [deg].

        Returns the input as applied: thrusts of the rounded duties (through the calibration)
        and the servo angle actually commanded.
        """
        applied = np.empty(3)
        for index, (motor, name) in enumerate((("left", "thrust_left"), ("right", "thrust_right"))):
            duty = self.motor.actuate(motor, self.to_pwm(name, float(u[index])))
            applied[index] = self.to_u(name, duty) if duty else 0.0
        applied[2] = math.radians(self.servo.actuate(math.degrees(float(u[2]))))
        self.standby.actuate(True)
        return applied

    def safe_inputs(self) -> np.ndarray:
        """Safe mode: no thrust, servo neutral (μ = -π/2)."""
        return np.array([0.0, 0.0, math.radians(self.servo.neutral_deg)])

    def simulated_hardware(
        self, *, initial_state: Sequence[float] | None, dt: float
    ) -> BlimpPinPlant:
        """A :class:`BlimpPinPlant` on this vehicle's pins and calibration.

        ``initial_state``: ``[x, y, z, yaw]`` at rest or the 12-state of
        :class:`~hilswarm.agents.sim.blimp.BlimpPlant` (default ``self.initial_state``, else
        hovering at altitude 1 m at the origin facing +x).
        """
        state = initial_state if initial_state is not None else self.initial_state
        if state is None:
            state = (0.0, 0.0, -1.0, 0.0)
        params: BlimpParams = _PARAMS.with_changes(
            battery=BatteryParams(
                multiplier=self.BATTERY_MULTIPLIER,
                low_v=self.BATTERY_LOW_V,
                initial_charge=float(self.params["battery_charge"]),
            )
        )
        motor = self.motor.pinout
        pinout = BlimpPinout(
            left_fwd=motor["left_fwd"],
            left_back=motor["left_back"],
            left_pwm=motor["left_pwm"],
            right_fwd=motor["right_fwd"],
            right_back=motor["right_back"],
            right_pwm=motor["right_pwm"],
            servo=self.servo.pin("pin"),
            standby=self.standby.pin("pin"),
            battery=self.battery.pin("pin"),
        )
        if self.calibration is None:  # pragma: no cover - the constructor always sets one
            raise VehicleError(f"vehicle {self.name!r} has no calibration")
        return BlimpPinPlant(
            self.calibration,
            initial_state=state,
            params=params,
            pinout=pinout,
            substeps=int(self.params["substeps"]),
        )
