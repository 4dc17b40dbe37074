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
