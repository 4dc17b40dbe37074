"""harness.sweep: a plan splits into units, units merge into one CSV per cell without
duplicates, a killed unit resumes from its checkpoint, and both engines write the same rows."""

import os
import textwrap

import pandas as pd
import pytest

from harness import learn, records, sweep

TINY_SETTINGS = """
[settings]
preset = "quick"
batch = 1
learned_trials = 1
optimiser_steps = 2
particles = 4
eval_runs = 2
pilco_steps = 2
gp_steps = 3
"""


def write_plan(tmp_path, cells: str, settings: str = TINY_SETTINGS) -> str:
    path = tmp_path / "plan.toml"
    path.write_text("schema_version = 1\n" + textwrap.dedent(settings) + f'out = "{tmp_path / "out"}"\n'
                    + f'checkpoints = "{tmp_path / "checkpoints"}"\n' + textwrap.dedent(cells))
    return str(path)


def test_a_plan_splits_into_units_in_priority_order_each_once(tmp_path):
    plan = write_plan(tmp_path, """
        [[cells]]
        task = "cartpole"
        cost = "angle"
        noise_k = 16.0
        repeats = { tp = 2, pilco = 1 }

        [[cells]]
        task = "cartpole"
        cost = "tip"
        noise_k = 1.0
        repeats = { lr = 1 }

        [[cells]]
        task = "cartpole"
        cost = "angle"
        noise_k = 16.0
        repeats = { tp = 3 }
        """)
    units = [u.describe() for u in sweep.load_plan(plan)]
    assert units == ["learn_cartpole_angle_k16_quick tp repeats 0-0", "learn_cartpole_angle_k16_quick tp repeats 1-1",
                     "learn_cartpole_angle_k16_quick pilco repeats 0-0", "learn_cartpole_tip_k1_quick lr repeats 0-0",
                     "learn_cartpole_angle_k16_quick tp repeats 2-2"]


@pytest.mark.parametrize("cells, message", [
    ('[[cells]]\ntask = "cartpole"\nrepeats = { nope = 2 }\n', "unknown methods"),
    ('[[cells]]\ntask = "cartpole"\nrepeats = 3\n', "repeats = {method = R"),
    ('[[cells]]\ntask = "cartpole"\nrepeats = { tp = 1 }\n[[cells\n', "not valid TOML"),
])
def test_a_bad_plan_is_named_with_what_is_wrong(tmp_path, cells, message):
    with pytest.raises(ValueError, match=message):
        sweep.load_plan(write_plan(tmp_path, cells))


def test_a_plan_without_its_schema_version_or_engine_is_refused(tmp_path):
    path = tmp_path / "old.toml"
    path.write_text('[settings]\nbatch = 1\n[[cells]]\ntask = "cartpole"\nrepeats = { tp = 1 }\n')
    with pytest.raises(ValueError, match="schema_version must be 1"):
        sweep.load_plan(str(path))
    with pytest.raises(ValueError, match="no plan file"):
        sweep.load_plan(str(tmp_path / "missing.toml"))
    with pytest.raises(ValueError, match="valid engines"):
        sweep.main(["--engine", "dask"])


def test_units_merge_into_one_csv_per_cell_and_a_killed_unit_resumes(tmp_path, monkeypatch, capsys):
    """Two units (TP repeats 0 and 1) of one cell: the first is killed after its random trial
    (its checkpoint saved), the sweep's status shows it partial; a rerun resumes it after that
    trial, writes each (repeat, trial) once into the cell's one CSV, with the rows of an
    uninterrupted run (the same computation: equal to round-off), and a third run writes nothing."""
    plan = write_plan(tmp_path, '[[cells]]\ntask = "cartpole"\ncost = "angle"\nnoise_k = 1.0\nrepeats = { tp = 2 }\n')
    units = sweep.load_plan(plan)
    real_save = learn.save_checkpoint

    def killed_after_first_save(*args):
        real_save(*args)
        raise KeyboardInterrupt

    monkeypatch.setattr(learn, "save_checkpoint", killed_after_first_save)
    with pytest.raises(KeyboardInterrupt):
        sweep.main(["--plan", plan, "--workers", "1"])
    monkeypatch.setattr(learn, "save_checkpoint", real_save)
    status = sweep.status_lines(units)
    assert status[0].startswith("partial") and "trial 1/2" in status[0] and status[1].startswith("left")
    assert "0 of 2 units done" in status[-1]
    sweep.main(["--plan", plan, "--workers", "1"])
    assert "resuming after trial 1/2" in capsys.readouterr().err
    csv = tmp_path / "out" / "learn_cartpole_angle_k1_quick.csv"
    rows = records.read_csv(str(csv))
    assert sorted(zip(rows.repeat, rows.trial)) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert (tmp_path / "out" / "learn_cartpole_angle_k1_quick.md").exists()
    assert not list((tmp_path / "checkpoints").glob("*.npz"))  # merged units leave no checkpoint
    alone = learn.run_experiments(units[0].learn_args(), "tp", [0])
    timing = ["seconds", "code_version"]
    pd.testing.assert_frame_equal(rows[rows.repeat == 0][pd.DataFrame(alone).columns].drop(columns=timing)
                                  .reset_index(drop=True), pd.DataFrame(alone).drop(columns=timing),
                                  check_exact=False, rtol=1e-9, check_dtype=False)
    assert sweep.merge(units[0], [{**learn.row_key(units[0].learn_args(), units[0].learn_args().make_task(), "tp",
                                                   row["repeat"]), **row} for row in alone]) == 0
    sweep.main(["--plan", plan, "--workers", "1"])
    assert len(records.read_csv(str(csv))) == 4
    assert "2 of 2 units done" in sweep.status_lines(units)[-1]


def test_a_unit_running_elsewhere_is_skipped_and_shown_running(tmp_path):
    plan = write_plan(tmp_path, '[[cells]]\ntask = "cartpole"\ncost = "angle"\nnoise_k = 1.0\nrepeats = { tp = 1 }\n')
    [unit] = sweep.load_plan(plan)
    with sweep.unit_lock(unit) as mine:
        assert mine and sweep.is_running(unit)
        assert sweep.run_unit(unit) is None
        assert sweep.status_lines([unit])[0].startswith("running")
    assert not sweep.is_running(unit)


@pytest.mark.slow
def test_the_ray_engine_writes_the_local_engines_rows(tmp_path):
    """A two-unit plan on the local process pool (two spawned workers) and on a local Ray
    instance (``num_cpus=2``) writes the same rows (all but the timing columns; equal to
    round-off: the same computation in other processes). Slow: the workers compile everything
    anew. Needs the ray extra (``pip install -e ".[ray]"``)."""
    ray = pytest.importorskip("ray", reason='the ray extra: pip install -e ".[ray]"')
    cells = '[[cells]]\ntask = "cartpole"\ncost = "angle"\nnoise_k = {k}\nrepeats = {{ tp = 1 }}\n'
    written = {}
    for engine in ("local", "ray"):
        folder = tmp_path / engine
        folder.mkdir()
        plan = write_plan(folder, cells.format(k=0.01) + cells.format(k=1.0))
        if engine == "ray":
            ray.init(num_cpus=2, include_dashboard=False)
        try:
            sweep.main(["--plan", plan, "--engine", engine, "--workers", "2"])
        finally:
            if engine == "ray":
                ray.shutdown()
        written[engine] = {k: records.read_csv(str(folder / "out" / f"learn_cartpole_angle_k{k}_quick.csv"))
                           .drop(columns=["seconds", "code_version"]) for k in ("0.01", "1")}
    for k, local in written["local"].items():
        assert len(local) == 2  # 1 random + 1 learned trial
        pd.testing.assert_frame_equal(written["ray"][k], local, check_exact=False, rtol=1e-9)


def test_the_chaos_scenarios_source_run_has_the_k1_tables_settings():
    """plans/chaos_scenario.toml's source run is TP at the k = 1 table's settings (the same task, settings key
    and precision as that cell of plans/paper_tables.toml), keeping its final state."""
    [source] = sweep.load_plan(os.path.join(records.ROOT, "plans", "chaos_scenario.toml"))
    table = [u for u in sweep.load_plan(os.path.join(records.ROOT, "plans", "paper_tables.toml"))
             if u.method == "tp" and u.learn_args().noise_k == 1.0 and u.learn_args().out == "reports"]
    ours, theirs = source.learn_args(), table[0].learn_args()
    assert source.method == "tp" and source.repeats == [0] and ours.keep_final
    assert (ours.settings_name("tp"), ours.make_task(), ours.x64) == (theirs.settings_name("tp"), theirs.make_task(), theirs.x64)
