"""Squared distances for the SE kernels (the GP's and the RBF policy's), in matrix products.

``|(p_i - x) / l|^2 = |p_i / l|^2 + |x / l|^2 - 2 (p_i / l) . (x / l)``: for one query x and N
points this is a matrix-vector product, and under ``vmap`` over queries one matrix product.
Reverse mode then keeps (N,) values per query as residuals instead of the (N, D) differences
``p_i - x``: for the particle rollouts (300 particles x 30 steps x 4 outputs x N points x D)
that is D times less memory traffic. Round-off can take a distance slightly below 0; it is
clipped there (relative error ~1e-16 |p / l|^2 in float64).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def scaled_sq_distances(points: jax.Array, x: jax.Array, lengthscales: jax.Array) -> jax.Array:
    """``|(points_i - x) / lengthscales|^2`` for points (N, D), x (D,), lengthscales (D,) -> (N,)."""
    p, q = points / lengthscales, x / lengthscales
    return jnp.maximum(jnp.sum(p * p, axis=-1) + jnp.sum(q * q) - 2.0 * (p @ q), 0.0)
