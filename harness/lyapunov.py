"""Finite-time Lyapunov exponents of the closed-loop particle dynamics (the chaos diagnostic).

With the noise eps fixed, particle i follows the deterministic closed-loop map
``s_{t+1} = f_t(s_t) = m(s_t, pi(s_t)) + sd(s_t, pi(s_t)) * eps_t``. Its finite-time
Lyapunov exponent over the horizon T is

    lambda = (1/T) log sigma_max(J_{T-1} ... J_1 J_0),    J_t = d f_t / d s (s_t)   (S, S)

per control step: the growth rate of the fastest-growing perturbation of the initial state.
RP's gradient is a sum of such Jacobian products, so lambda > 0 (chaos) lets it grow like
exp(lambda T): the paper's explanation of RP's exploding variance. The product is
accumulated with a renormalisation at each step, so it neither overflows nor underflows.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from estimators.base import Problem, draw_noise, next_state_distribution, theta_dtype


def closed_loop_step(problem: Problem, net, s: jax.Array, eps_t: jax.Array) -> jax.Array:
    """One particle's next state ``m + sd * eps_t`` under the policy's prepared ``net``, (S,)."""
    zeta = next_state_distribution(problem, net, s)
    return zeta.mean + zeta.std * eps_t


def normalised_product(jacobians: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(log c, M)`` with ``J_{T-1} ... J_0 = c M``, ``||M||_F = 1``, for jacobians (T, S, S)."""

    def accumulate(carry, jacobian):
        product, log_scale = carry
        product = jacobian @ product
        norm = jnp.linalg.norm(product)
        return (product / norm, log_scale + jnp.log(norm)), None

    eye = jnp.eye(jacobians.shape[-1], dtype=jacobians.dtype)
    (product, log_scale), _ = jax.lax.scan(accumulate, (eye, jnp.zeros((), jacobians.dtype)), jacobians)
    return log_scale, product


def exponent(log_scale, product, horizon: int) -> np.ndarray:
    """``(log c + log sigma_max(M)) / T``; the SVD runs in numpy (small matrices, and no
    batched LAPACK call inside XLA, see models/gp.py)."""
    sigma_max = np.linalg.svd(np.asarray(product), compute_uv=False)[..., 0]
    return (np.asarray(log_scale) + np.log(sigma_max)) / horizon


@functools.partial(jax.jit, static_argnums=3)
def particle_products(problem: Problem, theta, key: jax.Array, num_particles: int):
    """Each particle's normalised Jacobian product along the rollout drawn with ``key`` (the
    same particles as the estimators' with that key): log scales (P,), products (P, S, S)."""
    s0, eps = draw_noise(problem, key, num_particles, theta_dtype(theta))
    step = functools.partial(closed_loop_step, problem, problem.policy.prepare(theta))
    jacobian = jax.vmap(jax.jacfwd(step))

    def advance(s, eps_t):
        return jax.vmap(step)(s, eps_t), jacobian(s, eps_t)

    _, jacobians = jax.lax.scan(advance, s0, eps)  # (T, P, S, S)
    return jax.vmap(normalised_product, in_axes=1)(jacobians)


def finite_time_exponents(problem: Problem, theta, key: jax.Array, num_particles: int) -> np.ndarray:
    """Each particle's finite-time Lyapunov exponent per control step, (P,)."""
    return exponent(*particle_products(problem, theta, key, num_particles), problem.horizon)
