"""Nonlinear 6-DOF model of the Blimpduino airship (thesis §4.3, eqs. 4.1-4.20).

Frames (a deliberate deviation from the thesis, whose body frame is *left-handed*, §4.3):

* **body frame** — right-handed, origin at the centre of gravity (cg): x forward through the
  nose, y right (starboard), z down (towards the gondola). The centre of buoyancy (cb) is
  ``r_z`` above the cg, at ``(0, 0, -r_z)``.
* **world frame** — NED-like, right-handed: x and y horizontal, z **down**; the altitude is
  ``-z``. Heading ψ is measured from world x towards world y (ψ = atan2(Δy, Δx) points the nose
  along (Δx, Δy)). Attitude: Z-Y-X Euler angles (roll φ, pitch θ, heading ψ); the body-to-world
  rotation is ``R = Rz(ψ) Ry(θ) Rx(φ)`` (the transpose of the thesis' C_I/B, eq. 4.18).

State ``x`` (12): ``[x, y, z]`` position [m, world], ``[φ, θ, ψ]`` [rad],
``[u, v, w]`` body velocity [m/s, body], ``[p, q, r]`` body rates [rad/s, body].

Input ``u`` (3): ``[T_left, T_right, μ]`` — thrust of the left and right propeller [N]
(positive: along the thrust direction) and thrust angle μ [rad]. Thrusts are clipped to
``±thrust_limit_n`` and μ to the servo's physical range (default -π..0), as the hardware
would. A positive thrust at angle μ pushes along ``(cos μ, 0, sin μ)`` in the body frame, so
μ = 0 is forward, μ = -π/2 is **up** (-z) and μ = -π is backward (with z down this is the
thesis' eq. 4.11 unchanged; the servo's -180°..0° range covers the upper half-plane and
negative thrusts cover the rest, as in thesis §4.1).

Output ``y`` (4): ``[x, y, z, ψ]`` — what motion capture gives the controller (ψ wrapped to
[-π, π)).

Equations (eq. 4.20), with V = [v; ω] and M = M_RB + M_A (eqs. 4.2-4.10)::

    M dV/dt = F_p + F_d + F_g + F_c
    F_p = [(T_l + T_r) cos μ, 0, (T_l + T_r) sin μ,
           -(T_l - T_r) sin μ l, 0, (T_l - T_r) cos μ l]                  (4.11 + roll term)
    F_d = -diag(D_i + D_i2 |V_i|) V                                         (4.12, 4.13)
    F_g = [(W - F_b) g_b;  -r_z F_b cos θ sin φ, -r_z F_b sin θ, 0]         (4.14)
    F_c = [S(M11 v) ω;  S(M11 v) v + S(M22 ω) ω]                           (4.15, 4.16)
    dP/dt = R v,   dΦ/dt = H(φ, θ) ω                                        (4.17-4.19)

where ``S(a) b = a × b`` and ``g_b = R^T [0, 0, 1]`` is "down" in body axes.

Deviations from the printed thesis, each on purpose:

* right-handed frames (above);
* eq. 4.16 prints all three non-zero Coriolis blocks as S(M11 v + M12 ω); the lower-right block
  must be S(M21 v + M22 ω) (Kirchhoff's equations; M12 = M21 = 0 here because M is diagonal).
  With it the Coriolis forces do no work (Vᵀ F_c = 0), which the tests check;
* eq. 4.11 omits the roll moment of differential thrust when the thrust is tilted
  (``-(T_l - T_r) l sin μ``); it is included here (it vanishes at μ = 0);
* the net weight W - F_b (zero at neutral buoyancy, the thesis' assumption) is kept so an
  off-ballast blimp can be simulated;
* added mass uses the mass of displaced air ρV rather than m (equal at neutral buoyancy).

Like the thesis, the thrust line is taken through the cg (no pitch moment from thrust), drag
acts at the cg, and the added mass matrix is diagonal.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import ClassVar, Protocol

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.blimp_params import DEFAULT_BLIMP_PARAMS, BlimpParams
from hilswarm.agents.sim.plant import ContinuousPlant, integrate, wrap_angle
from numpy.typing import ArrayLike

__all__ = [
    "INPUT_NAMES",
    "OUTPUT_NAMES",
    "REDUCED_STATE_NAMES",
    "STATE_NAMES",
    "BatteryState",
    "BlimpPinPlant",
    "BlimpPinout",
    "BlimpPlant",
    "euler_rate_matrix",
    "full_state_from_reduced",
    "rotation_body_to_world",
    "wrap_angle",
]

STATE_NAMES = ("x", "y", "z", "roll", "pitch", "yaw", "u", "v", "w", "p", "q", "r")
INPUT_NAMES = ("thrust_left", "thrust_right", "thrust_angle")
OUTPUT_NAMES = ("x", "y", "z", "yaw")
#: The thesis' reduced 8-state model (§4.4.1): four velocities, four navigation states.
REDUCED_STATE_NAMES = ("u", "v", "w", "r", "x", "y", "z", "yaw")
#: Indices of the reduced states inside the full 12-state vector.
REDUCED_INDEX = (6, 7, 8, 11, 0, 1, 2, 5)


def rotation_body_to_world(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(ψ) Ry(θ) Rx(φ): body-frame vector -> world-frame vector (both right-handed)."""
    cf, sf = math.cos(roll), math.sin(roll)
    ct, st = math.cos(pitch), math.sin(pitch)
    cp, sp = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf],
            [sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf],
            [-st, ct * sf, ct * cf],
        ]
    )


def euler_rate_matrix(roll: float, pitch: float) -> np.ndarray:
    """H(φ, θ) of eq. 4.19: [φ̇, θ̇, ψ̇] = H [p, q, r] (singular at θ = ±π/2)."""
    cf, sf = math.cos(roll), math.sin(roll)
    ct, tt = math.cos(pitch), math.tan(pitch)
    return np.array([[1.0, sf * tt, cf * tt], [0.0, cf, -sf], [0.0, sf / ct, cf / ct]])


def full_state_from_reduced(reduced: ArrayLike) -> np.ndarray:
    """12-state vector from the reduced ``[u, v, w, r, x, y, z, ψ]`` (φ = θ = p = q = 0)."""
    s = np.asarray(reduced, dtype=float).reshape(-1)
    if s.shape != (8,):
        raise PlantError(
            f"reduced blimp state must have 8 entries {REDUCED_STATE_NAMES}, got {s.shape}"
        )
    x = np.zeros(12)
    x[list(REDUCED_INDEX)] = s
    return x


class BlimpPlant(ContinuousPlant):
    """The Blimpduino's nonlinear 6-DOF dynamics (see the module docstring for frames/units).

    Args:
        params: physical parameters (default :data:`DEFAULT_BLIMP_PARAMS`).

    Attributes:
        params: the parameters used.
        mass_diagonal: diagonal of M [kg ×3, kg·m² ×3].
    """

    #: :meth:`pose` is in the NED frame (z down), see :mod:`hilswarm.agents.mocap.frames`.
    pose_frame = "ned"
    #: Units of the inputs and outputs (recorded in the MCAP schemas, shown on plot axes).
    input_units: ClassVar[Mapping[str, str]] = {
        "thrust_left": "N",
        "thrust_right": "N",
        "thrust_angle": "rad",
    }
    output_units: ClassVar[Mapping[str, str]] = {"x": "m", "y": "m", "z": "m", "yaw": "rad"}

    def __init__(self, params: BlimpParams = DEFAULT_BLIMP_PARAMS) -> None:
        if not isinstance(params, BlimpParams):
            raise PlantError(f"BlimpPlant needs BlimpParams, got {type(params).__name__}")
        self.params = params
        self._set_sizes(
            12, 3, 4, state_names=STATE_NAMES, input_names=INPUT_NAMES, output_names=OUTPUT_NAMES
        )
        self.mass_diagonal = params.mass_matrix_diagonal
        self._inv_mass = 1.0 / self.mass_diagonal
        self._d_lin = np.asarray(params.damping_linear, dtype=float)
        self._d_quad = np.asarray(params.damping_quadratic, dtype=float)

    # -- inputs ------------------------------------------------------------------------------

    def saturate(self, u: ArrayLike) -> np.ndarray:
        """Clip ``[T_l, T_r, μ]`` to the thrust limits [N] and the servo range [rad]."""
        inputs = self.check_input(u)
        p = self.params
        limit = p.thrust_limit_n
        return np.array(
            [
                min(max(inputs[0], -limit), limit),
                min(max(inputs[1], -limit), limit),
                min(max(inputs[2], p.thrust_angle_min_rad), p.thrust_angle_max_rad),
            ]
        )

    def generalized_forces(self, x: np.ndarray, u: np.ndarray) -> dict[str, np.ndarray]:
        """The four force/moment vectors of eq. 4.20a in body axes [N ×3, N·m ×3].

        Returns a dict with keys ``propulsive``, ``damping``, ``restoring``, ``coriolis``.
        ``u`` is used as given (call :meth:`saturate` first for hardware limits).
        """
        p = self.params
        roll, pitch = x[3], x[4]
        vel = np.asarray(x[6:12], dtype=float)
        t_l, t_r, mu = u
        total, diff = t_l + t_r, t_l - t_r
        cm, sm = math.cos(mu), math.sin(mu)
        arm = p.thruster_arm_m
        propulsive = np.array([total * cm, 0.0, total * sm, -diff * sm * arm, 0.0, diff * cm * arm])
        damping = -(self._d_lin + self._d_quad * np.abs(vel)) * vel
        cf, sf, ct, st = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        net_weight = p.mass_kg * p.gravity_m_s2 - p.buoyancy_n
        restoring_moment = p.cg_below_cb_m * p.buoyancy_n
        restoring = np.array(
            [
                -net_weight * st,
                net_weight * ct * sf,
                net_weight * ct * cf,
                -restoring_moment * ct * sf,
                -restoring_moment * st,
                0.0,
            ]
        )
        m = self.mass_diagonal
        lin_momentum = m[:3] * vel[:3]
        ang_momentum = m[3:] * vel[3:]
        coriolis = np.concatenate(
            [
                np.cross(lin_momentum, vel[3:]),
                np.cross(lin_momentum, vel[:3]) + np.cross(ang_momentum, vel[3:]),
            ]
        )
        return {
            "propulsive": propulsive,
            "damping": damping,
            "restoring": restoring,
            "coriolis": coriolis,
        }

    # -- ContinuousPlant ---------------------------------------------------------------------

    def dynamics(self, t: float, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dx/dt of the 12-state model (eq. 4.20) with the input saturated."""
        state = self.check_state(x)
        inputs = self.saturate(u)
        forces = self.generalized_forces(state, inputs)
        accel = self._inv_mass * (
            forces["propulsive"] + forces["damping"] + forces["restoring"] + forces["coriolis"]
        )
        roll, pitch, yaw = state[3], state[4], state[5]
        if abs(math.cos(pitch)) < 1e-6:
            raise PlantError(f"BlimpPlant: pitch {pitch} rad is at the Euler singularity ±π/2")
        position_rate = rotation_body_to_world(roll, pitch, yaw) @ state[6:9]
        angle_rate = euler_rate_matrix(roll, pitch) @ state[9:12]
        return np.concatenate([position_rate, angle_rate, accel])

    def output(self, t: float, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """``[x, y, z, ψ]`` [m, m, m (world, z down), rad wrapped to [-π, π)]."""
        state = self.check_state(x)
        return np.array([state[0], state[1], state[2], wrap_angle(float(state[5]))])

    # -- the reduced model of §4.4.1 ---------------------------------------------------------

    def reduced_dynamics(self, s: ArrayLike, u: ArrayLike) -> np.ndarray:
        """d/dt of the reduced state ``[u, v, w, r, x, y, z, ψ]`` (φ = θ = p = q = 0).

        This is the thesis' eight-state model (§4.4.1) used for trim and linearisation. The
        input is *not* saturated (trim and Jacobians need the smooth model).
        """
        state = full_state_from_reduced(s)
        inputs = self.check_input(u)
        forces = self.generalized_forces(state, inputs)
        accel = self._inv_mass * (
            forces["propulsive"] + forces["damping"] + forces["restoring"] + forces["coriolis"]
        )
        yaw = state[5]
        position_rate = rotation_body_to_world(0.0, 0.0, yaw) @ state[6:9]
        return np.array([accel[0], accel[1], accel[2], accel[5], *position_rate, state[11]])

    # -- bookkeeping -------------------------------------------------------------------------

    def energy(self, x: ArrayLike) -> float:
        """Mechanical energy [J]: kinetic ½ Vᵀ M V (incl. added mass) + potential.

        Potential: the cg/cb couple ``r_z F_b (1 - cos φ cos θ)`` plus the net weight times the
        altitude ``(W - F_b)(-z)``. Conserved without thrust and damping.
        """
        state = self.check_state(x)
        p = self.params
        vel = state[6:12]
        kinetic = 0.5 * float(np.sum(self.mass_diagonal * vel**2))
        couple = p.cg_below_cb_m * p.buoyancy_n * (1.0 - math.cos(state[3]) * math.cos(state[4]))
        weight = (p.mass_kg * p.gravity_m_s2 - p.buoyancy_n) * (-state[2])
        return kinetic + couple + weight

    def initial_state(self, pose: Sequence[float] = (0.0, 0.0, 0.0, 0.0)) -> np.ndarray:
        """A 12-state at rest from ``[x, y, z, ψ]`` [m, m, m, rad] (level attitude)."""
        values = np.asarray(pose, dtype=float).reshape(-1)
        if values.shape != (4,) or not np.all(np.isfinite(values)):
            raise PlantError(f"BlimpPlant.initial_state needs [x, y, z, yaw], got {pose!r}")
        state = np.zeros(12)
        state[[0, 1, 2, 5]] = values
        return state


# --- the pin-level plant ------------------------------------------------------------------


class ThrustCalibration(Protocol):
    """What :class:`BlimpPinPlant` needs of a calibration: signed PWM duty -> thrust [N]."""

    def to_u(self, name: str, pwm: float) -> float:  # pragma: no cover - protocol
        """Input value (here thrust [N]) that signed duty ``pwm`` produces."""
        ...


class BlimpPinout:
    """Pin numbers of the Blimpduino (Arduino numbering, A0 = 14), thesis Code Sample A.2.

    Attributes:
        left_fwd, left_back, left_pwm: left motor H-bridge direction pins and PWM pin.
        right_fwd, right_back, right_pwm: right motor H-bridge pins.
        servo: thrust-angle servo pulse pin.
        standby: H-bridge enable (standby) pin, HIGH = motors enabled.
        battery: analog pin fed by the battery divider.
    """

    def __init__(
        self,
        *,
        left_fwd: int = 5,
        left_back: int = 4,
        left_pwm: int = 3,
        right_fwd: int = 7,
        right_back: int = 8,
        right_pwm: int = 11,
        servo: int = 10,
        standby: int = 6,
        battery: int = 14,
    ) -> None:
        self.left_fwd, self.left_back, self.left_pwm = left_fwd, left_back, left_pwm
        self.right_fwd, self.right_back, self.right_pwm = right_fwd, right_back, right_pwm
        self.servo, self.standby, self.battery = servo, standby, battery

    def __repr__(self) -> str:
        return f"BlimpPinout({vars(self)})"


class BatteryState:
    """Discharge model of the LiPo: charge integrates current; volts = OCV(charge) - I R.

    Args:
        params: battery parameters (from :class:`BlimpParams`).
    """

    def __init__(self, params: BlimpParams) -> None:
        self._battery = params.battery
        self._thrust_limit = params.thrust_limit_n
        self.charge = float(self._battery.initial_charge)
        self.current_a = self._battery.idle_current_a

    def advance(self, thrusts: Sequence[float], servo_on: bool, dt: float) -> None:
        """Draw the load of ``thrusts`` [N] (and the servo) for ``dt`` [s]."""
        b = self._battery
        current = b.idle_current_a + (b.servo_current_a if servo_on else 0.0)
        current += sum(b.motor_current_a * min(abs(t) / self._thrust_limit, 1.0) for t in thrusts)
        self.current_a = current
        self.charge = max(0.0, self.charge - current * dt / 3600.0 / b.capacity_ah)

    @property
    def volts(self) -> float:
        """Terminal voltage [V] under the present load."""
        b = self._battery
        return max(0.0, b.open_circuit_v(self.charge) - self.current_a * b.internal_resistance_ohm)

    @property
    def pin_volts(self) -> float:
        """Voltage [V] at the analog pin behind the divider."""
        return self.volts / self._battery.multiplier


class BlimpPinPlant:
    """The Blimpduino around a (simulated) board's pins: implements the ``PinPlant`` protocol.

    On each :meth:`advance` it reads the H-bridge direction pins, PWM duties and the standby
    pin (LOW: both motors off), turns each signed duty into a thrust [N] with the vehicle's
    calibration (``calibration.to_u("thrust_left" | "thrust_right", duty)``), turns the servo
    pulse [µs] into μ [rad] (linear between ``servo_min_us`` -> μ_min and ``servo_max_us`` ->
    μ_max; no pulse keeps the last angle), integrates :class:`BlimpPlant` over ``dt`` with
    RK4 and ``substeps`` steps, and reports the battery divider voltage on the battery pin.

    Args:
        calibration: signed duty -> thrust [N] for ``"thrust_left"`` and ``"thrust_right"``.
        initial_state: 12-state (see :class:`BlimpPlant`) or ``[x, y, z, ψ]`` at rest.
        params: physical parameters.
        pinout: pin numbers (default: Code Sample A.2).
        substeps: RK4 steps per ``dt``.
    """

    #: :meth:`pose` is in the NED frame (z down), see :mod:`hilswarm.agents.mocap.frames`.
    pose_frame = "ned"

    def __init__(
        self,
        calibration: ThrustCalibration,
        *,
        initial_state: Sequence[float] = (0.0, 0.0, -1.0, 0.0),
        params: BlimpParams = DEFAULT_BLIMP_PARAMS,
        pinout: BlimpPinout | None = None,
        substeps: int = 2,
    ) -> None:
        self.plant = BlimpPlant(params)
        values = np.asarray(initial_state, dtype=float).reshape(-1)
        if values.shape == (4,):
            values = self.plant.initial_state(values)
        self.state = self.plant.check_state(values)
        if not np.all(np.isfinite(self.state)):
            raise PlantError(f"BlimpPinPlant: initial_state must be finite, got {initial_state!r}")
        if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
            raise PlantError(f"BlimpPinPlant: substeps must be an int >= 1, got {substeps!r}")
        self._calibration = calibration
        self.pinout = pinout or BlimpPinout()
        self.substeps = substeps
        self.battery = BatteryState(params)
        self.time_s = 0.0
        self.inputs = np.array([0.0, 0.0, params.thrust_angle_min_rad / 2.0])

    def signed_duty(self, outputs: Mapping[int, int], fwd: int, back: int, pwm: int) -> int:
        """Signed duty [-255, 255] of one H-bridge channel (both or no direction pin: 0)."""
        if not outputs.get(self.pinout.standby, 0):
            return 0
        forward, backward = outputs.get(fwd, 0), outputs.get(back, 0)
        duty = int(outputs.get(pwm, 0))
        if forward and not backward:
            return duty
        if backward and not forward:
            return -duty
        return 0

    def thrust_angle(self, pulse_us: int) -> float:
        """μ [rad] for a servo pulse [µs] (clipped to the servo range)."""
        p = self.plant.params
        fraction = (pulse_us - p.servo_min_us) / (p.servo_max_us - p.servo_min_us)
        fraction = min(max(fraction, 0.0), 1.0)
        return p.thrust_angle_min_rad + fraction * (p.thrust_angle_max_rad - p.thrust_angle_min_rad)

    def advance(self, outputs: Mapping[int, int], dt: float) -> Mapping[int, float]:
        """Apply the board outputs (wire units) for ``dt`` [s]; return ``{battery pin: V}``."""
        pins = self.pinout
        thrusts = []
        for name, (fwd, back, pwm) in (
            ("thrust_left", (pins.left_fwd, pins.left_back, pins.left_pwm)),
            ("thrust_right", (pins.right_fwd, pins.right_back, pins.right_pwm)),
        ):
            duty = self.signed_duty(outputs, fwd, back, pwm)
            thrusts.append(float(self._calibration.to_u(name, duty)) if duty else 0.0)
        pulse = int(outputs.get(pins.servo, 0))
        mu = self.thrust_angle(pulse) if pulse > 0 else float(self.inputs[2])
        self.inputs = self.plant.saturate([thrusts[0], thrusts[1], mu])
        self.state = integrate(
            lambda t, x: self.plant.dynamics(t, x, self.inputs),
            self.time_s,
            self.state,
            dt,
            method="rk4",
            substeps=self.substeps,
        )
        self.battery.advance(self.inputs[:2], pulse > 0, dt)
        self.time_s += dt
        return self.analog_inputs()

    def analog_inputs(self) -> dict[int, float]:
        """Voltages [V] the plant drives: the battery divider on the battery pin."""
        return {self.pinout.battery: self.battery.pin_volts}

    def pose(self) -> np.ndarray:
        """``[x, y, z, roll, pitch, yaw]`` [m, world NED (z down); rad, yaw wrapped]."""
        s = self.state
        return np.array([s[0], s[1], s[2], s[3], s[4], wrap_angle(float(s[5]))])
