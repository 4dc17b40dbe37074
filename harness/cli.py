"""A typed dataclass that is both an experiment's configuration and its command line."""

from __future__ import annotations

import argparse
import dataclasses
import typing


def parse(args_class, argv=None):
    """Build ``args_class`` (a dataclass of str/int/float/bool fields with defaults) from the
    command line: field ``delta_theta`` is ``--delta-theta``; a bool is a ``--flag/--no-flag``."""
    hints = typing.get_type_hints(args_class)
    parser = argparse.ArgumentParser(description=(args_class.__doc__ or "").strip().splitlines()[0])
    for field in dataclasses.fields(args_class):
        flag = "--" + field.name.replace("_", "-")
        kind = hints[field.name]
        if kind is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=field.default)
        else:
            parser.add_argument(flag, type=kind, default=field.default, help=f"(default: {field.default})")
    return args_class(**vars(parser.parse_args(argv)))


def int_list(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def float_list(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x]


def str_list(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]
