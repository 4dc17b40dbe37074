"""LR and BIW-LR: likelihood-ratio gradients (PIPPS, section "Particle Model-Based Policy
Search", and its batch importance weighting).

Both are written as one score estimator with a weight matrix W (P, P) per step:

    dJ/dtheta = (1/P) sum_t sum_i sum_j W_ij d/dtheta log p(s_{j,t+1} | zeta_{i,t+1})

where ``zeta_{i,t+1}`` depends on theta through the policy at the fixed sample ``s_{i,t}``
(the samples themselves carry no gradient). With G the cost-to-go from t+1:

- LR: ``W = diag(G_i - b_i)``, ``b_i`` the mean of the other particles' G (leave-one-out);
- BIW-LR: ``W_ij = c_ij (G_j - b_ij)``, ``c_ij = p(s_j | zeta_i) / sum_k p(s_j | zeta_k)``
  (each sample weighted against the particles' mixture). O(P^2 S) per step, in log space, as
  matrix products (no (P, P, S) temporaries).

The baselines (``baseline=``):

- ``"leave_one_out"`` (the paper's): LR's leave-one-out mean; BIW-LR's normalised
  importance-sampled leave-one-out ``b_ij = b_i = sum_{k != i} c_ik G_k / sum_{k != i} c_ik``.
  It depends on the samples s_j it multiplies, which biases BIW-LR (the paper says so).
- ``"pairwise"`` (BIW-LR; for LR it is the leave-one-out): P^2 baselines ``b_ij``
  (``pairwise_baseline``), each independent of the sample s_j it multiplies and with the
  same expectation for every j, as the paper proposes to remove the bias: the baseline
  term's expectation is then exactly 0. O(P^2 S) per step.
- ``"importance_sampled"`` (LR; BIW-LR's leave-one-out is this already): LR with BIW-LR's
  normalised importance-sampled leave-one-out baseline ``b_i`` (``importance_sampled_baseline``), the
  baseline the paper's LR used in its variance figure ("used the importance sampled baseline").
  ``b_i`` depends on the other particles' samples only, so LR stays unbiased.
- ``"none"``: no baseline; both estimators are then exactly unbiased.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp

from estimators.base import (Estimate, Problem, Zeta, draw_noise, particle_estimate, particle_gradients, rollout,
                             theta_dtype)


class ScoreStatistics(NamedTuple):
    """Sufficient statistics of ``sum_j W_ij log N(s_j; m, sd)`` around ``centre`` = the
    value of m_i: ``A_i = sum_j W_ij (s_j - centre_i)^2``, ``B_i = sum_j W_ij (s_j - centre_i)``
    (P, S) and ``w_i = sum_j W_ij`` (P,). No gradient flows through them."""

    centre: jax.Array
    A: jax.Array
    B: jax.Array
    w: jax.Array


def centred(zeta: Zeta, s: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The samples and the means less the samples' mean per dimension, (P, S) each: the
    matrix-product forms below expand squares of differences, and centring keeps the terms
    they cancel small (round-off ~1e-16 |s - c|^2 / sd^2 in float64)."""
    centre = jnp.mean(s, axis=0)
    return s - centre, zeta.mean - centre


def log_density_matrix(zeta: Zeta, s: jax.Array) -> jax.Array:
    """``log p(s_j | zeta_i)`` for all pairs, (P, P) [i, j], for diagonal Gaussians. With
    ``tau = 1 / sd^2`` and centred samples and means (``centred``), the squared distances are
    ``sum_d tau_id (s_jd - m_id)^2 = (tau s^2T)_ij - 2 ((tau m) s^T)_ij + sum_d tau_id m_id^2``:
    two (P, S) x (S, P) products instead of (P, P, S) temporaries."""
    s_c, m_c = centred(zeta, s)
    tau = 1.0 / zeta.std**2
    quad = tau @ (s_c**2).T - 2.0 * (tau * m_c) @ s_c.T + jnp.sum(tau * m_c**2, axis=1)[:, None]
    log_norm = jnp.sum(jnp.log(zeta.std), axis=1)[:, None] + 0.5 * s.shape[-1] * jnp.log(2 * jnp.pi)
    return -0.5 * jnp.maximum(quad, 0.0) - log_norm  # round-off can take quad below 0


def leave_one_out_baseline(G: jax.Array) -> jax.Array:
    """``b_i = mean_{j != i} G_j``, (P,) -> (P,)."""
    return (G.sum() - G) / (G.shape[0] - 1)


def log_ratio_second_moments(zeta: Zeta) -> jax.Array:
    """``log E_{s ~ p_k}[(p_i(s) / p_k(s))^2]`` (P, P) [i, k] for the diagonal Gaussians
    p_i = N(m_i, diag v_i) of one step: per dimension, with ``d = 2 v_k - v_i``,
    ``log v_k - 1/2 log v_i - 1/2 log d + (m_i - m_k)^2 / d``, summed; +inf where some d <= 0
    (the ratio's variance is infinite). 0 on the diagonal, >= 0 everywhere (E[r] = 1)."""
    v = zeta.std**2
    v_i, v_k = v[:, None, :], v[None, :, :]
    d = 2.0 * v_k - v_i
    safe = jnp.where(d > 0, d, 1.0)
    per_dim = (jnp.log(v_k) - 0.5 * jnp.log(v_i) - 0.5 * jnp.log(safe)
               + (zeta.mean[:, None, :] - zeta.mean[None, :, :]) ** 2 / safe)
    return jnp.where(jnp.all(d > 0, axis=-1), jnp.sum(per_dim, axis=-1), jnp.inf)


PAIRWISE_MAX_RATIO_MOMENT = 2.0
"""``pairwise_baseline`` estimates b_ii only from samples k whose importance ratio has
``E[r_ik^2] <=`` this (relative variance at most 1)."""


def pairwise_baseline(zeta: Zeta, log_p: jax.Array, G: jax.Array,
                      max_ratio_moment: float = PAIRWISE_MAX_RATIO_MOMENT) -> jax.Array:
    """``b_ij`` (P, P) from log_p (P, P) [i, k] = log p_i(s_k) and G (P,). For a row i with
    partners, samples k != i whose importance ratio ``r_ik = p_i(s_k) / p_k(s_k)`` has
    ``E[r_ik^2] <= max_ratio_moment`` (``log_ratio_second_moments``; a choice made from the
    step's distributions alone): particle i's own cost-to-go ``G_i`` for j != i, and for j = i

        b_ii = sum_{partners k} a_ik r_ik G_k / sum_{partners k} a_ik,   a_ik = 1 / E[r_ik^2],

    where each r_ik G_k is an unbiased estimate of E_{p_i}[G] (s_k ~ p_k). Rows without
    partners get no baseline (b = 0). Either way every b_ij is independent of the sample s_j
    it multiplies and has the same expectation for every j (E_{p_i}[G], or 0), so the
    baseline term's expectation ``sum_j E[b_ij] E[c_ij d log p_i(s_j)]`` is that constant
    times ``d/dzeta_i int p_i = 0``."""
    off_diagonal = ~jnp.eye(G.shape[0], dtype=bool)
    log_moment = log_ratio_second_moments(zeta)
    partner = off_diagonal & (log_moment <= jnp.log(max_ratio_moment))
    log_a = jnp.where(partner, -log_moment, -jnp.inf)
    has_partner = jnp.any(partner, axis=1)
    normaliser = jnp.where(has_partner, jax.scipy.special.logsumexp(log_a, axis=1), 0.0)
    log_r = log_p - jnp.diag(log_p)[None, :]
    b_diag = jnp.exp(log_a + jnp.where(partner, log_r, 0.0) - normaliser[:, None]) @ G
    b = jnp.where(off_diagonal, G[:, None], b_diag[:, None])
    return jnp.where(has_partner[:, None], b, 0.0)


BASELINES = ("leave_one_out", "pairwise", "importance_sampled", "none")


def mixture_log_weights(zeta: Zeta, s: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``log p(s_j | zeta_i)`` and ``log c_ij = log p(s_j | zeta_i) - log sum_k p(s_j | zeta_k)``
    (P, P) [i, j] each: sample j's density under particle i against the particles' mixture."""
    log_p = log_density_matrix(zeta, s)
    return log_p, log_p - jax.scipy.special.logsumexp(log_p, axis=0, keepdims=True)


def importance_sampled_baseline(log_c: jax.Array, G: jax.Array) -> jax.Array:
    """``b_i = sum_{j != i} c_ij G_j / sum_{j != i} c_ij`` (P,) from log c (P, P) and G (P,): the
    other particles' cost-to-go weighted by how likely their samples are under particle i's
    distribution; a softmax of log c_ij over j != i, finite even when every c_ij underflows."""
    off_diagonal = jnp.where(jnp.eye(log_c.shape[0], dtype=bool), -jnp.inf, log_c)
    return jax.nn.softmax(off_diagonal, axis=1) @ G


def lr_statistics(zeta: Zeta, s: jax.Array, G: jax.Array, baseline: str = "leave_one_out"
                  ) -> tuple[ScoreStatistics, jax.Array]:
    """Statistics for ``W = diag(G - b)`` (b: the leave-one-out mean, which is also LR's
    pairwise baseline, the importance-sampled one, or 0 for "none"); returns them and the
    effective sample size P."""
    if baseline == "importance_sampled":
        weight = G - importance_sampled_baseline(mixture_log_weights(zeta, s)[1], G)
    else:
        weight = G if baseline == "none" else G - leave_one_out_baseline(G)
    r = s - zeta.mean
    return ScoreStatistics(zeta.mean, weight[:, None] * r**2, weight[:, None] * r, weight), jnp.asarray(
        G.shape[0], G.dtype)


def biw_statistics(zeta: Zeta, s: jax.Array, G: jax.Array, baseline: str = "leave_one_out"
                   ) -> tuple[ScoreStatistics, jax.Array]:
    """Statistics for the batch-importance-weighted W with ``baseline`` (module docstring);
    returns them and the mean over i of the effective sample size
    ``(sum_j c_ij)^2 / sum_j c_ij^2`` of particle i's weights."""
    log_p, log_c = mixture_log_weights(zeta, s)
    c = jnp.exp(log_c)
    W = c * G[None, :]
    if baseline in ("leave_one_out", "importance_sampled"):  # BIW-LR's leave-one-out is importance-sampled
        W = W - c * importance_sampled_baseline(log_c, G)[:, None]
    elif baseline == "pairwise":
        W = W - c * pairwise_baseline(zeta, log_p, G)
    # A_i = sum_j W_ij (s_j - m_i)^2 and B_i = sum_j W_ij (s_j - m_i), expanded (centred) into
    # products with W: (P, P) x (P, S).
    s_c, m_c = centred(zeta, s)
    w = W.sum(axis=1)
    Ws, Ws2 = W @ s_c, W @ s_c**2
    stats = ScoreStatistics(zeta.mean, Ws2 - 2.0 * m_c * Ws + m_c**2 * w[:, None], Ws - m_c * w[:, None], w)
    ess = jnp.mean(c.sum(axis=1) ** 2 / jnp.sum(c**2, axis=1))
    return stats, ess


def score_surrogate(zeta: Zeta, stats: ScoreStatistics) -> jax.Array:
    """``sum_j W_ij log N(s_j; m_i, sd_i)`` per particle, (P,), up to a constant, written so
    that its gradient with respect to zeta is exact and free of cancellation:
    with ``delta = m - centre`` (zero, but carrying the gradient),
    ``-sum_d (A - 2 delta B + w delta^2) / (2 sd^2) - w sum_d log sd``."""
    delta = zeta.mean - stats.centre
    w = stats.w[:, None]
    quad = (stats.A - 2 * delta * stats.B + w * delta**2) / (2 * zeta.std**2)
    return -jnp.sum(quad + w * jnp.log(zeta.std), axis=-1)


STATISTICS = {"lr": lr_statistics, "biw_lr": biw_statistics}


@dataclasses.dataclass(frozen=True)
class LikelihoodRatio:
    """LR (``weighting="lr"``) or BIW-LR (``weighting="biw_lr"``) estimator;
    ``__call__(problem, theta, key, P) -> Estimate``; aux adds ``ess`` (T,).

    ``baseline``: one of ``BASELINES`` (module docstring). Without one ("none") BIW-LR is
    unbiased (the samples are a stratified draw from the mixture); the paper's
    "leave_one_out" adds a bias that shrinks with P, "pairwise" removes most of it (both
    measured in tests/test_estimators.py).
    """

    weighting: str = "lr"
    baseline: str = "leave_one_out"

    def __post_init__(self):
        if self.weighting not in STATISTICS:
            raise ValueError(f"unknown weighting {self.weighting!r}; valid: {sorted(STATISTICS)}")
        if self.baseline not in BASELINES:
            raise ValueError(f"unknown baseline {self.baseline!r}; valid: {list(BASELINES)}")

    def step_statistics(self, zetas: Zeta, states: jax.Array, G: jax.Array):
        """Per-step statistics over the whole trajectory, one step at a time (lax.map keeps
        the (P, P, S) work of BIW transient). zetas (T, P, S), states (T, P, S), G (T, P)."""
        statistics = STATISTICS[self.weighting]
        return jax.lax.map(lambda args: statistics(*args, baseline=self.baseline), (zetas, states, G))

    def __call__(self, problem: Problem, theta, key: jax.Array, num_particles: int) -> Estimate:
        s0, eps = draw_noise(problem, key, num_particles, theta_dtype(theta))

        def objective(nets):
            traj = rollout(problem, nets, s0, eps, detach_samples=True)
            fixed = jax.lax.stop_gradient(traj)
            stats, ess = self.step_statistics(fixed.zetas, fixed.states[1:], fixed.cost_to_go)
            surrogate = jax.vmap(score_surrogate)(traj.zetas, stats)  # (T, P)
            return surrogate.sum(axis=0).mean(), (fixed.returns.mean(), ess)

        _, per_particle_grads, (value, ess) = particle_gradients(objective, problem, theta, num_particles)
        return particle_estimate(value, per_particle_grads, ess=ess)
