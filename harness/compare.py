"""Learned model versus true dynamics: gradient variance and direction, per estimator.

    python -m harness.compare --task cartpole [--models gp,jax] [--estimators rp,lr,biw_lr,tp]
        [--particles 10,30,100,300] [--repeats 20] [--reference-estimator lr|rp|...|fd]
        [--reference-fd-step 0.01] [--reference-particles 1000] [--reference-repeats 100] [--out DIR]

At theta0 of the scenario (``harness.scenario``; the same theta0 and task for every model):

- the reference: the true gradient, estimated by ``reference_repeats`` independent estimates of
  ``reference_estimator`` with ``reference_particles`` particles on the true dynamics
  (``reference_model``); its own relative standard error is reported. ``fd`` instead of an
  estimator: central finite differences of J with common random numbers (``fd_gradient``),
  whose variance stays bounded where the dynamics are chaotic and RP's per-particle gradients
  have heavy tails (the unicycle); the report then also gives the same reference at half the
  step, to show the step's bias;
- for each model, estimator and particle count, ``repeats`` independent estimates g_r: their
  variance (trace of the covariance) and, against the reference g*, the cosine similarity
  ``g_r . g* / (|g_r| |g*|)`` and the relative error ``|g_r - g*| / |g*|``, each as a mean over
  repeats with a 95 % interval (normal, 1.96 standard errors), and the cosine of the mean
  gradient (towards what averaging many estimates would give, the model's bias; the mean of
  ``repeats`` heavy-tailed estimates keeps much of their noise).

Rows go to ``compare_{task}.csv`` as each cell finishes (a rerun resumes); the reference to
``.cache/``; the markdown and metadata (``records.write_metadata``) beside the CSV.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import sys
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
import pandas as pd

import estimators
from harness import keys
from harness import scenario as scenario_lib
from harness.cli import Progress, check_sizes, int_list, parse, run_command, str_list
from harness.records import Command, ResultTable, write_metadata
from harness.variance import cell_statistics, repeated_estimates

KEY_COLUMNS = ["task", "model", "estimator", "particles", "repeats", "seed", "scenario", "reference"]
Z95 = 1.96


@dataclasses.dataclass(frozen=True)
class Args(scenario_lib.ExperimentArgs):
    """Learned-model against true-dynamics gradients: variance, cosine and relative error."""

    models: str = "gp,jax"
    """Comma-separated models to compare (gp, jax, mjx, or your own: harness.scenario.MODELS)."""
    estimators: str = "rp,lr,biw_lr,tp"
    """Comma-separated estimators."""
    particles: str = "10,30,100,300"
    """Comma-separated particle counts."""
    repeats: int = 20
    """Independent estimates per (model, estimator, particles) cell."""
    reference_model: str = "jax"
    """True dynamics of the reference gradient (jax or mjx)."""
    reference_estimator: str = "lr"
    """Estimator of the reference gradient, or fd: central finite differences of J with common random numbers."""
    reference_fd_step: float = 0.01
    """Step h of the fd reference, along each coordinate of theta."""
    reference_particles: int = 1000
    """Particles per reference estimate."""
    reference_repeats: int = 100
    """Reference estimates averaged into the reference gradient (100 LR estimates: a relative standard error
    of 0.11 at the cart-pole scenario, where 30 gave 0.22)."""

    def __post_init__(self):
        super().__post_init__()
        check_sizes(particles=(int_list(self.particles), 2), reference_particles=(self.reference_particles, 2))
        for model in str_list(self.models) + [self.reference_model]:
            scenario_lib.check_model(model)
        if scenario_lib.MODELS[self.reference_model].learned:
            true = [name for name, spec in scenario_lib.MODELS.items() if not spec.learned]
            raise ValueError(f"the reference must be a true-dynamics model ({', '.join(true)}), not the learned "
                             f"{self.reference_model}")
        references = [self.reference_estimator] if self.reference_estimator != "fd" else []
        scenario_lib.check_estimators(str_list(self.estimators), self.task, str_list(self.models))
        scenario_lib.check_estimators(references, self.task, [self.reference_model])
        if self.reference_fd_step <= 0:
            raise ValueError(f"reference_fd_step must be > 0; got {self.reference_fd_step}")
        if self.repeats < 2 or self.reference_repeats < 2:
            raise ValueError("repeats and reference_repeats must be >= 2")

    @property
    def reference_name(self) -> str:
        method = self.reference_estimator + (f"{self.reference_fd_step:g}" if self.reference_estimator == "fd" else "")
        return f"{self.reference_model}-{method}-P{self.reference_particles}-R{self.reference_repeats}"


def alignment(grads: np.ndarray, reference: np.ndarray) -> dict:
    """Cosine similarity and relative error of each estimate (rows of grads (R, n)) against
    the reference (n,): means over the finite rows with 95 % half-widths, and the cosine of
    the mean estimate."""
    grads = grads[np.all(np.isfinite(grads), axis=1)]
    ref_norm = np.linalg.norm(reference)
    cosine = grads @ reference / (np.linalg.norm(grads, axis=1) * ref_norm)
    rel_error = np.linalg.norm(grads - reference, axis=1) / ref_norm
    mean = grads.mean(axis=0)
    half = lambda x: Z95 * x.std(ddof=1) / np.sqrt(len(x)) if len(x) > 1 else np.nan  # noqa: E731
    return {
        "cosine": float(cosine.mean()), "cosine_ci": float(half(cosine)),
        "rel_error": float(rel_error.mean()), "rel_error_ci": float(half(rel_error)),
        "cosine_of_mean": float(mean @ reference / (np.linalg.norm(mean) * ref_norm)),
    }


@functools.partial(jax.jit, static_argnums=(3, 4))
def fd_gradient(problem, theta, key: jax.Array, num_particles: int, step: float) -> jax.Array:
    """Central finite differences of the sampled objective with common random numbers, (n,):
    ``g_i = (J(theta + h e_i) - J(theta - h e_i)) / 2h``, J the mean return of ``num_particles``
    particles drawn with ``key`` (the same draws on both sides), ``e_i`` the i-th coordinate of
    theta flattened. An estimate of the gradient of J smoothed over +-h: its bias is O(h^2), and
    its variance, that of the difference of the two means over (2h)^2, is at most Var(J-hat) / h^2
    however chaotic the dynamics."""
    flat, unflatten = ravel_pytree(theta)

    def objective(x):
        return scenario_lib.particle_returns(problem, unflatten(x), key, num_particles).mean()

    basis = step * jnp.eye(flat.size, dtype=flat.dtype)
    return jax.lax.map(lambda e: (objective(flat + e) - objective(flat - e)) / (2 * step), basis)


class Reference(NamedTuple):
    """The reference gradient g* (n,), its relative standard error |standard error| / |g*|, and
    for the fd reference the cosine and relative difference |g*_{h/2} - g*| / |g*| of the same
    reference at half the step, with the relative standard error of that difference over the
    paired draws (NaN otherwise)."""

    grad: np.ndarray
    rse: float
    half_step_cosine: float = np.nan
    half_step_difference: float = np.nan
    half_step_noise: float = np.nan


def mean_and_rse(grads: np.ndarray) -> tuple[np.ndarray, float]:
    """The mean of independent estimates (R, n) and its relative standard error."""
    mean = grads.mean(axis=0)
    return mean, float(np.sqrt(np.sum(grads.var(axis=0, ddof=1)) / len(grads)) / np.linalg.norm(mean))


def reference_gradient(args: Args, where: dict[str, scenario_lib.Setting], key: jax.Array) -> Reference:
    """The reference gradient at the theta0 of the Settings ``where`` (by model), cached under
    ``out`` by the scenario's content hash."""
    some = next(iter(where.values()))
    theta0, content = some.theta0, some.content
    path = os.path.join(args.out, ".cache", f"reference_{args.task}_{content}_{args.reference_name}.npz")
    if not os.path.exists(path):
        print(f"reference: {args.reference_repeats} x {args.reference_name.split('-')[1]} with "
              f"{args.reference_particles} particles on the {args.reference_model} dynamics",
              file=sys.stderr, flush=True)
        problem = (where[args.reference_model].problem if args.reference_model in where else
                   scenario_lib.model_problem(args.task, args.reference_model, some.scenario))
        if args.reference_estimator == "fd":
            def fd_estimate(r: int, h: float) -> np.ndarray:
                print(f"reference: fd estimate {r + 1}/{args.reference_repeats} (h = {h:g})", file=sys.stderr,
                      flush=True)
                return np.asarray(fd_gradient(problem, theta0, jax.random.fold_in(key, r),
                                              args.reference_particles, h))

            saved = {name: np.stack([fd_estimate(r, h) for r in range(args.reference_repeats)])
                     for name, h in (("grads", args.reference_fd_step), ("half_step", args.reference_fd_step / 2))}
        else:
            saved = dict(grads=repeated_estimates(estimators.make(args.reference_estimator), problem, theta0,
                                                  args.reference_particles, args.reference_repeats, key).grads)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        np.savez(path, **saved)
    saved = np.load(path)
    broken = sum(int((~np.isfinite(saved[name])).any(axis=1).sum()) for name in saved.files)
    if broken:
        raise ValueError(f"the reference {path} has {broken} non-finite estimates: its mean would be NaN and dropping "
                         "them would bias it; use --reference-estimator fd (bounded where RP's or LR's per-particle "
                         "gradients blow up), or more --reference-particles, and delete the file")
    grad, rse = mean_and_rse(saved["grads"])
    if "half_step" not in saved:
        return Reference(grad, rse)
    half = saved["half_step"].mean(axis=0)
    paired = saved["half_step"] - saved["grads"]  # the same draws at h and h / 2: (R, n)
    norm = np.linalg.norm(grad)
    return Reference(grad, rse, float(half @ grad / (np.linalg.norm(half) * norm)),
                     float(np.linalg.norm(half - grad) / norm),
                     float(np.sqrt(np.sum(paired.var(axis=0, ddof=1)) / len(paired)) / norm))


def run(args: Args) -> tuple[pd.DataFrame, Reference, dict[str, scenario_lib.Setting]]:
    """Measure every missing cell; returns this run's rows, the reference and the Setting per model."""
    table = ResultTable(os.path.join(args.out, f"compare_{args.task}.csv"), KEY_COLUMNS)
    seed_key = jax.random.key(args.seed)
    where = scenario_lib.settings(args, str_list(args.models))
    theta0, content = next(iter(where.values())).theta0, next(iter(where.values())).content
    reference = reference_gradient(args, where, keys.stream(seed_key, "reference"))
    cells = [(m, e, p) for m in str_list(args.models) for e in str_list(args.estimators)
             for p in int_list(args.particles)]
    progress = Progress(len(cells))
    for index, (model, name, num_particles) in enumerate(cells):
        row_key = dict(task=args.task, model=model, estimator=name, particles=num_particles, repeats=args.repeats,
                       seed=args.seed, scenario=content, reference=args.reference_name)
        if table.has(row_key):
            continue
        rep = repeated_estimates(estimators.make(name), where[model].problem, theta0, num_particles, args.repeats,
                                 keys.stream(seed_key, "estimates"))
        stats = {**cell_statistics(rep), **alignment(rep.grads, reference.grad)}
        table.append({**row_key, **stats, "scenario_settings": args.scenario_name})
        jax.clear_caches()  # no later cell reuses its programs (docs/extending.md: memory mappings)
        print(progress.line(index, f"{model:3s} {name:7s} P={num_particles:5d}: variance {stats['variance']:.3e}, "
                                   f"cosine {stats['cosine']:.3f} +- {stats['cosine_ci']:.3f}, rel. error "
                                   f"{stats['rel_error']:.3g}"), file=sys.stderr, flush=True)
    print(f"compare: scenario {content}: {table.summary()}", file=sys.stderr, flush=True)
    rows = table.read()
    keep = (rows.seed == args.seed) & (rows.repeats == args.repeats) & (rows.scenario == content) & (
        rows.reference == args.reference_name)
    return rows[keep], reference, where


def split_models(models: list[str]) -> tuple[list[str], list[str]]:
    """``models`` split into the learned ones and the true dynamics (``scenario.MODELS``)."""
    return ([m for m in models if scenario_lib.MODELS[m].learned],
            [m for m in models if not scenario_lib.MODELS[m].learned])


def findings(args: Args, rows: pd.DataFrame) -> list[str]:
    """Per estimator: the learned/true variance ratios and the cosines at the largest P that
    every model has (a model may lack the dearer cells)."""
    lines = ["## What the comparison shows", ""]
    models = str_list(args.models)
    learned, true = split_models(models)
    for name, group in rows[rows.model.isin(models)].groupby("estimator"):
        by_model = group.set_index(["model", "particles"]).sort_index()
        variance = {m: group[group.model == m].set_index("particles").variance for m in models}
        parts = []
        for fitted in learned:
            for model in true:
                ratio = (variance[fitted] / variance[model]).dropna()
                if len(ratio):
                    parts.append(f"variance {fitted} / {model} {ratio.min():.2g}-{ratio.max():.2g} over P = "
                                 f"{', '.join(map(str, ratio.index))}")
        shared = set.intersection(*(set(variance[m].index) for m in models))
        if shared:
            top = max(shared)
            for model in models:
                cell = by_model.loc[(model, top)]
                parts.append(f"cosine with g* at P = {top} on {model}: {cell.cosine:.3f} +- "
                             f"{cell.cosine_ci:.3f} (of the mean: {cell.cosine_of_mean:.3f})")
        lines.append(f"- {name}: " + ("; ".join(parts) + "." if parts else "no particle count measured on every model."))
    lines.append("")
    return lines


def reference_lines(args: Args, reference: Reference) -> list[str]:
    """The report's description of the reference and its quality."""
    what = (f"central finite differences of J with common random numbers (step h = {args.reference_fd_step:g} along "
            f"each coordinate of theta), each from" if args.reference_estimator == "fd" else
            f"{args.reference_estimator} estimates with")
    lines = [f"- Reference g*: the mean of {args.reference_repeats} {what} {args.reference_particles} particles on the "
             f"{args.reference_model} dynamics; its relative standard error (|standard error| / |g*|) is "
             f"{reference.rse:.3f}: even an exact gradient would show a relative error of about that and a cosine "
             f"of about 1 - {reference.rse:.3f}^2 / 2 = {1 - reference.rse**2 / 2:.3f} against it (in expectation; "
             "every cell shares g*'s error, which the intervals below do not include)."]
    if np.isfinite(reference.half_step_cosine):
        bias = reference.half_step_difference > 3 * reference.half_step_noise
        lines.append(f"- The same reference at h / 2 (the same draws): cosine with g* {reference.half_step_cosine:.3f}, "
                     f"relative difference {reference.half_step_difference:.3f}, against {reference.half_step_noise:.2g} "
                     "from the noise (the paired standard error): "
                     + (f"the step's bias, which for an O(h^2) bias puts g*'s own at about 4/3 of it, "
                        f"{4 / 3 * reference.half_step_difference:.3f} of |g*|." if bias else
                        "within the noise: no bias of the step is measurable."))
    return lines


def command(args: Args) -> Command:
    """The command that makes this report (its rows and reference reused): the markdown prints it, the metadata
    lists it."""
    fd_step = ["--reference-fd-step", f"{args.reference_fd_step:g}"] if args.reference_estimator == "fd" else []
    return Command("harness.compare", [
        "--task", args.task, "--models", args.models, "--estimators", args.estimators, "--particles", args.particles,
        "--repeats", str(args.repeats), "--reference-model", args.reference_model, "--reference-estimator",
        args.reference_estimator, *fd_step, "--reference-particles", str(args.reference_particles),
        "--reference-repeats", str(args.reference_repeats), "--seed", str(args.seed),
        *args.scenario_flags()])


def write_report(args: Args, rows: pd.DataFrame, reference: Reference, scenario_lines: list[str],
                 objective: Sequence[dict] = ()) -> None:
    """The markdown (settings, the reference's quality, the table and what it says) and the metadata
    (``records.write_metadata``; ``objective``: the J of ``scenario_lines``, ``scenario.objective_values``; none
    where these are none)."""
    made_by = command(args)
    models = str_list(args.models)
    wide = rows.pivot_table(index=["estimator", "particles"], columns="model", dropna=False,
                            values=["variance", "cosine", "cosine_ci", "rel_error", "rel_error_ci", "cosine_of_mean",
                                    "nonfinite_estimates"])
    wide = wide.dropna(how="all")  # dropna=False kept every model's columns, and every estimator x particles row
    table = pd.DataFrame(index=wide.index)
    for model in models:
        table[f"variance {model}"] = wide["variance"][model].map("{:.3g}".format)
        table[f"non-finite {model}"] = wide["nonfinite_estimates"][model].map(lambda n: f"{n:.0f}/{args.repeats}")
    learned, true = split_models(models)
    for fitted in learned:
        for model in true:
            table[f"variance {fitted} / {model}"] = (wide["variance"][fitted] / wide["variance"][model]).map(
                "{:.3g}".format)
    for model in models:
        table[f"cosine {model}"] = [f"{c:.3f} +- {h:.3f}" for c, h in zip(wide["cosine"][model], wide["cosine_ci"][model])]
        table[f"rel. error {model}"] = [f"{c:.3g} +- {h:.2g}" for c, h in
                                        zip(wide["rel_error"][model], wide["rel_error_ci"][model])]
        table[f"cosine of mean {model}"] = wide["cosine_of_mean"][model].map("{:.3f}".format)
        finite = args.repeats - wide["nonfinite_estimates"][model]
        table[f"noise of mean {model}"] = (np.sqrt(wide["variance"][model] / finite)
                                           / np.linalg.norm(reference.grad)).map("{:.2g}".format)
    for model in models:  # cells measured on some models only (a cell that ran counts its non-finite estimates)
        table.loc[wide["nonfinite_estimates"][model].isna(),
                  [c for c in table.columns if c.endswith(f" {model}")]] = "not run"
    lines = [
        f"# Learned model against true dynamics: {args.task}",
        "",
        f"Command: `{made_by.text}`",
        "",
        *scenario_lib.model_labels(args.task, str_list(args.models) + [args.reference_model]),
        *scenario_lines,
        *reference_lines(args, reference),
        f"- Per cell: {args.repeats} independent estimates; variance = trace of their covariance; cosine and relative "
        "error are means over the estimates with 95 % intervals; 'cosine of mean' is that of their average, and "
        "'noise of mean' the standard error of that average over |g*| (sqrt(variance / finite estimates) / |g*|: "
        "near or above 1, the average's direction is noise); "
        "'non-finite': estimates with a NaN or infinite component, left out of every statistic.",
        "",
        *findings(args, rows),
        table.reset_index().to_markdown(index=False, disable_numparse=True),
        "",
    ]
    stem = os.path.join(args.out, f"compare_{args.task}")
    with open(stem + ".md", "w") as f:
        f.write("\n".join(lines))
    write_metadata(stem, made_by, str(rows.scenario.iloc[0]), objective)


def main(argv=None) -> None:
    args = parse(Args, argv)
    jax.config.update("jax_enable_x64", args.x64)
    rows, reference, where = run(args)
    objective = scenario_lib.objective_values(where, args.seed)
    write_report(args, rows, reference, args.scenario_lines(where, rows, objective, "; every model is evaluated at its theta0"),
                 objective)
    print(f"wrote {os.path.join(args.out, f'compare_{args.task}')}.{{csv,md,json}}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
