"""The experiments end to end at a tiny size: the variance experiment (with its resume and
argument checks) and the benchmark."""

import os

import pandas as pd
import pytest

from harness import variance

TINY = ["--particles", "5,8", "--repeats", "3", "--estimators", "rp,biw_lr,tp", "--scenario-trials", "1",
        "--scenario-steps", "3", "--scenario-particles", "5"]


def test_variance_runs_end_to_end_and_resumes(tmp_path, capsys):
    out = str(tmp_path)
    variance.main(TINY + ["--out", out])
    stem = os.path.join(out, "variance_cartpole_gp")
    table = pd.read_csv(stem + ".csv")
    assert len(table) == 3 * 2 * 2  # estimators x particle counts x delta thetas
    assert (table.variance > 0).all() and (table.nan_count == 0).all()
    assert os.path.getsize(stem + ".png") > 1000
    report = open(stem + ".md").read()
    assert "Scenario:" in report and "delta_theta | estimator" in report
    capsys.readouterr()
    variance.main(TINY + ["--out", out])  # a rerun finds every cell done
    assert "variance" not in capsys.readouterr().err.split("wrote")[0]
    assert len(pd.read_csv(stem + ".csv")) == len(table)


@pytest.mark.parametrize("argv, message", [
    (["--model", "ode"], "valid models"),
    (["--estimators", "rp,reinforce"], "valid estimators"),
    (["--task", "pendulum"], "valid tasks"),
    (["--repeats", "1"], "repeats"),
])
def test_bad_arguments(argv, message):
    with pytest.raises(ValueError, match=message):
        variance.main(argv)


def test_bench_runs_tiny(tmp_path):
    from harness import bench

    bench.main(["--particles", "6", "--repeats", "2", "--trials", "1", "--gp-steps", "2", "--estimators", "rp,tp",
                "--out", str(tmp_path)])
    table = pd.read_csv(tmp_path / "bench.csv")
    assert set(table.estimator) == {"rp", "tp"} and (table.median_s > 0).all() and (table.peak_memory_mb > 0).all()
    assert "Ratio to RP" in (tmp_path / "bench.md").read_text()
