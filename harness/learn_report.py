"""Success tables and learning curves from the learning CSV alone (``harness.learn``).

    python -m harness.learn_report reports/learn_cartpole_angle_k1.csv

Success: the final learned trial's evaluation (mean cost of ``eval_runs`` real runs) is below
a threshold chosen from the pooled distribution of final evaluations of every method and
repeat in the table: the cut that minimises the within-group variance of the two groups it
makes (Otsu's rule; where learning either swings the pole up or does not, the final costs are
bimodal and the cut falls in the gap). The threshold, the two groups' separation (which says
whether there was a gap to find) and the sorted final costs are printed with every table. Rates carry Wilson 95 % intervals.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pandas as pd

Z95 = 1.96

PAPER = {  # PIPPS (Parmas et al. 2018), Tables 1-2: success rates over 100 repeats
    ("cartpole", "angle", 0.01): dict(pilco=0.88, rp=0.69, rp_fs=0.24, gr=0.63, gr_fs=0.74, lr=0.57, tp=0.82,
                                      **{"tp+sigma_n": 0.96}),
    ("cartpole", "angle", 1.0): dict(pilco=0.79, rp=0.74, rp_fs=0.23, gr=0.89, gr_fs=0.71, lr=0.96, tp=0.99,
                                     **{"tp-sigma_f": 0.93}),
    ("cartpole", "angle", 4.0): dict(pilco=0.70, rp=0.58, rp_fs=0.08, gr=0.62, gr_fs=0.41, lr=0.94, tp=0.95),
    ("cartpole", "angle", 9.0): dict(pilco=0.37, rp=0.44, rp_fs=0.04, gr=0.34, gr_fs=0.25, lr=0.86, tp=0.83),
    ("cartpole", "angle", 16.0): dict(pilco=0.01, rp=0.11, rp_fs=0.00, gr=0.08, gr_fs=0.02, lr=0.45, tp=0.40),
    ("cartpole", "tip", 0.01): dict(pilco=0.92, rp=0.44, rp_fs=0.20, gr=0.47, gr_fs=0.78, lr=0.36, tp=0.54),
    ("cartpole", "tip", 1.0): dict(pilco=0.73, rp=0.15, rp_fs=0.08, gr=0.68, gr_fs=0.50, lr=0.28, tp=0.48),
    ("unicycle", "default", 1.0): dict(pilco=0.91, rp=0.80, rp_fs=0.39, gr=0.96, gr_fs=0.63, lr=0.47, tp=0.94),
}


def otsu_threshold(values: np.ndarray) -> float:
    """The cut between sorted values that minimises the summed within-group variance."""
    v = np.sort(np.asarray(values, float))
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
    return max(0.0, centre - half), min(1.0, centre + half)


INVALID_METHODS = {
    "rp_fs_seed0": "every repeat and trial optimised on the same particles (noise seed 0: the fixed-seed bug "
                   "fixed in issue 18); not the paper's RP_FS",
    "gr_fs_seed0": "every repeat and trial optimised on the same particles (noise seed 0: the fixed-seed bug "
                   "fixed in issue 18); not the paper's GR_FS",
}
"""Method names of rows kept for the record that measure no method of the paper, and why."""


def with_labels(rows: pd.DataFrame) -> pd.DataFrame:
    """``rows`` with a ``label`` column: the method, followed by the task options that differ
    between the file's runs (``[angle_cost_scale=1.0,...]``) when there are several."""
    options = rows.task_options.astype(str).map(lambda text: dict(item.split("=", 1) for item in text.split(",")))
    names = sorted({name for opts in options for name in opts})
    varying = [name for name in names if len({opts.get(name) for opts in options}) > 1]
    suffix = options.map(lambda opts: " [" + ",".join(f"{n}={opts.get(n)}" for n in varying) + "]" if varying else "")
    return rows.assign(label=rows.method + suffix)


def final_evaluations(rows: pd.DataFrame) -> pd.DataFrame:
    """Per experiment (task, cost, noise_k, label, repeat): the last learned trial's row."""
    learned = with_labels(rows[rows.learned.astype(bool)])
    keys = ["task", "cost", "noise_k", "task_options", "label", "method", "settings", "repeat"]
    return learned.sort_values("trial").groupby(keys, as_index=False).last()


def column_order(labels) -> list[str]:
    """Labels in the paper's column order (``harness.learn.METHODS``), then any others."""
    from harness.learn import METHODS

    rank = {method: i for i, method in enumerate(METHODS)}
    return sorted(labels, key=lambda label: (rank.get(label.split(" [")[0], len(rank)), label))


def nonfinite_lines(learned: pd.DataFrame) -> list[str]:
    """Report lines on the optimiser steps whose gradient estimate was not finite (they move
    nothing): a flagged table of every learned trial with a count above zero, or that there
    were none. Rows written before the count was kept (no value) are counted as unknown."""
    counts = learned["nonfinite_steps"] if "nonfinite_steps" in learned else pd.Series(np.nan, learned.index)
    unknown = f" ({int(counts.isna().sum())} learned trials predate the count)" if counts.isna().any() else ""
    flagged = learned[counts > 0]
    if counts.isna().all():
        return [f"Non-finite gradient estimates: not counted; these {len(counts)} learned trials predate the count."]
    if flagged.empty:
        return [f"Non-finite gradient estimates: none in the {int(counts.notna().sum())} learned trials that count "
                f"them{unknown}."]
    columns = ["label", "settings", "repeat", "trial", "nonfinite_steps"]
    return [f"**WARNING: non-finite gradient estimates** in {len(flagged)} learned trials{unknown}. Each such "
            "optimiser step moved nothing (its NaN became a zero step); those runs optimised on fewer steps than "
            "their settings say:", "", flagged[columns].to_markdown(index=False)]


def success_table(rows: pd.DataFrame) -> tuple[pd.DataFrame, dict]:
    """Rows (task, cost, k), columns methods: 'rate [low, high] (paper p)'; and the
    threshold per (task, cost)."""
    final = final_evaluations(rows)
    thresholds = {key: otsu_threshold(group.eval_mean) for key, group in final.groupby(["task", "cost"])}
    cells = {}
    for (task, cost, k, label, method), group in final.groupby(["task", "cost", "noise_k", "label", "method"]):
        wins = int((group.eval_mean < thresholds[(task, cost)]).sum())
        low, high = wilson_interval(wins, len(group))
        paper = PAPER.get((task, cost, float(k)), {}).get(method)
        cells.setdefault((task, cost, k), {})[label] = (
            f"{wins / len(group):.2f} [{low:.2f}, {high:.2f}] n={len(group)}"
            + (f" (paper {paper:.2f})" if paper is not None else ""))
    table = pd.DataFrame.from_dict(cells, orient="index")
    table = table[column_order(table.columns)]
    table.index = pd.MultiIndex.from_tuples(table.index, names=["task", "cost", "k"])
    return table, thresholds


def write(rows: pd.DataFrame, stem: str, command: str) -> None:
    """``stem.md`` (thresholds, success table, per-method final costs) and ``stem.png``
    (learning curves: mean evaluation cost against trial, 95 % bands)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    table, thresholds = success_table(rows)
    final = final_evaluations(rows)
    learned = with_labels(rows[rows.learned.astype(bool)])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for index, label in enumerate(column_order(learned.label.unique())):
        stats = learned[learned.label == label].groupby("trial").eval_mean.agg(["mean", "std", "count"])
        half = Z95 * stats["std"].fillna(0) / np.sqrt(stats["count"])
        ax.plot(stats.index + 1, stats["mean"], marker="o", color=f"C{index}", label=label)
        ax.fill_between(stats.index + 1, stats["mean"] - half, stats["mean"] + half, color=f"C{index}", alpha=0.2)
    for (task, cost), threshold in thresholds.items():
        ax.axhline(threshold, color="k", linestyle="--", linewidth=0.8, label=f"success threshold {threshold:.2f}")
    ax.set_xlabel("trial")
    ax.set_ylabel("evaluation cost (mean of real runs)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(stem + ".png", dpi=110)
    plt.close(fig)

    lines = [f"# Learning: {os.path.basename(stem)}", "", f"Command: `{command}`", ""]
    for (task, cost), threshold in thresholds.items():
        values = np.sort(final[(final.task == task) & (final.cost == cost)].eval_mean.to_numpy())
        low, high = values[values < threshold], values[values >= threshold]
        spread = np.sqrt((np.sum((low - low.mean()) ** 2) + np.sum((high - high.mean()) ** 2)) / len(values))
        separation = (high.mean() - low.mean()) / spread if len(low) and len(high) and spread > 0 else np.nan
        lines.append(f"- Success threshold for {task}, {cost} cost: final evaluation cost < {threshold:.3f} (Otsu's "
                     f"cut of the {len(values)} pooled final costs; the two groups' means differ by {separation:.1f} "
                     "within-group sd, where one normal sample gives about 2.7 and a uniform one 3.4: only a value well "
                     "above that, say > 6, shows a real gap between learned and failed runs; below it the rates "
                     f"depend on an arbitrary cut). Sorted: {', '.join(f'{v:.2f}' for v in values)}.")
    lines += ["", *nonfinite_lines(learned), "",
              "Success rate [Wilson 95 % interval] n = repeats (the paper's rate, 100 repeats):", "",
              table.reset_index().to_markdown(index=False), "",
              *[f"- `{m}`: INVALID, {why}." for m, why in INVALID_METHODS.items() if m in set(final.method)],
              "", f"![learning curves]({os.path.basename(stem)}.png)", "",
              "Mean evaluation cost after each learned trial (mean over repeats):", "",
              learned.pivot_table(index="trial", columns="label", values="eval_mean", aggfunc="mean")[
                  column_order(learned.label.unique())].to_markdown(floatfmt=".2f"), "",
              "Final evaluation cost per method (mean, sd):", "",
              final.groupby(["label", "settings"]).eval_mean.agg(["mean", "std", "count"]).reset_index().to_markdown(
                  index=False, floatfmt=".3f"), "",
              "Task options of the runs: " + "; ".join(f"`{t}`" for t in sorted(final.task_options.unique())), ""]
    with open(stem + ".md", "w") as f:
        f.write("\n".join(lines))


def main(argv=None) -> None:
    paths = argv if argv is not None else sys.argv[1:]
    if len(paths) != 1 or not paths[0].endswith(".csv"):
        raise SystemExit("usage: python -m harness.learn_report PATH.csv")
    stem = paths[0][:-4]
    rows = pd.read_csv(paths[0])
    mixed = rows.groupby(["method", "task_options"]).settings.nunique()
    if (mixed > 1).any():
        raise SystemExit(f"{paths[0]} holds several settings for {list(mixed[mixed > 1].index)}: a rate mixes "
                         "them; keep one settings value per method (e.g. filter the CSV) and rerun.")
    write(rows, stem, f"python -m harness.learn_report {paths[0]}")
    print(f"wrote {stem}.{{md,png}}", file=sys.stderr)


if __name__ == "__main__":
    main()
