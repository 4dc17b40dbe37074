"""The curse-of-chaos scenario's check (``harness.chaos``) on a small copy of its plan, with the cart-pole's
pinned scenario standing in for the source run's final state; and a gradient experiment started from a
scenario file (``--scenario-file``)."""

import filecmp
import json
import os
import shutil

import pytest

from harness import chaos, landscape, learn, records, summary, sweep, variance
from harness.cli import parse

PLAN = os.path.join(records.ROOT, "plans", "chaos_scenario.toml")
PINNED = os.path.join(records.ROOT, "scenarios", "scenario_cartpole_27b490aadc97")


def small_plan(tmp_path, max_cost: float, extend_until_cost: float = 20.0) -> str:
    """The plan with its source run's output under tmp_path, 20 particles, ``max_cost`` and
    ``extend_until_cost``; the pinned scenario copied to where the source run keeps its final state."""
    text = open(PLAN).read()
    for old, new in [('out = "reports/chaos_source"', f'out = "{tmp_path / "source"}"'),
                     ("particles = 1000", "particles = 20"), ("max_cost = 10.0", f"max_cost = {max_cost}"),
                     ("extend_until_cost = 20.0", f"extend_until_cost = {extend_until_cost}")]:
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "plan.toml"
    path.write_text(text)
    [unit] = sweep.load_plan(str(path))
    final = learn.final_state_path(unit.learn_args(), "tp", 0)
    os.makedirs(os.path.dirname(final), exist_ok=True)
    for ext in (".npz", ".json"):
        shutil.copy(PINNED + ext, final + ext)
    return str(path)


def test_the_rule_is_quoted_before_its_numbers_and_decides_the_verdict(tmp_path, monkeypatch):
    monkeypatch.setattr(chaos, "VARIANCE_REPEATS", 3)
    monkeypatch.setattr(chaos, "MAX_DOUBLINGS", 1)
    chaos.main(["--plan", small_plan(tmp_path, max_cost=1.0), "--out", str(tmp_path)])
    report = (tmp_path / "chaos_scenario.md").read_text()
    assert report.index("max_cost = 1.0") < report.index("## At the source run's final state")
    # the pinned swing-up scenario has J near 25 of 30: above a cut of 1, so the rule fails and names the next repeat
    assert "(the rule: at most 1): NOT met" in report and "The rule fails at repeat 0" in report
    assert "set repeat = 1 in [theta0]" in report and "harness.landscape" not in report
    assert "the scenario file" in report and "J along the line: " in report
    numbers = json.loads((tmp_path / "chaos_scenario.json").read_text())
    assert numbers["schema_version"] == chaos.SCHEMA_VERSION and not numbers["holds"] and numbers["max_cost"] == 1.0
    assert f"{numbers['cost']:.2f} (the rule: at most 1): NOT met" in report
    [row] = summary.chaos_scenario_claims(str(tmp_path))  # the claims table's row says the same
    assert row.verdict == "rule fails: next repeat" and f"J {numbers['cost']:.2f}" in row.ours


def test_where_the_rule_holds_its_json_holds_the_commands_of_the_reports_at_the_scenario(tmp_path, monkeypatch):
    monkeypatch.setattr(chaos, "VARIANCE_REPEATS", 2)
    variances = iter([1.0, 2.0])  # RP's, then LR's: the rule's second condition is met
    monkeypatch.setattr(variance, "cell_statistics", lambda estimates: {"variance": next(variances)})
    # the pinned swing-up scenario (J near 25 of 30) meets a cut of 30, and its line passes J = 1 at delta theta 1
    chaos.main(["--plan", small_plan(tmp_path, max_cost=30.0, extend_until_cost=1.0), "--out", str(tmp_path)])
    report = (tmp_path / "chaos_scenario.md").read_text()
    numbers = json.loads((tmp_path / "chaos_scenario.json").read_text())
    assert numbers["holds"] and "The rule holds" in report and [p["delta"] for p in numbers["line"]] == [0.0, 1.0]
    for name, module in [("landscape", landscape), ("variance", variance)]:
        argv = numbers["reports"][name]
        assert f"python -m harness.{name} {' '.join(argv)}" in report
        args = parse(module.Args, argv)  # the source run's final state: here a copy of the pinned scenario
        assert filecmp.cmp(os.path.join(records.ROOT, args.scenario_file + ".npz"), PINNED + ".npz", shallow=False)
        assert args.out == chaos.REPORTS_OUT and args.seed == 0
    assert parse(landscape.Args, numbers["reports"]["landscape"]).delta_max == 1.0
    assert parse(variance.Args, numbers["reports"]["variance"]).delta_theta == "0,1"
    rows = summary.chaos_scenario_claims(str(tmp_path))  # no report at the scenario yet: the rule's row alone
    assert [row.verdict for row in rows] == ["rule holds"]


def test_a_gradient_experiment_starts_from_a_scenario_file(tmp_path):
    out = str(tmp_path / "out")
    variance.main(["--estimators", "rp", "--particles", "5", "--repeats", "2", "--delta-theta", "0",
                   "--scenario-file", PINNED, "--out", out])
    report = open(os.path.join(out, "variance_cartpole_gp.md")).read()
    assert f"the scenario file {PINNED}.{{npz,json}}" in report and f"--scenario-file {PINNED}" in report
    with pytest.raises(ValueError, match="keep-final"):
        variance.main(["--scenario-file", str(tmp_path / "none"), "--out", out])
    other = str(tmp_path / "k16")  # a learning run's final state under other task options is refused
    shutil.copy(PINNED + ".npz", other + ".npz")
    meta = json.loads(open(PINNED + ".json").read()) | {"task_options": "noise_k=16.0"}
    with open(other + ".json", "w") as f:
        json.dump(meta, f)
    with pytest.raises(ValueError, match="made under task options noise_k=16.0"):
        variance.main(["--scenario-file", other, "--out", out])
