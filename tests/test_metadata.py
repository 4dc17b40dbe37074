"""Each report's metadata, ``{stem}.json`` (``harness.records.write_metadata``): plain JSON with a schema
version, the command its markdown prints, and the committed reports' files."""

import glob
import json
import os
import shlex

import pytest

from harness import records, variance
from harness.cli import parse
from harness.records import Command, read_metadata, write_metadata

REPORTS = os.path.join(os.path.dirname(__file__), "..", "reports")


def command_line(md_path: str) -> str:
    """The markdown's "Command: `...`" line's command."""
    with open(md_path) as f:
        [line] = [line for line in f if line.startswith("Command: `")]
    return line.split("`")[1]


def test_metadata_round_trips_as_sorted_plain_json(tmp_path):
    stem = str(tmp_path / "variance_cartpole_gp")
    command = Command("harness.variance", ["--task", "cartpole", "--scenario-file", "a folder/learn final"])
    objective = [dict(model="gp", delta_theta=0.0, value=25.47, ci=0.08),
                 dict(model="gp", delta_theta=1.5, value=27.56, ci=0.06)]
    write_metadata(stem, command, "06b721e74402", objective)
    text = open(stem + ".json").read()
    assert text == json.dumps(json.loads(text), sort_keys=True, indent=1) + "\n"
    meta = read_metadata(stem + ".json")
    assert meta["schema_version"] == records.METADATA_SCHEMA_VERSION and meta["scenario"] == "06b721e74402"
    assert Command(**meta["command"]) == command and meta["objective"] == objective
    assert meta["code_version"] == records.code_version() and {"jax", "jaxlib", "numpy"} <= set(meta["libraries"])
    assert shlex.split(command.text) == ["python", "-m", "harness.variance", *command.argv]
    with open(stem + ".json", "w") as f:  # as written by other code: a rerun with the same content keeps it
        f.write(text.replace(meta["code_version"], "older"))
    write_metadata(stem, command, "06b721e74402", [dict(o, value=o["value"] + 1e-12) for o in objective])
    assert read_metadata(stem + ".json")["code_version"] == "older"  # J's round-off (below 6 digits) too
    write_metadata(stem, command, "06b721e74402", [dict(o, value=o["value"] + 0.01) for o in objective])
    assert read_metadata(stem + ".json")["code_version"] == records.code_version()  # other J: rewritten


@pytest.mark.parametrize("content, message", [
    (None, "is not readable report metadata"),
    ("{\"schema_version\": 1, ", "is not readable report metadata"),
    ("[1]", "report metadata of schema_version None, this code reads 1"),
    (json.dumps(dict(schema_version=2, command={}, scenario=None, objective=[])),
     "report metadata of schema_version 2, this code reads 1"),
    (json.dumps(dict(schema_version=1, command={}, scenario=None)), "report metadata lacks objective"),
])
def test_bad_metadata_is_refused_in_one_line(tmp_path, content, message):
    path = str(tmp_path / "report.json")
    if content is not None:
        with open(path, "w") as f:
            f.write(content)
    with pytest.raises(ValueError, match=message) as error:
        read_metadata(path)
    assert "\n" not in str(error.value) and path in str(error.value)


def test_a_variance_report_s_markdown_prints_its_metadata(tmp_path):
    """A tiny variance run at the pinned scenario: the markdown's Command line is the metadata's
    command, which parses back to the run's settings, and its content hash and J are the metadata's."""
    argv = ["--estimators", "rp", "--particles", "5", "--repeats", "2", "--delta-theta", "0", "--out", str(tmp_path)]
    variance.main(argv)
    stem = str(tmp_path / "variance_cartpole_gp")
    meta = read_metadata(stem + ".json")
    command = Command(**meta["command"])
    assert command_line(stem + ".md") == command.text and command.module == "harness.variance"
    assert parse(variance.Args, command.argv + ["--out", str(tmp_path)]) == parse(variance.Args, argv)
    report = open(stem + ".md").read()
    assert f"Content hash {meta['scenario']} (" in report
    assert [(j["model"], j["delta_theta"]) for j in meta["objective"]] == [("gp", 0.0), ("gp", 1.5)]
    printed = "; ".join(f"{j['value']:.2f} +- {j['ci']:.2f} at delta theta = {j['delta_theta']:g}"
                        for j in meta["objective"])
    assert f"- J under the gp model (2000 particles, 95 % interval; at most 30): {printed}." in report


def test_the_committed_reports_metadata_is_their_markdown_s_command():
    """Every committed report with metadata (a ``.json`` beside its ``.csv`` and ``.md``) reads, and its
    markdown prints its command."""
    stems = [path[:-len(".json")] for path in glob.glob(os.path.join(REPORTS, "**", "*.json"), recursive=True)
             if "archive" not in path and all(os.path.exists(path[:-len("json")] + ext) for ext in ("csv", "md"))]
    assert len(stems) >= 7
    for stem in stems:
        assert command_line(stem + ".md") == Command(**read_metadata(stem + ".json")["command"]).text, stem
