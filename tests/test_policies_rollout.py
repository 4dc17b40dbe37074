"""Policies and episodes on the real system."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from tasks.policies import RBF_NOISE_STD, linear_policy, rbf_weights, saturate
from tasks.rollout import run_episode, transitions


def test_saturation():
    a = jnp.linspace(-10, 10, 2001)
    sat = saturate(a)
    assert float(jnp.max(jnp.abs(sat))) <= 1.0 + 1e-15
    assert float(saturate(jnp.array(math.pi / 2))) == pytest.approx(1.0, abs=1e-15)  # (9 - 1) / 8
    # Near 0 the saturation is the identity to first order: derivative (9 + 3) / 8 = 1.5.
    assert float(jax.grad(saturate)(0.0)) == pytest.approx(1.5)


def test_rbf_policy_is_pilco_gp_mean():
    """pi~(f) = sum_i beta_i k(f, c_i), beta = (K + sn^2 I)^-1 y: at a centre, with a tiny
    noise, the network nearly interpolates its pseudo-target."""
    task = tasks.make("cartpole", rbf_parameterisation="pseudo_inputs")
    policy = task.default_policy()
    theta = policy.init(jax.random.key(1))
    assert theta.centres.shape == (50, 5) and theta.targets.shape == (50, 1)
    np.testing.assert_allclose(jnp.exp(theta.log_lengthscales), [[1, 1, 1, 0.7, 0.7]], rtol=1e-12)
    # Dense check of the weights in numpy.
    c, y = np.asarray(theta.centres), np.asarray(theta.targets[:, 0])
    ell = np.array([1, 1, 1, 0.7, 0.7])
    gram = np.exp(-0.5 * (((c[:, None] - c[None]) / ell) ** 2).sum(-1)) + RBF_NOISE_STD**2 * np.eye(50)
    beta = np.linalg.solve(gram, y)
    np.testing.assert_allclose(rbf_weights(theta)[0], beta, rtol=1e-8)
    f = jnp.array([0.05, -0.1, 0.2, 0.01, -0.99])
    pre = np.exp(-0.5 * (((np.asarray(f) - c) / ell) ** 2).sum(-1)) @ beta
    np.testing.assert_allclose(policy.apply(theta, f), 10 * saturate(pre), rtol=1e-8)


def test_direct_rbf_policy():
    """The direct form: theta holds the weights (U, B) themselves, small at the start; the
    centres start at the initial mean's features plus N(0, 1) noise."""
    task = tasks.make("cartpole", rbf_parameterisation="direct")
    policy = task.default_policy()
    theta = policy.init(jax.random.key(1))
    assert theta.centres.shape == (50, 5) and theta.weights.shape == (1, 50)
    scale = float(np.std(jax.vmap(policy.init)(jax.random.split(jax.random.key(3), 200)).weights))
    assert 0.097 < scale < 0.103  # 0.1 * N(0, 1): 10,000 draws, s.e. of the sd 0.7 %
    spread = np.asarray(theta.centres) - np.array([0.0, 0.0, 0.0, 0.0, 1.0])  # features of the mean state
    assert np.all(np.abs(spread.mean(0)) < 0.5) and np.all((0.7 < spread.std(0)) & (spread.std(0) < 1.3))
    f = jnp.array([0.05, -0.1, 0.2, 0.01, -0.99])
    ell = np.array([1, 1, 1, 0.7, 0.7])
    pre = np.exp(-0.5 * (((np.asarray(f) - np.asarray(theta.centres)) / ell) ** 2).sum(-1)) @ np.asarray(theta.weights[0])
    np.testing.assert_allclose(policy.apply(theta, f), 10 * saturate(pre), rtol=1e-10)


def test_linear_policy():
    policy = tasks.make("unicycle").default_policy()
    theta = policy.init(jax.random.key(2))
    assert theta.weight.shape == (2, 10) and float(jnp.abs(theta.bias).max()) == 0.0
    scale = float(np.std(jax.vmap(policy.init)(jax.random.split(jax.random.key(3), 500)).weight))
    assert 0.0097 < scale < 0.0103  # 1e-2 * N(0, 1): 10,000 draws, s.e. of the sd 0.7 %
    s = jnp.linspace(-1, 1, 10)
    np.testing.assert_allclose(policy.apply(theta, s), jnp.array([10.0, 50.0]) * saturate(theta.weight @ s), rtol=1e-14)
    big = linear_policy(10, (10.0, 50.0)).apply(theta._replace(bias=jnp.array([100.0, -100.0])), s)
    assert bool(jnp.all(jnp.abs(big) <= jnp.array([10.0, 50.0])))


def test_random_episode():
    task = tasks.make("cartpole")
    keys = jax.random.split(jax.random.key(3), 8)
    episodes = jax.jit(jax.vmap(lambda k: run_episode(task, k)))(keys)
    T = task.horizon
    assert episodes.latent.shape == (8, T + 1, 4) and episodes.controls.shape == (8, T, 1)
    assert bool(jnp.all(jnp.abs(episodes.controls) <= 10.0)) and float(episodes.controls.std()) > 4.0
    # Latent states follow the true dynamics exactly, with the recorded controls.
    step = jax.vmap(jax.vmap(task.step))
    np.testing.assert_allclose(step(episodes.latent[:, :-1], episodes.controls), episodes.latent[:, 1:], atol=1e-12)
    # Costs are on the latent state; observations carry the noise of the task.
    cost = jax.vmap(jax.vmap(task.cost))(episodes.latent[:, 1:])
    np.testing.assert_allclose(episodes.costs, cost, atol=1e-14)
    noise = (episodes.observed - episodes.latent).reshape(-1, 4)
    np.testing.assert_allclose(noise.std(0), task.obs_noise_std, rtol=0.2)  # 248 draws: std error ~5 %
    assert bool(jnp.all(episodes.alive))
    # The same key gives the same episode.
    again = run_episode(task, keys[0])
    np.testing.assert_allclose(again.observed, episodes.observed[0], atol=1e-12)


def test_policy_episode_and_transitions():
    task = tasks.make("cartpole")
    policy = task.default_policy()
    theta = policy.init(jax.random.key(4))
    episode = run_episode(task, jax.random.key(5), policy, theta)
    s_obs = episode.observed
    u_expected = jax.vmap(lambda o: policy.apply(theta, task.policy_features(o)))(s_obs[:-1])
    np.testing.assert_allclose(episode.controls, u_expected, atol=1e-12)
    inputs, targets, mask = transitions(task, episode)
    assert inputs.shape == (task.horizon, 6) and targets.shape == (task.horizon, 4)
    np.testing.assert_allclose(targets, s_obs[1:] - s_obs[:-1], atol=1e-15)
    assert bool(mask.all())


def test_unicycle_fall_freezes_episode():
    """A constant full wheel torque throws the frame over: after the fall the latent state
    stays put, the cost repeats, and the transitions are masked out."""
    task = tasks.make("unicycle")
    params = task.default_policy().init(jax.random.key(6))
    tipping = params._replace(weight=jnp.zeros((2, 10)), bias=jnp.array([0.0, 1.5]))
    episode = run_episode(task, jax.random.key(7), task.default_policy(), tipping)
    fell = np.asarray(jax.vmap(task.fallen)(episode.latent[1:]))
    assert fell.any(), "the test needs an episode that falls"
    first = int(np.argmax(fell))
    assert bool(episode.alive[first]) and not bool(episode.alive[first + 1:].any())
    np.testing.assert_allclose(episode.latent[first + 2:], jnp.broadcast_to(episode.latent[first + 1], episode.latent[first + 2:].shape))
    np.testing.assert_allclose(episode.costs[first:], episode.costs[first])
    assert bool(episode.alive[:first].all())
    mask = transitions(task, episode)[2]  # the transition into the fall is not training data
    assert bool(mask[:first].all()) and not bool(mask[first:].any())


def test_unicycle_step_stops_at_the_fall(unicycle_falling_state):
    """The ideal-rolling equations are singular where the wheel lies flat (det A -> 0 as
    |theta| -> pi/2). From this state (met in a variance run on the true dynamics) the
    integration through the fall diverged to NaN within one control period. ``Task.step`` stops
    at the first fallen substep: the result is finite and fallen, a fallen state stays put, and
    the step's Jacobian is finite."""
    task = tasks.make("unicycle")
    z, u = unicycle_falling_state
    step = jax.jit(task.step)  # one compilation for both states
    z1 = step(z, u)
    assert np.isfinite(z1).all() and bool(task.fallen(z1))
    np.testing.assert_array_equal(step(z1, u), z1)
    assert np.isfinite(jax.jit(jax.jacrev(task.step))(z, u)).all()
