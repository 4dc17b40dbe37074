"""Do the learning runs' programs meet jaxlib 0.10.2's wrong-results bug? Not part of the harness:
the provenance of the numbers in the README's jax 0.10.2 entry.

    python diagnostics/ynn_reduce_check.py [--full-gp-sizes | --optimiser]

The bug (jax-ml/jax#39103) lies in XLA:CPU's YNNPACK reduce fusions: with
``XLA_FLAGS=--xla_cpu_experimental_ynn_fusion_type=-reduce`` the BIW-LR test that fails under
0.10.2 (``tests/test_estimators.py::test_float32_estimates_batched_are_each_estimate_alone``)
passes (1.5e-6 of the largest entry, against 17 x without the flag). This script compiles each
program of a k = 1 learning trial at the jobs' shape (5 seeds vmapped, P = 300, the jobs'
XLA_FLAGS) three times, each in its own process: as the jobs do ("default"), with YNN reduce
fusion off ("off"), and, for the float32 particle estimators, off in float64 ("f64"); then
prints how far apart they are. Inputs: the cart-pole (angle cost, k = 1), 5 seeds with 6 and
11 random episodes (180 rows: the full GP; 330: FITC with 300 inducing inputs), a GP fitted with
30 L-BFGS steps, and each seed's initial policy. A program the bug hits differs between
default and off far beyond round-off; the float32 estimators' default-vs-f64 gap must then be
far above their off-vs-f64 gap (round-off grows along the rollout, so compare the columns).
The FITC fit's 100 L-BFGS steps on the inducing inputs can carry round-off into a different
path: its FITC objective and posterior are also compared at fixed inputs, and a control fits
data moved by 1e-12 (relative) with YNN reduce fusion off, to show how far round-off alone
moves the fit. ``--full-gp-sizes``: the programs whose shape follows the full GP's rows at the
run's other sizes (PILCO's value and gradient, the estimates at T = 5), as run and with the
fusions off only. ``--optimiser``: the policy optimisation program itself (the estimate inside
the optimiser's scan, fused anew), with 2 steps, as run and with the fusions off.
"""

import os
import pickle
import subprocess
import sys
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import jaxlib  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))
import estimators  # noqa: E402
import tasks  # noqa: E402
from estimators.base import task_problem  # noqa: E402
from estimators.pilco import pilco_objective  # noqa: E402
from harness.episodic import add_episode, cast_floating, data_capacity, evaluate_policy, in_precision, \
    policy_optimiser  # noqa: E402
from models import gp, sparse_gp  # noqa: E402
from tasks.rollout import run_episode  # noqa: E402

JOBS_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
"""The learning jobs' XLA_FLAGS (XLA reads no flag after the second, unprefixed one: put others first)."""
YNN_REDUCE_OFF = "--xla_cpu_experimental_ynn_fusion_type=-reduce"
TASK = tasks.make("cartpole", cost="angle", noise_k=1.0)
SEEDS, PARTICLES, INDUCING, EPISODES = 5, 300, 300, (6, 11)
FULL_GP_EPISODES = (1, 2, 3, 4, 5, 7, 8, 9, 10)
"""``--full-gp-sizes``: the other sizes of the full GP the optimiser runs on (30-300 rows, trimmed
to whole episodes); a fit's own shape is the buffer's (480 rows) at every size, and FITC's
posterior has 300 inducing inputs at every size."""
PARTS = ("all", "full-gp-sizes", "optimiser")
ESTIMATORS = {"tp": (5, TASK.horizon), "gr": (5, TASK.horizon), "rp": (5,), "biw_lr": (5,)}
"""Estimator -> horizons: 5 steps, where round-off has not yet grown, and the task's 30."""


def flat(tree) -> np.ndarray:
    """(SEEDS, n): every leaf of a seed-batched pytree, flattened side by side."""
    return np.concatenate([np.asarray(x, float).reshape(SEEDS, -1) for x in jax.tree.leaves(tree)], 1)


def run_counting_fusions(jitted, *args):
    """(``jitted(*args)``, how many YNN fusions of its compiled program reduce), compiled once."""
    compiled = jitted.lower(*args).compile()
    fusions = sum(1 for line in compiled.as_text().splitlines() if "__ynn_fusion" in line and "reduce" in line)
    return compiled(*args), fusions


def seed_keys() -> jax.Array:
    """(SEEDS,) keys of the estimates and evaluations."""
    return jax.vmap(lambda s: jax.random.fold_in(jax.random.key(s), 7))(jnp.arange(SEEDS))


def random_data(episodes: int):
    """(GPData batched over SEEDS, theta batched): ``episodes`` random trials per seed."""
    keys = jax.vmap(jax.random.key)(jnp.arange(SEEDS))
    data = gp.GPModel(TASK).empty_data(data_capacity(TASK))
    data = jax.tree.map(lambda x: jnp.broadcast_to(x, (SEEDS,) + x.shape), data)
    for e in range(episodes):
        episode = jax.vmap(lambda k: run_episode(TASK, jax.random.fold_in(k, e)))(keys)
        data = jax.vmap(lambda d, ep: add_episode(TASK, d, ep))(data, episode)
    theta = jax.vmap(lambda k: TASK.default_policy().init(jax.random.fold_in(k, 10_000)))(keys)
    return data, theta


def fit(data):
    """The learning trial's fit (``sparse_gp.fitter``, the full GP trimmed to whole episodes)."""
    rows = int(np.max(np.asarray(data.num_valid)))
    posterior = jax.vmap(sparse_gp.fitter(INDUCING, rows, 30))(data)
    if not sparse_gp.uses_fitc(INDUCING, rows):
        posterior = gp.truncate(posterior, -(-rows // TASK.horizon) * TASK.horizon)
    return posterior


def child(mode: str, folder: str, part: str) -> None:
    """Run the programs of ``part`` under this process's XLA_FLAGS; save ``{mode}.pkl``: (name ->
    (array, fusions), controls). "all": every program at ``EPISODES``; "full-gp-sizes": at
    ``FULL_GP_EPISODES``, the programs whose shape follows the full GP's rows, PILCO's and the
    T = 5 estimates, with no comparison of fits; "optimiser": ``optimiser_programs``."""
    out, control = {}, {}
    if part == "optimiser":
        optimiser_programs(mode, folder, out)
    else:
        all_programs(mode, folder, part == "all", out, control)
    with open(os.path.join(folder, f"{mode}.pkl"), "wb") as f:
        pickle.dump((out, control), f)


def off_posterior(mode: str, folder: str, episodes: int, data, fitted=None):
    """The fit of mode "off" (which runs first and saves it, ``fitted`` if given), so that every
    mode runs on the same GP."""
    posterior_file = os.path.join(folder, f"posterior_{episodes}.pkl")
    if mode == "off":
        with open(posterior_file, "wb") as f:
            pickle.dump(jax.device_get(fit(data) if fitted is None else fitted), f)
    with open(posterior_file, "rb") as f:
        return pickle.load(f)


def optimiser_programs(mode: str, folder: str, out: dict) -> None:
    """The jobs' policy optimisation program (``harness.episodic.policy_optimiser`` in float32,
    vmapped over the seeds) with 2 steps instead of 600 (the same scan body): theta after them
    and the 2 values, per estimator, at ``EPISODES``."""
    keys = seed_keys()
    for episodes in EPISODES:
        data, theta = random_data(episodes)
        problem = task_problem(TASK, gp.GPModel(TASK), off_posterior(mode, folder, episodes, data))
        for name in ESTIMATORS:
            run = jax.jit(jax.vmap(in_precision(policy_optimiser(name, 2, PARTICLES), jnp.float32)))
            result, fusions = run_counting_fusions(run, problem, theta, keys)
            label = f"{episodes * TASK.horizon} rows, {name} policy optimisation, 2 steps, P = {PARTICLES}"
            values_and_theta = np.concatenate([np.asarray(result.values, float), flat(result.theta)], 1)
            out[f"{label}, T = {TASK.horizon} (float32)"] = (values_and_theta, fusions)
        print(f"  {mode}: {episodes * TASK.horizon} rows done", file=sys.stderr, flush=True)


def all_programs(mode: str, folder: str, every_program: bool, out: dict, control: dict) -> None:
    """``child``'s parts "all" (``every_program``) and "full-gp-sizes"."""
    keys = seed_keys()
    dtype = jnp.float64 if mode == "f64" else jnp.float32
    for episodes in EPISODES if every_program else FULL_GP_EPISODES:
        data, theta = random_data(episodes)
        rows = f"{episodes * TASK.horizon} rows"
        fitted = None
        if mode == "off" or (mode == "default" and every_program):
            fitted = fit(data)
            out[f"{rows}, GP fit (float64)"] = (flat(fitted), None)
        posterior = off_posterior(mode, folder, episodes, data, fitted)  # every mode runs the programs below on it
        if mode != "f64" and every_program and sparse_gp.uses_fitc(INDUCING, episodes * TASK.horizon):
            nlml = jax.jit(jax.vmap(jax.value_and_grad(sparse_gp.fitc_neg_log_marginal_likelihood)))
            start = jax.vmap(lambda d: sparse_gp.initial_inducing(d, INDUCING))(data)
            (value, grad), fusions = run_counting_fusions(nlml, start, posterior.log_hyp, data)
            out[f"{rows}, FITC NLML and gradient at the initial inducing inputs (float64)"] = (
                np.concatenate([np.asarray(value)[:, None], flat(grad)], 1), fusions)
            fitc = jax.vmap(sparse_gp.fitc_posterior)
            out[f"{rows}, FITC posterior at off's inducing inputs (float64)"] = (
                flat(fitc(posterior.inputs, posterior.log_hyp, data)), None)
            if mode == "off":  # how far the fit moves for a change of the data at round-off
                moved = data._replace(inputs=data.inputs * (1 + 1e-12), targets=data.targets * (1 + 1e-12))
                control[rows] = (flat(fit(moved)), out[f"{rows}, GP fit (float64)"][0])
        if mode != "f64":
            problem = task_problem(TASK, gp.GPModel(TASK), posterior)
            pilco = jax.jit(jax.vmap(jax.value_and_grad(lambda pr, th: pilco_objective(pr, th)[0], argnums=1)))
            (value, grad), fusions = run_counting_fusions(pilco, problem, theta)
            out[f"{rows}, PILCO value and gradient (float64)"] = (
                np.concatenate([np.asarray(value)[:, None], flat(grad)], 1), fusions)
        if mode != "f64" and every_program:
            evaluate = jax.jit(jax.vmap(lambda th, k: evaluate_policy(TASK, problem.policy, th, k, num_runs=30)))
            costs, fusions = run_counting_fusions(evaluate, theta, keys)
            out[f"{rows}, evaluation, 30 runs (float64)"] = (np.asarray(costs), fusions)
        for name, horizons in ESTIMATORS.items():
            est = estimators.make(name)
            run = jax.jit(jax.vmap(lambda pr, th, k: est(pr, th, k, PARTICLES)))
            for horizon in horizons if every_program else horizons[:1]:
                problem = task_problem(TASK, gp.GPModel(TASK), cast_floating(posterior, dtype), horizon=horizon)
                args = (problem, cast_floating(theta, dtype), keys)
                estimate, fusions = run_counting_fusions(run, *args)
                out[f"{rows}, {name} gradient, P = {PARTICLES}, T = {horizon} (float32)"] = (
                    np.concatenate([np.asarray(estimate.value, float)[:, None], flat(estimate.grad)], 1),
                    fusions)
        print(f"  {mode}: {rows} done", file=sys.stderr, flush=True)


def gap(a: np.ndarray, b: np.ndarray) -> str:
    """The per-seed max |a - b| / max |b|, as its range over the seeds."""
    per_seed = np.abs(a - b).max(1) / np.abs(b).max(1)
    return f"{per_seed.min():.1e}-{per_seed.max():.1e}"


def main() -> None:
    part = sys.argv[1][2:] if len(sys.argv) > 1 else "all"
    if part not in PARTS:
        raise SystemExit(f"usage: python {sys.argv[0]} [--full-gp-sizes | --optimiser]")
    modes = (("off", f"{YNN_REDUCE_OFF} {JOBS_FLAGS}"), ("default", JOBS_FLAGS))
    modes += (("f64", f"{YNN_REDUCE_OFF} {JOBS_FLAGS}"),) if part == "all" else ()
    print("jax", jax.__version__, "jaxlib", jaxlib.__version__)
    with tempfile.TemporaryDirectory() as folder:
        results, controls = {}, {}
        for mode, flags in modes:
            subprocess.run([sys.executable, __file__, mode, folder, part], check=True,
                           env=os.environ | {"XLA_FLAGS": flags})
            with open(os.path.join(folder, f"{mode}.pkl"), "rb") as f:
                results[mode], controls[mode] = pickle.load(f)
    f64_columns = " | off vs f64 | default vs f64" if part == "all" else ""
    print(f"program | YNN reduce fusions (default) | default vs off{f64_columns} (per seed: max |difference| / "
          "max |reference|, range over 5 seeds; value and gradient together)")
    for name, (default, fusions) in results["default"].items():
        off = results["off"][name][0]
        line = f"{name} | {'-' if fusions is None else fusions} | {gap(default, off)}"
        if name in results.get("f64", {}):
            f64 = results["f64"][name][0]
            line += f" | {gap(off, f64)} | {gap(default, f64)}"
        print(line)
    for rows, (moved, fitted) in controls["off"].items():
        print(f"control: {rows}, GP fit (float64) to the data times 1 + 1e-12 against the fit to the data, both off: "
              f"{gap(moved, fitted)}")


if __name__ == "__main__":
    if len(sys.argv) > 1 and not sys.argv[1].startswith("--"):
        child(*sys.argv[1:])
    else:
        main()
