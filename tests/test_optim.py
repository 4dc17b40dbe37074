"""The paper's RMSprop-like optimiser."""

import jax.numpy as jnp
import numpy as np
import optax

from harness.optim import pipps_sgd


def test_update_matches_formula():
    opt = pipps_sgd(learning_rate=0.1, momentum=0.5)
    params = {"a": jnp.array([1.0, 2.0, 3.0])}
    state = opt.init(params)
    g1, v1 = {"a": jnp.array([3.0, -1.0, 0.0])}, {"a": jnp.array([16.0, 0.0, 0.0])}
    updates, state = opt.update(g1, state, grad_var=v1)
    m1 = np.array([3 / 5, -1.0, 0.0])  # g / sqrt(g^2 + V); 0/0 -> 0
    np.testing.assert_allclose(updates["a"], -0.1 * m1)
    g2, v2 = {"a": jnp.array([1.0, 1.0, 2.0])}, {"a": jnp.array([0.0, 3.0, 0.0])}
    updates, state = opt.update(g2, state, grad_var=v2)
    m2 = 0.5 * m1 + np.array([1.0, 0.5, 1.0])
    np.testing.assert_allclose(updates["a"], -0.1 * m2)
    np.testing.assert_allclose(optax.apply_updates(params, updates)["a"], np.array([1.0, 2.0, 3.0]) - 0.1 * m2)


def test_noise_free_steps_are_signs():
    opt = pipps_sgd()
    state = opt.init(jnp.zeros(2))
    updates, _ = opt.update(jnp.array([1e-8, -1e8]), state, grad_var=jnp.zeros(2))
    np.testing.assert_allclose(updates, [-5e-4, 5e-4])
