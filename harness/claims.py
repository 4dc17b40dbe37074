"""The paper's learning claims as verdicts from the success rates (``harness.success.success_rows``).

Each claim is a ``Finding``: the rates it compares and a ``verdict`` on the point estimates and on
two-sided tests at ``ALPHA``: (a) TP >= PILCO at k = 1, (b) LR and TP degrade least as k grows, (c)
RP_FS is the worst method, (d) TP+sigma_n above TP at k = 0.01 and, with the tip cost, PILCO and GR
above TP and LR (``ordering_lines``: every claim a table's rates can decide, a line each).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pandas as pd

from harness.methods import PAPER_METHODS, PAPER_RATES
from harness.success import fisher_p, interval_text, retained_fraction_p


ALPHA = 0.05
"""Level of the two-sided tests behind "significant" in the orderings."""


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
