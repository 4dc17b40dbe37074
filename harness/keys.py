"""Named random streams: every key the harness derives from a seed or a run's key, by name.

    key = keys.stream(jax.random.key(seed), "direction")
    key = keys.stream(run_key, "trial", t)

A stream is ``fold_in(base, offset + index)``: the offsets are the numbers the harness used before
the streams had names, so every key (and every pinned result made with it) is unchanged. Two kinds
of base: an experiment's seed key (``EXPERIMENT``) and a learning run's key (``RUN``, indexed by
trial; a run has fewer than ``MAX_INDEX`` trials, so its streams never meet). ``tests/test_keys.py``
checks that no two streams of one base give the same key.

One key changed when the streams got names: a scenario's learning run used the seed key itself, so
its random trials 1-6 (the unicycle has 5) drew from the keys of the experiment's streams; it now
uses the seed key's "scenario_run" stream. Pinned scenarios are loaded, not rebuilt, so no
committed result changes; ``--rebuild-scenario`` builds differ (as they already did across machines).
"""

from __future__ import annotations

import jax

EXPERIMENT = {
    "direction": 1,        # the random unit direction of the gradient experiments' line
    "estimates": 2,        # the repeated estimates of harness.variance and harness.compare (fold_in r)
    "landscape": 3,        # harness.landscape's rows
    "reference": 4,        # harness.compare's reference gradient
    "objective": 5,        # the J line of every gradient report
    "slices": 6,           # harness.landscape's value slices
    "scenario_run": 7,     # the learning run that builds a scenario
}
"""Streams of an experiment's seed key ``jax.random.key(seed)``."""

RUN = {
    "random_trial": 0,     # random trial r
    "theta0": 10_000,      # the policy's initial parameters
    "optimisation": 20_000,  # trial t's policy optimisation
    "trial": 30_000,       # trial t on the real system
    "evaluation": 40_000,  # the evaluation runs after trial t (harness.learn)
}
"""Streams of a learning run's key, each indexed by the trial."""

MAX_INDEX = 10_000
"""Indices of a stream stay below this (the gap between two RUN offsets)."""


def stream(base: jax.Array, name: str, index: int | jax.Array = 0) -> jax.Array:
    """The key of stream ``name`` (an ``EXPERIMENT`` or ``RUN`` name) at ``index``: ``fold_in(base,
    offset + index)``; a ValueError names the streams for an unknown name."""
    offsets = EXPERIMENT | RUN
    if name not in offsets:
        raise ValueError(f"unknown random stream {name!r}; streams: {sorted(offsets)}")
    return jax.random.fold_in(base, offsets[name] + index)
