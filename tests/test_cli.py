"""Every experiment's command line explains each of its flags."""

import dataclasses
import importlib

import pytest

from harness.cli import field_docs, parse, undocumented_fields

CLIS = ["bench", "compare", "landscape", "learn", "mjx_agreement", "summary", "sweep", "variance"]


@pytest.mark.parametrize("name", CLIS)
def test_every_flag_has_a_meaning_in_help(name, capsys):
    args_class = importlib.import_module(f"harness.{name}").Args
    assert undocumented_fields(args_class) == []
    with pytest.raises(SystemExit):
        parse(args_class, ["--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    for field in dataclasses.fields(args_class):
        assert "--" + field.name.replace("_", "-") in help_text
        assert field_docs(args_class)[field.name] in help_text, field.name


def test_field_docs_reads_the_literal_after_each_field_and_inherits():
    @dataclasses.dataclass
    class Base:
        a: int = 1
        """The a."""
        b: str = "x"

    @dataclasses.dataclass
    class Child(Base):
        c: float = 0.5
        """The
        c."""

    assert field_docs(Child) == {"a": "The a.", "c": "The c."}
    assert undocumented_fields(Child) == ["b"]


@pytest.mark.parametrize("module, argv, message", [
    ("variance", ["--particles", "0"], "error: particles must be >= 2; got 0"),
    ("variance", ["--particles", "abc"], "error: expected comma-separated integers such as 10,30,100; got 'abc'"),
    ("variance", ["--task", "nope"], "error: unknown task 'nope'"),
    ("learn", ["--methods", "nope"], "error: unknown methods ['nope']"),
    ("learn", ["--particles", "abc"], "error: argument --particles: invalid int value: 'abc'"),
    ("landscape", ["--particles", "1"], "error: particles must be >= 2; got 1"),
])
def test_bad_input_is_one_line_and_exit_status_2(module, argv, message, capsys):
    from harness.cli import run_command

    main = importlib.import_module(f"harness.{module}").main
    with pytest.raises(SystemExit) as stopped:
        run_command(lambda: main(argv))
    assert stopped.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(message), err


def test_a_corrupt_results_csv_is_named_and_left_untouched(tmp_path, capsys):
    from harness import variance
    from harness.cli import run_command

    corrupt = tmp_path / "variance_cartpole_gp.csv"
    corrupt.write_text('task,model\ncartpole,"gp\n')  # a quote never closed
    before = corrupt.read_bytes()
    with pytest.raises(SystemExit) as stopped:
        run_command(lambda: variance.main(["--out", str(tmp_path)]))
    assert stopped.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(corrupt) in err[0] and "not a readable results CSV" in err[0]
    assert corrupt.read_bytes() == before


def test_the_pipps_console_script_runs_each_command_and_names_a_wrong_one(capsys):
    from harness.cli import COMMANDS, pipps

    for name in COMMANDS:
        with pytest.raises(SystemExit) as stopped:
            pipps([name, "--help"])
        assert stopped.value.code == 0
    with pytest.raises(SystemExit) as stopped:
        pipps(["varience"])
    assert stopped.value.code == 2
    assert capsys.readouterr().err.strip().startswith("error: unknown command 'varience'; usage: pipps {variance,")
