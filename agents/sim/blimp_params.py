"""Every physical parameter of the Blimpduino model, in one documented place (thesis ch. 4).

Values the thesis gives:

* envelope: a 52-inch mylar balloon -> length 52 in = 1.321 m (§4.1);
* thrusters: "spaced out 5 inches from each other" -> arm l_Th:y = 2.5 in = 0.0635 m (§4.1);
* thrust limits ±0.0637 N per propeller, from the calibration of Fig. 4.4 (§4.5);
* thrust-angle servo: the shaft pivots over 180°, "the thrust angle servo can only pivot from
  -180 to 0 degrees" (§4.5.1);
* neutral buoyancy (F_b = m g) and the cg directly below the cb (§4.3, §4.3.4);
* battery: 2-cell lithium polymer, 7.4 V nominal; divider multiplier 3, reference 3.3 V
  (Arduino Fio), low-battery threshold 6.5 V (Code Sample A.2).

Values the thesis does **not** give (it took its damping data from a different blimp, [2], and
says they are "certainly not correct" for the Blimpduino) are chosen here to be physically
reasonable and are marked *chosen* below:

* envelope diameter 0.50 m (≈ 20 in, typical of 52-inch RC blimp envelopes; L/D ≈ 2.64);
* air density 1.204 kg/m³ (20 °C, sea level), g = 9.81 m/s²;
* mass distribution: envelope (mylar, ≈ 50 g/m² over ≈ 1.8 m²) ≈ 0.090 kg plus helium
  (0.166 kg/m³) at the cb; the rest of the neutrally buoyant mass ρ V is the gondola (Fio,
  XBee, motors, servo, LiPo, PCB ≈ 0.089 kg) hanging 0.30 m below the cb. This puts the cg
  r_z ≈ 0.13 m below the cb and gives the inertias (see :func:`_derived_inertia`);
* damping: quadratic terms ½ ρ C_D A with C_D = 0.5 on the frontal area π b² (surge) and
  C_D = 1.0 on the side area π a b (sway, heave); rotational quadratic terms from strip theory
  ½ ρ C_D ∫ 2 b(x) |x|³ dx with C_D = 1; small linear (laminar) terms. Full thrust then gives
  ≈ 1.3 m/s top speed and ≈ 0.5 rad/s turning in place, plausible for a 52-inch blimp;
* battery capacity 0.25 Ah, internal resistance 0.2 Ω, electronics 0.08 A, 0.6 A per motor at
  full thrust, 0.1 A for the servo.

Frames: body frame right-handed x forward (nose), y right (starboard), z down; world frame NED
(x, y horizontal, z down; altitude = -z). See :mod:`hilswarm.agents.sim.blimp`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
from hilswarm.agents.errors import PlantError
from hilswarm.agents.sim.added_mass import AddedMass, added_mass, spheroid_volume

__all__ = ["DEFAULT_BLIMP_PARAMS", "INCH_M", "BatteryParams", "BlimpParams"]

#: One inch [m].
INCH_M = 0.0254

_AIR_DENSITY = 1.204  # [kg/m³] chosen: dry air, 20 °C, 101.325 kPa
_HELIUM_DENSITY = 0.166  # [kg/m³] helium at 20 °C
_GRAVITY = 9.81  # [m/s²]
_LENGTH = 52 * INCH_M  # [m] thesis §4.1
_DIAMETER = 0.50  # [m] chosen
_ENVELOPE_SKIN_MASS = 0.090  # [kg] chosen (mylar ≈ 50 g/m², area ≈ 1.8 m²)
_GONDOLA_DROP = 0.30  # [m] chosen: gondola below the envelope centre (cb)


@dataclass(frozen=True, slots=True)
class BatteryParams:
    """The 2-cell LiPo and its load (a simple discharge model).

    Attributes:
        cells: number of series cells (thesis: 7.4 V pack -> 2).
        capacity_ah: charge when full [A·h] (chosen 0.25).
        internal_resistance_ohm: pack resistance [Ω] (chosen 0.2).
        idle_current_a: Fio + XBee + regulator draw [A] (chosen 0.08).
        motor_current_a: one motor's current at full thrust [A] (chosen 0.6); the current
            scales with |thrust| / thrust limit.
        servo_current_a: servo draw [A] (chosen 0.1).
        initial_charge: state of charge at t = 0, 0..1.
        multiplier: voltage divider ratio battery / pin (Code Sample A.2: 3).
        low_v: low-battery threshold [V] (Code Sample A.2: 6.5).
    """

    cells: int = 2
    capacity_ah: float = 0.25
    internal_resistance_ohm: float = 0.2
    idle_current_a: float = 0.08
    motor_current_a: float = 0.6
    servo_current_a: float = 0.1
    initial_charge: float = 1.0
    multiplier: float = 3.0
    low_v: float = 6.5

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                raise PlantError(
                    f"BatteryParams.{item.name} must be a finite number >= 0, got {value!r}"
                )
        if self.cells < 1 or self.capacity_ah <= 0 or self.multiplier < 1:
            raise PlantError(
                "BatteryParams needs cells >= 1, capacity_ah > 0 and multiplier >= 1, "
                f"got cells={self.cells}, capacity_ah={self.capacity_ah}, "
                f"multiplier={self.multiplier}"
            )
        if self.initial_charge > 1:
            raise PlantError(
                f"BatteryParams.initial_charge must be in [0, 1], got {self.initial_charge}"
            )

    def open_circuit_v(self, charge: float) -> float:
        """Open-circuit pack voltage [V] at state of charge ``charge`` (0..1).

        Piecewise-linear LiPo curve per cell: 3.0 V empty (cut-off), 3.3 V at 5 %, 3.6 V at
        10 %, 3.7 V at 50 %, 3.85 V at 80 %, 4.2 V full.
        """
        soc = (0.0, 0.05, 0.1, 0.5, 0.8, 1.0)
        cell_v = (3.0, 3.3, 3.6, 3.7, 3.85, 4.2)
        return self.cells * float(np.interp(min(max(charge, 0.0), 1.0), soc, cell_v))


@dataclass(frozen=True, slots=True)
class BlimpParams:
    """Physical parameters of the Blimpduino (SI units; frames in the module docstring).

    Attributes:
        envelope_length_m: envelope length 2a [m] (thesis: 52 in).
        envelope_diameter_m: envelope largest diameter 2b [m] (chosen 0.50).
        air_density_kg_m3: ρ of the surrounding air [kg/m³].
        gravity_m_s2: g [m/s²].
        mass_kg: total mass m including the lifting gas [kg] (default ρ V: neutral).
        buoyancy_n: buoyant force F_b [N] (default m g: neutral buoyancy, thesis §4.3.4).
        cg_below_cb_m: r_z, distance of the cg below the cb [m] (> 0: pendulum-stable).
        inertia_kg_m2: rigid-body (I_x, I_y, I_z) about the cg, body axes [kg·m²].
        damping_linear: (D_u, D_v, D_w) [N·s/m] and (D_p, D_q, D_r) [N·m·s/rad] (eq. 4.13).
        damping_quadratic: (D_u², D_v², D_w²) [N·s²/m²], (D_p², D_q², D_r²) [N·m·s²/rad²].
        thruster_arm_m: l_Th:y, lateral distance of each thruster from the x-z plane [m].
        thrust_limit_n: largest thrust of one propeller either way [N].
        thrust_angle_min_rad, thrust_angle_max_rad: physical range of μ [rad] (-π..0).
        servo_min_us, servo_max_us: servo pulse widths [µs] at μ = thrust_angle_min_rad and
            at μ = thrust_angle_max_rad (chosen 600/2400 µs, a 180° micro servo).
        use_lamb_table: added mass from Lamb's table (thesis) instead of the closed form.
        battery: the battery model's parameters.
    """

    envelope_length_m: float = _LENGTH
    envelope_diameter_m: float = _DIAMETER
    air_density_kg_m3: float = _AIR_DENSITY
    gravity_m_s2: float = _GRAVITY
    mass_kg: float = float("nan")
    buoyancy_n: float = float("nan")
    cg_below_cb_m: float = float("nan")
    inertia_kg_m2: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    damping_linear: tuple[float, float, float, float, float, float] = (
        0.02,
        0.05,
        0.05,
        0.02,
        0.02,
        0.005,
    )
    damping_quadratic: tuple[float, float, float, float, float, float] = (
        0.059,
        0.31,
        0.31,
        0.01,
        0.017,
        0.017,
    )
    thruster_arm_m: float = 2.5 * INCH_M
    thrust_limit_n: float = 0.0637
    thrust_angle_min_rad: float = -math.pi
    thrust_angle_max_rad: float = 0.0
    servo_min_us: int = 600
    servo_max_us: int = 2400
    use_lamb_table: bool = True
    battery: BatteryParams = BatteryParams()

    def __post_init__(self) -> None:
        derived = _derived_defaults(self)
        for name, value in derived.items():
            current = getattr(self, name)
            unset = (
                all(math.isnan(v) for v in current)
                if isinstance(current, tuple)
                else isinstance(current, float) and math.isnan(current)
            )
            if unset:
                object.__setattr__(self, name, value)
        self._validate()

    def _validate(self) -> None:
        positive = (
            "envelope_length_m",
            "envelope_diameter_m",
            "air_density_kg_m3",
            "gravity_m_s2",
            "mass_kg",
            "thruster_arm_m",
            "thrust_limit_n",
        )
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise PlantError(f"BlimpParams.{name} must be a finite number > 0, got {value!r}")
        for name in ("buoyancy_n", "cg_below_cb_m"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value)):
                raise PlantError(f"BlimpParams.{name} must be a finite number, got {value!r}")
        for name, size in (("inertia_kg_m2", 3), ("damping_linear", 6), ("damping_quadratic", 6)):
            values = np.asarray(getattr(self, name), dtype=float)
            if values.shape != (size,) or not np.all(np.isfinite(values)) or np.any(values < 0):
                raise PlantError(
                    f"BlimpParams.{name} must be {size} finite numbers >= 0, "
                    f"got {getattr(self, name)!r}"
                )
        if min(self.inertia_kg_m2) <= 0:
            raise PlantError(f"BlimpParams.inertia_kg_m2 must be > 0, got {self.inertia_kg_m2}")
        if self.envelope_length_m < self.envelope_diameter_m:
            raise PlantError(
                f"BlimpParams: envelope_length_m ({self.envelope_length_m}) must be >= "
                f"envelope_diameter_m ({self.envelope_diameter_m}) (prolate envelope)"
            )
        if not self.thrust_angle_min_rad < self.thrust_angle_max_rad:
            raise PlantError(
                "BlimpParams: thrust_angle_min_rad must be < thrust_angle_max_rad, got "
                f"{self.thrust_angle_min_rad} and {self.thrust_angle_max_rad}"
            )
        if not 500 <= self.servo_min_us < self.servo_max_us <= 2500:
            raise PlantError(
                "BlimpParams: need 500 <= servo_min_us < servo_max_us <= 2500 [µs], got "
                f"{self.servo_min_us} and {self.servo_max_us}"
            )

    # -- derived quantities ------------------------------------------------------------------

    @property
    def volume_m3(self) -> float:
        """Envelope volume V [m³] (prolate spheroid)."""
        return spheroid_volume(self.envelope_length_m, self.envelope_diameter_m)

    @property
    def displaced_air_kg(self) -> float:
        """Mass of displaced air ρ V [kg]."""
        return self.air_density_kg_m3 * self.volume_m3

    @property
    def added(self) -> AddedMass:
        """Added (virtual) mass terms, eqs. 4.4-4.9."""
        return added_mass(
            self.envelope_length_m,
            self.envelope_diameter_m,
            self.air_density_kg_m3,
            use_table=self.use_lamb_table,
        )

    @property
    def mass_matrix_diagonal(self) -> np.ndarray:
        """Diagonal of M = M_RB + M_A (eq. 4.10): [kg, kg, kg, kg·m², kg·m², kg·m²]."""
        rigid = np.array([self.mass_kg] * 3 + list(self.inertia_kg_m2), dtype=float)
        return rigid + self.added.diagonal()

    @property
    def restoring_stiffness_nm_per_rad(self) -> float:
        """r_z F_b [N·m/rad]: small-angle roll/pitch restoring stiffness (eq. 4.14)."""
        return self.cg_below_cb_m * self.buoyancy_n

    def with_changes(self, **changes: Any) -> BlimpParams:
        """A copy with some fields replaced (derived defaults are not recomputed)."""
        return replace(self, **changes)


def _derived_inertia(
    mass_kg: float, length_m: float, diameter_m: float, volume_m3: float
) -> tuple[float, tuple[float, float, float]]:
    """cg offset below the cb [m] and rigid-body inertias about the cg [kg·m²] (chosen model).

    Envelope skin: thin spheroidal shell (I_x = (2/3) m b², I_y = I_z = m (a² + b²)/3);
    helium: solid spheroid (I_x = (2/5) m b², I_y = I_z = m (a² + b²)/5); both at the cb.
    Gondola: point mass, _GONDOLA_DROP below the cb. Parallel-axis terms move everything to the
    cg; the vertical offsets add to I_x and I_y but not to I_z.
    """
    a, b = length_m / 2.0, diameter_m / 2.0
    helium = _HELIUM_DENSITY * volume_m3
    skin = _ENVELOPE_SKIN_MASS
    gondola = mass_kg - helium - skin
    if gondola <= 0:
        raise PlantError(
            f"BlimpParams: mass_kg {mass_kg} is too small for the envelope and gas "
            f"({helium + skin:.3f} kg); give inertia_kg_m2 and cg_below_cb_m explicitly"
        )
    r_z = gondola * _GONDOLA_DROP / mass_kg
    envelope_mass = helium + skin
    i_x = (2.0 / 3.0) * skin * b**2 + 0.4 * helium * b**2
    i_yz = skin * (a**2 + b**2) / 3.0 + helium * (a**2 + b**2) / 5.0
    offsets = envelope_mass * r_z**2 + gondola * (_GONDOLA_DROP - r_z) ** 2
    return r_z, (i_x + offsets, i_yz + offsets, i_yz)


def _derived_defaults(params: BlimpParams) -> dict[str, Any]:
    volume = spheroid_volume(params.envelope_length_m, params.envelope_diameter_m)
    mass = params.mass_kg
    if isinstance(mass, float) and math.isnan(mass):
        mass = params.air_density_kg_m3 * volume
    derived: dict[str, Any] = {"mass_kg": mass, "buoyancy_n": mass * params.gravity_m_s2}
    if math.isnan(params.cg_below_cb_m) or any(math.isnan(v) for v in params.inertia_kg_m2):
        r_z, inertia = _derived_inertia(
            mass, params.envelope_length_m, params.envelope_diameter_m, volume
        )
        derived["cg_below_cb_m"] = r_z
        derived["inertia_kg_m2"] = inertia
    return derived


#: The Blimpduino as modelled here.
DEFAULT_BLIMP_PARAMS = BlimpParams()
