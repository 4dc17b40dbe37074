"""Episodic learning with each method, and its success rates (PIPPS, section "Experiments").

    python -m harness.learn      # a demonstration in minutes: TP against PILCO, 2 repeats, the demo preset
    python -m harness.learn --task cartpole --cost angle --noise-k 1 \
        --methods pilco,rp,rp_fs,gr,gr_fs,lr,tp,tp-sigma_f,tp+sigma_n --repeats R --preset demo|quick|quick_p50|paper \
        [--task-options angle_cost_scale=1,rbf_parameterisation=pseudo_inputs] [--gp-inducing 300]

Each experiment (method, repeat) is one learning run (``harness.episodic.learning_run``): the
task's random trial(s), then per learned trial: fit the GP to all data, optimise the policy on
it, run one real trial and add its data. ``--gp-inducing M`` (0, the default: the full GP) fits
PILCO's FITC sparse GP with M inducing inputs once the data exceed M rows
(``models.sparse_gp``; pilco-matlab's cart-pole uses 300); the settings key then ends in
``-fitcM``. Particle methods take ``optimiser_steps`` steps of
the paper's optimiser with ``particles`` particles; PILCO takes ``pilco_steps`` L-BFGS steps on
its deterministic objective. After every trial the policy is scored by ``eval_runs`` runs on
the real system (evaluation only; their data are not used). Repeat r uses seed ``seed + r``.

A method's repeats run ``batch`` at a time, vmapped over their seeds (one compiled program
per batch; the optimiser works on the GP trimmed to the rows held). Every trial of a batch's
experiments is appended to ``learn_{task}_{cost}_k{k}[_{preset}].csv`` when the batch ends; a rerun
skips finished experiments. Between trials the batch's state (data, theta, rows so far) is
saved under ``{out}/.cache/learn/`` (or ``--checkpoints DIR``), so a rerun of an interrupted
batch continues after its last finished trial (with the same repeats, settings and precision). Progress (batch, trial,
optimiser step) goes to stderr. Each learned trial's row counts the optimiser steps whose
estimate was not finite (``nonfinite_steps``: such a step moves no parameter whose component
is not finite); the report flags every trial where it is above zero. The report pools every
method of the CSV run at the same settings, not only this run's (``harness.learn_report``
regenerates every table and figure from the CSV alone).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
import sys
import time

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

import tasks
from estimators.base import task_problem
from estimators.pilco import check_task
from harness import learn_report
from harness.cli import check_sizes, parse, run_command, str_list
from harness.episodic import RunState, evaluate_policy, in_precision, learning_run, policy_optimiser
from harness.keys import stream
from harness.methods import METHODS, runnable
from harness.records import ResultTable, code_version, load_legacy_pickle, load_state, save_state
from harness.scenario import (Scenario, policy_structure, provenance, save_scenario, theta_arrays,
                              theta_from_arrays)
from models import gp, sparse_gp

JAX_VERSIONS = f"jax {jax.__version__}, jaxlib {jaxlib.__version__}"
"""Saved with every checkpoint: a resume under other versions says so (round-off, and bugs such
as jaxlib 0.10.2's, differ between them)."""

PRESETS = {
    # learned trials (0: the task preset's), optimiser steps, particles, evaluation runs,
    # PILCO's L-BFGS steps, GP training steps
    # Every preset keeps the paper's 600 optimiser steps per trial (its step size assumes them):
    # 150 steps were tried first and move each parameter by at most 150 * 5e-4 / (1 - 0.9) =
    # 0.75 per trial; TP's policies stayed where they began.
    # quick: the paper's regime (300 particles, 600 steps, 150 L-BFGS steps) over fewer learned
    # trials, so that its rates say something about the paper's. quick_p50: the earlier quick
    # preset (50 particles, a regime the paper never ran), kept to extend and read its rows.
    "quick": dict(learned_trials=8, optimiser_steps=600, particles=300, eval_runs=30, pilco_steps=150, gp_steps=100),
    "quick_p50": dict(learned_trials=5, optimiser_steps=600, particles=50, eval_runs=10, pilco_steps=40, gp_steps=60),
    "paper": dict(learned_trials=0, optimiser_steps=600, particles=300, eval_runs=30, pilco_steps=150, gp_steps=100),
    # demo: the command's default, a demonstration in minutes on 2 cores (TP against PILCO, 2 repeats), not a
    # regime to read rates from
    "demo": dict(learned_trials=3, optimiser_steps=600, particles=50, eval_runs=5, pilco_steps=40, gp_steps=50),
}
PARTICLE_ONLY = ("optimiser_steps", "particles")
KEY_COLUMNS = ["task", "cost", "noise_k", "task_options", "method", "repeat", "seed", "settings"]
"""A row's key: ``task_options`` is every option of the task it ran (``tasks.describe``), so a
change of convention (e.g. the angle cost's scale) never reuses another's rows."""


@dataclasses.dataclass(frozen=True)
class Args:
    """Episodic learning: success rates and learning curves per method."""

    task: str = "cartpole"
    """Task name (a tasks.REGISTRY name: cartpole, unicycle)."""
    cost: str = ""
    """Cost type (cartpole: angle or tip; empty: the task preset's)."""
    noise_k: float = 1.0
    """Observation-noise multiplier k of the paper's tables."""
    task_options: str = ""
    """Task options over its preset's, NAME=VALUE,... (e.g. angle_cost_scale=1)."""
    methods: str = "tp,pilco"
    """Comma-separated methods (harness.methods.METHODS; the paper's columns: harness.methods.DEFAULT_METHODS)."""
    repeats: int = 2
    """Learning runs per method (repeat r uses seed + r)."""
    first_repeat: int = 0
    """Run repeats first_repeat..repeats-1 only (harness.sweep gives each unit its batch)."""
    preset: str = "demo"
    """Settings preset: demo (minutes), quick, quick_p50 or paper (learn.PRESETS)."""
    seed: int = 0
    """Seed of repeat 0."""
    out: str = "reports"
    """Folder for the CSV, report and figure (and .cache/learn/ checkpoints)."""
    checkpoints: str = ""
    """Folder for the between-trial checkpoints (empty: {out}/.cache/learn). A folder under
    version control carries an unfinished batch to another machine."""
    x64: bool = True
    """Compute in float64 (--no-x64: float32)."""
    rollout_float32: bool = False
    """Particle methods roll out in float32 on a float64-fitted GP."""
    learned_trials: int = -1
    """Learned trials per run (-1: the preset's; 0: the task preset's)."""
    optimiser_steps: int = -1
    """Steps of the paper's optimiser per trial (-1: the preset's)."""
    particles: int = -1
    """Particles per gradient estimate (-1: the preset's)."""
    eval_runs: int = -1
    """Real-system evaluation runs after each trial (-1: the preset's)."""
    pilco_steps: int = -1
    """PILCO's L-BFGS steps per trial (-1: the preset's)."""
    gp_steps: int = -1
    """L-BFGS steps of each GP fit (-1: the preset's)."""
    gp_inducing: int = 0
    """FITC sparse GP with this many inducing inputs once the data exceed it (0: full GP)."""
    batch: int = 10
    """Repeats of a method vmapped together in one program."""
    keep_final: bool = False
    """Keep each run's final state as a scenario file (plain arrays and JSON, ``final_state_path``): the
    data, the policy after the last trial and the GP the loop fits to all the data; gradient experiments
    can start from it (issue: the curse of chaos at a policy that works)."""

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; valid presets: {sorted(PRESETS)}")
        unknown = [m for m in str_list(self.methods) if m not in runnable()]
        if unknown:
            raise ValueError(f"unknown methods {unknown}; valid methods: {runnable()} (a new estimator becomes "
                             "a method with an entry in harness.methods.METHODS)")
        task = self.make_task()  # fails with the valid tasks and options
        if any(METHODS[m].estimator == "pilco" for m in str_list(self.methods)):
            check_task(task)
        if self.repeats < 1 or self.batch < 1:
            raise ValueError("repeats and batch must be >= 1")
        check_sizes(**{name: (getattr(self, name), least) for name, least in
                       [("particles", 2), ("optimiser_steps", 1), ("eval_runs", 1), ("pilco_steps", 1), ("gp_steps", 1)]
                       if getattr(self, name) != -1})
        if not 0 <= self.first_repeat < self.repeats:
            raise ValueError(f"first_repeat must be in 0..repeats-1, got {self.first_repeat}")
        if self.gp_inducing < 0:
            raise ValueError(f"gp_inducing must be >= 0 (0: the full GP; PILCO's cart-pole: 300); got "
                             f"{self.gp_inducing}")

    def make_task(self):
        """The task with cost, noise_k and ``task_options`` ("NAME=VALUE,...", e.g.
        "angle_cost_scale=1,rbf_parameterisation=pseudo_inputs") over its preset's."""
        options = {"noise_k": self.noise_k} | ({"cost": self.cost} if self.cost else {})
        return tasks.make(self.task, **options | tasks.parse_options(self.task, self.task_options))

    @property
    def settings(self) -> dict:
        """The preset's numbers with any given overrides (-1: the preset's; learned_trials 0:
        the task preset's number of learned trials)."""
        chosen = {name: getattr(self, name) if getattr(self, name) >= 0 else value
                  for name, value in PRESETS[self.preset].items()}
        if chosen["learned_trials"] == 0:
            chosen["learned_trials"] = self.make_task().num_learned_trials
        return chosen

    def settings_name(self, method: str) -> str:
        """The settings that ``method`` uses, as a CSV key: PILCO ignores the particle
        optimiser's steps and particles; the particle methods ignore PILCO's steps."""
        unused = PARTICLE_ONLY if METHODS[method].optimiser == "lbfgs" else ("pilco_steps",)
        name = "-".join(f"{key}{value}" for key, value in self.settings.items() if key not in unused)
        return (name + (f"-fitc{self.gp_inducing}" if self.gp_inducing else "")
                + ("-rollout_f32" if self.float32_rollouts(method) else ""))

    def float32_rollouts(self, method: str) -> bool:
        """Whether ``method`` optimises on float32 particle rollouts (``rollout_float32``: the
        particle methods under the paper's SGD, with the GP trained and factorised in float64; the
        L-BFGS methods, PILCO and the fixed-noise ones, stay float64)."""
        return self.rollout_float32 and METHODS[method].optimiser == "pipps_sgd"

    @property
    def stem(self) -> str:
        """``{out}/learn_{task}_{cost}_k{k}``, with ``_{preset}`` unless the preset is "paper"."""
        task = self.make_task()
        cost = getattr(task, "cost_type", "default")
        preset = "" if self.preset == "paper" else f"_{self.preset}"
        return os.path.join(self.out, f"learn_{self.task}_{cost}_k{self.noise_k:g}{preset}")


def checkpoint_path(args: Args, method: str, repeats: list[int]) -> str:
    """Where the batch of ``method`` over ``repeats`` saves its state between trials."""
    seeds = "-".join(str(args.seed + r) for r in repeats)
    precision = "f64" if args.x64 else "f32"
    task_hash = hashlib.sha256(tasks.describe(args.make_task()).encode()).hexdigest()[:8]
    name = (f"{os.path.basename(args.stem)}_{method}_{args.settings_name(method)}_task{task_hash}_{precision}"
            f"_seeds{seeds}.npz")
    return os.path.join(args.checkpoints or os.path.join(args.out, ".cache", "learn"), name)


def save_checkpoint(path: str, state: RunState, meta: dict) -> None:
    """A batch's state as plain data (``records.save_state``): the arrays ``data.*`` and ``theta.I`` (the I-th
    leaf of theta; each with a leading repeat axis) and, as JSON, ``meta`` with the trials done."""
    arrays = {f"data.{name}": value for name, value in state.data._asdict().items()}
    arrays |= theta_arrays(state.theta)
    save_state(path, arrays, dict(meta, trials_done=state.trials_done))


def load_checkpoint(path: str, task) -> dict:
    """``dict(state=RunState or None, rows=[...], and the rest of the meta)`` of the checkpoint at ``path``
    (``save_checkpoint``; theta rebuilt on the tree of ``task``'s default policy); a checkpoint pickled by
    older code at the same name with ``.pkl`` is read too; ``dict(state=None, rows=[])`` without one."""
    saved = load_state(path)
    if saved is None:
        return load_legacy_pickle(path[:-len(".npz")] + ".pkl") or dict(state=None, rows=[])
    arrays, meta = saved
    data = gp.GPData(**{name: arrays[f"data.{name}"] for name in gp.GPData._fields})
    # theta is None before the first learned trial
    theta = theta_from_arrays(arrays, policy_structure(task)) if "theta.0" in arrays else None
    return dict(meta, state=RunState(meta.pop("trials_done"), theta, data))


def final_state_path(args: Args, method: str, repeat: int) -> str:
    """``{out}/learn_final/{stem}_{method}_{settings}_seed{seed}`` (``.npz`` and ``.json``)."""
    return os.path.join(args.out, "learn_final", f"{os.path.basename(args.stem)}_{method}_"
                                                 f"{args.settings_name(method)}_seed{args.seed + repeat}")


def keep_final_states(args: Args, method: str, repeats: list[int], theta, data: gp.GPData, rows: list[dict]) -> None:
    """Each repeat's final state (theta and data with a leading repeat axis) as a scenario file
    (``harness.scenario.save_scenario``), with the GP fitted to all its data as the loop fits one
    (``gp_steps`` L-BFGS steps on the rows held; FITC past ``gp_inducing`` rows) and the key of its
    table rows."""
    rows_held = int(np.max(np.asarray(data.num_valid)))
    fit = jax.vmap(sparse_gp.fitter(args.gp_inducing, rows_held, args.settings["gp_steps"]))
    posterior = gp.check_posterior(fit(gp.trim_data(data, rows_held)))
    task = args.make_task()
    for index, repeat in enumerate(repeats):
        own = functools.partial(jax.tree.map, lambda x: np.asarray(x[index]))
        returns = np.array([row["trial_return"] for row in rows if row["repeat"] == repeat])
        path = final_state_path(args, method, repeat)
        save_scenario(dict(scenario=Scenario(own(data), own(posterior), own(theta), returns), provenance=provenance(),
                           meta=dict(row_key(args, task, method, repeat), code_version=code_version(),
                                     description=f"the final policy, data and GP of {method}'s learning run, repeat "
                                                 f"{repeat} (seed {args.seed + repeat}) of {os.path.basename(args.stem)} "
                                                 f"at settings {args.settings_name(method)}")), path)
        print(f"  {method} repeat {repeat}: final state kept in {path}.{{npz,json}}", file=sys.stderr, flush=True)


def run_experiments(args: Args, method: str, repeats: list[int]) -> list[dict]:
    """One learning run per repeat, all vmapped together (``learning_run(batched=True)``),
    continuing from the batch's checkpoint if there is one; returns a row per repeat and trial
    (progress on stderr)."""
    task, settings, chosen = args.make_task(), args.settings, METHODS[method]
    optimise = policy_optimiser(chosen.estimator, chosen.steps(settings), settings["particles"], chosen.quasi_newton)
    if args.float32_rollouts(method):
        optimise = in_precision(optimise, jnp.float32)
    problem = task_problem(task, gp.GPModel(task), **chosen.overrides)
    run_keys = jnp.stack([jax.random.key(args.seed + r) for r in repeats])
    evaluate = jax.vmap(lambda th, k: evaluate_policy(task, problem.policy, th, k, num_runs=settings["eval_runs"]))
    num_trials = task.num_random_trials + settings["learned_trials"]
    checkpoint = checkpoint_path(args, method, repeats)
    saved = load_checkpoint(checkpoint, task)
    # a checkpoint's rows carry the code that ran them (blank where it predates the column)
    rows, resume = [{"code_version": "", **row} for row in saved["rows"]], saved["state"]
    # fit on the rows held (same objective, other round-off), except in a batch begun before that
    # option existed: a resumed batch computes what it began with
    fit_rows_held = saved.get("fit_rows_held", resume is None)
    seeds_in_turn = saved.get("seeds_in_turn", resume is None)  # likewise: seeds optimised one after another
    if resume is not None:
        print(f"  {method} repeats {repeats[0]}-{repeats[-1]}: resuming after trial {resume.trials_done}/{num_trials}"
              f" ({checkpoint})", file=sys.stderr, flush=True)
        if (written := saved.get("jax", "unrecorded jax")) != JAX_VERSIONS:
            print(f"  WARNING: the checkpoint's trials ran under {written}, this process under {JAX_VERSIONS}: the "
                  "batch's trials would mix library versions (docs/deviations.md: the jax 0.10.2 entry)", file=sys.stderr,
                  flush=True)
    start = time.perf_counter() - (rows[-1]["seconds"] if rows else 0.0)
    pace = dict(since=time.perf_counter(), learned=0)  # for the time left

    def on_trial(record, data):
        if record.learned:
            eval_keys = jax.vmap(stream, in_axes=(0, None, None))(run_keys, "evaluation", record.trial)
            scores = np.asarray(evaluate(record.theta, eval_keys))  # (repeats, eval_runs)
        else:
            scores = np.full((len(repeats), 1), np.nan)
        seconds = time.perf_counter() - start
        returns, num_valid = np.asarray(record.episode.total_cost), np.asarray(data.num_valid)
        nonfinite = (np.asarray(record.nonfinite_steps) if record.learned
                     else np.full(len(repeats), np.nan))  # no optimisation before a random trial
        for i, repeat in enumerate(repeats):
            rows.append(dict(repeat=repeat, trial=record.trial, learned=record.learned,
                             trial_return=float(returns[i]), eval_mean=float(scores[i].mean()),
                             eval_std=float(scores[i].std(ddof=1)) if scores.shape[1] > 1 else np.nan,
                             data_points=int(num_valid[i]), nonfinite_steps=float(nonfinite[i]), seconds=seconds,
                             code_version=code_version()))
        save_checkpoint(checkpoint, RunState(record.trial + 1, record.theta, data),
                        dict(rows=rows, jax=JAX_VERSIONS, fit_rows_held=fit_rows_held, seeds_in_turn=seeds_in_turn))
        evaluation = f", evaluation mean {scores.mean():.2f}" if record.learned else ""
        if np.nansum(nonfinite) > 0:
            evaluation += f", NON-FINITE estimates in {nonfinite.astype(int).tolist()} optimiser steps"
        if record.learned:  # the time left from the learned trials this process ran (random ones cost nothing)
            pace["learned"] += 1
            left = (time.perf_counter() - pace["since"]) / pace["learned"] * (num_trials - record.trial - 1)
            evaluation += f"; about {left / 60:.0f} min left in this batch"
        else:
            pace["since"] = time.perf_counter()
        print(f"  {method} repeats {repeats[0]}-{repeats[-1]}: trial {record.trial + 1}/{num_trials},"
              f" returns {np.round(returns, 1).tolist()}{evaluation} ({seconds:.0f} s)", file=sys.stderr, flush=True)

    theta, data = learning_run(task, problem, run_keys, settings["learned_trials"], optimise, settings["gp_steps"],
                               on_trial, batched=True, trim_model=True, fit_rows_held=fit_rows_held,
                               seeds_in_turn=seeds_in_turn, resume=resume,
                               num_inducing=args.gp_inducing, optimisation_key_per_run=chosen.noise_fixed_per_run)
    if args.keep_final:
        keep_final_states(args, method, repeats, theta, data, rows)
    return rows


def row_key(args: Args, task, method: str, repeat: int) -> dict:
    """The key columns (``KEY_COLUMNS``) of ``method``'s repeat ``repeat`` under ``args``."""
    return dict(task=args.task, cost=getattr(task, "cost_type", "default"), noise_k=args.noise_k,
                task_options=tasks.describe(task), method=method, repeat=repeat, seed=args.seed + repeat,
                settings=args.settings_name(method))


def current_rows(args: Args, table: ResultTable):
    """Every method's rows in ``table`` at this run's task options, settings and seeds, whichever
    process ran them (so that two processes splitting the methods of one CSV write the same report)."""
    rows = table.read()
    valid = runnable()
    current = np.array([m in valid and s == args.settings_name(m) for s, m in zip(rows.settings, rows.method)], bool)
    return rows[current & (rows.task_options == tasks.describe(args.make_task()))
                & (rows.seed == rows.repeat + args.seed)]


def remove_checkpoint(checkpoint: str) -> None:
    """Delete a finished batch's checkpoint, and the ``.pkl`` that older code wrote at its name: its rows are in
    the table now."""
    for path in (checkpoint, checkpoint[:-len(".npz")] + ".pkl"):
        if os.path.exists(path):
            os.remove(path)


def run(args: Args):
    """Run every missing experiment, ``batch`` repeats at a time from ``first_repeat``, appending
    their trials as each batch ends; returns the rows the report pools (``current_rows``)."""
    table = ResultTable(args.stem + ".csv", KEY_COLUMNS)
    task = args.make_task()
    batches = [(m, list(range(first, min(first + args.batch, args.repeats))))
               for m in str_list(args.methods) for first in range(args.first_repeat, args.repeats, args.batch)]
    for index, (method, chunk) in enumerate(batches):
        missing = [r for r in chunk if not table.has(row_key(args, task, method, r))]
        if not missing:
            continue
        print(f"[batch {index + 1}/{len(batches)}] {method}, repeats {missing}", file=sys.stderr, flush=True)
        # one append, so that a stop is unlikely to leave some repeats' rows, which a rerun would take as done
        # (it is not atomic: success.final_evaluations leaves out an experiment with fewer trials than its settings)
        table.extend([{**row_key(args, task, method, row["repeat"]), **row}
                      for row in run_experiments(args, method, missing)])
        remove_checkpoint(checkpoint_path(args, method, missing))
        jax.clear_caches()  # each trial compiled its own programs (docs/extending.md: memory mappings)
    return current_rows(args, table)


def main(argv=None) -> None:
    args = parse(Args, argv)
    jax.config.update("jax_enable_x64", args.x64)
    # Asynchronous CPU dispatch with debug callbacks (the optimiser's progress lines) is a known
    # hang (jax-ml/jax#25861), so it is off (no cost at these sizes). The hangs seen in batched
    # runs were batched LAPACK calls, now avoided (numerics/linalg.py, tests/test_linalg.py).
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    rows = run(args)
    learn_report.write(rows, args.stem, f"python -m harness.learn {' '.join(argv or sys.argv[1:])}")
    print(f"wrote {args.stem}.{{csv,md,png}}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
