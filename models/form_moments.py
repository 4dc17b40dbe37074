"""Moments of the declarative forms of ``tasks.forms`` for a Gaussian state (PILCO's
augmentation and expected cost), built on ``models.moment_matching``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from models.moment_matching import Moments, saturating_cost_moments, trig_moments
from tasks.forms import SaturatingCost, TrigLinearMap


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
