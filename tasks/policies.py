"""Policies: pure functions ``init(key) -> theta`` and ``apply(theta, f) -> u``.

``apply(theta, f) = network(prepare(theta), f)``: ``prepare`` does the work that depends on
theta alone (the RBF network's weight solve), so that estimators evaluating many particles,
each with its own copy of the parameters, do it once rather than per particle and step.

Both policies squash a pre-activation ``a`` with PILCO's sine saturation
``sat(a) = (9 sin(a) + sin(3 a)) / 8`` (range [-1, 1]) and scale by the control limit:
``u = u_max * sat(a)``. ``apply`` acts on one feature vector; vmap for a batch.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from numerics.distances import scaled_sq_distances
from numerics.linalg import solve_det
from tasks.forms import PolicyForm

RBF_SIGNAL_STD = 1.0
"""Signal std of the RBF policy's GP-mean parameterisation (fixed, as in PILCO)."""
RBF_NOISE_STD = 0.01
"""Noise std of the RBF policy's GP-mean parameterisation (fixed, as in PILCO)."""


def identity(theta):
    """``prepare`` of a policy whose parameters are its network's (nothing to precompute)."""
    return theta


class Policy(NamedTuple):
    """``init(key) -> theta`` (a pytree); ``network(prepare(theta), features (F,)) -> u (U,)``.

    ``prepare`` maps theta to the network's parameters (default: identity). ``form`` says what
    the network computes, for PILCO's moment matching (``models.form_moments.policy_moments``),
    or None where it cannot be moment-matched.
    """

    init: Callable[[jax.Array], object]
    network: Callable[[object, jax.Array], jax.Array]
    prepare: Callable[[object], object] = identity
    form: PolicyForm | None = None

    def apply(self, theta, f: jax.Array) -> jax.Array:
        """``u = network(prepare(theta), f)`` for one feature vector f (F,) -> (U,)."""
        return self.network(self.prepare(theta), f)


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
    particles it is computed once. The solve is elementwise Gauss-Jordan (``numerics.linalg``):
    ``jacfwd`` through it (``estimators.base.prepared``) and ``vmap`` over seeds never batch a
    LAPACK call.
    """

    def one_output(log_ell, y):
        scaled = theta.centres / jnp.exp(log_ell)
        sq = jnp.sum((scaled[:, None, :] - scaled[None, :, :]) ** 2, axis=-1)
        gram = RBF_SIGNAL_STD**2 * jnp.exp(-0.5 * sq)
        gram = gram + RBF_NOISE_STD**2 * jnp.eye(gram.shape[0], dtype=gram.dtype)
        return solve_det(gram, y[:, None])[0][:, 0]

    return jax.vmap(one_output, in_axes=(0, 1))(theta.log_lengthscales, theta.targets)


class RBFNetwork(NamedTuple):
    """The RBF network's parameters: centres (B, F), weights beta (U, B), log_lengthscales (U, F)."""

    centres: jax.Array
    weights: jax.Array
    log_lengthscales: jax.Array


def rbf_network(theta: RBFParams) -> RBFNetwork:
    """theta (pseudo-data) -> the network's parameters (the weight solve, once per theta)."""
    return RBFNetwork(theta.centres, rbf_weights(theta), theta.log_lengthscales)


def rbf_preactivation(net: RBFNetwork, f: jax.Array) -> jax.Array:
    """``pi~(f) = sum_i beta_i exp(-1/2 (f - c_i)^T Lambda^-1 (f - c_i))``, (U,)."""

    def one_output(log_ell, beta_u):
        sq = scaled_sq_distances(net.centres, f, jnp.exp(log_ell))
        return RBF_SIGNAL_STD**2 * jnp.exp(-0.5 * sq) @ beta_u

    return jax.vmap(one_output)(net.log_lengthscales, net.weights)


def rbf_policy(
    num_basis: int,
    u_max: tuple[float, ...],
    sample_centres: Callable[[jax.Array, int], jax.Array],
    init_lengthscales: tuple[float, ...],
    direct: bool = False,
) -> Policy:
    """An RBF network policy ``u = u_max * sat(pi~(f))``, in one of two parameterisations:

    - PILCO's (``direct=False``): theta = ``RBFParams`` (pseudo-inputs, pseudo-targets y,
      length-scales), the weights ``beta = (K + 0.01^2 I)^-1 y`` solved by ``prepare``;
    - direct (``direct=True``): theta = ``RBFNetwork`` (centres, weights w, length-scales),
      ``prepare`` the identity (the authors' demo, proppo/pipps_demo).

    ``sample_centres(key, n) -> (n, F)`` draws the initial centres; the initial pseudo-targets
    (or weights) are ``0.1 * N(0, 1)``; the initial length-scales are ``init_lengthscales``
    (F,) for every control. PILCO's moment matching applies to both (``beta = w``).
    """
    u_max_arr = jnp.asarray(u_max)
    num_controls = len(u_max)

    def init(key):
        k_centres, k_targets = jax.random.split(key)
        centres = sample_centres(k_centres, num_basis)
        targets = 0.1 * jax.random.normal(k_targets, (num_basis, num_controls), centres.dtype)
        log_ell = jnp.tile(jnp.log(jnp.asarray(init_lengthscales, centres.dtype)), (num_controls, 1))
        if direct:
            return RBFNetwork(centres, targets.T, log_ell)
        return RBFParams(centres, targets, log_ell)

    def network(net, f):
        return u_max_arr.astype(f.dtype) * saturate(rbf_preactivation(net, f))

    return Policy(init, network, identity if direct else rbf_network, PolicyForm("rbf", tuple(u_max)))


def linear_policy(feature_dim: int, u_max: tuple[float, ...], init_scale: float = 1e-2) -> Policy:
    """A linear policy ``u = u_max * sat(W f + b)``; W ~ init_scale * N(0, 1), b = 0."""
    u_max_arr = jnp.asarray(u_max)
    num_controls = len(u_max)

    def init(key):
        weight = init_scale * jax.random.normal(key, (num_controls, feature_dim))
        return LinearParams(weight, jnp.zeros((num_controls,), weight.dtype))

    def network(theta, f):
        return u_max_arr.astype(f.dtype) * saturate(theta.weight @ f + theta.bias)

    return Policy(init, network, form=PolicyForm("linear", tuple(u_max)))
