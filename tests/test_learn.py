"""The learning experiment end to end at a tiny size, its resume, its argument checks, and
the success-table statistics."""

import numpy as np
import pandas as pd
import pytest

from harness import learn, learn_report

TINY = ["--repeats", "2", "--learned-trials", "1", "--optimiser-steps", "2", "--particles", "4", "--eval-runs", "2",
        "--pilco-steps", "2", "--gp-steps", "3"]


def test_learning_runs_end_to_end_and_an_interrupted_run_resumes(tmp_path, monkeypatch, capsys):
    argv = TINY + ["--methods", "pilco,tp+sigma_n", "--out", str(tmp_path)]
    real = learn.run_experiment
    calls = []

    def interrupted(args, method, repeat):
        if len(calls) == 2:
            raise KeyboardInterrupt  # the third experiment is cut off
        calls.append((method, repeat))
        return real(args, method, repeat)

    monkeypatch.setattr(learn, "run_experiment", interrupted)
    with pytest.raises(KeyboardInterrupt):
        learn.main(argv)
    csv = tmp_path / "learn_cartpole_angle_k1.csv"
    assert set(pd.read_csv(csv).method) == {"pilco"}  # the finished experiments are on disk
    calls.clear()
    monkeypatch.setattr(learn, "run_experiment", lambda *a: calls.append(a[1:]) or real(*a))
    learn.main(argv)
    assert calls == [("tp+sigma_n", 0), ("tp+sigma_n", 1)]  # only what was missing
    rows = pd.read_csv(csv)
    assert len(rows) == 2 * 2 * 2  # methods x repeats x (1 random + 1 learned trial)
    assert np.isfinite(rows[rows.learned].eval_mean).all()
    report = (tmp_path / "learn_cartpole_angle_k1.md").read_text()
    assert "Success threshold" in report and "paper" in report
    assert (tmp_path / "learn_cartpole_angle_k1.png").stat().st_size > 1000


@pytest.mark.parametrize("argv, message", [
    (["--methods", "pilco,ppo"], "valid methods"),
    (["--preset", "huge"], "valid presets"),
    (["--cost", "height"], "cost"),
    (["--noise-k", "-1"], "noise_k"),
])
def test_bad_arguments(argv, message):
    with pytest.raises(ValueError, match=message):
        learn.main(argv)


def test_success_statistics():
    bimodal = np.array([3.1, 2.9, 3.4, 27.0, 29.5, 28.8, 2.5])
    assert 3.4 < learn_report.otsu_threshold(bimodal) < 27.0
    low, high = learn_report.wilson_interval(8, 10)
    assert low == pytest.approx(0.4902, abs=1e-4) and high == pytest.approx(0.9433, abs=1e-4)  # textbook values
    assert learn_report.wilson_interval(0, 10)[0] == pytest.approx(0.0, abs=1e-12)


def test_sweep_runs_the_chosen_cells(tmp_path):
    from harness import sweep

    sweep.main(["--cells", "1", "--repeats", "1", "--methods", "tp", "--workers", "1", "--out", str(tmp_path),
                "--learn-args", " ".join(TINY[2:])])  # cell 1: the cart-pole, angle cost, k = 1
    assert (tmp_path / "learn_cartpole_angle_k1.csv").exists()
    with pytest.raises(ValueError, match="cells must be"):
        sweep.main(["--cells", "42"])
