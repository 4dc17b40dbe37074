"""Episodic model-based policy search, one piece per function (PIPPS, section "Experiments").

A learning run is: random trials -> [fit the GP to all data, optimise the policy on the
model, run it once on the real system and add the data] x learned trials. The functions here
are the pieces; ``harness.scenario`` and the learning experiment put them together.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

import estimators
from estimators.base import Problem
from estimators.pilco import pilco_objective
from harness import keys
from harness.optim import LEARNING_RATE, MOMENTUM, pipps_sgd
from models import gp, sparse_gp
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


PROGRESS_EVERY = 100
"""Optimiser steps between progress lines on stderr."""


def report_progress(step: jax.Array, num_steps: int) -> None:
    """From inside a jitted optimiser loop: a line on stderr every ``PROGRESS_EVERY`` steps
    (once per step index: under ``vmap`` the callback runs once per seed; with the seeds in turn,
    ``learning_run(seeds_in_turn=True)``, each seed counts up in turn)."""

    def show(step):
        step = int(step)
        if (step + 1) % PROGRESS_EVERY == 0 and step != _last_reported[0]:
            print(f"    optimiser step {step + 1}/{num_steps}", file=sys.stderr, flush=True)
        _last_reported[0] = step

    jax.debug.callback(show, step)


_last_reported = [-1]


class PolicyOptimisation(NamedTuple):
    """One trial's policy optimisation: the final ``theta``, the objective estimate at each step
    ``values`` (num_steps,), and ``nonfinite_steps``, how many steps had an estimate (value,
    gradient or its variance) that was not finite. Such a step moves no parameter whose
    component is not finite (``harness.optim.normalised_gradient`` maps it to 0; usually the
    whole gradient is NaN), so a run can look normal while many of its steps were lost: the
    count says so."""

    theta: Any
    values: jax.Array
    nonfinite_steps: jax.Array


def is_finite_tree(*trees) -> jax.Array:
    """Whether every entry of every leaf is finite (a scalar bool)."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(trees)]))


@functools.partial(jax.jit, static_argnames=("estimator", "num_steps", "num_particles", "learning_rate", "momentum"))
def optimise_policy(problem: Problem, theta, key: jax.Array, *, estimator, num_steps: int, num_particles: int,
                    learning_rate: float = LEARNING_RATE, momentum: float = MOMENTUM) -> PolicyOptimisation:
    """``num_steps`` steps of the paper's optimiser on the model, one gradient estimate per step
    with a fresh key ``jax.random.split(key, num_steps)[step]``, or with ``key`` itself at every
    step for an estimator that ``fixes_noise`` (RP_FS, GR_FS: ``estimators.base.FixedNoise``).
    One compilation serves every trial with the same buffer capacity."""
    optimiser = pipps_sgd(learning_rate, momentum)
    fixes_noise = getattr(estimator, "fixes_noise", False)

    def one_step(carry, inputs):
        theta, opt_state = carry
        step, step_key = inputs
        estimate = estimator(problem, theta, key if fixes_noise else step_key, num_particles)
        updates, opt_state = optimiser.update(estimate.grad, opt_state, grad_var=estimate.grad_var)
        report_progress(step, num_steps)
        finite = is_finite_tree(estimate.value, estimate.grad, estimate.grad_var)
        return (optax.apply_updates(theta, updates), opt_state), (estimate.value, finite)

    keys = jax.random.split(key, num_steps)
    (theta, _), (values, finite) = jax.lax.scan(one_step, (theta, optimiser.init(theta)),
                                                (jnp.arange(num_steps), keys))
    return PolicyOptimisation(theta, values, jnp.sum(~finite))


class LbfgsCarry(NamedTuple):
    """The loop state of ``lbfgs_step``: the iterate, optax's L-BFGS state, and the best finite
    iterate so far with its value."""

    theta: Any
    state: Any
    best: Any
    best_value: jax.Array


def lbfgs_start(solver, theta) -> LbfgsCarry:
    return LbfgsCarry(theta, solver.init(theta), theta, jnp.asarray(jnp.inf, jax.tree.leaves(theta)[0].dtype))


def lbfgs_step(solver, objective: Callable) -> Callable:
    """``step(carry) -> (carry, (value, finite))``: one L-BFGS step with optax's zoom line search on
    ``objective`` (theta -> scalar), keeping the best finite iterate (a NaN step cannot lose
    progress); ``finite``: whether the value and gradient at the iterate were finite."""
    value_and_grad = optax.value_and_grad_from_state(objective)

    def step(carry: LbfgsCarry):
        value, grad = value_and_grad(carry.theta, state=carry.state)
        updates, state = solver.update(grad, carry.state, carry.theta, value=value, grad=grad, value_fn=objective)
        better = jnp.isfinite(value) & (value < carry.best_value)
        best = jax.tree.map(lambda b, t: jnp.where(better, t, b), carry.best, carry.theta)
        return (LbfgsCarry(optax.apply_updates(carry.theta, updates), state, best,
                           jnp.where(better, value, carry.best_value)), (value, is_finite_tree(value, grad)))

    return step


def lbfgs_result(carry: LbfgsCarry, last_value: jax.Array, values: jax.Array, nonfinite_steps) -> PolicyOptimisation:
    """The last iterate if its value ``last_value`` beats the best one's, else the best."""
    theta = jax.tree.map(lambda b, t: jnp.where(last_value < carry.best_value, t, b), carry.best, carry.theta)
    return PolicyOptimisation(theta, values, nonfinite_steps)


@functools.lru_cache(maxsize=None)
def pilco_optimiser(num_steps: int):
    """``optimise(problem, theta, key) -> PolicyOptimisation``: ``num_steps`` L-BFGS steps with a zoom
    line search on PILCO's deterministic J (``lbfgs_step``)."""
    solver = optax.lbfgs()

    @jax.jit
    def optimise(problem, theta, key):
        del key
        objective = lambda th: pilco_objective(problem, th)[0]  # noqa: E731
        step = lbfgs_step(solver, objective)

        def scan_step(carry, index):
            report_progress(index, num_steps)
            return step(carry)

        carry, (values, finite) = jax.lax.scan(scan_step, lbfgs_start(solver, theta), jnp.arange(num_steps))
        return lbfgs_result(carry, objective(carry.theta), values, jnp.sum(~finite))

    return optimise


LINESEARCH_STEPS = 20
"""optax's default bound on the zoom line search's evaluations per L-BFGS step."""


@functools.lru_cache(maxsize=None)
def fixed_noise_lbfgs_optimiser(estimator_name: str, max_evaluations: int, num_particles: int):
    """``optimise(problem, theta, key) -> PolicyOptimisation``: the paper's "Deterministic optimizer"
    for a fixed-noise estimator (RP_FS, GR_FS): L-BFGS with a zoom line search (``lbfgs_step``) on
    its objective under ``key``, J(theta) = mean return of ``num_particles`` particles (deterministic;
    its autodiff gradient is the estimator's), for at most ``max_evaluations`` evaluations of J and
    its gradient (the paper's "600 policy evaluations between each trial"): a step starts only while
    its line search, up to ``LINESEARCH_STEPS`` evaluations, fits in what is left. ``values`` holds
    each step's J (NaN after the last step)."""
    estimator = estimators.make(estimator_name)
    if not getattr(estimator, "fixes_noise", False):
        raise ValueError(f"the deterministic optimiser needs a fixed-noise estimator (rp_fs, gr_fs); got "
                         f"{estimator_name!r}")
    if max_evaluations < 1 + LINESEARCH_STEPS:
        raise ValueError(f"the deterministic optimiser needs at least {1 + LINESEARCH_STEPS} evaluations per "
                         f"trial (one L-BFGS step); got {max_evaluations}")
    solver = optax.lbfgs(linesearch=optax.scale_by_zoom_linesearch(LINESEARCH_STEPS, initial_guess_strategy="one"))

    @jax.jit
    def optimise(problem, theta, key):
        objective = lambda th: estimator(problem, th, key, num_particles).value  # noqa: E731
        step = lbfgs_step(solver, objective)

        def go_on(loop):
            _, _, _, evaluations, _ = loop
            return evaluations + LINESEARCH_STEPS <= max_evaluations

        def loop_step(loop):
            carry, steps, values, evaluations, finite_steps = loop
            report_progress(steps, max_evaluations)  # "step N/M": N steps of at most M
            carry, (value, finite) = step(carry)
            spent = optax.tree.get(carry.state, "num_linesearch_steps")
            return carry, steps + 1, values.at[steps].set(value), evaluations + spent, finite_steps + finite

        nan_values = jnp.full((max_evaluations,), jnp.nan, jax.tree.leaves(theta)[0].dtype)
        loop = (lbfgs_start(solver, theta), 0, nan_values, 1, 0)  # the first step's J at theta: 1 evaluation
        carry, steps, values, _, finite_steps = jax.lax.while_loop(go_on, loop_step, loop)
        # the line search's value at the last iterate: no evaluation past the budget
        return lbfgs_result(carry, optax.tree.get(carry.state, "value"), values, steps - finite_steps)

    return optimise


def policy_optimiser(estimator_name: str, num_steps: int, num_particles: int, quasi_newton: bool = False):
    """``optimise(problem, theta, key) -> PolicyOptimisation``: PILCO's L-BFGS for "pilco"; with
    ``quasi_newton``, L-BFGS on a fixed-noise estimator's objective for ``num_steps`` evaluations
    (``fixed_noise_lbfgs_optimiser``); else ``num_steps`` steps of the paper's optimiser with that
    estimator and ``num_particles``."""
    if estimator_name == "pilco":
        return pilco_optimiser(num_steps)
    if quasi_newton:
        return fixed_noise_lbfgs_optimiser(estimator_name, num_steps, num_particles)
    estimator = estimators.make(estimator_name)

    def optimise(problem, theta, key):
        return optimise_policy(problem, theta, key, estimator=estimator, num_steps=num_steps,
                               num_particles=num_particles)

    return optimise


def cast_floating(tree, dtype):
    """Every floating leaf of ``tree`` cast to ``dtype`` (integer and boolean leaves as they are)."""
    return jax.tree.map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


def in_precision(optimise: Callable, dtype) -> Callable:
    """``optimise`` run on the model's parameters and theta cast to ``dtype``, its theta cast
    back: float32 particle rollouts on a GP trained and factorised in float64."""

    def run(problem: Problem, theta, key: jax.Array) -> PolicyOptimisation:
        problem = dataclasses.replace(problem, model_params=cast_floating(problem.model_params, dtype))
        result = optimise(problem, cast_floating(theta, dtype), key)
        return result._replace(theta=jax.tree.map(lambda new, old: new.astype(old.dtype), result.theta, theta))

    return run


@functools.partial(jax.jit, static_argnames=("task", "policy", "num_runs"))
def evaluate_policy(task: Task, policy, theta, key: jax.Array, num_runs: int) -> jax.Array:
    """Returns (num_runs,) of the policy on the real system (evaluation only); jitted once
    per task, policy and number of runs."""
    episodes = jax.vmap(lambda k: run_episode(task, k, policy, theta))(jax.random.split(key, num_runs))
    return episodes.total_cost


class RunState(NamedTuple):
    """A learning run between two trials: ``trials_done`` (random and learned), theta after the
    last learned trial (None before the first) and the data gathered so far; enough to resume
    the run exactly, since every key is derived from the run's key and the trial index."""

    trials_done: int
    theta: Any
    data: gp.GPData


class TrialRecord(NamedTuple):
    """One real-system trial of a learning run: ``trial`` (0-based over all trials), whether it
    was ``learned`` (else random), the episode, theta after it and the optimisation's count of
    non-finite steps (``PolicyOptimisation.nonfinite_steps``; both None for random trials)."""

    trial: int
    learned: bool
    episode: Episode
    theta: Any
    nonfinite_steps: Any = None


def learning_run(task: Task, problem: Problem, key: jax.Array, num_learned: int,
                 optimise: Callable[[Problem, Any, jax.Array], Any], gp_steps: int,
                 on_trial: Callable[[TrialRecord, gp.GPData], None] = lambda record, data: None,
                 batched: bool = False, trim_model: bool = False, fit_rows_held: bool = False,
                 seeds_in_turn: bool = False, resume: RunState | None = None,
                 num_inducing: int = 0, optimisation_key_per_run: bool = False):
    """The paper's episodic loop: the task's random trials, then ``num_learned`` times: fit the
    GP to all data (``gp_steps`` L-BFGS steps), ``theta = optimise(problem with the GP, theta,
    key).theta``, one real trial, add its data. Keys: the run's named streams (``harness.keys.RUN``:
    random trial r, theta0, trial t's optimisation and its real trial). ``on_trial`` sees each trial as it ends. Returns
    (theta, data).

    ``batched``: ``key`` is (B,) seeds and every piece (GP fit, optimisation, trial) is vmapped
    over them; records, theta and data then carry a leading axis B. A seed's run is the same
    computation either way, but batching may change round-off, which the closed loop's chaos
    can amplify: compare statistics, not digits, across batch sizes.

    ``trim_model``: optimise on the posterior cut to the rows held, rounded up to whole
    episodes (``gp.truncate``): prediction costs O(rows^2) instead of O(capacity^2), for one
    compilation of the optimiser per distinct size; worth it when the optimisation is long.

    ``fit_rows_held``: fit the GP on the buffer cut to the rows held (``gp.trim_data``): the same
    training set and objective as the whole buffer, whose padding rows are inert, at
    O(rows^3) instead of O(capacity^3) per step of the fit. It changes the fit's round-off,
    which the closed loop can amplify.

    ``seeds_in_turn`` (with ``batched``): optimise the seeds' policies one after another in one
    program (``lax.map``) instead of vmapped together: each seed's optimisation is then the
    unbatched program, which runs 6-15 % faster per seed than the vmapped one on the CPU (the
    GP's per-seed matrices batch the particle products badly). The GP fits and trials stay vmapped.

    ``num_inducing``: once the data hold more rows, fit PILCO's FITC sparse GP with that many
    inducing inputs instead of the full GP (``models.sparse_gp.fitter``; 0: always the full GP).

    ``optimisation_key_per_run``: every trial's optimisation gets the same key
    the "optimisation" stream at index 0: a fixed-noise estimator (RP_FS, GR_FS) then optimises on the same
    particles in every trial of the run, the other reading of the paper's "fixed seed"
    (``harness.methods.Method.noise_fixed_per_run``); the default fixes them per trial.

    ``resume``: continue from that state (the data and theta ``on_trial`` saw after trial
    ``trials_done - 1``) instead of starting afresh; the trials after it are the same
    computation as in an uninterrupted run.
    """
    over_seeds = jax.vmap if batched else (lambda f: f)
    def run_key(name: str, index: int = 0):  # the run's (or each seed's) key of a named stream
        return (jax.vmap(keys.stream, in_axes=(0, None, None)) if batched else keys.stream)(key, name, index)

    num_seeds = key.shape if batched else ()
    if resume is None:
        data = problem.model.empty_data(data_capacity(task, task.num_random_trials + num_learned))
        resume = RunState(0, None, jax.tree.map(lambda x: jnp.broadcast_to(x, num_seeds + x.shape), data))
    data, theta = jax.tree.map(jnp.asarray, (resume.data, resume.theta))  # it may hold numpy arrays
    add = over_seeds(functools.partial(add_episode, task))
    for trial in range(resume.trials_done, task.num_random_trials):
        episode = over_seeds(functools.partial(run_episode, task))(run_key("random_trial", trial))
        data = add(data, episode)
        on_trial(TrialRecord(trial, False, episode, None), data)
    if theta is None:
        theta = over_seeds(problem.policy.init)(run_key("theta0"))
    policy_episode = over_seeds(lambda k, th: run_episode(task, k, problem.policy, th))
    for trial in range(max(resume.trials_done - task.num_random_trials, 0), num_learned):
        rows_held = int(np.max(np.asarray(data.num_valid)))
        fit_data = gp.trim_data(data, rows_held) if fit_rows_held else data
        posterior = gp.check_posterior(over_seeds(sparse_gp.fitter(num_inducing, rows_held, gp_steps))(fit_data))
        if trim_model and not sparse_gp.uses_fitc(num_inducing, rows_held):
            whole_episodes = -(-rows_held // task.horizon) * task.horizon
            posterior = gp.truncate(posterior, whole_episodes)
        problem = dataclasses.replace(problem, model_params=posterior)
        optimisation_key = run_key("optimisation", 0 if optimisation_key_per_run else trial)
        if batched and seeds_in_turn:
            result = jax.lax.map(lambda args: optimise(*args), (problem, theta, optimisation_key))
        else:
            result = over_seeds(optimise)(problem, theta, optimisation_key)
        theta = result.theta
        episode = policy_episode(run_key("trial", trial), theta)
        data = add(data, episode)
        on_trial(TrialRecord(task.num_random_trials + trial, True, episode, theta, result.nonfinite_steps), data)
    return theta, data
