"""The curse of chaos: the value landscape along a direction (PIPPS, figure "curse of chaos").

    python -m harness.landscape --task cartpole [--model gp|jax|mjx] [--particles 1000]
        [--estimators rp_fs,lr,tp] [--delta-max 1.5] [--points 31] [--fd-step 0.1] [--out DIR]

theta = theta0 + delta d moves along the fixed random unit direction d of ``harness.scenario``.
One key, the same at every delta (the fixed seed), draws the particles. At each delta:

- (a) the objective J with a 95 % interval ``1.96 sd_i(R_i) / sqrt(P)`` over particle returns;
- (b)-(d) each estimator's gradient projected on d, ``d . g``, with the interval from the
  spread of the particles' projected contributions, beside the finite-difference slope
  ``(J(delta + h) - J(delta - h)) / 2h`` of the same fixed-seed objective (h = ``fd_step``,
  large enough to step over the fixed-seed jaggedness; interval from per-particle differences);
- the finite-time Lyapunov exponent of the same particles (``harness.lyapunov``) beside RP's
  variance (trace of the variance of its mean gradient, from the particle spread);
- (e)-(f) at ``slice_deltas``: V(s_1) = E[sum_{t=1..T} c(s_t) | s_1] over a 2-D slice of the
  first state (two named dimensions, by default the task's ``value_slice_dims``; the others at
  the mean of p(s_1)), each grid point averaged over ``slice_particles`` fixed-seed particles,
  over a box of ``box_stds`` standard deviations of p(s_1) (estimated from the particles).

Rows are appended to ``landscape_{task}_{model}.csv`` as each delta finishes (a rerun resumes);
the heatmaps go to ``landscape_{task}_{model}_slices.npz``; the figure, markdown and metadata
(``records.write_metadata``) beside.
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

import estimators
import tasks
from estimators.base import draw_noise, per_particle, rollout, theta_dtype
from harness import keys
from harness import scenario as scenario_lib
from harness.cli import Progress, check_sizes, float_list, parse, run_command, str_list
from harness.lyapunov import finite_time_exponents
from harness.records import Command, ResultTable, write_metadata

KEY_COLUMNS = ["task", "model", "particles", "delta_theta", "seed", "scenario", "fd_step", "estimators"]
Z95 = 1.96


@dataclasses.dataclass(frozen=True)
class Args(scenario_lib.ExperimentArgs):
    """The curse-of-chaos value landscape along a random direction in policy space."""

    model: str = "gp"
    """Dynamics: gp (the scenario's GP), jax or mjx, or one of your own (harness.scenario.MODELS)."""
    estimators: str = "rp_fs,lr,tp"
    """Comma-separated estimators whose projected gradients are plotted."""
    particles: int = 1000
    """Particles at every delta (one fixed key)."""
    delta_max: float = 1.5
    """The direction is scanned over [-delta_max, delta_max]."""
    points: int = 31
    """Number of deltas in the scan."""
    fd_step: float = 0.1
    """Finite-difference half-step h of the fixed-seed slope."""
    slice_dims: str = ""
    """Two comma-separated first-state dimensions of the value slices (empty: the task's)."""
    slice_deltas: str = "0,1.5"
    """Comma-separated deltas at which the value slices are computed."""
    slice_particles: int = 4
    """Fixed-seed particles averaged at each slice grid point."""
    grid: int = 41
    """Slice grid points per axis."""
    box_stds: float = 4.0
    """Half-width of the slice box in standard deviations of p(s_1)."""

    def __post_init__(self):
        super().__post_init__()
        scenario_lib.check_model(self.model)
        check_sizes(particles=(self.particles, 2), slice_particles=(self.slice_particles, 1))
        if "pilco" in str_list(self.estimators):
            raise ValueError("the landscape projects each particle's gradient (Estimate.aux['particle_grads']), "
                             "which pilco's deterministic objective has not: leave pilco out of --estimators")
        scenario_lib.check_estimators(str_list(self.estimators), self.task, [self.model])
        names = tasks.make(self.task).model_state_names
        dims = self.slice_names
        if len(dims) != 2 or not set(dims) <= set(names):
            raise ValueError(f"slice_dims must name two of the modelled state's dimensions {list(names)}, "
                             f"got {self.slice_dims!r}")
        if self.points < 2 or self.particles < 2 or self.grid < 2 or self.fd_step <= 0:
            raise ValueError("points, particles and grid must be >= 2 and fd_step > 0")

    @property
    def slice_names(self) -> list[str]:
        """The two dimensions of the value slices ("": the task's ``value_slice_dims``)."""
        return str_list(self.slice_dims) or list(tasks.make(self.task).value_slice_dims)

    @property
    def deltas(self) -> np.ndarray:
        return np.linspace(0.0, self.delta_max, self.points)

    @property
    def stem(self) -> str:
        return os.path.join(self.out, f"landscape_{self.task}_{self.model}")


def projected(particle_grads, direction) -> jax.Array:
    """Each particle's gradient contribution projected on the direction: ``d . g_i``, (P,)."""
    return sum(jnp.tensordot(g, d, axes=d.ndim)
               for g, d in zip(jax.tree.leaves(particle_grads), jax.tree.leaves(direction)))


def mean_and_interval(samples: np.ndarray) -> tuple[float, float]:
    """The mean of per-particle samples and the half-width of its 95 % interval (normal)."""
    samples = np.asarray(samples)
    return float(samples.mean()), float(Z95 * samples.std(ddof=1) / np.sqrt(len(samples)))


def measure_delta(args: Args, where: scenario_lib.Setting, delta: float, key: jax.Array, jitted: dict) -> dict:
    """Every column of one delta's row (see the module docstring)."""
    P = args.particles
    returns = jitted["returns"]
    row = {}
    row["value"], row["value_ci"] = mean_and_interval(returns(where.problem, where.theta(delta), key, P))
    slope = (returns(where.problem, where.theta(delta + args.fd_step), key, P)
             - returns(where.problem, where.theta(delta - args.fd_step), key, P)) / (2 * args.fd_step)
    row["fd_slope"], row["fd_slope_ci"] = mean_and_interval(slope)
    for name in str_list(args.estimators):
        e = jitted[name](where.problem, where.theta(delta), key, P)
        row[f"{name}_grad"], row[f"{name}_ci"] = mean_and_interval(projected(e.aux["particle_grads"], where.direction))
        row[f"{name}_variance"] = float(sum(jnp.sum(v) for v in jax.tree.leaves(e.grad_var)))
        row[f"{name}_nans"] = int(e.aux["nan_count"])
        if "k_lr" in e.aux:
            row[f"{name}_mean_k_lr"] = float(jnp.mean(e.aux["k_lr"]))
    exponents = finite_time_exponents(where.problem, where.theta(delta), key, P)
    row["ftle_mean"], row["ftle_median"] = float(np.mean(exponents)), float(np.median(exponents))
    row["ftle_positive_fraction"] = float(np.mean(exponents > 0))
    return row


def value_slice(args: Args, where: scenario_lib.Setting, delta: float, key: jax.Array) -> dict:
    """V(s_1) over the 2-D slice at ``delta``: the two axes (grid,) and the values (grid, grid)."""
    problem, theta = where.problem, where.theta(delta)
    names = tasks.make(args.task).model_state_names
    i, j = (names.index(n) for n in args.slice_names)
    box_key, tail_key = jax.random.split(key)
    s0, eps = draw_noise(problem, box_key, args.particles, theta_dtype(theta))
    s1 = rollout(problem, per_particle(problem.policy.prepare(theta), args.particles), s0, eps[:1]).states[1]
    centre, spread = jnp.mean(s1, axis=0), jnp.std(s1, axis=0)
    axis_i, axis_j = (jnp.linspace(centre[k] - args.box_stds * spread[k], centre[k] + args.box_stds * spread[k],
                                   args.grid) for k in (i, j))
    tail = dataclasses.replace(problem, horizon=problem.horizon - 1)
    n = args.slice_particles
    nets = per_particle(problem.policy.prepare(theta), n)
    tail_eps = jax.random.normal(tail_key, (tail.horizon, n, centre.shape[0]), centre.dtype)

    def value(a, b):
        start = jnp.broadcast_to(centre.at[i].set(a).at[j].set(b), (n, centre.shape[0]))
        later = rollout(tail, nets, start, tail_eps).returns if tail.horizon > 0 else 0.0
        return jnp.mean(jax.vmap(problem.cost)(start) + later)

    grid_a, grid_b = jnp.meshgrid(axis_i, axis_j, indexing="ij")
    values = jax.jit(lambda a, b: jax.lax.map(lambda ab: value(*ab), (a, b), batch_size=64))(
        grid_a.ravel(), grid_b.ravel()).reshape(grid_a.shape)
    return {"axis_i": np.asarray(axis_i), "axis_j": np.asarray(axis_j), "values": np.asarray(values)}


def check_aux(name: str, aux: dict) -> None:
    """Refuse an estimator whose ``Estimate.aux`` lacks what the landscape reads."""
    missing = [entry for entry in ("particle_grads", "nan_count") if entry not in aux]
    if missing:
        raise ValueError(f"estimator {name!r} gives no aux{missing}: the landscape projects each particle's "
                         "gradient (particle_grads) and counts non-finite terms (nan_count); "
                         "estimators.base.particle_estimate adds both")


def run(args: Args) -> tuple[pd.DataFrame, dict, scenario_lib.Setting]:
    """Measure every missing delta (appending to the CSV), then the slices; returns this run's
    rows, the slices {delta: value_slice(...)} and the Setting."""
    table = ResultTable(args.stem + ".csv", KEY_COLUMNS)
    where = scenario_lib.setting(args, args.model)
    key = keys.stream(jax.random.key(args.seed), "landscape")
    slice_key = keys.stream(jax.random.key(args.seed), "slices")  # apart from the rows'
    jitted = {name: jax.jit(estimators.make(name), static_argnums=3) for name in str_list(args.estimators)}
    jitted["returns"] = jax.jit(scenario_lib.particle_returns, static_argnums=3)
    for name in str_list(args.estimators):  # traced for shapes only: nothing computed
        estimate = jax.eval_shape(lambda pr, th, k: jitted[name](pr, th, k, args.particles), where.problem,
                                  where.theta0, key)
        check_aux(name, estimate.aux)
    progress = Progress(args.points)
    for index, delta in enumerate(args.deltas):
        row_key = dict(task=args.task, model=args.model, particles=args.particles, delta_theta=float(delta),
                       seed=args.seed, scenario=where.content, fd_step=args.fd_step, estimators=args.estimators)
        if table.has(row_key):
            continue
        start = time.perf_counter()
        row = measure_delta(args, where, float(delta), key, jitted)
        table.append({**row_key, **row, "scenario_settings": args.scenario_name})
        print(progress.line(index, f"delta={delta:.3f}: J {row['value']:.3f}, FD slope {row['fd_slope']:.3g}, "
                            + ", ".join(f"{n} {row[f'{n}_grad']:.3g}" for n in str_list(args.estimators))
                            + f", FTLE {row['ftle_mean']:.3f}  ({time.perf_counter() - start:.1f} s)"),
              file=sys.stderr, flush=True)
    slices_path = args.stem + "_slices.npz"
    slices = {}
    stored = dict(np.load(slices_path)) if os.path.exists(slices_path) else {}
    for delta in float_list(args.slice_deltas):
        name = f"{where.content}_seed{args.seed}_P{args.particles}_n{args.slice_particles}_grid{args.grid}_" \
               f"box{args.box_stds:g}_{','.join(args.slice_names)}_delta{delta:g}"
        if name + "_values" not in stored:
            print(f"value slice at delta={delta:g} ({args.grid}x{args.grid} starts)", file=sys.stderr, flush=True)
            for part, array in value_slice(args, where, delta, slice_key).items():
                stored[f"{name}_{part}"] = array
            np.savez(slices_path, **stored)
        slices[delta] = {part: stored[f"{name}_{part}"] for part in ("axis_i", "axis_j", "values")}
    print(f"landscape: scenario {where.content}: {table.summary()}", file=sys.stderr, flush=True)
    rows = table.read()
    rows = rows[(rows.seed == args.seed) & (rows.particles == args.particles) & (rows.scenario == where.content)
                & (rows.fd_step == args.fd_step) & (rows.estimators == args.estimators)]
    return rows.sort_values("delta_theta"), slices, where


def agreement(rows: pd.DataFrame, name: str) -> tuple[int, int, float]:
    """(agree, total, max |z|): at how many deltas the estimator's directional derivative and the
    FD slope differ by less than 1.96 standard errors of the difference, ``z = gap /
    hypot(se, se_FD)`` (the 95 % half-widths over 1.96), and the largest |z|. The two share
    particles, so the independent-errors denominator is only approximate. (Whether the two 95 %
    intervals overlap, the rule before 2026-12-06, is a test at about 99.4 %.)"""
    gap = np.abs(rows[f"{name}_grad"] - rows.fd_slope)
    z = gap / np.hypot(rows[f"{name}_ci"], rows.fd_slope_ci) * 1.96
    return int((z <= 1.96).sum()), len(rows), float(z.max())


def resamples(name: str) -> bool:
    """Whether the estimator ``name`` (or the estimator it fixes the noise of) resamples from a Gaussian (GR)."""
    estimate = estimators.make(name)
    return bool(getattr(getattr(estimate, "inner", estimate), "gaussian_resampling", False))


def findings(args: Args, rows: pd.DataFrame) -> list[str]:
    """What the landscape shows, with the numbers (markdown lines)."""
    lines = ["## What the landscape shows", ""]
    for name in str_list(args.estimators):
        agree, total, z_max = agreement(rows, name)
        width = rows[f"{name}_ci"]
        lines.append(f"- {name}: agrees with the FD slope (|difference| < 1.96 standard errors) at {agree} of {total} "
                     f"deltas (largest |z| {z_max:.2f}); "
                     f"interval half-width {width.min():.3g}-{width.max():.3g} (median {width.median():.3g}); "
                     f"{int(rows[f'{name}_nans'].sum())} non-finite entries."
                     + (" Its objective resamples the particles from their Gaussian at every step, a J other than "
                        "the particle rollout's whose slope FD measures, so it need not agree (that it is the exact "
                        "gradient of its own objective is tested: tests/test_estimators.py)." if resamples(name) else ""))
    rp = next((n for n in ("rp", "rp_fs") if n in str_list(args.estimators)), None)
    if rp is not None and len(rows) > 2:
        log_var = np.log(rows[f"{rp}_variance"].to_numpy())
        corr = pd.Series(rows.ftle_mean.to_numpy()).corr(pd.Series(log_var), method="spearman")
        first, last = rows.iloc[0], rows.iloc[-1]
        lines.append(f"- RP's variance (trace of the variance of its mean gradient, {rp}) goes from "
                     f"{first[f'{rp}_variance']:.2e} at delta {first.delta_theta:g} to {last[f'{rp}_variance']:.2e} at "
                     f"{last.delta_theta:g} (ratio {last[f'{rp}_variance'] / first[f'{rp}_variance']:.2e}; range "
                     f"{np.exp(log_var.min()):.2e}-{np.exp(log_var.max()):.2e}).")
        lines.append(f"- The finite-time Lyapunov exponent (mean over particles, per control step) goes from "
                     f"{first.ftle_mean:.3f} to {last.ftle_mean:.3f} (range {rows.ftle_mean.min():.3f}-"
                     f"{rows.ftle_mean.max():.3f}; positive for {100 * rows.ftle_positive_fraction.mean():.0f} % of "
                     f"particle-deltas). Spearman correlation with log RP variance across deltas: {corr:.2f}. "
                     "The paper's explanation (chaos, lambda > 0, drives RP's variance) predicts a strong positive "
                     "correlation.")
    lines.append(f"- J: {rows.value.min():.3f}-{rows.value.max():.3f} over the deltas (the horizon T bounds it).")
    lines.append("")
    return lines


def command(args: Args) -> Command:
    """The command that makes this report (its rows reused): the markdown prints it, the metadata lists it."""
    return Command("harness.landscape", [
        "--task", args.task, "--model", args.model, "--estimators", args.estimators,
        "--particles", str(args.particles), "--delta-max", f"{args.delta_max:g}", "--points", str(args.points),
        "--fd-step", f"{args.fd_step:g}", "--slice-dims", ",".join(args.slice_names), "--slice-deltas",
        args.slice_deltas, "--slice-particles", str(args.slice_particles), "--grid", str(args.grid),
        "--box-stds", f"{args.box_stds:g}", "--seed", str(args.seed), *args.scenario_flags()])


def write_report(args: Args, rows: pd.DataFrame, slices: dict, scenario_lines: list[str],
                 objective: list[dict]) -> None:
    """The figure (panels a-g), the markdown (settings, findings, the per-delta table) and the metadata
    (``records.write_metadata``; ``objective``: the J of ``scenario_lines``, ``scenario.objective_values``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = str_list(args.estimators)
    fig, axes = plt.subplots(2, max(4, 1 + len(names)), figsize=(4.2 * max(4, 1 + len(names)), 7.5))
    top, bottom = axes
    d = rows.delta_theta.to_numpy()

    def band(ax, mean, half, label, color):
        ax.plot(d, mean, color=color, label=label)
        ax.fill_between(d, mean - half, mean + half, color=color, alpha=0.25)

    band(top[0], rows.value, rows.value_ci, "J (fixed seed)", "k")
    top[0].set_title(f"(a) objective, P = {args.particles}")
    for index, (ax, name) in enumerate(zip(top[1:], names)):
        band(ax, rows.fd_slope, rows.fd_slope_ci, f"FD slope, h = {args.fd_step:g}", "gray")
        band(ax, rows[f"{name}_grad"], rows[f"{name}_ci"], f"{name}: d . grad", f"C{index}")
        fd_scale = float((rows.fd_slope.abs() + rows.fd_slope_ci).max())
        if float((rows[f"{name}_grad"].abs() + rows[f"{name}_ci"]).max()) > 1e3 * fd_scale:
            ax.set_yscale("symlog", linthresh=fd_scale)  # RP's chaotic estimates span many decades
        ax.set_title(f"({chr(ord('b') + index)}) {name} gradient along d")
        ax.legend(fontsize=8)
    for ax in top:
        ax.set_xlabel("delta theta")
    for ax in top[1 + len(names):]:
        ax.axis("off")
    panel = ord("b") + len(names)
    dim_i, dim_j = args.slice_names
    for ax, (delta, s) in zip(bottom, slices.items()):
        image = ax.pcolormesh(s["axis_j"], s["axis_i"], s["values"], shading="auto", cmap="viridis")
        fig.colorbar(image, ax=ax)
        ax.set_xlabel(dim_j)
        ax.set_ylabel(dim_i)
        ax.set_title(f"({chr(panel)}) V(s1), delta = {delta:g}")
        panel += 1
    ax = bottom[len(slices)]
    rp = next((n for n in ("rp", "rp_fs") if n in names), None)
    ax.plot(d, rows.ftle_mean, "r-", label="FTLE (mean)")
    ax.set_ylabel("FTLE per control step", color="r")
    if rp is not None:
        twin = ax.twinx()
        twin.semilogy(d, rows[f"{rp}_variance"], "b.-", label=f"{rp} variance")
        twin.set_ylabel(f"{rp} gradient variance", color="b")
    ax.set_xlabel("delta theta")
    ax.set_title(f"({chr(panel)}) chaos and RP's variance")
    for ax in bottom[len(slices) + 1:]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.stem + ".png", dpi=110)
    plt.close(fig)

    columns = ["delta_theta", "value", "value_ci", "fd_slope", "fd_slope_ci"] + [
        c for n in names for c in (f"{n}_grad", f"{n}_ci")] + ([f"{rp}_variance"] if rp else []) + [
        "ftle_mean", "ftle_positive_fraction"]
    made_by = command(args)
    lines = [
        f"# The curse of chaos: {args.task}, {args.model} model",
        "",
        f"Command: `{made_by.text}`",
        "",
        *scenario_lib.model_labels(args.task, [args.model]),
        *scenario_lines,
        f"- theta = theta0 + delta d, d a fixed random unit direction; one fixed key draws the {args.particles} "
        "particles at every delta; intervals are 95 % (1.96 standard errors over particles). FTLE: finite-time "
        "Lyapunov exponent of the closed-loop particle map with the noise fixed, per control step "
        "(`harness.lyapunov`).",
        f"- Heatmaps: V(s1) = E[sum_t c(s_t) | s1] over ({dim_i}, {dim_j}) of the first state, the other dimensions at "
        f"the particles' mean, +-{args.box_stds:g} standard deviations of p(s1), each point the mean of "
        f"{args.slice_particles} fixed-seed particles.",
        "",
        f"![landscape]({os.path.basename(args.stem)}.png)",
        "",
        *findings(args, rows),
        rows[columns].to_markdown(index=False, floatfmt=".4g"),
        "",
    ]
    with open(args.stem + ".md", "w") as f:
        f.write("\n".join(lines))
    write_metadata(args.stem, made_by, str(rows.scenario.iloc[0]), objective)


def main(argv=None) -> None:
    args = parse(Args, argv)
    jax.config.update("jax_enable_x64", args.x64)
    rows, slices, where = run(args)
    by_model = {args.model: where}
    objective = scenario_lib.objective_values(by_model, args.seed)
    write_report(args, rows, slices, args.scenario_lines(by_model, rows, objective), objective)
    print(f"wrote {args.stem}.{{csv,md,png,json}}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
