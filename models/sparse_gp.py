"""FITC sparse GP (Snelson & Ghahramani, NIPS 2006): PILCO's model once the data outgrow it.

pilco-matlab's cart-pole (``settings_cp.m``: ``dynmodel.induce = zeros(300,0,1)``) trains the
full GP's hyperparameters on all data and, once there are more than 300 points, places 300
inducing inputs u (M, D), shared by the E outputs, by minimising the FITC negative log
marginal likelihood with the hyperparameters held. Per output, with K_uu (M, M) (plus a
jitter of ``JITTER`` sf^2), K_uf (M, N) and

    Lambda = diag(K_ff - K_fu K_uu^-1 K_uf) + sn^2 I        (N,)
    y ~ N(0, K_fu K_uu^-1 K_uf + Lambda)                   (the FITC prior of the targets)
    Sigma = K_uu + K_uf Lambda^-1 K_fu
    mean(x) = k_u(x)^T beta,   beta = Sigma^-1 K_uf Lambda^-1 y
    model_var(x) = sf^2 - k_u(x)^T (K_uu^-1 - Sigma^-1) k_u(x).

``fitc_posterior`` returns these as a ``models.gp.GPPosterior`` over the inducing inputs:
alpha = beta and chol_inv = W with W^T W = K_uu^-1 - Sigma^-1, so the GP's prediction
(``predict_difference``, cost O(M^2) per output instead of O(N^2)) and PILCO's moment matching
(``k_inv = W^T W``, as pilco-matlab's gp1) apply unchanged. With u = the training inputs FITC
is the full GP (Lambda = sn^2).

Computation, with L_uu = chol(K_uu), V = L_uu^-1 K_uf, A = V Lambda^-1/2 (M, N), B = I + A A^T
= L_B L_B^T, c = L_B^-1 A Lambda^-1/2 y: ``nlml = 1/2 (|Lambda^-1/2 y|^2 - |c|^2) + 1/2 sum log
Lambda + sum log diag L_B + n/2 log 2 pi``; beta = L_uu^-T L_B^-T c; K_uu^-1 - Sigma^-1 =
L_uu^-T (I - B^-1) L_uu^-1, and W = chol(I - B^-1 + ``JITTER`` I)^T L_uu^-1. Padding rows of the
buffer are inert (K_uf column 0, Lambda 1, y 0). Linear algebra by ``numerics.linalg``: vmap
and reverse mode apply.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from models.gp import GPData, GPPosterior, clean, kernel_matrix, lbfgs_minimise, posterior, \
    split_hyp, train
from numerics.distances import scaled_sq_distances
from numerics.linalg import cholesky, solve_lower, solve_lower_t

JITTER = 1e-8
"""Added to K_uu's diagonal (times sf^2) and to I - B^-1 before their Cholesky factorisations;
it changes the predictive variance by at most JITTER sf^2."""


def _fitc_one(log_hyp_e, inducing, x, y, mask):
    """The FITC pieces of one output: (L_uu (M, M), L_B (M, M), c (M,), nlml)."""
    ls, sf2, sn2 = split_hyp(log_hyp_e)
    m = inducing.shape[0]
    eye = jnp.eye(m, dtype=x.dtype)
    chol_uu = cholesky(kernel_matrix(log_hyp_e, inducing) + JITTER * sf2 * eye)
    k_uf = sf2 * jnp.exp(-0.5 * jax.vmap(scaled_sq_distances, in_axes=(None, 0, None))(inducing, x, ls).T)
    v = solve_lower(chol_uu, jnp.where(mask, k_uf, 0.0))
    lam = jnp.where(mask, jnp.maximum(sf2 - jnp.sum(v * v, axis=0), 0.0) + sn2, 1.0)
    a = v / jnp.sqrt(lam)
    y_scaled = jnp.where(mask, y, 0.0) / jnp.sqrt(lam)
    chol_b = cholesky(eye + a @ a.T)
    c = solve_lower(chol_b, a @ y_scaled)
    n = jnp.sum(mask).astype(x.dtype)
    nlml = (0.5 * (y_scaled @ y_scaled - c @ c) + 0.5 * jnp.sum(jnp.log(lam))
            + jnp.sum(jnp.log(jnp.diag(chol_b))) + 0.5 * n * math.log(2.0 * math.pi))
    return chol_uu, chol_b, c, nlml


@jax.jit
def fitc_neg_log_marginal_likelihood(inducing: jax.Array, log_hyp: jax.Array, data: GPData) -> jax.Array:
    """FITC negative log marginal likelihood summed over the E outputs (scalar); inducing
    (M, D), log_hyp (E, D+2); only the valid rows of ``data`` count."""
    x, y, mask = clean(data)
    nlml = jax.vmap(lambda h, y_e: _fitc_one(h, inducing, x, y_e, mask)[3])(log_hyp, y.T)
    return jnp.sum(nlml)


def initial_inducing(data: GPData, num_inducing: int) -> jax.Array:
    """(M, D): valid rows spread evenly over the buffer's held rows (row floor(i n / M) for
    i < M, n = num_valid; jittable). Distinct rows when n >= M."""
    index = (jnp.arange(num_inducing) * data.num_valid) // num_inducing
    return data.inputs[index]


class InducingFit(NamedTuple):
    """inducing (M, D): the inputs with the lowest FITC NLML seen; history (num_steps + 1,)."""

    inducing: jax.Array
    history: jax.Array


@functools.partial(jax.jit, static_argnums=(2, 3))
def train_inducing(log_hyp: jax.Array, data: GPData, num_inducing: int, num_steps: int) -> InducingFit:
    """Inducing inputs (M, D) minimising the FITC NLML at the fixed hyperparameters log_hyp,
    from ``initial_inducing``, by ``num_steps`` L-BFGS steps (``models.gp.lbfgs_minimise``)."""
    nlml = functools.partial(fitc_neg_log_marginal_likelihood, log_hyp=log_hyp, data=data)
    return InducingFit(*lbfgs_minimise(nlml, initial_inducing(data, num_inducing), num_steps))


def _posterior_one(log_hyp_e, inducing, x, y, mask):
    chol_uu, chol_b, c, _ = _fitc_one(log_hyp_e, inducing, x, y, mask)
    eye = jnp.eye(inducing.shape[0], dtype=x.dtype)
    beta = solve_lower_t(chol_uu, solve_lower_t(chol_b, c))
    chol_b_inv = solve_lower(chol_b, eye)
    one_minus_b_inv = eye - chol_b_inv.T @ chol_b_inv
    factor = cholesky(one_minus_b_inv + JITTER * eye).T @ solve_lower(chol_uu, eye)
    return chol_uu @ chol_b, factor, beta


@jax.jit
def fitc_posterior(inducing: jax.Array, log_hyp: jax.Array, data: GPData) -> GPPosterior:
    """The FITC predictive as a ``GPPosterior`` over the inducing inputs (M, D) (module
    docstring): inputs = inducing, mask all True, chol = chol(Sigma) = L_uu L_B, chol_inv = W,
    alpha = beta. No checks (``models.gp.check_posterior`` does them)."""
    x, y, mask = clean(data)
    chol, factor, beta = jax.vmap(lambda h, y_e: _posterior_one(h, inducing, x, y_e, mask))(log_hyp, y.T)
    return GPPosterior(inputs=inducing, mask=jnp.ones(inducing.shape[0], bool), log_hyp=log_hyp,
                       chol=chol, chol_inv=factor, alpha=beta)


def fitter(num_inducing: int, rows_held: int, hyp_steps: int, inducing_steps: int = 100):
    """The fit of a learning trial, ``GPData -> GPPosterior`` (jittable, vmappable over seeds):
    the full GP (``train`` then ``posterior``) while ``rows_held <= num_inducing`` or
    ``num_inducing`` is 0, else FITC: the hyperparameters trained on the full GP, then
    ``num_inducing`` inducing inputs by ``train_inducing`` (pilco-matlab's procedure)."""
    if num_inducing < 0:
        raise ValueError(f"num_inducing must be >= 0 (0: the full GP); got {num_inducing}")

    def full(data):
        return posterior(train(data, num_steps=hyp_steps).log_hyp, data)

    def sparse(data):
        log_hyp = train(data, num_steps=hyp_steps).log_hyp
        inducing = train_inducing(log_hyp, data, num_inducing, inducing_steps).inducing
        return fitc_posterior(inducing, log_hyp, data)

    return sparse if uses_fitc(num_inducing, rows_held) else full


def uses_fitc(num_inducing: int, rows_held: int) -> bool:
    """Whether ``fitter`` switches to FITC at this many held rows (more than num_inducing > 0)."""
    return 0 < num_inducing < rows_held
