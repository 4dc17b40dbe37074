"""Projected time of one paper-setting learning experiment per method, from measured pieces
(the learning section of ``python -m harness.bench``).

A paper-setting cart-pole experiment (``harness.learn --preset paper``: 15 learned trials, 600
optimiser steps with 300 particles, or 150 L-BFGS steps for PILCO) takes hours on two cores,
too long to time whole for every method. This times its pieces on this machine, each after
compilation, and adds them up:

- an optimiser step at the data sizes of learned trials 1, 8 and 15 (30, 240 and 450 rows;
  ``learn`` optimises on the posterior trimmed to the rows held), interpolated by the
  quadratic through those three points (prediction is O(rows^2)) and summed over the 15
  trials' sizes and steps;
- the compilation of the optimiser, once per trial (the trimmed size changes every trial);
- a GP fit (100 L-BFGS steps on the rows held, as ``learn`` fits: ``gp.trim_data``) timed at
  the same three sizes and interpolated the same way, and the 30 evaluation runs, once per trial.

Methods listed in ``float32_methods`` are timed again in float32 (the GP fitted in float64,
its posterior cast). Methods listed in ``fitc_methods`` are timed again with PILCO's FITC sparse
GP (``learn --gp-inducing 300``): trials whose data exceed 300 rows optimise on 300 inducing
inputs, so their step costs what a 300-row step costs (the dense M x M variance factor costs as
much as the full GP's triangular one); the quadratic then runs through the steps timed at 30
and 240 rows and at the FITC posterior of trial 15, placed at 300 rows, and is evaluated at
min(30 t, 300). Their fit is FITC's (the full GP's hyperparameters, then 100 L-BFGS steps on the
inducing inputs), timed at trial 15's 450 rows, in those trials (an upper bound for trials 11-14).
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

import tasks
from estimators.base import task_problem
from harness import keys
from harness.episodic import add_episode, evaluate_policy, in_precision, policy_optimiser
from harness.cli import parse, str_list
from harness.learn import PRESETS, Args
from harness.methods import METHODS, runnable
from harness.records import read_csv
from models import gp, sparse_gp
from tasks.rollout import run_episode

PAPER_SETTINGS = dict(PRESETS["paper"], learned_trials=15)
"""The cart-pole's paper preset (15 learned trials: its `pipps` task preset)."""
TIMED_TRIALS = (1, 8, 15)
"""Learned trials whose optimiser steps are timed (the data then hold 30 t rows)."""
NUM_INDUCING = 300
"""pilco-matlab's cart-pole (settings_cp.m): FITC with 300 inducing inputs past 300 points."""


def timed(fn, *args) -> float:
    """Seconds of one call after a warm-up call (which compiles)."""
    jax.block_until_ready(fn(*args))
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def buffers(task, key, num_trials: int):
    """GP buffers after 1..num_trials episodes (random controls: timing does not depend on
    the policy), each with the capacity of the paper's 16 trials."""
    data = gp.GPModel(task).empty_data(16 * task.horizon)
    filled = []
    for trial in range(num_trials):
        data = add_episode(task, data, run_episode(task, keys.stream(key, "random_trial", trial)))
        filled.append(data)
    return filled


def optimiser_seconds(problem, posterior, theta, method: str, settings: dict, timed_steps: int, dtype):
    """(seconds per optimiser step, compile seconds) at this posterior, in ``dtype``."""
    chosen = METHODS[method]
    problem = dataclasses.replace(problem, model_params=posterior, **chosen.overrides)
    optimise = jax.jit(in_precision(policy_optimiser(chosen.estimator, timed_steps, settings["particles"]), dtype))
    key = jax.random.key(0)
    start = time.perf_counter()
    compiled = optimise.lower(problem, theta, key).compile()
    compile_s = time.perf_counter() - start
    return timed(compiled, problem, theta, key) / timed_steps, compile_s


def project(step_s: dict[int, float], trial_rows: np.ndarray, steps: int) -> float:
    """``steps`` x the quadratic through the timed (rows, seconds per step) points, summed over
    the trials' (effective) rows ``trial_rows``."""
    coefficients = np.polyfit(np.array(list(step_s)), np.array(list(step_s.values())), 2)
    return float(steps * np.polyval(coefficients, trial_rows).clip(0).sum())


def measure(methods: list[str], float32_methods: list[str], pseudo_input_methods: list[str] = (),
            fitc_methods: list[str] = (), fitc_float32_methods: list[str] = (), timed_steps: int = 3,
            seed: int = 0) -> pd.DataFrame:
    """A row per (method, dtype, RBF form, GP): seconds per optimiser step at the timed trials,
    compile, GP fit and evaluation seconds, and the projected minutes (``optimise_min``,
    ``total_min``). ``methods`` run in float64 with the task's default (direct) RBF policy and
    the full GP, ``float32_methods`` in float32, ``pseudo_input_methods`` in float64 with PILCO's
    pseudo-input RBF form (the default before issue 18), ``fitc_methods`` in float64 with FITC
    past ``NUM_INDUCING`` rows (module docstring), ``fitc_float32_methods`` with both."""
    everything = [*methods, *float32_methods, *pseudo_input_methods, *fitc_methods, *fitc_float32_methods]
    unknown = [m for m in everything if m not in runnable()]
    if unknown:
        raise ValueError(f"unknown methods {unknown}; valid methods: {runnable()}")
    settings = PAPER_SETTINGS
    task = tasks.make("cartpole")
    key = jax.random.key(seed)
    print("bench: fitting GPs at the timed sizes of a learning run ...", file=sys.stderr, flush=True)
    filled = buffers(task, key, max(TIMED_TRIALS))
    fit = jax.jit(lambda d: gp.posterior(gp.train(d, num_steps=settings["gp_steps"]).log_hyp, d))
    held = {t: gp.trim_data(filled[t - 1], t * task.horizon) for t in TIMED_TRIALS}  # as learn fits
    fit_s = {t * task.horizon: timed(fit, held[t]) for t in TIMED_TRIALS}
    posteriors = {t: gp.check_posterior(fit(held[t])) for t in TIMED_TRIALS}
    last = max(TIMED_TRIALS)
    fit_fitc = jax.jit(sparse_gp.fitter(NUM_INDUCING, last * task.horizon, settings["gp_steps"]))
    any_fitc = bool(fitc_methods) or bool(fitc_float32_methods)
    fitc_fit_s = timed(fit_fitc, held[last]) if any_fitc else float("nan")
    posteriors_fitc = posteriors | ({last: gp.check_posterior(fit_fitc(held[last]))} if any_fitc else {})
    trials = np.arange(1, settings["learned_trials"] + 1)
    problems = {form: task_problem(tasks.make("cartpole", rbf_parameterisation=form), gp.GPModel(task))
                for form in ("direct", "pseudo_inputs")}
    thetas = {form: problem.policy.init(keys.stream(key, "theta0")) for form, problem in problems.items()}
    eval_s = timed(lambda th, k: evaluate_policy(task, problems["direct"].policy, th, k, settings["eval_runs"]),
                   thetas["direct"], keys.stream(key, "evaluation"))
    runs = ([(m, "float64", jnp.float64, "direct", 0) for m in methods]
            + [(m, "float32", jnp.float32, "direct", 0) for m in float32_methods]
            + [(m, "float64", jnp.float64, "pseudo_inputs", 0) for m in pseudo_input_methods]
            + [(m, "float64", jnp.float64, "direct", NUM_INDUCING) for m in fitc_methods]
            + [(m, "float32", jnp.float32, "direct", NUM_INDUCING) for m in fitc_float32_methods])
    rows = []
    for index, (method, dtype_name, dtype, form, inducing) in enumerate(runs):
        steps = METHODS[method].steps(settings)
        chosen = posteriors_fitc if inducing else posteriors
        step_s, compile_s = {}, []
        for t in TIMED_TRIALS:
            step_s[t], c = optimiser_seconds(problems[form], chosen[t], thetas[form], method, settings,
                                             timed_steps, dtype)
            compile_s.append(c)
        rows_cap = inducing or np.inf
        effective_rows = {min(task.horizon * t, rows_cap): s for t, s in step_s.items()}
        optimise_total = project(effective_rows, np.minimum(task.horizon * trials, rows_cap), steps)
        fitc_trials = task.horizon * trials > rows_cap
        fits = project(fit_s, task.horizon * trials[~fitc_trials], 1) + fitc_trials.sum() * fitc_fit_s
        total = optimise_total + fits + settings["learned_trials"] * (np.mean(compile_s) + eval_s)
        gp_name = f"fitc{inducing}" if inducing else "full"
        rows.append({"method": method, "dtype": dtype_name, "rbf": form, "gp": gp_name, "steps_per_trial": steps,
                     **{f"step_s_trial{t}": s for t, s in step_s.items()},
                     "compile_s": float(np.mean(compile_s)), "gp_fit_min": fits / 60,
                     "eval_s": eval_s, "optimise_min": optimise_total / 60, "total_min": total / 60})
        print(f"[{index + 1}/{len(runs)}] learning {method} {dtype_name} {form} {gp_name}: {total / 60:.1f} min "
              f"projected (step {', '.join(f'{s:.3f}' for s in step_s.values())} s)", file=sys.stderr, flush=True)
    return pd.DataFrame(rows)


WHOLE_RUN = "bench_whole"
"""Folder (under the bench's --out) of the paper-setting TP experiment timed whole."""
WHOLE_RUN_ARGV = ["--preset", "paper", "--methods", "tp", "--repeats", "1", "--rollout-float32",
                  "--gp-inducing", "300"]
"""Its ``harness.learn`` flags: the sweep's TP setting (float32 rollouts, FITC past 300 points), one repeat."""


def whole_run(folder: str) -> float | None:
    """Minutes of the experiment ``WHOLE_RUN_ARGV`` timed whole with ``--out folder`` (its CSV's rows of that
    method and settings; ``seconds`` counts from the run's start), or None if there is none or it has not
    finished."""
    args = parse(Args, WHOLE_RUN_ARGV + ["--out", folder])
    if not os.path.exists(args.stem + ".csv"):
        return None
    [method] = str_list(args.methods)
    rows = read_csv(args.stem + ".csv")
    rows = rows[(rows.method == method) & (rows.settings == args.settings_name(method))]
    finished = rows.learned.sum() == args.settings["learned_trials"]
    return float(rows.seconds.max()) / 60 if finished else None


def report_lines(table: pd.DataFrame) -> list[str]:
    """The markdown section of ``bench.md``."""
    settings = PAPER_SETTINGS
    step_columns = [c for c in table.columns if c.startswith("step_s")]
    shown = table[["method", "dtype", "rbf", "gp", "steps_per_trial"] + step_columns
                  + ["compile_s", "gp_fit_min", "eval_s", "optimise_min", "total_min"]]
    return [
        "## One paper-setting learning experiment per method (projected)",
        "",
        f"- Setting: cart-pole, `harness.learn --preset paper`: 1 random then {settings['learned_trials']} learned "
        f"trials, {settings['optimiser_steps']} optimiser steps with {settings['particles']} particles per trial "
        f"(PILCO: {settings['pilco_steps']} L-BFGS steps), GP fit {settings['gp_steps']} L-BFGS steps on the rows "
        f"held, {settings['eval_runs']} evaluation runs per trial.",
        "- Projected from timed pieces (the sweep's TP setting can be timed whole: the targets above): "
        "seconds per optimiser step "
        f"measured at learned trials {', '.join(map(str, TIMED_TRIALS))} (30 t rows), interpolated "
        "quadratically in the rows and summed over the trials; the GP fits (`gp_fit_min`, all trials) likewise; "
        "plus per trial one compilation and the evaluation runs, each measured once. A PILCO step's cost varies with its line search. Rows "
        f"`gp fitc{NUM_INDUCING}`: PILCO's FITC sparse GP once the data exceed {NUM_INDUCING} rows (trials 11-15; "
        f"their steps cost a {NUM_INDUCING}-row step, their fit is FITC's at 450 rows: hyperparameters, then the "
        "inducing inputs); the others use the full GP throughout.",
        "- Earlier target (issue 18): a TP experiment in at most 20 minutes on 2 cores. Rows `rbf pseudo_inputs` "
        "time PILCO's pseudo-input RBF policy form, the default before it. The targets of issue 47 are above.",
        "",
        shown.to_markdown(index=False, floatfmt=".3g"),
        "",
    ]
