"""Exact kinematics of a differential-drive (two-wheeled) ground vehicle, and its pin-level plant.

Kinematics (thesis §5.3, eqs. 5.1-5.8), world frame x-y [m], heading ψ [rad] measured from the
world x axis towards the world y axis (counter-clockwise positive)::

    V    = (v_L + v_R) / 2          forward speed [m/s]                      (5.1)
    ψ̇    = (v_R - v_L) / b          yaw rate [rad/s], b = wheel track [m]    (5.2)
    ẋ    = V cos ψ,   ẏ = V sin ψ

With wheel speeds held constant over Δt the ODE has the closed-form circular-arc solution
(θ = ψ̇ Δt)::

    x = x0 + (V/ψ̇) [ sin θ cos ψ0 - (1 - cos θ) sin ψ0 ]
    y = y0 + (V/ψ̇) [ sin θ sin ψ0 + (1 - cos θ) cos ψ0 ]
    ψ = ψ0 + θ

**Corrections to the printed thesis.** Eqs. 5.3/5.4 (and 5.6/5.7) as printed write
``sin(ψ Δt)``/``cos(ψ Δt)`` where the argument must be the turned angle ``ψ̇ Δt``, and eq. 5.4
has the sign of the ``(1 - cos θ) cos ψ0`` term wrong: integrating ``ẏ = V sin(ψ0 + ψ̇ t)``
gives ``y - y0 = (V/ψ̇)[cos ψ0 - cos(ψ0 + θ)] = (V/ψ̇)[sin θ sin ψ0 + (1 - cos θ) cos ψ0]``
(a vehicle starting at ψ0 = 0 and turning left must move to +y, which the printed minus sign
contradicts). Eq. 5.2 divides by the robot radius R; physically the divisor is the distance
between the two wheel contact points (the track b). The Frisbee's wheels sit at the rim of its
18 cm body, so b = 0.18 m here (see :data:`FRISBEE_GEOMETRY`); the thesis' R reads as that
track.

**Straight-line limit without dividing by zero.** The update is evaluated as
``V Δt · [S(θ), C(θ)]`` rotated by ψ0, with ``S(θ) = sin θ / θ`` and ``C(θ) = (1 - cos θ)/θ``.
Below ``|θ| < SERIES_THRESHOLD`` both are evaluated by their Taylor series (error < 1e-20
relative), so ``v_L = v_R`` (θ = 0) gives exactly the straight line ``V Δt (cos ψ0, sin ψ0)``
and nearby speeds lose no precision to cancellation in ``1 - cos θ``; above it the half-angle
form ``C(θ) = 2 sin²(θ/2)/θ`` is used, which has no cancellation either.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import ClassVar, Protocol

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.plant import ContinuousPlant, wrap_angle
from numpy.typing import ArrayLike

#: Below this |θ| = |ψ̇ Δt| [rad] the arc functions use their Taylor series.
SERIES_THRESHOLD = 1e-2

_FLOAT64 = np.dtype(np.float64)


@dataclass(frozen=True, slots=True)
class DriveGeometry:
    """Geometry and limits of a differential-drive vehicle.

    Attributes:
        track_width_m: distance between the two wheels' contact points [m] (b in eq. 5.2).
        wheel_diameter_m: wheel diameter [m].
        max_wheel_speed_m_s: largest wheel surface speed either way [m/s] (> 0).
    """

    track_width_m: float
    wheel_diameter_m: float
    max_wheel_speed_m_s: float

    def __post_init__(self) -> None:
        for name in ("track_width_m", "wheel_diameter_m", "max_wheel_speed_m_s"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise PlantError(f"DriveGeometry.{name} must be a finite number > 0, got {value!r}")

    @property
    def max_yaw_rate_rad_s(self) -> float:
        """Yaw rate [rad/s] when the wheels turn at full speed in opposite directions."""
        return 2.0 * self.max_wheel_speed_m_s / self.track_width_m


#: The thesis' Frisbee bot (§5.1): 7 cm wheels at the rim of an 18 cm body, at most about
#: 1 wheel revolution per second (2π rad/s), i.e. π · 0.07 m/s ≈ 0.22 m/s at the tyre.
FRISBEE_GEOMETRY = DriveGeometry(
    track_width_m=0.18, wheel_diameter_m=0.07, max_wheel_speed_m_s=math.pi * 0.07
)


def body_rates(v_left: float, v_right: float, track_width_m: float) -> tuple[float, float]:
    """Wheel speeds [m/s] -> (forward speed V [m/s], yaw rate ψ̇ [rad/s]) (eqs. 5.1, 5.2)."""
    return 0.5 * (v_left + v_right), (v_right - v_left) / track_width_m


def wheel_speeds(speed: float, yaw_rate: float, track_width_m: float) -> tuple[float, float]:
    """(forward speed V [m/s], yaw rate ψ̇ [rad/s]) -> (v_left, v_right) [m/s]; inverse of
    :func:`body_rates`."""
    half = 0.5 * yaw_rate * track_width_m
    return speed - half, speed + half


def clip_wheel_speeds(v_left: float, v_right: float, limit: float) -> tuple[float, float]:
    """Clip each wheel speed [m/s] to ±limit on its own (what a saturated motor does)."""
    return min(max(v_left, -limit), limit), min(max(v_right, -limit), limit)


def scale_wheel_speeds(v_left: float, v_right: float, limit: float) -> tuple[float, float]:
    """Scale both wheel speeds [m/s] by one factor so the larger is at most ``limit``.

    Unlike :func:`clip_wheel_speeds` this keeps the ratio, hence the path curvature: what a
    controller should do before handing speeds to a saturating plant.
    """
    largest = max(abs(v_left), abs(v_right))
    if largest <= limit:
        return v_left, v_right
    factor = limit / largest
    return v_left * factor, v_right * factor


def arc_functions(theta: float) -> tuple[float, float]:
    """Return ``(sin θ / θ, (1 - cos θ) / θ)`` for a turned angle θ [rad], finite at θ = 0.

    Taylor series below :data:`SERIES_THRESHOLD` (truncation error below θ⁸/9! ≈ 3e-22), the
    cancellation-free half-angle forms above it.
    """
    if abs(theta) < SERIES_THRESHOLD:
        t2 = theta * theta
        sin_over = 1.0 - t2 / 6.0 * (1.0 - t2 / 20.0 * (1.0 - t2 / 42.0))
        one_minus_cos_over = theta / 2.0 * (1.0 - t2 / 12.0 * (1.0 - t2 / 30.0 * (1.0 - t2 / 56.0)))
        return sin_over, one_minus_cos_over
    half = 0.5 * theta
    return math.sin(theta) / theta, 2.0 * math.sin(half) ** 2 / theta


def arc_step(
    x: float,
    y: float,
    psi: float,
    v_left: float,
    v_right: float,
    *,
    dt: float,
    track_width_m: float,
) -> tuple[float, float, float]:
    """Exact pose after ``dt`` [s] at constant wheel speeds (the closed-form arc).

    Args:
        x, y: position [m, world frame] at the start.
        psi: heading [rad, from world x towards world y] at the start.
        v_left, v_right: wheel surface speeds [m/s], forward positive.
        dt: duration [s], >= 0.
        track_width_m: wheel track b [m].

    Returns:
        ``(x, y, psi)`` at the end; psi is not wrapped.
    """
    speed, yaw_rate = body_rates(v_left, v_right, track_width_m)
    theta = yaw_rate * dt
    s, c = arc_functions(theta)
    distance = speed * dt
    cos0, sin0 = math.cos(psi), math.sin(psi)
    forward, left = distance * s, distance * c  # displacement in the start body frame
    return x + forward * cos0 - left * sin0, y + forward * sin0 + left * cos0, psi + theta


class DifferentialDrive(ContinuousPlant):
    """Differential-drive kinematics as a :class:`ContinuousPlant` (python-control style).

    State ``x = [x, y, psi]`` (position [m, world frame], heading [rad, unwrapped]); input
    ``u = [v_left, v_right]`` wheel speeds [m/s]; output ``y = [x, y, psi]`` with psi wrapped
    to [-π, π). Wheel speeds beyond ``geometry.max_wheel_speed_m_s`` are clipped (saturated
    motors). :meth:`dynamics` serves generic integrators (:meth:`advance` with ``"euler"`` or
    ``"rk4"``); :meth:`step` — or :meth:`advance` with ``method="exact"`` — is the exact arc
    update and is what simulations of this vehicle should use.

    Args:
        geometry: track, wheel size and speed limit (default: the thesis' Frisbee bot).
    """

    #: Units of the inputs and outputs (recorded in the MCAP schemas, shown on plot axes).
    input_units: ClassVar[Mapping[str, str]] = {"v_left": "m/s", "v_right": "m/s"}
    output_units: ClassVar[Mapping[str, str]] = {"x": "m", "y": "m", "psi": "rad"}

    def __init__(self, geometry: DriveGeometry = FRISBEE_GEOMETRY) -> None:
        if not isinstance(geometry, DriveGeometry):
            raise PlantError(f"geometry must be a DriveGeometry, got {type(geometry).__name__}")
        self.geometry = geometry
        self._set_sizes(
            3,
            2,
            3,
            state_names=("x", "y", "psi"),
            input_names=("v_left", "v_right"),
            output_names=("x", "y", "psi"),
        )

    def _checked(
        self, x: ArrayLike, u: ArrayLike
    ) -> tuple[np.ndarray | list[float], tuple[float, float]]:
        if (
            type(x) is np.ndarray
            and type(u) is np.ndarray
            and x.dtype == _FLOAT64
            and u.dtype == _FLOAT64
            and x.shape == (3,)
            and u.shape == (2,)
        ):  # the common case, checked in plain floats (same values as the numpy path)
            state_values = x.tolist()
            v_left, v_right = u.tolist()
            if all(map(math.isfinite, state_values)) and math.isfinite(v_left + v_right):
                limit = self.geometry.max_wheel_speed_m_s
                return state_values, clip_wheel_speeds(v_left, v_right, limit)
        state = np.asarray(x, dtype=float).reshape(-1)
        inputs = np.asarray(u, dtype=float).reshape(-1)
        if state.shape != (3,):
            raise PlantError(
                f"differential drive state must be [x, y, psi], got shape {state.shape}"
            )
        if inputs.shape != (2,):
            raise PlantError(
                f"differential drive input must be [v_left, v_right], got shape {inputs.shape}"
            )
        if not (np.all(np.isfinite(state)) and np.all(np.isfinite(inputs))):
            raise PlantError(f"non-finite state {state} or input {inputs}")
        limit = self.geometry.max_wheel_speed_m_s
        return state, clip_wheel_speeds(float(inputs[0]), float(inputs[1]), limit)

    def dynamics(self, t: float, x: ArrayLike, u: ArrayLike) -> np.ndarray:
        """dx/dt = [V cos ψ, V sin ψ, ψ̇] [m/s, m/s, rad/s] for state x and input u."""
        state, (v_left, v_right) = self._checked(x, u)
        speed, yaw_rate = body_rates(v_left, v_right, self.geometry.track_width_m)
        return np.array([speed * math.cos(state[2]), speed * math.sin(state[2]), yaw_rate])

    def output(self, t: float, x: ArrayLike, u: ArrayLike | None = None) -> np.ndarray:
        """y = [x, y, psi] with psi wrapped to [-π, π)."""
        state = np.asarray(x, dtype=float).reshape(-1)
        if state.shape != (3,):
            raise PlantError(
                f"differential drive state must be [x, y, psi], got shape {state.shape}"
            )
        return np.array([state[0], state[1], wrap_angle(float(state[2]))])

    def advance(
        self,
        t: float,
        x: ArrayLike,
        u: ArrayLike,
        dt: float,
        *,
        method: str = "exact",
        substeps: int = 1,
    ) -> np.ndarray:
        """State at ``t + dt`` with ``u`` held: ``method="exact"`` (default) is the closed-form
        arc (``substeps`` ignored); ``"euler"``/``"rk4"`` integrate :meth:`dynamics`."""
        if method == "exact":
            return self.step(x, u, dt)
        return super().advance(t, x, u, dt, method=method, substeps=substeps)

    def step_floats(
        self, state: Sequence[float], wheels: Sequence[float], *, dt: float
    ) -> tuple[float, float, float]:
        """:meth:`step` on plain floats, the same values: ``state = (x, y, psi)`` [m, m, rad]
        after ``dt`` [s] at ``wheels = (v_left, v_right)`` [m/s] (clipped to the limit).

        Raises:
            PlantError: non-finite values or a negative/non-finite ``dt``.
        """
        if not (math.isfinite(dt) and dt >= 0):
            raise PlantError(f"dt must be a finite number >= 0 [s], got {dt!r}")
        x, y, psi = state
        v_left, v_right = wheels
        if not all(map(math.isfinite, (x, y, psi, v_left, v_right))):
            raise PlantError(f"non-finite state {[x, y, psi]} or input {[v_left, v_right]}")
        limit = self.geometry.max_wheel_speed_m_s
        v_left, v_right = clip_wheel_speeds(v_left, v_right, limit)
        return arc_step(
            x, y, psi, v_left, v_right, dt=dt, track_width_m=self.geometry.track_width_m
        )

    def step(self, x: ArrayLike, u: ArrayLike, dt: float) -> np.ndarray:
        """Exact state after ``dt`` [s] with the (clipped) input held constant."""
        if not (math.isfinite(dt) and dt >= 0):
            raise PlantError(f"dt must be a finite number >= 0 [s], got {dt!r}")
        state, (v_left, v_right) = self._checked(x, u)
        return np.array(
            arc_step(*state, v_left, v_right, dt=dt, track_width_m=self.geometry.track_width_m),
            dtype=float,
        )


class PwmToSpeed(Protocol):
    """What :class:`FrisbeePinPlant` needs of a calibration: signed PWM duty -> input value."""

    def to_u(self, name: str, pwm: float) -> float:  # pragma: no cover - protocol
        """Input value (here wheel speed [m/s]) that signed duty ``pwm`` produces."""
        ...


@dataclass(frozen=True, slots=True)
class HBridgePins:
    """Pins of one H-bridge channel (Arduino numbering, A0 = 14).

    Attributes:
        fwd: direction pin that is HIGH to drive forward.
        back: direction pin that is HIGH to drive backward.
        pwm: PWM pin carrying the duty 0-255.
    """

    fwd: int
    back: int
    pwm: int


@dataclass(frozen=True, slots=True)
class BatteryModel:
    """A battery that discharges linearly in time, as seen by a voltage divider on an analog pin.

    Attributes:
        pin: analog pin the divider feeds (Arduino numbering, A0 = 14).
        full_v: battery voltage at t = 0 [V].
        drain_v_per_s: voltage lost per second of simulated time [V/s] (>= 0).
        empty_v: the voltage never drops below this [V].
        multiplier: divider ratio, battery voltage / pin voltage (>= 1).
    """

    pin: int
    full_v: float = 12.6
    drain_v_per_s: float = 0.0
    empty_v: float = 9.0
    multiplier: float = 3.0

    def __post_init__(self) -> None:
        if self.drain_v_per_s < 0 or self.multiplier < 1 or self.empty_v > self.full_v:
            raise PlantError(
                "BatteryModel needs drain_v_per_s >= 0, multiplier >= 1 and empty_v <= full_v, "
                f"got {self}"
            )

    def voltage(self, t: float) -> float:
        """Battery voltage [V] after ``t`` [s] of simulated time."""
        return max(self.empty_v, self.full_v - self.drain_v_per_s * t)


class FrisbeePinPlant:
    """Pin-level plant of a differential-drive vehicle behind two H-bridge channels.

    Implements the ``PinPlant`` protocol of :mod:`hilswarm.agents.link.sim_board`: on every
    :meth:`advance` it reads both H-bridge channels from the board's outputs (direction pins
    and PWM duty, wire units), turns each signed duty into a wheel speed [m/s] through the
    *inverse* of the vehicle's calibration (``calibration.to_u``), clips it to the speed limit,
    and moves the pose by the exact arc over ``dt``. Direction pins both LOW or both HIGH mean
    the wheel stands still (coast/brake).

    Args:
        calibration: maps signed duty -> wheel speed for inputs ``"v_left"``/``"v_right"``.
        left, right: the two H-bridge channels.
        initial_state: ``[x, y, psi]`` [m, m, rad, world frame] at t = 0.
        geometry: track, wheels and speed limit.
        battery: optional battery whose divided voltage is reported on its analog pin.
        input_names: calibration names of the left and right wheel inputs.
    """

    def __init__(
        self,
        calibration: PwmToSpeed,
        *,
        left: HBridgePins,
        right: HBridgePins,
        initial_state: Sequence[float] = (0.0, 0.0, 0.0),
        geometry: DriveGeometry = FRISBEE_GEOMETRY,
        battery: BatteryModel | None = None,
        input_names: tuple[str, str] = ("v_left", "v_right"),
    ) -> None:
        self._drive = DifferentialDrive(geometry)
        state = np.asarray(initial_state, dtype=float).reshape(-1)
        if state.shape != (3,) or not np.all(np.isfinite(state)):
            raise PlantError(
                f"initial_state must be three finite numbers [x, y, psi], got {initial_state!r}"
            )
        self._calibration = calibration
        self._channels = (left, right)
        self._input_names = input_names
        self._battery = battery
        self.state = state
        self.time_s = 0.0
        self.wheel_speeds = np.zeros(2)

    @property
    def geometry(self) -> DriveGeometry:
        """Geometry and limits used."""
        return self._drive.geometry

    def signed_duty(self, outputs: Mapping[int, int], channel: HBridgePins) -> int:
        """Signed duty [-255, 255] an H-bridge channel is driven with (0 = stopped)."""
        fwd, back = outputs.get(channel.fwd, 0), outputs.get(channel.back, 0)
        duty = int(outputs.get(channel.pwm, 0))
        if fwd and not back:
            return duty
        if back and not fwd:
            return -duty
        return 0

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        """Apply the board's outputs (wire units) for ``dt`` [s]; return analog inputs [V]."""
        speeds = []
        to_u = self._calibration.to_u
        for name, channel in zip(self._input_names, self._channels, strict=True):
            duty = self.signed_duty(outputs, channel)
            speeds.append(float(to_u(name, duty)) if duty else 0.0)
        self.wheel_speeds = np.array(speeds, dtype=float)
        state = self.state
        if type(state) is np.ndarray and state.dtype == _FLOAT64 and state.shape == (3,):
            # The common case: the exact arc in plain floats.
            self.state = np.array(self._drive.step_floats(state.tolist(), speeds, dt=dt))
        else:
            self.state = self._drive.step(state, self.wheel_speeds, dt)
        self.time_s += dt
        return self.analog_inputs()

    def analog_inputs(self) -> dict[int, float]:
        """Voltages [V] at the analog pins the plant drives (the battery divider, if any)."""
        if self._battery is None:
            return {}
        return {self._battery.pin: self._battery.voltage(self.time_s) / self._battery.multiplier}

    def pose(self) -> np.ndarray:
        """``[x, y, z, roll, pitch, yaw]`` [m, world frame; rad], z = roll = pitch = 0."""
        state = self.state
        x, y, psi = state.tolist() if type(state) is np.ndarray else state
        return np.array([x, y, 0.0, 0.0, 0.0, wrap_angle(psi)])
