"""Thesis chapter 3: pole placement, SIL (Euler, RK45) and SHIL of the spring-mass-damper."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hilswarm.agents.sim.chapter3 import (
    DEFAULT_DT,
    THESIS_GAIN,
    THESIS_POLES,
    max_abs_difference,
    place_gains,
    shil,
    sil_adaptive,
    sil_fixed_step,
    tick_count,
)
from hilswarm.agents.sim.spring_mass_damper import SpringMassDamper
from scipy.linalg import expm

ROOT = Path(__file__).resolve().parents[2]
N_TICKS = tick_count(6.0, DEFAULT_DT)


@pytest.fixture(scope="module")
def gain() -> np.ndarray:
    return place_gains()


def test_gain_matches_eq_3_4(gain: np.ndarray) -> None:
    np.testing.assert_allclose(gain, THESIS_GAIN, atol=1e-9)
    plant = SpringMassDamper()
    # same characteristic polynomial as the requested poles (robust to eigenvalue ordering)
    np.testing.assert_allclose(
        np.poly(plant.A - plant.B @ gain), np.real(np.poly(THESIS_POLES)), atol=1e-9
    )


def test_repeated_poles_need_both_inputs() -> None:
    """With only F1 the pair {-2 ± 0.1i} cannot be placed twice (multiplicity > rank B)."""
    plant = SpringMassDamper()
    from scipy.signal import place_poles

    with pytest.raises(ValueError):
        place_poles(plant.A, plant.B[:, :1], np.array(THESIS_POLES))


def test_shil_equals_sil_euler_at_every_tick(gain: np.ndarray) -> None:
    sil = sil_fixed_step(gain, n_ticks=N_TICKS, method="euler")
    simulated = shil(gain, n_ticks=N_TICKS)
    assert simulated.z.shape == sil.z.shape == (N_TICKS + 1, 4)
    np.testing.assert_allclose(simulated.t, sil.t)
    per_tick = np.max(np.abs(simulated.z - sil.z), axis=1)
    assert np.all(per_tick <= 1e-9), per_tick
    np.testing.assert_allclose(simulated.u, sil.u, atol=1e-9)
    np.testing.assert_array_equal(simulated.z[0], [4.0, 0.0, -4.0, 0.0])


def test_sil_euler_closed_form(gain: np.ndarray) -> None:
    """Euler on the closed loop is z_k = (I + h (A - B K))^k z0."""
    plant = SpringMassDamper()
    sil = sil_fixed_step(gain, n_ticks=N_TICKS)
    step = np.eye(4) + DEFAULT_DT * (plant.A - plant.B @ gain)
    expected = np.array(
        [np.linalg.matrix_power(step, k) @ [4.0, 0.0, -4.0, 0.0] for k in range(N_TICKS + 1)]
    )
    np.testing.assert_allclose(sil.z, expected, atol=1e-12)


def test_sil_rk45_matches_the_exact_solution(gain: np.ndarray) -> None:
    plant = SpringMassDamper()
    adaptive = sil_adaptive(gain, n_ticks=N_TICKS, rtol=1e-10, atol=1e-12)
    closed = plant.A - plant.B @ gain
    exact = np.array([expm(closed * t) @ [4.0, 0.0, -4.0, 0.0] for t in adaptive.t])
    np.testing.assert_allclose(adaptive.z, exact, atol=1e-7)


def test_shil_differs_from_sil_rk45_by_a_clear_margin(gain: np.ndarray) -> None:
    simulated = shil(gain, n_ticks=N_TICKS)
    adaptive = sil_adaptive(gain, n_ticks=N_TICKS)
    euler = sil_fixed_step(gain, n_ticks=N_TICKS)
    assert max_abs_difference(simulated, adaptive) > 0.1  # ~0.44 at dt = 0.1 s
    assert max_abs_difference(simulated, adaptive) > 1e6 * max(
        max_abs_difference(simulated, euler), 1e-15
    )


def test_euler_error_shrinks_with_the_period(gain: np.ndarray) -> None:
    """The SHIL/SIL-RK45 gap is Euler's O(h) error: halving dt about halves it."""
    gaps = []
    for dt in (0.1, 0.05, 0.025):
        n = tick_count(6.0, dt)
        gaps.append(
            max_abs_difference(
                shil(gain, dt=dt, n_ticks=n), sil_adaptive(gain, dt=dt, n_ticks=n, rtol=1e-9)
            )
        )
    ratios = [gaps[0] / gaps[1], gaps[1] / gaps[2]]
    assert all(1.6 < r < 2.5 for r in ratios), (gaps, ratios)


def test_shil_with_rk4_plant_tracks_a_sampled_data_loop(gain: np.ndarray) -> None:
    """RK4 in the vehicle is the zero-order-hold loop: close to exp-discretised, not to Euler."""
    plant = SpringMassDamper()
    simulated = shil(gain, n_ticks=N_TICKS, integrator="rk4")
    big = expm(np.block([[plant.A, plant.B], [np.zeros((2, 6))]]) * DEFAULT_DT)
    ad, bd = big[:4, :4], big[:4, 4:]
    z = np.array([4.0, 0.0, -4.0, 0.0])
    for k in range(N_TICKS + 1):
        np.testing.assert_allclose(simulated.z[k], z, atol=1e-5)
        z = ad @ z + bd @ (-gain @ z)


def test_figure_script_writes_pngs(tmp_path: Path) -> None:
    result = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "reproduce_chapter3.py"),
            "--out",
            str(tmp_path / "figs"),
            "--duration",
            "3",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    pngs = sorted(p.name for p in (tmp_path / "figs").glob("*.png"))
    assert pngs == [
        "comparison.png",
        "fig3_3a_sil_rk45.png",
        "fig3_3b_sil_euler.png",
        "fig3_4_shil.png",
    ]
    for name in pngs:
        assert (tmp_path / "figs" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "max |SHIL - SIL-Euler| = 0.000e+00" in result.stdout
    assert "max |SHIL - SIL-RK45|" in result.stdout
