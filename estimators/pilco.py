"""PILCO: analytic moment matching (Deisenroth and Rasmussen, ICML 2011; PIPPS's baseline).

The state distribution is kept Gaussian, ``s_t ~ N(m_t, S_t)``, and propagated in closed form:

    f = features(s)          trig-linear map: sin/cos augmentation, then a selection
    u = policy moments(f)    RBF network (noise-free GP mean) or linear, then the saturation
    z = [s, u]               joint Gaussian, cov(s, u) = S io_f io_u
    s_{t+1} = model moments(z)   GP with a Gaussian input (+ its noise), s + delta
    J = sum_{t=1..T} E[c(s_t)]   the expected saturating cost in closed form

``io`` matrices are inverse input covariance times input-output covariance, so covariances
chain as ``cov(s, y) = S io_1 io_2 ...`` (PILCO's approximation). The gradient is autodiff
through the whole recursion; the objective is deterministic (``grad_var`` is zero). Needs the
task's declarative forms (``tasks.forms``) and a model with ``next_state_moments``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from estimators.base import Estimate, MomentForms, Problem, check_theta, task_moment_forms
from models.form_moments import expected_cost, map_moments, policy_moments


def symmetric(S: jax.Array) -> jax.Array:
    return 0.5 * (S + S.T)


def propagate(problem: Problem, net, m: jax.Array, S: jax.Array) -> tuple[jax.Array, jax.Array]:
    """One step of the moment recursion: (m_t, S_t) -> (m_{t+1}, S_{t+1})."""
    forms: MomentForms = problem.moment_forms
    f = map_moments(forms.features, m, S)
    u = policy_moments(problem.policy.form, net, f.mean, f.cov)
    cross = S @ f.io @ u.io  # cov(s, u)
    z_mean = jnp.concatenate([m, u.mean])
    z_cov = jnp.block([[S, cross], [cross.T, u.cov]])
    m_next, S_next = problem.model.next_state_moments(problem.model_params, z_mean, z_cov,
                                                      problem.model_var_scale, problem.noise_var_scale)
    return m_next, symmetric(S_next)


def pilco_objective(problem: Problem, theta) -> tuple[jax.Array, jax.Array]:
    """``J(theta)`` and the expected cost per step (T,); fails with what is missing where the
    problem cannot be moment-matched (``check_capabilities``)."""
    check_capabilities(problem)
    check_theta(problem, theta)
    forms = problem.moment_forms
    dtype = jax.tree.leaves(theta)[0].dtype
    net = problem.policy.prepare(theta)

    def step(carry, _):
        m, S = propagate(problem, net, *carry)
        return (m, S), expected_cost(forms.cost, m, S)

    init = (jnp.asarray(forms.init_mean, dtype), jnp.asarray(forms.init_cov, dtype))
    _, costs = jax.lax.scan(step, init, None, length=problem.horizon)
    return costs.sum(), costs


TASK_FORMS = ("the task's features and cost as forms: the Task properties policy_feature_map, gp_feature_map "
              "and cost_form (tasks.forms; tasks/cartpole.py defines its functions through them) and "
              "model_initial_moments; a task without them runs the particle estimators only")


POLICY_FORM = "a policy with a form (tasks.forms.PolicyForm: the RBF network or the linear policy)"


def check_task(task) -> None:
    """Fail now, naming what to add (the Task's forms, its default policy's form), when PILCO
    cannot moment-match ``task`` (rather than after a trial and a GP fit)."""
    if task_moment_forms(task) is None or task.gp_feature_map is None:
        raise ValueError(f"the pilco estimator needs {TASK_FORMS}; task {task.name!r} lacks them")
    if task.default_policy().form is None:
        raise ValueError(f"the pilco estimator needs {POLICY_FORM}; the default policy of task {task.name!r} has none")


def check_capabilities(problem: Problem) -> None:
    """Fail with what is missing when the problem cannot be moment-matched."""
    missing = []
    if problem.moment_forms is None:
        missing.append(TASK_FORMS)
    if problem.policy.form is None:
        missing.append(POLICY_FORM)
    if not hasattr(problem.model, "next_state_moments"):
        missing.append(f"a model with next_state_moments (the GP; not {type(problem.model).__name__})")
    if problem.model_var_scale not in (0.0, 1.0):
        missing.append("model_var_scale 0 or 1")
    if missing:
        raise ValueError("the pilco estimator needs " + "; ".join(missing))


@dataclasses.dataclass(frozen=True)
class Pilco:
    """``__call__(problem, theta, key, P) -> Estimate``; key and P are ignored (the objective is
    deterministic); aux: ``costs`` (T,) expected cost per step, ``nan_count``."""

    def __call__(self, problem: Problem, theta, key: Any = None, num_particles: int = 0) -> Estimate:
        (value, costs), grad = jax.value_and_grad(pilco_objective, argnums=1, has_aux=True)(problem, theta)
        nan_count = sum(jnp.sum(~jnp.isfinite(g)) for g in jax.tree.leaves(grad)) + jnp.sum(~jnp.isfinite(value))
        return Estimate(value, grad, jax.tree.map(jnp.zeros_like, grad), {"costs": costs, "nan_count": nan_count})
