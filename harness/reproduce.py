"""Recompute the committed reports at a small size and compare their key numbers.

    python -m harness.reproduce [--checks variance_cartpole_gp,...|all] [--reports reports] [--out DIR]

Each check reruns one committed report's own command (the ``command`` of its metadata,
``{stem}.json``, ``records.write_metadata``; for a learning table, the ``harness.learn`` command
its rows were made with) at the smaller
sizes listed in ``CHECKS``, into a fresh folder, then compares key numbers, committed against
recomputed, each by a stated rule:

- scenario: the content hash of theta0, the direction and the GP posterior is equal (the
  commands load the pinned scenario, so this checks the pinned file and the direction's draw;
  a rebuild is not reproducible across machines);
- a mean with a 95 % half-width (J, a slope, a directional derivative, a cosine): the two
  agree when ``|a - b| <= sqrt(ci_a^2 + ci_b^2)``, the 95 % interval of the difference of two
  independent means;
- a gradient variance from R_c (committed) and R_r (recomputed) estimates: the ratio
  recomputed / committed lies in the central 95 % of F(R_r - 1, R_c - 1), its distribution
  for independent normal estimates of one scalar (a trace over many parameters has more
  degrees of freedom, so this interval is the widest one). The experiments draw estimate r
  with key ``fold_in(key, r)``, so the recomputed estimates are the committed cell's first
  R_r: a subsample, which makes the rule conservative for normal estimates; a heavy-tailed
  estimator whose committed variance comes from one outlier among the others can still fall
  below the interval;
- a learning run (same seed and settings): the final cost is on the same side of the
  committed table's success threshold; a success rate: the committed rate lies inside the
  Wilson interval of the recomputed one.

Writes ``reproduce.{csv,md}`` under ``--out`` (default: a new temporary folder) and prints the
table: report, quantity, committed, recomputed, rule, agrees.
"""

from __future__ import annotations

import dataclasses
import importlib
import os
import re
import shlex
import sys
import tempfile
import time
from typing import Callable, NamedTuple

import numpy as np
import pandas as pd
from scipy import stats

import tasks
from harness.cli import flag_values, parse, run_command, str_list, with_flags
from harness.records import Command, read_csv, read_metadata
from harness.success import final_evaluations, otsu_thresholds, wilson_interval


class Check(NamedTuple):
    """How one committed report is recomputed: ``resize`` replaces the command's flags (the
    small size), ``compare(committed_stem, recomputed_stem, flags)`` returns the rows."""

    resize: dict[str, str]
    compare: Callable[[str, str, dict[str, str]], list[dict]]


def mean_rule(name: str, a: float, ci_a: float, b: float, ci_b: float) -> dict:
    """A row comparing two means with 95 % half-widths: agree if their difference lies inside
    the 95 % interval of a difference of independent means."""
    bound = float(np.hypot(ci_a, ci_b))
    return dict(quantity=name, committed=f"{a:.4g} +- {ci_a:.2g}", recomputed=f"{b:.4g} +- {ci_b:.2g}",
                rule=f"|diff| <= {bound:.2g}", agrees=bool(abs(a - b) <= bound))


def variance_rule(name: str, committed: float, repeats_c: int, recomputed: float, repeats_r: int) -> dict:
    """A row comparing two variance estimates by the F interval of their ratio."""
    low, high = stats.f.ppf([0.025, 0.975], repeats_r - 1, repeats_c - 1)
    ratio = recomputed / committed
    return dict(quantity=name, committed=f"{committed:.4g} (R={repeats_c})", recomputed=f"{recomputed:.4g} "
                f"(R={repeats_r})", rule=f"ratio {ratio:.2f} in [{low:.2f}, {high:.2f}]",
                agrees=bool(low <= ratio <= high))


def metadata(stem: str) -> dict:
    """The committed report's metadata, ``{stem}.json`` (``records.read_metadata``); where it is missing, a
    ValueError with the command that writes it: the report's own, which reuses its committed rows."""
    if not os.path.exists(stem + ".json"):
        shown = []
        if os.path.exists(stem + ".md"):
            with open(stem + ".md") as f:
                shown = [line.split("`")[1] for line in f if line.startswith("Command: `")]
        rerun = (f"{shown[0]} --out {shlex.quote(os.path.dirname(stem) or '.')}" if shown
                 else f"the command on the Command: line of {stem}.md")
        raise ValueError(f"{stem}.json is missing: write it with the report's own command, which reuses the "
                         f"committed rows: {rerun}")
    return read_metadata(stem + ".json")


def scenario_and_objective(committed: str, recomputed: str) -> list[dict]:
    """The content-hash row and one row per J that both reports' metadata hold (same model and delta theta)."""
    old, new = metadata(committed), metadata(recomputed)
    rows = [dict(quantity="scenario content hash", committed=old["scenario"] or "(none)",
                 recomputed=new["scenario"] or "(none)", rule="equal",
                 agrees=bool(old["scenario"] and old["scenario"] == new["scenario"]))]
    recomputed_j = {(j["model"], j["delta_theta"]): j for j in new["objective"]}
    for c in old["objective"]:
        if (r := recomputed_j.get((c["model"], c["delta_theta"]))) is not None:
            rows.append(mean_rule(f"J on {c['model']}, delta theta {c['delta_theta']:g}", c["value"], c["ci"],
                                  r["value"], r["ci"]))
    return rows


def committed_rows(stem: str) -> pd.DataFrame:
    """The committed CSV's rows that its report shows: those with its command's settings (of
    seed, repeats, reference, fd_step, estimators and a single particle count: the ones the
    CSV has as columns; defaults where the command leaves a flag out) and its scenario (any,
    where the metadata names none)."""
    rows = read_csv(stem + ".csv")
    meta = metadata(stem)
    command = Command(**meta["command"])
    tool = parse(importlib.import_module(command.module).Args, command.argv)
    settings = {column: getattr(tool, attribute, None) for column, attribute in (
        ("seed", "seed"), ("repeats", "repeats"), ("reference", "reference_name"), ("fd_step", "fd_step"),
        ("estimators", "estimators"), ("particles", "particles"))}
    for column, value in settings.items():
        if column in rows and value is not None and (column != "particles" or isinstance(value, int)):
            rows = rows[rows[column] == value]
    return rows[rows.scenario == meta["scenario"]] if meta["scenario"] else rows


def nothing_to_compare(what: str) -> list[dict]:
    """The row that says a check found no committed row matching a recomputed one."""
    return [dict(quantity=what, committed="-", recomputed="-", rule="rows with the same key", agrees=False)]


def compare_cells(committed: str, recomputed: str, flags: dict[str, str]) -> list[dict]:
    """Scenario, J, and each recomputed cell's variance (and, in a compare report, cosine with
    the reference gradient) against the committed cell's."""
    old, new = committed_rows(committed), read_csv(recomputed + ".csv")
    rows = scenario_and_objective(committed, recomputed)
    keys = ["model", "estimator", "particles"] + (["delta_theta"] if "delta_theta" in new else [])
    if old.duplicated(keys).any():
        raise ValueError(f"{committed}.csv has several rows per cell {keys} at its report's settings: "
                         "say which its report shows (committed_rows)")
    merged = old.merge(new, on=keys, suffixes=("_c", "_r"))
    if merged.empty:
        return rows + nothing_to_compare("cells")
    for _, cell in merged.iterrows():
        where = ", ".join(f"{k} {cell[k]}" for k in keys)
        rows.append(variance_rule(f"variance: {where}", cell.variance_c, int(cell.repeats_c), cell.variance_r,
                                  int(cell.repeats_r)))
        if "cosine_c" in cell:
            rows.append(mean_rule(f"cosine with g*: {where}", cell.cosine_c, cell.cosine_ci_c, cell.cosine_r,
                                  cell.cosine_ci_r))
    return rows


def compare_landscape(committed: str, recomputed: str, flags: dict[str, str]) -> list[dict]:
    """Scenario, J, and per recomputed delta: J, the finite-difference slope and each
    estimator's directional derivative against the committed ones."""
    old, new = committed_rows(committed), read_csv(recomputed + ".csv")
    rows = scenario_and_objective(committed, recomputed)
    quantities = [("value", "value_ci"), ("fd_slope", "fd_slope_ci")] + [
        (f"{name}_grad", f"{name}_ci") for name in str_list(flags["--estimators"])]
    merged = old.assign(delta=old.delta_theta.round(6)).merge(new.assign(delta=new.delta_theta.round(6)), on="delta",
                                                             suffixes=("_c", "_r"))
    if merged.empty:
        return rows + nothing_to_compare("deltas")
    for _, cell in merged.iterrows():
        for value, ci in quantities:
            rows.append(mean_rule(f"{value} at delta theta {cell.delta:g}", cell[value + "_c"], cell[ci + "_c"],
                                  cell[value + "_r"], cell[ci + "_r"]))
    return rows


LEARN_STEM = re.compile(r"learn_(\w+?)_(\w+)_k([\d.e+-]+?)(?:_(quick_p50|quick))?$")


def learn_command(stem: str, methods: str, repeats: int) -> tuple[list[str], pd.DataFrame]:
    """The ``harness.learn`` arguments that recompute ``repeats`` repeats of ``methods`` of
    the committed table at ``stem`` (its task, cost, k, preset and task options), and the
    committed rows they should reproduce."""
    task, cost, k, preset = LEARN_STEM.search(os.path.basename(stem)).groups()
    rows = read_csv(stem + ".csv")
    rows = rows[rows.method.isin(str_list(methods)) & (rows.repeat < repeats)]
    if rows.empty:
        raise ValueError(f"{stem}.csv has no rows of {methods} to reproduce")
    committed_options = dict(item.split("=", 1) for item in rows.task_options.iloc[0].split(","))
    today = tasks.describe(tasks.make(task, cost=cost, noise_k=float(k)))
    default = dict(item.split("=", 1) for item in today.split(","))
    changed = ",".join(f"{name}={value}" for name, value in committed_options.items() if default.get(name) != value)
    argv = ["--task", task, "--cost", cost, "--noise-k", k, "--preset", preset or "paper", "--methods", methods,
            "--repeats", str(repeats), "--batch", str(repeats)] + (["--task-options", changed] if changed else [])
    return argv, rows


def compare_learning(committed: str, recomputed: str, flags: dict[str, str]) -> list[dict]:
    """Each recomputed run's final cost against the committed run of the same seed (same side
    of the committed threshold), and the committed rate inside the recomputed Wilson interval."""
    everything = read_csv(committed + ".csv")
    final_all = final_evaluations(everything)
    thresholds = otsu_thresholds(final_all)  # the committed report's cut (invalid runs not pooled)
    if len(thresholds) != 1:
        raise ValueError(f"{committed}.csv has {len(thresholds)} success thresholds (cost scales "
                         f"{sorted(thresholds)}); reproduce compares a learning table with one")
    [threshold] = thresholds.values()
    new = final_evaluations(read_csv(recomputed + ".csv"))
    old = final_all[final_all.method.isin(new.method.unique())]
    keys = ["method", "repeat", "settings", "task_options"]
    merged = old.merge(new, on=keys, suffixes=("_c", "_r"))
    if merged.empty:
        return nothing_to_compare("learning runs (same method, repeat, settings, task options)")
    rows = []
    for _, run in merged.iterrows():
        same_side = (run.eval_mean_c < threshold) == (run.eval_mean_r < threshold)
        rows.append(dict(quantity=f"{run.method} repeat {run['repeat']}: final cost",
                         committed=f"{run.eval_mean_c:.2f}", recomputed=f"{run.eval_mean_r:.2f}",
                         rule=f"same side of {threshold:.2f}",
                         agrees=bool(same_side)))
    for method, group in new.groupby("method"):
        committed_group = old[(old.method == method) & old.settings.isin(group.settings)]
        rate_c = float((committed_group.eval_mean < threshold).mean())
        wins = int((group.eval_mean < threshold).sum())
        low, high = wilson_interval(wins, len(group))
        rows.append(dict(quantity=f"{method}: success rate", committed=f"{rate_c:.2f} (n={len(committed_group)})",
                         recomputed=f"{wins / len(group):.2f} (n={len(group)})", rule=f"inside [{low:.2f}, {high:.2f}]",
                         agrees=bool(low <= rate_c <= high)))
    return rows


EXPERIMENT = {"--particles": "10,100", "--repeats": "10"}
LANDSCAPE = {"--particles": "300", "--points": "4", "--slice-deltas": ""}
CHECKS = {
    "variance_cartpole_gp": Check(EXPERIMENT, compare_cells),
    "landscape_cartpole_gp": Check(LANDSCAPE, compare_landscape),
    "compare_cartpole": Check(EXPERIMENT, compare_cells),
    "learn_cartpole_angle_k1_quick_p50": Check({"--methods": "pilco", "--repeats": "2"}, compare_learning),
    "variance_unicycle_gp": Check(EXPERIMENT, compare_cells),
    "landscape_unicycle_gp": Check(LANDSCAPE, compare_landscape),
    "compare_unicycle": Check(EXPERIMENT, compare_cells),
}
"""Committed report -> its small size and comparison. Every variance and compare cell at
P = 10 and 100 with 10 estimates (the committed: 20-30); landscape J, slope and directional
derivatives at 4 of its deltas with 300 particles (the committed: 1000); the learning table's
PILCO runs of seeds 0 and 1. Not checked: timings (``bench``: machine-dependent), tables
whose report is made by hand from several runs (the conventions grid), MJX agreement."""
DEFAULT_CHECKS = "variance_cartpole_gp,landscape_cartpole_gp,compare_cartpole,learn_cartpole_angle_k1_quick_p50"


@dataclasses.dataclass(frozen=True)
class Args:
    """Recompute committed reports at a small size and compare their key numbers."""

    checks: str = DEFAULT_CHECKS
    """Comma-separated reports to check (reproduce.CHECKS), or all."""
    reports: str = "reports"
    """Folder of the committed reports."""
    out: str = ""
    """Folder for the recomputed reports and reproduce.{csv,md} (empty: a new temporary folder)."""

    def __post_init__(self):
        unknown = [name for name in self.names if name not in CHECKS]
        if unknown:
            raise ValueError(f"unknown check(s) {unknown}; valid: {sorted(CHECKS)} or all")

    @property
    def names(self) -> list[str]:
        return list(CHECKS) if self.checks == "all" else str_list(self.checks)


def recompute(name: str, args: Args, out: str) -> tuple[str, dict[str, str]]:
    """Run the check's command at its small size into ``out``; returns the module's command
    line and its flags."""
    committed = os.path.join(args.reports, name)
    check = CHECKS[name]
    if name.startswith("learn_"):
        argv, _ = learn_command(committed, check.resize["--methods"], int(check.resize["--repeats"]))
        module = "harness.learn"
    else:
        module, argv = Command(**metadata(committed)["command"])
        argv = with_flags(argv, check.resize)
    argv = with_flags(argv, {"--out": out})
    print(f"reproduce {name}: python -m {module} {shlex.join(argv)}", file=sys.stderr, flush=True)
    importlib.import_module(module).main(argv)
    return f"python -m {module} {shlex.join(argv)}", flag_values(argv)


def run(args: Args) -> pd.DataFrame:
    """Every check of ``args`` in turn (writing ``reproduce.csv`` after each); returns the table
    and writes ``reproduce.md`` with the commands run and how many quantities agree. A report without its
    metadata fails before anything is computed."""
    for name in args.names:
        if not name.startswith("learn_"):
            metadata(os.path.join(args.reports, name))
    out = args.out or tempfile.mkdtemp(prefix="reproduce_")
    rows, commands = [], []
    for name in args.names:
        start = time.perf_counter()
        command, flags = recompute(name, args, out)
        found = CHECKS[name].compare(os.path.join(args.reports, name), os.path.join(out, name), flags)
        rows += [dict(report=name, **row) for row in found]
        commands.append(f"- `{name}` ({time.perf_counter() - start:.0f} s): `{command}`")
        pd.DataFrame(rows).to_csv(os.path.join(out, "reproduce.csv"), index=False)
    table = pd.DataFrame(rows)
    agree = int(table.agrees.sum())
    lines = ["# Reproduction of the committed reports at a small size", "",
             f"Command: `python -m harness.reproduce --checks {','.join(args.names)} --reports {args.reports}`", "",
             "Rules: see `harness/reproduce.py`. Recomputed with:", "", *commands, "",
             f"{agree} of {len(table)} quantities agree.", "", table.to_markdown(index=False), ""]
    with open(os.path.join(out, "reproduce.md"), "w") as f:
        f.write("\n".join(lines))
    print(table.to_markdown(index=False))
    print(f"{agree} of {len(table)} agree; wrote {out}/reproduce.{{csv,md}}", file=sys.stderr)
    return table


def main(argv=None) -> None:
    run(parse(Args, argv))


if __name__ == "__main__":
    run_command(main)
