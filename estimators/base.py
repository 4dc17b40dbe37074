"""What every particle estimator shares: the problem, the estimate, the particle transition.

Particle rollout (PIPPS, section "Particle Model-Based Policy Search"): ``s_0 ~ p(s_0)``; for
t = 0..T-1: ``u_t = pi(features(s_t); theta)``, ``zeta_{t+1} = (m, sd)`` from the model's
prediction, ``s_{t+1} = m + sd * eps``; the objective is ``J = sum_{t=1..T} E[c(s_t)]``,
estimated by the mean over particles of each particle's return.

Shapes: P particles, T steps, S modelled-state dims; scan outputs are (T, P, S).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, ClassVar, NamedTuple

import jax
import jax.flatten_util
import jax.numpy as jnp

from models.prediction import Model
from tasks.base import Task
from tasks.forms import SaturatingCost, TrigLinearMap
from tasks.policies import Policy, identity


@functools.partial(
    jax.tree_util.register_dataclass,
    data_fields=["model_params"],
    meta_fields=["model", "policy", "cost", "features", "initial_state", "horizon",
                 "model_var_scale", "noise_var_scale", "moment_forms"],
)
@dataclasses.dataclass(frozen=True)
class Problem:
    """A particle policy-search problem: model, policy, cost and initial distribution.

    ``model_var_scale`` and ``noise_var_scale`` multiply the predicted model and noise
    variances before sampling (the paper's variants: TP-sigma_f samples only the learned noise,
    ``model_var_scale=0``; TP+sigma_n uses ``noise_var_scale=100``). A pytree whose only data
    is ``model_params`` (e.g. the GP posterior), so it can be passed to jitted functions.
    ``moment_forms`` (``MomentForms``) is what PILCO needs beyond this, or None.
    """

    model: Model
    model_params: Any
    policy: Policy
    cost: Callable[[jax.Array], jax.Array]
    features: Callable[[jax.Array], jax.Array]
    initial_state: Callable[[jax.Array], jax.Array]
    horizon: int
    model_var_scale: float = 1.0
    noise_var_scale: float = 1.0
    moment_forms: Any = None


def task_problem(task: Task, model: Model, model_params: Any = None, *, policy: Policy | None = None,
                 horizon: int | None = None, model_var_scale: float = 1.0,
                 noise_var_scale: float = 1.0) -> Problem:
    """The problem of ``task`` under ``model``: its cost, policy features, initial distribution
    (mapped to the modelled state), default policy and horizon unless given."""
    return Problem(
        model=model,
        model_params=model_params,
        policy=task.default_policy() if policy is None else policy,
        cost=task.cost,
        features=task.policy_features,
        initial_state=lambda key: task.to_model_state(task.sample_initial(key)),
        horizon=task.horizon if horizon is None else horizon,
        model_var_scale=model_var_scale,
        noise_var_scale=noise_var_scale,
        moment_forms=task_moment_forms(task),
    )


class MomentForms(NamedTuple):
    """What PILCO needs beyond the particle problem: the policy's features and the cost as
    forms (``tasks.forms``), and the initial distribution N(init_mean, init_cov) (nested tuples)."""

    features: TrigLinearMap
    cost: SaturatingCost
    init_mean: tuple
    init_cov: tuple


def task_moment_forms(task: Task):
    """The task's features, cost and initial moments for PILCO, or None if the task does not
    declare them."""
    initial = task.model_initial_moments
    if task.policy_feature_map is None or task.cost_form is None or initial is None:
        return None
    mean, cov = initial
    return MomentForms(task.policy_feature_map, task.cost_form, tuple(mean.tolist()), tuple(map(tuple, cov.tolist())))


class Estimate(NamedTuple):
    """value: the Monte Carlo estimate of J; grad: dJ/dtheta (pytree like theta);
    grad_var: per-parameter variance of ``grad`` (per-particle variance / P, like theta);
    aux: diagnostics (arrays; ``nan_count``, ``particle_grads`` (leaves (P, ...)), and e.g.
    ``k_lr`` (T,), ``ess`` (T,))."""

    value: jax.Array
    grad: Any
    grad_var: Any
    aux: dict


class Zeta(NamedTuple):
    """Distribution parameters of a particle's next state: mean and std, each (S,)."""

    mean: jax.Array
    std: jax.Array


def next_state_distribution(problem: Problem, net, s: jax.Array) -> Zeta:
    """``zeta_{t+1}(s_t; theta)`` for ONE particle, from the policy's prepared parameters
    ``net = policy.prepare(theta)``: the policy acts on ``features(s_t)``, the model
    predicts, the variances are scaled and summed."""
    u = problem.policy.network(net, problem.features(s))
    pred = problem.model.predict(problem.model_params, s, u)
    if wrong := {name: jnp.shape(x) for name, x in pred._asdict().items() if jnp.shape(x) != s.shape}:
        raise ValueError(f"{type(problem.model).__name__}.predict(params, s, u) returned {wrong} for one particle's "
                         f"state of shape {s.shape}: mean, model_var and noise_var must each be shaped like the state "
                         "(the estimators vmap over particles)")
    var = problem.model_var_scale * pred.model_var + problem.noise_var_scale * pred.noise_var
    return Zeta(pred.mean, jnp.sqrt(var))


class Trajectory(NamedTuple):
    """A particle rollout: states (T+1, P, S) s_0..s_T; zetas: Zeta of (T, P, S) for
    s_1..s_T; costs (T, P) c(s_1)..c(s_T)."""

    states: jax.Array
    zetas: Zeta
    costs: jax.Array

    @property
    def returns(self) -> jax.Array:
        """Each particle's return ``sum_t c(s_t)``, (P,)."""
        return self.costs.sum(axis=0)

    @property
    def cost_to_go(self) -> jax.Array:
        """``G[t, i] = sum_{tau >= t} costs[tau, i]``: cost-to-go from s_{t+1}, (T, P)."""
        return jnp.cumsum(self.costs[::-1], axis=0)[::-1]


def standard_normal(key: jax.Array, shape: tuple[int, ...], dtype) -> jax.Array:
    """N(0, 1) draws made in JAX's default float (float64 under ``jax_enable_x64``) and cast to
    ``dtype``: one key gives the same numbers, rounded, in float32 and float64 (common random
    numbers to compare the two precisions with)."""
    return jax.random.normal(key, shape, jnp.result_type(float)).astype(dtype)


def draw_noise(problem: Problem, key: jax.Array, num_particles: int, dtype):
    """Initial particles s0 (P, S) and the standard-normal noise eps (T, P, S) of a rollout (both
    drawn in the default float, then cast to ``dtype``)."""
    k_init, k_eps = jax.random.split(key)
    s0 = jax.vmap(problem.initial_state)(jax.random.split(k_init, num_particles)).astype(dtype)
    eps = standard_normal(k_eps, (problem.horizon,) + s0.shape, dtype)
    return s0, eps


def rollout(problem: Problem, nets, s0: jax.Array, eps: jax.Array, *, detach_samples: bool = False,
            resample: Callable[[jax.Array, jax.Array], jax.Array] | None = None,
            resample_noise: jax.Array | None = None) -> Trajectory:
    """Roll P particles forward with per-particle copies ``nets`` (leaves (P, ...)) of the
    policy's prepared parameters.

    Giving each particle its own copy makes ``d(objective)/d(nets)[i]`` particle i's
    contribution to the gradient, from which the gradient's variance is estimated.
    ``detach_samples`` holds each sample fixed (no gradient through the sampling: the
    likelihood-ratio estimators). ``resample(s_tilde (P, S), xi (P, S)) -> (P, S)`` replaces
    the sampled particles after each step (Gaussian resampling), with noise ``resample_noise``
    (T, P, S), which must be given with ``resample`` (drawn apart from eps: reusing eps was
    GR's bug until 2026-12-06).
    """
    if (resample is None) != (resample_noise is None):
        raise ValueError("rollout: give resample and resample_noise together (the resampling noise must be "
                         "drawn independently of eps, e.g. estimators.reparameterisation.draw_resampling_noise)")

    def one_step(s, inputs):
        eps_t, xi_t = inputs
        zeta = jax.vmap(functools.partial(next_state_distribution, problem))(nets, s)
        s_next = zeta.mean + zeta.std * eps_t
        if detach_samples:
            s_next = jax.lax.stop_gradient(s_next)
        if resample is not None:
            s_next = resample(s_next, xi_t)
        return s_next, (s_next, zeta, jax.vmap(problem.cost)(s_next))

    xi = eps if resample_noise is None else resample_noise  # without resample, a placeholder the scan ignores
    _, (states, zetas, costs) = jax.lax.scan(one_step, s0, (eps, xi))
    return Trajectory(jnp.concatenate([s0[None], states]), zetas, costs)


def per_particle(theta, num_particles: int):
    """A copy of theta per particle: every leaf broadcast to (P, ...)."""
    return jax.tree.map(lambda x: jnp.broadcast_to(x, (num_particles,) + jnp.shape(x)), theta)


def variance_of_mean(g: jax.Array) -> jax.Array:
    """``var_i(g_i) / P`` (ddof 1) of per-particle values g (P, ...), accumulated in JAX's widest
    float (float64 under ``jax_enable_x64``) and returned in it: a float32 gradient above about
    1.8e19 squares past float32's range, so its variance would overflow to inf while the gradient
    itself is finite. Without x64 it stays in g's dtype (and can overflow)."""
    wide = g.astype(jnp.promote_types(g.dtype, jnp.result_type(float)))
    return wide.var(axis=0, ddof=1) / g.shape[0]


def particle_estimate(value: jax.Array, per_particle_grads, extra_nans=0, **aux) -> Estimate:
    """The Estimate from per-particle gradient estimates g_i (leaves (P, ...)): the mean
    gradient, the variance of that mean ``var_i(g_i) / P`` (``variance_of_mean``: float64 under
    x64, whatever g's dtype), and in aux the count of non-finite entries (plus ``extra_nans``)
    and the g_i themselves as ``particle_grads`` (for statistics of projections, e.g. a
    directional derivative's confidence interval)."""
    grad = jax.tree.map(lambda g: g.mean(axis=0), per_particle_grads)
    grad_var = jax.tree.map(variance_of_mean, per_particle_grads)
    nan_count = sum(jnp.sum(~jnp.isfinite(g)) for g in jax.tree.leaves(per_particle_grads)) + extra_nans
    return Estimate(value, grad, grad_var, {**aux, "nan_count": nan_count, "particle_grads": per_particle_grads})


def check_theta(problem: Problem, theta) -> None:
    """Fail (while tracing) when theta is not shaped like ``problem.policy.init``'s parameters."""
    expected = jax.eval_shape(problem.policy.init, jax.random.key(0))
    same_shapes = [jnp.shape(x) for x in jax.tree.leaves(theta)] == [x.shape for x in jax.tree.leaves(expected)]
    if jax.tree.structure(theta) != jax.tree.structure(expected) or not same_shapes:
        raise ValueError(f"theta {jax.tree.map(jnp.shape, theta)} is not shaped like the policy's parameters "
                         f"{jax.tree.map(lambda x: x.shape, expected)} (problem.policy.init(key) makes them)")


def prepared(problem: Problem, theta):
    """``(net, to_theta)``: the policy's prepared parameters and the linear map taking a batch
    of cotangents for net (leaves (*batch, *net shape)) to cotangents for theta.

    The map is the transposed Jacobian of ``prepare``, materialised once per estimate (forward
    mode) as a (net size, theta size) matrix, so that mapping many per-particle cotangents is
    one matmul rather than a batch of solves through the RBF weights (the cart-pole's RBF
    network: 305 x 305). Where ``prepare`` is the identity the map is the identity, skipped.
    """
    check_theta(problem, theta)
    if problem.policy.prepare is identity:  # nothing to map (the direct RBF, the linear policy)
        return theta, lambda net_grads, batch_dims=1: net_grads
    flat_theta, unravel_theta = jax.flatten_util.ravel_pytree(theta)

    def flat_prepare(x):
        return jax.flatten_util.ravel_pytree(problem.policy.prepare(unravel_theta(x)))[0]

    jacobian = jax.jacfwd(flat_prepare)(flat_theta)  # (net size, theta size)

    def to_theta(net_grads, batch_dims: int = 1):
        leaves = jax.tree.leaves(net_grads)  # the order ravel_pytree uses
        batch = leaves[0].shape[:batch_dims]
        flat = jnp.concatenate([g.reshape(batch + (-1,)) for g in leaves], axis=-1)
        unravel = unravel_theta
        for _ in range(batch_dims):
            unravel = jax.vmap(unravel)
        return unravel(flat @ jacobian)

    return problem.policy.prepare(theta), to_theta


def particle_gradients(objective: Callable[[Any], tuple[jax.Array, Any]], problem: Problem, theta,
                       num_particles: int):
    """Differentiate a particle objective ``objective(nets) -> (mean over particles, aux)``
    with respect to per-particle copies of the prepared policy parameters; returns (value,
    per-particle gradients (leaves (P, ...) like theta), aux). Particle i's estimate is
    ``P * d objective / d nets[i]`` mapped to theta."""
    net, to_theta = prepared(problem, theta)
    (value, aux), grads = jax.value_and_grad(objective, has_aux=True)(per_particle(net, num_particles))
    return value, to_theta(jax.tree.map(lambda g: num_particles * g, grads)), aux


def theta_dtype(theta):
    """The floating dtype of the policy parameters (the rollout runs in it)."""
    return jax.tree.leaves(theta)[0].dtype


@dataclasses.dataclass(frozen=True)
class FixedNoise:
    """PEGASUS: ``inner`` with its noise fixed for a whole policy optimisation, so that the
    objective is deterministic and the gradient exact for it. The estimate is ``inner``'s with
    the key it is given; ``fixes_noise`` tells the optimiser (``harness.episodic``) to give the
    optimisation's own key at every step rather than a fresh key per step. So the noise is
    fixed within a trial's optimisation and differs across trials and repeats."""

    inner: Any
    fixes_noise: ClassVar[bool] = True

    def __call__(self, problem: Problem, theta, key: jax.Array, num_particles: int) -> Estimate:
        return self.inner(problem, theta, key, num_particles)
