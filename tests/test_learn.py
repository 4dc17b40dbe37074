"""The learning experiment end to end at a tiny size, its resume, its argument checks, and
the success-table statistics."""

import pickle

import numpy as np
import pandas as pd
import pytest

from harness import learn, methods, records, scenario
from harness.success import otsu_threshold, wilson_interval

TINY = ["--preset", "quick", "--repeats", "3", "--batch", "2", "--learned-trials", "1", "--optimiser-steps", "2", "--particles", "4", "--eval-runs", "2",
        "--pilco-steps", "2", "--gp-steps", "3"]


def test_learning_runs_end_to_end_and_an_interrupted_run_resumes(tmp_path, monkeypatch, capsys):
    from harness import episodic

    argv = TINY + ["--repeats", "1", "--methods", "pilco,tp+sigma_n", "--keep-final", "--out", str(tmp_path)]
    monkeypatch.setattr(episodic, "PROGRESS_EVERY", 1)
    real = learn.run_experiments
    calls = []

    def interrupted(args, method, repeats):
        if len(calls) == 1:
            raise KeyboardInterrupt  # the second batch is cut off
        calls.append((method, repeats))
        return real(args, method, repeats)

    monkeypatch.setattr(learn, "run_experiments", interrupted)
    with pytest.raises(KeyboardInterrupt):
        learn.main(argv)
    csv = tmp_path / "learn_cartpole_angle_k1_quick.csv"
    assert set(pd.read_csv(csv).method) == {"pilco"}  # the finished experiments are on disk
    calls.clear()
    monkeypatch.setattr(learn, "run_experiments", lambda *a: calls.append(a[1:]) or real(*a))
    learn.main(argv)
    assert calls == [("tp+sigma_n", [0])]  # only what was missing
    rows = pd.read_csv(csv)
    assert len(rows) == 2 * 1 * 2  # methods x repeats x (1 random + 1 learned trial)
    assert np.isfinite(rows[rows.learned].eval_mean).all() and (rows[rows.learned].nonfinite_steps == 0).all()
    for method in ("pilco", "tp+sigma_n"):  # --keep-final: each run's last state, as a scenario file
        args = learn.parse(learn.Args, argv)
        kept = scenario.load_scenario(learn.final_state_path(args, method, 0), "cartpole")
        ours = rows[rows.method == method]
        np.testing.assert_array_equal(kept["scenario"].returns, ours.trial_return)
        assert int(kept["scenario"].data.num_valid) == ours.data_points.max() and kept["meta"]["method"] == method
        assert np.isfinite(kept["scenario"].posterior.alpha).all() and kept["meta"]["settings"] == ours.settings.iloc[0]
    progress = capsys.readouterr().err
    assert "[batch 2/2] tp+sigma_n, repeats [0]" in progress and "trial 2/2" in progress
    assert "optimiser step 2/2" in progress  # from inside the jitted, vmapped optimiser
    report = (tmp_path / "learn_cartpole_angle_k1_quick.md").read_text()
    assert "Success threshold" in report and "paper" in report
    assert (tmp_path / "learn_cartpole_angle_k1_quick.png").stat().st_size > 1000
    learn.main(TINY + ["--repeats", "1", "--methods", "tp+sigma_n", "--out", str(tmp_path)])  # nothing missing
    assert calls == [("tp+sigma_n", [0])]
    rerun_report = (tmp_path / "learn_cartpole_angle_k1_quick.md").read_text()
    assert "| pilco " in rerun_report  # the report pools the CSV's other methods, as `learn_report` does
    assert rerun_report.split("\n")[4:] == report.split("\n")[4:]  # all but the command line


def test_a_batch_interrupted_between_trials_continues_after_its_last_trial(tmp_path, monkeypatch, capsys):
    """The batch's state is saved after every trial (here in a ``--checkpoints`` folder, as a
    run carried to another machine would); a rerun continues from it and gives the rows of an
    uninterrupted run (the same computation: equal to round-off), then removes it."""
    argv = TINY + ["--repeats", "2", "--learned-trials", "2", "--methods", "tp"]  # the last value of a flag wins
    learn.main(argv + ["--out", str(tmp_path / "whole")])
    whole = records.read_csv(str(tmp_path / "whole" / "learn_cartpole_angle_k1_quick.csv"))

    real, calls = learn.evaluate_policy, []

    def cut_at_the_second_evaluation(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt  # during learned trial 2: learned trial 1 is saved
        return real(*args, **kwargs)

    monkeypatch.setattr(learn, "evaluate_policy", cut_at_the_second_evaluation)
    out, carried = tmp_path / "cut", tmp_path / "carried"
    argv += ["--checkpoints", str(carried)]
    with pytest.raises(KeyboardInterrupt):
        learn.main(argv + ["--out", str(out)])
    assert not (out / "learn_cartpole_angle_k1_quick.csv").exists()
    assert len(list(carried.iterdir())) == 1 and not (out / ".cache" / "learn").exists()
    monkeypatch.setattr(learn, "evaluate_policy", real)
    [checkpoint] = carried.iterdir()  # plain data: one .npz that numpy reads without pickle
    saved = learn.load_checkpoint(str(checkpoint), learn.parse(learn.Args, argv).make_task())
    assert checkpoint.suffix == ".npz" and saved["state"].trials_done == 2 and len(saved["rows"]) == 2 * 2
    assert saved["jax"] == learn.JAX_VERSIONS and saved["fit_rows_held"] and saved["seeds_in_turn"]  # a new batch's
    checkpoint.unlink()  # as a pickle of older code, written before rows carried their code version, and before
    with open(checkpoint.with_suffix(".pkl"), "wb") as f:  # checkpoints named their jax version and loop options
        pickle.dump(dict(state=saved["state"], rows=[{n: v for n, v in r.items() if n != "code_version"}
                                                     for r in saved["rows"]]), f)
    capsys.readouterr()
    real_run, loop_options = learn.learning_run, []

    def recording_run(*args, **kwargs):
        loop_options.append((kwargs["fit_rows_held"], kwargs["seeds_in_turn"]))
        return real_run(*args, **kwargs)

    monkeypatch.setattr(learn, "learning_run", recording_run)
    learn.main(argv + ["--out", str(out)])
    assert loop_options == [(False, False)]  # a checkpoint from before the options resumes as it began
    progress = capsys.readouterr().err
    assert "tp repeats 0-1: resuming after trial 2/3" in progress and "trial 2/3," not in progress
    assert f"ran under unrecorded jax, this process under {learn.JAX_VERSIONS}" in progress
    resumed = records.read_csv(str(out / "learn_cartpole_angle_k1_quick.csv"))
    columns = ["repeat", "trial", "learned", "trial_return", "eval_mean", "data_points"]
    pd.testing.assert_frame_equal(resumed[columns], whole[columns], check_exact=False, rtol=1e-9)
    # each trial's row names the code that ran it: unrecorded (blank) for the trials of the old checkpoint
    assert (whole.code_version == records.code_version()).all()
    assert resumed.code_version.isna().tolist() == (resumed.trial < 2).tolist()
    assert (resumed.code_version[resumed.trial == 2] == records.code_version()).all()
    assert not list(carried.iterdir())  # the checkpoint is gone with its rows in the table


def test_non_finite_optimiser_steps_are_counted_in_the_table_and_flagged_in_the_report(tmp_path, monkeypatch):
    """A method whose every gradient estimate is NaN: each learned trial's row counts all its
    optimiser steps, and the report carries the warning (sound methods' rows count 0: the
    end-to-end test above)."""
    import jax
    import jax.numpy as jnp

    import estimators

    def nan_tp(**options):
        tp = estimators.make("tp", **options)

        def estimate(problem, theta, key, num_particles):
            e = tp(problem, theta, key, num_particles)
            return e._replace(grad=jax.tree.map(lambda g: g * jnp.nan, e.grad))

        return estimate

    monkeypatch.setitem(estimators.REGISTRY, "nan_tp", nan_tp)
    monkeypatch.setitem(methods.METHODS, "nan_tp", methods.Method("nan_tp"))
    learn.main(TINY + ["--repeats", "2", "--optimiser-steps", "3", "--methods", "nan_tp", "--out", str(tmp_path)])
    rows = pd.read_csv(tmp_path / "learn_cartpole_angle_k1_quick.csv")
    assert (rows[rows.learned].nonfinite_steps == 3).all()  # every step of both repeats' learned trial
    assert rows[~rows.learned].nonfinite_steps.isna().all()  # no optimisation before a random trial
    report = (tmp_path / "learn_cartpole_angle_k1_quick.md").read_text()
    assert "WARNING: non-finite gradient estimates** in 2 learned trials" in report


@pytest.mark.slow
def test_learning_runs_on_the_unicycle(tmp_path):
    """5 random trials, the linear policy and the fall test (a fallen run's rows are masked).
    Slow (2 min, the unicycle's programs compile slowly); the default suite keeps the
    unicycle's variance experiment end to end, PILCO's unicycle step against Monte Carlo and
    the lowering of every unicycle learning program (test_linalg)."""
    learn.main(TINY + ["--task", "unicycle", "--methods", "pilco,tp", "--out", str(tmp_path)])
    rows = pd.read_csv(tmp_path / "learn_unicycle_default_k1_quick.csv")
    assert set(rows.method) == {"pilco", "tp"}
    assert sorted(rows.trial.unique()) == list(range(6)) and (rows.data_points <= 20 * rows.trial.add(1)).all()
    assert np.isfinite(rows[rows.learned].eval_mean).all()


def test_gp_inducing_switches_the_learning_run_to_fitc_once_the_data_exceed_it(tmp_path, monkeypatch):
    """--gp-inducing 40: the first learned trial fits the full GP on 30 rows, the second FITC
    on 60; the key says so. (PILCO's moment matching on a FITC posterior: test_sparse_gp.)"""
    import tasks
    from models import sparse_gp

    calls = []
    real = sparse_gp.fitc_posterior
    monkeypatch.setattr(sparse_gp, "fitc_posterior", lambda u, *a: calls.append(u.shape) or real(u, *a))
    learn.main(TINY + ["--repeats", "1", "--methods", "tp", "--learned-trials", "2", "--gp-inducing", "40",
                       "--out", str(tmp_path)])
    rows = pd.read_csv(tmp_path / "learn_cartpole_angle_k1_quick.csv")
    assert calls == [(40, tasks.make("cartpole").gp_input_dim)]  # traced once under vmap, at trial 2 only
    assert rows.settings.str.endswith("-fitc40").all()
    assert np.isfinite(rows[rows.learned].eval_mean).all() and (rows[rows.learned].nonfinite_steps == 0).all()
    with pytest.raises(ValueError, match="gp_inducing"):
        learn.main(["--gp-inducing", "-1"])


@pytest.mark.parametrize("argv, message", [
    (["--methods", "pilco,ppo"], "valid methods"),
    (["--preset", "huge"], "valid presets"),
    (["--cost", "height"], "cost"),
    (["--noise-k", "-1"], "noise_k"),
])
def test_bad_arguments(argv, message):
    with pytest.raises(ValueError, match=message):
        learn.main(argv)


def test_the_learning_tables_lr_is_the_papers_batch_importance_weighted_lr():
    """The paper's learning column "LR" is "model-based batch importance weighted likelihood
    ratio": the method ``lr`` must run that estimator; plain LR is ``lr_plain``."""
    assert methods.method("lr").estimator == "biw_lr" and methods.method("lr_plain").estimator == "lr"
    assert "lr" in methods.DEFAULT_METHODS.split(",") and "lr_plain" not in methods.DEFAULT_METHODS.split(",")


def test_the_per_run_fixed_noise_methods_keep_one_optimisation_key_for_the_whole_run():
    """rp_fs / gr_fs fix their noise per trial: each trial's optimisation has its own key. The
    other reading, rp_fs_run / gr_fs_run, gives every trial's optimisation the same key, so a
    fixed-noise estimator (which uses that key at every step) sees the same particles all run."""
    import jax

    import estimators
    import tasks
    from estimators.base import task_problem
    from harness.episodic import PolicyOptimisation, learning_run
    from models import gp

    task = tasks.make("cartpole")
    problem = task_problem(task, gp.GPModel(task))

    def keys_seen(per_run):
        keys = []

        def optimise(problem, theta, key):
            keys.append(np.asarray(jax.random.key_data(key)))
            return PolicyOptimisation(theta, np.zeros(1), 0)

        learning_run(task, problem, jax.random.key(0), 2, optimise, 3, optimisation_key_per_run=per_run)
        return keys

    per_trial, per_run = keys_seen(False), keys_seen(True)
    assert not np.array_equal(per_trial[0], per_trial[1]) and np.array_equal(per_run[0], per_run[1])
    np.testing.assert_array_equal(per_run[0], per_trial[0])  # trial 1's key is the same in both readings
    per_run_methods = {name: m for name, m in methods.METHODS.items() if m.noise_fixed_per_run}
    assert sorted(per_run_methods) == ["gr_fs_run", "rp_fs_run"]
    for name, reading in per_run_methods.items():
        paper = methods.method(reading.reads)  # the same estimator and overrides, only the key differs
        assert (reading.estimator, reading.overrides) == (paper.estimator, paper.overrides)
        assert estimators.make(reading.estimator).fixes_noise


def test_success_statistics():
    bimodal = np.array([3.1, 2.9, 3.4, 27.0, 29.5, 28.8, 2.5])
    assert 3.4 < otsu_threshold(bimodal) < 27.0
    low, high = wilson_interval(8, 10)
    assert low == pytest.approx(0.4902, abs=1e-4) and high == pytest.approx(0.9433, abs=1e-4)  # textbook values
    assert wilson_interval(0, 10)[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("in_turn", [pytest.param(False, marks=pytest.mark.slow), True])
def test_a_batched_learning_run_is_each_seed_run_alone(in_turn):
    """learning_run(batched=True, trim_model=True) over two seeds is the same computation as
    each seed alone on the whole buffer; also with the fit on the rows held and the seeds
    optimised in turn (``learn``'s loop). The vmapped optimiser's case (``in_turn=False``, only batches
    resumed from older checkpoints run it) is slow: the interrupted-batch test above resumes with it and
    matches the uninterrupted run's rows.

    The optimiser here is a plain gradient step: the paper's normalised steps g / sqrt(g^2 + V)
    turn round-off-sized gradients of uninformed parameters into full steps, which would
    make this comparison a test of round-off."""
    import jax

    import estimators
    import tasks
    from estimators.base import task_problem
    from harness.episodic import PolicyOptimisation, learning_run
    from models import gp

    task = tasks.make("cartpole")
    problem = task_problem(task, gp.GPModel(task))
    tp = estimators.make("tp")

    def optimise(problem, theta, key):
        estimate = tp(problem, theta, key, 8)
        return PolicyOptimisation(jax.tree.map(lambda t, g: t - 0.1 * g, theta, estimate.grad), estimate.value[None], 0)

    keys = jax.numpy.stack([jax.random.key(3), jax.random.key(4)])
    theta_batch, data_batch = learning_run(task, problem, keys, 1, optimise, 5, batched=True, trim_model=True,
                                           fit_rows_held=in_turn, seeds_in_turn=in_turn)
    # Batching and trimming change round-off (GP predictions differ by ~1e-13); the gradient
    # through the model's 30-step rollout and the learned trial's closed loop amplify it (FTLE
    # ~0.3 per step, e^9 over 30 steps): 1e-6 bounds both, while a wrong key, buffer or
    # posterior would differ by O(1e-2) or more.
    for i in range(2):
        theta, data = learning_run(task, problem, keys[i], 1, optimise, 5)
        np.testing.assert_allclose(data_batch.targets[i], data.targets, rtol=0, atol=1e-6)
        for batched_leaf, leaf in zip(jax.tree.leaves(theta_batch), jax.tree.leaves(theta)):
            np.testing.assert_allclose(batched_leaf[i], leaf, rtol=1e-6, atol=1e-9)
