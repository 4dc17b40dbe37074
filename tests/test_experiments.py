"""The gradient experiments end to end at a tiny size (variance, landscape, compare, bench;
resume and argument checks), the scenario, and the statistics they report."""

import os
from types import SimpleNamespace

import jax
import numpy as np
import pandas as pd
import pytest

import tasks
from harness import variance

TINY = ["--particles", "5,8", "--repeats", "3", "--estimators", "rp,biw_lr,tp", "--scenario-estimator", "tp",
        "--scenario-trials", "1",
        "--scenario-steps", "3", "--scenario-particles", "5"]


@pytest.mark.slow
def test_variance_runs_on_mjx(tmp_path):
    variance.main(TINY + ["--model", "mjx", "--estimators", "rp,tp", "--particles", "5", "--out", str(tmp_path)])
    table = pd.read_csv(tmp_path / "variance_cartpole_mjx.csv")
    assert len(table) == 4 and (table.variance > 0).all() and (table.nan_count == 0).all()


def test_cell_statistics_against_numpy():
    """The variance experiment's numbers from a hand-made set of estimates: the variance is the
    trace of the covariance (ddof 1) of the finite estimates, the norm that of their mean; a
    non-finite estimate is counted and left out; k_LR and ESS are NaN-aware means."""
    grads = np.array([[1.0, 2.0], [3.0, -1.0], [np.nan, 0.0], [2.0, 5.0]])
    rep = variance.Repeats(grads, values=np.array([1.0, 2.0, 4.0, 5.0]), reported=np.array([0.5, np.nan, 1.5, 1.0]),
                           k_lr=np.array([0.2, 0.4, np.nan, 0.6]), ess=np.full(4, np.nan), nan_count=3,
                           seconds=0.1, compile_seconds=2.0)
    stats = variance.cell_statistics(rep)
    finite = grads[[0, 1, 3]]
    assert stats["variance"] == pytest.approx(np.var(finite[:, 0], ddof=1) + np.var(finite[:, 1], ddof=1), rel=1e-14)
    assert stats["variance"] == pytest.approx(1.0 + 9.0, rel=1e-14)  # the columns' variances by hand
    assert stats["grad_norm"] == pytest.approx(np.hypot(2.0, 2.0), rel=1e-14)
    assert stats["value"] == 3.0 and stats["value_std"] == pytest.approx(np.std([1.0, 2.0, 4.0, 5.0], ddof=1))
    assert stats["reported_variance"] == 1.0 and stats["mean_k_lr"] == pytest.approx(0.4)
    assert np.isnan(stats["mean_ess"]) and stats["nonfinite_estimates"] == 1 and stats["nan_count"] == 3


def test_variance_runs_end_to_end_and_resumes(tmp_path, capsys):
    out = str(tmp_path)
    variance.main(TINY + ["--out", out])
    stem = os.path.join(out, "variance_cartpole_gp")
    table = pd.read_csv(stem + ".csv")
    assert len(table) == 3 * 2 * 2  # estimators x particle counts x delta thetas
    assert (table.variance > 0).all() and (table.nan_count == 0).all()
    assert os.path.getsize(stem + ".png") > 1000
    report = open(stem + ".md").read()
    assert "Scenario:" in report and "delta_theta | estimator" in report and "Content hash" in report
    assert "J under the gp model (2000 particles" in report and "at delta theta = 1.5" in report
    capsys.readouterr()
    variance.main(TINY + ["--out", out])  # a rerun finds every cell done
    err = capsys.readouterr().err
    assert f"computed 0 cells, reused 12 from {stem}.csv" in err and "variance 1" not in err
    assert len(pd.read_csv(stem + ".csv")) == len(table)


def test_rows_of_a_changed_theta0_are_never_reused(tmp_path, capsys):
    """The cached scenario's theta0 moved by 1e-3 (same settings, so the same cache file):
    every cell is computed again, under a new content hash, beside the old rows."""
    from harness.scenario import load_scenario, save_scenario

    out = str(tmp_path)
    argv = TINY + ["--estimators", "rp", "--particles", "5", "--delta-theta", "0", "--out", out]
    variance.main(argv)
    [cached] = (tmp_path / ".cache").glob("scenario_cartpole_*.json")
    stem = str(cached)[:-len(".json")]
    saved = load_scenario(stem, "cartpole")
    scenario = saved["scenario"]
    save_scenario({**saved, "scenario": scenario._replace(theta=jax.tree.map(lambda t: t + 1e-3, scenario.theta))},
                  stem)
    capsys.readouterr()
    variance.main(argv)
    assert "computed 1 cells, reused 0" in capsys.readouterr().err
    rows = pd.read_csv(tmp_path / "variance_cartpole_gp.csv")
    assert len(rows) == 2 and rows.scenario.nunique() == 2 and rows.scenario_settings.nunique() == 1


def test_a_pinned_scenario_is_used_whatever_the_code_and_rebuild_ignores_it(tmp_path, capsys, monkeypatch):
    """Pinned once, the scenario is reused after a code change (every cell found done, no
    build); --rebuild-scenario builds under the current code instead."""
    from harness import scenario as scenario_lib

    out, pinned = str(tmp_path / "out"), str(tmp_path / "pinned")
    argv = TINY + ["--estimators", "rp", "--particles", "5", "--delta-theta", "0", "--out", out,
                   "--scenarios-dir", pinned]
    variance.main(argv + ["--pin-scenario"])
    [pinned_file] = (tmp_path / "pinned").glob("scenario_cartpole_*.json")
    stem = str(pinned_file)[:-len(".json")]
    report = open(os.path.join(out, "variance_cartpole_gp.md")).read()
    assert f"built under the current code and pinned to {stem}.{{npz,json}}" in report
    assert "code" in scenario_lib.load_scenario(stem, "cartpole")["provenance"]
    monkeypatch.setattr(scenario_lib, "code_digest", lambda: "changed-code")  # a new cache key
    capsys.readouterr()
    variance.main(argv)
    err = capsys.readouterr().err
    assert "the pinned" in err and "computed 0 cells, reused 1" in err and "scenario: trial" not in err
    assert f"the pinned {stem}.{{npz,json}}" in open(os.path.join(out, "variance_cartpole_gp.md")).read()
    variance.main(argv + ["--rebuild-scenario"])  # the code changed: no cached build under it
    err = capsys.readouterr().err
    assert "the pinned" not in err and "scenario: trial 1 done" in err


@pytest.mark.parametrize("argv, message", [
    (["--model", "ode"], "valid models"),
    (["--estimators", "rp,reinforce"], "valid estimators"),
    (["--task", "pendulum"], "valid tasks"),
    (["--repeats", "1"], "repeats"),
])
def test_bad_arguments(argv, message):
    with pytest.raises(ValueError, match=message):
        variance.main(argv)


def test_variance_runs_on_the_unicycle_at_its_pinned_scenario(tmp_path):
    """The unicycle's own command (its pinned scenario: no build) at a tiny size."""
    variance.main(["--task", "unicycle", "--estimators", "rp,tp", "--particles", "5", "--repeats", "2",
                   "--delta-theta", "0", "--out", str(tmp_path)])
    table = pd.read_csv(tmp_path / "variance_unicycle_gp.csv")
    assert set(table.estimator) == {"rp", "tp"} and np.isfinite(table.variance).all()
    assert "the pinned" in (tmp_path / "variance_unicycle_gp.md").read_text()


def test_bench_runs_tiny(tmp_path):
    from harness import bench

    argv = ["--particles", "6", "--repeats", "2", "--trials", "1", "--gp-steps", "2", "--estimators", "rp,tp",
            "--learning-methods", "", "--out", str(tmp_path)]
    bench.main(argv)
    table = pd.read_csv(tmp_path / "bench.csv")
    assert set(table.estimator) == {"rp", "tp"} and (table.median_s > 0).all() and (table.peak_memory_mb > 0).all()
    assert set(table.dtype) == {"float64", "float32"} and (table.roofline_fraction > 0).all()
    report = (tmp_path / "bench.md").read_text()
    assert "Ratio to RP, float32" in report and "Roofline fraction, float64" in report
    assert "## Targets" in report and "timed whole (`python -m harness.learn --preset paper" in report
    # --report-only rewrites the report from the CSVs and the run's flags (bench.json) alone, whatever flags it
    # is given, also from a bench.csv of older code (fewer columns)
    table.drop(columns=["matmul_gflops", "gp_points"]).to_csv(tmp_path / "bench.csv", index=False)
    (tmp_path / "bench.md").unlink()
    bench.main(["--report-only", "--out", str(tmp_path)])
    assert (tmp_path / "bench.md").read_text() == report


def test_the_bench_targets_are_judged_on_the_runs_own_numbers():
    from harness import bench

    gflop, rate = np.array([29.2, 43.7]), 200.0
    table = pd.DataFrame(dict(estimator=["rp", "tp"], dtype="float32", particles=300, median_s=[0.19, 0.30],
                              gflop=gflop, matmul_gflops=rate, gp_points=450,
                              roofline_fraction=gflop / rate / np.array([0.19, 0.30])))
    learning = pd.DataFrame(dict(method="tp", dtype="float32", rbf="direct", gp="fitc300", total_min=[12.5]))
    text = "\n".join(bench.target_lines(table, learning, 11.5))
    assert "RP, float32, P = 300, N = 450: 0.190 s (target 0.20 s: met)" in text
    assert "TP, float32, P = 300, N = 450: 0.300 s (target 0.25 s: not met)" in text
    assert "(29.2 GFLOP) take 0.146 s at this run's float32 matmul rate, so the target asks for a roofline " \
           "fraction of 0.73" in text
    assert "RP's roofline fraction, float32, P = 300: 0.77 (goal 0.4: met)" in text
    assert "projected: 12.5 min (target 12 min: not met)" in text and "after each trial in its CSV): 11.5 min." in text


def test_learning_time_projection_sums_the_quadratic_over_trials():
    from harness.bench_learning import project

    per_step = lambda rows: 0.1 + 1e-3 * rows + 1e-6 * rows**2  # noqa: E731
    rows = 30 * np.arange(1, 16)
    timed = {30 * t: per_step(30 * t) for t in (1, 8, 15)}
    expected = 600 * sum(per_step(r) for r in rows)
    assert project(timed, rows, 600) == pytest.approx(expected, rel=1e-9)
    # FITC with 300 inducing inputs: trials past 300 rows cost a 300-row step.
    capped = {min(r, 300): per_step(min(r, 300)) for r in (30, 240, 450)}
    assert project(capped, np.minimum(rows, 300), 600) == pytest.approx(
        600 * sum(per_step(min(r, 300)) for r in rows), rel=1e-9)


@pytest.mark.slow
def test_learning_time_measurement_runs(tmp_path):
    from harness import bench_learning

    table = bench_learning.measure(["lr"], ["lr"], fitc_methods=["lr"], timed_steps=1)
    assert list(table.dtype) == ["float64", "float32", "float64"] and list(table.gp) == ["full", "full", "fitc300"]
    assert (table.total_min > table.optimise_min).all()
    assert "paper-setting" in "\n".join(bench_learning.report_lines(table))


def test_content_hashes_read_back_as_text(tmp_path):
    """Hex hashes that look like numbers (``06172e414402``: 6.172e414402, inf) or lose a leading
    zero must come back as written, or a rerun recomputes the cell and a report's
    ``rows.scenario == content`` drops its rows."""
    from harness.records import ResultTable

    for content in ("06172e414402", "012345678901"):  # alone in their column, as in a fresh CSV
        path = str(tmp_path / f"{content}.csv")
        ResultTable(path, ["scenario"]).append(dict(scenario=content, variance=1.0))
        table = ResultTable(path, ["scenario"])
        assert table.read().scenario.tolist() == [content] and table.has(dict(scenario=content))


def test_result_table_writes_rows_in_its_header_order_and_skips_written_keys(tmp_path):
    from harness.records import ResultTable

    path = str(tmp_path / "table.csv")
    ResultTable(path, ["cell"]).append(dict(cell="a", variance=1.5, seconds=2.0))
    table = ResultTable(path, ["cell"])  # a rerun
    assert table.has(dict(cell="a")) and not table.has(dict(cell="b"))
    table.extend([dict(seconds=4.0, cell="b", variance=3.5), dict(cell="e", variance=0.5, seconds=1.0)])  # key order
    assert pd.read_csv(path).drop(columns="code_version").to_dict("list") == dict(
        cell=["a", "b", "e"], variance=[1.5, 3.5, 0.5], seconds=[2.0, 4.0, 1.0])
    with pytest.raises(ValueError, match="another --out folder"):
        table.append(dict(cell="c", variance=1.0))
    table.append(dict(cell="d", variance=1.0, seconds=1.0, scenario="abc"))  # a newer version's column
    rows = pd.read_csv(path)
    assert list(rows.columns) == ["cell", "variance", "seconds", "code_version", "scenario"]
    assert list(rows.cell) == ["a", "b", "e", "d"]
    assert rows.scenario.isna().tolist() == [True, True, True, False]
    assert table.summary() == f"computed 3 cells, reused 1 from {path}"
    with pytest.raises(ValueError, match="other rows"):  # one row of a batch lacks the batch's new column
        table.extend([dict(cell="f", variance=1.0, seconds=1.0, scenario="abc", trial=2),
                      dict(cell="g", variance=1.0, seconds=1.0, scenario="abc")])
    table.extend([])
    assert pd.read_csv(path).equals(rows)  # neither wrote anything
    ResultTable(str(tmp_path / "new.csv"), ["cell"]).extend([])
    assert not (tmp_path / "new.csv").exists()


def test_result_rows_say_which_code_wrote_them(tmp_path, monkeypatch):
    """Every row carries the code version of the process that wrote it (a row may bring its own:
    a learning batch's trials ran under the code of their own session); a rerun by other code
    says so; two processes that append to one file keep its columns aligned, whatever each of
    them saw when it opened the file."""
    from harness import records

    version = records.code_version()
    assert version  # a git checkout's commit, or the source digest
    path = str(tmp_path / "table.csv")
    first, second = records.ResultTable(path, ["cell"]), records.ResultTable(path, ["cell"])
    first.append(dict(cell="a", variance=1.0))
    second.extend([dict(cell="b", variance=2.0, seconds=3.0), dict(cell="c", variance=4.0, seconds=5.0,
                                                                    code_version="older")])
    first.append(dict(variance=6.0, cell="d", seconds=7.0))  # opened before `second` added `seconds`
    rows = pd.read_csv(path)
    assert list(rows.columns) == ["cell", "variance", "code_version", "seconds"]
    assert rows.cell.tolist() == ["a", "b", "c", "d"] and rows.variance.tolist() == [1.0, 2.0, 4.0, 6.0]
    assert rows.code_version.tolist() == [version, version, "older", version]
    assert rows.seconds.isna().tolist() == [True, False, False, False] and rows.seconds.tolist()[1:] == [3.0, 5.0, 7.0]
    rerun = records.ResultTable(path, ["cell"])
    assert rerun.has(dict(cell="a")) and rerun.summary().endswith(f"reused 1 from {path}")
    assert rerun.has(dict(cell="c")) and f"(written by code older; this run's is {version})" in rerun.summary()
    monkeypatch.setattr(records, "code_version", lambda: "newer")  # the code changed since the rows were written
    assert f"(written by code {', '.join(sorted(['older', version]))}; this run's is newer)" in rerun.summary()


def test_writers_take_turns_and_a_column_adding_rewrite_is_atomic(tmp_path, monkeypatch):
    """Writers hold an exclusive lock (PATH.lock) while they append or rewrite: another
    append, here one that adds a column, waits for it, while a reader goes on and sees the
    whole table as it was. A rewrite that dies half-way leaves the table as it was."""
    import fcntl
    import threading

    from harness import records

    path = str(tmp_path / "table.csv")
    table = records.ResultTable(path, ["cell"])
    table.append(dict(cell="a", variance=1.0))
    before = records.read_csv(path)
    with open(path + ".lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX)  # as another process's extend holds it
        writer = threading.Thread(target=table.append, args=(dict(cell="b", variance=2.0, seconds=3.0),))
        writer.start()
        writer.join(timeout=0.5)
        assert writer.is_alive()
        pd.testing.assert_frame_equal(table.read(), before)
    writer.join()
    rows = records.read_csv(path)
    assert rows.cell.tolist() == ["a", "b"] and rows.seconds.isna().tolist() == [True, False]

    write_csv = pd.DataFrame.to_csv

    def dies(frame, path_or_buf=None, **kwargs):  # a rewrite to a file stops half-way
        if path_or_buf is None:
            return write_csv(frame, **kwargs)
        with open(path_or_buf, "w") as f:
            f.write("cell,vari")
        raise OSError("disk full")

    monkeypatch.setattr(pd.DataFrame, "to_csv", dies)
    with pytest.raises(OSError, match="disk full"):
        table.append(dict(cell="c", variance=4.0, seconds=5.0, trial=1))  # a new column: a rewrite
    pd.testing.assert_frame_equal(records.read_csv(path), rows)


def test_commits_that_look_like_numbers_stay_text(tmp_path, monkeypatch):
    """Short commits such as 0123456 or 1e23456 read as numbers (123456, inf) unless read as text;
    a rewrite (a row bringing a new column) would then write the number back for good."""
    from harness import records

    path = str(tmp_path / "table.csv")
    for version in ("0123456", "1e23456"):
        monkeypatch.setattr(records, "code_version", lambda: version)
        records.ResultTable(path, ["cell"]).append(dict(cell=f"at {version}", variance=1.0))
    records.ResultTable(path, ["cell"]).append(dict(cell="x", variance=1.0, seconds=2.0, code_version="abc"))
    assert records.read_csv(path).code_version.tolist() == ["0123456", "1e23456", "abc"]
    rerun = records.ResultTable(path, ["cell"])
    assert rerun.has(dict(cell="at 0123456"))
    assert rerun.summary().endswith("(written by code 0123456; this run's is 1e23456)")
    (tmp_path / "empty.csv").write_text("")  # a file created and never written
    empty = records.ResultTable(str(tmp_path / "empty.csv"), ["cell"])
    empty.append(dict(cell="a", variance=1.0))
    assert records.read_csv(str(tmp_path / "empty.csv")).cell.tolist() == ["a"]


def test_code_outside_a_git_checkout_is_named_by_its_source_digest(tmp_path, monkeypatch):
    from harness import records

    for package in records.CODE_PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "module.py").write_text(f"NAME = {package!r}\n")
    monkeypatch.setattr(records, "ROOT", str(tmp_path))  # an installation without .git
    before = records.code_version.__wrapped__()  # uncached
    assert before == "source " + records.source_digest(records.CODE_PACKAGES) and len(before) == len("source ") + 12
    (tmp_path / "models" / "module.py").write_text("NAME = 'changed'\n")
    assert records.code_version.__wrapped__() != before


def test_alignment_statistics_on_known_cases():
    from harness.compare import alignment

    ref = np.array([3.0, 4.0, 0.0])
    orth = np.array([0.0, 0.0, 5.0])  # orthogonal to ref, same norm
    exact = alignment(np.stack([ref, ref, np.full(3, np.nan)]), ref)  # the NaN row is dropped
    assert exact["cosine"] == pytest.approx(1) and exact["rel_error"] == pytest.approx(0)
    assert exact["cosine_ci"] == pytest.approx(0, abs=1e-12)
    tilted = alignment(np.stack([ref + orth, ref - orth]), ref)
    assert tilted["cosine"] == pytest.approx(1 / np.sqrt(2)) and tilted["rel_error"] == pytest.approx(1)
    assert tilted["cosine_of_mean"] == pytest.approx(1)  # the errors cancel in the mean
    opposite = alignment(np.stack([-ref, -2 * ref]), ref)
    assert opposite["cosine"] == pytest.approx(-1) and opposite["rel_error"] == pytest.approx(2.5)
    assert opposite["rel_error_ci"] == pytest.approx(1.96 * np.std([2, 3], ddof=1) / np.sqrt(2))


def test_compare_findings_use_the_largest_particle_count_every_model_has():
    from harness.compare import Args, findings

    cells = [("gp", 10, 4.0), ("gp", 300, 1.0), ("jax", 10, 2.0)]  # jax lacks P = 300
    rows = pd.DataFrame([dict(estimator="rp", model=m, particles=p, variance=v, cosine=0.1 * p, cosine_ci=0.01,
                              cosine_of_mean=0.5) for m, p, v in cells])
    (line,) = [line for line in findings(Args(models="gp,jax"), rows) if line.startswith("- rp")]
    assert "variance gp / jax 2-2 over P = 10" in line and "at P = 10 on jax: 1.000" in line
    (alone,) = [line for line in findings(Args(models="gp,mjx"), rows) if line.startswith("- rp")]
    assert alone == "- rp: no particle count measured on every model."


def test_the_references_quality_lines_separate_the_steps_bias_from_the_noise():
    from harness.compare import Args, Reference, reference_lines

    args = Args(reference_estimator="fd")
    plain, biased = reference_lines(args, Reference(np.ones(3), 0.1, 1.0, 0.012, 0.0004))
    assert "relative error of about that and a cosine of about 1 - 0.100^2 / 2 = 0.995" in plain
    assert biased.endswith("the step's bias, which for an O(h^2) bias puts g*'s own at about 4/3 of it, 0.016 of |g*|.")
    noisy = reference_lines(args, Reference(np.ones(3), 0.1, 1.0, 0.012, 0.01))[1]
    assert noisy.endswith("within the noise: no bias of the step is measurable.")
    assert len(reference_lines(Args(), Reference(np.ones(3), 0.1))) == 1  # an estimator's reference: no h / 2


def test_an_estimator_without_a_nan_count_is_refused_with_what_to_add():
    import dataclasses

    import jax
    import jax.numpy as jnp

    import tasks
    from estimators.base import Estimate, task_problem
    from harness.variance import repeated_estimates
    from models.simulator import SimulatorModel

    @dataclasses.dataclass(frozen=True)
    class Silent:
        def __call__(self, problem, theta, key, num_particles):
            zeros = jax.tree.map(jnp.zeros_like, theta)
            return Estimate(jnp.zeros(()), zeros, zeros, {})

    task = tasks.make("cartpole")
    problem = task_problem(task, SimulatorModel(task))
    theta = task.default_policy().init(jax.random.key(0))
    with pytest.raises(ValueError, match="Silent's Estimate.aux lacks 'nan_count'"):
        repeated_estimates(Silent(), problem, theta, 4, 2, jax.random.key(1))


def test_the_landscape_refuses_an_estimate_without_what_it_reads():
    from harness.landscape import check_aux

    check_aux("tp", {"particle_grads": 0, "nan_count": 0})
    with pytest.raises(ValueError, match=r"'my_rp' gives no aux\['nan_count'\]"):
        check_aux("my_rp", {"particle_grads": 0})
    with pytest.raises(ValueError, match=r"no aux\['particle_grads', 'nan_count'\]"):
        check_aux("my_rp", {})


def test_a_reference_with_a_non_finite_estimate_is_refused(tmp_path):
    import jax

    from harness.compare import Args, reference_gradient

    args = Args(out=str(tmp_path))
    os.makedirs(tmp_path / ".cache")
    np.savez(tmp_path / ".cache" / f"reference_cartpole_abc_{args.reference_name}.npz",
             grads=np.array([[1.0, 2.0], [np.nan, 1.0], [1.0, 1.0]]))
    where = {"jax": SimpleNamespace(theta0=None, content="abc")}  # a Setting's fields that a cached reference needs
    with pytest.raises(ValueError, match="1 non-finite estimates.*--reference-estimator fd"):
        reference_gradient(args, where, jax.random.key(0))


def test_compare_report_marks_only_missing_cells_not_run(tmp_path):
    """A cell that ran with fewer than two finite estimates has no variance, but its non-finite
    count is shown; a cell not measured on a model is 'not run'; an estimator x particles pair
    measured on no model has no row."""
    from harness.compare import Args, Reference, write_report

    def cell(model, particles, variance, nonfinite, estimator="lr"):
        return dict(task="cartpole", model=model, estimator=estimator, particles=particles, repeats=20, seed=0,
                    scenario="abc", reference="r", variance=variance, cosine=0.5, cosine_ci=0.1, rel_error=1.0,
                    rel_error_ci=0.1, cosine_of_mean=0.5, nonfinite_estimates=nonfinite)

    rows = pd.DataFrame([cell("gp", 10, 1.0, 0), cell("jax", 10, np.nan, 19), cell("gp", 30, 2.0, 0),
                         cell("gp", 1000, 3.0, 0, estimator="rp")])
    write_report(Args(out=str(tmp_path)), rows, Reference(np.ones(3), 0.1), [])
    table = [line for line in (tmp_path / "compare_cartpole.md").read_text().splitlines() if line.startswith("| lr")]
    assert "19/20" in table[0] and "not run" not in table[0]
    assert len(table) == 2 and table[1].count("not run") == 7  # jax at P = 30: its seven columns (with gp / jax)


def test_compare_sets_every_learned_model_against_the_true_dynamics(tmp_path, monkeypatch):
    """A model added to MODELS as learned gets the variance ratio against each true-dynamics
    model, and cannot be the reference."""
    from harness import compare, scenario as scenario_lib

    monkeypatch.setitem(scenario_lib.MODELS, "gp2", scenario_lib.MODELS["gp"])
    assert compare.split_models(["gp", "jax", "gp2", "mjx"]) == (["gp", "gp2"], ["jax", "mjx"])
    rows = pd.DataFrame([dict(task="cartpole", model=model, estimator="lr", particles=10, repeats=20, seed=0,
                              scenario="abc", reference="r", variance=variance, cosine=0.5, cosine_ci=0.1,
                              rel_error=1.0, rel_error_ci=0.1, cosine_of_mean=0.5, nonfinite_estimates=0)
                         for model, variance in (("gp2", 1.0), ("jax", 4.0))])
    compare.write_report(compare.Args(out=str(tmp_path), models="gp2,jax"), rows, compare.Reference(np.ones(3), 0.1),
                         [])
    report = (tmp_path / "compare_cartpole.md").read_text()
    assert "variance gp2 / jax 0.25-0.25 over P = 10" in report and "| variance gp2 / jax " in report
    with pytest.raises(ValueError, match="true-dynamics model \\(jax, mjx\\), not the learned gp2"):
        compare.Args(reference_model="gp2")


@pytest.mark.parametrize("model", ["gp", pytest.param("jax", marks=pytest.mark.slow),
                                   pytest.param("mjx", marks=pytest.mark.slow)])
def test_landscape_runs_end_to_end_and_resumes(tmp_path, capsys, model):
    """The landscape on the GP; on the true dynamics with -m slow (the default suite runs the
    true dynamics through the compare experiment)."""
    from harness import landscape

    argv = ["--model", model, "--particles", "6", "--points", "2", "--grid", "3", "--scenario-estimator", "tp",
            "--scenario-trials", "1",
            "--scenario-steps", "3", "--scenario-particles", "5", "--out", str(tmp_path)]
    landscape.main(argv)
    stem = tmp_path / f"landscape_cartpole_{model}"
    rows = pd.read_csv(f"{stem}.csv")
    assert len(rows) == 2 and np.isfinite(rows[["value", "fd_slope", "tp_grad", "lr_ci", "ftle_mean"]]).all().all()
    assert os.path.getsize(f"{stem}.png") > 1000 and "FTLE" in open(f"{stem}.md").read()
    capsys.readouterr()
    landscape.main(argv)  # resumes: nothing measured again
    assert "delta=" not in capsys.readouterr().err and len(pd.read_csv(f"{stem}.csv")) == 2


def test_landscape_rejects_an_unknown_slice_dimension():
    from harness import landscape

    with pytest.raises(ValueError, match="slice_dims must name two"):
        landscape.main(["--slice-dims", "x,phi"])


def test_landscape_rejects_pilco():
    from harness import landscape

    with pytest.raises(ValueError, match="leave pilco out"):
        landscape.main(["--estimators", "rp,pilco"])


def test_pilco_where_it_cannot_run_fails_before_any_computation(monkeypatch):
    """A task without forms (a new one) cannot be moment-matched, nor can a true-dynamics model:
    every entry point that would run pilco says so before it builds a scenario or learns."""
    from harness import learn, landscape, scenario
    from tasks.cartpole import CartPole

    def computes(*args, **kwargs):
        raise AssertionError("computed before refusing")

    monkeypatch.setattr(scenario, "build", computes)
    monkeypatch.setattr(learn, "run_experiments", computes)
    with pytest.raises(ValueError, match="cannot run on the jax model"):
        variance.main(["--model", "jax", "--estimators", "rp,pilco", "--scenario-estimator", "tp"])
    monkeypatch.setattr(CartPole, "cost_form", property(lambda self: None))
    for main, argv in ((variance.main, []), (variance.main, ["--scenario-estimator", "tp", "--estimators", "pilco"]),
                       (landscape.main, []), (learn.main, ["--methods", "tp,pilco"])):
        with pytest.raises(ValueError, match="policy_feature_map, gp_feature_map and cost_form"):
            main(argv)


def test_landscape_slices_default_to_the_tasks_dimensions():
    from harness import landscape

    assert landscape.Args(task="cartpole").slice_names == ["x", "theta"]
    assert landscape.Args(task="unicycle").slice_names == ["theta", "psif"]
    assert landscape.Args(task="unicycle", slice_dims="xc,yc").slice_names == ["xc", "yc"]


def test_finite_difference_reference_is_the_derivative_of_the_same_sampled_objective(tmp_path):
    """With common random numbers, fd_gradient differentiates the sampled J (the mean return of
    the particles that one key draws): at a small step it equals jax.grad of that function to
    O(h^2), coordinate by coordinate, on a smooth model (the GP)."""
    import jax

    from harness import scenario as scenario_lib
    from harness.compare import fd_gradient
    from harness.variance import flatten

    args = scenario_lib.ExperimentArgs(scenario_estimator="tp", scenario_trials=1, scenario_steps=3,
                                       scenario_particles=5, out=str(tmp_path))
    where, key = scenario_lib.setting(args, "gp"), jax.random.key(3)  # float64 (conftest)
    exact = flatten(jax.grad(lambda t: scenario_lib.particle_returns(where.problem, t, key, 16).mean())(where.theta0))
    fd = fd_gradient(where.problem, where.theta0, key, 16, 1e-4)
    np.testing.assert_allclose(fd, exact, rtol=1e-5, atol=1e-7 * np.abs(exact).max())


def test_compare_runs_end_to_end(tmp_path):
    from harness import compare

    compare.main(["--particles", "4", "--repeats", "2", "--estimators", "lr,tp", "--reference-particles", "8",
                  "--reference-repeats", "2", "--reference-estimator", "fd", "--scenario-estimator", "tp",
                  "--scenario-trials", "1", "--scenario-steps", "3",
                  "--scenario-particles", "5", "--out", str(tmp_path)])
    rows = pd.read_csv(tmp_path / "compare_cartpole.csv")
    assert set(rows.model) == {"gp", "jax"} and len(rows) == 4 and set(rows.reference) == {"jax-fd0.01-P8-R2"}
    assert rows.cosine.between(-1, 1).all() and (rows.variance > 0).all()
    report = (tmp_path / "compare_cartpole.md").read_text()
    assert "cosine gp" in report and "The same reference at h / 2" in report
    with pytest.raises(ValueError, match="reference must be a true-dynamics model"):
        compare.main(["--reference-model", "gp"])


@pytest.mark.slow
def test_scenario_can_be_learned_with_pilco():
    """Slow (50 s); the default suite builds a TP scenario (the variance experiment's) and runs
    PILCO through the same learning loop (test_learn)."""
    from harness import scenario

    args = scenario.ScenarioArgs(learned_trials=1, optimiser_steps=2, estimator="pilco", gp_steps=3)
    built = scenario.build(args)
    assert len(built.returns) == 2 and np.isfinite(built.returns).all()
    assert "PILCO (2 L-BFGS steps)" in args.describe()
    start = tasks.make("cartpole").default_policy().init(jax.random.fold_in(jax.random.key(0), 10_000))
    moved = [not np.allclose(a, b) for a, b in zip(jax.tree.leaves(built.theta), jax.tree.leaves(start))]
    assert any(moved)  # the policy was optimised


def test_every_pinned_scenario_loads_from_arrays_and_json_and_reproduces_its_content_hash():
    """The pinned scenarios are plain data (``.npz`` + ``.json`` with a schema version, no pickle); each
    loads, and its content hash at seed 0 (theta0, the direction, the GP) is the one its JSON records,
    which is the ``scenario`` of the committed report rows made at it."""
    from harness import keys
    from harness import scenario as scenario_lib
    from harness.records import ROOT

    folder = os.path.join(ROOT, "scenarios")
    assert not [name for name in os.listdir(folder) if name.endswith(".pkl")]
    stems = sorted(os.path.join(folder, name[:-len(".json")]) for name in os.listdir(folder) if name.endswith(".json"))
    assert len(stems) == 2
    for stem in stems:
        task = os.path.basename(stem).split("_")[1]
        saved = scenario_lib.load_scenario(stem, task)
        scn = saved["scenario"]
        direction = scenario_lib.unit_direction(scn.theta, keys.stream(jax.random.key(0), "direction"))
        assert scenario_lib.content_hash(scn.theta, direction, scn.posterior) == saved["meta"]["content_hash_seed0"]
        rows = pd.read_csv(os.path.join(ROOT, "reports", f"variance_{task}_gp.csv"), dtype={"scenario": str})
        assert saved["meta"]["content_hash_seed0"] in set(rows.scenario)
