"""harness.reproduce: the agreement rules, the commands it reruns, and one check end to end (slow)."""

import os

import pandas as pd
import pytest
from scipy import stats

import tasks
from harness import learn, reproduce
from harness.cli import parse

REPORTS = os.path.join(os.path.dirname(__file__), "..", "reports")


def test_with_flags_replaces_and_appends():
    argv = ["--task", "cartpole", "--repeats", "30", "--particles", "10,30"]
    assert reproduce.with_flags(argv, {"--repeats": "10", "--out": "/tmp/x"}) == [
        "--task", "cartpole", "--particles", "10,30", "--repeats", "10", "--out", "/tmp/x"]


def test_variance_rule_is_the_f_interval():
    low, high = stats.f.ppf([0.025, 0.975], 9, 29)
    assert reproduce.variance_rule("v", 1.0, 30, 0.99 * high, 10)["agrees"]
    assert not reproduce.variance_rule("v", 1.0, 30, 1.01 * high, 10)["agrees"]
    assert not reproduce.variance_rule("v", 1.0, 30, 0.99 * low, 10)["agrees"]


def test_mean_rule_is_the_interval_of_a_difference():
    assert reproduce.mean_rule("J", 10.0, 0.3, 10.49, 0.4)["agrees"]  # bound 0.5
    assert not reproduce.mean_rule("J", 10.0, 0.3, 10.51, 0.4)["agrees"]


def test_learning_command_rebuilds_the_committed_rows_key():
    """The command reproduce reruns for a committed learning table gives its rows' settings
    and task options (the old conventions of the P = 50 table among them)."""
    stem = os.path.join(REPORTS, "learn_cartpole_angle_k1_quick_p50")
    argv, rows = reproduce.learn_command(stem, "pilco", 2)
    args = parse(learn.Args, argv)
    assert sorted(rows.repeat.unique()) == [0, 1]
    assert set(rows.settings) == {args.settings_name("pilco")}
    assert set(rows.task_options) == {tasks.describe(args.make_task())}


def write_cells(stem, content_hash, variance, j=(20.0, 0.5)):
    """A variance report's CSV and markdown as harness.variance writes them (the parts read)."""
    pd.DataFrame(dict(task="cartpole", model="gp", estimator=["rp", "tp"], particles=10, delta_theta=0.0,
                      repeats=10, seed=0, scenario=content_hash, variance=variance)).to_csv(stem + ".csv", index=False)
    with open(stem + ".md", "w") as f:
        f.write(f"Command: `python -m harness.variance --task cartpole --repeats 10 --seed 0`\n"
                f"- Scenario: ... Content hash {content_hash} (theta0, ...)\n"
                f"- J under the gp model (2000 particles, 95 % interval; at most 30): {j[0]} +- {j[1]} at delta theta "
                f"= 0; 25.0 +- 0.5 at delta theta = 1.5.\n")


def test_compare_cells_flags_a_changed_scenario_and_variance(tmp_path):
    committed, same, other = (str(tmp_path / name) for name in ("committed", "same", "other"))
    write_cells(committed, "abc123", [1.0, 2.0])
    write_cells(same, "abc123", [1.5, 2.2], j=(20.3, 0.5))
    write_cells(other, "def456", [50.0, 2.0], j=(28.0, 0.5))
    agree = reproduce.compare_cells(committed, same, {})
    assert len(agree) == 5 and all(row["agrees"] for row in agree)  # hash, 2 x J, 2 variances
    differ = {row["quantity"]: row["agrees"] for row in reproduce.compare_cells(committed, other, {})}
    assert not differ["scenario content hash"] and not differ["J on gp, delta theta 0"]
    assert differ["J on gp, delta theta 1.5"]
    assert not differ["variance: model gp, estimator rp, particles 10, delta_theta 0.0"]


def test_committed_rows_are_those_of_the_report_s_reference(tmp_path):
    """A compare CSV holds cells against two references (R30, then R100): the report's command
    names one, and only its cells are compared (before, both were: every cell counted twice)."""
    stem = str(tmp_path / "compare_cartpole")
    pd.DataFrame(dict(task="cartpole", model="gp", estimator="rp", particles=10, repeats=20, seed=0, scenario="abc123",
                      reference=["jax-lr-P1000-R30", "jax-lr-P1000-R100"], variance=[1.0, 2.0])
                 ).to_csv(stem + ".csv", index=False)
    with open(stem + ".md", "w") as f:
        f.write("Command: `python -m harness.compare --task cartpole --repeats 20 --reference-repeats 100 --seed 0`\n"
                "- Scenario: ... Content hash abc123 (theta0, ...)\n")
    rows = reproduce.committed_rows(stem)
    assert rows.reference.tolist() == ["jax-lr-P1000-R100"] and rows.variance.tolist() == [2.0]


def test_unknown_check_is_refused():
    with pytest.raises(ValueError, match="unknown check"):
        reproduce.Args(checks="variance_cartpol")


@pytest.mark.slow
def test_reproduce_recomputes_the_learning_table_s_pilco_runs(tmp_path):
    """The committed P = 50 table's PILCO runs of seeds 0 and 1, rerun: every quantity agrees."""
    table = reproduce.run(reproduce.Args(checks="learn_cartpole_angle_k1_quick_p50", reports=REPORTS,
                                         out=str(tmp_path)))
    assert len(table) == 3 and table.agrees.all(), table
    assert os.path.exists(tmp_path / "reproduce.md")
