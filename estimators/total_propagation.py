"""TP: total propagation (PIPPS, Algorithm "Total Propagation").

One forward pass samples the particles. One backward pass over t = T..1 then, per particle i
(re-linearising ``zeta_t(s_{t-1}, theta)`` at the stored samples):

    dG^RP/ds_t   = dc/ds_t + (mixed cotangent from step t+1 mapped through zeta_{t+1})
    g^RP_zeta    = (dG^RP/ds_t, dG^RP/ds_t * eps_t)          # s_t = m + sd * eps
    g^LR_zeta    = d/dzeta sum_j W_ij log p(s_j | zeta_i)     # BIW-LR (or LR) weights W
    (RP, LR)_theta, (RP, LR)_s = VJP of zeta_t(s_{t-1}, theta) with the two cotangents
    k_LR = 1 / (1 + tr var_i(LR_theta) / tr var_i(RP_theta))   clipped to [0, 1]
    dJ/dtheta += mean_i [k_LR LR_theta + (1 - k_LR) RP_theta]
    cotangent passed to step t-1: k_LR LR_s + (1 - k_LR) RP_s     (linearity of the VJP)

With ``fixed_k=0`` this is RP and with ``fixed_k=1`` it is the likelihood-ratio estimator it
mixes in (tested). A NaN k_LR (a NaN gradient) is reported in aux, never replaced.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from estimators.base import (Estimate, Problem, Trajectory, Zeta, draw_noise, next_state_distribution, prepared,
                             particle_estimate, theta_dtype)
from estimators.likelihood_ratio import LikelihoodRatio, score_surrogate


def mixing_weight(var_rp: jax.Array, var_lr: jax.Array) -> jax.Array:
    """``k_LR = 1 / (1 + var_LR / var_RP)`` clipped to [0, 1]; 0/0 (both estimates identical
    across particles) gives 1/2; var_RP = inf gives 1, var_LR = inf gives 0; NaN stays NaN."""
    both_zero = (var_rp == 0) & (var_lr == 0)
    k = 1.0 / (1.0 + var_lr / var_rp)
    return jnp.where(both_zero, 0.5, jnp.clip(k, 0.0, 1.0))


def trace_of_variance(per_particle) -> jax.Array:
    """``sum over parameters of var_i(g_i)`` for per-particle gradients (leaves (P, ...))."""
    return sum(jnp.sum(g.var(axis=0, ddof=1)) for g in jax.tree.leaves(per_particle))


@dataclasses.dataclass(frozen=True)
class TotalPropagation:
    """TP estimator; ``weighting`` picks its likelihood-ratio part ("biw_lr" as in the paper,
    or "lr") and ``baseline`` its baseline (``likelihood_ratio.BASELINES``: the paper's
    "leave_one_out", "pairwise" or "none"); ``fixed_k`` forces k_LR (None: inverse-variance
    weighting).
    ``__call__(problem, theta, key, P) -> Estimate``; aux adds ``k_lr`` (T,) and ``ess`` (T,)."""

    weighting: str = "biw_lr"
    baseline: str = "leave_one_out"
    fixed_k: float | None = None

    def __post_init__(self):
        LikelihoodRatio(self.weighting, self.baseline)  # checks both names

    def __call__(self, problem: Problem, theta, key: jax.Array, num_particles: int) -> Estimate:
        s0, eps = draw_noise(problem, key, num_particles, theta_dtype(theta))
        zeta_fn = functools.partial(next_state_distribution, problem)
        net, to_theta = prepared(problem, theta)

        def forward(s, eps_t):
            zeta = jax.vmap(zeta_fn, in_axes=(None, 0))(net, s)
            s_next = zeta.mean + zeta.std * eps_t
            return s_next, (s_next, zeta)

        _, (states, zetas) = jax.lax.scan(forward, s0, eps)
        traj = Trajectory(jnp.concatenate([s0[None], states]), zetas, jax.vmap(jax.vmap(problem.cost))(states))
        stats, ess = LikelihoodRatio(self.weighting, self.baseline).step_statistics(zetas, states, traj.cost_to_go)
        cost_grad = jax.vmap(jax.grad(problem.cost))

        def backward(carry, inputs):
            future_s, accumulated = carry
            s_prev, s_t, eps_t, zeta_t, stats_t = inputs
            dG_ds = cost_grad(s_t) + future_s
            rp = Zeta(dG_ds, dG_ds * eps_t)
            lr = jax.grad(lambda z: score_surrogate(z, stats_t).sum())(zeta_t)
            both = jax.tree.map(lambda a, b: jnp.stack([a, b], axis=1), rp, lr)  # (P, 2, S)
            # Re-linearise zeta_t(s_{t-1}, net) per particle (cheaper than storing VJP residuals,
            # which would hold a per-particle copy of the model's matrices at every step).
            def vjp_two(s_i, ct_i):
                _, vjp = jax.vjp(zeta_fn, net, s_i)
                return jax.vmap(vjp)(ct_i)

            net_ct, s_ct = jax.vmap(vjp_two)(s_prev, both)  # leaves (P, 2, ...)
            theta_ct = to_theta(net_ct, batch_dims=2)
            rp_theta = jax.tree.map(lambda g: g[:, 0], theta_ct)
            lr_theta = jax.tree.map(lambda g: g[:, 1], theta_ct)
            if self.fixed_k is None:
                k = mixing_weight(trace_of_variance(rp_theta), trace_of_variance(lr_theta))
            else:
                k = jnp.asarray(self.fixed_k, dG_ds.dtype)
            mix = lambda a, b: k * b + (1.0 - k) * a  # noqa: E731  (a: RP, b: LR)
            accumulated = jax.tree.map(lambda acc, a, b: acc + mix(a, b), accumulated, rp_theta, lr_theta)
            return (mix(s_ct[:, 0], s_ct[:, 1]), accumulated), k

        zeros = jax.tree.map(lambda x: jnp.zeros((num_particles,) + jnp.shape(x), x.dtype), theta)
        (_, per_particle_grads), k_lr = jax.lax.scan(
            backward, (jnp.zeros_like(s0), zeros), (traj.states[:-1], states, eps, zetas, stats), reverse=True)
        return particle_estimate(traj.returns.mean(), per_particle_grads, extra_nans=jnp.sum(~jnp.isfinite(k_lr)),
                                 k_lr=k_lr, ess=ess)
