"""Gradient estimators and their registry: ``estimators.make(name, **overrides)``.

Every estimator is called as ``est(problem, theta, key, num_particles) -> Estimate`` (see
``estimators.base``); ``num_particles`` fixes shapes, so jit with it static. Named variants
(``lr_is_baseline``, ``biw_lr_pairwise``, ``biw_lr_no_baseline``, ``tp_pairwise``) give the
experiments' CLIs the baselines of ``estimators.likelihood_ratio`` by name (``lr_is_baseline``:
LR with the importance-sampled baseline, as the paper's variance figure ran LR).
"""

from __future__ import annotations

import functools
import inspect
from typing import Callable

from estimators.base import Estimate, FixedNoise, Problem, task_problem
from estimators.likelihood_ratio import LikelihoodRatio
from estimators.pilco import Pilco
from estimators.reparameterisation import Reparameterisation
from estimators.total_propagation import TotalPropagation

REGISTRY: dict[str, Callable[..., object]] = {
    "rp": lambda **kw: Reparameterisation(**kw),
    "rp_fs": lambda: FixedNoise(Reparameterisation()),
    "gr": lambda **kw: Reparameterisation(gaussian_resampling=True, **kw),
    "gr_fs": lambda: FixedNoise(Reparameterisation(gaussian_resampling=True)),
    "lr": lambda **kw: LikelihoodRatio("lr", **kw),
    "lr_is_baseline": lambda: LikelihoodRatio("lr", baseline="importance_sampled"),
    "biw_lr": lambda **kw: LikelihoodRatio("biw_lr", **kw),
    "biw_lr_pairwise": lambda: LikelihoodRatio("biw_lr", baseline="pairwise"),
    "biw_lr_no_baseline": lambda: LikelihoodRatio("biw_lr", baseline="none"),
    "tp": lambda **kw: TotalPropagation(**kw),
    "tp_pairwise": lambda: TotalPropagation(baseline="pairwise"),
    "pilco": lambda: Pilco(),
}
"""name -> factory: ``REGISTRY[name](**options)`` returns the estimator (a hashable callable)."""


def make(name: str, **overrides):
    """The estimator ``name`` (one of ``REGISTRY``), with its options overridden."""
    if name not in REGISTRY:
        raise ValueError(f"unknown estimator {name!r}; valid estimators: {sorted(REGISTRY)}")
    factory = REGISTRY[name]
    if not (isinstance(factory, type) or inspect.isroutine(factory) or isinstance(factory, functools.partial)):
        raise TypeError(f"REGISTRY[{name!r}] is a {type(factory).__name__} object; it must be a factory that "
                        "returns the estimator: its class, or a function of its options")
    if not overrides:
        return factory()
    try:
        return factory(**overrides)
    except TypeError as err:
        raise ValueError(f"bad option for estimator {name!r}: {err}") from None


__all__ = ["Estimate", "Problem", "REGISTRY", "make", "task_problem"]
