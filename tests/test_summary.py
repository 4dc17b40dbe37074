"""harness.summary: the committed claims table and speed section are what the command writes, and its verdict
rules."""

import os

import numpy as np

from harness import summary
from harness.records import ROOT


def test_the_committed_summary_and_readme_table_are_what_the_command_writes():
    claims = summary.all_claims(os.path.join(ROOT, "reports"))
    with open(os.path.join(ROOT, "reports", "SUMMARY.md")) as f:
        assert f.read() == summary.summary_text(claims, os.path.join(ROOT, "reports")), \
            "reports/SUMMARY.md is stale: run python -m harness.summary"
    with open(os.path.join(ROOT, "README.md")) as f:
        readme = f.read()
    reports = os.path.join(ROOT, "reports")
    assert readme == summary.readme_text(readme, claims, reports), "the README is stale: python -m harness.summary"
    for old, new in [("| holds |", "| reproduced |"), ("(target 0.2", "(target 0.1")]:
        edited = readme.replace(old, new, 1)
        assert edited != readme and summary.readme_text(edited, claims, reports) == readme  # hand edits are overwritten


def test_the_verdict_rules():
    assert summary.cell_rule(8, 8) == "holds" and summary.cell_rule(0, 8) == "does not hold"
    assert summary.cell_rule(5, 8) == "mixed"
    assert summary.jump_rule(np.array([1e2, 4e5])) == "holds"
    assert summary.jump_rule(np.array([0.02, 0.3])) == "reversed"
    assert summary.jump_rule(np.array([0.5, 40.0])) == "mixed"


def test_the_learning_claims_come_from_the_csvs_once_they_are_in_reports(tmp_path):
    """With no CSV a claim is "not run yet"; with the k = 0.01 column's CSV, claim (d) is evaluated from it
    (``claims.claim_beats``), and claim (b) waits for a second k."""
    from test_learn_report import rows_of, wins

    assert [finding for _, _, finding, _ in summary.learning_findings(str(tmp_path))] == [None, None, None]
    rows_of({**wins("tp+sigma_n", 9, k=0.01), **wins("tp", 5, k=0.01), **wins("lr", 5, k=0.01)}).to_csv(
        tmp_path / "learn_cartpole_angle_k0.01.csv", index=False)
    claim_b, claim_d, tip = [finding for _, _, finding, _ in summary.learning_findings(str(tmp_path))]
    assert claim_b is None and tip is None
    assert claim_d.details == "TP+SIGMA_N 0.90 [0.60, 0.98] n=10, TP 0.50 [0.24, 0.76] n=10"
    assert claim_d.verdict.startswith("holds on the point estimates; not significant at 0.05, so undecided")
    rows_of({**wins("tp", 4, k=16.0), **wins("lr", 5, k=16.0)}).to_csv(tmp_path / "learn_cartpole_angle_k16.csv",
                                                                       index=False)
    claim_b = summary.learning_findings(str(tmp_path))[0][2]
    assert claim_b.verdict.startswith("not measured (no other method of the paper")


def test_the_readme_stays_one_page():
    """What a new user reads first (issue: a README of at most 12 KB; results live in reports/ and docs/)."""
    assert os.path.getsize(os.path.join(ROOT, "README.md")) <= 12 * 1024


def test_the_readme_merges_the_learning_tables_rows_into_one():
    """SUMMARY.md keeps a row per learning table; the README one row in place of the first, with each table's
    agreement and their sum, so that it stays one page as the tables land."""
    row = summary.Claim("a gradient claim", "4e5", "x 10", "mixed", "[variance](variance.md)")
    k1 = summary.Claim("learning, cartpole, angle cost, k = 1: success rates", "Table 1's column", "10 repeats",
                       summary.agreement(6, 8), "[k1](k1.md)",
                       summary.TableAgreement("cartpole, angle cost, k = 1", "10", 6, 8, ("rp_fs", "gr_fs")))
    k16 = k1._replace(claim="learning, cartpole, angle cost, k = 16: success rates",
                      cells=summary.TableAgreement("cartpole, angle cost, k = 16", "5", 2, 5))
    after = summary.Claim("a reading", "0.23", "1.00", "outside", "[r](r.md)")
    merged = summary.readme_claims([row, k1, after, k16])
    assert [c.claim for c in merged] == [row.claim, "learning tables at the paper's settings: success rates per cell",
                                         after.claim]
    assert merged[1].ours == ("cartpole, angle cost, k = 1 (10 repeats): 6 of 8 (outside: rp_fs, gr_fs); "
                              "cartpole, angle cost, k = 16 (5 repeats): 2 of 5")
    assert merged[1].verdict == "agrees in 8 of 13 cells"
    assert summary.readme_claims([row, after]) == [row, after]
    assert "(reports/SUMMARY.md)" in summary.claims_table(merged, "reports/")
