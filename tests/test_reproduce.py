"""harness.reproduce: the agreement rules, the commands it reruns, and one check end to end (slow)."""

import os

import pandas as pd
import pytest
from scipy import stats

import tasks
from harness import learn, reproduce
from harness.cli import parse
from harness.records import Command, write_metadata

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
    """A variance report's CSV and metadata as harness.variance writes them (the parts read)."""
    pd.DataFrame(dict(task="cartpole", model="gp", estimator=["rp", "tp"], particles=10, delta_theta=0.0,
                      repeats=10, seed=0, scenario=content_hash, variance=variance)).to_csv(stem + ".csv", index=False)
    objective = [dict(model="gp", delta_theta=0.0, value=j[0], ci=j[1]),
                 dict(model="gp", delta_theta=1.5, value=25.0, ci=0.5)]
    write_metadata(stem, Command("harness.variance", ["--task", "cartpole", "--repeats", "10", "--seed", "0"]),
                   content_hash, objective)


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
    write_metadata(stem, Command("harness.compare", ["--task", "cartpole", "--repeats", "20", "--reference-repeats",
                                                     "100", "--seed", "0"]), "abc123", [])
    rows = reproduce.committed_rows(stem)
    assert rows.reference.tolist() == ["jax-lr-P1000-R100"] and rows.variance.tolist() == [2.0]


def test_reproduce_reads_the_metadata_not_the_markdown(tmp_path):
    """The command, content hash and J come from ``{stem}.json``: a markdown that says otherwise
    is not read."""
    committed, recomputed = str(tmp_path / "committed"), str(tmp_path / "recomputed")
    write_cells(committed, "abc123", [1.0, 2.0])
    write_cells(recomputed, "abc123", [1.0, 2.0])
    with open(committed + ".md", "w") as f:
        f.write("Command: `python -m harness.variance --task cartpole --repeats 30 --seed 0`\n"
                "- Scenario: ... Content hash def456 (theta0, ...)\n"
                "- J under the gp model (2000 particles, 95 % interval; at most 30): 1.00 +- 0.01 at delta theta = 0\n")
    assert len(reproduce.committed_rows(committed)) == 2  # repeats 10 and abc123, as the metadata says
    rows = {row["quantity"]: row for row in reproduce.scenario_and_objective(committed, recomputed)}
    assert rows["scenario content hash"]["committed"] == "abc123" and rows["J on gp, delta theta 0"]["agrees"]


def test_a_report_without_metadata_is_refused_with_the_command_that_writes_it(tmp_path):
    stem = str(tmp_path / "variance_cartpole_gp")
    write_cells(stem, "abc123", [1.0, 2.0])
    os.remove(stem + ".json")
    with open(stem + ".md", "w") as f:
        f.write("# Gradient variance\n\nCommand: `python -m harness.variance --task cartpole --repeats 10`\n")
    with pytest.raises(ValueError) as error:
        reproduce.committed_rows(stem)
    assert str(error.value) == (f"{stem}.json is missing: write it with the report's own command, which reuses the "
                                f"committed rows: python -m harness.variance --task cartpole --repeats 10 "
                                f"--out {tmp_path}")


def test_reproduce_refuses_a_report_without_metadata_before_computing_anything(tmp_path):
    write_cells(str(tmp_path / "variance_cartpole_gp"), "abc123", [1.0, 2.0])
    with pytest.raises(ValueError, match="compare_cartpole.json is missing"):
        reproduce.run(reproduce.Args(checks="variance_cartpole_gp,compare_cartpole", reports=str(tmp_path),
                                     out=str(tmp_path / "out")))
    assert not os.path.exists(tmp_path / "out")


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
