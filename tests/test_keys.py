"""Named random streams (harness.keys): today's keys bit for bit, and no two streams alike."""

import jax
import numpy as np
import pytest

from harness import keys


def test_streams_are_the_keys_the_harness_used_before_they_had_names():
    base = jax.random.key(3)
    old = {("direction", 0): 1, ("estimates", 0): 2, ("landscape", 0): 3, ("reference", 0): 4, ("objective", 0): 5,
           ("slices", 0): 6, ("random_trial", 2): 2, ("theta0", 0): 10_000, ("optimisation", 7): 20_007,
           ("trial", 7): 30_007, ("evaluation", 15): 40_015}
    for (name, index), literal in old.items():
        np.testing.assert_array_equal(jax.random.key_data(keys.stream(base, name, index)),
                                      jax.random.key_data(jax.random.fold_in(base, literal)), err_msg=name)


def test_no_two_streams_give_the_same_key():
    """An experiment's streams of its seed key and the run streams (40 trials) of the learning run that builds
    its scenario (run key: the seed key's "scenario_run" stream) are all distinct; so are a run's streams."""
    seed_key = jax.random.key(0)
    scenario_run = keys.stream(seed_key, "scenario_run")
    drawn = {f"experiment {name}": keys.stream(seed_key, name) for name in keys.EXPERIMENT}
    drawn |= {f"scenario run {name} {t}": keys.stream(scenario_run, name, t) for name in keys.RUN for t in range(40)}
    bits = [tuple(np.asarray(jax.random.key_data(k)).ravel()) for k in drawn.values()]
    assert len(set(bits)) == len(bits)
    offsets = sorted(keys.RUN.values())
    assert all(b - a >= keys.MAX_INDEX for a, b in zip(offsets, offsets[1:]))  # a run's streams never meet


def test_an_unknown_stream_is_named():
    with pytest.raises(ValueError, match="unknown random stream 'nope'"):
        keys.stream(jax.random.key(0), "nope")
