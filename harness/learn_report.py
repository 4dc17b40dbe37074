"""Success tables and learning curves from the learning CSV alone (``harness.learn``).

    python -m harness.learn_report reports/learn_cartpole_angle_k1.csv
    python -m harness.learn_report reports/learn_cartpole_angle_k{0.01,1,4}.csv --out reports/learn_cartpole_angle

Success and its threshold are ``harness.success``'s, the paper's claims ``harness.claims``'s. The threshold,
the two groups' separation (which says whether there was a gap to find) and the sorted final costs are
printed with every table.

Beside the wide table the report holds: a long table (``success.success_rows``: per task, cost, k and method the
rate, its interval, the paper's rate and whether that lies inside the interval), every rate recomputed at the
threshold x (1 -+ ``success.ROBUSTNESS``) with what that changes (rates, orderings between methods, verdicts against
the paper), the paper's orderings evaluated from the rates (``claims.ordering_lines``), and the compute time per
method (``success.compute_hours``).
"""

from __future__ import annotations

import os
import sys

from itertools import combinations

import numpy as np
import pandas as pd
from scipy import stats

from harness.claims import ALPHA, ordering_lines
from harness.cli import OneLineParser, run_command
from harness.methods import INVALID as INVALID_METHODS
from harness.records import read_csv
from harness.success import (EXPERIMENT, PAPER_REPEATS, ROBUSTNESS, SCALES, THRESHOLD_KEYS, column_order, complete,
                             compute_hours, final_evaluations, interval_text, pooled_rows, rates_at_scales,
                             success_rows, success_table, with_labels)


def incomplete_lines(learned: pd.DataFrame) -> list[str]:
    """A warning naming the experiments left out for too few learned trials (``complete``), if any."""
    short = learned[~complete(learned)].groupby(EXPERIMENT).trial.nunique().reset_index()
    if short.empty:
        return []
    names = "; ".join(f"{e.label}, k = {e.noise_k:g}, repeat {e.repeat} ({e.trial} trials)" for e in short.itertuples())
    return [f"**Left out: {len(short)} experiments with fewer learned trials than their settings** (rows cut off "
            f"while written; rerun them after deleting their rows): {names}.", ""]


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


def threshold_name(key: tuple) -> str:
    """'task, cost' (then the options, if any) of an ``otsu_thresholds`` key."""
    task, cost, scale = key
    return f"{task}, {cost}{scale}"


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
