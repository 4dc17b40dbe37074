"""Episodic learning with each method, and its success rates (PIPPS, section "Experiments").

    python -m harness.learn --task cartpole --cost angle --noise-k 1 \
        --methods pilco,rp,rp_fs,gr,gr_fs,lr,tp,tp-sigma_f,tp+sigma_n --repeats R --preset quick|paper

Each experiment (method, repeat) is one learning run (``harness.episodic.learning_run``): the
task's random trial(s), then per learned trial: fit the GP to all data, optimise the policy on
it, run one real trial and add its data. Particle methods take ``optimiser_steps`` steps of
the paper's optimiser with ``particles`` particles; PILCO takes ``pilco_steps`` L-BFGS steps on
its deterministic objective. After every trial the policy is scored by ``eval_runs`` runs on
the real system (evaluation only; their data are not used). Repeat r uses seed ``seed + r``.

Every trial of an experiment is appended to ``learn_{task}_{cost}_k{k}.csv`` when the
experiment ends; a rerun skips finished experiments. The report (``harness.learn_report``)
regenerates every table and figure from the CSV alone.
"""

from __future__ import annotations

import dataclasses
import os
import sys
import time

import jax
import numpy as np

import tasks
from estimators.base import task_problem
from harness.cli import parse, str_list
from harness.episodic import evaluate_policy, learning_run, policy_optimiser
from harness.records import ResultTable
from models import gp

METHODS = {
    "pilco": ("pilco", {}),
    "rp": ("rp", {}),
    "rp_fs": ("rp_fs", {}),
    "gr": ("gr", {}),
    "gr_fs": ("gr_fs", {}),
    "lr": ("lr", {}),
    "biw_lr": ("biw_lr", {}),
    "tp": ("tp", {}),
    "tp-sigma_f": ("tp", {"model_var_scale": 0.0}),
    "tp+sigma_n": ("tp", {"noise_var_scale": 100.0}),
}
"""method name -> (estimator, problem overrides): the paper's TP variants change the model's
variances, not the estimator."""

PRESETS = {
    # learned trials (0: the task preset's), optimiser steps, particles, evaluation runs,
    # PILCO's L-BFGS steps, GP training steps
    "quick": dict(learned_trials=5, optimiser_steps=150, particles=100, eval_runs=10, pilco_steps=40, gp_steps=60),
    "paper": dict(learned_trials=0, optimiser_steps=600, particles=300, eval_runs=30, pilco_steps=150, gp_steps=100),
}
DEFAULT_METHODS = "pilco,rp,rp_fs,gr,gr_fs,lr,tp,tp-sigma_f,tp+sigma_n"
"""The paper's columns."""
KEY_COLUMNS = ["task", "cost", "noise_k", "method", "repeat", "seed", "settings"]


@dataclasses.dataclass(frozen=True)
class Args:
    """Episodic learning: success rates and learning curves per method."""

    task: str = "cartpole"
    cost: str = ""
    noise_k: float = 1.0
    methods: str = DEFAULT_METHODS
    repeats: int = 10
    preset: str = "quick"
    seed: int = 0
    out: str = "reports"
    x64: bool = True
    learned_trials: int = -1
    optimiser_steps: int = -1
    particles: int = -1
    eval_runs: int = -1
    pilco_steps: int = -1
    gp_steps: int = -1

    def __post_init__(self):
        if self.preset not in PRESETS:
            raise ValueError(f"unknown preset {self.preset!r}; valid presets: {sorted(PRESETS)}")
        unknown = [m for m in str_list(self.methods) if m not in METHODS]
        if unknown:
            raise ValueError(f"unknown methods {unknown}; valid methods: {list(METHODS)}")
        self.make_task()  # fails with the valid tasks and options
        if self.repeats < 1:
            raise ValueError("repeats must be >= 1")

    def make_task(self):
        options = {"noise_k": self.noise_k} | ({"cost": self.cost} if self.cost else {})
        return tasks.make(self.task, **options)

    @property
    def settings(self) -> dict:
        """The preset's numbers with any given overrides (-1: the preset's; learned_trials 0:
        the task preset's number of learned trials)."""
        chosen = {name: getattr(self, name) if getattr(self, name) >= 0 else value
                  for name, value in PRESETS[self.preset].items()}
        if chosen["learned_trials"] == 0:
            chosen["learned_trials"] = self.make_task().num_learned_trials
        return chosen

    @property
    def settings_name(self) -> str:
        return "-".join(f"{key}{value}" for key, value in self.settings.items())

    @property
    def stem(self) -> str:
        task = self.make_task()
        cost = getattr(task, "cost_type", "default")
        return os.path.join(self.out, f"learn_{self.task}_{cost}_k{self.noise_k:g}")


def run_experiment(args: Args, method: str, repeat: int) -> list[dict]:
    """One learning run; returns a row per trial (progress on stderr)."""
    task, settings = args.make_task(), args.settings
    name, overrides = METHODS[method]
    steps = settings["pilco_steps"] if name == "pilco" else settings["optimiser_steps"]
    optimise = policy_optimiser(name, steps, settings["particles"])
    problem = task_problem(task, gp.GPModel(task), **overrides)
    key = jax.random.key(args.seed + repeat)
    rows, start = [], time.perf_counter()

    def on_trial(record, data):
        if record.learned:
            scores = np.asarray(evaluate_policy(task, problem.policy, record.theta,
                                                jax.random.fold_in(key, 40_000 + record.trial),
                                                num_runs=settings["eval_runs"]))
            eval_mean, eval_std = float(scores.mean()), float(scores.std(ddof=1)) if len(scores) > 1 else 0.0
        else:
            eval_mean = eval_std = np.nan
        rows.append(dict(trial=record.trial, learned=record.learned, trial_return=float(record.episode.total_cost),
                         eval_mean=eval_mean, eval_std=eval_std, data_points=int(data.num_valid),
                         seconds=time.perf_counter() - start))
        print(f"  {method} repeat {repeat}: trial {record.trial + 1}/{task.num_random_trials + settings['learned_trials']}"
              f" return {rows[-1]['trial_return']:.2f}, evaluation {eval_mean:.2f} ({rows[-1]['seconds']:.0f} s)",
              file=sys.stderr, flush=True)

    learning_run(task, problem, key, settings["learned_trials"], optimise, settings["gp_steps"], on_trial)
    return rows


def run(args: Args):
    """Run every missing experiment, appending its trials; returns this run's rows."""
    table = ResultTable(args.stem + ".csv", KEY_COLUMNS)
    task = args.make_task()
    experiments = [(m, r) for m in str_list(args.methods) for r in range(args.repeats)]
    for index, (method, repeat) in enumerate(experiments):
        row_key = dict(task=args.task, cost=getattr(task, "cost_type", "default"), noise_k=args.noise_k,
                       method=method, repeat=repeat, seed=args.seed + repeat, settings=args.settings_name)
        if table.has(row_key):
            continue
        print(f"[{index + 1}/{len(experiments)}] {method}, repeat {repeat}", file=sys.stderr, flush=True)
        for row in run_experiment(args, method, repeat):
            table.append({**row_key, **row})
    rows = table.read()
    return rows[(rows.settings == args.settings_name) & rows.method.isin(str_list(args.methods))
                & (rows.repeat < args.repeats) & (rows.seed == rows.repeat + args.seed)]


def main(argv=None) -> None:
    from harness import learn_report

    args = parse(Args, argv)
    jax.config.update("jax_enable_x64", args.x64)
    rows = run(args)
    learn_report.write(rows, args.stem, f"python -m harness.learn {' '.join(argv or sys.argv[1:])}")
    print(f"wrote {args.stem}.{{csv,md,png}}", file=sys.stderr)


if __name__ == "__main__":
    main()
