"""The claims table: which of the paper's claims reproduce, from the committed results alone.

    python -m harness.summary            # writes reports/SUMMARY.md and the README's claims table
    python -m harness.summary --check    # exit status 1 if either differs from what it would write

Each claim is a row: the claim, the paper's number, ours, a verdict by a rule fixed here before
the numbers it decides, and the report it comes from. The gradient claims come from the variance
experiment's rows at its pinned scenario (``harness.variance.run`` reuses them: nothing is
computed), the learning claims from the learning CSVs (``harness.success.success_rows``).
Claims with no data yet say so and name the plan that will decide them.

Verdict rules:
- "TP has the lowest variance" and "BIW-LR below LR": holds in every cell, mixed in some,
  does not hold in none (cells: particle counts x the two points of the line).
- "RP's variance jumps along the line": the ratio var(delta theta = 1.5) / var(0) per particle
  count; holds if every ratio is at least 1e2, reversed if every ratio is below 1, else mixed.
- A learning table: agrees in the cells whose Wilson 95 % interval holds the paper's rate.
- The curse-of-chaos scenario (``harness.chaos``): its own rule; the gradient claims at it as above. Its rows
  on TP's and GR's variance at both ends and on the Lyapunov exponent give numbers only: their reports were
  computed before a rule for them was fixed, so none is applied after the fact.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys
from typing import NamedTuple

import jax
import numpy as np
import pandas as pd

from harness import bench, variance
from harness.claims import claim_beats, claim_lr_tp_degrade_least
from harness.cli import flag_values, parse, run_command, with_flags
from harness.methods import METHODS, PAPER_RATES
from harness.records import ROOT, read_csv
from harness.success import success_rows

CLAIMS_START = "<!-- claims table: written by python -m harness.summary; do not edit by hand -->"
CLAIMS_END = "<!-- end of claims table -->"
SPEED_START = "<!-- speed: written by python -m harness.summary from reports/bench.csv; do not edit by hand -->"
SPEED_END = "<!-- end of speed -->"
VARIANCE_COMMANDS = {task: ["--task", task] for task in ("cartpole", "unicycle")}
"""The variance reports' commands (each task's default: its pinned scenario)."""
LEARNING_TABLES = {f"cartpole, angle cost, k = {k:g}": f"learn_cartpole_angle_k{k:g}" for k in (0.01, 1.0, 4.0, 9.0, 16.0)}
LEARNING_TABLES |= {"cartpole, tip cost, k = 1": "learn_cartpole_tip_k1",
                    "unicycle, paper preset": "learn_unicycle_default_k1"}
"""Learning tables at the paper's settings (preset ``paper``), by the report's stem: a row each once its CSV
is in reports/ (each cell's rates against the paper's)."""


def paper_rates(task: str, cost: str, k: float, methods: tuple[str, ...]) -> str:
    """The paper's rates of ``methods`` in one cell (``harness.methods.PAPER_RATES``), "tp 0.82, ..."."""
    return ", ".join(f"{m} {PAPER_RATES[(task, cost, k)][m]:.2f}" for m in methods)


PAPER_KS = (0.01, 1.0, 4.0, 9.0, 16.0)
"""The paper's noise levels of the cart-pole's angle-cost table."""


def paper_success(reports: str, stems: list[str]):
    """``success_rows`` of the CSVs among ``stems`` that exist (None if none does)."""
    paths = [os.path.join(reports, stem + ".csv") for stem in stems]
    present = [path for path in paths if os.path.exists(path)]
    return success_rows(pd.concat([read_csv(p) for p in present], ignore_index=True)) if present else None


def learning_findings(reports: str) -> list[tuple[str, str, object, str]]:
    """The paper's learning claims beyond the k = 1 column: (claim, the paper's rates, a ``claims.Finding``
    or None where no run is in reports/ yet, the report stems that decide it)."""
    angle = [f"learn_cartpole_angle_k{k:g}" for k in PAPER_KS]
    findings = []
    success = paper_success(reports, angle)
    findings.append(("LR and TP degrade least as the noise k grows (claim b)",
                     "; ".join(f"k = {k:g}: {paper_rates('cartpole', 'angle', k, ('tp', 'lr', 'pilco'))}"
                               for k in (0.01, 16.0)),
                     None if success is None or success.k.nunique() < 2 else claim_lr_tp_degrade_least(
                         success[success.options == ""]), "learn_cartpole_angle_k*"))
    low = paper_success(reports, angle[:1])
    findings.append(("TP+sigma_n above TP at low noise (claim d)",
                     paper_rates("cartpole", "angle", 0.01, ("tp+sigma_n", "tp")),
                     None if low is None else claim_beats(low, ("tp+sigma_n",), ("tp",)),
                     angle[0]))
    tip = paper_success(reports, ["learn_cartpole_tip_k1"])
    findings.append(("With the tip cost, PILCO and GR beat the particle methods",
                     paper_rates("cartpole", "tip", 1.0, ("pilco", "gr", "tp", "lr")),
                     None if tip is None else claim_beats(tip, ("pilco", "gr"), ("tp", "lr")),
                     "learn_cartpole_tip_k1"))
    return findings


class TableAgreement(NamedTuple):
    """A learning table's cells whose rate agrees with the paper's (its interval holds it), of those compared."""

    table: str
    repeats: str
    """Repeats per method: "10", or "5-10" while a table is still being filled."""
    agree: int
    compared: int
    outside: tuple[str, ...] = ()
    """The methods whose interval misses the paper's rate."""


class Claim(NamedTuple):
    claim: str
    paper: str
    ours: str
    verdict: str
    report: str
    cells: TableAgreement | None = None
    """Set on a learning table's row: the README merges those rows into one (``readme_claims``)."""


@dataclasses.dataclass(frozen=True)
class Args:
    """Write the claims table (reports/SUMMARY.md and the README's) from the committed results."""

    check: bool = False
    """Write nothing; exit with status 1 if SUMMARY.md or the README's table is not what would be written."""
    reports: str = "reports"
    """Folder of the reports (relative to the repository root unless absolute)."""


def cell_rule(count: int, total: int) -> str:
    return "holds" if count == total else "does not hold" if count == 0 else "mixed"


def jump_rule(ratios: np.ndarray) -> str:
    return "holds" if (ratios >= 1e2).all() else "reversed" if (ratios < 1).all() else "mixed"


def variance_rows(argv: list[str], out: str):
    """The rows of the variance report that ``python -m harness.variance ARGV --out OUT`` writes
    (``harness.variance.run``: the committed rows are reused; only a cell missing from the CSV would be computed)."""
    jax.config.update("jax_enable_x64", True)
    args = parse(variance.Args, argv + ["--out", out])
    return variance.run(args)


def gradient_claims(rows: pd.DataFrame, where: str, link: str) -> list[Claim]:
    """The paper's gradient claims on one variance report's rows at one scenario (``where`` names it): TP lowest
    (against every other estimator but BIW-LR's baseline variants, as the report's findings), BIW-LR below LR (if
    both ran), RP's jump from the first delta theta to the last."""
    var = rows.pivot_table(index=["delta_theta", "particles"], columns="estimator", values="variance")
    others = var.drop(columns=["tp", *(c for c in variance.BIW_BASELINE_VARIANTS if c in var.columns)]).min(axis=1)
    share = var.tp / others
    lowest = int((share < 1).sum())
    claims = [Claim(f"{where}: TP has the lowest gradient variance", "10-50 % below the others at P <= 250",
                    f"lowest in {lowest} of {len(share)} cells (TP / best other {share.min():.2f}-{share.max():.2f})",
                    cell_rule(lowest, len(share)), link)]
    if {"lr", "biw_lr"} <= set(var.columns):
        ratio = var.biw_lr / var.lr
        claims.append(Claim(f"{where}: batch importance weights lower LR's variance", "BIW-LR below LR",
                            f"below in {int((ratio < 1).sum())} of {len(ratio)} cells (BIW-LR / LR {ratio.min():.2f}-"
                            f"{ratio.max():.2f})", cell_rule(int((ratio < 1).sum()), len(ratio)), link))
    deltas = sorted(rows.delta_theta.unique())
    rp = var.rp.unstack("delta_theta")
    jump = (rp[deltas[-1]] / rp[deltas[0]]).to_numpy()
    claims.append(Claim(f"{where}: RP's variance jumps along the line (curse of chaos)",
                        "about 4e5-fold, to 1e8-1e15",
                        f"x {jump.min():.2g} to x {jump.max():.2g} from delta theta {deltas[0]:g} to {deltas[-1]:g} "
                        f"({rp[deltas[-1]].min():.1e}-{rp[deltas[-1]].max():.1e})", jump_rule(jump), link))
    return claims


def variance_claims(task: str, reports: str) -> list[Claim]:
    rows, _ = variance_rows(VARIANCE_COMMANDS[task], reports)
    return gradient_claims(rows, task, f"[variance_{task}_gp](variance_{task}_gp.md)")


def learning_claims(name: str, stem: str, reports: str) -> list[Claim]:
    success = paper_success(reports, [stem])
    compared = success[success.inside != "-"]
    outside = compared[compared.inside == "no"]
    apart = "; ".join(f"{r.label} {r.rate:.2f} [{r.low:.2f}, {r.high:.2f}] against {r.paper:.2f}"
                      for r in outside.itertuples())
    repeats = sorted({int(n) for n in success.n})
    counts = f"{repeats[0]}" if len(repeats) == 1 else f"{repeats[0]}-{repeats[-1]}"
    cells = TableAgreement(name, counts, len(compared) - len(outside), len(compared), tuple(outside.label))
    return [Claim(f"learning, {name}: success rates", "Table 1's column",
                  f"{counts} repeats per method" + (f"; outside: {apart}" if apart else ""),
                  agreement(cells.agree, cells.compared),
                  f"[{stem}]({stem}.md)", cells)]


def agreement(agree: int, compared: int) -> str:
    return f"agrees in {agree} of {compared} cells"


def readme_claims(claims: list[Claim]) -> list[Claim]:
    """The README's table: ``claims`` with the learning tables' rows (one per table present) merged into one
    row in place of the first, each table's agreement in it; SUMMARY.md keeps their rows, so that the README stays
    one page as the tables land."""
    tables = [c for c in claims if c.cells is not None]
    if not tables:
        return claims
    per_table = "; ".join(f"{c.cells.table} ({c.cells.repeats} repeats): {c.cells.agree} of {c.cells.compared}"
                          + (f" (outside: {', '.join(c.cells.outside)})" if c.cells.outside else "") for c in tables)
    merged = Claim("learning tables at the paper's settings: success rates per cell", "Tables 1-2", per_table,
                   agreement(sum(c.cells.agree for c in tables), sum(c.cells.compared for c in tables)),
                   "[SUMMARY](SUMMARY.md), a row per table")
    first = claims.index(tables[0])
    return claims[:first] + [merged] + [c for c in claims[first:] if c.cells is None]


def reading_claims(reports: str, stem: str = "learn_cartpole_angle_k1") -> list[Claim]:
    """A row per reading of a convention (``harness.methods.READINGS``) in ``readings/STEM.csv``, judged at the
    cut of the table ``STEM.csv`` beside it, as the report that ``python -m harness.learn_report STEM.csv
    readings/STEM.csv --out reports/readings/beside_K`` writes (K: the stem's k part, e.g. k1)."""
    readings = os.path.join("readings", stem)
    if not all(os.path.exists(os.path.join(reports, name + ".csv")) for name in (stem, readings)):
        return []
    success = paper_success(reports, [stem, readings])
    read = set(read_csv(os.path.join(reports, readings + ".csv")).method)
    return [Claim(f"reading `{r.method}` of {METHODS[r.method].reads.upper()}'s convention, judged at the table's cut",
                  f"{METHODS[r.method].reads} {r.paper:.2f}", f"{r.rate:.2f} [{r.low:.2f}, {r.high:.2f}] of {r.n}",
                  "paper's rate inside" if r.inside == "yes" else "paper's rate outside",
                  f"[readings/beside_{stem.rsplit('_', 1)[-1]}](readings/beside_{stem.rsplit('_', 1)[-1]}.md)")
            for r in success.itertuples() if r.method in read]


def chaos_scenario_claims(reports: str) -> list[Claim]:
    """The curse-of-chaos scenario's rows (``harness.chaos``: chaos_scenario.json), if it was checked: its rule;
    where the rule holds, the paper's gradient claims on the variance report at the scenario, TP's and GR's
    variance at both ends of the line, and the landscape's Lyapunov exponent."""
    path = os.path.join(reports, "chaos_scenario.json")
    if not os.path.exists(path):
        return []
    with open(path) as f:
        found = json.load(f)
    rp, other = found["variance"]["rp"], {k: v for k, v in found["variance"].items() if k != "rp"}
    [(name, value)] = other.items()
    claims = [Claim(f"cartpole: a scenario at a policy that works ({found['method']} repeat {found['repeat']}, "
                    f"{found['plan']}'s rule)", "implied: RP well-behaved at delta theta = 0",
                    f"J {found['cost']:.2f} (at most {found['max_cost']:g}); RP / {name.upper()} variance "
                    f"{rp / value:.2g}", "rule holds" if found["holds"] else "rule fails: next repeat",
                    "[chaos_scenario](chaos_scenario.md)")]
    commands = found.get("reports", {})
    flags = {name: flag_values(argv) for name, argv in commands.items()}
    outs = {name: os.path.join(reports, os.path.relpath(given["--out"], "reports")) for name, given in flags.items()}
    where = "cartpole at a working policy"
    if "variance" in commands and os.path.exists(os.path.join(outs["variance"], "variance_cartpole_gp.csv")):
        # the scenario file is relative to the repository's root
        scenario_file = os.path.join(ROOT, flags["variance"]["--scenario-file"])
        argv = with_flags(commands["variance"], {"--scenario-file": scenario_file})
        rows, _ = variance_rows(argv, outs["variance"])
        link = "[chaos/variance_cartpole_gp](chaos/variance_cartpole_gp.md)"
        claims += gradient_claims(rows, where, link)
        var = rows.pivot_table(index="particles", columns=["estimator", "delta_theta"], values="variance")
        ends = "; ".join(f"{e.upper()} {var[e, d].min():.1e}-{var[e, d].max():.1e} at {d:g}"
                         for e in ("tp", "gr") for d in sorted(rows.delta_theta.unique()))
        claims.append(Claim(f"{where}: TP and GR (resampling) escape the curse of chaos",
                            "TP and GR stay low where RP's variance explodes",
                            f"{ends} (P = {var.index.min()}-{var.index.max()})",
                            "numbers only: no rule was fixed before them", link))
    if "landscape" in commands and os.path.exists(os.path.join(outs["landscape"], "landscape_cartpole_gp.csv")):
        claims.append(lyapunov_claim(found, int(flags["landscape"]["--seed"]), outs["landscape"], where))
    return claims


def lyapunov_claim(found: dict, seed: int, out: str, where: str) -> Claim:
    """The landscape at the scenario (its CSV's rows at the scenario's content, particle count and ``seed``): the
    finite-time Lyapunov exponent and RP_FS's variance along the line, their rank correlation."""
    rows = read_csv(os.path.join(out, "landscape_cartpole_gp.csv"))
    line = rows[(rows.scenario == found["content"]) & (rows.particles == found["particles"])
                & (rows.seed == seed)].sort_values("delta_theta")
    ends = line.iloc[[0, -1]]
    rho = line.ftle_mean.corr(np.log(line.rp_fs_variance), method="spearman")
    return Claim(f"{where}: chaos (a positive Lyapunov exponent) where RP's variance rises",
                 "the closed loop turns chaotic along the line",
                 f"FTLE {ends.ftle_mean.iloc[0]:.3f} at delta theta {ends.delta_theta.iloc[0]:g} to "
                 f"{ends.ftle_mean.iloc[-1]:.3f} at {ends.delta_theta.iloc[-1]:g}; RP_FS's variance x "
                 f"{ends.rp_fs_variance.iloc[-1] / ends.rp_fs_variance.iloc[0]:.2g}; Spearman(FTLE, log variance) "
                 f"{rho:.2f} over {len(line)} points (P = {found['particles']}, the seed fixed)",
                 "numbers only: no rule was fixed before them",
                 "[chaos/landscape_cartpole_gp](chaos/landscape_cartpole_gp.md)")


def all_claims(reports: str) -> list[Claim]:
    claims = [c for task in VARIANCE_COMMANDS for c in variance_claims(task, reports)]
    claims += chaos_scenario_claims(reports)
    claims += [c for name, stem in LEARNING_TABLES.items() if os.path.exists(os.path.join(reports, stem + ".csv"))
               for c in learning_claims(name, stem, reports)]
    claims += reading_claims(reports)
    for claim, paper, finding, stems in learning_findings(reports):
        link = f"`{stems}` (plans/paper_tables.toml)"
        claims.append(Claim(claim, paper, "not run yet", "undecided", link) if finding is None else
                      Claim(claim, paper, finding.details or "-", finding.verdict, link))
    if missing := [name for name, stem in LEARNING_TABLES.items()
                   if not os.path.exists(os.path.join(reports, stem + ".csv"))]:
        claims.append(Claim("The learning tables not in reports/ yet", "Tables 1-2", "; ".join(missing), "not run yet",
                            "`python -m harness.sweep --status` (plans/paper_tables.toml)"))
    return claims


def claims_table(claims: list[Claim], link_prefix: str = "") -> str:
    """The markdown table; ``link_prefix`` is put before each report link (``reports/`` in the README)."""
    lines = ["| claim | the paper | ours | verdict | report |", "|---|---|---|---|---|"]
    for c in claims:
        report = c.report.replace("](", f"]({link_prefix}") if c.report.startswith("[") else c.report
        lines.append(f"| {c.claim} | {c.paper} | {c.ours} | {c.verdict} | {report} |")
    return "\n".join(lines)


def report_index(reports: str) -> list[str]:
    """A line per report (``*.md`` under ``reports``, the archive last): its link and its title."""
    paths = sorted(os.path.relpath(os.path.join(folder, name), reports)
                   for folder, _, names in os.walk(reports) for name in names
                   if name.endswith(".md") and name != "SUMMARY.md" and ".cache" not in folder
                   and not name.endswith("_demo.md"))  # python -m harness.learn's demonstration: not a result
    paths.sort(key=lambda path: (path.startswith("archive"), path.count(os.sep), path))
    lines = []
    for path in paths:
        with open(os.path.join(reports, path)) as f:
            title = f.readline().lstrip("# ").strip()
        lines.append(f"- [{path}]({path}): {title}")
    return lines


def summary_text(claims: list[Claim], reports: str) -> str:
    return "\n".join([
        "# What reproduces", "",
        "Written by `python -m harness.summary` from the committed results (verdict rules: "
        "`harness/summary.py`). The README shows the same table, the learning tables' rows merged into one.", "",
        claims_table(claims), "",
        "Every report states its command, settings and scenario; `python -m harness.reproduce` recomputes "
        "them at a small size and compares.", "",
        "## Every report", "",
        "`archive/` holds results kept for the record: the gradient reports at the earlier, flat scenario, the "
        "conventions grid and runs superseded by a bug fix (their commands name the folders they were written to).",
        "", *report_index(reports), ""])


def readme_with_block(readme: str, start: str, end: str, text: str) -> str:
    """``readme`` with ``text`` between the markers ``start`` and ``end``."""
    if start not in readme or end not in readme:
        raise ValueError(f"README.md lacks the markers {start!r} ... {end!r}")
    head, rest = readme.split(start, 1)
    _, tail = rest.split(end, 1)
    return head + start + "\n" + text + "\n" + end + tail


def readme_with_table(readme: str, claims: list[Claim]) -> str:
    return readme_with_block(readme, CLAIMS_START, CLAIMS_END, claims_table(readme_claims(claims), "reports/"))


def speed_text(reports: str) -> str:
    """The README's speed section: ``harness.bench``'s targets, from its CSVs in ``reports``."""
    if not os.path.exists(os.path.join(reports, "bench.csv")):
        return "Not measured yet: `python -m harness.bench` writes reports/bench.md."
    table, learning = bench.saved_results(reports)
    lines = bench.report_targets(reports, table, learning)
    return "\n".join(["From [reports/bench.md](reports/bench.md) (`python -m harness.bench`, on "
                      f"{table.machine.iloc[0]}); a target not met is what is left.", "", *lines[2:-1]])


def readme_text(readme: str, claims: list[Claim], reports: str) -> str:
    """The README with its generated blocks: the claims table and the speed section."""
    return readme_with_block(readme_with_table(readme, claims), SPEED_START, SPEED_END, speed_text(reports))


def main(argv=None) -> None:
    args = parse(Args, argv)
    reports = args.reports if os.path.isabs(args.reports) else os.path.join(ROOT, args.reports)
    claims = all_claims(reports)
    targets = {os.path.join(reports, "SUMMARY.md"): summary_text(claims, reports)}
    readme = os.path.join(ROOT, "README.md")
    with open(readme) as f:
        targets[readme] = readme_text(f.read(), claims, reports)
    stale = []
    for path, text in targets.items():
        old = open(path).read() if os.path.exists(path) else None
        if old != text:
            stale.append(path)
            if not args.check:
                with open(path, "w") as f:
                    f.write(text)
    if args.check and stale:
        print(f"error: {', '.join(stale)} not as python -m harness.summary writes it: run it", file=sys.stderr)
        raise SystemExit(1)
    print(f"{'checked' if args.check else 'wrote'} {', '.join(targets)}", file=sys.stderr)


if __name__ == "__main__":
    run_command(main)
