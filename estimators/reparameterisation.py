"""RP and GR: reparameterisation gradients (PIPPS, section "Particle Model-Based Policy Search").

RP: ``dJ/dtheta = (1/P) sum_i d/dtheta sum_t c(s_{i,t})`` through ``s_{t+1} = m + sd * eps``
by the chain rule (autodiff through the whole rollout).

GR (Gaussian resampling): after each step the sampled particles ``s~_{t+1}`` are replaced by
``mu + L xi_i`` with ``mu`` and ``L L^T`` the particles' mean and covariance (ddof 1) and
``xi_i ~ N(0, I)``, independent of the noise that sampled ``s~``; the gradient goes through
the sampling, the fit and the Cholesky factor.
GR's particles are coupled, so the per-particle contributions behind its ``grad_var`` are
each particle's use of theta, not independent estimates.
"""

from __future__ import annotations

import dataclasses

import jax

from estimators.base import (Estimate, Problem, draw_noise, particle_estimate, particle_gradients, rollout,
                             standard_normal, theta_dtype)
from numerics.linalg import cholesky


def gaussian_resample(s_tilde: jax.Array, xi: jax.Array) -> jax.Array:
    """``mu + xi L^T`` with mu (S,) and L (S, S) the Cholesky factor of the particles'
    covariance; s_tilde, xi: (P, S) -> (P, S). A singular covariance gives NaN (counted).
    The Cholesky is ``numerics.linalg.cholesky``: vmap over seeds never batches LAPACK."""
    mu = s_tilde.mean(axis=0)
    centred = s_tilde - mu
    cov = centred.T @ centred / (s_tilde.shape[0] - 1)
    return mu + xi @ cholesky(cov).T


def draw_resampling_noise(problem: Problem, key: jax.Array, num_particles: int, dtype):
    """GR's noise: ``draw_noise``'s s0 (P, S) and eps (T, P, S), and the resampling noise xi
    (T, P, S) from a key of its own, so that xi is independent of s0 and eps. (Drawing xi from
    ``fold_in(key, 1)`` reused eps itself: jax's ``split(key)[1]`` is ``fold_in(key, 1)``.)"""
    noise_key, resample_key = jax.random.split(key)
    s0, eps = draw_noise(problem, noise_key, num_particles, dtype)
    return s0, eps, standard_normal(resample_key, eps.shape, dtype)


@dataclasses.dataclass(frozen=True)
class Reparameterisation:
    """RP (``gaussian_resampling=False``) or GR; ``__call__(problem, theta, key, P) -> Estimate``."""

    gaussian_resampling: bool = False

    def __call__(self, problem: Problem, theta, key: jax.Array, num_particles: int) -> Estimate:
        if self.gaussian_resampling:
            s0, eps, xi = draw_resampling_noise(problem, key, num_particles, theta_dtype(theta))
            resample = gaussian_resample
        else:
            s0, eps = draw_noise(problem, key, num_particles, theta_dtype(theta))
            resample, xi = None, None

        def objective(nets):
            traj = rollout(problem, nets, s0, eps, resample=resample, resample_noise=xi)
            return traj.returns.mean(), None

        value, per_particle_grads, _ = particle_gradients(objective, problem, theta, num_particles)
        return particle_estimate(value, per_particle_grads)
