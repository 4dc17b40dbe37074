"""Moments of the declarative forms of ``tasks.forms`` for a Gaussian input (PILCO's
augmentation, policy and expected cost), built on ``models.moment_matching``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from models.moment_matching import (Moments, rbf_policy_moments, saturating_cost_moments, saturation_moments,
                                    trig_moments)
from tasks.forms import PolicyForm, SaturatingCost, TrigLinearMap


def map_moments(form: TrigLinearMap, m: jax.Array, S: jax.Array) -> Moments:
    """Moments of ``form(s)`` for s ~ N(m (S,), S (S, S)); io (S, Q)."""
    angle_map, matrix, offset = form.arrays(m.dtype)
    if form.num_angles:
        trig = trig_moments(m, S, angle_map)
        y_mean = jnp.concatenate([m, trig.mean])
        cross = S @ trig.io
        y_cov = jnp.block([[S, cross], [cross.T, trig.cov]])
        y_io = jnp.concatenate([jnp.eye(m.shape[0], dtype=m.dtype), trig.io], axis=1)
    else:
        y_mean, y_cov, y_io = m, S, jnp.eye(m.shape[0], dtype=m.dtype)
    return Moments(matrix @ y_mean + offset, matrix @ y_cov @ matrix.T, y_io @ matrix.T)


def expected_cost(cost: SaturatingCost, m: jax.Array, S: jax.Array) -> jax.Array:
    """``E[c(s)]`` for s ~ N(m, S)."""
    point = map_moments(cost.point, m, S)
    mean, _ = saturating_cost_moments(point.mean, point.cov, jnp.zeros_like(point.mean),
                                      jnp.asarray(cost.weight, m.dtype))
    return mean


def policy_moments(form: PolicyForm, net, m: jax.Array, S: jax.Array) -> Moments:
    """Moments of the policy's control ``u`` for features f ~ N(m (F,), S (F, F)), ``net =
    policy.prepare(theta)``; io (F, U) chains the pre-activation's and the saturation's."""
    if form.network == "rbf":
        pre = rbf_policy_moments(net, m, S)
    elif form.network == "linear":  # exact for an affine map
        pre = Moments(net.weight @ m + net.bias, net.weight @ S @ net.weight.T, net.weight.T)
    else:
        raise ValueError(f"no moments for a policy network {form.network!r}; known: 'rbf', 'linear'")
    if form.u_max is None:
        return pre
    u = saturation_moments(pre.mean, pre.cov, jnp.asarray(form.u_max, m.dtype))
    return Moments(u.mean, u.cov, pre.io @ u.io)
