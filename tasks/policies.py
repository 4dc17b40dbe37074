"""Policies: a pair of pure functions ``init(key) -> theta`` and ``apply(theta, f) -> u``.

Both policies squash a pre-activation ``a`` with PILCO's sine saturation
``sat(a) = (9 sin(a) + sin(3 a)) / 8`` (range [-1, 1]) and scale by the control limit:
``u = u_max * sat(a)``. ``apply`` acts on one feature vector; vmap for a batch.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

RBF_SIGNAL_STD = 1.0
"""Signal std of the RBF policy's GP-mean parameterisation (fixed, as in PILCO)."""
RBF_NOISE_STD = 0.01
"""Noise std of the RBF policy's GP-mean parameterisation (fixed, as in PILCO)."""


class Policy(NamedTuple):
    """``init(key) -> theta`` (a pytree); ``apply(theta, features (F,)) -> u (U,)``."""

    init: Callable[[jax.Array], object]
    apply: Callable[[object, jax.Array], jax.Array]


class RBFParams(NamedTuple):
    """RBF policy parameters, PILCO's pseudo-data form.

    centres: (B, F) pseudo-inputs c_i; targets: (B, U) pseudo-targets y_i;
    log_lengthscales: (U, F) log of the diagonal of Lambda^(1/2), one row per control.
    """

    centres: jax.Array
    targets: jax.Array
    log_lengthscales: jax.Array


class LinearParams(NamedTuple):
    """Linear policy parameters: weight (U, F), bias (U,)."""

    weight: jax.Array
    bias: jax.Array


def saturate(a: jax.Array) -> jax.Array:
    """PILCO's sine saturation ``(9 sin(a) + sin(3 a)) / 8``, elementwise, range [-1, 1]."""
    return (9.0 * jnp.sin(a) + jnp.sin(3.0 * a)) / 8.0


def rbf_weights(theta: RBFParams) -> jax.Array:
    """The network's weights ``beta = (K + sn^2 I)^-1 y`` per control, (U, B).

    K is the SE kernel (signal std ``RBF_SIGNAL_STD``) of the centres under each control's
    length-scales; ``sn = RBF_NOISE_STD``. Depends on theta only, so under ``vmap`` over
    particles it is computed once.
    """

    def one_output(log_ell, y):
        scaled = theta.centres / jnp.exp(log_ell)
        sq = jnp.sum((scaled[:, None, :] - scaled[None, :, :]) ** 2, axis=-1)
        gram = RBF_SIGNAL_STD**2 * jnp.exp(-0.5 * sq)
        gram = gram + RBF_NOISE_STD**2 * jnp.eye(gram.shape[0], dtype=gram.dtype)
        return jax.scipy.linalg.solve(gram, y, assume_a="pos")

    return jax.vmap(one_output, in_axes=(0, 1))(theta.log_lengthscales, theta.targets)


def rbf_preactivation(theta: RBFParams, f: jax.Array) -> jax.Array:
    """``pi~(f) = sum_i beta_i exp(-1/2 (f - c_i)^T Lambda^-1 (f - c_i))``, (U,)."""
    beta = rbf_weights(theta)

    def one_output(log_ell, beta_u):
        diff = (f - theta.centres) / jnp.exp(log_ell)
        return RBF_SIGNAL_STD**2 * jnp.exp(-0.5 * jnp.sum(diff**2, axis=-1)) @ beta_u

    return jax.vmap(one_output)(theta.log_lengthscales, beta)


def rbf_policy(
    num_basis: int,
    u_max: tuple[float, ...],
    sample_features: Callable[[jax.Array, int], jax.Array],
    init_lengthscales: tuple[float, ...],
) -> Policy:
    """An RBF network policy ``u = u_max * sat(pi~(f))`` (PILCO's GP-mean policy).

    ``sample_features(key, n) -> (n, F)`` draws the initial centres (features of initial
    states); the initial pseudo-targets are ``0.1 * N(0, 1)``; the initial length-scales are
    ``init_lengthscales`` (F,) for every control.
    """
    u_max_arr = jnp.asarray(u_max)
    num_controls = len(u_max)

    def init(key):
        k_centres, k_targets = jax.random.split(key)
        centres = sample_features(k_centres, num_basis)
        targets = 0.1 * jax.random.normal(k_targets, (num_basis, num_controls), centres.dtype)
        log_ell = jnp.log(jnp.asarray(init_lengthscales, centres.dtype))
        return RBFParams(centres, targets, jnp.tile(log_ell, (num_controls, 1)))

    def apply(theta, f):
        return u_max_arr.astype(f.dtype) * saturate(rbf_preactivation(theta, f))

    return Policy(init, apply)


def linear_policy(feature_dim: int, u_max: tuple[float, ...], init_scale: float = 1e-2) -> Policy:
    """A linear policy ``u = u_max * sat(W f + b)``; W ~ init_scale * N(0, 1), b = 0."""
    u_max_arr = jnp.asarray(u_max)
    num_controls = len(u_max)

    def init(key):
        weight = init_scale * jax.random.normal(key, (num_controls, feature_dim))
        return LinearParams(weight, jnp.zeros((num_controls,), weight.dtype))

    def apply(theta, f):
        return u_max_arr.astype(f.dtype) * saturate(theta.weight @ f + theta.bias)

    return Policy(init, apply)
