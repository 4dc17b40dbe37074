"""A typed dataclass that is both an experiment's configuration and its command line.

Each field is a flag (``delta_theta`` is ``--delta-theta``; a bool is ``--flag/--no-flag``) and
the string literal right below a field is its help text, as in::

    particles: int = 300
    \"\"\"Particles per gradient estimate.\"\"\"
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import os
import sys
import textwrap
import time
import typing


def field_docs(args_class) -> dict[str, str]:
    """Each field's docstring (the string literal right after its annotated assignment),
    from the class and its dataclass bases (a subclass's text wins), whitespace collapsed."""
    docs = {}
    for cls in reversed(args_class.__mro__):
        if not dataclasses.is_dataclass(cls):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                    and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def undocumented_fields(args_class) -> list[str]:
    """The fields of ``args_class`` without a docstring (every flag must say what it means)."""
    docs = field_docs(args_class)
    return [field.name for field in dataclasses.fields(args_class) if field.name not in docs]


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, ``error: ...``, and exit status 2."""

    def error(self, message):
        print(f"error: {message} (--help lists the flags)", file=sys.stderr)
        raise SystemExit(2)


def run_command(main) -> None:
    """A command's entry point: ``main()``, with bad input (a ValueError, such as an unknown name, an
    impossible size, a corrupt results file or a failed Cholesky factorisation, or a missing file) answered by one
    line, ``error: ...``, and exit status 2 instead of a traceback (``PIPPS_TRACEBACK=1`` shows it)."""
    try:
        main()
    except (ValueError, FileNotFoundError) as error:
        if os.environ.get("PIPPS_TRACEBACK"):
            raise
        print(f"error: {error}", file=sys.stderr)
        raise SystemExit(2) from None


class Progress:
    """Progress lines with the time left: ``[i/n] TEXT (about M min left)``, M from the mean time of the items
    this process has computed so far (reused items cost nothing and are not counted)."""

    def __init__(self, total: int):
        self.total, self.started, self.computed = total, time.perf_counter(), 0

    def line(self, index: int, text: str) -> str:
        """The line after item ``index`` (0-based) was computed."""
        self.computed += 1
        left = (time.perf_counter() - self.started) / self.computed * (self.total - index - 1)
        return f"[{index + 1}/{self.total}] {text} (about {left / 60:.1f} min left)"


def check_sizes(**sizes) -> None:
    """Refuse impossible sizes before anything is computed: each NAME=(values, least) must be >= least."""
    for name, (values, least) in sizes.items():
        bad = [v for v in (values if isinstance(values, (list, tuple)) else [values]) if v < least]
        if bad:
            raise ValueError(f"{name} must be >= {least}; got {bad[0]}")


def parse(args_class, argv=None):
    """Build ``args_class`` (a dataclass of str/int/float/bool fields with defaults and
    docstrings) from the command line; ``--help`` lists every flag with its meaning and default."""
    hints = typing.get_type_hints(args_class)
    docs = field_docs(args_class)
    parser = OneLineParser(description=(args_class.__doc__ or "").strip().splitlines()[0])
    for field in dataclasses.fields(args_class):
        flag = "--" + field.name.replace("_", "-")
        kind = hints[field.name]
        text = f"{docs.get(field.name, '')} (default: {field.default!r})".strip()
        if kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=field.default,
                                help=text.replace("%", "%%"))
        else:
            parser.add_argument(flag, type=kind, default=field.default, help=text.replace("%", "%%"))
    return args_class(**vars(parser.parse_args(argv)))


def int_list(text: str) -> list[int]:
    """"10,30,100" -> [10, 30, 100]; a ValueError that quotes the text otherwise."""
    try:
        return [int(x) for x in text.split(",") if x]
    except ValueError:
        raise ValueError(f"expected comma-separated integers such as 10,30,100; got {text!r}") from None


def float_list(text: str) -> list[float]:
    """"0,1.5" -> [0.0, 1.5]; a ValueError that quotes the text otherwise."""
    try:
        return [float(x) for x in text.split(",") if x]
    except ValueError:
        raise ValueError(f"expected comma-separated numbers such as 0,1.5; got {text!r}") from None


def with_flags(argv: list[str], flags: dict[str, str]) -> list[str]:
    """``argv`` with each ``--flag value`` of ``flags`` replaced, or appended if absent."""
    out, skip = [], False
    for item in argv:
        if skip:
            skip = False
        elif item in flags:
            skip = True
        else:
            out.append(item)
    for flag, value in flags.items():
        out += [flag, value]
    return out


def flag_values(argv: list[str]) -> dict[str, str]:
    """``{"--flag": "value"}`` of an argument list whose flags all take one value."""
    return {flag: value for flag, value in zip(argv[::2], argv[1::2])}


def str_list(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


COMMANDS = ("variance", "landscape", "compare", "learn", "learn_report", "sweep", "bench", "reproduce", "summary",
            "mjx_agreement")
"""The experiments that ``pipps NAME ...`` runs (each is also ``python -m harness.NAME``)."""


def pipps(argv=None) -> None:
    """The ``pipps`` console script: ``pipps NAME [flags]`` runs ``harness.NAME``'s command."""
    import importlib

    argv = sys.argv[1:] if argv is None else list(argv)
    if not argv or argv[0] not in COMMANDS:
        given = f"unknown command {argv[0]!r}; " if argv and not argv[0].startswith("-") else ""
        print(f"error: {given}usage: pipps {{{','.join(COMMANDS)}}} [flags] (pipps NAME --help lists NAME's flags)",
              file=sys.stderr)
        raise SystemExit(2)
    main = importlib.import_module(f"harness.{argv[0]}").main
    run_command(lambda: main(argv[1:]))
