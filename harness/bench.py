"""Benchmark: one gradient estimate of each estimator on the paper's cart-pole setting, and
the projected time of one paper-setting learning experiment per method.

    python -m harness.bench [--particles 100,300,1000] [--repeats 5] [--estimators ...]
        [--learning-methods pilco,tp,... ("" to skip)] [--float32-learning-methods tp]
        [--pseudo-input-learning-methods tp] [--fitc-learning-methods tp,pilco]
        [--fitc-float32-learning-methods tp] [--out reports]

Setting: the cart-pole (``pipps`` preset, T = 30) with a GP trained on ``trials`` random
episodes (15 x 30 = 450 points, as after the paper's last trial), the RBF policy at its
initial parameters, float64. Per estimator and particle count: compile time, the median of
``repeats`` timed calls after compilation, and XLA's peak memory of the compiled program
(``memory_analysis``: arguments + outputs + temporaries; the CPU backend reports no live
device memory). In the same run it
measures the machine's float64 matmul rate and reports the RP gradient's achieved fraction of
it under a stated flop model. The learning section is ``harness.bench_learning``. Writes
``bench.md`` (and ``bench.csv``, ``bench_learning.csv``) under ``--out``; no wall-clock
assertions anywhere: compare the ratios measured in one run.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

import estimators
import tasks
from estimators.base import task_problem
from harness.cli import Progress, int_list, parse, run_command, str_list
from harness import bench_learning, keys
from harness.episodic import add_episode, cast_floating
from harness.methods import DEFAULT_METHODS
from harness.records import Command, code_version, read_csv, read_metadata, write_metadata
from models import gp
from tasks.rollout import run_episode


@dataclasses.dataclass(frozen=True)
class Args:
    """Time one gradient estimate of each estimator (compile time, median, peak memory)."""

    estimators: str = "rp,rp_fs,gr,gr_fs,lr,biw_lr,tp"
    """Comma-separated estimators to time."""
    particles: str = "100,300,1000"
    """Comma-separated particle counts."""
    repeats: int = 5
    """Timed calls per estimator and particle count (median reported)."""
    trials: int = 15
    """Random episodes in the GP's training data."""
    gp_steps: int = 30
    """L-BFGS steps of the GP fit."""
    seed: int = 0
    """Seed of the data and keys."""
    learning_methods: str = DEFAULT_METHODS
    """Methods of the projected learning experiment (empty: skip that section)."""
    float32_learning_methods: str = "tp"
    """Methods timed again with float32 rollouts."""
    pseudo_input_learning_methods: str = "tp"
    """Methods timed again with PILCO's pseudo-input RBF policy."""
    fitc_learning_methods: str = "tp,pilco"
    """Methods timed again with the FITC sparse GP past 300 points."""
    fitc_float32_learning_methods: str = "tp"
    """Methods timed again with both the FITC sparse GP and float32 rollouts."""
    dtypes: str = "float64,float32"
    """Comma-separated precisions of the gradient timings (float32: the GP fitted in float64, cast)."""
    out: str = "reports"
    """Folder for bench.md and the CSVs."""
    report_only: bool = False
    """Time nothing: rewrite bench.md from the CSVs in --out, with the flags of the run that timed them (its
    bench.json; CSVs of older code without one take the flags given here), and the whole run in {out}/bench_whole."""


def matmul_rate(n: int = 2048, repeats: int = 5, dtype=jnp.float64) -> float:
    """FLOP/s of an n x n matmul in ``dtype`` under XLA (median of ``repeats``)."""
    a = jax.random.normal(jax.random.key(0), (n, n), jnp.float64).astype(dtype)
    f = jax.jit(lambda x: x @ x)
    jax.block_until_ready(f(a))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f(a))
        times.append(time.perf_counter() - start)
    return 2 * n**3 / float(np.median(times))


MATRIX_PRODUCTS = {"tp": 3}
"""N x N matrix-vector products per particle, step and output, as implemented (``gp_gradient_flops``); 2 for
every estimator not listed."""


def gp_gradient_flops(estimator: str, num_particles: int, horizon: int, num_points: int, outputs: int) -> float:
    """Flop model of one value and gradient on the GP, as implemented: the dominant cost is the predictive
    variance's N x N products per particle, step and output, 2 N^2 each. Reverse mode through the rollout
    (RP, GR, LR, BIW-LR and their fixed-noise forms) forms ``v = L^-1 k`` and, for the gradient, ``w = L^-T v``
    (``models.gp.explained_variance``'s JVP): 2 products. TP rolls out once (``v``) and re-linearises every
    step in its backward pass (``v`` and ``w`` again): 3. The O(N D) kernel and O(P^2) BIW terms are left out."""
    return MATRIX_PRODUCTS.get(estimator, 2) * 2 * num_points**2 * outputs * num_particles * horizon


def bench_problem(args: Args):
    task = tasks.make("cartpole")
    model = gp.GPModel(task)
    data = model.empty_data(args.trials * task.horizon)
    key = jax.random.key(args.seed)
    for trial in range(args.trials):
        data = add_episode(task, data, run_episode(task, keys.stream(key, "random_trial", trial)))
    posterior = gp.fit(data, num_steps=args.gp_steps)
    policy = task.default_policy()
    return task, task_problem(task, model, posterior, policy=policy), policy.init(keys.stream(key, "theta0")), int(
        data.num_valid)


def time_estimator(estimator, problem, theta, num_particles: int, repeats: int) -> dict:
    jitted = jax.jit(estimator, static_argnums=3)
    key = jax.random.key(1)
    start = time.perf_counter()
    compiled = jitted.lower(problem, theta, key, num_particles).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(problem, theta, key))
    times = []
    for r in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(problem, theta, jax.random.fold_in(key, r)))
        times.append(time.perf_counter() - start)
    memory = compiled.memory_analysis()  # CPU reports peak_memory_in_bytes = 0: add the buffers
    buffers = (memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes
               if memory is not None else np.nan)
    return {"median_s": float(np.median(times)), "compile_s": compile_s, "peak_memory_mb": buffers / 2**20}


def this_machine() -> str:
    return (f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, JAX {jax.__version__} on "
            f"{jax.default_backend()} ({jax.devices()[0].device_kind})")


def saved_results(out: str) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """bench.csv and bench_learning.csv (None if absent) under ``out``."""
    learning = os.path.join(out, "bench_learning.csv")
    return read_csv(os.path.join(out, "bench.csv")), read_csv(learning) if os.path.exists(learning) else None


def complete_older_csv(out: str, num_points: int) -> None:
    """Give a bench.csv of older code its missing columns: ``matmul_gflops`` from its columns (gflop /
    (roofline_fraction x median_s)), ``gp_points`` = ``num_points``, ``machine`` this machine's description."""
    path = os.path.join(out, "bench.csv")
    table = read_csv(path)
    filled = dict(matmul_gflops=table.gflop / (table.roofline_fraction * table.median_s), gp_points=num_points,
                  machine="not recorded (timed by older code)")
    if missing := {name: value for name, value in filled.items() if name not in table}:
        table.assign(**missing).to_csv(path, index=False)


TARGETS = dict(rp_float32_s=0.20, tp_float32_s=0.25, rp_roofline=0.4, tp_experiment_min=12.0)
"""Issue 47's targets at P = 300 and the bench's GP (450 points): seconds per RP and TP estimate in float32, RP's
roofline fraction (a goal), and a paper-setting TP experiment (float32 rollouts, FITC past 300 points) in
minutes on 2 cores."""


def target_lines(table: pd.DataFrame, learning: pd.DataFrame | None, whole: float | None) -> list[str]:
    """The targets section: each target beside its measurement in this report, and what is left."""
    at = table[(table.particles == 300) & (table.dtype == "float32")].set_index("estimator")
    lines = ["## Targets (issue 47: twice as fast)", ""]
    if {"rp", "tp"} <= set(at.index):
        floor = at.gflop / at.matmul_gflops  # the flop model's seconds at the matmul rate
        for name in ("rp", "tp"):
            target = TARGETS[f"{name}_float32_s"]
            lines.append(f"- {name.upper()}, float32, P = 300, N = {at.gp_points[name]}: {at.median_s[name]:.3f} s "
                         f"(target {target:.2f} s: {'met' if at.median_s[name] <= target else 'not met'}); its flops "
                         f"alone ({at.gflop[name]:.1f} GFLOP) take {floor[name]:.3f} s at this run's float32 matmul "
                         f"rate, so the target asks for a roofline fraction of {floor[name] / target:.2f}.")
        reached = at.roofline_fraction["rp"] >= TARGETS["rp_roofline"]
        lines.append(f"- RP's roofline fraction, float32, P = 300: {at.roofline_fraction['rp']:.2f} (goal "
                     f"{TARGETS['rp_roofline']:.1f}: {'met' if reached else 'not met'}).")
    if learning is not None:
        sweep_setting = learning[(learning.method == "tp") & (learning.dtype == "float32") & (learning.gp != "full")
                                 & (learning.rbf == "direct")]
        if len(sweep_setting):
            projected = float(sweep_setting.total_min.iloc[0])
            lines.append(f"- A paper-setting TP experiment (float32 rollouts, FITC past 300 points: the sweep's "
                         f"settings), projected: {projected:.1f} min (target {TARGETS['tp_experiment_min']:g} min: "
                         f"{'met' if projected <= TARGETS['tp_experiment_min'] else 'not met'}).")
    command = Command("harness.learn", [*bench_learning.WHOLE_RUN_ARGV, "--out",
                                        f"reports/{bench_learning.WHOLE_RUN}"])
    lines.append(f"- The same experiment timed whole (`{command.text}`; seconds since its start after each trial "
                 "in its CSV): " + (f"{whole:.1f} min." if whole is not None else "not run yet."))
    return lines + [""]


def report_targets(out: str, table: pd.DataFrame, learning: pd.DataFrame | None) -> list[str]:
    """``target_lines`` with the whole run in ``{out}/bench_whole`` (``bench_learning.whole_run``)."""
    return target_lines(table, learning, bench_learning.whole_run(os.path.join(out, bench_learning.WHOLE_RUN)))


def command(args: Args) -> Command:
    """The flags of a timing run, as its report and metadata (``bench.json``) give them."""
    return Command("harness.bench", [
        "--estimators", args.estimators, "--particles", args.particles, "--repeats", str(args.repeats),
        "--trials", str(args.trials), "--gp-steps", str(args.gp_steps), "--seed", str(args.seed),
        "--dtypes", args.dtypes, "--learning-methods", args.learning_methods,
        "--float32-learning-methods", args.float32_learning_methods,
        "--pseudo-input-learning-methods", args.pseudo_input_learning_methods,
        "--fitc-learning-methods", args.fitc_learning_methods,
        "--fitc-float32-learning-methods", args.fitc_float32_learning_methods])


def main(argv=None) -> None:
    args = parse(Args, argv)
    if args.report_only:
        stem = os.path.join(args.out, "bench")
        if not os.path.exists(stem + ".json"):  # CSVs of older code: the flags given here are taken as the run's
            write_metadata(stem, command(args), None, [])
        run = parse(Args, read_metadata(stem + ".json")["command"]["argv"] + ["--out", args.out])
        complete_older_csv(args.out, run.trials * tasks.make("cartpole").horizon)
        return write_report(run, *saved_results(args.out))
    version = code_version()  # the code loaded now, whatever is committed while this runs
    jax.config.update("jax_enable_x64", True)
    for name in str_list(args.estimators):
        estimators.make(name)
    print("bench: building the GP ...", file=sys.stderr, flush=True)
    task, problem, theta, num_points = bench_problem(args)
    rates = {dtype: matmul_rate(dtype=jnp.dtype(dtype)) for dtype in str_list(args.dtypes)}
    rows = []
    cells = [(dtype, name, p) for dtype in rates for p in int_list(args.particles) for name in str_list(args.estimators)]
    progress = Progress(len(cells))
    cast = {dtype: (dataclasses.replace(problem, model_params=cast_floating(problem.model_params, jnp.dtype(dtype))),
                    cast_floating(theta, jnp.dtype(dtype))) for dtype in rates}
    for index, (dtype, name, num_particles) in enumerate(cells):
        stats = time_estimator(estimators.make(name), *cast[dtype], num_particles, args.repeats)
        flops = gp_gradient_flops(name, num_particles, task.horizon, num_points, task.model_state_dim)
        rows.append({"estimator": name, "dtype": dtype, "particles": num_particles, **stats,
                     "gflop": flops / 1e9, "matmul_gflops": rates[dtype] / 1e9, "gp_points": num_points,
                     "roofline_fraction": flops / rates[dtype] / stats["median_s"]})
        print(progress.line(index, f"{name:7s} {dtype} P={num_particles:5d}: {stats['median_s']:.3f} s "
                                   f"(compile {stats['compile_s']:.1f} s, peak {stats['peak_memory_mb']:.0f} MiB)"),
              file=sys.stderr, flush=True)
    table = pd.DataFrame(rows).assign(machine=this_machine(), code_version=version)
    os.makedirs(args.out, exist_ok=True)
    table.to_csv(os.path.join(args.out, "bench.csv"), index=False)
    learning = None
    if args.learning_methods:
        learning = bench_learning.measure(str_list(args.learning_methods), str_list(args.float32_learning_methods),
                                          str_list(args.pseudo_input_learning_methods),
                                          str_list(args.fitc_learning_methods),
                                          str_list(args.fitc_float32_learning_methods), seed=args.seed)
        learning.assign(code_version=version).to_csv(os.path.join(args.out, "bench_learning.csv"), index=False)
    write_metadata(os.path.join(args.out, "bench"), command(args), None, [])
    write_report(args, table, learning)


def write_report(args: Args, table: pd.DataFrame, learning: pd.DataFrame | None = None) -> None:
    """bench.md from the timings (and the learning section's, and the whole run's in {out}/bench_whole)."""
    task = tasks.make("cartpole")
    rates = {dtype: 1e9 * float(table[table.dtype == dtype].matmul_gflops.iloc[0]) for dtype in table.dtype.unique()}

    def wide(values: str, dtype: str, fmt: str) -> str:
        chosen = table[table.dtype == dtype].pivot(index="estimator", columns="particles", values=values)
        return chosen.reset_index().to_markdown(index=False, floatfmt=fmt)

    lines = [
        "# Benchmark: one gradient estimate, cart-pole, GP model",
        "",
        f"Command: `{command(args).text}`",
        "",
        f"- Machine: {table.machine.iloc[0]}.",
        f"- Setting: cart-pole `pipps` preset, T = {task.horizon}, GP with {table.gp_points.iloc[0]} training points "
        f"({args.trials} random episodes, {args.gp_steps} L-BFGS steps), RBF policy at its initial parameters; "
        "float32 casts the float64-fitted GP and theta.",
        "- Matmul rate measured in this run (2048 x 2048 under XLA): "
        + ", ".join(f"{dtype} {rate / 1e9:.1f} GFLOP/s" for dtype, rate in rates.items()) + ".",
        "- Flop model (`gp_gradient_flops`, as implemented): 2 N^2 per N x N product, per particle, step and output; "
        "2 products for the reverse-mode estimators (v = L^-1 k forward, w = L^-T v for the gradient), 3 for TP "
        "(its backward pass re-linearises each step). The roofline fraction is the time those flops take at the "
        "matmul rate over the time measured.",
        "",
    ]
    lines += report_targets(args.out, table, learning)
    lines += ["## One gradient estimate", ""]
    for dtype in rates:
        median = table[table.dtype == dtype].pivot(index="estimator", columns="particles", values="median_s")
        lines += [f"Median seconds per estimate after compilation, {dtype} (rows: estimator; columns: particles):", "",
                  median.reset_index().to_markdown(index=False, floatfmt=".3f"), ""]
        if "rp" in median.index:
            lines += [f"Ratio to RP, {dtype}:", "", median.div(median.loc["rp"]).reset_index().to_markdown(
                index=False, floatfmt=".2f"), ""]
        lines += [f"Roofline fraction, {dtype}:", "", wide("roofline_fraction", dtype, ".2f"), ""]
    first = next(iter(rates))
    lines += [f"Compile seconds ({first}):", "", wide("compile_s", first, ".1f"), "",
              f"Memory of the compiled program ({first}; MiB; arguments + outputs + temporaries, XLA "
              "memory_analysis):", "", wide("peak_memory_mb", first, ".0f"), ""]
    if learning is not None:
        lines += bench_learning.report_lines(learning)
    with open(os.path.join(args.out, "bench.md"), "w") as f:
        f.write("\n".join(lines))
    print(f"wrote {os.path.join(args.out, 'bench.md')}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
