"""The paper's "RMSprop-like" stochastic gradient descent (PIPPS, section "Policy Optimization").

    m     <- gamma m + g / sqrt(E[g]^2 + V[g])
    theta <- theta - alpha m

with g the gradient estimate (its own square stands in for E[g]^2) and V[g] the variance of
that estimate (per-particle variance / P, ``Estimate.grad_var``). Each parameter's step is
its gradient's sign scaled down where the estimate is noisy. An optax transformation whose
``update`` takes ``grad_var`` as an extra argument:

>>> opt = pipps_sgd()
>>> state = opt.init(theta)
>>> updates, state = opt.update(estimate.grad, state, grad_var=estimate.grad_var)
>>> theta = optax.apply_updates(theta, updates)
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

LEARNING_RATE = 5e-4
MOMENTUM = 0.9


class PippsSGDState(NamedTuple):
    """momentum: a pytree like the parameters."""

    momentum: Any


def normalised_gradient(g: jax.Array, var: jax.Array) -> jax.Array:
    """``g / sqrt(g^2 + var)`` elementwise, computed in the wider of the two dtypes (a float32
    gradient's variance comes in float64, ``estimators.base.variance_of_mean``) and returned in
    g's; 0 where both are 0 (no information) and where g or var is not finite (an overflowed or
    NaN estimate moves that parameter nothing; inf / inf would otherwise put NaN in the momentum
    and in theta for good)."""
    wide = jnp.promote_types(g.dtype, jnp.asarray(var).dtype)
    g_wide, var = g.astype(wide), jnp.asarray(var, wide)
    denom = jnp.sqrt(g_wide**2 + var)
    usable = (denom > 0) & jnp.isfinite(g_wide) & jnp.isfinite(var)
    return jnp.where(usable, g_wide / jnp.where(usable, denom, 1.0), 0.0).astype(g.dtype)


def pipps_sgd(learning_rate: float = LEARNING_RATE, momentum: float = MOMENTUM) -> optax.GradientTransformationExtraArgs:
    """The paper's optimiser; ``update(grads, state, params=None, *, grad_var)``."""

    def init(params):
        return PippsSGDState(jax.tree.map(jnp.zeros_like, params))

    def update(updates, state, params=None, *, grad_var, **extra_args):
        del params, extra_args
        m = jax.tree.map(lambda m, g, v: momentum * m + normalised_gradient(g, v), state.momentum, updates, grad_var)
        return jax.tree.map(lambda m: -learning_rate * m, m), PippsSGDState(m)

    return optax.GradientTransformationExtraArgs(init, update)
