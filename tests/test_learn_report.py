"""The learning report's comparison with the paper, on small synthetic tables: the inside-interval
verdict, the threshold's robustness, the compute time and the paper's orderings."""

import numpy as np
import pandas as pd
import pytest

from harness import learn_report, methods
from harness.claims import ordering_lines, partial
from harness.success import (ROBUSTNESS, SCALES, compute_hours, final_evaluations, inside, otsu_threshold,
                             otsu_thresholds, rates_at_scales, retained_fraction_p, success_rows, success_table,
                             wilson_interval, with_labels)

OPTIONS = "preset=pipps,horizon=30,cost_type=angle"
WIN, FAIL = 5.0, 30.0  # final costs of a learned and a failed run: Otsu's cut falls at 17.5 between them


def row(method, repeat, trial, eval_mean=np.nan, seconds=1.0, k=1.0):
    """One row of the learning CSV (trial 0 random, later trials learned)."""
    return dict(task="cartpole", cost="angle", noise_k=k, task_options=f"{OPTIONS},noise_k={k}", method=method,
                repeat=repeat,
                seed=repeat, settings="s", trial=trial, learned=trial > 0, trial_return=20.0, eval_mean=eval_mean,
                eval_std=0.1, data_points=30 * (trial + 1), nonfinite_steps=0.0 if trial else np.nan,
                seconds=seconds)


def rows_of(finals: dict) -> pd.DataFrame:
    """A random and a learned trial per repeat, each repeat its own batch; ``finals`` maps (method, k)
    to the final evaluation costs of its repeats."""
    return pd.DataFrame([r for (method, k), costs in finals.items() for repeat, cost in enumerate(costs)
                         for r in (row(method, repeat, 0, k=k), row(method, repeat, 1, cost, 10.0 + repeat, k=k))])


def wins(method: str, successes: int, n: int = 10, k: float = 1.0) -> dict:
    """``finals`` entry: ``successes`` of ``n`` repeats learned."""
    return {(method, k): [WIN] * successes + [FAIL] * (n - successes)}


def test_the_papers_rate_is_inside_or_outside_the_wilson_interval():
    success = success_rows(rows_of({**wins("tp", 7), **wins("pilco", 7), **wins("lr_plain", 7)}))
    by_method = success.set_index("method")
    assert list(success.method) == ["pilco", "lr_plain", "tp"]  # the paper's column order
    # 7 of 10, by hand (z = 1.96; the report's exact 1.959964 moves the ends by 7e-6):
    # centre (0.7 + 1.96^2/20) / (1 + 1.96^2/10) = 0.64449,
    # half width 1.96 sqrt(0.7 * 0.3 / 10 + 1.96^2 / 400) / (1 + 1.96^2/10) = 0.24772
    assert by_method.loc["tp", "low"] == pytest.approx(0.64449 - 0.24772, abs=1e-4)
    assert by_method.loc["tp", "high"] == pytest.approx(0.64449 + 0.24772, abs=1e-4)
    assert by_method.loc["tp", ["wins", "n", "rate"]].tolist() == [7, 10, 0.7]
    assert (by_method.loc["tp", "paper"], by_method.loc["tp", "inside"]) == (0.99, "no")
    assert (by_method.loc["pilco", "paper"], by_method.loc["pilco", "inside"]) == (0.79, "yes")
    assert np.isnan(by_method.loc["lr_plain", "paper"]) and by_method.loc["lr_plain", "inside"] == "-"
    per_run = success_rows(rows_of(wins("rp_fs_run", 7))).set_index("method")
    assert per_run.loc["rp_fs_run", "paper"] == 0.23  # the other reading of RP_FS, beside RP_FS's rate
    # 7 of 10 against 99 of 100: [[7, 3], [99, 1]], two-sided Fisher exact p = 0.002115
    assert by_method.loc["tp", "paper_p"] == pytest.approx(0.002115, rel=1e-3)
    assert np.isnan(by_method.loc["lr_plain", "paper_p"])
    assert inside(0.3968, 0.3968, 0.8922) == "yes"  # the ends belong to the interval
    table, thresholds = success_table(rows_of({**wins("tp", 7), **wins("pilco", 7)}))
    assert table.loc[("cartpole", "angle", 1.0), "tp"] == "0.70 [0.40, 0.89] n=10 (paper 0.99)"
    assert thresholds == {("cartpole", "angle", ""): pytest.approx(17.5)}


def robustness(rows: pd.DataFrame) -> list[str]:
    """The report's robustness lines of ``rows``."""
    thresholds = otsu_thresholds(final_evaluations(rows))
    return learn_report.robustness_lines(rates_at_scales(rows), thresholds)


def test_threshold_robustness_reports_flips_only_where_a_final_cost_lies_within_the_margin():
    steady = robustness(rows_of({**wins("tp", 7), **wins("pilco", 7)}))
    assert "- Thresholds for cartpole, angle: 15.750 / 17.500 / 19.250" in steady
    assert all(line.endswith(": none.") for line in steady[-3:])
    # pilco's costs 16, 16 and 18 lie within 10 % of the threshold (Otsu's cut: 17): 5, 7, 8 wins
    pilco = {("pilco", 1.0): [WIN] * 5 + [16.0, 16.0, 18.0, FAIL, FAIL]}
    moved = robustness(rows_of({**wins("tp", 7), **pilco}))
    assert "- Thresholds for cartpole, angle: 15.300 / 17.000 / 18.700" in moved
    assert "- Rates that change (flips): 1 (cartpole, angle, k = 1, pilco: 0.50 / 0.70 / 0.80)." in moved
    assert ("- Orderings between methods (INVALID ones left out) that change: 1 (cartpole, angle, k = 1, pilco vs "
            "tp: < / = / >).") in moved
    # 5 of 10: [0.24, 0.76] leaves out the paper's 0.79
    assert ("- Inside/outside verdicts against the paper that change: 1 (cartpole, angle, k = 1, pilco: "
            "no / yes / yes).") in moved
    assert SCALES == (1 - ROBUSTNESS, 1.0, 1 + ROBUSTNESS)


def test_compute_time_counts_each_batch_once():
    """A batch writes its clock (seconds since it began) on every repeat's row: tp's repeats 0 and 1
    share a batch of 250 s, repeat 2 ran alone for 200 s, pilco's one repeat for 120 s."""
    timed = [("tp", 0, 5.0, 250.0), ("tp", 1, 5.0, 250.0), ("tp", 2, 4.0, 200.0), ("pilco", 0, 3.0, 120.0)]
    rows = pd.DataFrame([r for method, repeat, first, last in timed
                         for r in (row(method, repeat, 0, seconds=first), row(method, repeat, 1, WIN, last))])
    hours = compute_hours(rows)
    assert list(hours.index) == ["pilco", "tp", "total"]
    assert hours.repeats.tolist() == [1, 3, 4]
    assert hours.hours.tolist() == pytest.approx([120 / 3600, 450 / 3600, 570 / 3600])
    assert hours["hours per repeat"].tolist() == pytest.approx([120 / 3600, 150 / 3600, 570 / 3600 / 4])


def orderings(finals: dict) -> list[str]:
    """The report's ordering lines of ``finals``."""
    return ordering_lines(success_rows(rows_of(finals)))


def test_orderings_hold_significantly_or_are_not_measured():
    tp_ahead = orderings({**wins("tp", 9), **wins("pilco", 2)})
    assert tp_ahead[0] == ("- (a) TP >= PILCO at k = 1 (cartpole, angle): TP 0.90 [0.60, 0.98] n=10 vs PILCO 0.20 "
                           "[0.06, 0.51] n=10: holds on the point estimates; significant at 0.05 (two-sided Fisher "
                           "exact p = 0.00548); the paper's own: TP 0.99, PILCO 0.79.")  # [[9, 1], [2, 8]]: p = 0.0055
    assert "(b) LR and TP degrade least as k grows (cartpole, angle): not measured (no LR rows)." in tp_ahead[1]
    assert tp_ahead[2].endswith("(c) RP_FS is the worst method (cartpole, angle, k = 1): not measured (no RP_FS rows).")
    tied = orderings({**wins("tp", 7), **wins("pilco", 7)})[0]
    assert "holds on the point estimates; not significant at 0.05, so undecided (two-sided Fisher exact p = 1)" in tied
    assert orderings(wins("tp", 9))[0].endswith("not measured (no PILCO rows) at k = 1.")


def test_degradation_and_worst_method_claims():
    single_k = orderings({**wins("lr", 9), **wins("tp", 9), **wins("pilco", 9)})[1]
    assert single_k.endswith("undecided: needs k in {0.01, 1, 4, 9, 16} (this file has only k = 1).")
    finals = {**wins("lr", 9), **wins("tp", 9), **wins("pilco", 9), **wins("rp", 9),
              **wins("lr", 8, k=16.0), **wins("tp", 8, k=16.0), **wins("pilco", 1, k=16.0), **wins("rp", 0, k=16.0)}
    assert orderings(finals)[1] == (
        "- (b) LR and TP degrade least as k grows (cartpole, angle): partial, RP_FS, GR and GR_FS not measured: "
        "relative drop in rate (1 - rate at k = 16 / rate "
        "at k = 1): LR 0.11, TP 0.11, PILCO 0.89, RP 1.00: holds on the point estimates; significant at 0.05 "
        "(two-sided Wald test of equal log ratios, Agresti-Caffo adjusted, p = 0.0296, the largest of 4: LR vs "
        "PILCO).")  # log(9/10) - log(2/10) = 1.504 over sd sqrt(1/60 + 1/36 + 1/60 + 5/12) = 0.6912: z = 2.176
    finals.update({**wins("rp_fs", 3), **wins("rp_fs", 0, k=16.0)})  # loses all: more than LR, not significantly
    lines = orderings(finals)
    assert "RP_FS 1.00: holds on the point estimates; not significant at 0.05, so undecided" in lines[1]
    assert lines[1].endswith("the largest of 6: LR vs RP_FS).")
    assert lines[1].startswith("- (b) LR and TP degrade least as k grows (cartpole, angle): partial, GR and GR_FS "
                               "not measured: relative drop")
    assert lines[2] == ("- (c) RP_FS is the worst method (cartpole, angle, k = 1): partial, GR and GR_FS not measured: "
                        "RP_FS 0.30 [0.11, 0.60] n=10 vs "
                        "the lowest other, PILCO 0.90 [0.60, 0.98] n=10: holds on the point estimates; significant at "
                        "0.05 (two-sided Fisher exact p = 0.0198, the largest of 4: RP_FS vs PILCO).")
    assert "holds on the point estimates; not significant at 0.05, so undecided" in lines[3]  # k = 16: RP_FS = RP = 0
    success = success_rows(rows_of(finals)).set_index(["method", "k"])
    equal = retained_fraction_p(*(success.loc[key] for key in [("lr", 1.0), ("lr", 16.0),
                                                                          ("tp", 1.0), ("tp", 16.0)]))
    assert equal == pytest.approx(1.0)


def test_claims_name_the_missing_methods_of_the_paper_and_are_whole_without_them():
    every = {key: value for m in methods.PAPER_METHODS for key, value in wins(m, 9).items()}
    every.update(wins("rp_fs", 2))
    whole = orderings(every)[2]
    assert whole.startswith("- (c) RP_FS is the worst method (cartpole, angle, k = 1): RP_FS 0.20 [0.06, 0.51] n=10")
    assert "partial" not in whole and "significant at 0.05" in whole
    present = ["rp_fs", "tp", "pilco", "rp", "gr", "lr"]
    assert partial(present, ("rp_fs",)) == "partial, GR_FS not measured: "


def test_invalid_runs_take_no_part_in_the_threshold():
    """TP's costs alone cut at 10.5 (5 of 10 learned); ten invalid runs at 30 would pull Otsu's cut
    to 23 (TP 10 of 10) if they were pooled. A file of invalid runs alone is cut on its own costs."""
    tp = {("tp", 1.0): [5.0] * 5 + [16.0] * 5}
    invalid = {("gr_xi_eq_eps", 1.0): [30.0] * 10}
    assert otsu_threshold(np.array(tp["tp", 1.0] + invalid["gr_xi_eq_eps", 1.0])) == 23.0
    success = success_rows(rows_of({**tp, **invalid})).set_index("method")
    assert success.loc["tp", "wins"] == 5 and success.loc["gr_xi_eq_eps", "wins"] == 0
    final = final_evaluations(rows_of({**tp, **invalid}))
    assert otsu_thresholds(final) == {("cartpole", "angle", ""): 10.5}
    line = learn_report.threshold_lines(final, {("cartpole", "angle", ""): 10.5})[0]
    assert "the 10 final costs of INVALID runs are not pooled" in line and "cut of the 10 pooled" in line
    assert learn_report.invalid_lines(final)[0].startswith("- `gr_xi_eq_eps`: INVALID (its costs not in the")
    alone = final_evaluations(rows_of({("gr_xi_eq_eps", 1.0): [5.0] * 5 + [16.0] * 5}))
    assert otsu_thresholds(alone) == {("cartpole", "angle", ""): 10.5}
    assert "cut on these invalid costs alone" in learn_report.invalid_lines(alone)[0]


def test_other_readings_are_judged_at_the_tables_cut():
    """A reading of a convention (``harness.methods.READINGS``) reported beside the table takes no part in its cut:
    TP's costs alone cut at 10.5, where pooling the reading's costs would cut elsewhere. Alone, a file of readings
    is cut on its own costs."""
    tp = {("tp", 1.0): [5.0] * 5 + [16.0] * 5}
    reading = {("rp_fs_run", 1.0): [12.0] * 3 + [30.0] * 7}
    assert otsu_threshold(np.array(tp["tp", 1.0] + reading["rp_fs_run", 1.0])) != 10.5
    final = final_evaluations(rows_of({**tp, **reading}))
    assert otsu_thresholds(final) == {("cartpole", "angle", ""): 10.5}
    success = success_rows(rows_of({**tp, **reading})).set_index("method")
    assert success.loc["tp", "wins"] == 5 and success.loc["rp_fs_run", "wins"] == 0  # 12 fails at the table's cut
    line = learn_report.threshold_lines(final, {("cartpole", "angle", ""): 10.5})[0]
    assert "the 10 final costs of other readings (rp_fs_run) are not pooled" in line and "cut of the 10 pooled" in line
    alone = final_evaluations(rows_of(reading))
    assert otsu_thresholds(alone) == {("cartpole", "angle", ""): 21.0}


def test_the_report_carries_the_comparison_with_the_paper(tmp_path):
    path = tmp_path / "learn_cartpole_angle_k1_quick.csv"
    rows_of({**wins("tp", 9), **wins("pilco", 2), **wins("rp_fs_seed0", 3)}).to_csv(path, index=False)
    learn_report.main([str(path)])
    report = (tmp_path / "learn_cartpole_angle_k1_quick.md").read_text()
    for text in ["Success threshold for cartpole, angle cost: final evaluation cost < 17.500",
                 "| task     | cost   | k   | label       | n   | rate [95 % interval]   | paper   | inside   |",
                 "| cartpole | angle  | 1   | tp          | 10  | 0.90 [0.60, 0.98]      | 0.99    | no       | 0.17 ",
                 "Threshold robustness", "- Rates that change (flips): none.",
                 "The paper's orderings", "- (a) TP >= PILCO at k = 1 (cartpole, angle): TP 0.90",
                 "Compute time", "| total       |        30 |",
                 "`rp_fs_seed0`: INVALID", "Non-finite gradient estimates: none", "![learning curves]"]:
        assert text in report, text
    assert (tmp_path / "learn_cartpole_angle_k1_quick.png").exists()


def test_several_k_share_labels_and_the_threshold_is_per_cost_scale():
    """k is a column of its own, not part of a method's label; a task option that changes the
    cost's scale (``angle_cost_scale``) gets a threshold of its own, one that does not shares it."""
    success = success_rows(rows_of({**wins("tp", 9), **wins("tp", 4, k=16.0)}))
    assert success.label.tolist() == ["tp", "tp"] and success.k.tolist() == [1.0, 16.0]
    halved = rows_of(wins("tp", 5)).assign(task_options=lambda r: r.task_options + ",angle_cost_scale=0.5",
                                          eval_mean=lambda r: r.eval_mean / 2)
    scaled = pd.concat([rows_of(wins("tp", 5)).assign(task_options=lambda r: r.task_options + ",angle_cost_scale=1"),
                        halved.assign(repeat=halved.repeat + 10, seed=halved.seed + 10)])
    thresholds = otsu_thresholds(final_evaluations(scaled))
    assert thresholds == {("cartpole", "angle", " [angle_cost_scale=0.5]"): pytest.approx(8.75),
                          ("cartpole", "angle", " [angle_cost_scale=1]"): pytest.approx(17.5)}
    policies = pd.concat([scaled, scaled.assign(task_options=scaled.task_options + ",rbf=pseudo",
                                                repeat=scaled.repeat + 20, seed=scaled.seed + 20)])
    assert otsu_thresholds(final_evaluations(policies)) == thresholds  # not a scale



def test_a_report_over_several_csvs_keeps_each_k_apart(tmp_path):
    """One CSV per k, pooled by ``--out``: the curves, per-trial means and final costs are per
    method and k (k = 1's 9 wins and k = 16's 1 win are not averaged)."""
    low, high = tmp_path / "learn_cartpole_angle_k1.csv", tmp_path / "learn_cartpole_angle_k16.csv"
    rows_of(wins("tp", 9)).to_csv(low, index=False)
    rows_of(wins("tp", 1, k=16.0)).to_csv(high, index=False)
    with pytest.raises(SystemExit):  # several CSVs and nowhere to write
        learn_report.main([str(low), str(high)])
    learn_report.main([str(low), str(high), "--out", str(tmp_path / "pooled")])
    report = (tmp_path / "pooled.md").read_text()
    mean_low, mean_high = (9 * WIN + FAIL) / 10, (WIN + 9 * FAIL) / 10
    for text in ["| cartpole | angle  |   1 | 0.90 [0.60, 0.98] n=10 (paper 0.99) |",
                 "| cartpole | angle  |  16 | 0.10 [0.02, 0.40] n=10 (paper 0.40) |",
                 "per method and k", "|   trial |   tp [k=1] |   tp [k=16] |",
                 f"|       1 |       {mean_low:.2f} |       {mean_high:.2f} |",
                 f"| tp [k=16] | s          | {mean_high:.3f} |"]:
        assert text in report, text
    assert (tmp_path / "pooled.png").exists()
    assert "![success rate against k](pooled_rates.png)" in report and (tmp_path / "pooled_rates.png").exists()


def test_the_final_evaluation_is_the_last_trials_row_of_each_complete_experiment():
    rows = pd.DataFrame([row("tp", 0, 0), row("tp", 0, 1, WIN), row("tp", 0, 2, np.nan),  # diverged at the end
                         row("tp", 1, 0), row("tp", 1, 1, WIN), row("tp", 1, 2, WIN),
                         row("tp", 2, 0), row("tp", 2, 1, WIN),  # its last trial's row was never written
                         row("tp", 3, 0), row("tp", 3, 1, FAIL), row("tp", 3, 2, FAIL)]).assign(
        settings="learned_trials2-particles300")
    rows = pd.concat([rows, rows[rows.repeat == 1].assign(seed=101, eval_mean=FAIL)])  # the same repeat, --seed 100
    final = final_evaluations(rows).set_index(["repeat", "seed"]).eval_mean
    assert np.isnan(final[(0, 0)]) and final[(1, 1)] == WIN and final[(1, 101)] == FAIL and final[(3, 3)] == FAIL
    assert (2, 2) not in final.index
    assert otsu_threshold(np.array([1.0, 2.0, 3.0, 20.0, 21.0, np.nan])) == pytest.approx(11.5)
    assert success_rows(rows).set_index("method").loc["tp", ["wins", "n"]].tolist() == [1, 4]
    warning = learn_report.incomplete_lines(with_labels(rows[rows.learned]))[0]
    assert warning.endswith("tp, k = 1, repeat 2 (1 trials).")


def test_a_batch_is_counted_once_by_the_clock_of_its_first_trial():
    """Repeats 0 and 1 share a batch whose rows for repeat 1's last trial are missing: its time is
    still the batch's largest clock, counted once."""
    rows = pd.DataFrame([row("tp", 0, 0, seconds=5.0), row("tp", 0, 1, WIN, 250.0),
                         row("tp", 1, 0, seconds=5.0), row("tp", 2, 0, seconds=7.0), row("tp", 2, 1, WIN, 100.0)])
    assert compute_hours(rows).loc["tp", "hours"] == pytest.approx(350 / 3600)


def test_a_significant_reversal_refutes_a_claim_and_a_method_without_success_loses_nothing():
    cell = orderings({**wins("rp_fs", 9), **wins("gr", 0), **wins("tp", 9)})
    assert ("does not hold on the point estimates; refuted at 0.05 (two-sided Fisher exact p = 0.000119, the "
            "smallest of 1 against the claim: RP_FS vs GR).") in cell[2]
    never = orderings({**wins("lr", 9), **wins("tp", 9), **wins("pilco", 9), **wins("rp_fs", 0),
                       **wins("lr", 9, k=16.0), **wins("tp", 9, k=16.0), **wins("pilco", 1, k=16.0),
                       **wins("rp_fs", 0, k=16.0)})[1]
    assert "LR 0.00, TP 0.00, PILCO 0.89, RP_FS -: holds on the point estimates" in never
    assert never.endswith("the largest of 2: LR vs PILCO).")  # RP_FS, with nothing to lose, is left out
    assert wilson_interval(0, 11)[0] == 0.0 and wilson_interval(21, 21)[1] == 1.0


def test_nonfinite_steps_are_flagged_with_the_float32_cause_only_under_float32_rollouts():
    rows = rows_of({**wins("tp", 1, n=2), **wins("rp", 1, n=2)})
    learned = with_labels(rows[rows.learned])
    assert learn_report.nonfinite_lines(learned) == [
        "Non-finite gradient estimates: none in the 4 learned trials that count them."]
    learned.loc[learned.method == "rp", "nonfinite_steps"] = [3.0, 0.0]
    float64_lines = learn_report.nonfinite_lines(learned)
    assert float64_lines[0].startswith("**WARNING: non-finite gradient estimates** in 1 learned trials.")
    assert "rp" in float64_lines[2] and learn_report.FLOAT32_NONFINITE_CAUSE not in float64_lines
    learned["settings"] = "particles300-rollout_f32"
    assert learn_report.nonfinite_lines(learned)[-1] == learn_report.FLOAT32_NONFINITE_CAUSE


def test_claim_d_and_the_tip_cost_claim():
    """(d) TP+sigma_n above TP at k = 0.01, and with the tip cost PILCO and GR above TP and LR: one verdict
    over the pairs (Fisher exact); each line only where its cell is in the table."""
    lines = orderings({**wins("tp+sigma_n", 9, k=0.01), **wins("tp", 5, k=0.01)})
    [d] = [line for line in lines if line.startswith("- (d)")]
    assert d.startswith("- (d) TP+sigma_n above TP at k = 0.01 (cartpole, angle): TP+SIGMA_N 0.90 [0.60, 0.98] n=10, "
                        "TP 0.50 [0.24, 0.76] n=10: holds on the point estimates; not significant at 0.05, so undecided")
    assert [line for line in orderings(wins("tp", 5, k=0.01)) if line.startswith("- (d)")] == [
        "- (d) TP+sigma_n above TP at k = 0.01 (cartpole, angle): not measured (no TP+SIGMA_N rows)."]
    assert not [line for line in orderings(wins("tp", 5)) if line.startswith("- (d)")]  # no k = 0.01 cell
    tip = rows_of({**wins("pilco", 9), **wins("gr", 8), **wins("tp", 2), **wins("lr", 1)})
    tip = tip.assign(cost="tip", task_options=tip.task_options.str.replace("cost_type=angle", "cost_type=tip"))
    [line] = [line for line in ordering_lines(success_rows(tip))
              if line.startswith("- Tip cost")]
    assert "holds on the point estimates; significant at 0.05" in line and line.endswith("the largest of 4: GR vs TP).")
