"""The finite-time Lyapunov exponent against linear systems whose exponent is known."""

import jax
import jax.numpy as jnp
import numpy as np

from harness.lyapunov import exponent, finite_time_exponents, normalised_product
from estimators.linear_gaussian import LinearGaussianSystem
from tasks.policies import LinearParams


def test_diagonal_map_has_the_log_of_its_largest_multiplier():
    jacobians = jnp.broadcast_to(jnp.diag(jnp.array([2.0, 0.5, -1.5])), (40, 3, 3))
    np.testing.assert_allclose(exponent(*normalised_product(jacobians), 40), np.log(2.0), rtol=1e-12)


def test_product_is_renormalised_so_long_horizons_do_not_overflow():
    jacobians = jnp.broadcast_to(jnp.diag(jnp.array([1e3, 1.0])), (500, 2, 2))  # 1e1500 overall
    np.testing.assert_allclose(exponent(*normalised_product(jacobians), 500), np.log(1e3), rtol=1e-12)


def test_linear_gaussian_closed_loop_matches_the_matrix_power():
    """s_tp1 = (A + B W) s + b + sd * eps: every particle's Jacobian is F = A + B W, so the
    exponent is (1/T) log sigma_max(F^T) exactly, whatever the noise."""
    system = LinearGaussianSystem(horizon=25)
    theta = LinearParams(jnp.array([[-2.0, 3.0]]), jnp.array([0.1]))
    F = np.asarray(system.A) + np.asarray(system.B) @ np.asarray(theta.weight)
    expected = np.log(np.linalg.svd(np.linalg.matrix_power(F, 25), compute_uv=False)[0]) / 25
    got = finite_time_exponents(system.problem(), theta, jax.random.key(0), 7)
    assert got.shape == (7,)
    np.testing.assert_allclose(got, expected, rtol=1e-10)
    assert expected > 0  # this gain destabilises the system: a positive exponent
