"""The paper's RMSprop-like optimiser."""

import jax.numpy as jnp
import pytest
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


def test_an_infinite_or_nan_component_moves_that_parameter_nothing():
    """An overflowed component (inf, with a finite or infinite variance) or a NaN one gives 0,
    never NaN, so the momentum and theta stay finite; the finite components take their step."""
    opt = pipps_sgd()
    state = opt.init(jnp.zeros(4))
    grad = jnp.array([jnp.inf, -jnp.inf, jnp.nan, 2.0])
    updates, state = opt.update(grad, state, grad_var=jnp.array([0.0, jnp.inf, 1.0, 0.0]))
    np.testing.assert_array_equal(updates, [0.0, 0.0, 0.0, -5e-4])
    np.testing.assert_array_equal(state.momentum, [0.0, 0.0, 0.0, 1.0])


def test_non_finite_estimates_at_chosen_steps_are_counted_and_move_nothing():
    """An estimator of J = |theta|^2 / 2 that returns NaN at steps 2 and 5 of 8 (it knows the
    step by its key: ``optimise_policy`` gives step s the key ``split(key, 8)[s]``)."""
    import jax

    from estimators.base import Estimate
    from harness.episodic import optimise_policy

    key, num_steps, nan_steps = jax.random.key(0), 8, jnp.array([2, 5])
    bad_keys = jax.random.key_data(jax.random.split(key, num_steps)[nan_steps])

    def nan_at_chosen_steps(problem, theta, step_key, num_particles):
        bad = jnp.any(jnp.all(bad_keys == jax.random.key_data(step_key), axis=-1))
        grad = jnp.where(bad, jnp.nan, theta)
        return Estimate(0.5 * jnp.sum(theta**2), grad, jnp.zeros_like(theta), {})

    theta0 = jnp.array([1.0, -2.0])
    result = optimise_policy(None, theta0, key, estimator=nan_at_chosen_steps, num_steps=num_steps, num_particles=1)
    assert int(result.nonfinite_steps) == 2
    assert bool(jnp.all(jnp.isfinite(result.theta)))
    # The steps' momentum sums: 6 finite sign steps of size 1, the NaN steps add 0.
    momentum, moved = 0.0, 0.0
    for step in range(num_steps):
        momentum = 0.9 * momentum + (0.0 if step in (2, 5) else 1.0)
        moved += 5e-4 * momentum
    np.testing.assert_allclose(result.theta, theta0 - moved * jnp.sign(theta0), rtol=1e-12)


def test_a_float32_particle_gradient_past_1e19_still_takes_its_step():
    """Regression (RP's repeat 0 at k = 1, ``diagnostics/rp_nonfinite_replay.py``): float32
    particle gradients with a median near 1e15 and one particle at 1e25 are finite, but their
    squares pass float32's 3.4e38, so a float32 variance overflowed and the optimiser moved those
    parameters nothing. The variance is now accumulated in float64 (x64 is on in the tests): it is
    finite, equals numpy's float64 variance, and the step is float64's g / sqrt(g^2 + var)."""
    from estimators.base import particle_estimate

    rng = np.random.default_rng(13)
    particle_grads = (1e15 * rng.standard_normal((300, 3))).astype(np.float32)
    particle_grads[17, 1] = 1e25  # one exploded particle, as at the replay's non-finite steps
    estimate = particle_estimate(jnp.float32(1.0), jnp.asarray(particle_grads))
    assert estimate.grad.dtype == jnp.float32 and np.isfinite(estimate.grad).all()
    wide = particle_grads.astype(np.float64)
    expected_var = wide.var(axis=0, ddof=1) / 300
    np.testing.assert_allclose(estimate.grad_var, expected_var, rtol=1e-12)
    opt = pipps_sgd()
    updates, state = opt.update(estimate.grad, opt.init(jnp.zeros(3, jnp.float32)), grad_var=estimate.grad_var)
    assert updates.dtype == jnp.float32 and state.momentum.dtype == jnp.float32
    g = np.asarray(estimate.grad, np.float64)
    np.testing.assert_allclose(updates, -5e-4 * g / np.sqrt(g**2 + expected_var), rtol=1e-6)
    assert abs(float(updates[1])) > 1e-5  # the exploded parameter moves (it moved 0 in float32)


def test_the_deterministic_optimiser_keeps_to_its_evaluation_budget_and_descends(monkeypatch):
    """L-BFGS on RP_FS's fixed-noise objective (``fixed_noise_lbfgs_optimiser``), 50 evaluations: every
    evaluation of the objective is counted (a callback inside it) and none is past the budget; the
    objective at the returned theta is the lowest of its steps' and below theta0's; a method whose noise
    is not fixed is refused."""
    import jax

    import estimators
    from harness import bench, episodic

    jax.config.update("jax_enable_x64", True)
    _, problem, theta, _ = bench.bench_problem(bench.Args(trials=1, gp_steps=5))
    inner, calls = estimators.make("rp_fs"), []

    def counted(problem, theta, key, num_particles):
        estimate = inner(problem, theta, key, num_particles)
        jax.debug.callback(lambda: calls.append(1))
        return estimate

    counted.fixes_noise = True
    monkeypatch.setattr(estimators, "make", lambda name: counted if name == "counted_rp_fs" else inner)
    key = jax.random.key(3)
    result = episodic.fixed_noise_lbfgs_optimiser("counted_rp_fs", 50, 8)(problem, theta, key)
    values = np.asarray(result.values)
    steps = values[np.isfinite(values)]
    assert 0 < len(calls) <= 50 and len(steps) >= 2 and int(result.nonfinite_steps) == 0
    final = float(inner(problem, result.theta, key, 8).value)
    assert final <= steps.min() + 1e-9 and final < steps[0]  # steps[0]: J at theta0
    monkeypatch.undo()
    with pytest.raises(ValueError, match="fixed-noise estimator"):
        episodic.fixed_noise_lbfgs_optimiser("rp", 50, 8)
