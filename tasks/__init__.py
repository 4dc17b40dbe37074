"""Tasks, defined once: ``tasks.make(name, **options)``.

>>> task = tasks.make("cartpole", cost="tip", noise_k=4.0)
>>> task = tasks.make("unicycle", preset="pilco")
"""

from __future__ import annotations

import dataclasses
import typing

from tasks.base import Task
from tasks.cartpole import CartPole
from tasks.unicycle import Unicycle

REGISTRY: dict[str, type[Task]] = {cls.name: cls for cls in (CartPole, Unicycle)}

OPTION_ALIASES = {"cost": "cost_type"}
"""User-facing option names that differ from the dataclass field (``cost`` is a method)."""


def options(name: str) -> list[str]:
    """The option names that ``make(name, ...)`` accepts."""
    aliases = {field: option for option, field in OPTION_ALIASES.items()}
    cls = _task_class(name)
    return sorted(aliases.get(f.name, f.name) for f in dataclasses.fields(cls))


def make(name: str, preset: str = "pipps", **overrides) -> Task:
    """The task ``name`` with the preset's settings, then ``overrides`` on top.

    Raises ValueError naming the valid tasks, presets or options when one is unknown.
    """
    cls = _task_class(name)
    if preset not in cls.presets:
        raise ValueError(f"unknown preset {preset!r} for task {name!r}; valid presets: {sorted(cls.presets)}")
    valid = options(name)
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"unknown option(s) {unknown} for task {name!r}; valid options: {valid}")
    settings = {**cls.presets[preset], **overrides, "preset": preset}
    return cls(**{OPTION_ALIASES.get(k, k): v for k, v in settings.items()})


def parse_options(name: str, text: str) -> dict:
    """``"angle_cost_scale=1,rbf_parameterisation=pseudo_inputs"`` -> the options of task
    ``name`` as a dict for ``make``, each value of its option's type (``""``: none)."""
    cls = _task_class(name)
    types = typing.get_type_hints(cls)
    parsed = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        option, sep, value = item.partition("=")
        kind = types.get(OPTION_ALIASES.get(option, option)) if option in options(name) else None
        if not sep or kind is None:
            raise ValueError(f"bad task option {item!r} for {name!r}: write NAME=VALUE with NAME one of {options(name)}")
        parsed[option] = value.lower() in ("1", "true", "yes") if kind is bool else kind(value)
    return parsed


def describe(task: Task) -> str:
    """Every option of ``task`` as ``name=value,...`` (what a result was computed with)."""
    return ",".join(f"{f.name}={getattr(task, f.name)}" for f in dataclasses.fields(task))


def _task_class(name: str) -> type[Task]:
    if name not in REGISTRY:
        raise ValueError(f"unknown task {name!r}; valid tasks: {sorted(REGISTRY)}")
    return REGISTRY[name]


__all__ = ["Task", "CartPole", "Unicycle", "REGISTRY", "describe", "make", "options", "parse_options"]
