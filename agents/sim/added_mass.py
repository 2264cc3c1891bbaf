"""Added (virtual) mass of a prolate spheroid: Lamb's k-factors (thesis §4.3.1, eqs. 4.3-4.9).

A body accelerating through a fluid must also accelerate some of the fluid around it. For an
ellipsoid of revolution (semi-axis ``a`` along the body x axis, ``b`` = ``c`` across it) moving
in an ideal fluid of density ρ, Lamb (*Hydrodynamics*, §§114-115, 373) gives the added mass as
fractions of the mass of displaced fluid ``m_f = ρ V`` and of the displaced fluid's moment of
inertia ``I_f = m_f (a² + b²) / 5`` about a transverse axis:

* ``k1`` — axial (surge) added mass fraction:        ``m_Ax = k1 m_f``
* ``k2`` — transverse (sway/heave) fraction:          ``m_Ay = m_Az = k2 m_f``
* ``k'`` — transverse rotation (pitch/yaw) fraction:  ``I_Ay = I_Az = k' I_f``; ``I_Ax = 0``.

Closed form, with eccentricity ``e = sqrt(1 - (b/a)²)``::

    α0 = 2 (1 - e²)/e³ · (½ ln((1 + e)/(1 - e)) - e)
    β0 = 1/e² - (1 - e²)/(2 e³) · ln((1 + e)/(1 - e))
    k1 = α0 / (2 - α0)        k2 = β0 / (2 - β0)
    k' = e⁴ (β0 - α0) / ((2 - e²) [2 e² - (2 - e²)(β0 - α0)])

Limits: a sphere (e -> 0) has k1 = k2 = 1/2 and k' = 0; an infinitely slender body (e -> 1)
has k1 -> 0, k2 -> 1, k' -> 1.

The thesis interpolated Lamb's *table* with a spline; :func:`k_factors_from_table` does the
same (monotone PCHIP over D/L so the slender limit is part of the table), and
:func:`k_factors` evaluates the closed form. Tests check one against the other. Near e = 0 the
closed form loses precision to cancellation, so below ``e < 1e-3`` it uses the series
``α0 ≈ β0 ≈ 2/3`` (k1 = k2 = 1/2, k' = 0 to O(e²)).

Units: lengths [m], densities [kg/m³], masses [kg], moments of inertia [kg·m²].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from hilswarm.agents.errors import PlantError
from scipy.interpolate import PchipInterpolator

__all__ = [
    "LAMB_TABLE",
    "AddedMass",
    "KFactors",
    "added_mass",
    "k_factors",
    "k_factors_from_table",
    "spheroid_volume",
]

#: Lamb's table of k-factors for prolate spheroids: columns L/D, k1, k2, k'
#: (Lamb, *Hydrodynamics*, 6th ed., §373; reproduced by Munk, NACA Report 184, and by
#: van de Loo / the thesis' reference [6]). The last row is the slender-body limit L/D -> ∞.
LAMB_TABLE: tuple[tuple[float, float, float, float], ...] = (
    (1.00, 0.500, 0.500, 0.000),
    (1.50, 0.305, 0.621, 0.094),
    (2.00, 0.209, 0.702, 0.240),
    (2.51, 0.156, 0.763, 0.367),
    (2.99, 0.122, 0.803, 0.465),
    (3.99, 0.082, 0.860, 0.608),
    (4.99, 0.059, 0.895, 0.701),
    (6.01, 0.045, 0.918, 0.764),
    (6.97, 0.036, 0.933, 0.805),
    (8.01, 0.029, 0.945, 0.840),
    (9.02, 0.024, 0.954, 0.865),
    (9.97, 0.021, 0.960, 0.883),
    (math.inf, 0.000, 1.000, 1.000),
)

#: Below this eccentricity the closed form is replaced by the sphere values.
_SMALL_ECCENTRICITY = 1e-3


@dataclass(frozen=True, slots=True)
class KFactors:
    """Lamb's k-factors of one prolate spheroid (dimensionless).

    Attributes:
        k1: axial added-mass fraction of the displaced fluid mass.
        k2: transverse added-mass fraction of the displaced fluid mass.
        k_rot: k', transverse-rotation added inertia fraction of the displaced fluid's
            transverse moment of inertia.
    """

    k1: float
    k2: float
    k_rot: float


def _check_slenderness(length_m: float, diameter_m: float) -> float:
    for name, value in (("length_m", length_m), ("diameter_m", diameter_m)):
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise PlantError(f"spheroid {name} must be a finite number > 0 [m], got {value!r}")
    if length_m < diameter_m:
        raise PlantError(
            f"Lamb's k-factors here are for prolate spheroids: length_m ({length_m}) must be "
            f">= diameter_m ({diameter_m})"
        )
    return float(length_m) / float(diameter_m)


def k_factors(length_m: float, diameter_m: float) -> KFactors:
    """Lamb's k-factors of a prolate spheroid from the closed-form expressions.

    Args:
        length_m: length along the axis of symmetry, 2a [m].
        diameter_m: largest diameter, 2b [m] (<= length_m).

    Raises:
        PlantError: non-positive, non-finite or oblate (length < diameter) dimensions.
    """
    slenderness = _check_slenderness(length_m, diameter_m)
    e = math.sqrt(max(0.0, 1.0 - 1.0 / slenderness**2))
    if e < _SMALL_ECCENTRICITY:
        return KFactors(0.5, 0.5, 0.0)
    log_term = math.log((1.0 + e) / (1.0 - e)) if e < 1.0 else math.inf
    if not math.isfinite(log_term):
        return KFactors(0.0, 1.0, 1.0)
    alpha0 = 2.0 * (1.0 - e**2) / e**3 * (0.5 * log_term - e)
    beta0 = 1.0 / e**2 - (1.0 - e**2) / (2.0 * e**3) * log_term
    k1 = alpha0 / (2.0 - alpha0)
    k2 = beta0 / (2.0 - beta0)
    diff = beta0 - alpha0
    k_rot = e**4 * diff / ((2.0 - e**2) * (2.0 * e**2 - (2.0 - e**2) * diff))
    return KFactors(k1, k2, k_rot)


@lru_cache(maxsize=1)
def _table_interpolators() -> tuple[PchipInterpolator, PchipInterpolator, PchipInterpolator]:
    table = np.array(LAMB_TABLE[::-1], dtype=float)  # increasing D/L: slender limit first
    d_over_l = np.where(np.isinf(table[:, 0]), 0.0, 1.0 / table[:, 0])
    return tuple(PchipInterpolator(d_over_l, table[:, column]) for column in (1, 2, 3))  # type: ignore[return-value]


def k_factors_from_table(length_m: float, diameter_m: float) -> KFactors:
    """Lamb's k-factors interpolated from :data:`LAMB_TABLE` (the thesis' method).

    The table is interpolated with a monotone cubic (PCHIP) in D/L ∈ [0, 1], which includes
    the slender-body limit, so every prolate spheroid is covered.

    Raises:
        PlantError: bad dimensions (see :func:`k_factors`).
    """
    slenderness = _check_slenderness(length_m, diameter_m)
    x = 1.0 / slenderness
    k1, k2, k_rot = (float(f(x)) for f in _table_interpolators())
    return KFactors(k1, k2, k_rot)


def spheroid_volume(length_m: float, diameter_m: float) -> float:
    """Volume [m³] of a prolate spheroid of length 2a and diameter 2b: (4/3) π a b²."""
    _check_slenderness(length_m, diameter_m)
    return 4.0 / 3.0 * math.pi * (length_m / 2.0) * (diameter_m / 2.0) ** 2


@dataclass(frozen=True, slots=True)
class AddedMass:
    """Added-mass terms of thesis eqs. 4.4-4.9 (body axes, origin on the axis of symmetry).

    Attributes:
        m_x: surge added mass m_Ax [kg].
        m_y: sway added mass m_Ay [kg].
        m_z: heave added mass m_Az [kg].
        i_x: roll added inertia I_Ax [kg·m²] (0: rolling an axisymmetric body moves no air).
        i_y: pitch added inertia I_Ay [kg·m²].
        i_z: yaw added inertia I_Az [kg·m²].
    """

    m_x: float
    m_y: float
    m_z: float
    i_x: float
    i_y: float
    i_z: float

    def diagonal(self) -> np.ndarray:
        """``[m_x, m_y, m_z, i_x, i_y, i_z]`` — the diagonal of M_A (eq. 4.3)."""
        return np.array([self.m_x, self.m_y, self.m_z, self.i_x, self.i_y, self.i_z])


def added_mass(
    length_m: float, diameter_m: float, fluid_density_kg_m3: float, *, use_table: bool = True
) -> AddedMass:
    """Added mass and inertia of a prolate spheroid in a fluid (thesis eqs. 4.4-4.9).

    The thesis writes ``m_Ax = k1 m`` with m the airship's mass; strictly the fraction applies
    to the mass of displaced fluid ``ρ V``. The two are equal for a neutrally buoyant airship,
    which the thesis assumes; this function uses ``ρ V`` so it stays right when they differ.

    Args:
        length_m: envelope length [m].
        diameter_m: envelope largest diameter [m].
        fluid_density_kg_m3: density of the surrounding fluid (air) [kg/m³].
        use_table: interpolate Lamb's table (thesis) rather than the closed form.

    Raises:
        PlantError: bad dimensions or density.
    """
    if not (
        isinstance(fluid_density_kg_m3, int | float)
        and math.isfinite(fluid_density_kg_m3)
        and fluid_density_kg_m3 > 0
    ):
        raise PlantError(
            f"fluid_density_kg_m3 must be a finite number > 0 [kg/m³], got {fluid_density_kg_m3!r}"
        )
    factors = (k_factors_from_table if use_table else k_factors)(length_m, diameter_m)
    fluid_mass = fluid_density_kg_m3 * spheroid_volume(length_m, diameter_m)
    a, b = length_m / 2.0, diameter_m / 2.0
    fluid_inertia = fluid_mass * (a**2 + b**2) / 5.0
    return AddedMass(
        m_x=factors.k1 * fluid_mass,
        m_y=factors.k2 * fluid_mass,
        m_z=factors.k2 * fluid_mass,
        i_x=0.0,
        i_y=factors.k_rot * fluid_inertia,
        i_z=factors.k_rot * fluid_inertia,
    )
