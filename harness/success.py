"""The statistics of success in the learning CSV (``harness.learn``): the rates that ``harness.claims``
judges and ``harness.learn_report`` writes.

Success: the final learned trial's evaluation (mean cost of ``eval_runs`` real runs) is below a
threshold chosen from the pooled distribution of final evaluations of every method, k and
repeat in the table under one cost scale (``THRESHOLD_KEYS``): the cut that minimises the
within-group variance of the two groups it makes (Otsu's rule; where learning either swings the
pole up or does not, the final costs are bimodal and the cut falls in the gap). Rates carry
Wilson 95 % intervals (``success_rows``: per task, cost, k and method the rate, its interval, the
paper's rate and whether that lies inside the interval) and are recomputed at the threshold
x (1 -+ ``ROBUSTNESS``) by ``rates_at_scales``; ``compute_hours`` gives the compute time per method.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

from harness.methods import INVALID as INVALID_METHODS
from harness.methods import METHODS, READINGS, paper_rate


Z95 = float(stats.norm.ppf(0.975))
"""1.95996...: the two-sided 95 % normal quantile of the Wilson interval."""
ROBUSTNESS = 0.1
"""Every rate is recomputed at the threshold x (1 - ROBUSTNESS) and x (1 + ROBUSTNESS)."""
SCALES = (1 - ROBUSTNESS, 1.0, 1 + ROBUSTNESS)


def otsu_threshold(values: np.ndarray) -> float:
    """The cut between sorted values that minimises the summed within-group variance; non-finite
    values (a run whose evaluation diverged: a failure at any cut) take no part."""
    v = np.asarray(values, float)
    v = np.sort(v[np.isfinite(v)])
    if len(v) < 2 or v[0] == v[-1]:
        return float(v[-1]) if len(v) else np.nan
    costs = [np.var(v[:i]) * i + np.var(v[i:]) * (len(v) - i) for i in range(1, len(v))]
    i = int(np.argmin(costs)) + 1
    return float(0.5 * (v[i - 1] + v[i]))


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """Wilson score 95 % interval of a binomial proportion."""
    if n == 0:
        return np.nan, np.nan
    p = successes / n
    centre = (p + Z95**2 / (2 * n)) / (1 + Z95**2 / n)
    half = Z95 * np.sqrt(p * (1 - p) / n + Z95**2 / (4 * n**2)) / (1 + Z95**2 / n)
    # exact ends where every run failed or learned (round-off would leave them a few ulps inside 0 or 1)
    return (0.0 if successes == 0 else centre - half), (1.0 if successes == n else centre + half)


OPTIONS_IN_COLUMNS = ("noise_k", "cost_type")
"""Task options that are columns of their own (``noise_k``, ``cost``): never part of a label."""
COST_SCALE_OPTIONS = ("preset", "dt", "horizon", "angle_cost_scale")
"""Task options that change the cost of the same trajectory: final costs under different values
of these are not pooled for a threshold."""


def with_labels(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` with ``options``, the task options (other than ``OPTIONS_IN_COLUMNS``) that differ
    between the file's runs (``" [angle_cost_scale=1.0,...]"``, "" when none do), ``label``, the
    method followed by them, and ``scale``, those of them in ``COST_SCALE_OPTIONS``."""
    parsed = rows.task_options.astype(str).map(lambda text: dict(item.split("=", 1) for item in text.split(",")))
    names = sorted({name for opts in parsed for name in opts} - set(OPTIONS_IN_COLUMNS))
    varying = [name for name in names if len({opts.get(name) for opts in parsed}) > 1]

    def suffix(names):
        return parsed.map(lambda opts: " [" + ",".join(f"{n}={opts.get(n)}" for n in names) + "]" if names else "")

    options = suffix(varying)
    return rows.assign(options=options, label=rows.method + options,
                       scale=suffix([name for name in varying if name in COST_SCALE_OPTIONS]))


EXPERIMENT = ["task", "cost", "noise_k", "task_options", "label", "settings", "repeat", "seed"]
"""The columns that name one experiment (one repeat of one method under one set of settings)."""


def final_evaluations(rows: pd.DataFrame) -> pd.DataFrame:
    """Per experiment (``EXPERIMENT``): its last learned trial's row, whole. Experiments with
    fewer learned trials than their settings name (``complete``) are left out."""
    learned = with_labels(rows[rows.learned.astype(bool)])
    learned = learned[complete(learned)]
    return learned.sort_values("trial", kind="stable").drop_duplicates(EXPERIMENT, keep="last").reset_index(drop=True)


def complete(learned: pd.DataFrame) -> pd.Series:
    """Whether each row's experiment has as many learned trials as its ``settings`` name
    (``learned_trialsN``; settings without that count pass): not so for a batch whose rows
    were cut off while being written."""
    wanted = learned.settings.astype(str).str.extract(r"learned_trials(\d+)", expand=False).astype(float)
    trials = learned.groupby(EXPERIMENT).trial.transform("nunique")
    return wanted.isna() | (trials >= wanted)


def column_order(labels) -> list[str]:
    """Labels in the paper's column order (``harness.methods.METHODS``), then any others."""
    rank = {method: i for i, method in enumerate(METHODS)}
    return sorted(labels, key=lambda label: (rank.get(label.split(" [")[0], len(rank)), label))


THRESHOLD_KEYS = ["task", "cost", "scale"]
"""A threshold per cost scale (``with_labels``: the ``COST_SCALE_OPTIONS`` that vary)."""


def otsu_thresholds(final: pd.DataFrame) -> dict:
    """Otsu's threshold of the pooled final evaluation costs per (task, cost, scale), every k and method
    but those of ``INVALID_METHODS`` (kept for the record, they must not move the valid rates' cut) and
    ``harness.methods.READINGS`` (judged at the table's cut), unless a group holds nothing else (a file of
    readings, or of superseded runs, is cut on its own costs)."""
    return {key: otsu_threshold(pooled_rows(group).eval_mean.to_numpy())
            for key, group in final.groupby(THRESHOLD_KEYS)}


def pooled_rows(group: pd.DataFrame) -> pd.DataFrame:
    """The final rows of one threshold group whose costs make its cut (``otsu_thresholds``)."""
    for left_out in (list(INVALID_METHODS) + list(READINGS), list(INVALID_METHODS)):
        kept = group[~group.method.isin(left_out)]
        if len(kept):
            return kept
    return group


def inside(paper: float, low: float, high: float) -> str:
    """'yes' where the paper's rate lies in [low, high], 'no' where not, '-' where the paper has none."""
    if np.isnan(paper):
        return "-"
    return "yes" if low <= paper <= high else "no"


def success_rows(rows: pd.DataFrame, scale: float = 1.0) -> pd.DataFrame:
    """One row per (task, cost, k, label), in the paper's method order: its ``method``, ``options``
    (the label's task options suffix), successes ``wins`` (final evaluation cost below ``scale`` x Otsu's threshold of
    the task and cost), ``n`` repeats, ``rate``, its Wilson 95 % ``low`` and ``high``, the ``paper``'s
    rate (for a reading, that of the paper's method it reads: ``harness.methods.paper_rate``; NaN where it has
    none) and ``inside`` (whether that lies in the interval)."""

    final = final_evaluations(rows)
    thresholds = otsu_thresholds(final)
    cells = []
    for (task, cost, cut, k, label), group in final.groupby(THRESHOLD_KEYS + ["noise_k", "label"]):
        method, options = group.method.iloc[0], group.options.iloc[0]  # the label is the method and options
        wins, n = int((group.eval_mean < scale * thresholds[(task, cost, cut)]).sum()), len(group)
        low, high = wilson_interval(wins, n)
        paper = paper_rate(method, task, cost, k)
        cells.append(dict(task=task, cost=cost, k=float(k), label=label, method=method, options=options,
                          wins=wins, n=n, rate=wins / n, low=low, high=high, paper=paper,
                          inside=inside(paper, low, high), paper_p=paper_p(wins, n, paper)))
    table = pd.DataFrame(cells)
    rank = table.label.map({label: i for i, label in enumerate(column_order(table.label.unique()))})
    table = table.assign(rank=rank).sort_values(["task", "cost", "k", "rank"])
    return table.drop(columns="rank").reset_index(drop=True)


PAPER_REPEATS = 100
"""Repeats behind each of the paper's rates."""


def paper_p(wins: int, n: int, paper: float) -> float:
    """Two-sided Fisher exact p-value of our ``wins`` of ``n`` against the paper's rate as
    ``PAPER_REPEATS`` repeats (the paper's own sampling error counted; NaN where it has none)."""
    if np.isnan(paper):
        return np.nan
    theirs = round(paper * PAPER_REPEATS)
    return float(stats.fisher_exact([[wins, n - wins], [theirs, PAPER_REPEATS - theirs]])[1])


def interval_text(row) -> str:
    """'rate [low, high]' of a ``success_rows`` row."""
    return f"{row.rate:.2f} [{row.low:.2f}, {row.high:.2f}]"


def success_table(rows: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    """Rows (task, cost, k), columns methods: 'rate [low, high] n=N (paper p)'; and the
    threshold per (task, cost)."""
    success = success_rows(rows)
    text = success.apply(lambda row: f"{interval_text(row)} n={row.n}"
                         + ("" if np.isnan(row.paper) else f" (paper {row.paper:.2f})"), axis=1)
    table = success.assign(text=text).pivot(index=["task", "cost", "k"], columns="label", values="text")
    return table[column_order(table.columns)], otsu_thresholds(final_evaluations(rows))


def rates_at_scales(rows: pd.DataFrame) -> dict[float, pd.DataFrame]:
    """``success_rows`` at the threshold x every scale of ``SCALES``, indexed by (task, cost, k, label)."""
    return {scale: success_rows(rows, scale).set_index(["task", "cost", "k", "label"]) for scale in SCALES}


def fisher_p(a, b) -> float:
    """Two-sided Fisher exact p-value of equal success rates of two ``success_rows`` rows."""
    return float(stats.fisher_exact([[a.wins, a.n - a.wins], [b.wins, b.n - b.wins]])[1])


def retained_fraction_p(a_first, a_last, b_first, b_last) -> float:
    """Two-sided p-value of equal fractions of the rate kept from the smallest to the largest k
    (``a_last / a_first`` against ``b_last / b_first``, four independent ``success_rows`` rows): a
    Wald z-test of the difference of the log ratios (delta method: var log p = (1 - p) / (n p)),
    each rate adjusted by one success and one failure (Agresti and Caffo), so that rates of 0 or
    1 keep a finite log and a variance."""
    rates = [((r.wins + 1) / (r.n + 2), r.n + 2) for r in (a_first, a_last, b_first, b_last)]
    logs = [np.log(p) for p, _ in rates]
    difference = (logs[1] - logs[0]) - (logs[3] - logs[2])
    sd = np.sqrt(sum((1 - p) / (n * p) for p, n in rates))
    return float(2 * stats.norm.sf(abs(difference) / sd))


def compute_hours(rows: pd.DataFrame) -> pd.DataFrame:
    """Per label, and in total: ``repeats``, ``hours`` and ``hours per repeat`` of compute.

    ``harness.learn`` runs a method's repeats in batches, vmapped together, and writes on every
    repeat's row of a trial the same ``seconds``: the wall time since the batch began (carried
    over a resume; the time between an interruption and its rerun is not in it). So a batch's
    time is its last trial's ``seconds``, repeated on each of its repeats' rows: summing rows
    would count it once per trial and repeat. A batch is recognised by the clock of its first
    trial, the same on all its repeats' rows and on no other batch's, and each batch's time (its
    largest ``seconds``) is counted once. Hours per repeat = hours / repeats: the repeats of a batch
    share its time. Batches run one after another within a run; runs in parallel processes add up."""
    rows = with_labels(rows)
    setting = EXPERIMENT[:-2]  # without repeat and seed
    clock = rows.sort_values("trial", kind="stable").groupby(EXPERIMENT).seconds
    experiments = pd.DataFrame({"started": clock.first(), "seconds": clock.max()}).reset_index()
    batches = experiments.groupby(setting + ["started"]).seconds.max().reset_index()
    table = pd.DataFrame({"repeats": experiments.groupby("label").size(),
                          "hours": batches.groupby("label").seconds.sum() / 3600})
    table = table.loc[column_order(table.index)]
    table.loc["total"] = table.sum()
    return table.assign(**{"hours per repeat": table.hours / table.repeats}).rename_axis("label")
