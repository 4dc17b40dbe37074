"""A task's MuJoCo model (under MJX) against its reference equations over short horizons.

    python -m harness.mjx_agreement --task unicycle [--states 64] [--horizon 5]
        [--control-fractions 0,0.1,0.3,1] [--seed 0] [--out reports]

From ``states`` initial states drawn from the task's initial distribution, each with its own
random controls, uniform over ``fraction`` of their range and held for one control period each,
both models run ``horizon`` control steps: MJX (float64) and ``task.step``. Per fraction and
step k the report gives, over the states, the median absolute error of every ODE state
component and the largest error on any component, and counts the states whose MJX state is not
finite and those that have fallen under the equations (left out of the errors: past the fall the
equations describe no real unicycle). Per fraction it also counts the states whose reverse-mode gradient of
``sum_k |s_k|^2`` (the modelled states over the whole horizon) with respect to the initial state
and the controls is not finite. A model that only approximates the equations (``task.mjcf_label``)
is labelled so in the report.

Rows go to ``mjx_agreement_{task}.csv`` as each fraction finishes (a rerun resumes); the
markdown and metadata (``records.write_metadata``) beside it.
"""

from __future__ import annotations

import dataclasses
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

import tasks
from harness.cli import float_list, parse, run_command
from harness.records import Command, ResultTable, write_metadata

KEY_COLUMNS = ["task", "control_fraction", "step", "states", "seed"]


@dataclasses.dataclass(frozen=True)
class Args:
    """MuJoCo (MJX) model against the task's reference equations over short horizons."""

    task: str = "unicycle"
    """Task with a MuJoCo model (cartpole or unicycle)."""
    states: int = 64
    """Initial states drawn from the task's initial distribution."""
    horizon: int = 5
    """Control steps compared."""
    control_fractions: str = "0,0.1,0.3,1"
    """Comma-separated fractions of the control range for the random controls."""
    seed: int = 0
    """Seed of the states and controls."""
    out: str = "reports"
    """Folder for the CSV and markdown."""

    def __post_init__(self):
        task = tasks.make(self.task)  # fails with the list of tasks
        if task.mjcf is None:
            raise ValueError(f"task {self.task!r} has no MuJoCo model: nothing to compare")
        if self.states < 1 or self.horizon < 1:
            raise ValueError("--states and --horizon must be at least 1")
        if any(not 0.0 <= f <= 1.0 for f in float_list(self.control_fractions)):
            raise ValueError("--control-fractions must lie in [0, 1] (fractions of each control's range)")


def _trajectory(step, z, controls):
    """States after each control step: z (n,), controls (H, m) -> (H, n)."""
    return jax.lax.scan(lambda z, u: (step(z, u),) * 2, z, controls)[1]


def comparison_functions(task, mjx_step):
    """Jitted once per run, over a batch of states z0 (N, n) and controls (N, H, m):
    ``rollouts -> (mjx, ideal)`` states (N, H, n), and ``gradient_is_finite -> (N,)``, whether
    the MJX gradient of ``sum_k |s_k|^2`` w.r.t. (z0, controls) is finite."""

    def loss(z, us):
        return jnp.sum(jax.vmap(task.to_model_state)(_trajectory(mjx_step, z, us)) ** 2)

    def finite(z, us):
        g_z, g_u = jax.grad(loss, argnums=(0, 1))(z, us)
        return jnp.all(jnp.isfinite(g_z)) & jnp.all(jnp.isfinite(g_u))

    rollouts = jax.jit(jax.vmap(lambda z, us: (_trajectory(mjx_step, z, us), _trajectory(task.step, z, us))))
    return rollouts, jax.jit(jax.vmap(finite))


def measure(args: Args, fraction: float, functions) -> list[dict]:
    """The rows of one control fraction: one per step k = 1..horizon."""
    task = tasks.make(args.task)
    key_z, key_u = jax.random.split(jax.random.fold_in(jax.random.key(args.seed), round(1000 * fraction)))
    z0 = task.init_mean + task.init_std * jax.random.normal(key_z, (args.states, task.state_dim), jnp.float64)
    u_max = jnp.asarray(task.u_max, jnp.float64)
    controls = fraction * u_max * jax.random.uniform(
        key_u, (args.states, args.horizon, task.control_dim), jnp.float64, -1.0, 1.0)
    rollouts, gradient_is_finite = functions
    z_mjx, z_ideal = (np.asarray(z) for z in rollouts(z0, controls))
    grad_ok = np.asarray(gradient_is_finite(z0, controls))
    rows = []
    for k in range(args.horizon):
        finite = np.all(np.isfinite(z_mjx[:, k]), axis=1)
        fallen = np.asarray(jax.vmap(task.fallen)(z_ideal[:, k]))
        kept = finite & ~fallen
        err = np.abs(z_mjx[kept, k] - z_ideal[kept, k])
        row = dict(task=args.task, control_fraction=fraction, step=k + 1, states=args.states, seed=args.seed,
                   seconds=round((k + 1) * task.dt, 6), nan_states=int(np.sum(~finite)),
                   fallen_states=int(np.sum(fallen)), nan_gradients=int(np.sum(~grad_ok)))
        if err.size:
            worst = np.unravel_index(np.argmax(err), err.shape)[1]
            row.update(max_abs_error=float(err.max()), worst_component=task.state_names[worst])
        row.update({f"median_{name}": float(np.median(err[:, i])) if err.size else np.nan
                    for i, name in enumerate(task.state_names)})
        rows.append(row)
    return rows


def run(args: Args) -> pd.DataFrame:
    from tasks.mjx_dynamics import mjx_step_fn

    table = ResultTable(os.path.join(args.out, f"mjx_agreement_{args.task}.csv"), KEY_COLUMNS)
    task = tasks.make(args.task)
    functions = None
    for fraction in float_list(args.control_fractions):
        if table.has(dict(task=args.task, control_fraction=fraction, step=args.horizon, states=args.states,
                          seed=args.seed)):
            continue
        if functions is None:
            functions = comparison_functions(task, mjx_step_fn(task, jnp.float64))
        print(f"[mjx_agreement] {args.task}: controls up to {fraction:g} of their range, "
              f"{args.states} states, {args.horizon} steps (compiling MJX takes minutes)", file=sys.stderr, flush=True)
        for row in measure(args, fraction, functions):
            table.append(row)
    frame = table.read()
    return frame[(frame.states == args.states) & (frame.seed == args.seed) & (frame.step <= args.horizon)]


def command(args: Args) -> Command:
    """The command that makes this report (its rows reused): the markdown prints it, the metadata lists it."""
    return Command("harness.mjx_agreement", [
        "--task", args.task, "--states", str(args.states), "--horizon", str(args.horizon), "--control-fractions",
        args.control_fractions, "--seed", str(args.seed)])


def write_report(args: Args, frame: pd.DataFrame) -> None:
    """The markdown (settings, the per-fraction and step table) and the metadata (``records.write_metadata``: no
    scenario, no J)."""
    made_by = command(args)
    task = tasks.make(args.task)
    stem = os.path.join(args.out, f"mjx_agreement_{args.task}")
    medians = [f"median_{name}" for name in task.state_names]
    shown = ["control_fraction", "step", "seconds", "max_abs_error", "worst_component", *medians,
             "fallen_states", "nan_states", "nan_gradients"]
    frame = frame.sort_values(["control_fraction", "step"])
    label = task.mjcf_label or f"the MuJoCo model {os.path.basename(task.mjcf)}"
    lines = [
        f"# MuJoCo (MJX) model against the reference equations: {args.task}",
        "",
        f"**{label}.**" if task.mjcf_label else f"Model: {label}.",
        "",
        f"Command: `{made_by.text}`",
        "",
        f"- {args.states} initial states from the task's initial distribution; each gets random controls, "
        "uniform over the given fraction of every control's range, held for one control period each; "
        "MJX (float64) and the reference equations run from the same state under the same controls.",
        "- Errors are absolute, on the ODE state (rad, rad/s, m, m/s); medians over the states that the "
        "equations have not yet seen fall (`fallen_states`: the task's fall test on the equations' state) "
        "and whose MJX state is finite; "
        "`max_abs_error` is the largest over states and components, `worst_component` where it occurs.",
        "- `nan_states`: states whose MJX state is not finite at that step; `nan_gradients`: states whose "
        "reverse-mode gradient of the summed squared modelled states over the whole horizon, with respect "
        "to the initial state and the controls, is not finite.",
        "",
        frame[shown].to_markdown(index=False, floatfmt=".3g"),
        "",
    ]
    with open(stem + ".md", "w") as f:
        f.write("\n".join(lines))
    write_metadata(stem, made_by, None, [])


def main(argv=None) -> None:
    args = parse(Args, argv)
    jax.config.update("jax_enable_x64", True)
    frame = run(args)
    write_report(args, frame)
    print(f"wrote {os.path.join(args.out, f'mjx_agreement_{args.task}')}.{{csv,md,json}}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
