"""harness.summary: the committed claims table is what the command writes, and its verdict rules."""

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
    assert readme == summary.readme_with_table(readme, claims), "the README's table is stale: python -m harness.summary"
    edited = readme.replace("| holds |", "| reproduced |", 1)
    assert edited != readme and summary.readme_with_table(edited, claims) == readme  # a hand edit is overwritten


def test_the_verdict_rules():
    assert summary.cell_rule(8, 8) == "holds" and summary.cell_rule(0, 8) == "does not hold"
    assert summary.cell_rule(5, 8) == "mixed"
    assert summary.jump_rule(np.array([1e2, 4e5])) == "holds"
    assert summary.jump_rule(np.array([0.02, 0.3])) == "reversed"
    assert summary.jump_rule(np.array([0.5, 40.0])) == "mixed"
