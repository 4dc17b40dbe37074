"""Success tables and learning curves from the learning CSV alone (``harness.learn``).

    python -m harness.learn_report reports/learn_cartpole_angle_k1.csv
    python -m harness.learn_report reports/learn_cartpole_angle_k{0.01,1,4}.csv --out reports/learn_cartpole_angle

Success: the final learned trial's evaluation (mean cost of ``eval_runs`` real runs) is below a
threshold chosen from the pooled distribution of final evaluations of every method, k and
repeat in the table under one cost scale (``THRESHOLD_KEYS``): the cut that minimises the
within-group variance of the two groups it makes (Otsu's rule; where learning either swings the
pole up or does not, the final costs are bimodal and the cut falls in the gap). The threshold,
the two groups' separation (which says whether there was a gap to find) and the sorted final
costs are printed with every table. Rates carry Wilson 95 % intervals.

Beside the wide table the report holds: a long table (``success_rows``: per task, cost, k and method the rate, its
interval, the paper's rate and whether that lies inside the interval), every rate recomputed at the threshold
x (1 -+ ``ROBUSTNESS``) with what that changes (rates, orderings between methods, verdicts against the paper), the
paper's orderings evaluated from the rates (``ordering_lines``), and the compute time per method (``compute_hours``).
"""

from __future__ import annotations

import argparse
import os
import sys

from itertools import combinations
from typing import NamedTuple

import numpy as np
import pandas as pd
from scipy import stats

from harness.cli import OneLineParser, run_command
from harness.methods import INVALID as INVALID_METHODS
from harness.methods import METHODS, PAPER_METHODS, PAPER_RATES, READINGS, paper_rate
from harness.records import read_csv

Z95 = float(stats.norm.ppf(0.975))
"""1.95996...: the two-sided 95 % normal quantile of the Wilson interval."""
ALPHA = 0.05
"""Level of the two-sided tests behind "significant" in the orderings."""
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


def incomplete_lines(learned: pd.DataFrame) -> list[str]:
    """A warning naming the experiments left out for too few learned trials (``complete``), if any."""
    short = learned[~complete(learned)].groupby(EXPERIMENT).trial.nunique().reset_index()
    if short.empty:
        return []
    names = "; ".join(f"{e.label}, k = {e.noise_k:g}, repeat {e.repeat} ({e.trial} trials)" for e in short.itertuples())
    return [f"**Left out: {len(short)} experiments with fewer learned trials than their settings** (rows cut off "
            f"while written; rerun them after deleting their rows): {names}.", ""]


def column_order(labels) -> list[str]:
    """Labels in the paper's column order (``harness.methods.METHODS``), then any others."""
    rank = {method: i for i, method in enumerate(METHODS)}
    return sorted(labels, key=lambda label: (rank.get(label.split(" [")[0], len(rank)), label))


def nonfinite_lines(learned: pd.DataFrame) -> list[str]:
    """Report lines on the optimiser steps whose gradient estimate was not finite (they move no
    parameter whose component is not finite): a flagged table of every learned trial with a
    count above zero, or that there were none. Rows written before the count was kept (no
    value) are counted as unknown."""
    counts = learned["nonfinite_steps"] if "nonfinite_steps" in learned else pd.Series(np.nan, learned.index)
    unknown = f" ({int(counts.isna().sum())} learned trials predate the count)" if counts.isna().any() else ""
    flagged = learned[counts > 0]
    if counts.isna().all():
        return [f"Non-finite gradient estimates: not counted; these {len(counts)} learned trials predate the count."]
    if flagged.empty:
        return [f"Non-finite gradient estimates: none in the {int(counts.notna().sum())} learned trials that count "
                f"them{unknown}."]
    columns = ["label", "noise_k", "settings", "repeat", "trial", "nonfinite_steps"]
    lines = [f"**WARNING: non-finite gradient estimates** in {len(flagged)} learned trials{unknown}. Each such "
             "optimiser step moved no parameter whose component was not finite (a zero step there); those runs "
             "optimised on fewer steps than their settings say:", "", flagged[columns].to_markdown(index=False)]
    if flagged["settings"].str.contains(FLOAT32_ROLLOUT_SETTING).any():
        lines += ["", FLOAT32_NONFINITE_CAUSE]
    return lines


FLOAT32_ROLLOUT_SETTING = "rollout_f32"
"""The part of ``settings`` that ``harness.learn --rollout-float32`` adds."""
FLOAT32_NONFINITE_CAUSE = (
    "Under `rollout_f32` (particle rollouts in float32) the one traced cause so far is float32 overflow: a "
    "particle's gradient beyond about 1.8e19 squares past float32's largest number in the estimate's variance "
    "(`grad_var`), while the value and gradient stay finite (`diagnostics/rp_nonfinite_replay.py`, RP "
    "on cart-pole at k = 1); the CSV keeps only the count, not which part was not finite.")


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


def threshold_name(key: tuple) -> str:
    """'task, cost' (then the options, if any) of an ``otsu_thresholds`` key."""
    task, cost, scale = key
    return f"{task}, {cost}{scale}"


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


def long_table(at: dict[float, pd.DataFrame]) -> pd.DataFrame:
    """The long table for the report: per cell n, rate [interval], the paper's rate, whether it lies
    inside, and the rate at the threshold x every scale."""
    base = at[1.0]
    table = pd.DataFrame({"n": base.n, "rate [95 % interval]": base.apply(interval_text, axis=1),
                          "paper": base.paper.map(lambda p: "-" if np.isnan(p) else f"{p:.2f}"), "inside": base.inside,
                          "p vs paper": base.paper_p.map(lambda p: "-" if np.isnan(p) else f"{p:.2g}")})
    for scale in SCALES:
        table[f"rate at T x {scale:g}"] = at[scale].rate.map("{:.2f}".format)
    table = table.reset_index()
    return table.assign(k=table.k.map("{:g}".format))


def cell_name(key: tuple) -> str:
    """'task, cost, k = K, label' of a (task, cost, k, label) key."""
    return f"{key[0]}, {key[1]}, k = {key[2]:g}, {key[3]}"


def changes(values: pd.DataFrame, shown=str) -> list[str]:
    """'cell: v1 / v2 / v3' (each value as ``shown`` writes it) for every row of ``values`` (cells x
    scales) whose value differs between scales."""
    return [f"{cell_name(key)}: {' / '.join(map(shown, row))}" for key, row in values.iterrows() if row.nunique() > 1]


def ordering_changes(rates: pd.DataFrame) -> list[str]:
    """Pairs of labels in one (task, cost, k) whose order by rate ('<', '=', '>') differs between the
    scales of ``rates`` (cells x scales); labels of ``INVALID_METHODS`` are left out."""
    found = []
    for (task, cost, k), cell in rates.groupby(level=["task", "cost", "k"]):
        cell = cell.droplevel(["task", "cost", "k"])
        cell = cell[[label.split(" [")[0] not in INVALID_METHODS for label in cell.index]]
        for a, b in combinations(cell.index, 2):
            signs = np.sign(cell.loc[a] - cell.loc[b]).map({-1.0: "<", 0.0: "=", 1.0: ">"})
            if signs.nunique() > 1:
                found.append(f"{cell_name((task, cost, k, a))} vs {b}: {' / '.join(signs)}")
    return found


def robustness_lines(at: dict[float, pd.DataFrame], thresholds: dict) -> list[str]:
    """What changes when the threshold T is scaled by each of ``SCALES``: the rates, the orderings
    between methods and the verdicts against the paper, each listed as 'value at T x 0.9 / T / T x 1.1'."""
    scales = " / ".join(f"T x {scale:g}" for scale in SCALES)
    lines = [f"Threshold robustness: the rule stays Otsu's, fixed before the data; every rate recomputed at {scales} "
             f"(ROBUSTNESS = {ROBUSTNESS:g}), values listed in that order:", ""]
    lines += [f"- Thresholds for {threshold_name(key)}: " + " / ".join(f"{scale * t:.3f}" for scale in SCALES)
              for key, t in thresholds.items()]
    rates = pd.concat({scale: cells.rate for scale, cells in at.items()}, axis=1)
    found = {"Rates that change (flips)": changes(rates, "{:.2f}".format),
             "Orderings between methods (INVALID ones left out) that change": ordering_changes(rates),
             "Inside/outside verdicts against the paper that change": changes(
                 pd.concat({scale: cells.inside for scale, cells in at.items()}, axis=1))}
    return lines + [f"- {what}: " + (f"{len(items)} ({'; '.join(items)})" if items else "none") + "."
                    for what, items in found.items()]


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


def verdict(comparisons: dict[str, tuple[float, bool]], test: str) -> str:
    """A claim made of pairwise comparisons (``comparisons``: name -> (two-sided p-value, whether
    its point estimates agree with the claim)): 'holds' on the point estimates where every one
    agrees, else 'does not hold'; then 'significant' where every one agrees with p < ``ALPHA``
    (quoting the largest p), 'refuted' where one disagrees with p < ``ALPHA`` (quoting the
    smallest such p), else 'undecided' (quoting the largest p, or the smallest of those that
    disagree)."""
    against = {name: p for name, (p, agrees) in comparisons.items() if not agrees}
    if against:
        quoted = min(against, key=against.get)
        p, pool = against[quoted], f"of {len(against)} against the claim"
    else:
        quoted = max(comparisons, key=lambda name: comparisons[name][0])
        p, pool = comparisons[quoted][0], f"of {len(comparisons)}"
    which = f", the {'smallest' if against else 'largest'} {pool}: {quoted}" if len(comparisons) > 1 else ""
    if p < ALPHA:
        sign = f"{'refuted' if against else 'significant'} at {ALPHA:g}"
    else:
        sign = f"not significant at {ALPHA:g}, so undecided"
    return f"{'does not hold' if against else 'holds'} on the point estimates; {sign} ({test} p = {p:.3g}{which})"


def rate_text(row) -> str:
    """'METHOD rate [low, high] n=N' of a ``success_rows`` row."""
    return f"{row.method.upper()} {interval_text(row)} n={row.n}"


def missing(present, methods) -> str:
    """'not measured (no ... rows)' where a method of ``methods`` is not among ``present``, else ''."""
    present = set(present)
    absent = [m.upper() for m in methods if m not in present]
    return f"not measured (no {', '.join(absent)} rows)" if absent else ""


def partial(present, own: tuple[str, ...]) -> str:
    """'partial, GR and GR_FS not measured: ' where a method of ``PAPER_METHODS`` (other than the
    claim's ``own``) is not among ``present``: the claim is then judged against the others only."""
    absent = [m.upper() for m in PAPER_METHODS if m not in set(present) and m not in own]
    if not absent:
        return ""
    names = absent[0] if len(absent) == 1 else ", ".join(absent[:-1]) + " and " + absent[-1]
    return f"partial, {names} not measured: "


class Finding(NamedTuple):
    """A claim's evaluation: ``details`` (the rates compared; "" where nothing was) and its ``verdict``; as text
    "details: verdict"."""

    details: str
    verdict: str

    def __str__(self) -> str:
        return f"{self.details}: {self.verdict}" if self.details else self.verdict


def claim_tp_not_below_pilco(group: pd.DataFrame) -> Finding:
    """Claim (a), TP >= PILCO at k = 1, in one (task, cost, options) group of ``success_rows``."""
    cell = group[group.k == 1.0].set_index("method", drop=False)
    if absent := missing(cell.index, ["tp", "pilco"]):
        return Finding("", absent + " at k = 1")
    tp, pilco = cell.loc["tp"], cell.loc["pilco"]
    paper = PAPER_RATES.get((tp.task, tp.cost, 1.0), {})
    theirs = f"; the paper's own: TP {paper['tp']:.2f}, PILCO {paper['pilco']:.2f}" if paper else ""
    return Finding(f"{rate_text(tp)} vs {rate_text(pilco)}", verdict(
        {"TP vs PILCO": (fisher_p(tp, pilco), tp.rate >= pilco.rate)}, "two-sided Fisher exact") + theirs)


def needs_ks(task: str, cost: str, k: float) -> str:
    """Claim (b) undecided on a file with the single k ``k``: the k it needs (the paper's for the task and cost)."""
    paper_ks = sorted(pk for t, c, pk in PAPER_RATES if (t, c) == (task, cost))
    needed = f"k in {{{', '.join(f'{pk:g}' for pk in paper_ks)}}}" if len(paper_ks) > 1 else "at least two k"
    return f"undecided: needs {needed} (this file has only k = {k:g})"


def claim_lr_tp_degrade_least(group: pd.DataFrame) -> Finding:
    """Claim (b), LR and TP lose the smallest fraction of their rate from the smallest to the
    largest k, in one (task, cost, options) group of ``success_rows``; compares the paper's
    methods measured at both ends."""
    ks = sorted(group.k.unique())
    if absent := missing(group.method, ["lr", "tp"]):
        return Finding("", absent)
    if len(ks) < 2:
        return Finding("", needs_ks(group.task.iloc[0], group.cost.iloc[0], ks[0]))
    first, last = (group[group.k == k].set_index("method", drop=False) for k in (ks[0], ks[-1]))
    both = set(first.index) & set(last.index)
    if absent := missing(both, ["lr", "tp"]):
        return Finding("", f"{absent} at both k = {ks[0]:g} and k = {ks[-1]:g}")
    others = [m for m in PAPER_METHODS if m not in ("lr", "tp") and m in both]
    drops = {m: relative_drop(first.loc[m].rate, last.loc[m].rate) for m in ["lr", "tp", *others]}
    listed = ", ".join(f"{m.upper()} {'-' if np.isnan(drop) else f'{drop:.2f}'}" for m, drop in drops.items())
    dash = "; -: no success to lose" if any(np.isnan(drop) for drop in drops.values()) else ""
    header = (f"{partial(both, ('lr', 'tp'))}relative drop in rate (1 - rate at k = {ks[-1]:g} / rate at "
              f"k = {ks[0]:g}{dash}): {listed}")
    if nothing := [m.upper() for m in ("lr", "tp") if np.isnan(drops[m])]:
        return Finding(header, f"undecided ({' and '.join(nothing)} had no success at k = {ks[0]:g})")
    others = [m for m in others if not np.isnan(drops[m])]
    if not others:
        return Finding(header, f"not measured (no other method of the paper with a success at k = {ks[0]:g})")
    comparisons = {f"{a.upper()} vs {b.upper()}": (retained_fraction_p(first.loc[a], last.loc[a], first.loc[b],
                                                                       last.loc[b]), drops[a] <= drops[b])
                   for a in ("lr", "tp") for b in others}
    return Finding(header, verdict(comparisons, "two-sided Wald test of equal log ratios, Agresti-Caffo adjusted,"))


def relative_drop(first: float, last: float) -> float:
    """``1 - last / first``: the fraction of its rate a method loses (NaN where it had none to lose)."""
    return 1 - last / first if first > 0 else np.nan


def claim_rp_fs_worst(cell: pd.DataFrame) -> Finding:
    """Claim (c), RP_FS has the lowest rate of the paper's methods, in one (task, cost, k, options)
    cell of ``success_rows``."""
    cell = cell.set_index("method", drop=False)
    others = [m for m in PAPER_METHODS if m != "rp_fs" and m in cell.index]
    if absent := missing(cell.index, ["rp_fs"]):
        return Finding("", absent)
    if not others:
        return Finding("", "not measured (no other method of the paper)")
    rp_fs, lowest = cell.loc["rp_fs"], cell.loc[others].rate.idxmin()
    comparisons = {f"RP_FS vs {m.upper()}": (fisher_p(rp_fs, cell.loc[m]), rp_fs.rate <= cell.loc[m].rate)
                   for m in others}
    return Finding(f"{partial(cell.index, ('rp_fs',))}{rate_text(rp_fs)} vs the lowest other, "
                   f"{rate_text(cell.loc[lowest])}", verdict(comparisons, "two-sided Fisher exact"))


def claim_beats(cell: pd.DataFrame, winners: tuple[str, ...], losers: tuple[str, ...]) -> Finding:
    """Each method of ``winners`` has a higher rate than each of ``losers`` in one (task, cost, k, options) cell
    of ``success_rows``: a verdict over every pair present (two-sided Fisher exact)."""
    cell = cell.set_index("method", drop=False)
    if absent := missing(cell.index, list(winners) + list(losers)):
        return Finding("", absent)
    listed = ", ".join(rate_text(cell.loc[m]) for m in winners + losers)
    comparisons = {f"{a.upper()} vs {b.upper()}": (fisher_p(cell.loc[a], cell.loc[b]),
                                                    cell.loc[a].rate > cell.loc[b].rate)
                   for a in winners for b in losers}
    return Finding(listed, verdict(comparisons, "two-sided Fisher exact"))


def ordering_lines(success: pd.DataFrame) -> list[str]:
    """The paper's orderings evaluated from ``success_rows``, a line each per (task, cost, task options)
    and, for (c), per k: (a) TP >= PILCO at k = 1, (b) LR and TP degrade least as k grows, (c) RP_FS
    is the worst method; where the cell is present, (d) TP+sigma_n above TP at k = 0.01 (angle cost)
    and, with the tip cost at k = 1, PILCO and GR above the particle methods TP and LR."""
    lines = []
    for (task, cost, options), group in success.groupby(["task", "cost", "options"]):
        name = f"{task}, {cost}{options}"
        lines += [f"- (a) TP >= PILCO at k = 1 ({name}): {claim_tp_not_below_pilco(group)}.",
                  f"- (b) LR and TP degrade least as k grows ({name}): {claim_lr_tp_degrade_least(group)}."]
        lines += [f"- (c) RP_FS is the worst method ({name}, k = {k:g}): {claim_rp_fs_worst(cell)}."
                  for k, cell in group.groupby("k")]
        if cost == "angle" and (group.k == 0.01).any():
            lines.append(f"- (d) TP+sigma_n above TP at k = 0.01 ({name}): "
                         f"{claim_beats(group[group.k == 0.01], ('tp+sigma_n',), ('tp',))}.")
        if cost == "tip" and (group.k == 1.0).any():
            lines.append(f"- Tip cost: PILCO and GR above TP and LR at k = 1 ({name}): "
                         f"{claim_beats(group[group.k == 1.0], ('pilco', 'gr'), ('tp', 'lr'))}.")
    return lines


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


def paper_comparison_lines(rows: pd.DataFrame, thresholds: dict) -> list[str]:
    """Report lines: the long table (rates against the paper's, at the three thresholds), what the
    threshold's scaling changes, and the paper's orderings evaluated from the rates."""
    at = rates_at_scales(rows)
    return ["Per cell (T: the threshold above): success rate [Wilson 95 % interval], the paper's rate, whether it "
            "lies inside the interval ('-': the paper has no rate), the two-sided Fisher exact p-value of our rate "
            f"against the paper's as {PAPER_REPEATS} repeats (which counts the paper's sampling error too; with some "
            "50 cells, a few below 0.05 are expected by chance), and the rate at the threshold scaled:", "",
            long_table(at).to_markdown(index=False, disable_numparse=True), "", *robustness_lines(at, thresholds), "",
            f"The paper's orderings from these rates (holds: the point estimates agree with the claim; significant: "
            f"a two-sided test rejects equality at {ALPHA:g}; 'not measured': a method of the claim is absent):", "",
            *ordering_lines(at[1.0].reset_index())]


def compute_lines(rows: pd.DataFrame) -> list[str]:
    """Report lines: the compute time per method (``compute_hours``) and what it counts."""
    return ["Compute time: per batch of repeats vmapped together, its wall time (the `seconds` of its last trial, "
            "which `harness.learn` writes on every repeat's row as the time since the batch began), counted once per "
            "batch and summed; hours per repeat = hours / repeats (a batch's repeats share its time):", "",
            compute_hours(rows).reset_index().to_markdown(index=False, floatfmt=".2f"), ""]


def threshold_lines(final: pd.DataFrame, thresholds: dict) -> list[str]:
    """A report line per threshold (``otsu_thresholds`` of the ``final_evaluations`` ``final``): the
    cut, how far apart the two groups it makes are (in within-group sd: whether there was a gap
    to find) and the sorted pooled final costs."""
    lines = []
    for key, group in final.groupby(THRESHOLD_KEYS):
        threshold, kept = thresholds[key], pooled_rows(group)
        pooled = kept.eval_mean.to_numpy()
        values = np.sort(pooled[np.isfinite(pooled)])
        diverged = (f"; {len(pooled) - len(values)} non-finite final costs, failures at any cut, are not pooled"
                    if len(values) < len(pooled) else "")
        left_out = group.drop(kept.index)
        if invalid := left_out.method.isin(list(INVALID_METHODS)).sum():
            diverged += f"; the {invalid} final costs of INVALID runs are not pooled"
        if readings := sorted(set(left_out.method) - set(INVALID_METHODS)):
            diverged += (f"; the {len(left_out) - invalid} final costs of other readings "
                         f"({', '.join(readings)}) are not pooled: they are judged at this cut")
        low, high = values[values < threshold], values[values >= threshold]
        separation = np.nan  # one group is empty where every run is on the same side of the cut
        if len(low) and len(high):
            spread = np.sqrt((np.sum((low - low.mean()) ** 2) + np.sum((high - high.mean()) ** 2)) / len(values))
            separation = (high.mean() - low.mean()) / spread if spread > 0 else np.nan
        task, cost, cut = key
        lines.append(f"- Success threshold for {task}, {cost} cost{cut}: final evaluation "
                     f"cost < {threshold:.3f} (Otsu's cut of the {len(values)} pooled final costs; the two groups' "
                     f"means differ by {separation:.1f} within-group sd, where one normal sample gives about 2.7 and "
                     "a uniform one 3.4: only a value well above that, say > 6, shows a real gap between learned and "
                     f"failed runs; below it the rates depend on an arbitrary cut{diverged}). Sorted: "
                     f"{', '.join(f'{v:.2f}' for v in values)}.")
    return lines


def invalid_lines(final: pd.DataFrame) -> list[str]:
    """A line per method of ``INVALID_METHODS`` in ``final``: why it is invalid, and whether its
    costs took part in the threshold (only in a file of invalid runs alone: ``pooled_rows``)."""
    alone = final.method.isin(list(INVALID_METHODS)).all()
    pool = "the threshold is cut on these invalid costs alone" if alone else "its costs not in the threshold's pool"
    return [f"- `{m}`: INVALID ({pool}), {why}." for m, why in INVALID_METHODS.items() if m in set(final.method)]


def with_curve_labels(frame: pd.DataFrame, several_k: bool) -> pd.DataFrame:
    """``frame`` (``with_labels``) with ``curve``: the label, followed by " [k=K]" where the report
    holds several k (a learning curve or a final cost per method and k, never pooled over k)."""
    return frame.assign(curve=frame.label + (" [k=" + frame.noise_k.map("{:g}".format) + "]" if several_k else ""))


def curve_order(frame: pd.DataFrame) -> list[str]:
    """The ``curve`` labels of ``frame`` in the paper's column order, each method's by k."""
    rank = {label: i for i, label in enumerate(column_order(frame.label.unique()))}
    first = frame.drop_duplicates("curve")
    return list(first.assign(rank=first.label.map(rank)).sort_values(["rank", "noise_k"]).curve)


def rate_figure(success: pd.DataFrame, path: str) -> None:
    """Success rate against k per method label (one panel per task and cost), with Wilson 95 % intervals as
    bars and the paper's rates as crosses; ``success``: ``success_rows``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = list(success.groupby(["task", "cost"]))
    fig, axes = plt.subplots(1, len(groups), figsize=(6.5 * len(groups), 4.5), squeeze=False)
    for ax, ((task, cost), group) in zip(axes[0], groups):
        labels = column_order(group.label.unique())
        for index, label in enumerate(labels):
            line = group[group.label == label].sort_values("k")
            shifted = line.k * 10 ** (0.04 * (index - (len(labels) - 1) / 2))  # side by side at each k
            ax.errorbar(shifted, line.rate, yerr=[line.rate - line.low, line.high - line.rate], marker="o",
                        color=f"C{index % 10}", capsize=3, label=label)
            ax.plot(shifted, line.paper, "x", color=f"C{index % 10}", markersize=8)
        ax.set_xscale("log")
        ax.set_xlabel("observation-noise multiplier k")
        ax.set_ylabel("success rate (x: the paper's)")
        ax.set_title(f"{task}, {cost} cost")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(rows: pd.DataFrame, stem: str, command: str) -> None:
    """``stem.md`` (thresholds, success tables, threshold robustness, the paper's orderings, compute
    time, per-method final costs) and ``stem.png``
    (learning curves: mean evaluation cost against trial, 95 % bands)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table, thresholds = success_table(rows)
    several_k = rows.noise_k.nunique() > 1
    if several_k:
        rate_figure(success_rows(rows), stem + "_rates.png")
    final = with_curve_labels(final_evaluations(rows), several_k)
    learned = with_curve_labels(with_labels(rows[rows.learned.astype(bool)]), several_k)
    curves = curve_order(learned)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for index, curve_label in enumerate(curves):
        curve = learned[learned.curve == curve_label].groupby("trial").eval_mean.agg(["mean", "std", "count"])
        t95 = stats.t.ppf(0.975, np.maximum(curve["count"] - 1, 1))  # no band from a single repeat: its sd is NaN
        half = t95 * curve["std"].fillna(0) / np.sqrt(curve["count"])
        ax.plot(curve.index, curve["mean"], marker="o", color=f"C{index}", label=curve_label)
        ax.fill_between(curve.index, curve["mean"] - half, curve["mean"] + half, color=f"C{index}", alpha=0.2)
    for key, threshold in thresholds.items():
        name = f" ({threshold_name(key)})" if len(thresholds) > 1 else ""
        ax.axhline(threshold, color="k", linestyle="--", linewidth=0.8,
                   label=f"success threshold {threshold:.2f}{name}")
    ax.set_xlabel("trial (numbered as in the CSV: the random trials first, from 0)")
    ax.set_ylabel("evaluation cost (mean of real runs)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(stem + ".png", dpi=110)
    plt.close(fig)

    per = "method and k" if several_k else "method"
    lines = [f"# Learning: {os.path.basename(stem)}", "", f"Command: `{command}`", "",
             *threshold_lines(final, thresholds), "", *incomplete_lines(learned), *nonfinite_lines(learned), "",
             "Success rate [Wilson 95 % interval] n = repeats (the paper's rate, 100 repeats):", "",
             table.reset_index().to_markdown(index=False), "",
             *invalid_lines(final),
             "", *paper_comparison_lines(rows, thresholds), "", *compute_lines(rows),
             "", f"![learning curves]({os.path.basename(stem)}.png)", "",
             *([f"![success rate against k]({os.path.basename(stem)}_rates.png)", ""] if several_k else []),
             f"Mean evaluation cost after each learned trial (mean over repeats, per {per}):", "",
             learned.pivot_table(index="trial", columns="curve", values="eval_mean", aggfunc="mean")[
                 curves].to_markdown(floatfmt=".2f"), "",
             f"Final evaluation cost per {per} (mean, sd):", "",
             final.groupby("curve").agg(settings=("settings", "first"), mean=("eval_mean", "mean"),
                                        std=("eval_mean", "std"), count=("eval_mean", "count")).loc[
                 curve_order(final)].rename_axis("label").reset_index().to_markdown(index=False, floatfmt=".3f"),
             "",
             "Task options of the runs: " + "; ".join(f"`{t}`" for t in sorted(final.task_options.unique())), ""]
    with open(stem + ".md", "w") as f:
        f.write("\n".join(lines))


def main(argv=None) -> None:
    parser = OneLineParser(
        prog="python -m harness.learn_report",
        description="Success tables and learning curves from learning CSVs (harness.learn). Several CSVs (e.g. one "
                    "per k, for the claims across k) are pooled into one report, written to --out.")
    parser.add_argument("paths", nargs="+", metavar="PATH.csv")
    parser.add_argument("--out", help="stem of the report (STEM.md, STEM.png); default: the one CSV's stem")
    args = parser.parse_args(argv)
    if not all(path.endswith(".csv") for path in args.paths):
        parser.error("every PATH must be a .csv written by harness.learn")
    if len(args.paths) > 1 and args.out is None:
        parser.error("several CSVs need --out STEM (where to write the pooled report)")
    stem = args.out or args.paths[0][:-4]
    rows = pd.concat([read_csv(path) for path in args.paths], ignore_index=True)
    mixed = rows.groupby(["method", "task_options"]).settings.nunique()
    if (mixed > 1).any():
        raise ValueError(f"{' '.join(args.paths)} hold several settings for {list(mixed[mixed > 1].index)}: a rate "
                         "mixes them; keep one settings value per method (e.g. filter the CSV) and rerun.")
    out = f" --out {args.out}" if args.out else ""
    write(rows, stem, f"python -m harness.learn_report {' '.join(args.paths)}{out}")
    print(f"wrote {stem}.{{md,png}}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
