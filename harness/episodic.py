"""Episodic model-based policy search, one piece per function (PIPPS, section "Experiments").

A learning run is: random trials -> [fit the GP to all data, optimise the policy on the
model, run it once on the real system and add the data] x learned trials. The functions here
are the pieces; ``harness.scenario`` and the learning experiment put them together.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

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


class TrialRecord(NamedTuple):
    """One real-system trial of a learning run: ``trial`` (0-based over all trials), whether it
    was ``learned`` (else random), the episode, and theta after it (None for random trials)."""

    trial: int
    learned: bool
    episode: Episode
    theta: Any


def learning_run(task: Task, problem: Problem, key: jax.Array, num_learned: int,
                 optimise: Callable[[Problem, Any, jax.Array], Any], gp_steps: int,
                 on_trial: Callable[[TrialRecord, gp.GPData], None] = lambda record, data: None):
    """The paper's episodic loop: the task's random trials, then ``num_learned`` times: fit the
    GP to all data (``gp_steps`` L-BFGS steps), ``theta = optimise(problem with the GP, theta,
    key)``, one real trial, add its data. Keys: random trial r ``fold_in(key, r)``, theta0
    ``fold_in(key, 10_000)``, optimisation and trial t ``fold_in(key, 20_000 + t)`` and
    ``fold_in(key, 30_000 + t)``. ``on_trial`` sees each trial as it ends. Returns
    (theta, data)."""
    data = problem.model.empty_data(data_capacity(task, task.num_random_trials + num_learned))
    for trial in range(task.num_random_trials):
        episode = run_episode(task, jax.random.fold_in(key, trial))
        data = add_episode(task, data, episode)
        on_trial(TrialRecord(trial, False, episode, None), data)
    theta = problem.policy.init(jax.random.fold_in(key, 10_000))
    for trial in range(num_learned):
        posterior = gp.fit(data, num_steps=gp_steps)
        problem = dataclasses.replace(problem, model_params=posterior)
        theta = optimise(problem, theta, jax.random.fold_in(key, 20_000 + trial))
        episode = run_episode(task, jax.random.fold_in(key, 30_000 + trial), problem.policy, theta)
        data = add_episode(task, data, episode)
        on_trial(TrialRecord(task.num_random_trials + trial, True, episode, theta), data)
    return theta, data
