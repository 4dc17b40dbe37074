"""Replay one learned trial of RP's repeat 0 (cart-pole, angle cost, k = 1, paper preset) from a
committed checkpoint, to see where its non-finite gradient estimates come from (README, the
learning table's progress). Not part of the harness: the provenance of numbers quoted there.

    git show 7984992:reports/learn_checkpoints/<RP repeats 0-4 checkpoint> > state.pkl  # after trial 12
    python diagnostics/rp_nonfinite_replay.py state.pkl fit posterior.pkl      # batched, as the run
    python diagnostics/rp_nonfinite_replay.py state.pkl replay posterior.pkl f32|f64 [batched]

``fit`` refits the GP of all five repeats as ``harness.episodic.learning_run`` does. ``replay``
runs the trial's 600 optimiser steps with the run's key: ``batched`` all five repeats through
``harness.episodic.policy_optimiser`` (the run's program), else repeat 0 alone, printing per step
which of value, gradient and ``grad_var`` were not finite and the largest per-particle gradient.
"""

import dataclasses
import pickle
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

import estimators
from estimators.base import task_problem
from harness import learn
from harness.episodic import cast_floating, in_precision, is_finite_tree, policy_optimiser
from harness.optim import pipps_sgd
from models import gp, sparse_gp

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_cpu_enable_async_dispatch", False)
ARGS = learn.Args(task="cartpole", cost="angle", methods="rp", preset="paper", rollout_float32=True, gp_inducing=300)
REPEATS = 5


def replay_one(problem, theta, key, settings):
    """Repeat 0's trial step by step: per step (value, grad, grad_var finite; max |particle grad|).
    ``harness.episodic.optimise_policy``'s loop, keeping what it does not: which part was not finite."""
    estimator, optimiser = estimators.make("rp"), pipps_sgd()

    def step(carry, step_key):
        theta, state = carry
        estimate = estimator(problem, theta, step_key, settings["particles"])
        updates, state = optimiser.update(estimate.grad, state, grad_var=estimate.grad_var)
        largest = jnp.max(jnp.stack([jnp.max(jnp.abs(g)) for g in jax.tree.leaves(estimate.aux["particle_grads"])]))
        flags = tuple(is_finite_tree(x) for x in (estimate.value, estimate.grad, estimate.grad_var))
        return (optax.apply_updates(theta, updates), state), flags + (largest,)

    keys = jax.random.split(key, settings["optimiser_steps"])
    return jax.jit(lambda th: jax.lax.scan(step, (th, optimiser.init(th)), keys)[1])(theta)


def main(state_file, command, posterior_file, precision="f32", how="single"):
    task, settings = ARGS.make_task(), ARGS.settings
    with open(state_file, "rb") as f:
        state = pickle.load(f)["state"]
    data = jax.tree.map(jnp.asarray, state.data)
    trial = state.trials_done - task.num_random_trials  # the learned trial replayed
    rows_held = int(np.max(np.asarray(data.num_valid)))
    start = time.perf_counter()
    if command == "fit":
        posterior = jax.vmap(sparse_gp.fitter(ARGS.gp_inducing, rows_held, settings["gp_steps"]))(data)
        with open(posterior_file, "wb") as f:
            pickle.dump(jax.tree.map(np.asarray, gp.check_posterior(posterior)), f)
        print(f"fitted {rows_held} rows in {time.perf_counter() - start:.0f} s")
        return
    dtype = {"f32": jnp.float32, "f64": jnp.float64}[precision]
    with open(posterior_file, "rb") as f:
        posterior = jax.tree.map(jnp.asarray, pickle.load(f))
    problem = dataclasses.replace(task_problem(task, gp.GPModel(task)), model_params=posterior)
    keys = jnp.stack([jax.random.fold_in(jax.random.key(r), 20_000 + trial) for r in range(REPEATS)])
    if how == "batched":
        optimise = in_precision(policy_optimiser("rp", settings["optimiser_steps"], settings["particles"]), dtype)
        counts = np.asarray(jax.vmap(optimise)(problem, state.theta, keys).nonfinite_steps)
        print(f"{precision} batched: non-finite steps per repeat {counts.tolist()}")
    else:
        first = lambda tree: jax.tree.map(lambda x: jnp.asarray(x)[0], tree)  # noqa: E731
        problem = dataclasses.replace(problem, model_params=cast_floating(first(posterior), dtype))
        value_ok, grad_ok, var_ok, largest = map(np.asarray, replay_one(
            problem, cast_floating(first(state.theta), dtype), keys[0], settings))
        bad = ~(value_ok & grad_ok & var_ok)
        print(f"{precision} repeat 0: {bad.sum()} non-finite steps (value {(~value_ok).sum()}, grad "
              f"{(~grad_ok).sum()}, grad_var {(~var_ok).sum()})")
        print("log10 max |particle grad|: at those steps", np.log10(largest[bad]).round(1).tolist(),
              "; quantiles 50/90/99/100 over all steps", np.log10(np.quantile(largest, [.5, .9, .99, 1])).round(1))
    print(f"{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main(*sys.argv[1:])
