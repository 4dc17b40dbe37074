"""Episodic model-based policy search, one piece per function (PIPPS, section "Experiments").

A learning run is: random trials -> [fit the GP to all data, optimise the policy on the
model, run it once on the real system and add the data] x learned trials. The functions here
are the pieces; ``harness.scenario`` and the learning experiment put them together.
"""

from __future__ import annotations

import functools

import jax
import optax

from estimators.base import Problem
from harness.optim import LEARNING_RATE, MOMENTUM, pipps_sgd
from models import gp
from tasks.base import Task
from tasks.rollout import Episode, run_episode, transitions


def data_capacity(task: Task, num_trials: int | None = None) -> int:
    """Rows a GP buffer needs for ``num_trials`` episodes (default: the preset's random and
    learned trials)."""
    if num_trials is None:
        num_trials = task.num_random_trials + task.num_learned_trials
    return num_trials * task.horizon


def add_episode(task: Task, data: gp.GPData, episode: Episode) -> gp.GPData:
    """Append an episode's valid transitions (observed states) to the GP buffer."""
    return gp.add_data(data, *transitions(task, episode))


@functools.partial(jax.jit, static_argnames=("estimator", "num_steps", "num_particles", "learning_rate", "momentum"))
def optimise_policy(problem: Problem, theta, key: jax.Array, *, estimator, num_steps: int, num_particles: int,
                    learning_rate: float = LEARNING_RATE, momentum: float = MOMENTUM):
    """``num_steps`` steps of the paper's optimiser on the model (one gradient estimate with a
    fresh key per step). Returns the final theta and the objective estimate at each step
    (num_steps,). One compilation serves every trial with the same buffer capacity."""
    optimiser = pipps_sgd(learning_rate, momentum)

    def one_step(carry, step_key):
        theta, opt_state = carry
        estimate = estimator(problem, theta, step_key, num_particles)
        updates, opt_state = optimiser.update(estimate.grad, opt_state, grad_var=estimate.grad_var)
        return (optax.apply_updates(theta, updates), opt_state), estimate.value

    keys = jax.random.split(key, num_steps)
    (theta, _), values = jax.lax.scan(one_step, (theta, optimiser.init(theta)), keys)
    return theta, values


def evaluate_policy(task: Task, policy, theta, key: jax.Array, num_runs: int) -> jax.Array:
    """Returns (num_runs,) of the policy on the real system (evaluation only)."""
    episodes = jax.vmap(lambda k: run_episode(task, k, policy, theta))(jax.random.split(key, num_runs))
    return episodes.total_cost
