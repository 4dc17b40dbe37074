"""The curse-of-chaos scenario: a policy that works, checked against a rule fixed before its numbers.

    python -m harness.sweep --plan plans/chaos_scenario.toml     # the source run (hours; resumable)
    python -m harness.chaos [--plan plans/chaos_scenario.toml]   # check the rule, find the line, write the report

The plan (``plans/chaos_scenario.toml``) states the rule: theta0 and the GP are the final state of one
learning run at the k = 1 table's settings (kept by ``harness.learn --keep-final``); J under the GP at theta0
must be at most ``max_cost``, and RP's gradient variance at delta theta = 0 at most LR's. The line is the
scenario's fixed random unit direction d (``harness.scenario.unit_direction``, the seed's "direction" stream);
delta theta = 1, 2, 4, ... until J(theta0 + delta d) exceeds ``extend_until_cost``. J and the variances use
``particles`` particles: J one fixed key (the seed fixed, as the paper's landscape), each variance the trace of
the covariance of ``VARIANCE_REPEATS`` estimates with independent keys (``harness.variance``).

Writes ``{out}/chaos_scenario.md``: the rule, quoted from the plan, then the numbers, the verdict, and the
commands of the landscape and variance reports at the scenario (or, if the rule fails, the repeat to try next);
and ``{out}/chaos_scenario.json``, the same numbers and those commands' arguments as plain data
(``harness.summary`` reads it, and the reports the commands wrote).
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
import tomllib

import jax
import numpy as np

import estimators
from harness import keys, learn, sweep, variance
from harness import scenario as scenario_lib
from harness.cli import parse, run_command
from harness.records import ROOT

SCHEMA_VERSION = 2
"""Version of chaos_scenario.json's layout (2: "reports", the reports' arguments by module, where the rule holds)."""
VARIANCE_REPEATS = 30
"""Estimates behind each variance of the rule (``harness.variance``'s default repeats)."""
MAX_DOUBLINGS = 12
"""The line stops at delta theta = 2^12 if J never exceeds the plan's cost: the report says so."""


@dataclasses.dataclass(frozen=True)
class Args:
    """Check the curse-of-chaos scenario's rule at its source run's final state and find its line."""

    plan: str = os.path.join(ROOT, "plans", "chaos_scenario.toml")
    """The plan holding the rule ([theta0], [line], [landscape]) and the source run ([settings], [[cells]])."""
    seed: int = 0
    """Seed of the direction and the estimates' keys (the gradient reports' --seed)."""
    out: str = "reports"
    """Folder of chaos_scenario.md."""


def source_file(plan_path: str, rule: dict) -> str:
    """The final-state file of the rule's method and repeat in the plan's source run."""
    units = [u for u in sweep.load_plan(plan_path) if u.method == rule["method"] and rule["repeat"] in u.repeats]
    if not units:
        raise ValueError(f"{plan_path}: no unit of its [[cells]] runs {rule['method']} repeat {rule['repeat']}")
    unit_args = units[0].learn_args()
    if not unit_args.keep_final:
        raise ValueError(f"{plan_path}: its source run must keep its final state (keep_final = true in [settings])")
    return learn.final_state_path(unit_args, rule["method"], rule["repeat"])


particle_returns = jax.jit(scenario_lib.particle_returns, static_argnums=3)
"""Compiled once for every point of the line."""


def objective(problem, theta, key, num_particles: int) -> float:
    """J: the mean particle return under one fixed key."""
    return float(np.mean(np.asarray(particle_returns(problem, theta, key, num_particles))))


def line_extent(where: scenario_lib.Setting, key, num_particles: int, above: float) -> tuple[list, bool]:
    """[(delta, J)] at delta = 0, 1, 2, 4, ... up to the first J above ``above`` (or 2^MAX_DOUBLINGS);
    and whether J got there."""
    points = [(0.0, objective(where.problem, where.theta(0.0), key, num_particles))]
    for power in range(MAX_DOUBLINGS + 1):
        delta = float(2**power)
        points.append((delta, objective(where.problem, where.theta(delta), key, num_particles)))
        if points[-1][1] > above:
            return points, True
    return points, False


REPORTS_OUT = "reports/chaos"
"""Folder of the landscape and variance reports at the scenario."""


def report_commands(path: str, seed: int, particles: int, delta_max: float, line: dict, landscape: dict
                    ) -> dict[str, list[str]]:
    """The arguments of the landscape and variance reports at the scenario (file ``path``), by module name."""
    flags = ["--scenario-file", path, "--seed", str(seed)]
    return {"landscape": [*flags, "--particles", str(particles), "--delta-max", f"{delta_max:g}", "--points",
                          str(line["points"]), "--box-stds", f"{landscape['heatmap_box_side_sd']:g}", "--estimators",
                          "rp_fs,gr_fs,lr,tp", "--out", REPORTS_OUT],
            "variance": [*flags, "--delta-theta", f"0,{delta_max:g}", "--estimators", "rp,gr,lr,lr_is_baseline,tp",
                         "--out", REPORTS_OUT]}


def check(args: Args) -> tuple[list[str], dict]:
    """The report's lines and its numbers (module docstring)."""
    with open(args.plan, "rb") as f:
        plan = tomllib.load(f)
    rule, line, landscape = plan["theta0"], plan["line"], plan["landscape"]
    path = source_file(args.plan, rule)
    task = plan["cells"][0]["task"]
    experiment = scenario_lib.ExperimentArgs(task=task, seed=args.seed, scenario_file=path)
    where = scenario_lib.setting(experiment, "gp")
    particles = int(landscape["particles"])
    key = keys.stream(jax.random.key(args.seed), "estimates")
    print(f"chaos: J along the line ({particles} particles) ...", file=sys.stderr, flush=True)
    points, reached = line_extent(where, keys.stream(jax.random.key(args.seed), "objective"), particles,
                                  float(line["extend_until_cost"]))
    cost0 = points[0][1]
    variances = {}
    for name in ("rp", rule["rp_variance_at_most"]):
        print(f"chaos: {name}'s variance at delta theta = 0 ({VARIANCE_REPEATS} estimates) ...", file=sys.stderr,
              flush=True)
        estimates = variance.repeated_estimates(estimators.make(name), where.problem, where.theta(0.0), particles,
                                                VARIANCE_REPEATS, key)
        variances[name] = variance.cell_statistics(estimates)["variance"]
    low_cost = cost0 <= float(rule["max_cost"])
    calm = variances["rp"] <= variances[rule["rp_variance_at_most"]]
    with open(args.plan) as f:
        rule_text = [f"    {text}" for text in f.read().splitlines()]
    lines = ["# The curse-of-chaos scenario on the cart-pole", "",
             f"Command: `python -m harness.chaos --plan {os.path.relpath(args.plan, ROOT)} --seed {args.seed}`", "",
             "## The rule, fixed before these numbers", "", *rule_text, "",
             "## At the source run's final state", "",
             f"- Scenario: {where.source}; content hash {where.content}.",
             f"- J under the GP at theta0 ({particles} particles, one key): {cost0:.2f} (the rule: at most "
             f"{rule['max_cost']:g}): {'met' if low_cost else 'NOT met'}.",
             f"- Gradient variance at delta theta = 0 (trace of the covariance of {VARIANCE_REPEATS} estimates, "
             f"P = {particles}): RP {variances['rp']:.3e}, {rule['rp_variance_at_most'].upper()} "
             f"{variances[rule['rp_variance_at_most']]:.3e} (the rule: RP's at most): {'met' if calm else 'NOT met'}.",
             f"- J along the line: {'; '.join(f'{j:.2f} at {d:g}' for d, j in points)}"
             + ("" if reached else f" (never above {line['extend_until_cost']:g} up to delta theta = "
                                   f"{points[-1][0]:g})") + ".", ""]
    numbers = dict(schema_version=SCHEMA_VERSION, plan=os.path.relpath(args.plan, ROOT), method=rule["method"],
                   repeat=rule["repeat"], source=where.source, content=where.content, particles=particles,
                   cost=cost0, max_cost=float(rule["max_cost"]), variance=variances,
                   line=[dict(delta=d, cost=j) for d, j in points], line_reaches=reached,
                   holds=bool(low_cost and calm and reached))
    if numbers["holds"]:
        numbers["reports"] = report_commands(os.path.relpath(path, ROOT), args.seed, particles, points[-1][0],
                                             line, landscape)
        lines += ["**The rule holds: this is the scenario.** Its reports:", "",
                  *(f"    python -m harness.{name} {' '.join(argv)}" for name, argv in numbers["reports"].items()), ""]
    else:
        lines += [f"**The rule fails at repeat {rule['repeat']}.** As the plan says, the next repeat of the same "
                  f"table is taken: set repeat = {rule['repeat'] + 1} in [theta0] and repeats = "
                  f"{{ {rule['method']} = {rule['repeat'] + 2} }} in [[cells]], then rerun the sweep and this "
                  "command.", ""]
    return lines, numbers


def main(argv=None) -> None:
    args = parse(Args, argv)
    jax.config.update("jax_enable_x64", True)
    lines, numbers = check(args)
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "chaos_scenario.md"), "w") as f:
        f.write("\n".join(lines))
    with open(os.path.join(args.out, "chaos_scenario.json"), "w") as f:
        json.dump(numbers, f, indent=1, sort_keys=True)
    print("\n".join(lines[-6:]), file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
